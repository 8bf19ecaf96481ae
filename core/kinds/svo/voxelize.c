/*
 * voxelize.c - conservative surface and parity-filled solid voxelisation of
 * an asset into an SVO (voxelize.h; paper 004, issue 5).
 *
 * Pipeline (surface):
 *  1. every vertex to bind space, then to grid units (finest cell = 1) in
 *     double, so overlap and distance tests neither overflow nor round away
 *     a touching triangle;
 *  2. triangles binned into the cells of a coarse level B (<= 4, <= 4096
 *     bins) they overlap; bins are numbered by Morton code, so concatenating
 *     bins in index order keeps the finest voxels in Morton order and no
 *     global sort of the (large) voxel/triangle pairs is needed;
 *  3. per bin (parallel, one bin per task): each triangle descends from the
 *     finest level at which its clipped bounding box spans <= 2 cells per
 *     axis, testing the 8 children of every overlapping cell, and emits
 *     (code, triangle, squared distance of the cell centre) at the finest
 *     level; the bin's pairs are radix-sorted by code and each voxel keeps
 *     the pair with the smallest (distance, triangle id). That rule is a
 *     total order, so the result does not depend on which worker ran what;
 *  4. attributes per voxel (parallel), then a serial palette dedupe in
 *     Morton order (deterministic numbering), retried with coarser weight
 *     steps while the palette overflows;
 *  5. solid mode adds interior cells (row parity, see voxelize.h);
 *  6. mr_svo_compact and mr_svo_build (svo_build.h); its leaf_keys are
 *     dropped unless the caller keeps them (voxelize.h).
 * Peak memory is about 16 bytes per voxel/triangle pair of the largest bin
 * per worker plus ~45 bytes per output voxel.
 */
#include "kinds/svo/voxelize.h"

#include <float.h>
#include <math.h>
#include <stdatomic.h>
#include <stdlib.h>
#include <string.h>

#include "util/morton.h"
#include "util/radix_sort.h"
#include "kinds/svo/svo_build.h"
#include "util/parallel.h"

/* Cells are grown by this many finest cells in every overlap test: covers
 * the rounding of the double-precision tests so a triangle that touches a
 * cell is never lost; costs only cells within 1e-4 of the triangle. */
#define VOX_MARGIN 1e-4
/* Coarsest bin level: 8^4 = 4096 bins. */
#define VOX_BIN_LEVEL 4u
/* Triangles whose clipped box has at most this many finest cells are
 * tested cell by cell instead of hierarchically. */
#define VOX_DIRECT_CELLS 64u
#define VOX_ATTR_GRAIN 4096
#define VOX_PALETTE_SLOTS (1u << 17)

/* ------------------------------------------------------------------------ */
/* Geometry primitives                                                       */

/* fmin/fmax are library calls (NaN rules); inputs here are finite. */
static inline double dmin(double a, double b) { return a < b ? a : b; }
static inline double dmax(double a, double b) { return a > b ? a : b; }

static inline bool finite3(const double v[3])
{
    return isfinite(v[0]) && isfinite(v[1]) && isfinite(v[2]);
}

/* Is the projection interval [min(p), max(p)] disjoint from [-r, r]? */
static inline bool separated(double p0, double p1, double p2, double r)
{
    double lo = dmin(p0, dmin(p1, p2)), hi = dmax(p0, dmax(p1, p2));
    return lo > r || hi < -r;
}

bool mr_tri_box_overlap(const double center[3], const double half[3], const double v0[3],
                        const double v1[3], const double v2[3])
{
    if (!center || !half || !v0 || !v1 || !v2)
        return false;
    if (!finite3(center) || !finite3(half) || !finite3(v0) || !finite3(v1) || !finite3(v2))
        return false;
    if (half[0] < 0 || half[1] < 0 || half[2] < 0)
        return false;
    double a[3], b[3], c[3];
    for (int i = 0; i < 3; i++) {
        a[i] = v0[i] - center[i];
        b[i] = v1[i] - center[i];
        c[i] = v2[i] - center[i];
    }
    /* Box face normals. */
    for (int i = 0; i < 3; i++)
        if (separated(a[i], b[i], c[i], half[i]))
            return false;
    double e[3][3];
    for (int i = 0; i < 3; i++) {
        e[0][i] = b[i] - a[i];
        e[1][i] = c[i] - b[i];
        e[2][i] = a[i] - c[i];
    }
    /* Edge x box axis: unit_k x e. A zero axis projects everything to 0
     * against radius 0 and never separates. */
    for (int k = 0; k < 3; k++) {
        const double *d = e[k];
        double ax[3][3] = {{0.0, -d[2], d[1]}, {d[2], 0.0, -d[0]}, {-d[1], d[0], 0.0}};
        for (int j = 0; j < 3; j++) {
            const double *L = ax[j];
            double r = half[0] * fabs(L[0]) + half[1] * fabs(L[1]) + half[2] * fabs(L[2]);
            double pa = L[0] * a[0] + L[1] * a[1] + L[2] * a[2];
            double pb = L[0] * b[0] + L[1] * b[1] + L[2] * b[2];
            double pc = L[0] * c[0] + L[1] * c[1] + L[2] * c[2];
            if (separated(pa, pb, pc, r))
                return false;
        }
    }
    /* Triangle normal (all three vertices projected: rounding may differ). */
    double n[3] = {e[0][1] * e[1][2] - e[0][2] * e[1][1], e[0][2] * e[1][0] - e[0][0] * e[1][2],
                   e[0][0] * e[1][1] - e[0][1] * e[1][0]};
    double r = half[0] * fabs(n[0]) + half[1] * fabs(n[1]) + half[2] * fabs(n[2]);
    double pa = n[0] * a[0] + n[1] * a[1] + n[2] * a[2];
    double pb = n[0] * b[0] + n[1] * b[1] + n[2] * b[2];
    double pc = n[0] * c[0] + n[1] * c[1] + n[2] * c[2];
    return !separated(pa, pb, pc, r);
}

/* Closest point of segment a-b to p as parameter t in [0, 1]. */
static double seg_closest(const double p[3], const double a[3], const double b[3], double *d2)
{
    double ab[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]};
    double ap[3] = {p[0] - a[0], p[1] - a[1], p[2] - a[2]};
    double l2 = mr_dot3d(ab, ab);
    double t = l2 > 0 ? mr_dot3d(ap, ab) / l2 : 0.0;
    if (!(t > 0))
        t = 0;
    if (t > 1)
        t = 1;
    double q[3] = {ap[0] - t * ab[0], ap[1] - t * ab[1], ap[2] - t * ab[2]};
    *d2 = mr_dot3d(q, q);
    return t;
}

static double degenerate_closest(const double p[3], const double a[3], const double b[3],
                                 const double c[3], double w[3])
{
    double d_ab, d_bc, d_ca;
    double t_ab = seg_closest(p, a, b, &d_ab);
    double t_bc = seg_closest(p, b, c, &d_bc);
    double t_ca = seg_closest(p, c, a, &d_ca);
    if (d_ab <= d_bc && d_ab <= d_ca) {
        w[0] = 1 - t_ab, w[1] = t_ab, w[2] = 0;
        return d_ab;
    }
    if (d_bc <= d_ca) {
        w[0] = 0, w[1] = 1 - t_bc, w[2] = t_bc;
        return d_bc;
    }
    w[0] = t_ca, w[1] = 0, w[2] = 1 - t_ca;
    return d_ca;
}

