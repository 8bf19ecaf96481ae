/*
 * dmm_trace.c - tessellation-free traversal of a DMM patch (dmm_trace.h).
 *
 * Recursion depth is at most MR_UMESH_MAX_LEVEL, so the quadtree is walked
 * recursively with every node's state on the C stack (no restart, no
 * epsilon pushes). Lattice points carry their interpolated frame (point,
 * direction and, for interpolated patches, matrix) in double, computed once
 * per node from the three base corners.
 */
#include <float.h>
#include <math.h>
#include <string.h>

#include "geom/dmm_trace.h"

/* Relative widening of every box: covers the final float rounding of a
 * micro-vertex (2^-24 relative) and the double evaluation error with room. */
#define BOX_PAD 0x1p-20
/* Far-distance widening of the slab test: 1 + 2 * gamma(3) in float. */
#define SLAB_FAR_SCALE (1.0f + 2.0f * 3.0f * FLT_EPSILON)

typedef struct lattice_pt {
    uint32_t a, b;
    double p[3], n[3];
    double m[12]; /* interpolated patches only */
} lattice_pt;

typedef struct trace_ctx {
    const mr_dmm_patch *patch;
    const mr_dmm_ray *ray;
    unsigned leaf;      /* leaf sublevel */
    uint32_t segments;  /* 2^level */
    float tmin, tmax;
    bool any_hit, found;
    mr_dmm_hit *hit;
    mr_dmm_trace_stats *stats;
} trace_ctx;

unsigned mr_dmm_trace_leaf_sublevel(unsigned level) { return level ? level - 1 : 0; }

uint32_t mr_dmm_trace_pyramid_size(unsigned level)
{
    return mr_dmm_pyramid_size(mr_dmm_trace_leaf_sublevel(level));
}

mr_dmm_ray mr_dmm_ray_setup(mr_vec3 org, mr_vec3 dir)
{
    mr_dmm_ray r = {.org = org, .dir = dir};
    const float d[3] = {dir.x, dir.y, dir.z};
    for (int k = 0; k < 3; k++) {
        r.parallel[k] = d[k] == 0.0f;
        r.inv[k] = r.parallel[k] ? 0.0f : 1.0f / d[k];
    }
    r.wt = mr_wt_ray_setup(org, dir);
    return r;
}

static float disp_of(const mr_dmm_patch *p, uint32_t a, uint32_t b)
{
    return mr_dmm_value_to_float(p->enc, p->values[mr_umesh_vertex_index(p->level, a, b)]);
}

mr_vec3 mr_dmm_vertex(const mr_dmm_patch *p, uint32_t a, uint32_t b)
{
    mr_vec3 out = {0, 0, 0};
    float d = disp_of(p, a, b);
    if (p->mats[0])
        mr_umesh_eval_interpolated(&p->tri, p->mats, p->level, a, b, d, &out, NULL);
    else
        mr_umesh_eval(&p->tri, p->level, a, b, d, &out, NULL);
    return out;
}

static void lattice(const trace_ctx *c, uint32_t a, uint32_t b, lattice_pt *out)
{
    const mr_dmm_patch *p = c->patch;
    double n = c->segments, w[3] = {(n - a - b) / n, a / n, b / n};
    out->a = a;
    out->b = b;
    const mr_vec3 *v = p->tri.pos, *d = p->tri.dir;
    out->p[0] = w[0] * v[0].x + w[1] * v[1].x + w[2] * v[2].x;
    out->p[1] = w[0] * v[0].y + w[1] * v[1].y + w[2] * v[2].y;
    out->p[2] = w[0] * v[0].z + w[1] * v[1].z + w[2] * v[2].z;
    out->n[0] = w[0] * d[0].x + w[1] * d[1].x + w[2] * d[2].x;
    out->n[1] = w[0] * d[0].y + w[1] * d[1].y + w[2] * d[2].y;
    out->n[2] = w[0] * d[0].z + w[1] * d[1].z + w[2] * d[2].z;
    if (p->mats[0])
        for (int e = 0; e < 12; e++)
            out->m[e] = w[0] * p->mats[0]->m[e] + w[1] * p->mats[1]->m[e] +
                        w[2] * p->mats[2]->m[e];
}

