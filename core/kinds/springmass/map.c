/* map.c - the detailed mesh bound to the node grid (map.h). */
#include "kinds/springmass/map.h"

#include <math.h>
#include <stdbool.h>
#include <stdlib.h>
#include <string.h>

#include "math/mr_math.h"
#include "util/parallel.h"

/* An approximate normal is trusted where the unit vectors of its node sum
 * to at least this (a node on a flat surface: 1 + 4 / sqrt 2 = 3.8; a
 * node inside: 0) and, at rest, it is within 60 degrees of the surface's
 * normal there (the triangle's; one_to_one: the vertex's). A node of a
 * one-node-thin part fails the second test for the faces of the sheet
 * (no neighbour across it: its normal lies in the sheet) and passes it on
 * the sheet's rim, where its normal does point outwards. */
#define NORMAL_STRENGTH_MIN 1.0f
#define CURVATURE_COS_MIN 0.5
/* ... and N_c at least 17 degrees away from the triangle's first edge (eq.
 * 8 crosses them). */
#define CURVATURE_SIN_MIN 0.3
/* What a triangle node below the surface adds to a candidate's score (in
 * units of barycentric weight outside the triangle). */
#define INNER_NODE_COST 0.1
/* And a node whose approximate normal cannot stand for the vertex's
 * surface (the curvature mapping would fall back to the constant basis). */
#define ASTRAY_NORMAL_COST 0.25
/* Cells around a vertex searched for the grid's surface (its faces lie in
 * cells holding nodes, at most this many cells away). */
#define BOUNDARY_REACH 2
/* Shells of cells searched for a nearest node before all nodes are. */
#define SEARCH_SHELLS 4

enum { BIND_CONSTANT = 0, BIND_CURVATURE, BIND_TRANSLATE };
/* one_to_one: the node's normal is not to be trusted (a flag on the cell). */
#define ONE_WEAK_NORMAL 0x80000000u

typedef struct tri_bind {
    uint32_t c[3];   /* cells of p1, p2, p3 (BIND_TRANSLATE: c[0] only) */
    float w[3];      /* eq. 4 */
    float o[3], n[3];   /* offset and normal in the constant basis (eq. 7) */
    float oc[3], nc[3]; /* in the interpolated basis at rest (BIND_CURVATURE) */
    float t[3], tc[3];  /* the tangent in each (3.3.4; 0 without tangents) */
    uint8_t mode;
} tri_bind;

/* What a frame reads of a triangle-bound vertex, packed (40 bytes rather
 * than tri_bind's 76): its triangle (of tris; HOT_CURVATURE set when it
 * maps by the interpolated basis; UINT32_MAX: BIND_TRANSLATE), weights,
 * and the offset and normal in the basis it maps by (oc, nc for
 * BIND_CURVATURE: the constant ones, for a frame whose N_c degenerates,
 * stay in tri_bind). */
typedef struct tri_hot {
    uint32_t tri;
    float w[3];
    float o[3], n[3];
} tri_hot;
#define HOT_CURVATURE 0x80000000u
/* Vertices ahead whose triangle record apply_range prefetches. */
#define PREFETCH_AHEAD 8

typedef struct lin_bind {
    int32_t corner[8]; /* >= 0: the node's cell; < 0: ghost -(g + 1) */
    float u[3];        /* position in the cell, grid units */
    float n[3];        /* rest normal */
} lin_bind;

/* A cell corner that is not a node: its nearest node n, and per axis how
 * the position changes along it at n (D_a, per cell): from n's neighbour
 * on that axis, or, on an axis without one (across a one-node-thin
 * sheet), the cross product of the other two scaled by 1/h (exact for a
 * rotation). Per frame d_g = d_n + sum_a delta_a (D_a - D_a at rest). */
enum { AXIS_NONE = 0, AXIS_NEIGHBOUR, AXIS_CROSS };

typedef struct ghost {
    uint32_t node;
    uint32_t nb[3];    /* AXIS_NEIGHBOUR: the neighbour's cell */
    uint8_t kind[3];
    float sign[3];     /* the neighbour's side, +1 or -1 */
    float delta[3];    /* from n to the corner, cells */
    float rest_d[3][3];
    bool far;          /* two cells or more from n, with all three D: rigid (below) */
} ghost;

/* Three floats in the first lanes of a 4-lane vector (the fourth is 0):
 * the per-frame arithmetic on points and directions, lane by lane the
 * scalar formulas' operations in their order, so the bits are those of
 * three scalar evaluations. */
typedef float v4 __attribute__((vector_size(16)));

/* A triangle this frame: its constant basis T, N, B (eq. 6) and its nodes'
 * positions P and approximate normals Q. */
typedef struct tri_frame {
    v4 T, N, B, P[3], Q[3];
} tri_frame;

struct sm_map {
    int mapping;
    uint32_t vertex_count;
    float h;
    uint32_t *one;        /* one_to_one: cell per vertex */
    tri_bind *tri;
    tri_hot *hot;         /* triangle mappings: per vertex */
    uint32_t *tri_of;     /* triangle mappings: per vertex its triangle (of tris), UINT32_MAX: none */
    uint32_t *tris;       /* the distinct triangles' cells, 3 each */
    size_t tri_count;
    tri_frame *tri_frame; /* per triangle, this frame's basis and nodes */
    lin_bind *lin;
    ghost *ghosts;
    size_t ghost_count;
    float *gdisp;         /* 3 per ghost, this frame's */
    float *rest_pos, *rest_nrm;
    float *rest_tan;      /* NULL: no tangents to carry */
    float *hot_t;         /* triangle mappings and one_to_one, with tangents: per vertex
                             the tangent in the basis of hot (3 floats) */
    sm_map_info info;
};

void sm_map_free(sm_map *m)
{
    if (!m)
        return;
    free(m->one);
    free(m->tri);
    free(m->hot);
    free(m->tri_of);
    free(m->tris);
    free(m->tri_frame);
    free(m->lin);
    free(m->ghosts);
    free(m->gdisp);
    free(m->rest_pos);
    free(m->rest_nrm);
    free(m->rest_tan);
    free(m->hot_t);
    free(m);
}

const sm_map_info *sm_map_get_info(const sm_map *m) { return &m->info; }

uint32_t sm_map_triangle_of(const sm_map *m, uint32_t v)
{
    return m->tri_of && v < m->vertex_count ? m->tri_of[v] : UINT32_MAX;
}

size_t sm_map_bytes(const sm_map *m)
{
    size_t v = m->vertex_count;
    return sizeof *m + v * 6 * sizeof(float) + (m->rest_tan ? v * 3 * sizeof(float) : 0) +
           (m->hot_t ? v * 3 * sizeof(float) : 0) + (m->one ? v * sizeof *m->one : 0) +
           (m->tri ? v * (sizeof *m->tri + sizeof *m->tri_of + sizeof *m->hot) : 0) +
           m->tri_count * sizeof *m->tri_frame +
           (m->lin ? v * sizeof *m->lin : 0) +
           m->ghost_count * (sizeof *m->ghosts + 3 * sizeof(float));
}

/* ---- small vector helpers (double at set-up, float per frame) */

