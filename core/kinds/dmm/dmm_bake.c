/*
 * dmm_bake.c - detailed mesh -> DMM base mesh + per-micro-vertex
 * displacements (dmm_bake.h). Simplification by meshoptimizer, distances by
 * Embree rays, error report by Embree closest-point queries.
 */
#include "kinds/dmm/dmm_bake.h"

#include <embree3/rtcore.h>
#include <float.h>
#include <meshoptimizer.h>
#include <stdlib.h>
#include <string.h>

#include "kinds/dmm/dmm_encode.h"
#include "kinds/dmm/micromesh.h"
#include "math/closest_mesh.h"
#include "util/parallel.h"

mr_dmm_bake_params mr_dmm_bake_params_default(void)
{
    mr_dmm_bake_params p;
    memset(&p, 0, sizeof p);
    p.target_ratio = 0.05f;
    p.level = 3;
    return p;
}

void mr_dmm_bake_free(mr_dmm_bake *bake)
{
    if (!bake)
        return;
    free(bake->base_positions);
    free(bake->base_directions);
    free(bake->base_indices);
    free(bake->base_source);
    free(bake->joints);
    free(bake->weights);
    free(bake->displacements);
    free(bake->tri_info);
    free(bake);
}

size_t mr_dmm_bake_memory(const mr_dmm_bake *b)
{
    if (!b)
        return 0;
    size_t v = b->base_vertex_count, t = b->base_triangle_count;
    size_t bytes = sizeof *b + v * (6 * sizeof(float) + sizeof(uint32_t)) +
                   t * (3 * sizeof(uint32_t) + sizeof(uint8_t));
    if (b->displacements) /* absent when the bake came from a file */
        bytes += t * (size_t)b->micro_vertex_count * sizeof(float);
    if (b->joints)
        bytes += v * MR_MAX_INFLUENCES * (sizeof(uint16_t) + sizeof(float));
    return bytes;
}

/* ---- double-precision vectors ---- */

typedef struct d3 { double x, y, z; } d3;
static d3 d3_sub(d3 a, d3 b) { return (d3){a.x - b.x, a.y - b.y, a.z - b.z}; }
static double d3_dot(d3 a, d3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }

static d3 vtx(const float *pos, uint32_t i) { return (d3){pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]}; }

/* Distance from p to the detailed mesh; *at (may be NULL) gets the closest
 * point. */
static double closest_point(const mr_closest_mesh *m, mr_vec3 p, d3 *at)
{
    double q[3] = {p.x, p.y, p.z}, c[3];
    double d = mr_closest_mesh_distance(m, q, c);
    if (at)
        *at = (d3){c[0], c[1], c[2]};
    return d;
}

/* ---- per-triangle bake, run in parallel ---- */

typedef struct bake_ctx {
    RTCScene scene;               /* the detailed mesh's (closest) */
    const mr_closest_mesh *closest;
    const float *detail_pos;      /* welded detailed positions */
    const uint32_t *detail_idx;   /* welded detailed indices */
    mr_dmm_bake *bake;
    float max_displacement;       /* the parameter's bound, or INFINITY */
    uint32_t *fallbacks;          /* per base triangle */
    double *sum2;                 /* per base triangle */
    double *maxd;                 /* per base triangle */
    uint32_t *samples;            /* per base triangle: error report samples */
    mr_vec3 *scratch;             /* per worker: micro_vertex_count positions */
    const float *reach;           /* per base vertex: its longest base edge */
    mr_umesh_topology topo;       /* surviving micro-triangles per level and mask */
} bake_ctx;

/* Most surfaces one displacement ray passes through before it gives up
 * looking for one that faces its way (a bound on the work per ray). */
#define MAX_CROSSINGS 16

/* The first crossing of the detailed surface along org + t * sign * dir,
 * 0 <= t <= tfar, where the surface faces the way dir points (its outward
 * normal . dir > 0); INFINITY when there is none. */
