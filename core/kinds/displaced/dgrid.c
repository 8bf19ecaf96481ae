/* dgrid.c - height textures on a repeating grid and their min/max pyramid (dgrid.h). */
#include "kinds/displaced/dgrid.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "kinds/displaced/dsurf.h"
#include "util/parallel.h"

#if defined(__SSE2__)
#include <emmintrin.h>
#endif
#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#endif

void mr_dgrid_free(mr_dgrid *g)
{
    if (!g)
        return;
    free(g->owned);
    free(g->qmin);
    free(g->qmax);
    free(g->bmin);
    free(g->bmax);
    memset(g, 0, sizeof *g);
}

size_t mr_dgrid_memory(const mr_dgrid *g)
{
    size_t b = g->levels ? (g->first[g->levels] + 1) * 2 * (g->bmin ? 1 : sizeof(uint16_t)) : 0;
    if (g->owned)
        b += (size_t)g->w * g->h * sizeof(float);
    return b;
}

/* Quantised bounds (dgrid.h): the minimum a step lower and the maximum a
 * step higher than the rounded values, clamped to the range, whose ends
 * dequantise exactly. */
static inline uint16_t q_lo(const mr_dgrid *g, double s)
{
    if (g->qstep == 0)
        return 0;
    double q = floor((s - g->gmin) / g->qstep) - 1;
    return q <= 0 ? 0 : q >= 65535 ? 65535 : (uint16_t)q;
}

static inline uint16_t q_hi(const mr_dgrid *g, double s)
{
    if (g->qstep == 0)
        return 65535;
    double q = ceil((s - g->gmin) / g->qstep) + 1;
    return q <= 0 ? 0 : q >= 65535 ? 65535 : (uint16_t)q;
}

/* The quantised bounds of an 8-bit value over the whole 0..255 range: what
 * q_lo and q_hi give there (linear8 checks it for the grid at hand). */
static inline uint16_t linear8_lo(uint8_t v) { return v ? (uint16_t)(257 * v - 1) : 0; }
static inline uint16_t linear8_hi(uint8_t v) { return v < 255 ? (uint16_t)(257 * v + 1) : 65535; }

/* Whether an 8-bit grid's quantisation is exactly linear8_lo/hi (then its
 * pyramid keeps the samples' own 8-bit extremes: half the memory). */
static bool linear8(const mr_dgrid *g)
{
    if (g->type != MR_SAMPLE_U8)
        return false;
    for (unsigned v = 0; v < 256; v++)
        if (q_lo(g, v) != linear8_lo((uint8_t)v) || q_hi(g, v) != linear8_hi((uint8_t)v))
            return false;
    return true;
}

static inline double dq(const mr_dgrid *g, uint16_t q)
{
    return q == 0 ? g->gmin : q == 65535 ? g->gmax : g->gmin + q * g->qstep;
}

/* mr_dgrid_node_samples, inline in both its callers here (the traversal
 * asks for a node's heights every time it makes the node's box). */
static inline __attribute__((always_inline)) void node_samples(const mr_dgrid *g, unsigned l,
                                                               uint32_t I, uint32_t J, double *lo,
                                                               double *hi)
{
    if (l == 0) {
        uint32_t i1 = I + 1 == g->w ? 0 : I + 1, j1 = J + 1 == g->h ? 0 : J + 1;
        double a = mr_dgrid_sample(g, I, J), b = mr_dgrid_sample(g, i1, J);
        double c = mr_dgrid_sample(g, I, j1), d = mr_dgrid_sample(g, i1, j1);
        double ab = a < b ? a : b, cd = c < d ? c : d, AB = a > b ? a : b, CD = c > d ? c : d;
        *lo = ab < cd ? ab : cd;
        *hi = AB > CD ? AB : CD;
        return;
    }
    size_t k = g->first[l] + (size_t)J * g->lw[l] + I;
    if (g->bmin) {
        *lo = dq(g, linear8_lo(g->bmin[k]));
        *hi = dq(g, linear8_hi(g->bmax[k]));
        return;
    }
    *lo = dq(g, g->qmin[k]);
    *hi = dq(g, g->qmax[k]);
}

void mr_dgrid_node_samples(const mr_dgrid *g, unsigned l, uint32_t I, uint32_t J, double *lo,
                           double *hi)
{
    node_samples(g, l, I, J, lo, hi);
}

void mr_dgrid_node_heights_slow(const mr_dgrid *g, unsigned l, uint32_t I, uint32_t J, double *lo,
                                double *hi)
{
    double a, b;
    node_samples(g, l, I, J, &a, &b);
    double ha = mr_dgrid_height_of(g, a), hb = mr_dgrid_height_of(g, b);
    *lo = ha < hb ? ha : hb;
    *hi = ha > hb ? ha : hb;
}