static void d_sub(const double *a, const double *b, double *o)
{
    for (int i = 0; i < 3; i++)
        o[i] = a[i] - b[i];
}
static double d_dot(const double *a, const double *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
static void d_cross(const double *a, const double *b, double *o)
{
    double r[3] = {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
    memcpy(o, r, sizeof r);
}
static double d_norm(double *a)
{
    double l = sqrt(d_dot(a, a));
    if (l > 0)
        for (int i = 0; i < 3; i++)
            a[i] /= l;
    return l;
}

static inline void f_cross(const float *a, const float *b, float *o)
{
    float r[3] = {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
    memcpy(o, r, sizeof r);
}
static inline float f_norm(float *a)
{
    float l = sqrtf(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
    if (l > 0) {
        float inv = 1.0f / l;
        for (int i = 0; i < 3; i++)
            a[i] *= inv;
    }
    return l;
}

static inline void v4_store3(float *p, v4 a)
{
    p[0] = a[0];
    p[1] = a[1];
    p[2] = a[2];
}
static inline v4 v4_splat(float f) { return (v4){f, f, f, f}; }
/* f_cross */
static inline v4 v4_cross(v4 a, v4 b)
{
    return __builtin_shufflevector(a, a, 1, 2, 0, 3) * __builtin_shufflevector(b, b, 2, 0, 1, 3) -
           __builtin_shufflevector(a, a, 2, 0, 1, 3) * __builtin_shufflevector(b, b, 1, 2, 0, 3);
}
/* f_norm */
static inline float v4_norm(v4 *a)
{
    v4 sq = *a * *a;
    float l = sqrtf(sq[0] + sq[1] + sq[2]);
    if (l > 0)
        *a *= v4_splat(1.0f / l);
    return l;
}

static void set3(float *dst, const float *src)
{
    dst[0] = src[0];
    dst[1] = src[1];
    dst[2] = src[2];
}

/* ---- grid look-ups */

typedef struct grid_view {
    const sm_grid *g;
    const float *rest[3];
    const float *nrm[3];
    const float *nstr;
    uint8_t *surface;  /* per cell: a surface node */
    uint8_t *anchor;   /* per cell: a surface node with a triangle around it */
    uint8_t *framed;   /* per cell: a node with a neighbour on two axes or three */
    /* the surface of the grid's solid (boundary faces of cells whose 8
     * corners are nodes), two outward triangles per face, listed by the
     * cell they belong to: the triangles of cell c are first[c]..first[c+1] */
    uint32_t *btri;
    uint32_t *bfirst;
} grid_view;

static void cell_ijk(const sm_grid *g, size_t c, int64_t ijk[3])
{
    ijk[0] = (int64_t)(c % g->n[0]);
    ijk[1] = (int64_t)((c / g->n[0]) % g->n[1]);
    ijk[2] = (int64_t)(c / ((size_t)g->n[0] * g->n[1]));
}

static void cell_rest(const grid_view *gv, size_t c, double p[3])
{
    for (int a = 0; a < 3; a++)
        p[a] = gv->rest[a][c];
}

/* The node nearest to p among the cells whose eligible[] is set (NULL:
 * every node); ties: lowest cell. Shells of cells around p first, then
 * every cell. -1 when none is eligible. */
static int64_t nearest_node(const grid_view *gv, const double p[3], const uint8_t *eligible)
{
    const sm_grid *g = gv->g;
    int64_t center[3];
    for (int a = 0; a < 3; a++) {
        double f = floor((p[a] - g->origin[a]) / g->h + 0.5);
        center[a] = f < 0 ? 0 : f > g->n[a] - 1 ? (int64_t)g->n[a] - 1 : (int64_t)f;
    }
    int64_t best = -1;
    double best_d2 = INFINITY;
    for (int r = 0; r <= SEARCH_SHELLS; r++) {
        for (int64_t dk = -r; dk <= r; dk++)
            for (int64_t dj = -r; dj <= r; dj++)
                for (int64_t di = -r; di <= r; di++) {
                    if (llabs(di) != r && llabs(dj) != r && llabs(dk) != r)
                        continue; /* the shell only */
                    int64_t q[3] = {center[0] + di, center[1] + dj, center[2] + dk};
                    if (q[0] < 0 || q[1] < 0 || q[2] < 0 || q[0] >= g->n[0] || q[1] >= g->n[1] || q[2] >= g->n[2])
                        continue;
                    size_t c = sm_grid_cell(g, (uint32_t)q[0], (uint32_t)q[1], (uint32_t)q[2]);
                    if (!(eligible ? eligible[c] : g->active[c]))
                        continue;
                    double np[3], d[3];
                    cell_rest(gv, c, np);
                    d_sub(np, p, d);
                    double d2 = d_dot(d, d);
                    if (d2 < best_d2 || (d2 == best_d2 && (int64_t)c < best)) {
                        best_d2 = d2;
                        best = (int64_t)c;
                    }
                }
        /* every cell of the next shell is at least (r + 1/2) h away */
        if (best >= 0 && sqrt(best_d2) <= (r + 0.5) * g->h)
            return best;
    }
    for (size_t c = 0; c < g->cells; c++) {
        if (!(eligible ? eligible[c] : g->active[c]))
            continue;
        double np[3], d[3];
        cell_rest(gv, c, np);
        d_sub(np, p, d);
        double d2 = d_dot(d, d);
        if (d2 < best_d2) {
            best_d2 = d2;
            best = (int64_t)c;
        }
    }
    return best;
}

/* ---- triangle bindings */

/* The constant basis (eq. 6) of p1, p2, p3 (double). */
static void basis_d(const double *p1, const double *p2, const double *p3, double T[3], double N[3], double B[3])
{
    double bt[3];
    d_sub(p2, p1, T);
    d_norm(T);
    d_sub(p3, p1, bt);
    d_norm(bt);
    d_cross(T, bt, N);
    d_norm(N);
    d_cross(N, T, B);
}

typedef struct bind_ctx {
    const grid_view *gv;
    int mapping;
    const float *pos, *nrm, *tan; /* tan: NULL without tangents */
    tri_bind *out;
} bind_ctx;

/* Whether cells a and b are 18-neighbours. */
static bool neighbours18(const sm_grid *g, size_t a, size_t b)
{
    int64_t p[3], q[3];
    cell_ijk(g, a, p);
    cell_ijk(g, b, q);
    int64_t s = 0;
    for (int i = 0; i < 3; i++) {
        int64_t d = llabs(p[i] - q[i]);
        if (d > 1)
            return false;
        s += d;
    }
    return s == 1 || s == 2;
}

/* The point of triangle (a, b, c) closest to p (Ericson, Real-Time
 * Collision Detection 5.1.5), as barycentric weights of a, b, c. */
static void closest_on_triangle(const double *p, const double *a, const double *b, const double *c, double w[3])
{
    double ab[3], ac[3], ap[3], bp[3], cp[3];
    d_sub(b, a, ab);
    d_sub(c, a, ac);
    d_sub(p, a, ap);
    double d1 = d_dot(ab, ap), d2 = d_dot(ac, ap);
    if (d1 <= 0 && d2 <= 0) {
        w[0] = 1, w[1] = 0, w[2] = 0;
        return;
    }
    d_sub(p, b, bp);
    double d3 = d_dot(ab, bp), d4 = d_dot(ac, bp);
    if (d3 >= 0 && d4 <= d3) {
        w[0] = 0, w[1] = 1, w[2] = 0;
        return;
    }
    double vc = d1 * d4 - d3 * d2;
    if (vc <= 0 && d1 >= 0 && d3 <= 0) {
        double t = d1 / (d1 - d3);
        w[0] = 1 - t, w[1] = t, w[2] = 0;
        return;
    }
    d_sub(p, c, cp);
    double d5 = d_dot(ab, cp), d6 = d_dot(ac, cp);
    if (d6 >= 0 && d5 <= d6) {
        w[0] = 0, w[1] = 0, w[2] = 1;
        return;
    }
    double vb = d5 * d2 - d1 * d6;
    if (vb <= 0 && d2 >= 0 && d6 <= 0) {
        double t = d2 / (d2 - d6);
        w[0] = 1 - t, w[1] = 0, w[2] = t;
        return;
    }
    double va = d3 * d6 - d5 * d4;
    if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) {
        double t = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        w[0] = 0, w[1] = 1 - t, w[2] = t;
        return;
    }
    double den = 1 / (va + vb + vc);
    w[1] = vb * den;
    w[2] = vc * den;
    w[0] = 1 - w[1] - w[2];
}

/* The triangle of the grid's surface closest to p within BOUNDARY_REACH
 * cells (ties: the first listed), into bc and bw; false if there is none
 * that near. */
static bool nearest_boundary(const grid_view *gv, const double p[3], size_t bc[3], double bw[3])
{
    const sm_grid *g = gv->g;
    int64_t at[3];
    for (int a = 0; a < 3; a++)
        at[a] = (int64_t)floor((p[a] - g->origin[a]) / g->h);
    double best = INFINITY;
    for (int64_t dk = -BOUNDARY_REACH; dk <= BOUNDARY_REACH; dk++)
        for (int64_t dj = -BOUNDARY_REACH; dj <= BOUNDARY_REACH; dj++)
            for (int64_t di = -BOUNDARY_REACH; di <= BOUNDARY_REACH; di++) {
                int64_t q[3] = {at[0] + di, at[1] + dj, at[2] + dk};
                if (q[0] < 0 || q[1] < 0 || q[2] < 0 || q[0] >= g->n[0] || q[1] >= g->n[1] || q[2] >= g->n[2])
                    continue;
                size_t cell = sm_grid_cell(g, (uint32_t)q[0], (uint32_t)q[1], (uint32_t)q[2]);
                for (uint32_t t = gv->bfirst[cell]; t < gv->bfirst[cell + 1]; t++) {
                    const uint32_t *tri = gv->btri + (size_t)t * 3;
                    double P[3][3], w[3], r[3], d[3];
                    for (int k = 0; k < 3; k++)
                        cell_rest(gv, tri[k], P[k]);
                    closest_on_triangle(p, P[0], P[1], P[2], w);
                    for (int a = 0; a < 3; a++)
                        r[a] = w[0] * P[0][a] + w[1] * P[1][a] + w[2] * P[2][a];
                    d_sub(p, r, d);
                    double d2 = d_dot(d, d);
                    if (d2 < best) {
                        best = d2;
                        for (int k = 0; k < 3; k++) {
                            bc[k] = tri[k];
                            bw[k] = w[k];
                        }
                    }
                }
            }
    return best < INFINITY;
}

/* 1 when node c's approximate normal cannot stand for the surface with
 * normal vn (weak, or more than 60 degrees off), else 0. */
static double astray_normal(const grid_view *gv, size_t c, const double vn[3])
{
    double d = gv->nrm[0][c] * vn[0] + gv->nrm[1][c] * vn[1] + gv->nrm[2][c] * vn[2];
    return gv->nstr[c] < NORMAL_STRENGTH_MIN || d < CURVATURE_COS_MIN ? 1.0 : 0.0;
}

static void bind_vertex(const bind_ctx *x, uint32_t v, tri_bind *tb)
{
    const grid_view *gv = x->gv;
    const sm_grid *g = gv->g;
    double p[3] = {x->pos[(size_t)v * 3], x->pos[(size_t)v * 3 + 1], x->pos[(size_t)v * 3 + 2]};
    double vn[3] = {x->nrm[(size_t)v * 3], x->nrm[(size_t)v * 3 + 1], x->nrm[(size_t)v * 3 + 2]};
    memset(tb, 0, sizeof *tb);
    size_t bc[3];
    double bw[3];
    double P[3][3], T[3], N[3], B[3];
    if (d_norm(vn) == 0) {
        int64_t c = nearest_node(gv, p, NULL);
        for (int a = 0; a < 3; a++)
            vn[a] = gv->nrm[a][c];
    }
    /* the surface of the simulated grid itself, where there is one near */
    if (gv->btri && nearest_boundary(gv, p, bc, bw)) {
        for (int k = 0; k < 3; k++)
            cell_rest(gv, bc[k], P[k]);
        basis_d(P[0], P[1], P[2], T, N, B);
        goto bound;
    }
    /* else the nearest surface node with a triangle around it (an isolated
     * node, or a line of them, has none); any node if there is no such one */
    int64_t n1 = nearest_node(gv, p, gv->anchor);
    if (n1 < 0)
        n1 = nearest_node(gv, p, NULL);
    tb->c[0] = (uint32_t)n1;
    /* the nodes around n1: on a surface running diagonally through the
     * grid, surface nodes alone are linked only in a zig-zag with no
     * triangle between them, so nodes below the surface take part too (at
     * a small cost in the score) */
    size_t nb[18], nn = 0;
    for (int d = 0; d < 18; d++) {
        size_t c = (size_t)((ptrdiff_t)n1 + sm_grid_offset(g, sm_neighbour_dir[d]));
        if (g->active[c])
            nb[nn++] = c;
    }
    double best = INFINITY;
    bc[0] = (size_t)n1;
    bw[0] = bw[1] = bw[2] = 0;
    double p1[3];
    cell_rest(gv, (size_t)n1, p1);
    for (size_t i = 0; i < nn; i++)
        for (size_t j = i + 1; j < nn; j++) {
            if (!neighbours18(g, nb[i], nb[j]))
                continue;
            double p2[3], p3[3], e1[3], e2[3], q[3], n[3];
            cell_rest(gv, nb[i], p2);
            cell_rest(gv, nb[j], p3);
            d_sub(p2, p1, e1);
            d_sub(p3, p1, e2);
            d_sub(p, p1, q);
            double d00 = d_dot(e1, e1), d01 = d_dot(e1, e2), d11 = d_dot(e2, e2);
            double d20 = d_dot(q, e1), d21 = d_dot(q, e2), den = d00 * d11 - d01 * d01;
            if (!(den > 0))
                continue;
            double w2 = (d11 * d20 - d01 * d21) / den, w3 = (d00 * d21 - d01 * d20) / den, w1 = 1 - w2 - w3;
            d_cross(e1, e2, n);
            d_norm(n);
            double outside = fmax(0, -w1) + fmax(0, -w2) + fmax(0, -w3);
            double below = !(g->flags[nb[i]] & SM_NODE_SURFACE) + !(g->flags[nb[j]] & SM_NODE_SURFACE);
            double astray = astray_normal(gv, (size_t)n1, vn) + astray_normal(gv, nb[i], vn) +
                            astray_normal(gv, nb[j], vn);
            double score = outside + 0.5 * (1 - fabs(d_dot(n, vn))) + INNER_NODE_COST * below +
                           ASTRAY_NORMAL_COST * astray;
            if (score < best) {
                best = score;
                bc[1] = nb[i];
                bc[2] = nb[j];
                bw[0] = w1;
                bw[1] = w2;
                bw[2] = w3;
            }
        }
    if (best == INFINITY) {
        tb->mode = BIND_TRANSLATE;
        return;
    }
    for (int k = 0; k < 3; k++)
        cell_rest(gv, bc[k], P[k]);
    basis_d(P[0], P[1], P[2], T, N, B);
    if (d_dot(N, vn) < 0) { /* node order so that N faces the vertex normal */
        size_t tc = bc[1];
        bc[1] = bc[2];
        bc[2] = tc;
        double tw = bw[1];
        bw[1] = bw[2];
        bw[2] = tw;
        for (int a = 0; a < 3; a++) {
            double t = P[1][a];
            P[1][a] = P[2][a];
            P[2][a] = t;
        }
        basis_d(P[0], P[1], P[2], T, N, B);
    }
bound:;
    double r[3], o[3], rn[3] = {x->nrm[(size_t)v * 3], x->nrm[(size_t)v * 3 + 1], x->nrm[(size_t)v * 3 + 2]};
    for (int a = 0; a < 3; a++)
        r[a] = bw[0] * P[0][a] + bw[1] * P[1][a] + bw[2] * P[2][a];
    d_sub(p, r, o);
    for (int k = 0; k < 3; k++) {
        tb->c[k] = (uint32_t)bc[k];
        tb->w[k] = (float)bw[k];
    }
    tb->o[0] = (float)d_dot(o, T);
    tb->o[1] = (float)d_dot(o, N);
    tb->o[2] = (float)d_dot(o, B);
    tb->n[0] = (float)d_dot(rn, T);
    tb->n[1] = (float)d_dot(rn, N);
    tb->n[2] = (float)d_dot(rn, B);
    double rt[3] = {0, 0, 0};
    if (x->tan)
        for (int a = 0; a < 3; a++)
            rt[a] = x->tan[(size_t)v * 3 + a];
    tb->t[0] = (float)d_dot(rt, T);
    tb->t[1] = (float)d_dot(rt, N);
    tb->t[2] = (float)d_dot(rt, B);
    tb->mode = BIND_CONSTANT;
    if (x->mapping != MR_SPRINGMASS_TRIANGLE_CURVATURE)
        return;
    /* the interpolated basis at rest, where the approximate normals hold */
    double Nc[3] = {0, 0, 0};
    for (int k = 0; k < 3; k++) {
        size_t c = bc[k];
        if (gv->nstr[c] < NORMAL_STRENGTH_MIN)
            return;
        for (int a = 0; a < 3; a++)
            Nc[a] += bw[k] * gv->nrm[a][c];
    }
    if (d_norm(Nc) == 0 || d_dot(Nc, vn) < CURVATURE_COS_MIN)
        return;
    double Bc[3], Tc[3];
    d_cross(Nc, T, Bc);
    if (d_norm(Bc) < CURVATURE_SIN_MIN)
        return;
    d_cross(Bc, Nc, Tc);
    tb->oc[0] = (float)d_dot(o, Tc);
    tb->oc[1] = (float)d_dot(o, Nc);
    tb->oc[2] = (float)d_dot(o, Bc);
    tb->nc[0] = (float)d_dot(rn, Tc);
    tb->nc[1] = (float)d_dot(rn, Nc);
    tb->nc[2] = (float)d_dot(rn, Bc);
    tb->tc[0] = (float)d_dot(rt, Tc);
    tb->tc[1] = (float)d_dot(rt, Nc);
    tb->tc[2] = (float)d_dot(rt, Bc);
    tb->mode = BIND_CURVATURE;
}

static void bind_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    const bind_ctx *x = ctx;
    for (size_t v = begin; v < end; v++)
        bind_vertex(x, (uint32_t)v, &x->out[v]);
}

/* ---- trilinear set-up */

/* D_a for each axis from positions xyz (ghost recipe above). */
static void ghost_derivatives(const ghost *gh, const float *const xyz[3], float inv_h, float D[3][3])
{
    for (int a = 0; a < 3; a++) {
        for (int c = 0; c < 3; c++)
            D[a][c] = 0;
        if (gh->kind[a] == AXIS_NEIGHBOUR)
            for (int c = 0; c < 3; c++)
                D[a][c] = gh->sign[a] * (xyz[c][gh->nb[a]] - xyz[c][gh->node]);
    }
    for (int a = 0; a < 3; a++)
        if (gh->kind[a] == AXIS_CROSS) {
            const float *u = D[(a + 1) % 3], *w = D[(a + 2) % 3];
            f_cross(u, w, D[a]);
            for (int c = 0; c < 3; c++)
                D[a][c] *= inv_h;
        }
}

/* An orthonormal frame (rows) from the axis derivatives D: Gram-Schmidt of
 * D[0], D[1], then their cross product; a turned frame for a turned D. */
static void frame_of(const float D[3][3], float R[3][3])
{
    float t[3];
    set3(R[0], D[0]);
    f_norm(R[0]);
    float along = R[0][0] * D[1][0] + R[0][1] * D[1][1] + R[0][2] * D[1][2];
    for (int c = 0; c < 3; c++)
        t[c] = D[1][c] - along * R[0][c];
    f_norm(t);
    set3(R[1], t);
    f_cross(R[0], R[1], R[2]);
}

static ghost ghost_recipe(const grid_view *gv, size_t cell)
{
    const sm_grid *g = gv->g;
    double p[3];
    cell_rest(gv, cell, p);
    ghost r;
    memset(&r, 0, sizeof r);
    /* the nearest node with neighbours on two axes at least (the third then
     * follows by a cross product); any node if there is none */
    int64_t n = nearest_node(gv, p, gv->framed);
    if (n < 0)
        n = nearest_node(gv, p, NULL);
    int64_t gi[3], ni[3];
    cell_ijk(g, cell, gi);
    cell_ijk(g, (size_t)n, ni);
    r.node = (uint32_t)n;
    for (int a = 0; a < 3; a++) {
        r.delta[a] = (float)(gi[a] - ni[a]);
        int8_t dir[3] = {0, 0, 0};
        for (int side = 0; side < 2; side++) {
            int s = (gi[a] >= ni[a]) == (side == 0) ? 1 : -1; /* towards the corner first */
            int64_t mi = ni[a] + s;
            dir[a] = (int8_t)s;
            if (mi < 0 || mi >= g->n[a])
                continue;
            size_t m = (size_t)(n + sm_grid_offset(g, dir));
            if (!g->active[m])
                continue;
            r.kind[a] = AXIS_NEIGHBOUR;
            r.nb[a] = (uint32_t)m;
            r.sign[a] = (float)s;
            break;
        }
    }
    for (int a = 0; a < 3; a++)
        if (r.kind[a] == AXIS_NONE && r.kind[(a + 1) % 3] == AXIS_NEIGHBOUR && r.kind[(a + 2) % 3] == AXIS_NEIGHBOUR)
            r.kind[a] = AXIS_CROSS;
    ghost_derivatives(&r, gv->rest, (float)(1.0 / g->h), r.rest_d);
    bool framed = r.kind[0] != AXIS_NONE && r.kind[1] != AXIS_NONE && r.kind[2] != AXIS_NONE;
    r.far = framed && (fabsf(r.delta[0]) >= 2 || fabsf(r.delta[1]) >= 2 || fabsf(r.delta[2]) >= 2);
    return r;
}

static int setup_trilinear(sm_map *m, const grid_view *gv, const float *pos, const float *nrm, mr_error *err)
{
    const sm_grid *g = gv->g;
    int32_t *ghost_of = malloc(g->cells * sizeof *ghost_of);
    m->lin = malloc((size_t)m->vertex_count * sizeof *m->lin);
    if (!ghost_of || !m->lin) {
        free(ghost_of);
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory binding %u vertices", m->vertex_count);
    }
    for (size_t c = 0; c < g->cells; c++)
        ghost_of[c] = -1;
    size_t cap = 0;
    for (uint32_t v = 0; v < m->vertex_count; v++) {
        lin_bind *lb = &m->lin[v];
        int64_t base[3];
        for (int a = 0; a < 3; a++) {
            double f = ((double)pos[(size_t)v * 3 + a] - g->origin[a]) / g->h;
            double b = floor(f);
            b = b < 0 ? 0 : b > g->n[a] - 2 ? g->n[a] - 2 : b;
            base[a] = (int64_t)b;
            lb->u[a] = (float)(f - b);
            lb->n[a] = nrm[(size_t)v * 3 + a];
        }
        for (int k = 0; k < 8; k++) {
            size_t c = sm_grid_cell(g, (uint32_t)(base[0] + (k & 1)), (uint32_t)(base[1] + ((k >> 1) & 1)),
                                    (uint32_t)(base[2] + (k >> 2)));
            if (g->active[c]) {
                lb->corner[k] = (int32_t)c;
                continue;
            }
            if (ghost_of[c] < 0) {
                if (m->ghost_count == cap) {
                    cap = cap ? cap * 2 : 1024;
                    ghost *ng = realloc(m->ghosts, cap * sizeof *ng);
                    if (!ng) {
                        free(ghost_of);
                        return mr_error_set(err, MR_ERR_NOMEM, "out of memory binding %u vertices",
                                            m->vertex_count);
                    }
                    m->ghosts = ng;
                }
                m->ghosts[m->ghost_count] = ghost_recipe(gv, c);
                ghost_of[c] = (int32_t)m->ghost_count++;
            }
            lb->corner[k] = -(ghost_of[c] + 1);
        }
    }
    free(ghost_of);
    m->info.ghost_corners = m->ghost_count;
    if (!(m->gdisp = calloc(m->ghost_count * 3 + 1, sizeof *m->gdisp)))
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory binding %u vertices", m->vertex_count);
    return MR_OK;
}

typedef struct tri_key {
    uint32_t c[3];
    uint32_t vertex;
} tri_key;

static int tri_key_cmp(const void *pa, const void *pb)
{
    const tri_key *a = pa, *b = pb;
    for (int k = 0; k < 3; k++)
        if (a->c[k] != b->c[k])
            return a->c[k] < b->c[k] ? -1 : 1;
    return (a->vertex > b->vertex) - (a->vertex < b->vertex);
}

/* The distinct triangles of the bindings (their basis is made once per
 * frame, not once per vertex). */
static int index_triangles(sm_map *m, mr_error *err)
{
    uint32_t nv = m->vertex_count;
    tri_key *keys = malloc((size_t)nv * sizeof *keys + 1);
    m->tri_of = malloc((size_t)nv * sizeof *m->tri_of + 1);
    if (!keys || !m->tri_of) {
        free(keys);
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory binding %u vertices", nv);
    }
    size_t n = 0;
    for (uint32_t v = 0; v < nv; v++) {
        m->tri_of[v] = UINT32_MAX;
        if (m->tri[v].mode != BIND_TRANSLATE)
            keys[n++] = (tri_key){{m->tri[v].c[0], m->tri[v].c[1], m->tri[v].c[2]}, v};
    }
    qsort(keys, n, sizeof *keys, tri_key_cmp);
    m->tris = malloc(n * 3 * sizeof *m->tris + 1);
    if (!m->tris) {
        free(keys);
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory binding %u vertices", nv);
    }
    for (size_t i = 0; i < n; i++) {
        if (i == 0 || memcmp(keys[i].c, keys[i - 1].c, sizeof keys[i].c) != 0) {
            memcpy(m->tris + m->tri_count * 3, keys[i].c, sizeof keys[i].c);
            m->tri_count++;
        }
        m->tri_of[keys[i].vertex] = (uint32_t)(m->tri_count - 1);
    }
    free(keys);
    if (!(m->hot = malloc((size_t)nv * sizeof *m->hot + 1)))
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory binding %u vertices", nv);
    for (uint32_t v = 0; v < nv; v++) {
        const tri_bind *tb = &m->tri[v];
        tri_hot *th = &m->hot[v];
        bool curved = tb->mode == BIND_CURVATURE;
        th->tri = tb->mode == BIND_TRANSLATE ? UINT32_MAX : m->tri_of[v] | (curved ? HOT_CURVATURE : 0);
        set3(th->w, tb->w);
        set3(th->o, curved ? tb->oc : tb->o);
        set3(th->n, curved ? tb->nc : tb->n);
    }
    if (m->rest_tan) {
        if (!(m->hot_t = malloc((size_t)nv * 3 * sizeof *m->hot_t + 1)))
            return mr_error_set(err, MR_ERR_NOMEM, "out of memory binding %u vertices", nv);
        for (uint32_t v = 0; v < nv; v++)
            set3(m->hot_t + (size_t)v * 3, m->tri[v].mode == BIND_CURVATURE ? m->tri[v].tc : m->tri[v].t);
    }
    if (!(m->tri_frame = aligned_alloc(_Alignof(tri_frame), (m->tri_count + 1) * sizeof *m->tri_frame)))
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory binding %u vertices", nv);
    return MR_OK;
}

/* Surface nodes, and those with a triangle of pairwise 18-neighbours
 * around them (bind_vertex's candidates). */
static void mark_anchors(grid_view *gv)
{
    const sm_grid *g = gv->g;
    for (size_t c = 0; c < g->cells; c++) {
        if (!g->active[c])
            continue;
        int axes = 0;
        for (int a = 0; a < 3; a++) {
            ptrdiff_t o = sm_grid_offset(g, sm_neighbour_dir[2 * a]);
            axes += g->active[c + o] || g->active[c - o];
        }
        gv->framed[c] = axes >= 2;
        if (!(g->flags[c] & SM_NODE_SURFACE))
            continue;
        gv->surface[c] = 1;
        size_t nb[18], nn = 0;
        for (int d = 0; d < 18; d++) {
            size_t q = (size_t)((ptrdiff_t)c + sm_grid_offset(g, sm_neighbour_dir[d]));
            if (g->active[q])
                nb[nn++] = q;
        }
        for (size_t i = 0; i < nn && !gv->anchor[c]; i++)
            for (size_t j = i + 1; j < nn && !gv->anchor[c]; j++)
                gv->anchor[c] = neighbours18(g, nb[i], nb[j]);
    }
}

static int map_setup(sm_map *m, grid_view *gv, int mapping, const float *rest_positions,
                     const float *rest_normals, const float *rest_tangents, uint32_t vertex_count,
                     unsigned threads, mr_error *err);

/* Whether cell (i, j, k) and its 7 neighbours towards +x, +y, +z are all
 * nodes: a solid cell of the grid. */
static bool solid_cell(const sm_grid *g, int64_t i, int64_t j, int64_t k)
{
    if (i < 0 || j < 0 || k < 0 || i + 1 >= g->n[0] || j + 1 >= g->n[1] || k + 1 >= g->n[2])
        return false;
    for (int q = 0; q < 8; q++)
        if (!g->active[sm_grid_cell(g, (uint32_t)(i + (q & 1)), (uint32_t)(j + ((q >> 1) & 1)),
                                    (uint32_t)(k + (q >> 2)))])
            return false;
    return true;
}

/* The surface of the grid's solid cells (grid_view.btri/bfirst): each face
 * of a solid cell that no solid cell shares, as two triangles whose normal
 * points out of the solid. */
static int build_boundary(grid_view *gv, mr_error *err)
{
    const sm_grid *g = gv->g;
    size_t count = 0, cap = 0;
    uint32_t *tri = NULL;
    if (!(gv->bfirst = calloc(g->cells + 1, sizeof *gv->bfirst)))
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory for the grid's surface");
    for (uint32_t k = 0; k < g->n[2]; k++)
        for (uint32_t j = 0; j < g->n[1]; j++)
            for (uint32_t i = 0; i < g->n[0]; i++) {
                size_t c = sm_grid_cell(g, i, j, k);
                gv->bfirst[c] = (uint32_t)count;
                if (!solid_cell(g, i, j, k))
                    continue;
                int64_t ijk[3] = {i, j, k};
                for (int a = 0; a < 3; a++)
                    for (int side = 0; side < 2; side++) {
                        int64_t n[3] = {ijk[0], ijk[1], ijk[2]};
                        n[a] += side ? 1 : -1;
                        if (solid_cell(g, n[0], n[1], n[2]))
                            continue;
                        /* the face's corners, counter-clockwise seen from outside */
                        int b = (a + 1) % 3, d = (a + 2) % 3;
                        static const int plus[4][2] = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};
                        static const int minus[4][2] = {{0, 0}, {0, 1}, {1, 1}, {1, 0}};
                        uint32_t q[4];
                        for (int v = 0; v < 4; v++) {
                            int64_t at[3] = {ijk[0], ijk[1], ijk[2]};
                            at[a] += side;
                            at[b] += side ? plus[v][0] : minus[v][0];
                            at[d] += side ? plus[v][1] : minus[v][1];
                            q[v] = (uint32_t)sm_grid_cell(g, (uint32_t)at[0], (uint32_t)at[1], (uint32_t)at[2]);
                        }
                        if (count + 2 > cap) {
                            cap = cap ? cap * 2 : 4096;
                            uint32_t *grown = realloc(tri, cap * 3 * sizeof *grown);
                            if (!grown) {
                                free(tri);
                                return mr_error_set(err, MR_ERR_NOMEM, "out of memory for the grid's surface");
                            }
                            tri = grown;
                        }
                        uint32_t t2[6] = {q[0], q[1], q[2], q[0], q[2], q[3]};
                        memcpy(tri + count * 3, t2, sizeof t2);
                        count += 2;
                    }
            }
    gv->bfirst[g->cells] = (uint32_t)count;
    gv->btri = tri;
    return MR_OK;
}

int sm_map_new(const sm_sim *sim, int mapping, const float *rest_positions, const float *rest_normals,
               const float *rest_tangents, uint32_t vertex_count, unsigned threads, sm_map **out, mr_error *err)
{
    *out = NULL;
    sm_map *m = calloc(1, sizeof *m);
    if (!m)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    m->mapping = mapping;
    m->vertex_count = vertex_count;
    grid_view gv = {.g = sm_sim_grid(sim)};
    sm_sim_rest(sim, gv.rest);
    sm_sim_rest_normals(sim, gv.nrm, &gv.nstr);
    m->h = (float)gv.g->h;
    if (!(gv.surface = calloc(gv.g->cells, 1)) || !(gv.anchor = calloc(gv.g->cells, 1)) ||
        !(gv.framed = calloc(gv.g->cells, 1))) {
        free(gv.surface);
        free(gv.anchor);
        sm_map_free(m);
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory binding %u vertices", vertex_count);
    }
    mark_anchors(&gv);
    int rc = mapping == MR_SPRINGMASS_TRILINEAR ? MR_OK : build_boundary(&gv, err);
    if (rc == MR_OK)
        rc = map_setup(m, &gv, mapping, rest_positions, rest_normals, rest_tangents, vertex_count, threads, err);
    free(gv.surface);
    free(gv.anchor);
    free(gv.framed);
    free(gv.btri);
    free(gv.bfirst);
    if (rc < 0) {
        sm_map_free(m);
        return rc;
    }
    *out = m;
    return MR_OK;
}

static int map_setup(sm_map *m, grid_view *gv_, int mapping, const float *rest_positions,
                     const float *rest_normals, const float *rest_tangents, uint32_t vertex_count,
                     unsigned threads, mr_error *err)
{
    grid_view gv = *gv_;
    size_t bytes = (size_t)vertex_count * 3 * sizeof(float);
    m->rest_pos = malloc(bytes + 1);
    m->rest_nrm = malloc(bytes + 1);
    if (!m->rest_pos || !m->rest_nrm)
        goto nomem;
    memcpy(m->rest_pos, rest_positions, bytes);
    memcpy(m->rest_nrm, rest_normals, bytes);
    if (rest_tangents) {
        if (!(m->rest_tan = malloc(bytes + 1)))
            goto nomem;
        memcpy(m->rest_tan, rest_tangents, bytes);
    }
    switch (mapping) {
    case MR_SPRINGMASS_ONE_TO_ONE: {
        /* where the node's approximate normal does not hold (3.5), the
         * vertex's normal comes from a constant triangle basis instead */
        if (!(m->one = malloc((size_t)vertex_count * sizeof *m->one + 1)) ||
            !(m->tri = malloc((size_t)vertex_count * sizeof *m->tri + 1)))
            goto nomem;
        bind_ctx bc = {&gv, MR_SPRINGMASS_TRIANGLE_BASIS, rest_positions, rest_normals, rest_tangents, m->tri};
        mr_parallel_for(threads, vertex_count, 256, bind_range, &bc);
        for (uint32_t v = 0; v < vertex_count; v++) {
            double p[3] = {rest_positions[(size_t)v * 3], rest_positions[(size_t)v * 3 + 1],
                           rest_positions[(size_t)v * 3 + 2]};
            uint32_t c = (uint32_t)nearest_node(&gv, p, gv.surface);
            m->one[v] = c;
            double facing = gv.nrm[0][c] * rest_normals[(size_t)v * 3] + gv.nrm[1][c] * rest_normals[(size_t)v * 3 + 1] +
                            gv.nrm[2][c] * rest_normals[(size_t)v * 3 + 2];
            if (gv.nstr[c] < NORMAL_STRENGTH_MIN || facing < CURVATURE_COS_MIN) {
                m->one[v] |= ONE_WEAK_NORMAL;
                m->info.constant_fallback++;
            }
        }
        break;
    }
    case MR_SPRINGMASS_TRIANGLE_BASIS:
    case MR_SPRINGMASS_TRIANGLE_CURVATURE: {
        if (!(m->tri = malloc((size_t)vertex_count * sizeof *m->tri + 1)))
            goto nomem;
        bind_ctx bc = {&gv, mapping, rest_positions, rest_normals, rest_tangents, m->tri};
        mr_parallel_for(threads, vertex_count, 256, bind_range, &bc);
        for (uint32_t v = 0; v < vertex_count; v++) {
            m->info.translation_only += m->tri[v].mode == BIND_TRANSLATE;
            m->info.constant_fallback +=
                mapping == MR_SPRINGMASS_TRIANGLE_CURVATURE && m->tri[v].mode == BIND_CONSTANT;
        }
        break;
    }
    case MR_SPRINGMASS_TRILINEAR:
        return setup_trilinear(m, &gv, rest_positions, rest_normals, err);
    default:
        return mr_error_set(err, MR_ERR_INVALID, "unknown mapping %d", mapping);
    }
    return index_triangles(m, err);
nomem:
    return mr_error_set(err, MR_ERR_NOMEM, "out of memory binding %u vertices", vertex_count);
}

/* ---- per frame */

typedef struct apply_ctx {
    const sm_map *m;
    const float *pos[3], *rest[3], *nrm[3];
    float *out_pos, *out_nrm;
    float *out_tan; /* NULL: no tangents (none asked for, or the map has none) */
} apply_ctx;


static void apply_tri(const apply_ctx *x, uint32_t v);

/* A tangent carried some way made orthogonal to the unit normal n again
 * (mr_v3_tangent_to); a zero one (a mesh without tangents) stays zero. */
static inline void fit_tangent(const float t[3], const float n[3], float *out)
{
    mr_vec3 r = mr_v3(0, 0, 0);
    if (t[0] != 0.0f || t[1] != 0.0f || t[2] != 0.0f)
        r = mr_v3_tangent_to(mr_v3(t[0], t[1], t[2]), mr_v3(n[0], n[1], n[2]), true);
    out[0] = r.x;
    out[1] = r.y;
    out[2] = r.z;
}

/* one_to_one (3.2) has only the node's approximate normal, no tangent
 * frame (3.5): the vertex's tangent is carried by its constant triangle
 * basis (the one its normal falls back to; the rest tangent moved by
 * translation where it has no triangle) and made orthogonal to the node's
 * normal. */
static void apply_one(const apply_ctx *x, uint32_t v)
{
    const sm_map *m = x->m;
    uint32_t c = m->one[v] & ~ONE_WEAK_NORMAL;
    float p[3] = {x->pos[0][c], x->pos[1][c], x->pos[2][c]};
    float n[3] = {x->nrm[0][c], x->nrm[1][c], x->nrm[2][c]};
    if ((m->one[v] & ONE_WEAK_NORMAL) || f_norm(n) == 0) {
        /* the constant basis' normal and tangent; its position is overwritten */
        apply_tri(x, v);
        set3(x->out_pos + (size_t)v * 3, p);
        return;
    }
    set3(x->out_pos + (size_t)v * 3, p);
    set3(x->out_nrm + (size_t)v * 3, n);
    if (x->out_tan) {
        const tri_hot *th = &m->hot[v];
        float t[3];
        if (th->tri == UINT32_MAX) {
            set3(t, m->rest_tan + (size_t)v * 3);
        } else {
            const tri_frame *tf = &m->tri_frame[th->tri];
            const float *tt = m->hot_t + (size_t)v * 3;
            v4_store3(t, v4_splat(tt[0]) * tf->T + v4_splat(tt[1]) * tf->N + v4_splat(tt[2]) * tf->B);
        }
        fit_tangent(t, n, x->out_tan + (size_t)v * 3);
    }
}

static void apply_tri(const apply_ctx *x, uint32_t v)
{
    const sm_map *m = x->m;
    const tri_hot *th = &m->hot[v];
    float *op = x->out_pos + (size_t)v * 3, *on = x->out_nrm + (size_t)v * 3;
    if (th->tri == UINT32_MAX) { /* BIND_TRANSLATE */
        uint32_t c = m->tri[v].c[0];
        for (int a = 0; a < 3; a++)
            op[a] = m->rest_pos[(size_t)v * 3 + a] + (x->pos[a][c] - x->rest[a][c]);
        set3(on, m->rest_nrm + (size_t)v * 3);
        if (x->out_tan)
            set3(x->out_tan + (size_t)v * 3, m->rest_tan + (size_t)v * 3);
        return;
    }
    const tri_frame *tf = &m->tri_frame[th->tri & ~HOT_CURVATURE];
    const v4 w0 = v4_splat(th->w[0]), w1 = v4_splat(th->w[1]), w2 = v4_splat(th->w[2]);
    const v4 r = w0 * tf->P[0] + w1 * tf->P[1] + w2 * tf->P[2];
    v4 T = tf->T, N = tf->N, B = tf->B;
    const float *o = th->o, *n = th->n, *tt = m->hot_t ? m->hot_t + (size_t)v * 3 : NULL;
    if (th->tri & HOT_CURVATURE) {
        v4 Nc = w0 * tf->Q[0] + w1 * tf->Q[1] + w2 * tf->Q[2];
        v4 Bc = {0};
        if (v4_norm(&Nc) > 1e-3f)
            Bc = v4_cross(Nc, T);
        if (v4_norm(&Bc) > 1e-3f) {
            T = v4_cross(Bc, Nc);
            N = Nc;
            B = Bc;
        } else { /* this frame keeps the constant basis */
            o = m->tri[v].o;
            n = m->tri[v].n;
            tt = m->tri[v].t;
        }
    }
    /* an orthonormal basis keeps the stored unit normal unit (to rounding) */
    v4_store3(op, r + (v4_splat(o[0]) * T + v4_splat(o[1]) * N + v4_splat(o[2]) * B));
    v4_store3(on, v4_splat(n[0]) * T + v4_splat(n[1]) * N + v4_splat(n[2]) * B);
    /* and so does the tangent, orthogonal to that normal (3.3.4) */
    if (x->out_tan)
        v4_store3(x->out_tan + (size_t)v * 3, v4_splat(tt[0]) * T + v4_splat(tt[1]) * N + v4_splat(tt[2]) * B);
}

/* Each distinct triangle's constant basis (eq. 6) and nodes, this frame. */
static void basis_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    const apply_ctx *x = ctx;
    const sm_map *m = x->m;
    for (size_t t = begin; t < end; t++) {
        const uint32_t *c = m->tris + t * 3;
        tri_frame *tf = &m->tri_frame[t];
        for (int k = 0; k < 3; k++) {
            tf->P[k] = (v4){x->pos[0][c[k]], x->pos[1][c[k]], x->pos[2][c[k]], 0};
            tf->Q[k] = (v4){x->nrm[0][c[k]], x->nrm[1][c[k]], x->nrm[2][c[k]], 0};
        }
        v4 T = tf->P[1] - tf->P[0], Bt = tf->P[2] - tf->P[0];
        v4_norm(&T);
        v4_norm(&Bt);
        v4 N = v4_cross(T, Bt);
        v4_norm(&N);
        tf->T = T;
        tf->N = N;
        tf->B = v4_cross(N, T);
    }
}