static float crossing(const bake_ctx *c, mr_vec3 org, mr_vec3 dir, float sign, float tfar)
{
    float tnear = 0.0f;
    mr_vec3 sd = mr_v3_scale(dir, sign);
    for (int k = 0; k < MAX_CROSSINGS; k++) {
        struct RTCRayHit rh;
        memset(&rh, 0, sizeof rh);
        rh.ray.org_x = org.x, rh.ray.org_y = org.y, rh.ray.org_z = org.z;
        rh.ray.dir_x = sd.x, rh.ray.dir_y = sd.y, rh.ray.dir_z = sd.z;
        rh.ray.tnear = tnear;
        rh.ray.tfar = tfar;
        rh.ray.mask = 0xFFFFFFFFu;
        rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
        struct RTCIntersectContext ic;
        rtcInitIntersectContext(&ic);
        rtcIntersect1(c->scene, &ic, &rh);
        if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID)
            break;
        float t = rh.ray.tfar;
        const uint32_t *ix = c->detail_idx + 3 * (size_t)rh.hit.primID;
        d3 p0 = vtx(c->detail_pos, ix[0]), e1 = d3_sub(vtx(c->detail_pos, ix[1]), p0),
           e2 = d3_sub(vtx(c->detail_pos, ix[2]), p0);
        d3 ng = {e1.y * e2.z - e1.z * e2.y, e1.z * e2.x - e1.x * e2.z, e1.x * e2.y - e1.y * e2.x};
        if (d3_dot(ng, (d3){dir.x, dir.y, dir.z}) > 0)
            return t;
        if (!(t < tfar))
            break;
        tnear = nextafterf(t, INFINITY);
    }
    return INFINITY;
}

static mr_umesh_tri base_tri(const mr_dmm_bake *b, uint32_t t)
{
    mr_umesh_tri tri;
    for (int k = 0; k < 3; k++) {
        uint32_t v = b->base_indices[3 * t + k];
        const float *p = b->base_positions + 3 * v, *d = b->base_directions + 3 * v;
        tri.pos[k] = mr_v3(p[0], p[1], p[2]);
        tri.dir[k] = mr_v3(d[0], d[1], d[2]);
    }
    return tri;
}

/* Step 5 of dmm_bake.h for micro-vertex (a, b) of base triangle t: the
 * search bound (in direction-length units) and the displacement; *unmatched
 * is set when no crossing faced the right way within it. */
static float displacement(const bake_ctx *c, const mr_umesh_tri *tri, const uint32_t *corner,
                          unsigned level, uint32_t a, uint32_t b, bool *unmatched)
{
    mr_vec3 p, d;
    mr_umesh_frame(tri, level, a, b, &p, &d, NULL);
    *unmatched = false;
    float len = sqrtf(mr_v3_dot(d, d));
    if (!(len > 0))
        return 0.0f;
    /* the reach of the corners the micro-vertex depends on (a max, so the
     * two triangles of a shared edge agree bit for bit) */
    uint32_t n = mr_umesh_segments(level);
    float reach = 0;
    if (n - a - b > 0)
        reach = fmaxf(reach, c->reach[corner[0]]);
    if (a > 0)
        reach = fmaxf(reach, c->reach[corner[1]]);
    if (b > 0)
        reach = fmaxf(reach, c->reach[corner[2]]);
    float tfar = fminf(MR_DMM_BAKE_REACH * reach / len, c->max_displacement);
    float tp = crossing(c, p, d, 1.0f, tfar), tn = crossing(c, p, d, -1.0f, tfar);
    if (tp <= tn && tp < INFINITY)
        return tp;
    if (tn < INFINITY)
        return -tn;
    /* no crossing: the height, along d, of the nearest detailed point */
    *unmatched = true;
    d3 q;
    closest_point(c->closest, p, &q);
    double h = d3_dot(d3_sub(q, (d3){p.x, p.y, p.z}), (d3){d.x, d.y, d.z}) / ((double)len * len);
    return (float)fmax(-(double)tfar, fmin((double)tfar, h));
}