#if defined(__x86_64__) && defined(__GNUC__)
/* mr_dgrid_height_of of four samples (AVX2): its operations lane by lane. */
__attribute__((target("avx2"))) static inline __m256d heights4(const mr_dgrid *g, __m256d s)
{
    if (g->unit != 1)
        s = _mm256_div_pd(s, _mm256_set1_pd(g->unit));
    return _mm256_add_pd(_mm256_set1_pd(g->offset), _mm256_mul_pd(_mm256_set1_pd(g->scale), s));
}

/* dq of four quantised values (AVX2): gmin + q qstep, gmax for the top
 * value (gmin for 0 is the same formula). */
__attribute__((target("avx2"))) static inline __m256d dq4(const mr_dgrid *g, __m128i q)
{
    const __m256d v = _mm256_add_pd(_mm256_set1_pd(g->gmin),
                                    _mm256_mul_pd(_mm256_cvtepi32_pd(q), _mm256_set1_pd(g->qstep)));
    const __m128i top = _mm_cmpeq_epi32(q, _mm_set1_epi32(65535));
    return _mm256_blendv_pd(v, _mm256_set1_pd(g->gmax),
                            _mm256_castsi256_pd(_mm256_cvtepi32_epi64(top)));
}

__attribute__((target("avx2"))) void mr_dgrid_child_heights_avx2(const mr_dgrid *g, unsigned c,
                                                                   uint32_t I0, uint32_t J0,
                                                                   unsigned mask, double hl[4],
                                                                   double hh[4])
{
    /* one by one: 8-bit samples (looked up: no faster four at once), a
     * missing child, a cell across the period's edge, a byte pyramid */
    if (g->lut8 || I0 + 1 >= g->lw[c] || J0 + 1 >= g->lh[c] ||
        (c == 0 ? I0 + 2 >= g->w || J0 + 2 >= g->h : !g->qmin)) {
        for (unsigned m = mask; m; m &= m - 1) {
            const unsigned k = (unsigned)__builtin_ctz(m);
            mr_dgrid_node_heights(g, c, I0 + (k & 1u), J0 + (k >> 1), &hl[k], &hh[k]);
        }
        return;
    }
    __m256d a, b; /* each child's smallest and largest sample */
    if (c == 0) {
        /* the four cells' 3 x 3 corners; cell k's corner (x, y) is
         * v[y + (k >> 1)][x + (k & 1)], in node_samples' order of min
         * and max (a, b, c, d: corners (0, 0), (1, 0), (0, 1), (1, 1)) */
        double v[3][3];
        for (uint32_t y = 0; y < 3; y++)
            for (uint32_t x = 0; x < 3; x++)
                v[y][x] = mr_dgrid_sample(g, I0 + x, J0 + y);
        const __m256d s00 = _mm256_set_pd(v[1][1], v[1][0], v[0][1], v[0][0]);
        const __m256d s10 = _mm256_set_pd(v[1][2], v[1][1], v[0][2], v[0][1]);
        const __m256d s01 = _mm256_set_pd(v[2][1], v[2][0], v[1][1], v[1][0]);
        const __m256d s11 = _mm256_set_pd(v[2][2], v[2][1], v[1][2], v[1][1]);
        a = _mm256_min_pd(_mm256_min_pd(s00, s10), _mm256_min_pd(s01, s11));
        b = _mm256_max_pd(_mm256_max_pd(s00, s10), _mm256_max_pd(s01, s11));
    } else {
        const size_t k0 = g->first[c] + (size_t)J0 * g->lw[c] + I0, k1 = k0 + g->lw[c];
        a = dq4(g, _mm_set_epi32(g->qmin[k1 + 1], g->qmin[k1], g->qmin[k0 + 1], g->qmin[k0]));
        b = dq4(g, _mm_set_epi32(g->qmax[k1 + 1], g->qmax[k1], g->qmax[k0 + 1], g->qmax[k0]));
    }
    const __m256d ha = heights4(g, a), hb = heights4(g, b);
    _mm256_storeu_pd(hl, _mm256_min_pd(ha, hb)); /* (ordered: scale may be negative) */
    _mm256_storeu_pd(hh, _mm256_max_pd(ha, hb));
}
#endif

/* The period holding cell i of a grid of n cells per period. */
static inline int64_t period_of(int64_t i, uint32_t n)
{
    return (uint64_t)i < n ? 0 : mr_floor_div(i, n);
}

