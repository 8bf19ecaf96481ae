/*
 * sha256.h - SHA-256 (FIPS 180-4), for content-addressed assets,
 * idempotency body hashes and the keys of the baked-DMM disk cache.
 * Written from the standard; no dependency.
 */
#ifndef MR_SHA256_H
#define MR_SHA256_H

#include <stddef.h>
#include <stdint.h>

typedef struct mr_sha256 {
    uint32_t h[8];
    uint64_t length;     /* bytes hashed so far */
    uint8_t block[64];
    size_t used;         /* bytes in block */
} mr_sha256;

void mr_sha256_init(mr_sha256 *s);
void mr_sha256_update(mr_sha256 *s, const void *data, size_t size);
void mr_sha256_final(mr_sha256 *s, uint8_t digest[32]);
/* One-shot: lowercase hex digest of data into hex (65 bytes with the NUL). */
void mr_sha256_hex(const void *data, size_t size, char hex[65]);

#endif