/* Displacement of a corner: a node's, or a ghost's of this frame. */
static inline void corner_disp(const apply_ctx *x, int32_t corner, float d[3])
{
    if (corner >= 0) {
        for (int a = 0; a < 3; a++)
            d[a] = x->pos[a][corner] - x->rest[a][corner];
    } else {
        set3(d, x->m->gdisp + (size_t)(-corner - 1) * 3);
    }
}

static void apply_lin(const apply_ctx *x, uint32_t v)
{
    const sm_map *m = x->m;
    const lin_bind *lb = &m->lin[v];
    float *op = x->out_pos + (size_t)v * 3, *on = x->out_nrm + (size_t)v * 3;
    const float u = lb->u[0], w = lb->u[1], s = lb->u[2];
    float disp[3] = {0, 0, 0}, J[3][3] = {{0}}; /* J[axis][component]: d(disp)/d(axis), per h */
    for (int k = 0; k < 8; k++) {
        int bx = k & 1, by = (k >> 1) & 1, bz = k >> 2;
        float fx = bx ? u : 1 - u, fy = by ? w : 1 - w, fz = bz ? s : 1 - s;
        float gx = bx ? 1.0f : -1.0f, gy = by ? 1.0f : -1.0f, gz = bz ? 1.0f : -1.0f;
        float wt = fx * fy * fz, dx = gx * fy * fz, dy = fx * gy * fz, dz = fx * fy * gz;
        float d[3];
        corner_disp(x, lb->corner[k], d);
        for (int a = 0; a < 3; a++) {
            disp[a] += wt * d[a];
            J[0][a] += dx * d[a];
            J[1][a] += dy * d[a];
            J[2][a] += dz * d[a];
        }
    }
    const float ih = 1.0f / m->h;
    for (int a = 0; a < 3; a++) {
        op[a] = m->rest_pos[(size_t)v * 3 + a] + disp[a];
        for (int r = 0; r < 3; r++)
            J[r][a] = J[r][a] * ih + (r == a ? 1.0f : 0.0f);
    }
    /* the cofactor of the Jacobian (columns J[0], J[1], J[2]) maps normals */
    float c0[3], c1[3], c2[3], nn[3];
    f_cross(J[1], J[2], c0);
    f_cross(J[2], J[0], c1);
    f_cross(J[0], J[1], c2);
    for (int a = 0; a < 3; a++)
        nn[a] = lb->n[0] * c0[a] + lb->n[1] * c1[a] + lb->n[2] * c2[a];
    if (f_norm(nn) == 0)
        set3(nn, lb->n);
    set3(on, nn);
    /* the Jacobian itself maps directions in the surface: the tangent,
     * made orthogonal to the mapped normal */
    if (x->out_tan) {
        const float *t0 = m->rest_tan + (size_t)v * 3;
        float t[3];
        for (int a = 0; a < 3; a++)
            t[a] = t0[0] * J[0][a] + t0[1] * J[1][a] + t0[2] * J[2][a];
        fit_tangent(t, nn, x->out_tan + (size_t)v * 3);
    }
}

