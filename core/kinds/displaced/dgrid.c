/* dgrid.c - height textures on a repeating grid and their min/max pyramid (dgrid.h). */
#include "kinds/displaced/dgrid.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "util/parallel.h"

void mr_dgrid_free(mr_dgrid *g)
{
    if (!g)
        return;
    free(g->owned);
    free(g->qmin);
    free(g->qmax);
    memset(g, 0, sizeof *g);
}

size_t mr_dgrid_memory(const mr_dgrid *g)
{
    size_t b = g->levels ? (g->first[g->levels] + 1) * 2 * sizeof(uint16_t) : 0;
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

static inline double dq(const mr_dgrid *g, uint16_t q)
{
    return q == 0 ? g->gmin : q == 65535 ? g->gmax : g->gmin + q * g->qstep;
}

void mr_dgrid_node_samples(const mr_dgrid *g, unsigned l, uint32_t I, uint32_t J, double *lo,
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
    *lo = dq(g, g->qmin[k]);
    *hi = dq(g, g->qmax[k]);
}

void mr_dgrid_node_heights(const mr_dgrid *g, unsigned l, uint32_t I, uint32_t J, double *lo,
                           double *hi)
{
    double a, b;
    mr_dgrid_node_samples(g, l, I, J, &a, &b);
    double ha = mr_dgrid_height_of(g, a), hb = mr_dgrid_height_of(g, b);
    *lo = ha < hb ? ha : hb;
    *hi = ha > hb ? ha : hb;
}

static inline int64_t fdiv(int64_t a, int64_t b)
{
    int64_t q = a / b;
    return (a % b != 0 && ((a < 0) != (b < 0))) ? q - 1 : q;
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
    for (unsigned l = l0; l <= g->levels; l++) {
        int64_t ti0 = fdiv(i0, g->w), ti1 = fdiv(i1, g->w), tj0 = fdiv(j0, g->h), tj1 = fdiv(j1, g->h);
        int64_t x0 = ti0 * g->lw[l] + ((i0 - ti0 * g->w) >> l), x1 = ti1 * g->lw[l] + ((i1 - ti1 * g->w) >> l);
        int64_t y0 = tj0 * g->lh[l] + ((j0 - tj0 * g->h) >> l), y1 = tj1 * g->lh[l] + ((j1 - tj1 * g->h) >> l);
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
 * straight from the rows (no conversion per sample) and quantised by table:
 * about 20x faster, which is what makes a new height texture cheap. */
#define LEVEL1_INT(T)                                                                        \
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
        for (size_t J = begin; J < end; J++) {                                               \
            /* the node row's sample rows j0 .. j0 + 2 (the last wrapping) */                 \
            uint32_t j0 = (uint32_t)J * 2, j1 = j0 + 2 < g->h ? j0 + 2 : g->h;               \
            const T *r0 = px + (size_t)(g->h - 1 - j0) * w;                                  \
            for (uint32_t x = 0; x < w; x++)                                                 \
                cmin[x] = cmax[x] = r0[x];                                                   \
            for (uint32_t j = j0 + 1; j <= j1; j++) {                                        \
                const T *r = px + (size_t)(g->h - 1 - (j == g->h ? 0 : j)) * w;              \
                for (uint32_t x = 0; x < w; x++) {                                           \
                    T v = r[x];                                                              \
                    cmin[x] = v < cmin[x] ? v : cmin[x];                                     \
                    cmax[x] = v > cmax[x] ? v : cmax[x];                                     \
                }                                                                            \
            }                                                                                \
            cmin[w] = cmin[0], cmax[w] = cmax[0]; /* the repeat */                           \
            size_t k = g->first[1] + J * nw;                                                 \
            for (uint32_t I = 0; I < nw; I++, k++) {                                         \
                uint32_t i0 = I * 2, i1 = i0 + 2 < w ? i0 + 2 : w;                           \
                T lo = cmin[i0], hi = cmax[i0];                                              \
                for (uint32_t i = i0 + 1; i <= i1; i++) {                                    \
                    lo = cmin[i] < lo ? cmin[i] : lo;                                        \
                    hi = cmax[i] > hi ? cmax[i] : hi;                                        \
                }                                                                            \
                g->qmin[k] = c->tlo[lo];                                                     \
                g->qmax[k] = c->thi[hi];                                                     \
            }                                                                                \
        }                                                                                    \
        free(cmin);                                                                          \
    }
LEVEL1_INT(uint8_t)
LEVEL1_INT(uint16_t)

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

/* Level l > 1 from level l - 1 (quantised values combine exactly). */
static void build_upper(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    build_ctx *c = ctx;
    const mr_dgrid *g = c->g;
    unsigned l = c->level;
    uint32_t cw = g->lw[l - 1], ch = g->lh[l - 1];
    for (size_t J = begin; J < end; J++)
        for (uint32_t I = 0; I < g->lw[l]; I++) {
            uint16_t lo = 65535, hi = 0;
            for (uint32_t b = 0; b < 2; b++)
                for (uint32_t a = 0; a < 2; a++) {
                    uint32_t ci = I * 2 + a, cj = (uint32_t)J * 2 + b;
                    if (ci >= cw || cj >= ch)
                        continue;
                    size_t k = g->first[l - 1] + (size_t)cj * cw + ci;
                    lo = g->qmin[k] < lo ? g->qmin[k] : lo;
                    hi = g->qmax[k] > hi ? g->qmax[k] : hi;
                }
            size_t k = g->first[l] + J * g->lw[l] + I;
            g->qmin[k] = lo;
            g->qmax[k] = hi;
        }
}

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
        mr_parallel_for(threads, g->lh[l], 16, build_upper, &c);
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
    if (total) {
        g->qmin = malloc(total * sizeof(uint16_t));
        g->qmax = malloc(total * sizeof(uint16_t));
        if (!g->qmin || !g->qmax) {
            mr_dgrid_free(g);
            return mr_error_set(err, MR_ERR_NOMEM, "out of memory for a %ux%u min/max pyramid",
                                img->width, img->height);
        }
    }
    mr_dgrid_rebuild(g, threads);
    return MR_OK;
}
