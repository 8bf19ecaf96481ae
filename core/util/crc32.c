/* crc32.c - CRC-32 (crc32.h) by libdeflate. */
#include "util/crc32.h"

#include <libdeflate.h>

uint32_t mr_crc32(const void *data, size_t n)
{
    return n ? libdeflate_crc32(0, data, n) : 0;
}