static void apply_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    const apply_ctx *x = ctx;
    const sm_map *m = x->m;
    if (m->mapping == MR_SPRINGMASS_TRIANGLE_BASIS || m->mapping == MR_SPRINGMASS_TRIANGLE_CURVATURE) {
        /* a vertex's triangle record is anywhere in the table: ask for the
         * one PREFETCH_AHEAD vertices on while this one is mapped */
        for (size_t v = begin; v < end; v++) {
            if (v + PREFETCH_AHEAD < end) {
                uint32_t t = m->hot[v + PREFETCH_AHEAD].tri;
                if (t != UINT32_MAX) {
                    const char *rec = (const char *)&m->tri_frame[t & ~HOT_CURVATURE];
                    __builtin_prefetch(rec);
                    __builtin_prefetch(rec + 64);
                    __builtin_prefetch(rec + sizeof(tri_frame) - 1);
                }
            }
            apply_tri(x, (uint32_t)v);
        }
        return;
    }
    for (size_t v = begin; v < end; v++) {
        switch (m->mapping) {
        case MR_SPRINGMASS_ONE_TO_ONE: apply_one(x, (uint32_t)v); break;
        case MR_SPRINGMASS_TRILINEAR: apply_lin(x, (uint32_t)v); break;
        default: apply_tri(x, (uint32_t)v); break;
        }
    }
}