void mr_dgrid_range_samples(const mr_dgrid *g, int64_t i0, int64_t i1, int64_t j0, int64_t j1,
                            double *lo, double *hi)
{
    mr_dgrid_node_samples(g, g->levels, 0, 0, lo, hi);
    if (i1 - i0 >= (int64_t)g->w || j1 - j0 >= (int64_t)g->h)
        return;
    /* within one period per axis (possibly straddling its border): nodes
     * of level l are indexed per period. Nodes of 2^l cells hold any
     * span of at most 2^l cells in two, so the search starts one below */
    int64_t span = (i1 - i0 > j1 - j0 ? i1 - i0 : j1 - j0) + 1;
    unsigned l0 = 0;
    while (l0 < g->levels && ((int64_t)2 << l0) < span)
        l0++;
    /* the periods of the corners and the cells within them, once for every
     * level (and divisions only outside the first period) */
    int64_t ti0 = period_of(i0, g->w), ti1 = period_of(i1, g->w);
    int64_t tj0 = period_of(j0, g->h), tj1 = period_of(j1, g->h);
    int64_t ri0 = i0 - ti0 * g->w, ri1 = i1 - ti1 * g->w, rj0 = j0 - tj0 * g->h, rj1 = j1 - tj1 * g->h;
    for (unsigned l = l0; l <= g->levels; l++) {
        int64_t x0 = ti0 * g->lw[l] + (ri0 >> l), x1 = ti1 * g->lw[l] + (ri1 >> l);
        int64_t y0 = tj0 * g->lh[l] + (rj0 >> l), y1 = tj1 * g->lh[l] + (rj1 >> l);
        if (x1 - x0 > 1 || y1 - y0 > 1)
            continue;
        double mn = INFINITY, mx = -INFINITY;
        for (int64_t y = y0; y <= y1; y++)
            for (int64_t x = x0; x <= x1; x++) {
                double a, b;
                mr_dgrid_node_samples(g, l, (uint32_t)mr_dgrid_wrap(x, g->lw[l]),
                                      (uint32_t)mr_dgrid_wrap(y, g->lh[l]), &a, &b);
                mn = a < mn ? a : mn;
                mx = b > mx ? b : mx;
            }
        *lo = mn;
        *hi = mx;
        return;
    }
}

/* ---- building ---------------------------------------------------------------- */

typedef struct build_ctx {
    mr_dgrid *g;
    unsigned level;
    uint16_t *tlo, *thi; /* integer samples: their quantised bounds, by value */
} build_ctx;

/* Level 1 of 8 or 16 bit samples: the same nodes as build_level1, read
 * straight from the rows (no conversion per sample) and quantised by table
 * (or, for the 8-bit pyramid, kept as they are), which is what makes a new
 * height texture cheap. A node row's three sample
 * rows are reduced column by column 16 bytes at a time (GCC vector
 * extensions: SSE2 on x86-64; unsigned compares select by mask), then each
 * node takes the smallest and largest of its three columns. */
typedef uint8_t v16u8 __attribute__((vector_size(16)));
typedef int8_t v16i8 __attribute__((vector_size(16)));
typedef uint16_t v8u16 __attribute__((vector_size(16)));
typedef int16_t v8i16 __attribute__((vector_size(16)));

/* The smallest (or largest) of columns 2I, 2I+1, 2I+2 of c for 16 nodes
 * from node I on: triples at every column, then every other one. Reads
 * c[2I .. 2I+33]. */
#if defined(__SSE2__)
static inline __m128i triples_u8(const uint8_t *c, bool largest)
{
    __m128i t[2];
    for (int h = 0; h < 2; h++) {
        __m128i a = _mm_loadu_si128((const __m128i *)(c + 16 * h));
        __m128i b = _mm_loadu_si128((const __m128i *)(c + 16 * h + 1));
        __m128i d = _mm_loadu_si128((const __m128i *)(c + 16 * h + 2));
        t[h] = largest ? _mm_max_epu8(_mm_max_epu8(a, b), d) : _mm_min_epu8(_mm_min_epu8(a, b), d);
    }
    __m128i even = _mm_set1_epi16(0x00ff);
    return _mm_packus_epi16(_mm_and_si128(t[0], even), _mm_and_si128(t[1], even));
}
#endif

/* Nodes [I, ...) of a level-1 row of 8-bit samples 16 at a time while all
 * their columns are in c[0 .. w], node I at k0 + I; returns the first node
 * not done. */
