/*
 * sha256.h - the number feed of the derived-data cache keys. SHA-256 itself
 * (mr_sha256, init/update/final/hex) is public: microray.h.
 */
#ifndef MR_SHA256_H
#define MR_SHA256_H

#include <stddef.h>
#include <stdint.h>

#include "microray.h"

/* Numbers into a SHA-256 as little-endian bytes (util/le.h), batched
 * through a small buffer: the cache keys of baked DMMs and voxelisations
 * hash whole meshes value by value, independent of the host's byte order.
 * Raw bytes fed in between keep their place in the stream. */
typedef struct mr_sha256_feed {
    mr_sha256 sha;
    uint8_t buf[4096];
    size_t used;         /* bytes in buf, not yet hashed */
} mr_sha256_feed;

void mr_sha256_feed_init(mr_sha256_feed *f);
void mr_sha256_feed_bytes(mr_sha256_feed *f, const void *data, size_t size);
void mr_sha256_feed_u32(mr_sha256_feed *f, uint32_t v);
void mr_sha256_feed_u64(mr_sha256_feed *f, uint64_t v);
void mr_sha256_feed_u16s(mr_sha256_feed *f, const uint16_t *v, size_t n);
void mr_sha256_feed_u32s(mr_sha256_feed *f, const uint32_t *v, size_t n);
/* Floats as their bit patterns: -0 and 0 differ, as they do in a file. */
void mr_sha256_feed_f32s(mr_sha256_feed *f, const float *v, size_t n);
void mr_sha256_feed_final(mr_sha256_feed *f, uint8_t digest[32]);

#endif
