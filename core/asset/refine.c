/*
 * refine.c - Loop subdivision with skin weights and procedural detail
 * (refine.h has the rules; this file has the bookkeeping).
 *
 * Per round the state is: welded vertices (double positions so rounds do
 * not accumulate float rounding, plus influences), wedges (output vertices:
 * a welded id and a UV) and triangles of wedge indices. Edges are found by
 * sorting (min, max, triangle, corner) records, which gives a deterministic
 * edge order without hashing; a second sort over wedge pairs finds the
 * distinct wedge edges that become output vertices.
 */
#include "asset/refine.h"
#include "util/dup.h"
#include "util/parallel.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#define GRAIN 1024
#define NOISE_CLAMP 1.0e9 /* lattice coordinates beyond this are clamped (int64 safety) */

/* ------------------------------------------------------------------------ */
/* noise                                                                      */

static uint32_t hash_u32(uint32_t x)
{
    /* An integer finaliser with good avalanche; written from the usual
     * xorshift-multiply pattern. */
    x ^= x >> 16;
    x *= 0x7feb352du;
    x ^= x >> 15;
    x *= 0x846ca68bu;
    x ^= x >> 16;
    return x;
}

static double lattice_grad(int64_t i, int64_t j, int64_t k, uint32_t seed, double x, double y,
                           double z)
{
    uint32_t h = hash_u32(seed ^ 0x9e3779b9u);
    h = hash_u32(h ^ (uint32_t)i);
    h = hash_u32(h ^ (uint32_t)j);
    h = hash_u32(h ^ (uint32_t)k);
    /* The 12 cube-edge directions of improved Perlin noise. */
    switch (h % 12u) {
    case 0: return x + y;
    case 1: return -x + y;
    case 2: return x - y;
    case 3: return -x - y;
    case 4: return x + z;
    case 5: return -x + z;
    case 6: return x - z;
    case 7: return -x - z;
    case 8: return y + z;
    case 9: return -y + z;
    case 10: return y - z;
    default: return -y - z;
    }
}

static double fade(double t) { return t * t * t * (t * (t * 6.0 - 15.0) + 10.0); }
static double lerp(double a, double b, double t) { return a + (b - a) * t; }

static double gradient_noise(double x, double y, double z, uint32_t seed)
{
    x = fmax(-NOISE_CLAMP, fmin(NOISE_CLAMP, x));
    y = fmax(-NOISE_CLAMP, fmin(NOISE_CLAMP, y));
    z = fmax(-NOISE_CLAMP, fmin(NOISE_CLAMP, z));
    double fx = floor(x), fy = floor(y), fz = floor(z);
    int64_t i = (int64_t)fx, j = (int64_t)fy, k = (int64_t)fz;
    double u = x - fx, v = y - fy, w = z - fz;
    double n[8];
    for (int c = 0; c < 8; c++) {
        int di = c & 1, dj = (c >> 1) & 1, dk = (c >> 2) & 1;
        n[c] = lattice_grad(i + di, j + dj, k + dk, seed, u - di, v - dj, w - dk);
    }
    double su = fade(u), sv = fade(v), sw = fade(w);
    double x00 = lerp(n[0], n[1], su), x10 = lerp(n[2], n[3], su);
    double x01 = lerp(n[4], n[5], su), x11 = lerp(n[6], n[7], su);
    return lerp(lerp(x00, x10, sv), lerp(x01, x11, sv), sw);
}

double mr_refine_noise(double x, double y, double z, unsigned octaves, uint32_t seed)
{
    if (!isfinite(x) || !isfinite(y) || !isfinite(z))
        return 0.0;
    if (octaves == 0)
        octaves = 1;
    if (octaves > MR_REFINE_MAX_OCTAVES)
        octaves = MR_REFINE_MAX_OCTAVES;
    double sum = 0.0, total = 0.0, weight = 1.0, scale = 1.0;
    for (unsigned o = 0; o < octaves; o++) {
        /* Each band gets its own seed so bands do not line up at the origin. */
        sum += weight * gradient_noise(x * scale, y * scale, z * scale, seed + o * 0x632be5abu);
        total += weight;
        weight *= 0.5;
        scale *= 2.0;
    }
    double r = sum / total;
    /* Gradient noise with these gradients peaks just about at +-1; clamp so
     * the documented bound holds exactly. */
    return fmax(-1.0, fmin(1.0, r));
}

/* ------------------------------------------------------------------------ */
/* refinement state                                                           */

