/*
 * svo_sweep.h - the resampling measurement of paper 004 (Willcocks, 3.4
 * "Measurement", Figs. 20-28) on the kind's internals, for
 * tests/hard/test_svo_sweep.c (which asserts its qualitative results).
 * bench/bench_svo.c prints the sweep through the public API instead (jobs,
 * films, stats fields). Header-only and without cmocka.
 *
 * Test shape: the thesis measures a low-resolution human. Ours is the real
 * skinned character BCN_Epileptic.X voxelised at a low depth in bind space
 * (y up, 1.81 units tall): surface voxels at depth 6 give 3,426 voxels, solid
 * voxels at depth 7 give 36,591 (the thesis' figure is 33,720).
 *
 * Deformation fields (mr_svo_deformer.field), over the shape's bounds
 * (y0 = lowest y, H = height, centre c):
 *  - shear in x by amount a: x' = x + a (y - y0). The amount is relative:
 *    the top moves sideways by a shape heights (the thesis' shapes fill a
 *    unit cube, so its x + a y is the same map). The matrix is constant.
 *  - twist about the vertical axis through c by amount a: the point at
 *    height y turns by a (y - y0) / H radians (a radians over the height).
 *    The matrix at a point is the rotation at that point's height about the
 *    axis, i.e. R(angle(y)) with the translation c - R c, which maps that
 *    point exactly (the field's local affine map, without the dangle / dy
 *    term).
 *  - uniform scale by s about c (a constant matrix).
 *
 * Coverage, the thesis' image-space metric: an orthographic view along -z
 * onto a grid of square pixels over the xy bounds of everything measured
 * (direct boxes and both octrees' leaves, so no output falls outside the
 * grid). The pixel has a fixed size, a quarter of a source voxel by default
 * (the thesis renders every amount with the same view), so every amount of
 * a sweep is measured at the same resolution: the undeformed character is
 * about 4 x 64 = 256 pixels tall at depth 6 and a shear keeps its area. A pixel is covered when its centre lies in the
 * closed xy rectangle of some box: the selection's deformed boxes for
 * "direct", the leaf boxes of the rebuilt octree (mr_svo_collect_keys, then
 * key -> cube) for resize and emit. Per method:
 *  - error   = |coverage XOR direct| / |direct| (pixels wrongly covered plus
 *              pixels lost, relative to the direct silhouette's area);
 *  - diff    = (|coverage| - |direct|) / |direct|, the thesis' "subtracted
 *              pixel coverage sums" (Figs. 21, 23, 25): lost and extra
 *              pixels cancel in it;
 *  - missing = pixels direct covers and the method does not (holes and
 *              silhouette erosion);
 *  - cells   = samples emitted before compaction (Figs. 27-28).
 */
#ifndef MR_TEST_SVO_SWEEP_H
#define MR_TEST_SVO_SWEEP_H

#include <float.h>
#include <math.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "asset/asset.h"
#include "kinds/svo/deform.h"
#include "util/morton.h"
#include "kinds/svo/svo.h"
#include "kinds/svo/voxelize.h"

#define SW_BCN_MODEL "/usr/share/assimp/models/X/BCN_Epileptic.X"

/* ---- the test shape */

/* Loads the BCN character (*asset, release with mr_asset_free) and
 * voxelises it at depth in mode (*svo, release with mr_svo_voxelize_free). */
static inline int sw_bcn_octree(unsigned depth, mr_svo_voxelize_mode mode, unsigned threads,
                                mr_asset **asset, mr_svo **svo, mr_error *err)
{
    *asset = NULL;
    *svo = NULL;
    int rc = mr_asset_load(SW_BCN_MODEL, asset, err);
    if (rc < 0)
        return rc;
    mr_svo_voxelize_params p = {.depth = depth, .mode = mode, .threads = threads};
    rc = mr_svo_voxelize(*asset, &p, svo, err);
    if (rc < 0) {
        mr_asset_free(*asset);
        *asset = NULL;
    }
    return rc;
}

/* All leaf keys of svo in Morton order (*keys: leaf_count entries, free()). */
static inline int sw_octree_keys(const mr_svo *svo, mr_svo_key **keys, mr_error *err)
{
    *keys = malloc(((size_t)svo->leaf_count + 1) * sizeof **keys);
    if (!*keys)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory for %u keys", svo->leaf_count);
    int rc = mr_svo_collect_keys(svo, *keys, NULL, err);
    if (rc < 0) {
        free(*keys);
        *keys = NULL;
    }
    return rc;
}

/* The cube of a key: lo, hi per axis, in double (exact for the dyadic
 * coordinates, then one rounding per bound). */
