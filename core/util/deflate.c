/*
 * deflate.c - the fast zlib-format compressor of deflate.h.
 *
 * Written from RFC 1950 (zlib wrapper) and RFC 1951 (deflate). Greedy
 * parsing: at each position the longest match among the candidate
 * distances (1, 2, 4, the row) is taken if it is at least 3 bytes long,
 * else a literal. Only dynamic Huffman blocks are
 * written; a block ends after MR_DEFLATE_BLOCK tokens. Code lengths are
 * Huffman's, limited to 15 (7 for the code-length code) by halving the
 * frequencies until they fit, which keeps every code complete; an
 * alphabet with fewer than two symbols in use gets dummy symbols so that
 * it never relies on the single-code special case of some inflaters.
 */
#include "util/deflate.h"

#include <libdeflate.h> /* libdeflate_adler32: the checksum, vectorised */
#include <stdbool.h>
#include <stdlib.h>
#include <string.h>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#define LITLEN_SYMS 286 /* 0-255 literals, 256 end of block, 257-285 lengths */
#define END_OF_BLOCK 256
#define DIST_SYMS 30
#define CL_SYMS 19
#define MAX_BITS 15
#define CL_MAX_BITS 7
#define WINDOW 32768u
#define MIN_MATCH 3u
#define MAX_MATCH 258u

struct mr_deflate {
    uint32_t tokens[MR_DEFLATE_BLOCK]; /* literal: the byte; match: length << 16 | distance */
    uint32_t lit_freq[LITLEN_SYMS], dist_freq[DIST_SYMS];
};

mr_deflate *mr_deflate_new(void)
{
    return calloc(1, sizeof(mr_deflate));
}

void mr_deflate_free(mr_deflate *d)
{
    free(d);
}

/* ------------------------------------------------------------------ */
/* bits out (deflate packs codes from the least significant bit up)    */

typedef struct bit_out {
    uint64_t acc;
    unsigned n;     /* bits held in acc, < 32 between calls */
    uint8_t *p, *end;
    bool full;      /* ran out of room: the result is discarded */
} bit_out;

static inline void put_bits(bit_out *w, uint64_t v, unsigned n)
{
    w->acc |= v << w->n;
    w->n += n;
    if (w->n >= 32) {
        if (w->end - w->p >= 4) {
            w->p[0] = (uint8_t)w->acc;
            w->p[1] = (uint8_t)(w->acc >> 8);
            w->p[2] = (uint8_t)(w->acc >> 16);
            w->p[3] = (uint8_t)(w->acc >> 24);
            w->p += 4;
        } else {
            w->full = true;
        }
        w->acc >>= 32;
        w->n -= 32;
    }
}

/* Pads with zero bits to a byte boundary and writes out what is held. */
static void flush_bits(bit_out *w)
{
    while (w->n > 0) {
        if (w->p < w->end)
            *w->p++ = (uint8_t)w->acc;
        else
            w->full = true;
        w->acc >>= 8;
        w->n = w->n > 8 ? w->n - 8 : 0;
    }
}

/* ------------------------------------------------------------------ */
/* Huffman codes                                                       */

/* Sorts key[0, m) ascending (keys below 2^24): three counting passes over
 * bytes; tmp has room for m keys. */
static void sort_keys(uint32_t *key, uint32_t *tmp, int m)
{
    uint32_t *from = key, *to = tmp, *t;
    for (unsigned shift = 0; shift < 24; shift += 8) {
        unsigned start[257] = {0};
        int k;
        for (k = 0; k < m; k++)
            start[((from[k] >> shift) & 255u) + 1]++;
        for (k = 1; k < 257; k++)
            start[k] += start[k - 1];
        for (k = 0; k < m; k++)
            to[start[(from[k] >> shift) & 255u]++] = from[k];
        t = from;
        from = to;
        to = t;
    }
    memcpy(key, from, (size_t)m * sizeof *key); /* three passes: the keys are in tmp */
}

/* Gives frequency to the lowest unused symbols until at least two are in
 * use, so that every code built is complete. */
static void at_least_two(uint32_t *freq, int n)
{
    int used = 0, s;
    for (s = 0; s < n; s++)
        used += freq[s] != 0;
    for (s = 0; s < n && used < 2; s++)
        if (!freq[s]) {
            freq[s] = 1;
            used++;
        }
}

/* Code lengths for freq[0, n) (n <= LITLEN_SYMS, at least two symbols in
 * use) of at most limit bits; 0 for unused symbols. Huffman's two-queue
 * construction over the symbols sorted by (frequency, symbol); while the
 * deepest leaf is too deep the frequencies are halved, rounding up, which
 * flattens the tree (all ones give depth ceil(log2 n) <= limit). */