double mr_tri_closest_point(const double p[3], const double a[3], const double b[3],
                            const double c[3], double w[3])
{
    double ab[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]};
    double ac[3] = {c[0] - a[0], c[1] - a[1], c[2] - a[2]};
    double ap[3] = {p[0] - a[0], p[1] - a[1], p[2] - a[2]};
    double cr[3] = {ab[1] * ac[2] - ab[2] * ac[1], ab[2] * ac[0] - ab[0] * ac[2],
                    ab[0] * ac[1] - ab[1] * ac[0]};
    double area2 = mr_dot3d(cr, cr);
    /* Slivers: the region logic below divides by quantities that vanish. */
    if (!(area2 > 1e-24 * mr_dot3d(ab, ab) * mr_dot3d(ac, ac)))
        return degenerate_closest(p, a, b, c, w);
    /* Voronoi regions of the vertices, edges and face (Ericson 5.1.5). */
    double d1 = mr_dot3d(ab, ap), d2 = mr_dot3d(ac, ap);
    if (d1 <= 0 && d2 <= 0) {
        w[0] = 1, w[1] = 0, w[2] = 0;
    } else {
        double bp[3] = {p[0] - b[0], p[1] - b[1], p[2] - b[2]};
        double d3 = mr_dot3d(ab, bp), d4 = mr_dot3d(ac, bp);
        double cp[3] = {p[0] - c[0], p[1] - c[1], p[2] - c[2]};
        double d5 = mr_dot3d(ab, cp), d6 = mr_dot3d(ac, cp);
        double vc = d1 * d4 - d3 * d2, vb = d5 * d2 - d1 * d6, va = d3 * d6 - d5 * d4;
        if (d3 >= 0 && d4 <= d3) {
            w[0] = 0, w[1] = 1, w[2] = 0;
        } else if (vc <= 0 && d1 >= 0 && d3 <= 0) {
            double t = d1 / (d1 - d3);
            w[0] = 1 - t, w[1] = t, w[2] = 0;
        } else if (d6 >= 0 && d5 <= d6) {
            w[0] = 0, w[1] = 0, w[2] = 1;
        } else if (vb <= 0 && d2 >= 0 && d6 <= 0) {
            double t = d2 / (d2 - d6);
            w[0] = 1 - t, w[1] = 0, w[2] = t;
        } else if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) {
            double t = (d4 - d3) / ((d4 - d3) + (d5 - d6));
            w[0] = 0, w[1] = 1 - t, w[2] = t;
        } else {
            double s = va + vb + vc;
            if (!(s > 0) || !isfinite(s))
                return degenerate_closest(p, a, b, c, w);
            w[1] = vb / s, w[2] = vc / s, w[0] = 1 - w[1] - w[2];
        }
    }
    for (int i = 0; i < 3; i++)
        if (!(w[i] >= 0) || !isfinite(w[i]))
            return degenerate_closest(p, a, b, c, w);
    double q[3];
    for (int i = 0; i < 3; i++)
        q[i] = p[i] - (w[0] * a[i] + w[1] * b[i] + w[2] * c[i]);
    return mr_dot3d(q, q);
}

void mr_svo_quantize_weights(const float *w, unsigned n, unsigned step, uint8_t *out)
{
    if (!out)
        return;
    if (n > MR_SVO_INFLUENCES)
        n = MR_SVO_INFLUENCES;
    memset(out, 0, n);
    if (!w || n == 0)
        return;
    if (step == 0 || 255u % step != 0)
        step = 1;
    unsigned units = 255u / step;
    double sum = 0;
    for (unsigned i = 0; i < n; i++) {
        if (!isfinite(w[i]))
            return;
        if (w[i] > 0)
            sum += w[i];
    }
    if (!(sum > 0))
        return;
    unsigned q[MR_SVO_INFLUENCES], total = 0;
    double rem[MR_SVO_INFLUENCES];
    for (unsigned i = 0; i < n; i++) {
        double x = w[i] > 0 ? (double)w[i] / sum * units : 0.0;
        double f = floor(x);
        if (f > units)
            f = units;
        q[i] = (unsigned)f;
        rem[i] = x - f;
        total += q[i];
    }
    while (total < units) {
        unsigned best = 0;
        for (unsigned i = 1; i < n; i++)
            if (rem[i] > rem[best])
                best = i;
        q[best]++;
        rem[best] = -1.0;
        total++;
    }
    /* Rounding of x can only overshoot when sum was tiny; take it back from
     * the largest. */
    while (total > units) {
        unsigned best = 0;
        for (unsigned i = 1; i < n; i++)
            if (q[i] > q[best])
                best = i;
        q[best]--;
        total--;
    }
    for (unsigned i = 0; i < n; i++)
        out[i] = (uint8_t)(q[i] * step);
}

/* ------------------------------------------------------------------------ */
/* Bind space and cube                                                       */

typedef struct vmesh {
    double *g;          /* 3 per vertex: bind space, then grid units */
    float *n;           /* 3 per vertex: bind-space unit normals */
    uint32_t first_tri; /* global id of the mesh's first triangle */
} vmesh;

typedef struct bin_out {
    size_t count;
    uint64_t *codes;
    uint32_t *tris;
} bin_out;

typedef struct scratch {
    size_t cap;
    size_t count;
    uint64_t *codes;
    uint32_t *tris;
    float *dist;
    mr_svo_key *keys, *keys_tmp;
    uint32_t *perm, *perm_tmp;
} scratch;

typedef struct vctx {
    const mr_asset *asset;
    unsigned depth;
    uint32_t n;          /* 2^depth */
    vmesh *meshes;
    uint8_t *tri_mesh;   /* mesh of each global triangle */
    size_t tri_count;
    /* bins */
    unsigned bin_level;
    size_t *bin_start;   /* bin_count + 1 */
    uint32_t *bin_tris;
    uint32_t *bins;      /* non-empty bin indices */
    size_t used_bins;
    bin_out *outs;
    scratch *scr;        /* one per worker */
    atomic_int status;
    atomic_size_t pairs;
    /* attributes */
    const uint64_t *codes;
    const uint32_t *vtris;
    mr_svo_leaf *leaves;
    mr_svo_attr *attrs;
    uint8_t albedo[MR_SVO_VOXELIZE_MAX_MESHES][3];
    unsigned step;
} vctx;

static void rest_globals(const mr_asset *a, mr_mat4 *g)
{
    for (size_t i = 0; i < a->node_count; i++) {
        int p = a->nodes[i].parent;
        if (p < 0 || (size_t)p >= i)
            g[i] = a->nodes[i].local;
        else
            g[i] = mr_mat4_mul(&g[p], &a->nodes[i].local);
    }
}

static void mesh_tri(const vctx *c, uint32_t t, const mr_mesh **m, const vmesh **vm,
                     uint32_t idx[3])
{
    unsigned mi = c->tri_mesh[t];
    *m = &c->asset->meshes[mi];
    *vm = &c->meshes[mi];
    const uint32_t *ind = &(*m)->indices[(size_t)(t - (*vm)->first_tri) * 3];
    idx[0] = ind[0], idx[1] = ind[1], idx[2] = ind[2];
}

static void free_meshes(vmesh *ms, size_t count)
{
    if (!ms)
        return;
    for (size_t i = 0; i < count; i++) {
        free(ms[i].g);
        free(ms[i].n);
    }
    free(ms);
}