typedef struct state {
    size_t nv, nw, nt;
    double *pos;      /* 3 per welded vertex */
    uint16_t *joints; /* MR_MAX_INFLUENCES per welded vertex, or NULL (rigid mesh) */
    float *weights;
    uint32_t *weld;   /* per wedge: welded vertex */
    float *uv;        /* 2 per wedge or NULL */
    uint32_t *tri;    /* 3 wedges per triangle */
} state;

static void state_free(state *s)
{
    free(s->pos);
    free(s->joints);
    free(s->weights);
    free(s->weld);
    free(s->uv);
    free(s->tri);
    memset(s, 0, sizeof *s);
}

typedef struct edge_rec {
    uint32_t a, b; /* a <= b */
    uint32_t t;    /* triangle */
    uint32_t k;    /* corner: edge from corner k to k+1 */
} edge_rec;

static int edge_rec_cmp(const void *pa, const void *pb)
{
    const edge_rec *x = pa, *y = pb;
    if (x->a != y->a)
        return x->a < y->a ? -1 : 1;
    if (x->b != y->b)
        return x->b < y->b ? -1 : 1;
    if (x->t != y->t)
        return x->t < y->t ? -1 : 1;
    return x->k < y->k ? -1 : (x->k > y->k);
}

/* Welded edges of one round. */
typedef struct edges {
    size_t ne;
    uint32_t *a, *b;   /* endpoints (welded) */
    uint32_t *faces;   /* number of triangle sides on the edge */
    uint32_t *opp;     /* 2 per edge: opposite welded vertices of the first two faces */
    uint32_t *corner;  /* per triangle corner: its edge */
    /* vertex -> incident edges (CSR), ordered by edge index */
    uint32_t *vstart;  /* nv + 1 */
    uint32_t *vedge;
} edges;

static void edges_free(edges *e)
{
    free(e->a);
    free(e->b);
    free(e->faces);
    free(e->opp);
    free(e->corner);
    free(e->vstart);
    free(e->vedge);
    memset(e, 0, sizeof *e);
}

static int edges_build(const state *s, edges *e)
{
    int rc = MR_ERR_NOMEM;
    size_t nr = s->nt * 3;
    edge_rec *r = malloc(nr * sizeof *r);
    if (!r)
        goto cleanup;
    for (size_t t = 0; t < s->nt; t++)
        for (uint32_t k = 0; k < 3; k++) {
            uint32_t va = s->weld[s->tri[t * 3 + k]], vb = s->weld[s->tri[t * 3 + (k + 1) % 3]];
            r[t * 3 + k] = (edge_rec){va < vb ? va : vb, va < vb ? vb : va, (uint32_t)t, k};
        }
    qsort(r, nr, sizeof *r, edge_rec_cmp);
    size_t ne = 0;
    for (size_t i = 0; i < nr; i++)
        if (i == 0 || r[i].a != r[i - 1].a || r[i].b != r[i - 1].b)
            ne++;
    e->ne = ne;
    e->a = malloc(ne * sizeof *e->a);
    e->b = malloc(ne * sizeof *e->b);
    e->faces = calloc(ne, sizeof *e->faces);
    e->opp = malloc(ne * 2 * sizeof *e->opp);
    e->corner = malloc(nr * sizeof *e->corner);
    e->vstart = calloc(s->nv + 1, sizeof *e->vstart);
    if (!e->a || !e->b || !e->faces || !e->opp || !e->corner || !e->vstart)
        goto cleanup;
    size_t id = 0;
    for (size_t i = 0; i < nr; i++) {
        if (i > 0 && (r[i].a != r[i - 1].a || r[i].b != r[i - 1].b))
            id++;
        e->a[id] = r[i].a;
        e->b[id] = r[i].b;
        uint32_t opp = s->weld[s->tri[(size_t)r[i].t * 3 + (r[i].k + 2) % 3]];
        if (e->faces[id] < 2)
            e->opp[id * 2 + e->faces[id]] = opp;
        e->faces[id]++;
        e->corner[(size_t)r[i].t * 3 + r[i].k] = (uint32_t)id;
    }
    /* Incidence, skipping degenerate edges (a == b): they have no neighbour. */
    for (size_t i = 0; i < ne; i++)
        if (e->a[i] != e->b[i]) {
            e->vstart[e->a[i] + 1]++;
            e->vstart[e->b[i] + 1]++;
        }
    for (size_t v = 0; v < s->nv; v++)
        e->vstart[v + 1] += e->vstart[v];
    e->vedge = malloc((e->vstart[s->nv] ? e->vstart[s->nv] : 1) * sizeof *e->vedge);
    uint32_t *fill = malloc((s->nv ? s->nv : 1) * sizeof *fill);
    if (!e->vedge || !fill) {
        free(fill);
        goto cleanup;
    }
    memcpy(fill, e->vstart, s->nv * sizeof *fill);
    for (size_t i = 0; i < ne; i++)
        if (e->a[i] != e->b[i]) {
            e->vedge[fill[e->a[i]]++] = (uint32_t)i;
            e->vedge[fill[e->b[i]]++] = (uint32_t)i;
        }
    free(fill);
    rc = MR_OK;
cleanup:
    free(r);
    return rc;
}