typedef struct dbox {
    double lo[3], hi[3];
} dbox;

static void grow(dbox *b, const double x[3])
{
    for (int k = 0; k < 3; k++) {
        b->lo[k] = x[k] < b->lo[k] ? x[k] : b->lo[k];
        b->hi[k] = x[k] > b->hi[k] ? x[k] : b->hi[k];
    }
}

static void apply(const double m[12], const double x[3], double out[3])
{
    for (int r = 0; r < 3; r++)
        out[r] = m[r * 4] * x[0] + m[r * 4 + 1] * x[1] + m[r * 4 + 2] * x[2] + m[r * 4 + 3];
}

/* Box of the micro-geometry over sub-triangle (L[0], L[1], L[2]) whose
 * displacements lie in [dmin, dmax]. */
static dbox node_box(const mr_dmm_patch *p, const lattice_pt *const L[3], double dmin,
                     double dmax)
{
    dbox b = {{INFINITY, INFINITY, INFINITY}, {-INFINITY, -INFINITY, -INFINITY}};
    const double ds[2] = {dmin, dmax};
    for (int s = 0; s < 2; s++) {
        double x[3][3];
        for (int k = 0; k < 3; k++)
            for (int e = 0; e < 3; e++)
                x[k][e] = L[k]->p[e] + ds[s] * L[k]->n[e];
        if (!p->mats[0]) {
            for (int k = 0; k < 3; k++)
                grow(&b, x[k]);
            continue;
        }
        /* Control points of the quadratic patch M(w) x_d(w) over this
         * sub-triangle: the blossom at pairs of corners. */
        for (int i = 0; i < 3; i++)
            for (int j = i; j < 3; j++) {
                double c[3], q[3];
                apply(L[i]->m, x[j], c);
                if (j != i) {
                    apply(L[j]->m, x[i], q);
                    for (int e = 0; e < 3; e++)
                        c[e] = 0.5 * (c[e] + q[e]);
                }
                grow(&b, c);
            }
    }
    for (int k = 0; k < 3; k++) {
        double mag = fabs(b.lo[k]) > fabs(b.hi[k]) ? fabs(b.lo[k]) : fabs(b.hi[k]);
        double pad = mag * BOX_PAD + DBL_MIN;
        b.lo[k] -= pad;
        b.hi[k] += pad;
    }
    return b;
}

/* Entry distance of the ray into the box within [tmin, tmax], or INFINITY. */
static float slab(const mr_dmm_ray *r, const dbox *b, float tmin, float tmax)
{
    const float o[3] = {r->org.x, r->org.y, r->org.z};
    float t0 = tmin, t1 = tmax * SLAB_FAR_SCALE;
    for (int k = 0; k < 3; k++) {
        float lo = (float)b->lo[k], hi = (float)b->hi[k];
        if (r->parallel[k]) {
            if (o[k] < lo || o[k] > hi)
                return INFINITY;
            continue;
        }
        float a = (lo - o[k]) * r->inv[k], z = (hi - o[k]) * r->inv[k];
        if (a > z) {
            float s = a;
            a = z, z = s;
        }
        t0 = a > t0 ? a : t0;
        t1 = z < t1 ? z : t1;
        if (!(t0 <= t1))
            return INFINITY;
    }
    return t0;
}

static double disp_min(const trace_ctx *c, uint32_t entry)
{
    return mr_dmm_value_to_float(c->patch->enc, c->patch->minv[entry]);
}

static double disp_max(const trace_ctx *c, uint32_t entry)
{
    return mr_dmm_value_to_float(c->patch->enc, c->patch->maxv[entry]);
}