static uint32_t nodes_uint8_t(const build_ctx *c, const uint8_t *cmin, const uint8_t *cmax,
                              uint32_t I, uint32_t full, uint32_t w, size_t k0)
{
#if defined(__SSE2__)
    const mr_dgrid *g = c->g;
    for (; I + 16 <= full && 2 * I + 34 <= w + 1; I += 16) {
        __m128i lo = triples_u8(cmin + 2 * I, false), hi = triples_u8(cmax + 2 * I, true);
        if (g->bmin) {
            _mm_storeu_si128((__m128i *)(g->bmin + k0 + I), lo);
            _mm_storeu_si128((__m128i *)(g->bmax + k0 + I), hi);
            continue;
        }
        uint8_t l[16], h[16];
        _mm_storeu_si128((__m128i *)l, lo);
        _mm_storeu_si128((__m128i *)h, hi);
        for (int k = 0; k < 16; k++) {
            g->qmin[k0 + I + k] = c->tlo[l[k]];
            g->qmax[k0 + I + k] = c->thi[h[k]];
        }
    }
#else
    (void)c, (void)cmin, (void)cmax, (void)full, (void)w, (void)k0;
#endif
    return I;
}

static uint32_t nodes_uint16_t(const build_ctx *c, const uint16_t *cmin, const uint16_t *cmax,
                               uint32_t I, uint32_t full, uint32_t w, size_t k0)
{
    (void)c, (void)cmin, (void)cmax, (void)full, (void)w, (void)k0;
    return I;
}

/* Node k of level 1 from its samples' extremes lo, hi: the extremes
 * themselves (8-bit pyramid) or their quantised bounds by table. */
#define PUT_NODE(k, lo, hi)                                                                  \
    do {                                                                                     \
        if (g->bmin) {                                                                       \
            g->bmin[k] = (uint8_t)(lo);                                                      \
            g->bmax[k] = (uint8_t)(hi);                                                      \
        } else {                                                                             \
            g->qmin[k] = c->tlo[lo];                                                         \
            g->qmax[k] = c->thi[hi];                                                         \
        }                                                                                    \
    } while (0)

#define LEVEL1_INT(T, VT, VI)                                                                 \
    static void build_level1_##T(void *ctx, size_t begin, size_t end, unsigned worker)       \
    {                                                                                        \
        (void)worker;                                                                        \
        const build_ctx *c = ctx;                                                            \
        const mr_dgrid *g = c->g;                                                            \
        const T *px = g->samples;                                                            \
        uint32_t nw = g->lw[1], w = g->w;                                                    \
        T *cmin = malloc(((size_t)w + 1) * 2 * sizeof(T)), *cmax = cmin + w + 1;             \
        if (!cmin)                                                                           \
            return;                                                                          \
        const uint32_t lanes = sizeof(VT) / sizeof(T);                                       \
        for (size_t J = begin; J < end; J++) {                                               \
            /* the node row's sample rows j0 .. j0 + 2 (the last wrapping; one row less    \
             * when h is odd and this is the last node row) */                               \
            uint32_t j0 = (uint32_t)J * 2, j1 = j0 + 2 < g->h ? j0 + 2 : g->h;               \
            const T *r[3];                                                                   \
            for (uint32_t k = 0; k < 3; k++) {                                               \
                uint32_t j = j0 + k <= j1 ? j0 + k : j1;                                     \
                r[k] = px + (size_t)(g->h - 1 - (j == g->h ? 0 : j)) * w;                    \
            }                                                                                \
            uint32_t x = 0;                                                                  \
            for (; x + lanes <= w; x += lanes) {                                             \
                VT a, b, d;                                                                  \
                memcpy(&a, r[0] + x, sizeof a);                                              \
                memcpy(&b, r[1] + x, sizeof b);                                              \
                memcpy(&d, r[2] + x, sizeof d);                                              \
                VI m = a < b;                                                                \
                VT lo = (VT)((m & (VI)a) | (~m & (VI)b)), hi = (VT)((m & (VI)b) | (~m & (VI)a)); \
                m = d < lo;                                                                  \
                lo = (VT)((m & (VI)d) | (~m & (VI)lo));                                      \
                m = d > hi;                                                                  \
                hi = (VT)((m & (VI)d) | (~m & (VI)hi));                                      \
                memcpy(cmin + x, &lo, sizeof lo);                                            \
                memcpy(cmax + x, &hi, sizeof hi);                                            \
            }                                                                                \
            for (; x < w; x++) {                                                             \
                T a = r[0][x], b = r[1][x], d = r[2][x];                                     \
                T lo = a < b ? a : b, hi = a < b ? b : a;                                    \
                cmin[x] = d < lo ? d : lo;                                                   \
                cmax[x] = d > hi ? d : hi;                                                   \
            }                                                                                \
            cmin[w] = cmin[0], cmax[w] = cmax[0]; /* the repeat */                           \
            size_t k0 = g->first[1] + J * nw;                                                \
            uint32_t full = (w - 1) / 2; /* nodes with all three columns */                  \
            uint32_t I0 = nodes_##T(c, cmin, cmax, 0, full, w, k0);                          \
            size_t k = k0 + I0;                                                              \
            for (uint32_t I = I0; I < full; I++, k++) {                                      \
                const T *lo3 = cmin + 2 * I, *hi3 = cmax + 2 * I;                            \
                T lo = lo3[0] < lo3[1] ? lo3[0] : lo3[1];                                    \
                T hi = hi3[0] > hi3[1] ? hi3[0] : hi3[1];                                    \
                lo = lo3[2] < lo ? lo3[2] : lo;                                              \
                hi = hi3[2] > hi ? hi3[2] : hi;                                              \
                PUT_NODE(k, lo, hi);                                                         \
            }                                                                                \
            for (uint32_t I = full; I < nw; I++, k++) {                                      \
                uint32_t i0 = I * 2, i1 = i0 + 2 < w ? i0 + 2 : w;                           \
                T lo = cmin[i0], hi = cmax[i0];                                              \
                for (uint32_t i = i0 + 1; i <= i1; i++) {                                    \
                    lo = cmin[i] < lo ? cmin[i] : lo;                                        \
                    hi = cmax[i] > hi ? cmax[i] : hi;                                        \
                }                                                                            \
                PUT_NODE(k, lo, hi);                                                         \
            }                                                                                \
        }                                                                                    \
        free(cmin);                                                                          \
    }