static void bake_range(void *vctx, size_t begin, size_t end, unsigned worker)
{
    bake_ctx *c = vctx;
    mr_dmm_bake *b = c->bake;
    mr_vec3 *pts = c->scratch + (size_t)worker * b->micro_vertex_count;
    for (size_t t = begin; t < end; t++) {
        const unsigned level = mr_dmm_info_level(b->tri_info[t]);
        const unsigned decimate = mr_dmm_info_decimate(b->tri_info[t]);
        const uint32_t mvc = mr_umesh_vertex_count(level);
        mr_umesh_tri tri = base_tri(b, (uint32_t)t);
        float *disp = b->displacements + t * b->micro_vertex_count;
        uint32_t fb = 0;
        for (uint32_t i = 0; i < mvc; i++) {
            uint32_t a, bb;
            bool unmatched;
            mr_umesh_vertex_coords(level, i, &a, &bb);
            disp[i] = displacement(c, &tri, b->base_indices + 3 * t, level, a, bb, &unmatched);
            fb += unmatched;
        }
        c->fallbacks[t] = fb;

        /* error report: displaced micro-vertices (collapsed ones where they
         * went) and the surviving micro-triangles' centroids */
        mr_umesh_eval_all(&tri, level, decimate, disp, pts, NULL);
        double s2 = 0, mx = 0;
        for (uint32_t i = 0; i < mvc; i++) {
            double dd = closest_point(c->closest, pts[i], NULL);
            s2 += dd * dd;
            mx = fmax(mx, dd);
        }
        uint32_t mtc = c->topo.count[level][decimate];
        for (uint32_t k = 0; k < mtc; k++) {
            const uint32_t *idx = c->topo.tris[level][decimate] + 3 * k;
            mr_vec3 cen = mr_v3_scale(mr_v3_add(mr_v3_add(pts[idx[0]], pts[idx[1]]), pts[idx[2]]),
                                      1.0f / 3.0f);
            double dd = closest_point(c->closest, cen, NULL);
            s2 += dd * dd;
            mx = fmax(mx, dd);
        }
        c->sum2[t] = s2;
        c->maxd[t] = mx;
        c->samples[t] = mvc + mtc;
    }
}

static bool finite3(const float *p) { return isfinite(p[0]) && isfinite(p[1]) && isfinite(p[2]); }

static int check_input(const mr_mesh *m, const mr_dmm_bake_params *pr, mr_error *err)
{
    if (!m || !pr)
        return mr_error_set(err, MR_ERR_INVALID, "dmm bake: mesh and parameters are required");
    if (pr->level > MR_UMESH_MAX_LEVEL)
        return mr_error_set(err, MR_ERR_INVALID, "dmm bake: level %u is above %u", pr->level,
                            MR_UMESH_MAX_LEVEL);
    if (pr->target_triangles == 0 && !(pr->target_ratio > 0 && pr->target_ratio <= 1))
        return mr_error_set(err, MR_ERR_INVALID,
                            "dmm bake: target_ratio %g must be in (0, 1] when target_triangles is 0",
                            (double)pr->target_ratio);
    if (!(pr->max_error >= 0 && isfinite(pr->max_error)))
        return mr_error_set(err, MR_ERR_INVALID, "dmm bake: max_error must be >= 0 and finite");
    if (!(pr->max_displacement >= 0 && isfinite(pr->max_displacement)))
        return mr_error_set(err, MR_ERR_INVALID,
                            "dmm bake: max_displacement must be >= 0 and finite");
    if (m->vertex_count == 0 || m->triangle_count == 0 || !m->positions || !m->indices)
        return mr_error_set(err, MR_ERR_INVALID, "dmm bake: mesh '%s' has no triangles",
                            m->name ? m->name : "");
    if (m->triangle_count > MR_MAX_ASSET_TRIANGLES || m->vertex_count > MR_MAX_ASSET_VERTICES)
        return mr_error_set(err, MR_ERR_LIMIT, "dmm bake: mesh is above the asset caps");
    for (uint32_t i = 0; i < m->vertex_count; i++)
        if (!finite3(m->positions + 3 * (size_t)i))
            return mr_error_set(err, MR_ERR_INVALID, "dmm bake: vertex %u is not finite", i);
    for (size_t i = 0; i < 3 * (size_t)m->triangle_count; i++)
        if (m->indices[i] >= m->vertex_count)
            return mr_error_set(err, MR_ERR_INVALID, "dmm bake: index %zu (%u) is out of range",
                                i, m->indices[i]);
    return MR_OK;
}

/* Area-weighted vertex normals of the base mesh, unit. A vertex whose
 * weighted sum vanishes (e.g. two opposite faces) takes its first
 * non-degenerate face's normal, and (0, 0, 1) when it has none. */
