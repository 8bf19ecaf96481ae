/*
 * sha256.c - SHA-256 as specified in FIPS 180-4 (sections 4.1.2, 4.2.2,
 * 5.1.1, 5.3.3 and 6.2), written from the standard. Assets are named by
 * their hash, idempotent submissions compare body hashes and baked DMMs are
 * cached under a hash of their inputs, so microray needs exactly this one
 * digest and no crypto library for it. It lives in core because the DMM
 * cache (core/kinds/dmm/dmm_file.c) uses it and core must not depend on server.
 */
#include "util/sha256.h"

#include <string.h>

#include "util/hex.h"
#include "util/le.h"

/* First 32 bits of the fractional parts of the cube roots of the first 64
 * primes (FIPS 180-4, 4.2.2). */
static const uint32_t K[64] = {
    0x428a2f98, 0x71374491, 0xb5c0fbcf, 0xe9b5dba5, 0x3956c25b, 0x59f111f1, 0x923f82a4, 0xab1c5ed5,
    0xd807aa98, 0x12835b01, 0x243185be, 0x550c7dc3, 0x72be5d74, 0x80deb1fe, 0x9bdc06a7, 0xc19bf174,
    0xe49b69c1, 0xefbe4786, 0x0fc19dc6, 0x240ca1cc, 0x2de92c6f, 0x4a7484aa, 0x5cb0a9dc, 0x76f988da,
    0x983e5152, 0xa831c66d, 0xb00327c8, 0xbf597fc7, 0xc6e00bf3, 0xd5a79147, 0x06ca6351, 0x14292967,
    0x27b70a85, 0x2e1b2138, 0x4d2c6dfc, 0x53380d13, 0x650a7354, 0x766a0abb, 0x81c2c92e, 0x92722c85,
    0xa2bfe8a1, 0xa81a664b, 0xc24b8b70, 0xc76c51a3, 0xd192e819, 0xd6990624, 0xf40e3585, 0x106aa070,
    0x19a4c116, 0x1e376c08, 0x2748774c, 0x34b0bcb5, 0x391c0cb3, 0x4ed8aa4a, 0x5b9cca4f, 0x682e6ff3,
    0x748f82ee, 0x78a5636f, 0x84c87814, 0x8cc70208, 0x90befffa, 0xa4506ceb, 0xbef9a3f7, 0xc67178f2,
};

static inline uint32_t rotr(uint32_t x, unsigned n) { return (x >> n) | (x << (32 - n)); }

static void compress(uint32_t h[8], const uint8_t block[64])
{
    uint32_t w[64];
    /* Big-endian words, assembled byte by byte so alignment and host byte
     * order never matter. */
    for (int t = 0; t < 16; t++)
        w[t] = (uint32_t)block[4 * t] << 24 | (uint32_t)block[4 * t + 1] << 16 |
               (uint32_t)block[4 * t + 2] << 8 | (uint32_t)block[4 * t + 3];
    for (int t = 16; t < 64; t++) {
        uint32_t s0 = rotr(w[t - 15], 7) ^ rotr(w[t - 15], 18) ^ (w[t - 15] >> 3);
        uint32_t s1 = rotr(w[t - 2], 17) ^ rotr(w[t - 2], 19) ^ (w[t - 2] >> 10);
        w[t] = w[t - 16] + s0 + w[t - 7] + s1;
    }
    uint32_t a = h[0], b = h[1], c = h[2], d = h[3], e = h[4], f = h[5], g = h[6], hh = h[7];
    for (int t = 0; t < 64; t++) {
        uint32_t S1 = rotr(e, 6) ^ rotr(e, 11) ^ rotr(e, 25);
        uint32_t ch = (e & f) ^ (~e & g);
        uint32_t t1 = hh + S1 + ch + K[t] + w[t];
        uint32_t S0 = rotr(a, 2) ^ rotr(a, 13) ^ rotr(a, 22);
        uint32_t maj = (a & b) ^ (a & c) ^ (b & c);
        uint32_t t2 = S0 + maj;
        hh = g;
        g = f;
        f = e;
        e = d + t1;
        d = c;
        c = b;
        b = a;
        a = t1 + t2;
    }
    h[0] += a;
    h[1] += b;
    h[2] += c;
    h[3] += d;
    h[4] += e;
    h[5] += f;
    h[6] += g;
    h[7] += hh;
}