static void test_triangle(trace_ctx *c, const lattice_pt *const L[3], const mr_vec3 v[3])
{
    if (c->stats)
        c->stats->triangles++;
    mr_wt_hit h;
    if (!mr_wt_intersect(&c->ray->wt, v[0], v[1], v[2], c->tmin, c->tmax, &h))
        return;
    c->found = true;
    c->tmax = h.t;
    if (!c->hit)
        return;
    float w0 = 1.0f - h.u - h.v, n = (float)c->segments;
    c->hit->t = h.t;
    c->hit->u = (w0 * (float)L[0]->a + h.u * (float)L[1]->a + h.v * (float)L[2]->a) / n;
    c->hit->v = (w0 * (float)L[0]->b + h.u * (float)L[1]->b + h.v * (float)L[2]->b) / n;
    c->hit->ng = mr_v3_cross(mr_v3_sub(v[1], v[0]), mr_v3_sub(v[2], v[0]));
}

/* Children of sub-triangle (P0, P1, P2) with edge midpoints m01, m12, m20,
 * in pyramid order (dmm_encode.h): (P0, m01, m20), (m01, P1, m12),
 * (m20, m12, P2), (m12, m20, m01). Indices into {P0, P1, P2, m01, m12, m20}. */
static const int CHILD[4][3] = {{0, 3, 5}, {3, 1, 4}, {5, 4, 2}, {4, 5, 3}};

static void midpoints(const trace_ctx *c, const lattice_pt *const P[3], lattice_pt m[3])
{
    for (int e = 0; e < 3; e++) {
        const lattice_pt *x = P[e], *y = P[(e + 1) % 3];
        lattice(c, (x->a + y->a) / 2, (x->b + y->b) / 2, &m[e]);
    }
}

static void leaf(trace_ctx *c, const lattice_pt *const P[3])
{
    const mr_dmm_patch *p = c->patch;
    if (p->level == 0) {
        mr_vec3 v[3];
        for (int k = 0; k < 3; k++)
            v[k] = mr_dmm_vertex(p, P[k]->a, P[k]->b);
        test_triangle(c, P, v);
        return;
    }
    /* Lattice coordinates are all the micro-triangle test needs here. */
    lattice_pt mid[3];
    for (int e = 0; e < 3; e++) {
        const lattice_pt *x = P[e], *y = P[(e + 1) % 3];
        mid[e].a = (x->a + y->a) / 2;
        mid[e].b = (x->b + y->b) / 2;
    }
    const lattice_pt *pts[6] = {P[0], P[1], P[2], &mid[0], &mid[1], &mid[2]};
    mr_vec3 v[6];
    for (int k = 0; k < 6; k++)
        v[k] = mr_dmm_vertex(p, pts[k]->a, pts[k]->b);
    for (int k = 0; k < 4 && !(c->any_hit && c->found); k++) {
        const lattice_pt *L[3] = {pts[CHILD[k][0]], pts[CHILD[k][1]], pts[CHILD[k][2]]};
        const mr_vec3 tv[3] = {v[CHILD[k][0]], v[CHILD[k][1]], v[CHILD[k][2]]};
        test_triangle(c, L, tv);
    }
}

static uint32_t level_start(unsigned sublevel) { return ((1u << (2 * sublevel)) - 1) / 3; }

/* Sub-triangle `id` of `sublevel` whose box the ray already enters. */
static void visit(trace_ctx *c, unsigned sublevel, uint32_t id, const lattice_pt *const P[3])
{
    if (sublevel == c->leaf) {
        leaf(c, P);
        return;
    }
    lattice_pt mid[3];
    midpoints(c, P, mid);
    const lattice_pt *pts[6] = {P[0], P[1], P[2], &mid[0], &mid[1], &mid[2]};
    float entry[4];
    int order[4], count = 0;
    uint32_t first = level_start(sublevel + 1) + 4 * id;
    for (int k = 0; k < 4; k++) {
        const lattice_pt *L[3] = {pts[CHILD[k][0]], pts[CHILD[k][1]], pts[CHILD[k][2]]};
        dbox b = node_box(c->patch, L, disp_min(c, first + (uint32_t)k),
                          disp_max(c, first + (uint32_t)k));
        if (c->stats)
            c->stats->boxes++;
        float t = slab(c->ray, &b, c->tmin, c->tmax);
        if (t == INFINITY)
            continue;
        /* insertion by entry distance: nearest first */
        int at = count++;
        while (at > 0 && entry[at - 1] > t) {
            entry[at] = entry[at - 1];
            order[at] = order[at - 1];
            at--;
        }
        entry[at] = t;
        order[at] = k;
    }
    for (int i = 0; i < count; i++) {
        if (entry[i] > c->tmax * SLAB_FAR_SCALE || (c->any_hit && c->found))
            break;
        int k = order[i];
        const lattice_pt *L[3] = {pts[CHILD[k][0]], pts[CHILD[k][1]], pts[CHILD[k][2]]};
        visit(c, sublevel + 1, 4 * id + (uint32_t)k, L);
    }
}