/* ------------------------------------------------------------------------ */
/* stencils                                                                   */

typedef struct stencil_ctx {
    const state *s;
    const edges *e;
    state *o;              /* next round: welded vertices [0, nv) old, [nv, nv + ne) edges */
    int failed[MR_MAX_THREADS];
} stencil_ctx;

/* Applies a stencil (count parents with coefficients) to the influences and
 * writes the normalised result for welded vertex `dst` of o. */
static int mix_weights(const state *s, const uint32_t *parents, const double *coef, size_t count,
                       state *o, size_t dst)
{
    uint32_t jl[64 * MR_MAX_INFLUENCES];
    float wl[64 * MR_MAX_INFLUENCES];
    uint32_t *j = jl;
    float *w = wl;
    size_t cap = count * MR_MAX_INFLUENCES;
    if (count > 64) {
        j = malloc(cap * sizeof *j);
        w = malloc(cap * sizeof *w);
        if (!j || !w) {
            if (j != jl)
                free(j);
            if (w != wl)
                free(w);
            return MR_ERR_NOMEM;
        }
    }
    size_t n = 0;
    for (size_t p = 0; p < count; p++)
        for (int k = 0; k < MR_MAX_INFLUENCES; k++) {
            float pw = s->weights[(size_t)parents[p] * MR_MAX_INFLUENCES + k];
            if (pw > 0.0f) {
                j[n] = s->joints[(size_t)parents[p] * MR_MAX_INFLUENCES + k];
                w[n] = (float)(coef[p] * pw);
                n++;
            }
        }
    int rc = mr_influences_normalize(j, w, n, &o->joints[dst * MR_MAX_INFLUENCES],
                                     &o->weights[dst * MR_MAX_INFLUENCES]);
    if (j != jl)
        free(j);
    if (w != wl)
        free(w);
    return rc < 0 ? rc : MR_OK;
}

static double loop_beta(size_t n)
{
    double c = 0.375 + 0.25 * cos(2.0 * 3.14159265358979323846 / (double)n);
    return (0.625 - c * c) / (double)n;
}

static void vertex_rule(void *ctx, size_t begin, size_t end, unsigned worker)
{
    stencil_ctx *c = ctx;
    const state *s = c->s;
    const edges *e = c->e;
    uint32_t par_local[65];
    double coef_local[65];
    for (size_t v = begin; v < end; v++) {
        size_t first = e->vstart[v], n = e->vstart[v + 1] - first;
        size_t crease = 0;
        uint32_t cn[2] = {0, 0};
        for (size_t i = 0; i < n; i++) {
            uint32_t ed = e->vedge[first + i];
            if (e->faces[ed] != 2) {
                if (crease < 2)
                    cn[crease] = e->a[ed] == v ? e->b[ed] : e->a[ed];
                crease++;
            }
        }
        uint32_t *par = par_local;
        double *coef = coef_local;
        size_t count = 1;
        if (n + 1 > 65) {
            par = malloc((n + 1) * sizeof *par);
            coef = malloc((n + 1) * sizeof *coef);
            if (!par || !coef) {
                if (par != par_local)
                    free(par);
                if (coef != coef_local)
                    free(coef);
                c->failed[worker] = 1;
                return;
            }
        }
        par[0] = (uint32_t)v;
        coef[0] = 1.0;
        if (n > 0 && crease == 0) {
            double beta = loop_beta(n);
            coef[0] = 1.0 - (double)n * beta;
            for (size_t i = 0; i < n; i++) {
                uint32_t ed = e->vedge[first + i];
                par[count] = e->a[ed] == v ? e->b[ed] : e->a[ed];
                coef[count++] = beta;
            }
        } else if (crease == 2) {
            coef[0] = 0.75;
            par[1] = cn[0];
            par[2] = cn[1];
            coef[1] = coef[2] = 0.125;
            count = 3;
        }
        double p[3] = {0, 0, 0};
        for (size_t i = 0; i < count; i++)
            for (int d = 0; d < 3; d++)
                p[d] += coef[i] * s->pos[(size_t)par[i] * 3 + d];
        memcpy(&c->o->pos[v * 3], p, sizeof p);
        if (s->joints && mix_weights(s, par, coef, count, c->o, v) < 0)
            c->failed[worker] = 1;
        if (par != par_local)
            free(par);
        if (coef != coef_local)
            free(coef);
    }
}

