/*
 * crc32.h - CRC-32 of IEEE 802.3 / zlib (reflected polynomial 0xEDB88320,
 * initial value and final xor all ones; "123456789" gives 0xCBF43926), the
 * checksum of every microray file format. One table lookup per byte: the
 * arrays of a big base mesh or a deep octree run to hundreds of MB. The
 * table is the caller's (1 KB, filled once per file), not a global.
 */
#ifndef MR_CRC32_H
#define MR_CRC32_H

#include <stddef.h>
#include <stdint.h>

typedef struct mr_crc32_table {
    uint32_t t[256];
} mr_crc32_table;

void mr_crc32_init(mr_crc32_table *tab);
/* CRC-32 of n bytes at data (n == 0 gives 0). */
uint32_t mr_crc32(const mr_crc32_table *tab, const void *data, size_t n);

#endif