/* Bind-space positions and normals of every mesh; checks finiteness. */
static int prepare_meshes(const mr_asset *a, vmesh **out, mr_error *err)
{
    int rc = MR_OK;
    mr_mat4 *glob = NULL;
    vmesh *ms = calloc(a->mesh_count ? a->mesh_count : 1, sizeof *ms);
    if (!ms)
        return mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory");
    if (a->node_count) {
        glob = malloc(a->node_count * sizeof *glob);
        if (!glob) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory");
            goto cleanup;
        }
        rest_globals(a, glob);
    }
    uint32_t first = 0;
    for (size_t mi = 0; mi < a->mesh_count; mi++) {
        const mr_mesh *m = &a->meshes[mi];
        vmesh *vm = &ms[mi];
        vm->first_tri = first;
        first += m->triangle_count;
        if (m->triangle_count && (!m->positions || !m->indices)) {
            rc = mr_error_set(err, MR_ERR_INVALID, "voxelize: mesh %zu '%s' has no vertex data",
                              mi, m->name ? m->name : "");
            goto cleanup;
        }
        size_t nv = m->vertex_count;
        vm->g = malloc((nv ? nv : 1) * 3 * sizeof *vm->g);
        vm->n = malloc((nv ? nv : 1) * 3 * sizeof *vm->n);
        if (!vm->g || !vm->n) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory");
            goto cleanup;
        }
        bool rigid = m->joint_count == 0;
        mr_mat4 M = mr_mat4_identity();
        if (rigid && glob && m->node >= 0 && (size_t)m->node < a->node_count)
            M = glob[m->node];
        if (!mr_mat4_is_finite(&M)) {
            rc = mr_error_set(err, MR_ERR_INVALID,
                              "voxelize: mesh %zu '%s': rest transform of its node is not finite",
                              mi, m->name ? m->name : "");
            goto cleanup;
        }
        mr_mat4 N = mr_mat4_normal_matrix(&M);
        for (size_t v = 0; v < nv; v++) {
            const float *p = &m->positions[v * 3];
            if (!isfinite(p[0]) || !isfinite(p[1]) || !isfinite(p[2])) {
                rc = mr_error_set(err, MR_ERR_INVALID,
                                  "voxelize: mesh %zu '%s', vertex %zu: position is not finite",
                                  mi, m->name ? m->name : "", v);
                goto cleanup;
            }
            mr_vec3 q = mr_v3(p[0], p[1], p[2]);
            if (rigid)
                q = mr_mat4_point(&M, q);
            if (!isfinite(q.x) || !isfinite(q.y) || !isfinite(q.z)) {
                rc = mr_error_set(err, MR_ERR_INVALID,
                                  "voxelize: mesh %zu '%s', vertex %zu: placed position is not finite",
                                  mi, m->name ? m->name : "", v);
                goto cleanup;
            }
            vm->g[v * 3] = q.x, vm->g[v * 3 + 1] = q.y, vm->g[v * 3 + 2] = q.z;
            mr_vec3 nn = m->normals ? mr_v3(m->normals[v * 3], m->normals[v * 3 + 1],
                                            m->normals[v * 3 + 2])
                                    : mr_v3(0, 0, 0);
            if (rigid)
                nn = mr_mat4_dir(&N, nn);
            nn = mr_v3_normalize_or(nn, mr_v3(0, 0, 0));
            vm->n[v * 3] = nn.x, vm->n[v * 3 + 1] = nn.y, vm->n[v * 3 + 2] = nn.z;
        }
        for (size_t t = 0; t < (size_t)m->triangle_count * 3; t++)
            if (m->indices[t] >= nv) {
                rc = mr_error_set(err, MR_ERR_INVALID,
                                  "voxelize: mesh %zu '%s', triangle %zu: vertex index out of range",
                                  mi, m->name ? m->name : "", t / 3);
                goto cleanup;
            }
    }
cleanup:
    free(glob);
    if (rc < 0)
        free_meshes(ms, a->mesh_count);
    else
        *out = ms;
    return rc;
}

static void cube_of(const double lo[3], const double hi[3], bool any, mr_vec3 *origin,
                    float *size)
{
    if (!any) {
        *origin = mr_v3(0, 0, 0);
        *size = 1.0f;
        return;
    }
    double ext = dmax(hi[0] - lo[0], dmax(hi[1] - lo[1], hi[2] - lo[2]));
    double mag = 0;
    for (int i = 0; i < 3; i++)
        mag = dmax(mag, dmax(fabs(lo[i]), fabs(hi[i])));
    /* Relative pad keeps points off the far face; the absolute part covers
     * flat or point-like input and float rounding of origin and size. */
    double s = ext * (1.0 + 1.0 / 512.0) + 1e-5 * mag + 1e-30;
    double o[3];
    for (int i = 0; i < 3; i++)
        o[i] = 0.5 * (lo[i] + hi[i]) - 0.5 * s;
    /* The float rounding of origin and size (<= 1.2e-7 * mag each) is far
     * inside the pads above. */
    *origin = mr_v3((float)o[0], (float)o[1], (float)o[2]);
    *size = (float)s;
}

static void mesh_bounds(const mr_asset *a, const vmesh *ms, double lo[3], double hi[3], bool *any)
{
    *any = false;
    for (int i = 0; i < 3; i++)
        lo[i] = DBL_MAX, hi[i] = -DBL_MAX;
    for (size_t mi = 0; mi < a->mesh_count; mi++) {
        const mr_mesh *m = &a->meshes[mi];
        for (size_t t = 0; t < (size_t)m->triangle_count * 3; t++) {
            const double *p = &ms[mi].g[(size_t)m->indices[t] * 3];
            for (int i = 0; i < 3; i++)
                lo[i] = dmin(lo[i], p[i]), hi[i] = dmax(hi[i], p[i]);
            *any = true;
        }
    }
}

int mr_svo_voxelize_bounds(const mr_asset *asset, mr_vec3 *origin, float *size, mr_error *err)
{
    if (!asset || !origin || !size)
        return mr_error_set(err, MR_ERR_INVALID, "voxelize: NULL argument");
    vmesh *ms = NULL;
    int rc = prepare_meshes(asset, &ms, err);
    if (rc < 0)
        return rc;
    double lo[3], hi[3];
    bool any;
    mesh_bounds(asset, ms, lo, hi, &any);
    cube_of(lo, hi, any, origin, size);
    free_meshes(ms, asset->mesh_count);
    return MR_OK;
}

/* ------------------------------------------------------------------------ */
/* Surface voxels                                                            */

static void set_status(vctx *c, int rc)
{
    int expected = MR_OK;
    atomic_compare_exchange_strong(&c->status, &expected, rc);
}

static bool scratch_grow(scratch *s, size_t need)
{
    if (need <= s->cap)
        return true;
    size_t cap = s->cap ? s->cap : 4096;
    while (cap < need)
        cap *= 2;
    uint64_t *codes = realloc(s->codes, cap * sizeof *codes);
    if (codes)
        s->codes = codes;
    uint32_t *tris = realloc(s->tris, cap * sizeof *tris);
    if (tris)
        s->tris = tris;
    float *dist = realloc(s->dist, cap * sizeof *dist);
    if (dist)
        s->dist = dist;
    if (!codes || !tris || !dist)
        return false;
    s->cap = cap;
    return true;
}

static void scratch_free(scratch *s)
{
    free(s->codes);
    free(s->tris);
    free(s->dist);
    free(s->keys);
    free(s->keys_tmp);
    free(s->perm);
    free(s->perm_tmp);
}