static void huffman_lengths(const uint32_t *freq, int n, unsigned limit, uint8_t *len)
{
    uint32_t w[LITLEN_SYMS], key[LITLEN_SYMS], tmp[LITLEN_SYMS];
    uint32_t weight[2 * LITLEN_SYMS];
    uint16_t parent[2 * LITLEN_SYMS];
    uint8_t depth[2 * LITLEN_SYMS];
    int s, m;

    for (s = 0; s < n; s++)
        w[s] = freq[s];
    memset(len, 0, (size_t)n);
    for (;;) {
        int leaf = 0, inner, next, k;
        unsigned deepest = 0;

        /* Frequencies stay below 2^15 (a block's tokens, MR_DEFLATE_BLOCK),
         * symbols below 2^9: keys below 2^24. */
        for (m = 0, s = 0; s < n; s++)
            if (w[s])
                key[m++] = w[s] << 9 | (uint32_t)s;
        if (m < 2) { /* not for callers that keep the rule above */
            for (k = 0; k < m; k++)
                len[key[k] & 511u] = 1;
            return;
        }
        sort_keys(key, tmp, m);
        for (k = 0; k < m; k++)
            weight[k] = key[k] >> 9;
        inner = next = m;
        while (next < 2 * m - 1) {
            int pick[2];
            for (k = 0; k < 2; k++) {
                if (leaf < m && (inner >= next || weight[leaf] <= weight[inner]))
                    pick[k] = leaf++;
                else
                    pick[k] = inner++;
            }
            weight[next] = weight[pick[0]] + weight[pick[1]];
            parent[pick[0]] = parent[pick[1]] = (uint16_t)next;
            next++;
        }
        /* Parents are made after their children: one pass from the root. */
        depth[2 * m - 2] = 0;
        for (k = 2 * m - 3; k >= 0; k--)
            depth[k] = (uint8_t)(depth[parent[k]] + 1);
        for (k = 0; k < m; k++)
            if (depth[k] > deepest)
                deepest = depth[k];
        if (deepest <= limit) {
            for (k = 0; k < m; k++)
                len[key[k] & 511u] = depth[k];
            return;
        }
        for (s = 0; s < n; s++)
            if (w[s])
                w[s] = (w[s] + 1) / 2;
    }
}

/* Canonical codes (RFC 1951 3.2.2), bit-reversed for LSB-first output. */
static void canonical_codes(const uint8_t *len, int n, uint16_t *code)
{
    unsigned count[MAX_BITS + 1] = {0}, next[MAX_BITS + 1] = {0}, c = 0, b;
    int s;

    for (s = 0; s < n; s++)
        count[len[s]]++;
    count[0] = 0;
    for (b = 1; b <= MAX_BITS; b++) {
        c = (c + count[b - 1]) << 1;
        next[b] = c;
    }
    for (s = 0; s < n; s++) {
        unsigned l = len[s], v;
        if (!l)
            continue;
        v = next[l]++; /* l bits, reversed: all 16 reversed, shifted down */
        v = ((v >> 1) & 0x5555u) | ((v & 0x5555u) << 1);
        v = ((v >> 2) & 0x3333u) | ((v & 0x3333u) << 2);
        v = ((v >> 4) & 0x0f0fu) | ((v & 0x0f0fu) << 4);
        v = ((v >> 8) & 0x00ffu) | ((v & 0x00ffu) << 8);
        code[s] = (uint16_t)(v >> (16 - l));
    }
}

static inline unsigned floor_log2(uint32_t v)
{
    return 31u - (unsigned)__builtin_clz(v);
}

/* Length 3..258: its symbol, and the extra bits (count, value). */
static inline unsigned length_symbol(unsigned len, unsigned *nbits, unsigned *extra)
{
    unsigned v = len - 3, b;
    if (len == MAX_MATCH) {
        *nbits = *extra = 0;
        return 285;
    }
    if (v < 8) {
        *nbits = *extra = 0;
        return 257 + v;
    }
    b = floor_log2(v);
    *nbits = b - 2;
    *extra = v & ((1u << (b - 2)) - 1);
    return 257 + 4 * (b - 1) + ((v >> (b - 2)) & 3u);
}