static bool base_normals(mr_dmm_bake *b)
{
    size_t nv = b->base_vertex_count;
    double *acc = calloc(nv * 3, sizeof(double));
    float *first = calloc(nv * 3, sizeof(float));
    if (!acc || !first) {
        free(acc);
        free(first);
        return false;
    }
    for (uint32_t t = 0; t < b->base_triangle_count; t++) {
        const uint32_t *ix = b->base_indices + 3 * t;
        d3 p0 = vtx(b->base_positions, ix[0]), p1 = vtx(b->base_positions, ix[1]),
           p2 = vtx(b->base_positions, ix[2]);
        d3 e1 = d3_sub(p1, p0), e2 = d3_sub(p2, p0);
        d3 n = {e1.y * e2.z - e1.z * e2.y, e1.z * e2.x - e1.x * e2.z, e1.x * e2.y - e1.y * e2.x};
        double len = sqrt(d3_dot(n, n));
        for (int k = 0; k < 3; k++) {
            double *a = acc + 3 * ix[k];
            a[0] += n.x, a[1] += n.y, a[2] += n.z;
            float *f = first + 3 * ix[k];
            if (len > 0 && f[0] == 0 && f[1] == 0 && f[2] == 0)
                f[0] = (float)(n.x / len), f[1] = (float)(n.y / len), f[2] = (float)(n.z / len);
        }
    }
    for (size_t v = 0; v < nv; v++) {
        mr_vec3 fb = mr_v3(0, 0, 1);
        if (first[3 * v] != 0 || first[3 * v + 1] != 0 || first[3 * v + 2] != 0)
            fb = mr_v3(first[3 * v], first[3 * v + 1], first[3 * v + 2]);
        double *a = acc + 3 * v, len = sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
        /* normalise in double: the sum can be tiny or huge in float; a sum
         * that cancels to (nearly) nothing relative to its faces' areas
         * would give a meaningless direction, but exact cancellation is the
         * only case caught here (hard case for the next stage) */
        mr_vec3 s = len > 0 && isfinite(len)
                        ? mr_v3((float)(a[0] / len), (float)(a[1] / len), (float)(a[2] / len))
                        : fb;
        b->base_directions[3 * v] = s.x;
        b->base_directions[3 * v + 1] = s.y;
        b->base_directions[3 * v + 2] = s.z;
    }
    free(acc);
    free(first);
    return true;
}

static double tri_area(const float *pos, const uint32_t *ix)
{
    d3 p0 = vtx(pos, ix[0]), p1 = vtx(pos, ix[1]), p2 = vtx(pos, ix[2]);
    d3 e1 = d3_sub(p1, p0), e2 = d3_sub(p2, p0);
    d3 n = {e1.y * e2.z - e1.z * e2.y, e1.z * e2.x - e1.x * e2.z, e1.x * e2.y - e1.y * e2.x};
    return 0.5 * sqrt(d3_dot(n, n));
}

/* Step 4 of dmm_bake.h: b->tri_info from the detail's mean triangle area
 * (welded mesh wpos / widx, wi indices). */
static bool assign_levels(mr_dmm_bake *b, const float *wpos, const uint32_t *widx, size_t wi,
                          bool adaptive)
{
    uint32_t nt = b->base_triangle_count;
    uint8_t *level = malloc(nt), *decimate = calloc(nt, 1);
    mr_umesh_edges e = {0};
    bool ok = level && decimate && mr_umesh_edges_init(&e, b->base_indices, nt, NULL) == MR_OK;
    if (ok) {
        double detail = 0;
        for (size_t t = 0; adaptive && t < wi; t += 3)
            detail += tri_area(wpos, widx + t);
        detail /= (double)(wi / 3);
        for (uint32_t t = 0; t < nt; t++) {
            level[t] = (uint8_t)b->level;
            double ratio = tri_area(b->base_positions, b->base_indices + 3 * t) / detail;
            if (adaptive && ratio < INFINITY) /* else (no detail area) the finest */
                level[t] = (uint8_t)(ratio > 1 ? fmin(nearbyint(0.5 * log2(ratio)), b->level) : 0);
        }
        mr_umesh_balance(&e, level, decimate);
        for (uint32_t t = 0; t < nt; t++)
            b->tri_info[t] = mr_dmm_tri_info(level[t], decimate[t]);
    }
    mr_umesh_edges_free(&e);
    free(decimate);
    free(level);
    return ok;
}