static void root(const trace_ctx *c, lattice_pt P[3])
{
    uint32_t n = c->segments;
    lattice(c, 0, 0, &P[0]);
    lattice(c, n, 0, &P[1]);
    lattice(c, 0, n, &P[2]);
}

bool mr_dmm_patch_bounds(const mr_dmm_patch *p, mr_vec3 *lo, mr_vec3 *hi)
{
    trace_ctx c = {.patch = p, .segments = mr_umesh_segments(p->level)};
    lattice_pt P[3];
    root(&c, P);
    const lattice_pt *L[3] = {&P[0], &P[1], &P[2]};
    dbox b = node_box(p, L, disp_min(&c, 0), disp_max(&c, 0));
    *lo = mr_v3((float)b.lo[0], (float)b.lo[1], (float)b.lo[2]);
    *hi = mr_v3((float)b.hi[0], (float)b.hi[1], (float)b.hi[2]);
    return isfinite(lo->x) && isfinite(lo->y) && isfinite(lo->z) && isfinite(hi->x) &&
           isfinite(hi->y) && isfinite(hi->z);
}

bool mr_dmm_intersect(const mr_dmm_patch *p, const mr_dmm_ray *ray, float tmin, float *tmax,
                      bool any_hit, mr_dmm_hit *hit, mr_dmm_trace_stats *stats)
{
    if (p->level > MR_UMESH_MAX_LEVEL || !(tmin <= *tmax))
        return false;
    trace_ctx c = {.patch = p,
                   .ray = ray,
                   .leaf = mr_dmm_trace_leaf_sublevel(p->level),
                   .segments = mr_umesh_segments(p->level),
                   .tmin = tmin,
                   .tmax = *tmax,
                   .any_hit = any_hit,
                   .hit = hit,
                   .stats = stats};
    lattice_pt P[3];
    root(&c, P);
    const lattice_pt *L[3] = {&P[0], &P[1], &P[2]};
    /* The caller's BVH has tested the patch box; the root needs no test. */
    visit(&c, 0, 0, L);
    if (c.found)
        *tmax = c.tmax;
    return c.found;
}

void mr_dmm_locate(unsigned level, float u, float v, uint32_t a[3], uint32_t b[3])
{
    uint32_t n = mr_umesh_segments(level);
    if (n == 0)
        n = 1;
    float x = u * (float)n, y = v * (float)n;
    x = x > 0 ? x : 0;
    y = y > 0 ? y : 0;
    uint32_t ia = x < (float)n ? (uint32_t)x : n - 1, ib = y < (float)n ? (uint32_t)y : n - 1;
    if (ia + ib > n - 1) {
        /* outside the triangle by rounding: pull back onto the last row */
        if (ia > n - 1 - ib)
            ia = n - 1 - ib;
    }
    float fx = x - (float)ia, fy = y - (float)ib;
    if (fx + fy <= 1.0f || ia + ib + 1 > n - 1) {
        a[0] = ia, b[0] = ib;
        a[1] = ia + 1, b[1] = ib;
        a[2] = ia, b[2] = ib + 1;
    } else {
        a[0] = ia + 1, b[0] = ib;
        a[1] = ia + 1, b[1] = ib + 1;
        a[2] = ia, b[2] = ib + 1;
    }
}