static void edge_rule(void *ctx, size_t begin, size_t end, unsigned worker)
{
    stencil_ctx *c = ctx;
    const state *s = c->s;
    const edges *e = c->e;
    for (size_t i = begin; i < end; i++) {
        uint32_t par[4] = {e->a[i], e->b[i], 0, 0};
        double coef[4] = {0.5, 0.5, 0, 0};
        size_t count = 2;
        if (e->a[i] == e->b[i]) {
            coef[0] = 1.0;
            count = 1;
        } else if (e->faces[i] == 2) {
            par[2] = e->opp[i * 2];
            par[3] = e->opp[i * 2 + 1];
            coef[0] = coef[1] = 0.375;
            coef[2] = coef[3] = 0.125;
            count = 4;
        }
        double p[3] = {0, 0, 0};
        for (size_t k = 0; k < count; k++)
            for (int d = 0; d < 3; d++)
                p[d] += coef[k] * s->pos[(size_t)par[k] * 3 + d];
        size_t dst = s->nv + i;
        memcpy(&c->o->pos[dst * 3], p, sizeof p);
        if (s->joints && mix_weights(s, par, coef, count, c->o, dst) < 0)
            c->failed[worker] = 1;
    }
}

/* One Loop round: s -> o. */
static int loop_round(const state *s, state *o, unsigned threads, mr_error *err)
{
    int rc = MR_OK;
    edges e = {0};
    edge_rec *r = NULL;
    uint32_t *wedge_edge = NULL;
    memset(o, 0, sizeof *o);
    if ((rc = edges_build(s, &e)) < 0)
        goto nomem;
    size_t nr = s->nt * 3;
    if (s->nt > MR_MAX_ASSET_TRIANGLES / 4 || s->nv + e.ne > MR_MAX_ASSET_VERTICES) {
        rc = mr_error_set(err, MR_ERR_LIMIT,
                          "refine: the next round would exceed %u triangles or %u vertices",
                          MR_MAX_ASSET_TRIANGLES, MR_MAX_ASSET_VERTICES);
        goto cleanup;
    }

    /* Distinct wedge edges: each becomes one output vertex. */
    r = malloc(nr * sizeof *r);
    wedge_edge = malloc(nr * sizeof *wedge_edge);
    if (!r || !wedge_edge)
        goto nomem;
    for (size_t t = 0; t < s->nt; t++)
        for (uint32_t k = 0; k < 3; k++) {
            uint32_t wa = s->tri[t * 3 + k], wb = s->tri[t * 3 + (k + 1) % 3];
            r[t * 3 + k] = (edge_rec){wa < wb ? wa : wb, wa < wb ? wb : wa, (uint32_t)t, k};
        }
    qsort(r, nr, sizeof *r, edge_rec_cmp);
    size_t nwe = 0;
    for (size_t i = 0; i < nr; i++) {
        if (i > 0 && (r[i].a != r[i - 1].a || r[i].b != r[i - 1].b))
            nwe++;
        wedge_edge[(size_t)r[i].t * 3 + r[i].k] = (uint32_t)nwe;
    }
    if (nr > 0)
        nwe++;
    if (s->nw + nwe > MR_MAX_ASSET_VERTICES) {
        rc = mr_error_set(err, MR_ERR_LIMIT, "refine: the next round would exceed %u vertices",
                          MR_MAX_ASSET_VERTICES);
        goto cleanup;
    }

    o->nv = s->nv + e.ne;
    o->nw = s->nw + nwe;
    o->nt = s->nt * 4;
    o->pos = malloc(o->nv * 3 * sizeof *o->pos);
    o->weld = malloc(o->nw * sizeof *o->weld);
    o->tri = malloc(o->nt * 3 * sizeof *o->tri);
    if (!o->pos || !o->weld || !o->tri)
        goto nomem;
    if (s->uv && !(o->uv = malloc(o->nw * 2 * sizeof *o->uv)))
        goto nomem;
    if (s->joints) {
        o->joints = malloc(o->nv * MR_MAX_INFLUENCES * sizeof *o->joints);
        o->weights = malloc(o->nv * MR_MAX_INFLUENCES * sizeof *o->weights);
        if (!o->joints || !o->weights)
            goto nomem;
    }

    stencil_ctx *c = calloc(1, sizeof *c);
    if (!c)
        goto nomem;
    c->s = s;
    c->e = &e;
    c->o = o;
    mr_parallel_for(threads, s->nv, GRAIN, vertex_rule, c);
    mr_parallel_for(threads, e.ne, GRAIN, edge_rule, c);
    int failed = 0;
    for (unsigned k = 0; k < MR_MAX_THREADS; k++)
        failed |= c->failed[k];
    free(c);
    if (failed)
        goto nomem;

    /* Wedges: old ones keep their index and UV; edge wedges follow. */
    memcpy(o->weld, s->weld, s->nw * sizeof *o->weld);
    if (s->uv)
        memcpy(o->uv, s->uv, s->nw * 2 * sizeof *o->uv);
    for (size_t t = 0; t < s->nt; t++)
        for (size_t k = 0; k < 3; k++) {
            size_t w = s->nw + wedge_edge[t * 3 + k];
            o->weld[w] = (uint32_t)(s->nv + e.corner[t * 3 + k]);
            if (s->uv) {
                uint32_t wa = s->tri[t * 3 + k], wb = s->tri[t * 3 + (k + 1) % 3];
                /* Fixed operand order (smaller wedge first) so both
                 * triangles on the edge write the same bits. */
                uint32_t lo = wa < wb ? wa : wb, hi = wa < wb ? wb : wa;
                o->uv[w * 2] = 0.5f * (s->uv[lo * 2] + s->uv[hi * 2]);
                o->uv[w * 2 + 1] = 0.5f * (s->uv[lo * 2 + 1] + s->uv[hi * 2 + 1]);
            }
        }
    /* 1:4 split, children keep the parent's winding. */
    for (size_t t = 0; t < s->nt; t++) {
        uint32_t a = s->tri[t * 3], b = s->tri[t * 3 + 1], cc = s->tri[t * 3 + 2];
        uint32_t ab = (uint32_t)(s->nw + wedge_edge[t * 3]);
        uint32_t bc = (uint32_t)(s->nw + wedge_edge[t * 3 + 1]);
        uint32_t ca = (uint32_t)(s->nw + wedge_edge[t * 3 + 2]);
        uint32_t *d = &o->tri[t * 12];
        d[0] = a, d[1] = ab, d[2] = ca;
        d[3] = ab, d[4] = b, d[5] = bc;
        d[6] = ca, d[7] = bc, d[8] = cc;
        d[9] = ab, d[10] = bc, d[11] = ca;
    }
    goto cleanup;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "refine: out of memory");