/* This frame's ghost displacements and triangle bases: what every vertex
 * of the mapping reads. */
static void prepare(apply_ctx *x, const sm_sim *sim, unsigned threads)
{
    sm_map *m = (sm_map *)x->m;
    sm_sim_positions(sim, x->pos);
    sm_sim_rest(sim, x->rest);
    sm_sim_normals(sim, x->nrm);
    const float inv_h = 1.0f / m->h;
    for (size_t q = 0; q < m->ghost_count; q++) {
        const ghost *gh = &m->ghosts[q];
        float D[3][3], d[3];
        ghost_derivatives(gh, x->pos, inv_h, D);
        for (int c = 0; c < 3; c++)
            d[c] = x->pos[c][gh->node] - x->rest[c][gh->node];
        if (gh->far) {
            /* the offset from n turned by n's rotation: the frames of D and of
             * D at rest, orthonormalised (Gram-Schmidt), R R0^T o - o */
            float R[3][3], R0[3][3], o[3] = {0, 0, 0}, local[3], turned[3];
            frame_of(D, R);
            frame_of(gh->rest_d, R0);
            for (int a = 0; a < 3; a++)
                for (int c = 0; c < 3; c++)
                    o[c] += gh->delta[a] * gh->rest_d[a][c];
            for (int a = 0; a < 3; a++)
                local[a] = R0[a][0] * o[0] + R0[a][1] * o[1] + R0[a][2] * o[2];
            for (int c = 0; c < 3; c++) {
                turned[c] = R[0][c] * local[0] + R[1][c] * local[1] + R[2][c] * local[2];
                d[c] += turned[c] - o[c];
            }
        } else {
            for (int c = 0; c < 3; c++)
                for (int a = 0; a < 3; a++)
                    d[c] += gh->delta[a] * (D[a][c] - gh->rest_d[a][c]);
        }
        set3(m->gdisp + q * 3, d);
    }
    if (m->tri_count)
        mr_parallel_for(threads, m->tri_count, 2048, basis_range, x);
}