typedef struct tri_job {
    vctx *c;
    scratch *s;
    const double *v[3];
    uint32_t tri;
    bool failed;
} tri_job;

static void emit(tri_job *j, uint32_t x, uint32_t y, uint32_t z)
{
    scratch *s = j->s;
    if (s->count >= MR_SVO_VOXELIZE_MAX_VOXELS || !scratch_grow(s, s->count + 1)) {
        j->failed = true;
        return;
    }
    double p[3] = {x + 0.5, y + 0.5, z + 0.5}, w[3];
    double d2 = mr_tri_closest_point(p, j->v[0], j->v[1], j->v[2], w);
    s->codes[s->count] = mr_morton_encode(x, y, z);
    s->tris[s->count] = j->tri;
    s->dist[s->count] = (float)d2;
    s->count++;
}

static bool cell_overlaps(const tri_job *j, unsigned shift, uint32_t x, uint32_t y, uint32_t z)
{
    double s = (double)(1u << shift);
    double ctr[3] = {(x + 0.5) * s, (y + 0.5) * s, (z + 0.5) * s};
    double h = 0.5 * s + VOX_MARGIN;
    double half[3] = {h, h, h};
    return mr_tri_box_overlap(ctr, half, j->v[0], j->v[1], j->v[2]);
}

/* Cell (x, y, z) at `shift` levels above the finest. */
static void descend(tri_job *j, unsigned shift, uint32_t x, uint32_t y, uint32_t z)
{
    if (j->failed || !cell_overlaps(j, shift, x, y, z))
        return;
    if (shift == 0) {
        emit(j, x, y, z);
        return;
    }
    for (unsigned ch = 0; ch < 8; ch++)
        descend(j, shift - 1, 2 * x + (ch & 1), 2 * y + ((ch >> 1) & 1), 2 * z + (ch >> 2));
}

/* Clipped finest-cell range of the triangle's bounding box (grown by the
 * margin) inside [blo, bhi]; false if empty. */
static bool tri_range(const double *const v[3], const uint32_t blo[3], const uint32_t bhi[3],
                      uint32_t lo[3], uint32_t hi[3])
{
    for (int i = 0; i < 3; i++) {
        double mn = dmin(v[0][i], dmin(v[1][i], v[2][i])) - VOX_MARGIN;
        double mx = dmax(v[0][i], dmax(v[1][i], v[2][i])) + VOX_MARGIN;
        double fl = floor(mn), fh = floor(mx);
        if (fh < blo[i] || fl > bhi[i])
            return false;
        lo[i] = fl < blo[i] ? blo[i] : (uint32_t)fl;
        hi[i] = fh > bhi[i] ? bhi[i] : (uint32_t)fh;
    }
    return true;
}

static void voxelize_tri(tri_job *j, const uint32_t blo[3], const uint32_t bhi[3])
{
    uint32_t lo[3], hi[3];
    if (!tri_range(j->v, blo, bhi, lo, hi))
        return;
    uint64_t cells = (uint64_t)(hi[0] - lo[0] + 1) * (hi[1] - lo[1] + 1) * (hi[2] - lo[2] + 1);
    if (cells <= VOX_DIRECT_CELLS) {
        for (uint32_t z = lo[2]; z <= hi[2]; z++)
            for (uint32_t y = lo[1]; y <= hi[1]; y++)
                for (uint32_t x = lo[0]; x <= hi[0]; x++)
                    if (!j->failed && cell_overlaps(j, 0, x, y, z))
                        emit(j, x, y, z);
        return;
    }
    /* Finest level at which the range spans <= 2 cells per axis. */
    unsigned shift = 0;
    for (;;) {
        bool ok = true;
        for (int i = 0; i < 3; i++)
            if ((hi[i] >> shift) - (lo[i] >> shift) > 1)
                ok = false;
        if (ok)
            break;
        shift++;
    }
    for (uint32_t z = lo[2] >> shift; z <= hi[2] >> shift; z++)
        for (uint32_t y = lo[1] >> shift; y <= hi[1] >> shift; y++)
            for (uint32_t x = lo[0] >> shift; x <= hi[0] >> shift; x++)
                descend(j, shift, x, y, z);
}

static bool scratch_sort_bufs(scratch *s, size_t n)
{
    mr_svo_key *k = realloc(s->keys, (n ? n : 1) * sizeof *k);
    if (k)
        s->keys = k;
    mr_svo_key *kt = realloc(s->keys_tmp, (n ? n : 1) * sizeof *kt);
    if (kt)
        s->keys_tmp = kt;
    uint32_t *p = realloc(s->perm, (n ? n : 1) * sizeof *p);
    if (p)
        s->perm = p;
    uint32_t *pt = realloc(s->perm_tmp, (n ? n : 1) * sizeof *pt);
    if (pt)
        s->perm_tmp = pt;
    return k && kt && p && pt;
}

static void bin_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    vctx *c = ctx;
    scratch *s = &c->scr[worker];
    unsigned shift = c->depth - c->bin_level;
    for (size_t bi = begin; bi < end; bi++) {
        if (atomic_load(&c->status) != MR_OK)
            return;
        uint32_t b = c->bins[bi];
        uint32_t bx, by, bz;
        mr_morton_decode(b, &bx, &by, &bz);
        uint32_t blo[3] = {bx << shift, by << shift, bz << shift};
        uint32_t bhi[3] = {blo[0] + (1u << shift) - 1, blo[1] + (1u << shift) - 1,
                           blo[2] + (1u << shift) - 1};
        s->count = 0;
        tri_job j = {.c = c, .s = s};
        for (size_t k = c->bin_start[b]; k < c->bin_start[b + 1]; k++) {
            uint32_t t = c->bin_tris[k], idx[3];
            const mr_mesh *m;
            const vmesh *vm;
            mesh_tri(c, t, &m, &vm, idx);
            for (int q = 0; q < 3; q++)
                j.v[q] = &vm->g[(size_t)idx[q] * 3];
            j.tri = t;
            voxelize_tri(&j, blo, bhi);
            if (j.failed)
                break;
        }
        if (j.failed) {
            set_status(c, s->count >= MR_SVO_VOXELIZE_MAX_VOXELS ? MR_ERR_LIMIT : MR_ERR_NOMEM);
            return;
        }
        size_t n = s->count;
        if (n == 0)
            continue;
        if (atomic_fetch_add(&c->pairs, n) + n > 4ull * MR_SVO_VOXELIZE_MAX_VOXELS) {
            set_status(c, MR_ERR_LIMIT);
            return;
        }
        if (!scratch_sort_bufs(s, n)) {
            set_status(c, MR_ERR_NOMEM);
            return;
        }
        for (size_t i = 0; i < n; i++) {
            s->keys[i].code = s->codes[i];
            s->keys[i].level = c->depth;
            s->perm[i] = (uint32_t)i;
        }
        if (mr_svo_radix_sort_payload(s->keys, s->perm, n, s->keys_tmp, s->perm_tmp, 1, NULL) <
            0) {
            set_status(c, MR_ERR_NOMEM);
            return;
        }
        size_t uniq = 0;
        for (size_t i = 0; i < n; i++)
            if (i == 0 || s->keys[i].code != s->keys[i - 1].code)
                uniq++;
        bin_out *o = &c->outs[b];
        o->codes = malloc(uniq * sizeof *o->codes);
        o->tris = malloc(uniq * sizeof *o->tris);
        if (!o->codes || !o->tris) {
            set_status(c, MR_ERR_NOMEM);
            return;
        }
        size_t u = 0;
        for (size_t i = 0; i < n;) {
            size_t best = s->perm[i];
            size_t e = i + 1;
            for (; e < n && s->keys[e].code == s->keys[i].code; e++) {
                size_t p = s->perm[e];
                if (s->dist[p] < s->dist[best] ||
                    (s->dist[p] == s->dist[best] && s->tris[p] < s->tris[best]))
                    best = p;
            }
            o->codes[u] = s->keys[i].code;
            o->tris[u] = s->tris[best];
            u++;
            i = e;
        }
        o->count = uniq;
    }
}