int mr_dmm_bake_run(const mr_mesh *detail, const mr_dmm_bake_params *params, mr_dmm_bake **out,
                    mr_error *err)
{
    int rc = MR_OK;
    uint32_t *remap = NULL, *rep = NULL, *widx = NULL, *sidx = NULL, *bmap = NULL;
    float *wpos = NULL, *reach = NULL;
    mr_dmm_bake *b = NULL;
    mr_closest_mesh closest = {0};
    bake_ctx ctx;
    memset(&ctx, 0, sizeof ctx);
    if (out)
        *out = NULL;
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "dmm bake: out is NULL");
    rc = check_input(detail, params, err);
    if (rc < 0)
        return rc;

    /* 1. weld by position (bitwise) */
    size_t nv = detail->vertex_count, ni = 3 * (size_t)detail->triangle_count;
    remap = malloc(nv * sizeof *remap);
    widx = malloc(ni * sizeof *widx);
    sidx = malloc(ni * sizeof *sidx);
    if (!remap || !widx || !sidx)
        goto nomem;
    size_t nw = meshopt_generateVertexRemap(remap, NULL, nv, detail->positions, nv, 3 * sizeof(float));
    wpos = malloc(nw * 3 * sizeof *wpos);
    rep = malloc(nw * sizeof *rep);
    if (!wpos || !rep)
        goto nomem;
    for (size_t i = 0; i < nw; i++)
        rep[i] = UINT32_MAX;
    for (size_t i = 0; i < nv; i++)
        if (rep[remap[i]] == UINT32_MAX) {
            rep[remap[i]] = (uint32_t)i;
            memcpy(wpos + 3 * remap[i], detail->positions + 3 * i, 3 * sizeof(float));
        }
    size_t wi = 0;
    for (size_t t = 0; t < ni; t += 3) {
        uint32_t a = remap[detail->indices[t]], c1 = remap[detail->indices[t + 1]],
                 c2 = remap[detail->indices[t + 2]];
        if (a == c1 || c1 == c2 || c2 == a)
            continue; /* collapsed by the weld */
        widx[wi++] = a, widx[wi++] = c1, widx[wi++] = c2;
    }
    if (wi == 0) {
        rc = mr_error_set(err, MR_ERR_INVALID, "dmm bake: every triangle is degenerate");
        goto cleanup;
    }

    /* 2. simplify */
    size_t target = params->target_triangles ? params->target_triangles
                                             : (size_t)((double)params->target_ratio * (double)(wi / 3));
    if (target < 1)
        target = 1;
    if (target > wi / 3) /* more than there are keeps them all (meshopt_simplify asserts it) */
        target = wi / 3;
    float rerr = 0;
    size_t si = meshopt_simplify(sidx, widx, wi, wpos, nw, 3 * sizeof(float), 3 * target,
                                 params->max_error > 0 ? params->max_error : FLT_MAX, 0, &rerr);

    b = calloc(1, sizeof *b);
    bmap = malloc(nw * sizeof *bmap);
    if (!b || !bmap)
        goto nomem;
    for (size_t i = 0; i < nw; i++)
        bmap[i] = UINT32_MAX;
    b->level = params->level;
    b->micro_vertex_count = mr_umesh_vertex_count(params->level);
    b->simplify_error = rerr * meshopt_simplifyScale(wpos, nw, 3 * sizeof(float));
    b->base_indices = malloc((si ? si : 3) * sizeof(uint32_t));
    if (!b->base_indices)
        goto nomem;
    uint32_t nbv = 0, nbt = 0;
    for (size_t t = 0; t < si; t += 3) {
        if (sidx[t] == sidx[t + 1] || sidx[t + 1] == sidx[t + 2] || sidx[t + 2] == sidx[t])
            continue;
        for (int k = 0; k < 3; k++) {
            uint32_t w = sidx[t + k];
            if (bmap[w] == UINT32_MAX)
                bmap[w] = nbv++;
            b->base_indices[3 * nbt + k] = bmap[w];
        }
        nbt++;
    }
    if (nbt == 0) {
        rc = mr_error_set(err, MR_ERR_INVALID, "dmm bake: simplification left no triangles (raise "
                                                "dmm.base_triangles or dmm.base_ratio)");
        goto cleanup;
    }
    b->base_vertex_count = nbv;
    b->base_triangle_count = nbt;
    b->base_positions = malloc((size_t)nbv * 3 * sizeof(float));
    b->base_directions = malloc((size_t)nbv * 3 * sizeof(float));
    b->base_source = malloc((size_t)nbv * sizeof(uint32_t));
    b->displacements = calloc((size_t)nbt * b->micro_vertex_count, sizeof(float));
    b->tri_info = malloc(nbt);
    if (!b->base_positions || !b->base_directions || !b->base_source || !b->displacements ||
        !b->tri_info)
        goto nomem;
    bool skinned = detail->joint_count > 0 && detail->joints && detail->weights;
    if (skinned) {
        b->joints = malloc((size_t)nbv * MR_MAX_INFLUENCES * sizeof(uint16_t));
        b->weights = malloc((size_t)nbv * MR_MAX_INFLUENCES * sizeof(float));
        if (!b->joints || !b->weights)
            goto nomem;
    }
    for (size_t w = 0; w < nw; w++) {
        uint32_t v = bmap[w];
        if (v == UINT32_MAX)
            continue;
        uint32_t src = rep[w];
        b->base_source[v] = src;
        memcpy(b->base_positions + 3 * (size_t)v, detail->positions + 3 * (size_t)src,
               3 * sizeof(float));
        if (skinned) {
            memcpy(b->joints + (size_t)v * MR_MAX_INFLUENCES,
                   detail->joints + (size_t)src * MR_MAX_INFLUENCES,
                   MR_MAX_INFLUENCES * sizeof(uint16_t));
            memcpy(b->weights + (size_t)v * MR_MAX_INFLUENCES,
                   detail->weights + (size_t)src * MR_MAX_INFLUENCES,
                   MR_MAX_INFLUENCES * sizeof(float));
        }
    }

    /* 3. directions, 4. levels */
    if (!base_normals(b) || !assign_levels(b, wpos, widx, wi, params->adaptive))
        goto nomem;

    /* 4. Embree scene of the (welded) detailed mesh */
    if ((rc = mr_closest_mesh_init(&closest, NULL, wpos, nw, widx, (uint32_t)(wi / 3), "dmm bake",
                                   err)) < 0)
        goto cleanup;

    /* 5. displacements and error report per base triangle */
    unsigned threads = params->threads ? params->threads : mr_cpu_count();
    if (threads > MR_MAX_THREADS)
        threads = MR_MAX_THREADS;
    ctx.scene = closest.scene;
    ctx.closest = &closest;
    ctx.detail_pos = wpos;
    ctx.detail_idx = widx;
    ctx.bake = b;
    ctx.max_displacement = params->max_displacement > 0 ? params->max_displacement : INFINITY;
    reach = calloc(nbv, sizeof *reach);
    if (!reach)
        goto nomem;
    for (uint32_t t = 0; t < nbt; t++)
        for (int k = 0; k < 3; k++) {
            uint32_t u = b->base_indices[3 * t + k], v = b->base_indices[3 * t + (k + 1) % 3];
            d3 ed = d3_sub(vtx(b->base_positions, u), vtx(b->base_positions, v));
            float len = (float)sqrt(d3_dot(ed, ed));
            reach[u] = fmaxf(reach[u], len);
            reach[v] = fmaxf(reach[v], len);
        }
    ctx.reach = reach;

    ctx.fallbacks = calloc(nbt, sizeof *ctx.fallbacks);
    ctx.sum2 = calloc(nbt, sizeof *ctx.sum2);
    ctx.maxd = calloc(nbt, sizeof *ctx.maxd);
    ctx.samples = calloc(nbt, sizeof *ctx.samples);
    ctx.scratch = malloc((size_t)threads * b->micro_vertex_count * sizeof(mr_vec3));
    if (!ctx.fallbacks || !ctx.sum2 || !ctx.maxd || !ctx.samples || !ctx.scratch)
        goto nomem;
    if ((rc = mr_umesh_topology_init(&ctx.topo, b->level, err)) < 0)
        goto cleanup;
    mr_parallel_for(threads, nbt, 4, bake_range, &ctx);
    double s2 = 0, mx = 0;
    for (uint32_t t = 0; t < nbt; t++) {
        b->fallback_count += ctx.fallbacks[t];
        b->sample_count += ctx.samples[t];
        s2 += ctx.sum2[t];
        mx = fmax(mx, ctx.maxd[t]);
    }
    b->rms_distance = sqrt(s2 / (double)b->sample_count);
    b->max_distance = mx;
    *out = b;
    b = NULL;
    goto cleanup;

nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "dmm bake: out of memory");
cleanup:
    free(ctx.fallbacks);
    free(ctx.sum2);
    free(ctx.maxd);
    free(ctx.samples);
    free(ctx.scratch);
    free(reach);
    mr_umesh_topology_free(&ctx.topo);
    mr_closest_mesh_free(&closest);
    mr_dmm_bake_free(b);
    free(remap);
    free(rep);
    free(widx);
    free(sidx);
    free(bmap);
    free(wpos);
    return rc;
}