LEVEL1_INT(uint8_t, v16u8, v16i8)
LEVEL1_INT(uint16_t, v8u16, v8i16)

/* Level 1 from the samples: node (I, J) covers cells [2I, min(2I+2, w)),
 * i.e. samples 2I .. min(2I+2, w) (the last wrapping to 0). Rows of nodes
 * [begin, end). */
static void build_level1(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    const mr_dgrid *g = ((build_ctx *)ctx)->g;
    uint32_t nw = g->lw[1];
    for (size_t J = begin; J < end; J++) {
        uint32_t j0 = (uint32_t)J * 2, j1 = j0 + 2 < g->h ? j0 + 2 : g->h;
        for (uint32_t I = 0; I < nw; I++) {
            uint32_t i0 = I * 2, i1 = i0 + 2 < g->w ? i0 + 2 : g->w;
            double lo = INFINITY, hi = -INFINITY;
            for (uint32_t j = j0; j <= j1; j++)
                for (uint32_t i = i0; i <= i1; i++) {
                    double s = mr_dgrid_sample(g, i == g->w ? 0 : i, j == g->h ? 0 : j);
                    lo = fmin(lo, s);
                    hi = fmax(hi, s);
                }
            size_t k = g->first[1] + J * nw + I;
            g->qmin[k] = q_lo(g, lo);
            g->qmax[k] = q_hi(g, hi);
        }
    }
}

/* Children pairs (2I, 2I+1) of rows a and b: the smallest (or largest) of
 * each 2x2 block, for 8 nodes from node I on, into out[8]. Unsigned 16-bit
 * values are compared as signed after flipping the top bit (SSE2 has only
 * signed 16-bit min and max); reads a and b at 2I .. 2I+15. */
#if defined(__SSE2__)
static inline void blocks_u16(const uint16_t *a, const uint16_t *b, bool largest, uint16_t *out)
{
    const __m128i flip = _mm_set1_epi16((short)0x8000);
    __m128i h[2];
    for (int k = 0; k < 2; k++) {
        __m128i x = _mm_xor_si128(_mm_loadu_si128((const __m128i *)(a + 8 * k)), flip);
        __m128i y = _mm_xor_si128(_mm_loadu_si128((const __m128i *)(b + 8 * k)), flip);
        __m128i v = largest ? _mm_max_epi16(x, y) : _mm_min_epi16(x, y);
        __m128i odd = _mm_srli_epi32(v, 16);
        v = largest ? _mm_max_epi16(v, odd) : _mm_min_epi16(v, odd);
        h[k] = _mm_srai_epi32(_mm_slli_epi32(v, 16), 16); /* the even lanes, sign-extended */
    }
    _mm_storeu_si128((__m128i *)out, _mm_xor_si128(_mm_packs_epi32(h[0], h[1]), flip));
}
#endif

/* The same for 8-bit values, 16 nodes from node I on (reads a and b at
 * 2I .. 2I+31): the smaller (larger) of the rows, then of each byte pair. */