/* Triangle -> bins it overlaps, counting-sorted by bin (triangle order kept). */
static int bin_triangles(vctx *c, mr_error *err)
{
    unsigned B = c->bin_level, shift = c->depth - B;
    size_t bin_count = (size_t)1 << (3 * B);
    size_t cap = c->tri_count + 16, count = 0;
    uint64_t *pairs = malloc(cap * sizeof *pairs); /* bin << 32 | tri */
    c->bin_start = calloc(bin_count + 1, sizeof *c->bin_start);
    if (!pairs || !c->bin_start)
        goto nomem;
    uint32_t nb = 1u << B;
    uint32_t blo[3] = {0, 0, 0}, bhi[3] = {c->n - 1, c->n - 1, c->n - 1};
    for (size_t t = 0; t < c->tri_count; t++) {
        uint32_t idx[3], lo[3], hi[3];
        const mr_mesh *m;
        const vmesh *vm;
        mesh_tri(c, (uint32_t)t, &m, &vm, idx);
        tri_job j = {.c = c};
        for (int q = 0; q < 3; q++)
            j.v[q] = &vm->g[(size_t)idx[q] * 3];
        if (!tri_range(j.v, blo, bhi, lo, hi))
            continue;
        for (uint32_t z = lo[2] >> shift; z <= hi[2] >> shift && z < nb; z++)
            for (uint32_t y = lo[1] >> shift; y <= hi[1] >> shift && y < nb; y++)
                for (uint32_t x = lo[0] >> shift; x <= hi[0] >> shift && x < nb; x++) {
                    if (!cell_overlaps(&j, shift, x, y, z))
                        continue;
                    if (count == cap) {
                        if (cap >= MR_SVO_VOXELIZE_MAX_VOXELS) {
                            free(pairs);
                            return mr_error_set(err, MR_ERR_LIMIT,
                                                "voxelize: too many triangle/bin pairs");
                        }
                        cap *= 2;
                        uint64_t *np = realloc(pairs, cap * sizeof *np);
                        if (!np)
                            goto nomem;
                        pairs = np;
                    }
                    uint64_t bin = mr_morton_encode(x, y, z);
                    pairs[count++] = bin << 32 | (uint64_t)t;
                    c->bin_start[bin + 1]++;
                }
    }
    for (size_t b = 0; b < bin_count; b++)
        c->bin_start[b + 1] += c->bin_start[b];
    c->bin_tris = malloc((count ? count : 1) * sizeof *c->bin_tris);
    c->bins = malloc(bin_count * sizeof *c->bins);
    size_t *fill = malloc(bin_count * sizeof *fill);
    if (!c->bin_tris || !c->bins || !fill) {
        free(fill);
        goto nomem;
    }
    memcpy(fill, c->bin_start, bin_count * sizeof *fill);
    for (size_t i = 0; i < count; i++)
        c->bin_tris[fill[pairs[i] >> 32]++] = (uint32_t)pairs[i];
    free(fill);
    free(pairs);
    c->used_bins = 0;
    for (size_t b = 0; b < bin_count; b++)
        if (c->bin_start[b + 1] > c->bin_start[b])
            c->bins[c->used_bins++] = (uint32_t)b;
    return MR_OK;
nomem:
    free(pairs);
    return mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory binning triangles");
}

/* ------------------------------------------------------------------------ */
/* Attributes                                                                */

typedef struct influence {
    uint16_t joint;
    float w;
} influence;

/* Voxel code's attributes from its triangle t, and its unit normal into
 * *normal (the caller encodes normals several at a time). */
static void voxel_attr(const vctx *c, uint64_t code, uint32_t t, mr_svo_leaf *leaf, mr_svo_attr *attr,
                       mr_vec3 *normal)
{
    uint32_t x, y, z, idx[3];
    mr_morton_decode(code, &x, &y, &z);
    const mr_mesh *m;
    const vmesh *vm;
    mesh_tri(c, t, &m, &vm, idx);
    const double *v[3];
    for (int q = 0; q < 3; q++)
        v[q] = &vm->g[(size_t)idx[q] * 3];
    double p[3] = {x + 0.5, y + 0.5, z + 0.5}, w[3];
    mr_tri_closest_point(p, v[0], v[1], v[2], w);
    mr_vec3 n = mr_v3(0, 0, 0);
    for (int q = 0; q < 3; q++) {
        const float *vn = &vm->n[(size_t)idx[q] * 3];
        n = mr_v3_add(n, mr_v3_scale(mr_v3(vn[0], vn[1], vn[2]), (float)w[q]));
    }
    if (!(mr_v3_len(n) > 1e-12f)) {
        /* Grid units are bind space scaled uniformly: same direction. */
        mr_vec3 e1 = mr_v3((float)(v[1][0] - v[0][0]), (float)(v[1][1] - v[0][1]),
                           (float)(v[1][2] - v[0][2]));
        mr_vec3 e2 = mr_v3((float)(v[2][0] - v[0][0]), (float)(v[2][1] - v[0][1]),
                           (float)(v[2][2] - v[0][2]));
        n = mr_v3_cross(e1, e2);
    }
    *normal = mr_v3_normalize_or(n, mr_v3(0, 0, 1));
    leaf->attr = 0;

    memset(attr, 0, sizeof *attr);
    unsigned mi = c->tri_mesh[t];
    memcpy(attr->albedo, c->albedo[mi], 3);
    attr->mesh = (uint8_t)mi;
    if (m->joint_count == 0 || !m->joints || !m->weights)
        return;
    influence inf[3 * MR_MAX_INFLUENCES];
    unsigned ni = 0;
    for (int q = 0; q < 3; q++) {
        if (!(w[q] > 0))
            continue;
        for (unsigned s = 0; s < MR_MAX_INFLUENCES; s++) {
            size_t k = (size_t)idx[q] * MR_MAX_INFLUENCES + s;
            float wt = m->weights[k];
            uint16_t jt = m->joints[k];
            if (!(wt > 0) || !isfinite(wt) || jt >= m->joint_count)
                continue;
            float contrib = (float)(w[q] * wt);
            unsigned f = 0;
            while (f < ni && inf[f].joint != jt)
                f++;
            if (f == ni)
                inf[ni++] = (influence){jt, 0.0f};
            inf[f].w += contrib;
        }
    }
    /* Partial selection sort: 4 largest, ties by lower joint. */
    unsigned keep = ni < MR_SVO_INFLUENCES ? ni : MR_SVO_INFLUENCES;
    for (unsigned i = 0; i < keep; i++) {
        unsigned best = i;
        for (unsigned k = i + 1; k < ni; k++)
            if (inf[k].w > inf[best].w || (inf[k].w == inf[best].w && inf[k].joint < inf[best].joint))
                best = k;
        influence tmp = inf[i];
        inf[i] = inf[best];
        inf[best] = tmp;
    }
    float ws[MR_SVO_INFLUENCES] = {0};
    for (unsigned i = 0; i < keep; i++)
        ws[i] = inf[i].w;
    uint8_t qw[MR_SVO_INFLUENCES];
    mr_svo_quantize_weights(ws, MR_SVO_INFLUENCES, c->step, qw);
    for (unsigned i = 0; i < MR_SVO_INFLUENCES; i++) {
        attr->weights[i] = qw[i];
        attr->joints[i] = qw[i] ? inf[i].joint : 0; /* canonical: shares more entries */
    }
}