static inline void sw_key_box(const mr_svo *svo, mr_svo_key k, double lo[3], double hi[3])
{
    uint32_t c[3];
    mr_morton_decode(k.code, &c[0], &c[1], &c[2]);
    const double cell = (double)svo->size / (double)(1ull << svo->depth);
    const double side = cell * (double)(1ull << (svo->depth - k.level));
    const double o[3] = {svo->origin.x, svo->origin.y, svo->origin.z};
    for (int a = 0; a < 3; a++) {
        lo[a] = o[a] + (double)c[a] * cell;
        hi[a] = lo[a] + side;
    }
}

typedef struct sw_bounds {
    double lo[3], hi[3];
} sw_bounds;

static inline void sw_bounds_empty(sw_bounds *b)
{
    for (int a = 0; a < 3; a++) {
        b->lo[a] = DBL_MAX;
        b->hi[a] = -DBL_MAX;
    }
}

static inline void sw_bounds_add(sw_bounds *b, const double lo[3], const double hi[3])
{
    for (int a = 0; a < 3; a++) {
        b->lo[a] = fmin(b->lo[a], lo[a]);
        b->hi[a] = fmax(b->hi[a], hi[a]);
    }
}

/* Bounds of every leaf box of svo. */
static inline int sw_octree_bounds(const mr_svo *svo, sw_bounds *b, mr_error *err)
{
    sw_bounds_empty(b);
    mr_svo_key *keys = NULL;
    int rc = sw_octree_keys(svo, &keys, err);
    if (rc < 0)
        return rc;
    for (uint32_t i = 0; i < svo->leaf_count; i++) {
        double lo[3], hi[3];
        sw_key_box(svo, keys[i], lo, hi);
        sw_bounds_add(b, lo, hi);
    }
    free(keys);
    return MR_OK;
}

/* ---- deformation fields */

typedef enum sw_kind { SW_SHEAR = 0, SW_TWIST, SW_SCALE } sw_kind;

static inline const char *sw_kind_name(sw_kind k)
{
    return k == SW_SHEAR ? "shear" : k == SW_TWIST ? "twist" : "scale";
}

typedef struct sw_field {
    sw_kind kind;
    double amount;
    double y0, height; /* the shape's lowest y and height */
    double c[3];       /* the shape's centre */
} sw_field;

static inline sw_field sw_field_make(sw_kind kind, double amount, const sw_bounds *shape)
{
    sw_field f = {.kind = kind, .amount = amount, .y0 = shape->lo[1],
                  .height = shape->hi[1] - shape->lo[1]};
    for (int a = 0; a < 3; a++)
        f.c[a] = 0.5 * (shape->lo[a] + shape->hi[a]);
    if (!(f.height > 0))
        f.height = 1;
    return f;
}

/* The matrix of the field at bind-space point p, computed in double. */
static inline void sw_field_matrix_d(const sw_field *f, const double p[3], double m[12])
{
    memset(m, 0, 12 * sizeof *m);
    m[0] = m[5] = m[10] = 1;
    switch (f->kind) {
    case SW_SHEAR:
        m[1] = f->amount;
        m[3] = -f->amount * f->y0;
        break;
    case SW_TWIST: {
        const double ang = f->amount * (p[1] - f->y0) / f->height;
        const double cs = cos(ang), sn = sin(ang);
        /* rotation about y: x' = c dx + s dz, z' = -s dx + c dz */
        m[0] = cs;
        m[2] = sn;
        m[8] = -sn;
        m[10] = cs;
        m[3] = f->c[0] - (cs * f->c[0] + sn * f->c[2]);
        m[11] = f->c[2] - (-sn * f->c[0] + cs * f->c[2]);
        break;
    }
    case SW_SCALE:
        for (int a = 0; a < 3; a++) {
            m[5 * a] = f->amount;
            m[4 * a + 3] = f->c[a] * (1 - f->amount);
        }
        break;
    }
}

/* mr_svo_deformer.field callback; ctx is a const sw_field *. */
static inline mr_affine sw_field_matrix(void *ctx, mr_vec3 p)
{
    const double pd[3] = {p.x, p.y, p.z};
    double m[12];
    sw_field_matrix_d(ctx, pd, m);
    mr_affine r;
    for (int i = 0; i < 12; i++)
        r.m[i] = (float)m[i];
    return r;
}

/* Where the field moves p (the map the matrices are local versions of). */
static inline void sw_field_apply(const sw_field *f, const double p[3], double out[3])
{
    double m[12];
    sw_field_matrix_d(f, p, m);
    for (int r = 0; r < 3; r++)
        out[r] = m[4 * r] * p[0] + m[4 * r + 1] * p[1] + m[4 * r + 2] * p[2] + m[4 * r + 3];
}