#if defined(__SSE2__)
static inline void blocks_u8(const uint8_t *a, const uint8_t *b, bool largest, uint8_t *out)
{
    const __m128i low = _mm_set1_epi16(0x00ff);
    __m128i h[2];
    for (int k = 0; k < 2; k++) {
        __m128i x = _mm_loadu_si128((const __m128i *)(a + 16 * k));
        __m128i y = _mm_loadu_si128((const __m128i *)(b + 16 * k));
        __m128i v = largest ? _mm_max_epu8(x, y) : _mm_min_epu8(x, y);
        __m128i odd = _mm_srli_epi16(v, 8);
        v = largest ? _mm_max_epu8(v, odd) : _mm_min_epu8(v, odd);
        h[k] = _mm_and_si128(v, low);
    }
    _mm_storeu_si128((__m128i *)out, _mm_packus_epi16(h[0], h[1]));
}
#endif

/* Level l > 1 from level l - 1 (quantised values combine exactly): a node
 * takes the 2x2 children that exist (the last column or row of children
 * is missing when the level below has an odd count). One function per node
 * type: 16-bit values (lo, hi: qmin, qmax) and the 8-bit pyramid's (bmin,
 * bmax), blocks of 16 bytes of nodes at a time with SSE2. */
#if defined(__SSE2__)
#define UPPER_BLOCKS(blocks, T, min0, min1, max0, max1, omin, omax, I, cw)                       \
    for (; 2 * I + 32 / sizeof(T) <= cw; I += 16 / sizeof(T)) {                                \
        blocks(min0 + 2 * I, min1 + 2 * I, false, omin + I);                                   \
        blocks(max0 + 2 * I, max1 + 2 * I, true, omax + I);                                    \
    }
#else
#define UPPER_BLOCKS(blocks, T, min0, min1, max0, max1, omin, omax, I, cw)
#endif
#define BUILD_UPPER(name, T, lo, hi, blocks)                                                   \
    static void name(void *ctx, size_t begin, size_t end, unsigned worker)                     \
    {                                                                                          \
        (void)worker;                                                                          \
        build_ctx *c = ctx;                                                                    \
        const mr_dgrid *g = c->g;                                                              \
        unsigned l = c->level;                                                                 \
        uint32_t cw = g->lw[l - 1], ch = g->lh[l - 1], nw = g->lw[l];                          \
        const T *cmin = g->lo + g->first[l - 1], *cmax = g->hi + g->first[l - 1];              \
        for (size_t J = begin; J < end; J++) {                                                 \
            uint32_t cj = (uint32_t)J * 2;                                                     \
            const T *min0 = cmin + (size_t)cj * cw, *max0 = cmax + (size_t)cj * cw;            \
            /* the second row of children, or the first again when it is missing */           \
            size_t down = cj + 1 < ch ? cw : 0;                                                \
            const T *min1 = min0 + down, *max1 = max0 + down;                                  \
            T *omin = g->lo + g->first[l] + J * nw, *omax = g->hi + g->first[l] + J * nw;      \
            uint32_t I = 0;                                                                    \
            UPPER_BLOCKS(blocks, T, min0, min1, max0, max1, omin, omax, I, cw)                 \
            for (; I < nw; I++) {                                                              \
                uint32_t a = I * 2, b = a + 1 < cw ? a + 1 : a;                                \
                T lo0 = min0[a] < min0[b] ? min0[a] : min0[b];                                 \
                T lo1 = min1[a] < min1[b] ? min1[a] : min1[b];                                 \
                T hi0 = max0[a] > max0[b] ? max0[a] : max0[b];                                 \
                T hi1 = max1[a] > max1[b] ? max1[a] : max1[b];                                 \
                omin[I] = lo0 < lo1 ? lo0 : lo1;                                               \
                omax[I] = hi0 > hi1 ? hi0 : hi1;                                               \
            }                                                                                  \
        }                                                                                      \
    }
BUILD_UPPER(build_upper, uint16_t, qmin, qmax, blocks_u16)
BUILD_UPPER(build_upper_bytes, uint8_t, bmin, bmax, blocks_u8)

typedef struct range_ctx {
    const mr_dgrid *g;
    double lo[MR_MAX_THREADS], hi[MR_MAX_THREADS];
} range_ctx;