cleanup:
    if (rc < 0)
        state_free(o);
    free(r);
    free(wedge_edge);
    edges_free(&e);
    return rc;
}

/* ------------------------------------------------------------------------ */
/* welding                                                                    */

typedef struct weld_item {
    float x, y, z;
    uint32_t index;
} weld_item;

static int weld_cmp(const void *pa, const void *pb)
{
    const weld_item *a = pa, *b = pb;
    /* == treats -0 and +0 as equal; positions are finite (checked). */
    if (a->x != b->x)
        return a->x < b->x ? -1 : 1;
    if (a->y != b->y)
        return a->y < b->y ? -1 : 1;
    if (a->z != b->z)
        return a->z < b->z ? -1 : 1;
    return a->index < b->index ? -1 : (a->index > b->index);
}

/* Builds the round-0 state from the input mesh. */
static int weld(const mr_mesh *m, state *s, mr_error *err)
{
    int rc = MR_OK;
    size_t nw = m->vertex_count, nt = m->triangle_count;
    weld_item *it = malloc(nw * sizeof *it);
    uint32_t *rep = NULL; /* welded vertex -> first wedge (lowest index) */
    if (!it)
        goto nomem;
    for (size_t i = 0; i < nw; i++)
        it[i] = (weld_item){m->positions[i * 3], m->positions[i * 3 + 1],
                            m->positions[i * 3 + 2], (uint32_t)i};
    qsort(it, nw, sizeof *it, weld_cmp);
    s->nw = nw;
    s->nt = nt;
    s->weld = malloc(nw * sizeof *s->weld);
    s->tri = malloc(nt * 3 * sizeof *s->tri);
    rep = malloc(nw * sizeof *rep);
    if (!s->weld || !s->tri || !rep)
        goto nomem;
    /* Welded ids in order of first appearance in the input, so they do not
     * depend on the sort. */
    uint32_t *group = malloc(nw * sizeof *group); /* wedge -> first wedge of its group */
    if (!group)
        goto nomem;
    for (size_t i = 0; i < nw; i++) {
        bool same = i > 0 && it[i].x == it[i - 1].x && it[i].y == it[i - 1].y &&
                    it[i].z == it[i - 1].z;
        group[it[i].index] = same ? group[it[i - 1].index] : it[i].index;
    }
    size_t nv = 0;
    for (size_t i = 0; i < nw; i++) {
        if (group[i] == i) {
            rep[nv] = (uint32_t)i;
            s->weld[i] = (uint32_t)nv++;
        } else {
            s->weld[i] = s->weld[group[i]]; /* group[i] < i: already numbered */
        }
    }
    free(group);
    s->nv = nv;
    memcpy(s->tri, m->indices, nt * 3 * sizeof *s->tri);
    s->pos = malloc(nv * 3 * sizeof *s->pos);
    if (!s->pos)
        goto nomem;
    for (size_t v = 0; v < nv; v++)
        for (int d = 0; d < 3; d++)
            s->pos[v * 3 + d] = m->positions[(size_t)rep[v] * 3 + d];
    if (m->uvs) {
        if (!(s->uv = malloc(nw * 2 * sizeof *s->uv)))
            goto nomem;
        memcpy(s->uv, m->uvs, nw * 2 * sizeof *s->uv);
    }
    if (m->joint_count > 0 && m->joints && m->weights) {
        s->joints = malloc(nv * MR_MAX_INFLUENCES * sizeof *s->joints);
        s->weights = malloc(nv * MR_MAX_INFLUENCES * sizeof *s->weights);
        if (!s->joints || !s->weights)
            goto nomem;
        /* Average the influences of all wedges of a welded vertex (they are
         * normally equal). Wedges are visited in index order per group. */
        uint32_t *cnt = calloc(nv, sizeof *cnt);
        if (!cnt)
            goto nomem;
        for (size_t i = 0; i < nw; i++)
            cnt[s->weld[i]]++;
        for (size_t v = 0; v < nv; v++) {
            if (cnt[v] == 1) {
                memcpy(&s->joints[v * MR_MAX_INFLUENCES], &m->joints[(size_t)rep[v] * MR_MAX_INFLUENCES],
                       MR_MAX_INFLUENCES * sizeof *s->joints);
                memcpy(&s->weights[v * MR_MAX_INFLUENCES],
                       &m->weights[(size_t)rep[v] * MR_MAX_INFLUENCES],
                       MR_MAX_INFLUENCES * sizeof *s->weights);
            }
        }
        /* Groups of several wedges: gather from the sorted items, where a
         * group is contiguous. */
        for (size_t i = 0; i < nw;) {
            size_t j = i + 1;
            while (j < nw && s->weld[it[j].index] == s->weld[it[i].index])
                j++;
            if (j - i > 1) {
                size_t n = (j - i) * MR_MAX_INFLUENCES;
                uint32_t *jj = malloc(n * sizeof *jj);
                float *ww = malloc(n * sizeof *ww);
                int r2 = MR_ERR_NOMEM;
                if (jj && ww) {
                    for (size_t g = i; g < j; g++)
                        for (int k = 0; k < MR_MAX_INFLUENCES; k++) {
                            size_t src = (size_t)it[g].index * MR_MAX_INFLUENCES + k;
                            jj[(g - i) * MR_MAX_INFLUENCES + k] = m->joints[src];
                            ww[(g - i) * MR_MAX_INFLUENCES + k] = m->weights[src];
                        }
                    size_t v = s->weld[it[i].index];
                    r2 = mr_influences_normalize(jj, ww, n, &s->joints[v * MR_MAX_INFLUENCES],
                                                 &s->weights[v * MR_MAX_INFLUENCES]);
                }
                free(jj);
                free(ww);
                if (r2 < 0) {
                    free(cnt);
                    goto nomem;
                }
            }
            i = j;
        }
        free(cnt);
    }
    goto cleanup;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "refine: out of memory");