void sm_map_apply(sm_map *m, const sm_sim *sim, float *positions, float *normals, float *tangents,
                  unsigned threads)
{
    apply_ctx x = {.m = m, .out_pos = positions, .out_nrm = normals, .out_tan = m->rest_tan ? tangents : NULL};
    prepare(&x, sim, threads);
    mr_parallel_for(threads, m->vertex_count, 2048, apply_range, &x);
}

typedef struct sample_ctx {
    apply_ctx x;
    uint32_t stride;
} sample_ctx;

static void sample_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    const sample_ctx *c = ctx;
    for (size_t k = begin; k < end; k++) {
        uint32_t v = (uint32_t)(k * c->stride);
        switch (c->x.m->mapping) {
        case MR_SPRINGMASS_ONE_TO_ONE: apply_one(&c->x, v); break;
        case MR_SPRINGMASS_TRILINEAR: apply_lin(&c->x, v); break;
        default: apply_tri(&c->x, v); break;
        }
    }
}

void sm_map_apply_every(sm_map *m, const sm_sim *sim, uint32_t stride, float *positions,
                        float *normals, unsigned threads)
{
    sample_ctx c = {.x = {.m = m, .out_pos = positions, .out_nrm = normals}, .stride = stride};
    prepare(&c.x, sim, threads);
    size_t samples = stride ? (m->vertex_count + stride - 1) / stride : 0;
    mr_parallel_for(threads, samples, 256, sample_range, &c);
}
