/*
 * dgrid.h - a height texture as the displaced kind samples it: heights on
 * the integer points of an infinite, repeating grid, and the min/max
 * pyramid (the thesis' minmax mipmap, 4.2.2) the traversal bounds them
 * with.
 *
 * Grid space: a texture of W x H samples (a mip level of the image) puts
 * sample (i, j) at texture coordinates (i / W, j / H), repeating with
 * period W and H: grid point (i, j) has height
 *     H(i, j) = offset + scale * s(i mod W, j mod H) / unit
 * where s is the sample (row 0 of the picture at the top: grid row j is
 * picture row H - 1 - j, so v grows upwards as in OpenGL and assimp) and
 * unit 255, 65535 or 1 for 8-bit, 16-bit and float samples. Cell (i, j) is
 * the square [i, i+1] x [j, j+1]; its heights lie between the smallest and
 * largest of its four corners, whatever the cell's surface (two triangles
 * or a bilinear patch) does in between.
 *
 * The pyramid: level 1 has ceil(W/2) x ceil(H/2) nodes, node (I, J)
 * covering the cells [2I, 2I+2) x [2J, 2J+2) that exist in one period (the
 * last column of nodes covers one cell when W is odd), and so on up to a
 * single node covering the period; level 0 (one cell) is read from its four
 * samples directly, which saves three quarters of the pyramid. Any W and H
 * (not only powers of two). Node values are the min and max sample of the
 * nodes' cells' corners, quantised to 16 bits over [gmin, gmax] (a float
 * texture's range; an integer texture's type range, so no scan is needed)
 * with the minimum rounded down and the maximum up by one more step, so a
 * dequantised bound always contains the true one: 4 bytes per node, 1.33
 * bytes per texel. The top node bounds the whole texture.
 */
#ifndef MR_DGRID_H
#define MR_DGRID_H

#include <stdbool.h>
#include <stdint.h>

#include "asset/image.h"
#include "kinds/displaced/dsurf.h"

#define MR_DGRID_MAX_LEVELS 32

typedef struct mr_dgrid {
    uint32_t w, h;             /* samples per period */
    mr_sample_type type;
    const void *samples;       /* w * h in picture order (row 0 at the top) */
    void *owned;               /* samples when a mip level was made (float), else NULL */
    double unit, scale, offset;
    double gmin, gmax;         /* the quantisation's range: the smallest and largest
                                  sample (float), the type's range (8 and 16 bit) */
    double qstep;              /* (gmax - gmin) / 65535: one quantisation step, 0 when flat */
    unsigned levels;           /* top pyramid level (a single node); 0 for a 1x1 texture */
    uint32_t lw[MR_DGRID_MAX_LEVELS + 1], lh[MR_DGRID_MAX_LEVELS + 1];
    size_t first[MR_DGRID_MAX_LEVELS + 1]; /* index of level l's node (0, 0) */
    uint16_t *qmin, *qmax;     /* node values, levels 1..levels, quantised to 16 bits */
    uint8_t *bmin, *bmax;      /* instead, for 8-bit samples quantised over 0..255 (where the
                                  16-bit bounds are 257 v -+ 1): the samples' own extremes,
                                  half the memory; read through mr_dgrid_node_samples */
    /* 8-bit samples: the heights of every byte value, as mr_dgrid_height_of
     * gives them (so equal bit for bit), looked up instead of computed by
     * the traversal: a sample's (h8), and a byte pyramid node's lower and
     * upper bound (lo8 of bmin, hi8 of bmax) */
    bool lut8;
    double h8[256], lo8[256], hi8[256];
} mr_dgrid;

/* The grid of image img's mip level `level` (box filter of 2^level x
 * 2^level texels, partial blocks at the edges averaged over the texels they
 * have; level 0 borrows img's samples, which must then outlive the grid),
 * with heights offset + scale * sample / unit, and its pyramid, built on
 * `threads` threads. MR_ERR_NOMEM. */
int mr_dgrid_init(mr_dgrid *g, const mr_image *img, unsigned level, double scale, double offset,
                  unsigned threads, mr_error *err);
/* Rebuilds the pyramid (after the samples changed in place). */
void mr_dgrid_rebuild(mr_dgrid *g, unsigned threads);
void mr_dgrid_free(mr_dgrid *g);
size_t mr_dgrid_memory(const mr_dgrid *g); /* bytes owned: pyramid and made levels */

static inline int64_t mr_dgrid_wrap(int64_t i, uint32_t n)
{
    if ((uint64_t)i < n) /* within the first period: no division */
        return i;
    int64_t r = i % (int64_t)n;
    return r < 0 ? r + n : r;
}

/* Sample (i, j) of one period (0 <= i < w, 0 <= j < h), grid orientation. */
static inline double mr_dgrid_sample(const mr_dgrid *g, uint32_t i, uint32_t j)
{
    size_t k = (size_t)(g->h - 1 - j) * g->w + i;
    switch (g->type) {
    case MR_SAMPLE_U8: return ((const uint8_t *)g->samples)[k];
    case MR_SAMPLE_U16: return ((const uint16_t *)g->samples)[k];
    default: return ((const float *)g->samples)[k];
    }
}