static void sample_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    range_ctx *c = ctx;
    const mr_dgrid *g = c->g;
    double lo = c->lo[worker], hi = c->hi[worker];
    if (g->type == MR_SAMPLE_U8 || g->type == MR_SAMPLE_U16) {
        unsigned mn = 65535, mx = 0;
        for (size_t j = begin; j < end; j++) {
            size_t row = (size_t)j * g->w;
            for (uint32_t i = 0; i < g->w; i++) {
                unsigned v = g->type == MR_SAMPLE_U8 ? ((const uint8_t *)g->samples)[row + i]
                                                     : ((const uint16_t *)g->samples)[row + i];
                mn = v < mn ? v : mn;
                mx = v > mx ? v : mx;
            }
        }
        if (end > begin) {
            c->lo[worker] = fmin(lo, mn);
            c->hi[worker] = fmax(hi, mx);
        }
        return;
    }
    for (size_t j = begin; j < end; j++)
        for (uint32_t i = 0; i < g->w; i++) {
            double s = mr_dgrid_sample(g, i, (uint32_t)j);
            lo = fmin(lo, s);
            hi = fmax(hi, s);
        }
    c->lo[worker] = lo;
    c->hi[worker] = hi;
}

void mr_dgrid_rebuild(mr_dgrid *g, unsigned threads)
{
    range_ctx *rc = g->type == MR_SAMPLE_F32 ? malloc(sizeof *rc) : NULL;
    double lo = INFINITY, hi = -INFINITY;
    if (g->type != MR_SAMPLE_F32 && g->levels) {
        /* integer samples: quantise over the type's whole range (no scan of
         * the texture; a value's bounds are still exact to a step) */
        lo = 0;
        hi = g->unit;
    } else if (rc) {
        rc->g = g;
        for (unsigned w = 0; w < MR_MAX_THREADS; w++)
            rc->lo[w] = INFINITY, rc->hi[w] = -INFINITY;
        mr_parallel_for(threads, g->h, 64, sample_range, rc);
        for (unsigned w = 0; w < MR_MAX_THREADS; w++)
            lo = fmin(lo, rc->lo[w]), hi = fmax(hi, rc->hi[w]);
        free(rc);
    } else {
        range_ctx one = {.g = g};
        one.lo[0] = INFINITY, one.hi[0] = -INFINITY;
        sample_range(&one, 0, g->h, 0);
        lo = one.lo[0], hi = one.hi[0];
    }
    g->gmin = lo;
    g->gmax = hi;
    g->qstep = hi > lo ? (hi - lo) / 65535.0 : 0.0;
    if (!g->levels)
        return;
    build_ctx c = {.g = g, .level = 1};
    size_t values = g->type == MR_SAMPLE_U8 ? 256 : g->type == MR_SAMPLE_U16 ? 65536 : 0;
    if (values) {
        c.tlo = malloc(values * sizeof *c.tlo);
        c.thi = malloc(values * sizeof *c.thi);
    }
    if (c.tlo && c.thi) {
        for (size_t v = 0; v < values; v++) {
            c.tlo[v] = q_lo(g, (double)v);
            c.thi[v] = q_hi(g, (double)v);
        }
        mr_parallel_for(threads, g->lh[1], 16,
                        g->type == MR_SAMPLE_U8 ? build_level1_uint8_t : build_level1_uint16_t, &c);
    } else {
        mr_parallel_for(threads, g->lh[1], 16, build_level1, &c);
    }
    free(c.tlo);
    free(c.thi);
    for (unsigned l = 2; l <= g->levels; l++) {
        c.level = l;
        mr_parallel_for(threads, g->lh[l], 16, g->bmin ? build_upper_bytes : build_upper, &c);
    }
}

/* Mip level `level` of img, box-filtered, in picture order. */
static float *downsample(const mr_image *img, unsigned level, uint32_t *w, uint32_t *h)
{
    uint32_t s = 1u << level;
    uint32_t nw = (img->width + s - 1) / s, nh = (img->height + s - 1) / s;
    float *o = malloc((size_t)nw * nh * sizeof(float));
    if (!o)
        return NULL;
    for (uint32_t y = 0; y < nh; y++)
        for (uint32_t x = 0; x < nw; x++) {
            double sum = 0;
            uint32_t n = 0;
            for (uint32_t yy = y * s; yy < (y + 1) * s && yy < img->height; yy++)
                for (uint32_t xx = x * s; xx < (x + 1) * s && xx < img->width; xx++, n++)
                    sum += mr_image_sample(img, xx, yy);
            o[(size_t)y * nw + x] = (float)(sum / n);
        }
    *w = nw;
    *h = nh;
    return o;
}