/* Distance 1..32768: its symbol and extra bits. */
static inline unsigned dist_symbol(unsigned dist, unsigned *nbits, unsigned *extra)
{
    unsigned v = dist - 1, b;
    if (v < 4) {
        *nbits = *extra = 0;
        return v;
    }
    b = floor_log2(v);
    *nbits = b - 1;
    *extra = v & ((1u << (b - 1)) - 1);
    return 2 * b + ((v >> (b - 1)) & 1u);
}

/* ------------------------------------------------------------------ */
/* blocks                                                              */

/* One dynamic block of d->tokens[0, ntok) (RFC 1951 3.2.7). */
static void write_block(mr_deflate *d, bit_out *w, size_t ntok, bool final)
{
    static const uint8_t order[CL_SYMS] = {16, 17, 18, 0, 8, 7, 9, 6, 10, 5,
                                           11, 4, 12, 3, 13, 2, 14, 1, 15};
    uint8_t llen[LITLEN_SYMS], dlen[DIST_SYMS], cllen[CL_SYMS], lens[LITLEN_SYMS + DIST_SYMS];
    uint16_t lcode[LITLEN_SYMS], dcode[DIST_SYMS], clcode[CL_SYMS];
    uint8_t item_sym[LITLEN_SYMS + DIST_SYMS], item_extra[LITLEN_SYMS + DIST_SYMS];
    uint32_t cl_freq[CL_SYMS] = {0};
    int hlit, hdist, hclen, total, nitems = 0, k;
    size_t t;

    d->lit_freq[END_OF_BLOCK] = 1;
    at_least_two(d->lit_freq, LITLEN_SYMS);
    at_least_two(d->dist_freq, DIST_SYMS);
    huffman_lengths(d->lit_freq, LITLEN_SYMS, MAX_BITS, llen);
    huffman_lengths(d->dist_freq, DIST_SYMS, MAX_BITS, dlen);
    for (hlit = LITLEN_SYMS; hlit > 257 && !llen[hlit - 1]; hlit--)
        ;
    for (hdist = DIST_SYMS; hdist > 1 && !dlen[hdist - 1]; hdist--)
        ;

    /* Both length lists as one sequence, runs coded with 16 (repeat the
     * last length 3-6 times), 17 (3-10 zeros) and 18 (11-138 zeros). */
    memcpy(lens, llen, (size_t)hlit);
    memcpy(lens + hlit, dlen, (size_t)hdist);
    total = hlit + hdist;
    for (k = 0; k < total;) {
        int v = lens[k], run = 1;
        while (k + run < total && lens[k + run] == v)
            run++;
        k += run;
        if (v == 0) {
            while (run >= 11) {
                int r = run > 138 ? 138 : run;
                item_sym[nitems] = 18;
                item_extra[nitems++] = (uint8_t)(r - 11);
                run -= r;
            }
            if (run >= 3) {
                item_sym[nitems] = 17;
                item_extra[nitems++] = (uint8_t)(run - 3);
                run = 0;
            }
        } else {
            item_sym[nitems] = (uint8_t)v;
            item_extra[nitems++] = 0;
            run--;
            while (run >= 3) {
                int r = run > 6 ? 6 : run;
                item_sym[nitems] = 16;
                item_extra[nitems++] = (uint8_t)(r - 3);
                run -= r;
            }
        }
        while (run-- > 0) {
            item_sym[nitems] = (uint8_t)v;
            item_extra[nitems++] = 0;
        }
    }
    for (k = 0; k < nitems; k++)
        cl_freq[item_sym[k]]++;
    at_least_two(cl_freq, CL_SYMS);
    huffman_lengths(cl_freq, CL_SYMS, CL_MAX_BITS, cllen);
    canonical_codes(cllen, CL_SYMS, clcode);
    for (hclen = CL_SYMS; hclen > 4 && !cllen[order[hclen - 1]]; hclen--)
        ;

    put_bits(w, (final ? 1u : 0u) | 2u << 1, 3);
    put_bits(w, (unsigned)(hlit - 257), 5);
    put_bits(w, (unsigned)(hdist - 1), 5);
    put_bits(w, (unsigned)(hclen - 4), 4);
    for (k = 0; k < hclen; k++)
        put_bits(w, cllen[order[k]], 3);
    for (k = 0; k < nitems; k++) {
        unsigned s = item_sym[k];
        put_bits(w, clcode[s], cllen[s]);
        if (s == 16)
            put_bits(w, item_extra[k], 2);
        else if (s == 17)
            put_bits(w, item_extra[k], 3);
        else if (s == 18)
            put_bits(w, item_extra[k], 7);
    }

    canonical_codes(llen, LITLEN_SYMS, lcode);
    canonical_codes(dlen, DIST_SYMS, dcode);
    t = 0;
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
    /* With room for the worst case (48 bits a token) plus an 8-byte
     * store, no check per token: each token is one put of at most 48 bits
     * onto at most 7 held ones, and the whole 64-bit word is stored,
     * advancing by the bytes completed. */
    if ((size_t)(w->end - w->p) >= ntok * 6 + 8 + 4) {
        uint64_t acc;
        unsigned held;
        uint8_t *p;
        while (w->n >= 8) { /* hold at most 7 bits */
            *w->p++ = (uint8_t)w->acc;
            w->acc >>= 8;
            w->n -= 8;
        }
        acc = w->acc;
        held = w->n;
        p = w->p;
        for (; t < ntok; t++) {
            uint32_t tok = d->tokens[t];
            unsigned len = tok >> 16, nb, ex, ls, ds, bits;
            uint64_t v;
            if (!len) {
                v = lcode[tok];
                bits = llen[tok];
            } else {
                ls = length_symbol(len, &nb, &ex);
                v = lcode[ls] | (uint64_t)ex << llen[ls];
                bits = llen[ls] + nb;
                ds = dist_symbol(tok & 0xffffu, &nb, &ex);
                v |= (dcode[ds] | (uint64_t)ex << dlen[ds]) << bits;
                bits += dlen[ds] + nb;
            }
            acc |= v << held;
            held += bits;
            memcpy(p, &acc, 8);
            p += held >> 3;
            acc >>= held & ~7u;
            held &= 7u;
        }
        w->acc = acc;
        w->n = held;
        w->p = p;
    }
#endif
    for (; t < ntok; t++) {
        uint32_t tok = d->tokens[t];
        unsigned len = tok >> 16, nb, ex, ls, ds;
        if (!len) {
            put_bits(w, lcode[tok], llen[tok]);
            continue;
        }
        ls = length_symbol(len, &nb, &ex);
        put_bits(w, lcode[ls] | (uint64_t)ex << llen[ls], llen[ls] + nb);
        ds = dist_symbol(tok & 0xffffu, &nb, &ex);
        put_bits(w, dcode[ds] | (uint64_t)ex << dlen[ds], dlen[ds] + nb);
    }
    put_bits(w, lcode[END_OF_BLOCK], llen[END_OF_BLOCK]);
}