static void attr_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    vctx *c = ctx;
    for (size_t i0 = begin; i0 < end; i0 += MR_SVO_NORMAL_LANES) {
        const unsigned n = end - i0 < MR_SVO_NORMAL_LANES ? (unsigned)(end - i0) : MR_SVO_NORMAL_LANES;
        float x[MR_SVO_NORMAL_LANES], y[MR_SVO_NORMAL_LANES], z[MR_SVO_NORMAL_LANES];
        for (unsigned k = 0; k < n; k++) {
            const size_t i = i0 + k;
            mr_vec3 nv;
            voxel_attr(c, c->codes[i], c->vtris[i], &c->leaves[i], &c->attrs[i], &nv);
            x[k] = nv.x;
            y[k] = nv.y;
            z[k] = nv.z;
        }
        uint8_t code[MR_SVO_NORMAL_LANES][2];
        mr_svo_normal_encode_lanes(n, x, y, z, code);
        for (unsigned k = 0; k < n; k++)
            memcpy(c->leaves[i0 + k].normal, code[k], 2);
    }
}

static uint64_t attr_hash(const mr_svo_attr *a)
{
    uint64_t w[2];
    memcpy(w, a, sizeof w);
    uint64_t h = w[0] * 0x9E3779B97F4A7C15ull ^ (w[1] + 0x632BE59BD9B4E019ull);
    h ^= h >> 29;
    h *= 0xBF58476D1CE4E5B9ull;
    h ^= h >> 32;
    return h;
}

/* Numbers distinct attrs in order of first use. Returns the palette count,
 * or 0 when it exceeds MR_SVO_MAX_PALETTE. */
static uint32_t build_palette(const mr_svo_attr *attrs, size_t count, mr_svo_leaf *leaves,
                              uint32_t *slots, mr_svo_attr *palette)
{
    _Static_assert(sizeof(mr_svo_attr) == 16, "attr hashed as 16 bytes");
    memset(slots, 0, VOX_PALETTE_SLOTS * sizeof *slots);
    uint32_t pc = 0;
    for (size_t i = 0; i < count; i++) {
        uint64_t h = attr_hash(&attrs[i]) & (VOX_PALETTE_SLOTS - 1);
        for (;;) {
            uint32_t s = slots[h];
            if (s == 0) {
                if (pc == MR_SVO_MAX_PALETTE)
                    return 0;
                palette[pc] = attrs[i];
                slots[h] = ++pc;
                leaves[i].attr = (uint16_t)(pc - 1);
                break;
            }
            if (memcmp(&palette[s - 1], &attrs[i], sizeof *attrs) == 0) {
                leaves[i].attr = (uint16_t)(s - 1);
                break;
            }
            h = (h + 1) & (VOX_PALETTE_SLOTS - 1);
        }
    }
    return pc;
}

/* ------------------------------------------------------------------------ */
/* Solid interior                                                            */

typedef struct crossing {
    uint32_t row;
    float x;
} crossing;

static int crossing_cmp(const void *a, const void *b)
{
    const crossing *p = a, *q = b;
    if (p->row != q->row)
        return p->row < q->row ? -1 : 1;
    return (p->x > q->x) - (p->x < q->x);
}

/* Sign of the yz edge function of (a -> b) at p, evaluated in a canonical
 * endpoint order so that the two triangles sharing an edge get exactly
 * opposite values; zero is resolved by perturbing p by (eps, eps^2), one
 * perturbation for every triangle, so shared edges and vertices are crossed
 * exactly once. */
static int edge_sign(const double *a, const double *b, double py, double pz, double *val)
{
    bool swap = a[1] > b[1] || (a[1] == b[1] && a[2] > b[2]);
    if (swap) {
        const double *t = a;
        a = b;
        b = t;
    }
    double dy = b[1] - a[1], dz = b[2] - a[2];
    double e = dy * (pz - a[2]) - dz * (py - a[1]);
    int s = e > 0 ? 1 : e < 0 ? -1 : 0;
    if (s == 0)
        s = dz != 0 ? (dz > 0 ? -1 : 1) : (dy > 0 ? 1 : dy < 0 ? -1 : 0);
    *val = swap ? -e : e;
    return swap ? -s : s;
}

static int row_crossings(const vctx *c, crossing **out, size_t *out_count, mr_error *err)
{
    size_t cap = 1024, count = 0;
    crossing *cr = malloc(cap * sizeof *cr);
    if (!cr)
        return mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory");
    uint32_t n = c->n;
    for (size_t t = 0; t < c->tri_count; t++) {
        uint32_t idx[3];
        const mr_mesh *m;
        const vmesh *vm;
        mesh_tri(c, (uint32_t)t, &m, &vm, idx);
        const double *v[3];
        for (int q = 0; q < 3; q++)
            v[q] = &vm->g[(size_t)idx[q] * 3];
        double ymin = dmin(v[0][1], dmin(v[1][1], v[2][1])), ymax = dmax(v[0][1], dmax(v[1][1], v[2][1]));
        double zmin = dmin(v[0][2], dmin(v[1][2], v[2][2])), zmax = dmax(v[0][2], dmax(v[1][2], v[2][2]));
        double y0 = dmax(0, ceil(ymin - 0.5) - 1), y1 = dmin(n - 1, floor(ymax - 0.5) + 1);
        double z0 = dmax(0, ceil(zmin - 0.5) - 1), z1 = dmin(n - 1, floor(zmax - 0.5) + 1);
        for (double zz = z0; zz <= z1; zz++)
            for (double yy = y0; yy <= y1; yy++) {
                double py = yy + 0.5, pz = zz + 0.5, e0, e1, e2;
                int s0 = edge_sign(v[1], v[2], py, pz, &e0);
                int s1 = edge_sign(v[2], v[0], py, pz, &e1);
                int s2 = edge_sign(v[0], v[1], py, pz, &e2);
                if (s0 == 0 || s0 != s1 || s1 != s2)
                    continue;
                double sum = e0 + e1 + e2, x;
                if (sum != 0 && isfinite(sum))
                    x = (e0 * v[0][0] + e1 * v[1][0] + e2 * v[2][0]) / sum;
                else
                    x = (v[0][0] + v[1][0] + v[2][0]) / 3.0;
                if (count == cap) {
                    if (cap >= MR_SVO_VOXELIZE_MAX_VOXELS) {
                        free(cr);
                        return mr_error_set(err, MR_ERR_LIMIT, "voxelize: too many row crossings");
                    }
                    cap *= 2;
                    crossing *nc = realloc(cr, cap * sizeof *nc);
                    if (!nc) {
                        free(cr);
                        return mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory");
                    }
                    cr = nc;
                }
                cr[count++] = (crossing){(uint32_t)zz * n + (uint32_t)yy, (float)x};
            }
    }
    qsort(cr, count, sizeof *cr, crossing_cmp);
    *out = cr;
    *out_count = count;
    return MR_OK;
}

/* Appends interior voxels (codes and leaves copied from the row's nearest
 * surface voxel) after the count surface voxels of codes/leaves, growing
 * both arrays. */