cleanup:
    free(it);
    free(rep);
    return rc;
}

/* ------------------------------------------------------------------------ */
/* normals and detail                                                         */

/* Area-weighted unit normals per welded vertex (3 doubles each); +Z where
 * undefined, as the importer does. */
static int welded_normals(const state *s, double *out)
{
    memset(out, 0, s->nv * 3 * sizeof *out);
    for (size_t t = 0; t < s->nt; t++) {
        uint32_t v[3];
        for (int k = 0; k < 3; k++)
            v[k] = s->weld[s->tri[t * 3 + k]];
        const double *a = &s->pos[v[0] * 3], *b = &s->pos[v[1] * 3], *c = &s->pos[v[2] * 3];
        double e1[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]};
        double e2[3] = {c[0] - a[0], c[1] - a[1], c[2] - a[2]};
        double n[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                       e1[0] * e2[1] - e1[1] * e2[0]};
        for (int k = 0; k < 3; k++)
            for (int d = 0; d < 3; d++)
                out[(size_t)v[k] * 3 + d] += n[d];
    }
    for (size_t i = 0; i < s->nv; i++) {
        double *n = &out[i * 3];
        double len = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
        if (len > 0.0 && isfinite(len)) {
            n[0] /= len;
            n[1] /= len;
            n[2] /= len;
        } else {
            n[0] = n[1] = 0.0;
            n[2] = 1.0;
        }
    }
    return MR_OK;
}

