/* crc32.c - table-driven CRC-32 (crc32.h), written from the definition. */
#include "util/crc32.h"

void mr_crc32_init(mr_crc32_table *tab)
{
    for (uint32_t i = 0; i < 256; i++) {
        uint32_t c = i;
        for (int k = 0; k < 8; k++)
            c = (c >> 1) ^ (0xEDB88320u & (0u - (c & 1u)));
        tab->t[i] = c;
    }
}

uint32_t mr_crc32(const mr_crc32_table *tab, const void *data, size_t n)
{
    const uint8_t *p = data;
    uint32_t c = 0xFFFFFFFFu;
    for (size_t i = 0; i < n; i++)
        c = tab->t[(c ^ p[i]) & 0xFFu] ^ (c >> 8);
    return ~c;
}