static int add_interior(const vctx *c, unsigned threads, uint64_t **codes_io,
                        mr_svo_leaf **leaves_io, size_t *count_io, mr_error *err)
{
    int rc = MR_OK;
    crossing *cr = NULL;
    size_t ncr = 0, ns = *count_io;
    mr_svo_key *rk = NULL;
    uint32_t *rp = NULL;
    uint32_t n = c->n;
    rc = row_crossings(c, &cr, &ncr, err);
    if (rc < 0)
        return rc;
    /* Surface voxels by (row, x). */
    rk = malloc((ns ? ns : 1) * sizeof *rk);
    rp = malloc((ns ? ns : 1) * sizeof *rp);
    if (!rk || !rp) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory");
        goto cleanup;
    }
    for (size_t i = 0; i < ns; i++) {
        uint32_t x, y, z;
        mr_morton_decode((*codes_io)[i], &x, &y, &z);
        rk[i].code = ((uint64_t)z * n + y) * n + x;
        rk[i].level = 0;
        rp[i] = (uint32_t)i;
    }
    rc = mr_svo_radix_sort_payload(rk, rp, ns, NULL, NULL, threads, err);
    if (rc < 0)
        goto cleanup;
    size_t cap = ns, total = ns;
    size_t si = 0;
    for (size_t a = 0; a < ncr;) {
        uint32_t row = cr[a].row;
        size_t b = a;
        while (b < ncr && cr[b].row == row)
            b++;
        /* Surface voxels of this row: [s0, s1). */
        while (si < ns && rk[si].code / n < row)
            si++;
        size_t s0 = si, s1 = si;
        while (s1 < ns && rk[s1].code / n == row)
            s1++;
        if ((b - a) % 2 == 0 && s1 > s0) {
            size_t k = s0;
            uint32_t y = row % n, z = row / n;
            for (size_t pidx = a; pidx < b; pidx += 2) {
                double xa = cr[pidx].x, xb = cr[pidx + 1].x;
                double i0 = dmax(0, ceil(xa - 0.5)), i1 = dmin(n - 1, floor(xb - 0.5));
                for (double xi = i0; xi <= i1; xi++) {
                    uint32_t xc = (uint32_t)xi;
                    while (k < s1 && rk[k].code % n < xc)
                        k++;
                    if (k < s1 && rk[k].code % n == xc)
                        continue;
                    size_t pick;
                    if (k == s0)
                        pick = k;
                    else if (k == s1)
                        pick = k - 1;
                    else
                        pick = (xc - rk[k - 1].code % n) <= (rk[k].code % n - xc) ? k - 1 : k;
                    if (total == cap) {
                        if (total >= MR_SVO_VOXELIZE_MAX_VOXELS) {
                            rc = mr_error_set(err, MR_ERR_LIMIT,
                                              "voxelize: solid voxel count above %llu",
                                              (unsigned long long)MR_SVO_VOXELIZE_MAX_VOXELS);
                            goto cleanup;
                        }
                        cap = cap ? cap * 2 : 1024;
                        uint64_t *nc = realloc(*codes_io, cap * sizeof *nc);
                        if (nc)
                            *codes_io = nc;
                        mr_svo_leaf *nl = realloc(*leaves_io, cap * sizeof *nl);
                        if (nl)
                            *leaves_io = nl;
                        if (!nc || !nl) {
                            rc = mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory");
                            goto cleanup;
                        }
                    }
                    (*codes_io)[total] = mr_morton_encode(xc, y, z);
                    (*leaves_io)[total] = (*leaves_io)[rp[pick]];
                    total++;
                }
            }
        }
        a = b;
    }
    *count_io = total;
cleanup:
    free(cr);
    free(rk);
    free(rp);
    return rc;
}

/* ------------------------------------------------------------------------ */

void mr_svo_voxelize_free(mr_svo *svo)
{
    if (!svo)
        return;
    mr_svo_free(svo);
    free(svo);
}

static const unsigned weight_steps[] = {1, 3, 5, 15, 17, 51, 85, 255};