typedef struct detail_ctx {
    state *s;
    const double *normals;
    const mr_refine_params *p;
} detail_ctx;

static void detail_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    detail_ctx *c = ctx;
    double f = c->p->frequency, amp = c->p->amplitude;
    for (size_t v = begin; v < end; v++) {
        double *p = &c->s->pos[v * 3];
        double d = amp * mr_refine_noise(p[0] * f, p[1] * f, p[2] * f, c->p->octaves, c->p->seed);
        for (int k = 0; k < 3; k++)
            p[k] += d * c->normals[v * 3 + k];
    }
}

/* ------------------------------------------------------------------------ */
/* public                                                                     */

void mr_refine_mesh_free(mr_mesh *m) { mr_mesh_release(m); }

static int check_input(const mr_mesh *in, const mr_refine_params *p, mr_error *err)
{
    if (!in || !p)
        return mr_error_set(err, MR_ERR_INVALID, "refine: NULL mesh or params");
    const char *name = in->name ? in->name : "";
    if (p->rounds > MR_REFINE_MAX_ROUNDS)
        return mr_error_set(err, MR_ERR_INVALID, "refine: %u rounds (at most %d)", p->rounds,
                            MR_REFINE_MAX_ROUNDS);
    if (!isfinite(p->amplitude) || !isfinite(p->frequency) || p->frequency < 0.0f ||
        (p->amplitude != 0.0f && !(p->frequency > 0.0f)))
        return mr_error_set(err, MR_ERR_INVALID,
                            "refine: amplitude %g / frequency %g must be finite, frequency > 0",
                            (double)p->amplitude, (double)p->frequency);
    if (p->octaves > MR_REFINE_MAX_OCTAVES)
        return mr_error_set(err, MR_ERR_INVALID, "refine: %u octaves (at most %d)", p->octaves,
                            MR_REFINE_MAX_OCTAVES);
    if (in->vertex_count == 0 || in->triangle_count == 0 || !in->positions || !in->indices)
        return mr_error_set(err, MR_ERR_INVALID, "refine: mesh '%s' has no triangles", name);
    if (in->vertex_count > MR_MAX_ASSET_VERTICES || in->triangle_count > MR_MAX_ASSET_TRIANGLES)
        return mr_error_set(err, MR_ERR_LIMIT, "refine: mesh '%s' exceeds the caps", name);
    for (size_t i = 0; i < (size_t)in->vertex_count * 3; i++)
        if (!isfinite(in->positions[i]))
            return mr_error_set(err, MR_ERR_INVALID,
                                "refine: mesh '%s' vertex %zu has a non-finite position", name,
                                i / 3);
    for (size_t i = 0; i < (size_t)in->triangle_count * 3; i++)
        if (in->indices[i] >= in->vertex_count)
            return mr_error_set(err, MR_ERR_INVALID,
                                "refine: mesh '%s' triangle %zu uses vertex %u of %u", name, i / 3,
                                in->indices[i], in->vertex_count);
    if (in->joint_count > 0) {
        if (!in->joint_nodes || !in->inverse_bind || !in->joints || !in->weights)
            return mr_error_set(err, MR_ERR_INVALID, "refine: mesh '%s' has a partial skin",
                                name);
        for (size_t i = 0; i < (size_t)in->vertex_count * MR_MAX_INFLUENCES; i++)
            if (in->weights[i] > 0.0f && in->joints[i] >= in->joint_count)
                return mr_error_set(err, MR_ERR_INVALID,
                                    "refine: mesh '%s' vertex %zu names joint %u of %u", name,
                                    i / MR_MAX_INFLUENCES, in->joints[i], in->joint_count);
    }
    return MR_OK;
}