/* ------------------------------------------------------------------ */
/* matching                                                            */

/* The 3 bytes at p (4 readable), as a number. */
static inline uint32_t load24(const uint8_t *p)
{
    uint32_t v;
    memcpy(&v, p, 4);
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_BIG_ENDIAN__
    return v >> 8;
#else
    return v & 0xffffffu;
#endif
}

/* Equal leading bytes of a and b, at most max (a and b may overlap). */
static inline size_t match_length(const uint8_t *a, const uint8_t *b, size_t max)
{
    size_t l = 0;
#if defined(__SSE2__)
    while (l + 16 <= max) {
        __m128i x = _mm_loadu_si128((const __m128i *)(const void *)(a + l));
        __m128i y = _mm_loadu_si128((const __m128i *)(const void *)(b + l));
        unsigned eq = (unsigned)_mm_movemask_epi8(_mm_cmpeq_epi8(x, y));
        if (eq != 0xffffu)
            return l + (size_t)__builtin_ctz(~eq);
        l += 16;
    }
#endif
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
    while (l + 8 <= max) {
        uint64_t x, y;
        memcpy(&x, a + l, 8);
        memcpy(&y, b + l, 8);
        if (x != y)
            return l + (size_t)(__builtin_ctzll(x ^ y) >> 3);
        l += 8;
    }
#endif
    while (l < max && a[l] == b[l])
        l++;
    return l;
}

#if defined(__SSE2__)
/* How many of the 16 positions from p on start no match of 3 bytes at any
 * candidate distance (all of cand[0, ncand) reachable; p[0, 18) and
 * p - cand[k] readable): the number before the first that does, 16 if
 * none does. */
static inline unsigned literal_run16(const uint8_t *p, const size_t *cand, int ncand)
{
    const __m128i a = _mm_loadu_si128((const __m128i *)(const void *)p);
    const __m128i b = _mm_loadu_si128((const __m128i *)(const void *)(p + 2));
    unsigned starts = 0;
    for (int k = 0; k < ncand; k++) {
        const uint8_t *q = p - cand[k];
        unsigned ea = (unsigned)_mm_movemask_epi8(
            _mm_cmpeq_epi8(a, _mm_loadu_si128((const __m128i *)(const void *)q)));
        unsigned eb = (unsigned)_mm_movemask_epi8(
            _mm_cmpeq_epi8(b, _mm_loadu_si128((const __m128i *)(const void *)(q + 2))));
        unsigned eq = ea | (eb >> 14) << 16; /* bit j: p[j] == q[j], j < 18 */
        starts |= eq & (eq >> 1) & (eq >> 2);
    }
    starts &= 0xffffu;
    return starts ? (unsigned)__builtin_ctz(starts) : 16u;
}
#endif