int mr_dgrid_init(mr_dgrid *g, const mr_image *img, unsigned level, double scale, double offset,
                  unsigned threads, mr_error *err)
{
    memset(g, 0, sizeof *g);
    g->unit = mr_image_unit(img);
    g->scale = scale;
    g->offset = offset;
    if (level > 0) {
        if (level > 30)
            level = 30;
        if (!(g->owned = downsample(img, level, &g->w, &g->h)))
            return mr_error_set(err, MR_ERR_NOMEM, "out of memory for mip level %u", level);
        g->samples = g->owned;
        g->type = MR_SAMPLE_F32;
    } else {
        g->w = img->width;
        g->h = img->height;
        g->samples = img->samples;
        g->type = img->type;
    }
    /* pyramid shape: halve (rounding up) until one node; level 0 is the cells */
    uint32_t w = g->w, h = g->h;
    g->lw[0] = w;
    g->lh[0] = h;
    size_t total = 0;
    unsigned l = 0;
    while (w > 1 || h > 1) {
        l++;
        w = (w + 1) / 2;
        h = (h + 1) / 2;
        g->lw[l] = w;
        g->lh[l] = h;
        g->first[l] = total;
        total += (size_t)w * h;
    }
    g->levels = l;
    /* 8-bit samples quantise over the type's range (mr_dgrid_rebuild): when
     * that is linear8, the pyramid keeps their own extremes in bytes */
    g->gmin = 0;
    g->gmax = g->unit;
    g->qstep = g->unit > 0 ? g->unit / 65535.0 : 0.0;
    bool bytes = l > 0 && linear8(g);
    if (total && bytes) {
        g->bmin = malloc(total);
        g->bmax = malloc(total);
        if (!g->bmin || !g->bmax) {
            mr_dgrid_free(g);
            return mr_error_set(err, MR_ERR_NOMEM, "out of memory for a %ux%u min/max pyramid",
                                img->width, img->height);
        }
    } else if (total) {
        g->qmin = malloc(total * sizeof(uint16_t));
        g->qmax = malloc(total * sizeof(uint16_t));
        if (!g->qmin || !g->qmax) {
            mr_dgrid_free(g);
            return mr_error_set(err, MR_ERR_NOMEM, "out of memory for a %ux%u min/max pyramid",
                                img->width, img->height);
        }
    }
    mr_dgrid_rebuild(g, threads);
    if (g->type == MR_SAMPLE_U8) {
        for (unsigned v = 0; v < 256; v++) {
            g->h8[v] = mr_dgrid_height_of(g, v);
            if (g->bmin) {
                g->lo8[v] = mr_dgrid_height_of(g, dq(g, linear8_lo((uint8_t)v)));
                g->hi8[v] = mr_dgrid_height_of(g, dq(g, linear8_hi((uint8_t)v)));
            }
        }
        g->lut8 = true;
    }
    return MR_OK;
}

static double height_at(const void *g, int64_t i, int64_t j) { return mr_dgrid_height(g, i, j); }

mr_dheights mr_dgrid_heights(const mr_dgrid *g) { return (mr_dheights){height_at, g}; }

/* ---- distance between two grids (levels of detail) ---- */

/* Worst height difference, per worker, between the samples of grid a and
 * the height field of grid b at the same texture coordinates. */
typedef struct stray_ctx {
    const mr_dgrid *a, *b;
    double worst[MR_MAX_THREADS];
} stray_ctx;

static void stray_rows(void *ctx, size_t begin, size_t end, unsigned worker)
{
    stray_ctx *c = ctx;
    const mr_dheights hb = mr_dgrid_heights(c->b);
    const double sx = (double)c->b->w / c->a->w, sy = (double)c->b->h / c->a->h;
    double worst = c->worst[worker];
    for (size_t j = begin; j < end; j++)
        for (uint32_t i = 0; i < c->a->w; i++) {
            double d = mr_dgrid_height(c->a, i, (int64_t)j) -
                       mr_dsurf_height_at(&hb, i * sx, (double)j * sy);
            worst = fmax(worst, fabs(d));
        }
    c->worst[worker] = worst;
}

static double stray(const mr_dgrid *a, const mr_dgrid *b, unsigned threads)
{
    stray_ctx *c = calloc(1, sizeof *c);
    if (!c)
        return INFINITY; /* unknown */
    c->a = a;
    c->b = b;
    mr_parallel_for(threads, a->h, 16, stray_rows, c);
    double worst = 0;
    for (unsigned w = 0; w < MR_MAX_THREADS; w++)
        worst = fmax(worst, c->worst[w]);
    free(c);
    return worst;
}

double mr_dgrid_distance(const mr_dgrid *a, const mr_dgrid *b, unsigned threads)
{
    return fmax(stray(a, b, threads), stray(b, a, threads));
}