void mr_sha256_init(mr_sha256 *s)
{
    /* First 32 bits of the fractional parts of the square roots of the
     * first 8 primes (FIPS 180-4, 5.3.3). */
    static const uint32_t H0[8] = {0x6a09e667, 0xbb67ae85, 0x3c6ef372, 0xa54ff53a,
                                   0x510e527f, 0x9b05688c, 0x1f83d9ab, 0x5be0cd19};
    memcpy(s->h, H0, sizeof H0);
    s->length = 0;
    s->used = 0;
    memset(s->block, 0, sizeof s->block);
}

void mr_sha256_update(mr_sha256 *s, const void *data, size_t size)
{
    /* NULL with size 0 is allowed ("" hashes fine); memcpy must not see it. */
    if (size == 0)
        return;
    const uint8_t *p = data;
    s->length += size;
    if (s->used > 0) {
        size_t take = 64 - s->used;
        if (take > size)
            take = size;
        memcpy(s->block + s->used, p, take);
        s->used += take;
        p += take;
        size -= take;
        if (s->used < 64)
            return;
        compress(s->h, s->block);
        s->used = 0;
    }
    /* Whole blocks straight from the caller's buffer, no copy. */
    while (size >= 64) {
        compress(s->h, p);
        p += 64;
        size -= 64;
    }
    if (size > 0) {
        memcpy(s->block, p, size);
        s->used = size;
    }
}

void mr_sha256_final(mr_sha256 *s, uint8_t digest[32])
{
    /* The length is in bits; messages are limited to 2^64 bits, so a byte
     * count above 2^61 wraps as the standard's mod 2^64 would. */
    uint64_t bits = s->length * 8u;
    s->block[s->used++] = 0x80;
    if (s->used > 56) {
        memset(s->block + s->used, 0, 64 - s->used);
        compress(s->h, s->block);
        s->used = 0;
    }
    memset(s->block + s->used, 0, 56 - s->used);
    for (int i = 0; i < 8; i++)
        s->block[56 + i] = (uint8_t)(bits >> (56 - 8 * i));
    compress(s->h, s->block);
    for (int i = 0; i < 8; i++) {
        digest[4 * i] = (uint8_t)(s->h[i] >> 24);
        digest[4 * i + 1] = (uint8_t)(s->h[i] >> 16);
        digest[4 * i + 2] = (uint8_t)(s->h[i] >> 8);
        digest[4 * i + 3] = (uint8_t)s->h[i];
    }
    /* Wipe the state so a finished context cannot be extended by mistake
     * into a wrong digest; a fresh init is required to reuse it. */
    memset(s, 0, sizeof *s);
}

void mr_sha256_hex(const void *data, size_t size, char hex[65])
{
    mr_sha256 s;
    uint8_t d[32];
    mr_sha256_init(&s);
    mr_sha256_update(&s, data, size);
    mr_sha256_final(&s, d);
    mr_hex_encode(d, sizeof d, hex);
}

/* ---- little-endian feed */

void mr_sha256_feed_init(mr_sha256_feed *f)
{
    mr_sha256_init(&f->sha);
    f->used = 0;
}

static void feed_flush(mr_sha256_feed *f)
{
    mr_sha256_update(&f->sha, f->buf, f->used);
    f->used = 0;
}

/* Room for need more bytes in buf. */
static uint8_t *feed_room(mr_sha256_feed *f, size_t need)
{
    if (f->used + need > sizeof f->buf)
        feed_flush(f);
    uint8_t *p = f->buf + f->used;
    f->used += need;
    return p;
}

void mr_sha256_feed_bytes(mr_sha256_feed *f, const void *data, size_t size)
{
    feed_flush(f);
    mr_sha256_update(&f->sha, data, size);
}

void mr_sha256_feed_u32(mr_sha256_feed *f, uint32_t v) { mr_le_put_u32(feed_room(f, 4), v); }

void mr_sha256_feed_u64(mr_sha256_feed *f, uint64_t v) { mr_le_put_u64(feed_room(f, 8), v); }

void mr_sha256_feed_u16s(mr_sha256_feed *f, const uint16_t *v, size_t n)
{
    for (size_t i = 0; i < n; i++)
        mr_le_put_u16(feed_room(f, 2), v[i]);
}

void mr_sha256_feed_u32s(mr_sha256_feed *f, const uint32_t *v, size_t n)
{
    for (size_t i = 0; i < n; i++)
        mr_le_put_u32(feed_room(f, 4), v[i]);
}

void mr_sha256_feed_f32s(mr_sha256_feed *f, const float *v, size_t n)
{
    for (size_t i = 0; i < n; i++)
        mr_le_put_u32(feed_room(f, 4), mr_f32_bits(v[i]));
}

void mr_sha256_feed_final(mr_sha256_feed *f, uint8_t digest[32])
{
    feed_flush(f);
    mr_sha256_final(&f->sha, digest);
}