/* ---- coverage */

typedef struct sw_grid {
    double x0, y0, px; /* lower corner, square pixel side */
    int w, h;
} sw_grid;

/* Square pixels of side px over [lo, hi] in x and y; px grows (by powers of
 * two) while the grid would exceed max_pixels. */
static inline sw_grid sw_grid_fit(const double lo[2], const double hi[2], double px,
                                  double max_pixels)
{
    const double wx = fmax(hi[0] - lo[0], 0), wy = fmax(hi[1] - lo[1], 0);
    if (!(px > 0) || !isfinite(px))
        px = fmax(fmax(wx, wy), 1e-30);
    while ((ceil(wx / px) + 1) * (ceil(wy / px) + 1) > max_pixels)
        px *= 2;
    sw_grid g = {.x0 = lo[0], .y0 = lo[1], .px = px};
    g.w = (int)fmax(ceil(wx / px), 1);
    g.h = (int)fmax(ceil(wy / px), 1);
    return g;
}

/* Marks the pixels whose centres (x0 + (i + 1/2) px, ...) lie in the
 * closed rectangle [lox, hix] x [loy, hiy]. */
static inline void sw_cover_rect(const sw_grid *g, uint8_t *mask, double lox, double loy,
                                 double hix, double hiy)
{
    /* centre i is inside when lox <= x0 + (i + 1/2) px <= hix */
    double i0 = ceil((lox - g->x0) / g->px - 0.5), i1 = floor((hix - g->x0) / g->px - 0.5);
    double j0 = ceil((loy - g->y0) / g->px - 0.5), j1 = floor((hiy - g->y0) / g->px - 0.5);
    /* the divisions round: settle the boundary pixels against the exact test */
    while (i0 > 0 && g->x0 + (i0 - 0.5) * g->px >= lox)
        i0--;
    while (i0 <= i1 && g->x0 + (i0 + 0.5) * g->px < lox)
        i0++;
    while (i1 + 1 < g->w && g->x0 + (i1 + 1.5) * g->px <= hix)
        i1++;
    while (i1 >= i0 && g->x0 + (i1 + 0.5) * g->px > hix)
        i1--;
    while (j0 > 0 && g->y0 + (j0 - 0.5) * g->px >= loy)
        j0--;
    while (j0 <= j1 && g->y0 + (j0 + 0.5) * g->px < loy)
        j0++;
    while (j1 + 1 < g->h && g->y0 + (j1 + 1.5) * g->px <= hiy)
        j1++;
    while (j1 >= j0 && g->y0 + (j1 + 0.5) * g->px > hiy)
        j1--;
    i0 = fmax(i0, 0);
    j0 = fmax(j0, 0);
    i1 = fmin(i1, g->w - 1);
    j1 = fmin(j1, g->h - 1);
    if (!(i0 <= i1 && j0 <= j1)) /* empty, outside the grid, or NaN */
        return;
    for (int j = (int)j0; j <= (int)j1; j++)
        memset(mask + (size_t)j * (size_t)g->w + (size_t)i0, 1, (size_t)(i1 - i0) + 1);
}

static inline void sw_cover_selection(const sw_grid *g, uint8_t *mask, const mr_svo_selection *s)
{
    for (size_t i = 0; i < s->count; i++) {
        const float *b = s->box + 6 * i;
        sw_cover_rect(g, mask, b[0], b[1], b[3], b[4]);
    }
}

static inline void sw_cover_keys(const sw_grid *g, uint8_t *mask, const mr_svo *svo,
                                 const mr_svo_key *keys)
{
    for (uint32_t i = 0; i < svo->leaf_count; i++) {
        double lo[3], hi[3];
        sw_key_box(svo, keys[i], lo, hi);
        sw_cover_rect(g, mask, lo[0], lo[1], hi[0], hi[1]);
    }
}

/* ---- one measurement: select + deform with a field, resample both ways,
 * compare coverage */

enum { SW_RESIZE = 0, SW_EMIT = 1, SW_METHODS = 2 };

typedef struct sw_result {
    size_t voxels;              /* selected and deformed (direct boxes) */
    uint64_t cells[SW_METHODS]; /* emitted before compaction */
    uint32_t leaves[SW_METHODS];/* voxels of the rebuilt octree */
    uint64_t direct_px;
    uint64_t px[SW_METHODS], missing[SW_METHODS], extra[SW_METHODS];
    double error[SW_METHODS];   /* (missing + extra) / direct_px */
    double diff[SW_METHODS];    /* (px - direct_px) / direct_px */
    sw_grid grid;
} sw_result;