/* Height of a sample value: the one formula every height goes through
 * (monotone in s, so bounds of samples map to bounds of heights). */
static inline double mr_dgrid_height_of(const mr_dgrid *g, double s)
{
    /* (a float texture's unit is 1: no division, the same value) */
    return g->offset + g->scale * (g->unit == 1 ? s : s / g->unit);
}

/* H(i, j) of any grid point. */
static inline double mr_dgrid_height(const mr_dgrid *g, int64_t i, int64_t j)
{
    return mr_dgrid_height_of(g, mr_dgrid_sample(g, (uint32_t)mr_dgrid_wrap(i, g->w),
                                                 (uint32_t)mr_dgrid_wrap(j, g->h)));
}

/* Smallest and largest sample of node (I, J) of level l (1..levels; I <
 * lw[l], J < lh[l]), dequantised outward; level 0: cell (I, J) of the
 * period from its four corners, exactly. */
void mr_dgrid_node_samples(const mr_dgrid *g, unsigned l, uint32_t I, uint32_t J, double *lo,
                           double *hi);
/* Smallest and largest sample over the cells [i0, i1] x [j0, j1] of the
 * repeating grid (any integers, i0 <= i1, j0 <= j1): the nodes of the
 * lowest level at which the range spans at most two per axis (4.2.7's
 * root selection), so at most four look-ups; ranges wider than a period
 * get the texture's range. */
void mr_dgrid_range_samples(const mr_dgrid *g, int64_t i0, int64_t i1, int64_t j0, int64_t j1,
                            double *lo, double *hi);
/* The grid as the surface's source of heights (dsurf.h): H(i, j). */
mr_dheights mr_dgrid_heights(const mr_dgrid *g);
/* How far apart the height fields of grids a and b (say two mip levels of
 * one image, with the same scale and offset) are: the largest difference of
 * their heights, each linear over its cell halves (dsurf.h,
 * mr_dsurf_height_at), at every sample of either over one period, both
 * grids mapped to texture coordinates (sample (i, j) at (i / w, j / h)).
 * Between samples it can be exceeded where the two grids' cell edges cross
 * away from any sample: for a mip level 2^k of a texture whose sides 2^k
 * divides, every crossing is a sample of the finer one, and the figure is
 * the largest difference anywhere. INFINITY when out of memory. */
double mr_dgrid_distance(const mr_dgrid *a, const mr_dgrid *b, unsigned threads);
/* The same as heights (ordered: scale may be negative). */
void mr_dgrid_node_heights_slow(const mr_dgrid *g, unsigned l, uint32_t I, uint32_t J, double *lo,
                                double *hi);
/* mr_dgrid_node_heights of the children in mask of a node of level c + 1
 * (child k: node (I0 + (k & 1), J0 + (k >> 1)) of level c) into hl[k],
 * hh[k], the four at once where they exist and do not wrap, for 16-bit
 * and float samples: the same bits. x86-64 with AVX2 (the caller checks
 * the CPU); the traversal's float mip levels spent 3 % of a frame on the
 * heights one by one. */
#if defined(__x86_64__) && defined(__GNUC__)
void mr_dgrid_child_heights_avx2(const mr_dgrid *g, unsigned c, uint32_t I0, uint32_t J0,
                                 unsigned mask, double hl[4], double hh[4]);
#endif
static inline void mr_dgrid_node_heights(const mr_dgrid *g, unsigned l, uint32_t I, uint32_t J,
                                         double *lo, double *hi)
{
    double a, b;
    if (!g->lut8) {
        mr_dgrid_node_heights_slow(g, l, I, J, lo, hi);
        return;
    }
    if (l == 0) { /* the cell's four corners; heights are monotone in the sample */
        const uint8_t *s = g->samples;
        uint32_t i1 = I + 1 == g->w ? 0 : I + 1, j1 = J + 1 == g->h ? 0 : J + 1;
        size_t r0 = (size_t)(g->h - 1 - J) * g->w, r1 = (size_t)(g->h - 1 - j1) * g->w;
        uint8_t c0 = s[r0 + I], c1 = s[r0 + i1], c2 = s[r1 + I], c3 = s[r1 + i1];
        uint8_t m01 = c0 < c1 ? c0 : c1, m23 = c2 < c3 ? c2 : c3;
        uint8_t M01 = c0 > c1 ? c0 : c1, M23 = c2 > c3 ? c2 : c3;
        a = g->h8[m01 < m23 ? m01 : m23];
        b = g->h8[M01 > M23 ? M01 : M23];
    } else if (g->bmin) {
        size_t k = g->first[l] + (size_t)J * g->lw[l] + I;
        a = g->lo8[g->bmin[k]];
        b = g->hi8[g->bmax[k]];
    } else {
        mr_dgrid_node_heights_slow(g, l, I, J, lo, hi);
        return;
    }
    *lo = a < b ? a : b;
    *hi = a > b ? a : b;
}

#endif