int mr_refine_mesh(const mr_mesh *in, const mr_refine_params *params, mr_mesh *out,
                   mr_error *err)
{
    int rc = MR_OK;
    state cur = {0}, next = {0};
    double *nrm = NULL;
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "refine: out is NULL");
    memset(out, 0, sizeof *out);
    if ((rc = check_input(in, params, err)) < 0)
        return rc;
    bool identity = params->rounds == 0 && params->amplitude == 0.0f;
    /* Copy the input's normals only when nothing moved and it has them. */
    bool copy_normals = identity && in->normals;
    bool skinned = in->joint_count > 0;

    if ((rc = weld(in, &cur, err)) < 0)
        goto cleanup;
    for (unsigned r = 0; r < params->rounds; r++) {
        if ((rc = loop_round(&cur, &next, params->threads, err)) < 0)
            goto cleanup;
        state_free(&cur);
        cur = next;
        memset(&next, 0, sizeof next);
    }
    if (!copy_normals) {
        if (!(nrm = malloc(cur.nv * 3 * sizeof *nrm)))
            goto nomem;
        if (params->amplitude != 0.0f) {
            welded_normals(&cur, nrm);
            detail_ctx dc = {&cur, nrm, params};
            mr_parallel_for(params->threads, cur.nv, GRAIN, detail_range, &dc);
        }
        welded_normals(&cur, nrm);
    }

    /* Output. */
    out->node = in->node;
    out->vertex_count = (uint32_t)cur.nw;
    out->triangle_count = (uint32_t)cur.nt;
    out->name = mr_strdup(in->name);
    out->positions = malloc(cur.nw * 3 * sizeof(float));
    out->normals = malloc(cur.nw * 3 * sizeof(float));
    out->indices = mr_memdup(cur.tri, cur.nt * 3 * sizeof(uint32_t));
    if ((in->name && !out->name) || !out->positions || !out->normals || !out->indices)
        goto nomem;
    if (cur.uv && !(out->uvs = mr_memdup(cur.uv, cur.nw * 2 * sizeof(float))))
        goto nomem;
    for (size_t w = 0; w < cur.nw; w++) {
        size_t v = cur.weld[w];
        for (int d = 0; d < 3; d++) {
            out->positions[w * 3 + d] = (float)cur.pos[v * 3 + d];
            out->normals[w * 3 + d] = copy_normals ? in->normals[w * 3 + d] : (float)nrm[v * 3 + d];
        }
    }
    if (mr_mesh_tangents(out) < 0) /* the refined surface's own, from its uvs */
        goto nomem;
    if (skinned) {
        out->joint_count = in->joint_count;
        out->joint_nodes = mr_memdup(in->joint_nodes, in->joint_count * sizeof(int));
        out->inverse_bind = mr_memdup(in->inverse_bind, in->joint_count * sizeof(mr_mat4));
        out->joints = malloc(cur.nw * MR_MAX_INFLUENCES * sizeof *out->joints);
        out->weights = malloc(cur.nw * MR_MAX_INFLUENCES * sizeof *out->weights);
        if (!out->joint_nodes || !out->inverse_bind || !out->joints || !out->weights)
            goto nomem;
        for (size_t w = 0; w < cur.nw; w++) {
            /* Without rounds the input wedges keep their own influences. */
            const uint16_t *js = params->rounds == 0
                                     ? &in->joints[w * MR_MAX_INFLUENCES]
                                     : &cur.joints[(size_t)cur.weld[w] * MR_MAX_INFLUENCES];
            const float *ws = params->rounds == 0
                                  ? &in->weights[w * MR_MAX_INFLUENCES]
                                  : &cur.weights[(size_t)cur.weld[w] * MR_MAX_INFLUENCES];
            memcpy(&out->joints[w * MR_MAX_INFLUENCES], js, MR_MAX_INFLUENCES * sizeof *js);
            memcpy(&out->weights[w * MR_MAX_INFLUENCES], ws, MR_MAX_INFLUENCES * sizeof *ws);
        }
    }
    goto cleanup;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "refine: out of memory");
cleanup:
    if (rc < 0)
        mr_refine_mesh_free(out);
    state_free(&cur);
    state_free(&next);
    free(nrm);
    return rc;
}

/* ------------------------------------------------------------------------ */
/* the refined asset                                                          */

int mr_refine_asset(const mr_asset *in, const mr_refine_params *params, mr_asset **out,
                    mr_error *err)
{
    int rc = MR_OK;
    mr_asset *a = NULL;
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "refine: out is NULL");
    *out = NULL;
    if (!in || !params)
        return mr_error_set(err, MR_ERR_INVALID, "refine: NULL asset or params");
    if (in->image)
        return mr_error_set(err, MR_ERR_INVALID, "%s is an image: only models can be refined",
                            in->path);
    if (mr_asset_copy_shell(in, 0, &a) < 0)
        goto nomem;
    if (in->mesh_count) {
        size_t total = 0;
        for (size_t i = 0; i < in->mesh_count; i++) {
            if ((rc = mr_refine_mesh(&in->meshes[i], params, &a->meshes[i], err)) < 0) {
                mr_error_prefix(err, "mesh %zu: ", i);
                goto cleanup;
            }
            total += a->meshes[i].triangle_count;
        }
        a->triangle_count = total;
    }
    *out = a;
    return MR_OK;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "refine: out of memory copying the asset");
cleanup:
    mr_asset_free(a);
    return rc;
}