typedef struct sw_params {
    unsigned out_depth;      /* rebuilt octree's depth; 0: the source depth + 10 (max 21) */
    double pixels_per_voxel; /* pixel side = source voxel side / this; 0: 4 */
    double max_pixels;       /* cap on the grid (pixels grow beyond it); 0: 2^24 */
    unsigned threads;        /* 0: all cores */
} sw_params;

/* Selects every leaf of svo (no view), deforms it with field f, resamples
 * with resize and emit and measures coverage against the direct boxes. */
static inline int sw_measure(const mr_svo *svo, const mr_svo_extremes *ex, const sw_field *f,
                             const sw_params *p, sw_result *r, mr_error *err)
{
    memset(r, 0, sizeof *r);
    mr_svo_selection sel = {0};
    mr_svo out[SW_METHODS] = {{0}};
    mr_svo_key *keys[SW_METHODS] = {NULL};
    uint8_t *mask[1 + SW_METHODS] = {NULL};
    const mr_svo_method method[SW_METHODS] = {MR_SVO_RESIZE, MR_SVO_EMIT};
    unsigned depth = p->out_depth ? p->out_depth : svo->depth + 10;
    depth = depth > MR_SVO_MAX_DEPTH ? MR_SVO_MAX_DEPTH : depth;
    const mr_svo_deformer d = {.field = sw_field_matrix, .field_ctx = (void *)f};
    int rc = mr_svo_select(svo, ex, &d, NULL, svo->depth, p->threads, &sel, err);
    if (rc < 0)
        goto cleanup;
    r->voxels = sel.count;
    sw_bounds b;
    sw_bounds_empty(&b);
    for (size_t i = 0; i < sel.count; i++) {
        const double lo[3] = {sel.box[6 * i], sel.box[6 * i + 1], sel.box[6 * i + 2]};
        const double hi[3] = {sel.box[6 * i + 3], sel.box[6 * i + 4], sel.box[6 * i + 5]};
        sw_bounds_add(&b, lo, hi);
    }
    for (int m = 0; m < SW_METHODS; m++) {
        rc = mr_svo_resample(&sel, method[m], depth, svo->palette, svo->palette_count,
                             p->threads, &out[m], &r->cells[m], err);
        if (rc < 0)
            goto cleanup;
        r->leaves[m] = out[m].leaf_count;
        rc = sw_octree_keys(&out[m], &keys[m], err);
        if (rc < 0)
            goto cleanup;
        for (uint32_t i = 0; i < out[m].leaf_count; i++) {
            double lo[3], hi[3];
            sw_key_box(&out[m], keys[m][i], lo, hi);
            sw_bounds_add(&b, lo, hi);
        }
    }
    const double voxel = (double)svo->size / (double)(1ull << svo->depth);
    r->grid = sw_grid_fit(b.lo, b.hi, voxel / (p->pixels_per_voxel > 0 ? p->pixels_per_voxel : 4),
                          p->max_pixels > 0 ? p->max_pixels : (double)(1 << 24));
    const size_t n = (size_t)r->grid.w * (size_t)r->grid.h;
    for (int k = 0; k <= SW_METHODS; k++) {
        mask[k] = calloc(n, 1);
        if (!mask[k]) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory for a %zu pixel mask", n);
            goto cleanup;
        }
    }
    sw_cover_selection(&r->grid, mask[0], &sel);
    for (int m = 0; m < SW_METHODS; m++)
        sw_cover_keys(&r->grid, mask[1 + m], &out[m], keys[m]);
    for (size_t i = 0; i < n; i++) {
        r->direct_px += mask[0][i];
        for (int m = 0; m < SW_METHODS; m++) {
            r->px[m] += mask[1 + m][i];
            r->missing[m] += mask[0][i] && !mask[1 + m][i];
            r->extra[m] += !mask[0][i] && mask[1 + m][i];
        }
    }
    for (int m = 0; m < SW_METHODS; m++) {
        const double dpx = r->direct_px ? (double)r->direct_px : 1.0;
        r->error[m] = (double)(r->missing[m] + r->extra[m]) / dpx;
        r->diff[m] = ((double)r->px[m] - (double)r->direct_px) / dpx;
    }
cleanup:
    for (int k = 0; k <= SW_METHODS; k++)
        free(mask[k]);
    for (int m = 0; m < SW_METHODS; m++) {
        free(keys[m]);
        mr_svo_free(&out[m]);
    }
    mr_svo_selection_free(&sel);
    return rc;
}

#endif /* MR_TEST_SVO_SWEEP_H */