int mr_svo_voxelize(const mr_asset *asset, const mr_svo_voxelize_params *p, mr_svo **out,
                    mr_error *err)
{
    int rc = MR_OK;
    vctx c;
    memset(&c, 0, sizeof c);
    atomic_init(&c.status, MR_OK);
    atomic_init(&c.pairs, 0);
    unsigned workers = 0;
    uint64_t *codes = NULL;
    uint32_t *vtris = NULL;
    mr_svo_leaf *leaves = NULL;
    mr_svo_attr *attrs = NULL, *palette = NULL;
    uint32_t *slots = NULL;
    mr_svo_key *keys = NULL;
    uint32_t *kept = NULL;
    mr_svo_leaf *kleaves = NULL;
    mr_svo *svo = NULL;
    size_t bin_count = 0;

    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "voxelize: out is NULL");
    *out = NULL;
    if (!asset || !p)
        return mr_error_set(err, MR_ERR_INVALID, "voxelize: NULL asset or params");
    if (p->depth < 1 || p->depth > MR_SVO_MAX_DEPTH)
        return mr_error_set(err, MR_ERR_INVALID, "voxelize: depth %u outside 1..%u", p->depth,
                            MR_SVO_MAX_DEPTH);
    if (p->mode != MR_SVO_VOXELIZE_SURFACE && p->mode != MR_SVO_VOXELIZE_SOLID)
        return mr_error_set(err, MR_ERR_INVALID, "voxelize: unknown mode %d", (int)p->mode);
    if (p->mode == MR_SVO_VOXELIZE_SOLID && p->depth > MR_SVO_SOLID_MAX_DEPTH)
        return mr_error_set(err, MR_ERR_INVALID,
                            "voxelize: solid mode supports depth up to %u (interior voxels are "
                            "stored at the finest level), got %u",
                            MR_SVO_SOLID_MAX_DEPTH, p->depth);
    if (asset->mesh_count > MR_SVO_VOXELIZE_MAX_MESHES)
        return mr_error_set(err, MR_ERR_LIMIT, "voxelize: %zu meshes, at most %u fit the palette",
                            asset->mesh_count, MR_SVO_VOXELIZE_MAX_MESHES);
    for (size_t mi = 0; mi < asset->mesh_count; mi++)
        for (int k = 0; k < 3; k++) {
            float a = p->albedo ? p->albedo[mi * 3 + k] : 0.8f;
            if (!isfinite(a))
                return mr_error_set(err, MR_ERR_INVALID, "voxelize: albedo of mesh %zu is not finite",
                                    mi);
            a = a < 0 ? 0 : a > 1 ? 1 : a;
            c.albedo[mi][k] = (uint8_t)lrintf(a * 255.0f);
        }
    if (asset->mesh_count && !asset->meshes)
        return mr_error_set(err, MR_ERR_INVALID, "voxelize: asset has no mesh array");

    c.asset = asset;
    c.depth = p->depth;
    c.n = 1u << p->depth;
    c.bin_level = p->depth < VOX_BIN_LEVEL ? p->depth : VOX_BIN_LEVEL;
    rc = prepare_meshes(asset, &c.meshes, err);
    if (rc < 0)
        return rc;
    for (size_t mi = 0; mi < asset->mesh_count; mi++) {
        if (c.tri_count + asset->meshes[mi].triangle_count > UINT32_MAX) {
            rc = mr_error_set(err, MR_ERR_LIMIT, "voxelize: too many triangles");
            goto cleanup;
        }
        c.tri_count += asset->meshes[mi].triangle_count;
    }
    double lo[3], hi[3];
    bool any;
    mesh_bounds(asset, c.meshes, lo, hi, &any);
    mr_vec3 origin;
    float size;
    cube_of(lo, hi, any, &origin, &size);
    double o[3] = {origin.x, origin.y, origin.z}, scale = (double)c.n / (double)size;
    for (size_t mi = 0; mi < asset->mesh_count; mi++)
        for (size_t v = 0; v < (size_t)asset->meshes[mi].vertex_count * 3; v++)
            c.meshes[mi].g[v] = (c.meshes[mi].g[v] - o[v % 3]) * scale;

    c.tri_mesh = malloc(c.tri_count ? c.tri_count : 1);
    if (!c.tri_mesh) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory");
        goto cleanup;
    }
    for (size_t mi = 0; mi < asset->mesh_count; mi++)
        memset(c.tri_mesh + c.meshes[mi].first_tri, (int)mi, asset->meshes[mi].triangle_count);

    rc = bin_triangles(&c, err);
    if (rc < 0)
        goto cleanup;
    bin_count = (size_t)1 << (3 * c.bin_level);
    workers = p->threads ? p->threads : mr_cpu_count();
    if (workers > MR_MAX_THREADS)
        workers = MR_MAX_THREADS;
    c.outs = calloc(bin_count, sizeof *c.outs);
    c.scr = calloc(workers, sizeof *c.scr);
    if (!c.outs || !c.scr) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory");
        goto cleanup;
    }
    mr_parallel_for(workers, c.used_bins, 1, bin_range, &c);
    for (unsigned w = 0; w < workers; w++)
        scratch_free(&c.scr[w]);
    rc = atomic_load(&c.status);
    if (rc < 0) {
        rc = rc == MR_ERR_LIMIT
                 ? mr_error_set(err, rc, "voxelize: more than %llu voxels at depth %u",
                                (unsigned long long)MR_SVO_VOXELIZE_MAX_VOXELS, c.depth)
                 : mr_error_set(err, rc, "voxelize: out of memory");
        goto cleanup;
    }

    /* Concatenate bins in Morton order. */
    size_t count = 0;
    for (size_t b = 0; b < bin_count; b++)
        count += c.outs[b].count;
    if (count > MR_SVO_VOXELIZE_MAX_VOXELS) {
        rc = mr_error_set(err, MR_ERR_LIMIT, "voxelize: %zu voxels, above %llu", count,
                          (unsigned long long)MR_SVO_VOXELIZE_MAX_VOXELS);
        goto cleanup;
    }
    codes = malloc((count ? count : 1) * sizeof *codes);
    vtris = malloc((count ? count : 1) * sizeof *vtris);
    if (!codes || !vtris) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory (%zu voxels)", count);
        goto cleanup;
    }
    size_t at = 0;
    for (size_t b = 0; b < bin_count; b++) {
        bin_out *bo = &c.outs[b];
        if (bo->count) {
            memcpy(codes + at, bo->codes, bo->count * sizeof *codes);
            memcpy(vtris + at, bo->tris, bo->count * sizeof *vtris);
            at += bo->count;
        }
        free(bo->codes);
        free(bo->tris);
        bo->codes = NULL;
        bo->tris = NULL;
    }

    /* Attributes and palette. */
    leaves = malloc((count ? count : 1) * sizeof *leaves);
    attrs = malloc((count ? count : 1) * sizeof *attrs);
    palette = malloc(MR_SVO_MAX_PALETTE * sizeof *palette);
    slots = malloc(VOX_PALETTE_SLOTS * sizeof *slots);
    if (!leaves || !attrs || !palette || !slots) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory (%zu voxels)", count);
        goto cleanup;
    }
    c.codes = codes;
    c.vtris = vtris;
    c.leaves = leaves;
    c.attrs = attrs;
    uint32_t palette_count = 0;
    for (size_t si = 0; si < sizeof weight_steps / sizeof *weight_steps; si++) {
        c.step = weight_steps[si];
        mr_parallel_for(workers, count, VOX_ATTR_GRAIN, attr_range, &c);
        palette_count = build_palette(attrs, count, leaves, slots, palette);
        if (palette_count > 0 || count == 0)
            break;
    }
    if (palette_count == 0 && count > 0) {
        rc = mr_error_set(err, MR_ERR_LIMIT,
                          "voxelize: more than %u distinct (albedo, mesh, joints) palette entries "
                          "even with one joint per voxel",
                          MR_SVO_MAX_PALETTE);
        goto cleanup;
    }
    free(attrs);
    attrs = NULL;
    free(vtris);
    vtris = NULL;
    free(slots);
    slots = NULL;

    if (p->mode == MR_SVO_VOXELIZE_SOLID) {
        rc = add_interior(&c, workers, &codes, &leaves, &count, err);
        if (rc < 0)
            goto cleanup;
    }

    keys = malloc((count ? count : 1) * sizeof *keys);
    kept = malloc((count ? count : 1) * sizeof *kept);
    if (!keys || !kept) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory (%zu voxels)", count);
        goto cleanup;
    }
    for (size_t i = 0; i < count; i++) {
        keys[i].code = codes[i];
        keys[i].level = c.depth;
        kept[i] = (uint32_t)i;
    }
    free(codes);
    codes = NULL;
    if (p->mode == MR_SVO_VOXELIZE_SOLID) {
        /* Interior voxels were appended row by row. */
        rc = mr_svo_radix_sort_payload(keys, kept, count, NULL, NULL, workers, err);
        if (rc < 0)
            goto cleanup;
    }
    size_t kcount = 0;
    uint32_t *from = malloc((count ? count : 1) * sizeof *from);
    if (!from) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory");
        goto cleanup;
    }
    rc = mr_svo_compact(keys, count, c.depth, from, &kcount, err);
    if (rc < 0) {
        free(from);
        goto cleanup;
    }
    kleaves = malloc((kcount ? kcount : 1) * sizeof *kleaves);
    if (!kleaves) {
        free(from);
        rc = mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory");
        goto cleanup;
    }
    for (size_t i = 0; i < kcount; i++)
        kleaves[i] = leaves[kept[from[i]]];
    free(from);
    free(leaves);
    leaves = NULL;
    free(kept);
    kept = NULL;

    svo = calloc(1, sizeof *svo);
    if (!svo) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "voxelize: out of memory");
        goto cleanup;
    }
    rc = mr_svo_build(keys, kleaves, kcount, c.depth, origin, size, palette, palette_count,
                      workers, svo, err);
    if (rc < 0) {
        mr_error_prefix(err, "voxelize: ");
        free(svo);
        svo = NULL;
        goto cleanup;
    }
    if (!p->keep_leaf_keys)
        mr_svo_drop_leaf_keys(svo);
    *out = svo;
    svo = NULL;

cleanup:
    if (c.outs)
        for (size_t b = 0; b < bin_count; b++) {
            free(c.outs[b].codes);
            free(c.outs[b].tris);
        }
    free(c.outs);
    free(c.scr);
    free(c.bin_start);
    free(c.bin_tris);
    free(c.bins);
    free(c.tri_mesh);
    free_meshes(c.meshes, asset->mesh_count);
    free(codes);
    free(vtris);
    free(leaves);
    free(attrs);
    free(palette);
    free(slots);
    free(keys);
    free(kept);
    free(kleaves);
    return rc;
}