size_t mr_deflate_zlib(mr_deflate *d, const uint8_t *in, size_t n, size_t row, uint8_t *out,
                       size_t cap)
{
    bit_out w;
    size_t cand[4], i = 0;
    int ncand = 0;
    uint32_t adler;

    if (!d || !out || (!in && n) || cap < 2 + 4 || n >= UINT32_MAX)
        return 0;
    out[0] = 0x78; /* deflate, 32 KiB window */
    out[1] = 0x01; /* no dictionary, "fastest"; (0x78 << 8 | 0x01) % 31 == 0 */
    w.acc = 0;
    w.n = 0;
    w.p = out + 2;
    w.end = out + cap - 4; /* room for the Adler-32 */
    w.full = false;

    /* Ascending, so the first one out of reach ends the search. */
    cand[ncand++] = 1;
    cand[ncand++] = 2;
    cand[ncand++] = 4;
    if (row > 4 && row <= WINDOW)
        cand[ncand++] = row;

    do {
        size_t ntok = 0;
        memset(d->lit_freq, 0, sizeof d->lit_freq);
        memset(d->dist_freq, 0, sizeof d->dist_freq);
        while (i < n && ntok < MR_DEFLATE_BLOCK) {
            size_t max = n - i < MAX_MATCH ? n - i : MAX_MATCH, best = 0, dist = 0;
#if defined(__SSE2__)
            /* Literals come in stretches (the detail between runs): 16
             * positions at a time, those where no candidate repeats the
             * next 3 bytes are literals, exactly as the test below finds. */
            if (i >= 4 && n - i >= 18 + 16 && ntok + 16 <= MR_DEFLATE_BLOCK) {
                unsigned lits = literal_run16(in + i, cand, i >= cand[ncand - 1] ? ncand : 3);
                if (lits) {
                    for (unsigned j = 0; j < lits; j++) {
                        d->tokens[ntok++] = in[i + j];
                        d->lit_freq[in[i + j]]++;
                    }
                    i += lits;
                    continue;
                }
            }
#endif
            if (max >= 4) {
                /* Which candidates share the next 3 bytes, without a branch
                 * per candidate (at a literal, none does: one branch). */
                uint32_t cur = load24(in + i);
                unsigned hits = 0;
                for (int k = 0; k < ncand && cand[k] <= i; k++)
                    hits |= (unsigned)(load24(in + i - cand[k]) == cur) << k;
                while (hits) {
                    int k = __builtin_ctz(hits);
                    size_t l;
                    hits &= hits - 1;
                    if (in[i + best] != in[i + best - cand[k]])
                        continue;
                    l = match_length(in + i, in + i - cand[k], max);
                    if (l > best) {
                        best = l;
                        dist = cand[k];
                        if (l == max)
                            break;
                    }
                }
            } else if (max == 3) { /* the last 3 bytes */
                for (int k = 0; k < ncand && cand[k] <= i && !best; k++)
                    if (match_length(in + i, in + i - cand[k], 3) == 3) {
                        best = 3;
                        dist = cand[k];
                    }
            }
            if (best >= MIN_MATCH) {
                unsigned nb, ex;
                d->tokens[ntok++] = (uint32_t)best << 16 | (uint32_t)dist;
                d->lit_freq[length_symbol((unsigned)best, &nb, &ex)]++;
                d->dist_freq[dist_symbol((unsigned)dist, &nb, &ex)]++;
                i += best;
            } else {
                d->tokens[ntok++] = in[i];
                d->lit_freq[in[i]]++;
                i++;
            }
        }
        write_block(d, &w, ntok, i >= n);
        if (w.full)
            return 0;
    } while (i < n);

    flush_bits(&w);
    if (w.full)
        return 0;
    adler = libdeflate_adler32(1, in, n);
    w.p[0] = (uint8_t)(adler >> 24); /* big-endian (RFC 1950) */
    w.p[1] = (uint8_t)(adler >> 16);
    w.p[2] = (uint8_t)(adler >> 8);
    w.p[3] = (uint8_t)adler;
    return (size_t)(w.p + 4 - out);
}
