/*
 * test_dmm_seams.c - watertightness of the `dmm` kind where base triangles
 * of different subdivision levels meet (issue 4 part 2: "levels differ by
 * at most one, the finer edge decimated, so no ray passes between them"),
 * through the whole kind: bake with "levels": "adaptive", encode, decode,
 * pose, and either tessellate or trace without tessellation.
 *
 * Subject: the real BCN_Epileptic.X rig refined once (20k triangles) and
 * baked to ~1.3k base triangles at largest level 4 with adaptive levels, at
 * a posed frame of its clip, in both deformations.
 *  1. The bake really mixes levels: at least two levels occur, every shared
 *     base edge joins levels at most one apart, and exactly the finer side
 *     of every mixed edge is decimated.
 *  2. The tessellation has no cracks: welding its vertices by bit pattern,
 *     a micro-edge used by exactly one micro-triangle lies on an open edge
 *     of the base mesh, so their number equals the sum over open base edges
 *     of 2^level. A crack (an undecimated fine edge, or shared-edge vertices
 *     that differ in a bit) adds unmatched micro-edges.
 *  3. No ray leaks: at every micro-edge along a base edge (both endpoints
 *     shared by several base triangles' vertex blocks) two rays aim at its
 *     midpoint from either side of the surface, through the tessellation-free
 *     Embree user geometry; every one must hit. Without decimation the fine
 *     side's odd micro-vertices leave slits exactly there.
 * Then the same three parts where a pixel tolerance ("tolerance_px", issue
 * 16) picks a level per base triangle each frame (dmm_kind.c): the bake at
 * its largest level 4 everywhere, the camera at three distances so the
 * levels traced mix; the frame's levels and decimation must obey part 1's
 * rules, and parts 2 and 3 hold on the surface traced.
 * The figures of each part are reported for `make hard` (hard_report.h).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <cmocka.h>

#include <limits.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "../support/bcn_fixture.h"
#include "anim/pose.h"
#include "kinds/dmm/dmm_bake.h"
#include "kinds/dmm/dmm_encode.h"
#include "kinds/dmm/dmm_kind.h"
#include "kinds/kind.h"

#define HARD_KIND "dmm"
#include "../support/hard_report.h"

#define LEVEL 4u
#define BASE_RATIO 0.0625f

static mr_dmm_params adaptive_desc(mr_dmm_mode mode)
{
    return (mr_dmm_params){.level = LEVEL,
                           .levels = MR_DMM_LEVELS_ADAPTIVE,
                           .base_ratio = BASE_RATIO,
                           .mode = mode,
                           .deform = mode == MR_DMM_INTERPOLATED ? MR_DMM_DEFORM_INTERPOLATED
                                                                 : MR_DMM_DEFORM_BASE};
}

/* ---- base-mesh edges, keyed by vertex pair */

typedef struct edge {
    uint32_t lo, hi, tri, k;
} edge;

static int edge_cmp(const void *x, const void *y)
{
    const edge *a = x, *b = y;
    if (a->lo != b->lo)
        return a->lo < b->lo ? -1 : 1;
    return a->hi < b->hi ? -1 : a->hi > b->hi;
}

static edge *base_edges(const mr_dmm_bake *b)
{
    size_t n = (size_t)b->base_triangle_count * 3;
    edge *e = malloc(n * sizeof *e);
    assert_non_null(e);
    for (uint32_t t = 0; t < b->base_triangle_count; t++)
        for (uint32_t k = 0; k < 3; k++) {
            uint32_t u = b->base_indices[3 * t + k], v = b->base_indices[3 * t + (k + 1) % 3];
            e[3 * t + k] = (edge){u < v ? u : v, u < v ? v : u, t, k};
        }
    qsort(e, n, sizeof *e, edge_cmp);
    return e;
}

/* What part 1 found, over the meshes of an asset. */
typedef struct level_figures {
    uint64_t edges, far_apart; /* shared base edges; those joining levels > 1 apart */
    uint64_t decimation_wrong; /* edge sides decimated but not the finer, or the reverse */
    uint64_t fewest_mixed;     /* the fewest base edges joining two levels in a mesh */
    uint64_t mixed;            /* base edges joining two levels, in all */
    unsigned fewest_levels;    /* the fewest levels a mesh uses */
} level_figures;

/* Part 1 into *lf, and the number of unmatched micro-edges a crack-free
 * tessellation has (open base edges times their triangle's 2^level). */
static uint64_t check_levels(const mr_dmm_bake *b, level_figures *lf)
{
    edge *e = base_edges(b);
    size_t n = (size_t)b->base_triangle_count * 3;
    unsigned per_level[MR_UMESH_MAX_LEVEL + 1] = {0};
    for (uint32_t t = 0; t < b->base_triangle_count; t++)
        per_level[mr_dmm_info_level(b->tri_info[t])]++;
    uint64_t open = 0, mixed = 0;
    for (size_t i = 0, j; i < n; i = j) {
        unsigned lo = 99, hi = 0;
        for (j = i; j < n && e[j].lo == e[i].lo && e[j].hi == e[i].hi; j++) {
            unsigned l = mr_dmm_info_level(b->tri_info[e[j].tri]);
            lo = l < lo ? l : lo;
            hi = l > hi ? l : hi;
        }
        lf->edges += j - i > 1;
        HARD_EXPECT(lf->far_apart, hi - lo <= 1);
        mixed += hi > lo;
        for (size_t m = i; m < j; m++) {
            unsigned l = mr_dmm_info_level(b->tri_info[e[m].tri]);
            bool decimated = mr_dmm_info_decimate(b->tri_info[e[m].tri]) >> e[m].k & 1u;
            HARD_EXPECT(lf->decimation_wrong, decimated == (l > lo));
        }
        if (j - i == 1)
            open += 1u << mr_dmm_info_level(b->tri_info[e[i].tri]);
    }
    unsigned distinct = 0;
    for (unsigned l = 0; l <= MR_UMESH_MAX_LEVEL; l++) {
        distinct += per_level[l] > 0;
        print_message("level %u: %u base triangles\n", l, per_level[l]);
    }
    print_message("%llu base edges join two levels\n", (unsigned long long)mixed);
    lf->fewest_levels = distinct < lf->fewest_levels ? distinct : lf->fewest_levels;
    lf->fewest_mixed = mixed < lf->fewest_mixed ? mixed : lf->fewest_mixed;
    lf->mixed += mixed;
    free(e);
    return open;
}

/* What parts 2 and 3 found in one mode. */
typedef struct seam_figures {
    uint64_t unmatched, want_unmatched; /* micro-edges used once; open base edges' share */
    uint64_t rays, leaks;               /* rays at base-edge micro-edges, those that missed */
} seam_figures;

/* ---- the tessellation, welded by vertex bit pattern */

typedef struct welded {
    uint32_t *id;    /* per vertex: its weld class */
    uint32_t *dups;  /* per class: how many vertices share it */
} welded;

typedef struct keyed_vertex {
    uint32_t bits[3]; /* the position's bit patterns */
    uint32_t index;
} keyed_vertex;

static int keyed_cmp(const void *x, const void *y)
{
    const keyed_vertex *a = x, *b = y;
    for (int k = 0; k < 3; k++)
        if (a->bits[k] != b->bits[k])
            return a->bits[k] < b->bits[k] ? -1 : 1;
    return a->index < b->index ? -1 : a->index > b->index;
}

static welded weld(const mr_trimesh *m)
{
    welded w;
    uint32_t n = m->vertex_count;
    keyed_vertex *order = malloc(n * sizeof *order);
    w.id = malloc(n * sizeof *w.id);
    w.dups = calloc(n, sizeof *w.dups);
    assert_true(order && w.id && w.dups);
    for (uint32_t i = 0; i < n; i++) {
        memcpy(order[i].bits, m->positions + 3 * (size_t)i, sizeof order[i].bits);
        order[i].index = i;
    }
    qsort(order, n, sizeof *order, keyed_cmp);
    uint32_t cls = 0;
    for (uint32_t i = 0; i < n; i++) {
        if (i > 0 && memcmp(order[i - 1].bits, order[i].bits, sizeof order[i].bits) != 0)
            cls++;
        w.id[order[i].index] = cls;
        w.dups[cls]++;
    }
    free(order);
    return w;
}

typedef struct micro_edge {
    uint32_t lo, hi; /* weld classes */
    uint32_t tri;    /* a micro-triangle using it */
    uint32_t va, vb; /* its vertices in that triangle */
} micro_edge;

static int micro_edge_cmp(const void *x, const void *y)
{
    const micro_edge *a = x, *b = y;
    if (a->lo != b->lo)
        return a->lo < b->lo ? -1 : 1;
    if (a->hi != b->hi)
        return a->hi < b->hi ? -1 : 1;
    return a->tri < b->tri ? -1 : a->tri > b->tri;
}

static mr_vec3 vtx(const mr_trimesh *m, uint32_t i)
{
    const float *p = m->positions + 3 * (size_t)i;
    return mr_v3(p[0], p[1], p[2]);
}

static mr_vec3 unit_normal(const mr_trimesh *m, uint32_t tri)
{
    const uint32_t *ix = m->indices + 3 * (size_t)tri;
    mr_vec3 a = vtx(m, ix[0]), b = vtx(m, ix[1]), c = vtx(m, ix[2]);
    mr_vec3 n = mr_v3_cross(mr_v3_sub(b, a), mr_v3_sub(c, a));
    float len = mr_v3_len(n);
    return len > 0 ? mr_v3_scale(n, 1.0f / len) : mr_v3(0, 0, 0);
}

/* Sorted micro-edges (non-degenerate triangles only); *count of them. */
static micro_edge *micro_edges(const mr_trimesh *m, const welded *w, size_t *count)
{
    micro_edge *e = malloc((size_t)m->triangle_count * 3 * sizeof *e);
    assert_non_null(e);
    size_t n = 0;
    for (uint32_t t = 0; t < m->triangle_count; t++)
        for (int k = 0; k < 3; k++) {
            uint32_t a = m->indices[3 * (size_t)t + k], b = m->indices[3 * (size_t)t + (k + 1) % 3];
            uint32_t ca = w->id[a], cb = w->id[b];
            if (ca == cb)
                continue;
            e[n++] = (micro_edge){ca < cb ? ca : cb, ca < cb ? cb : ca, t, a, b};
        }
    qsort(e, n, sizeof *e, micro_edge_cmp);
    *count = n;
    return e;
}

static float diagonal(const mr_trimesh *m)
{
    mr_vec3 lo = vtx(m, 0), hi = lo;
    for (uint32_t i = 1; i < m->vertex_count; i++) {
        mr_vec3 p = vtx(m, i);
        lo = mr_v3(fminf(lo.x, p.x), fminf(lo.y, p.y), fminf(lo.z, p.z));
        hi = mr_v3(fmaxf(hi.x, p.x), fmaxf(hi.y, p.y), fmaxf(hi.z, p.z));
    }
    return mr_v3_len(mr_v3_sub(hi, lo));
}

static bool hits(RTCScene scene, mr_vec3 org, mr_vec3 dir)
{
    struct RTCRayHit rh;
    memset(&rh, 0, sizeof rh);
    rh.ray.org_x = org.x, rh.ray.org_y = org.y, rh.ray.org_z = org.z;
    rh.ray.dir_x = dir.x, rh.ray.dir_y = dir.y, rh.ray.dir_z = dir.z;
    rh.ray.tnear = 0.0f;
    rh.ray.tfar = INFINITY;
    rh.ray.mask = 0xFFFFFFFFu;
    rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
    struct RTCIntersectContext ic;
    rtcInitIntersectContext(&ic);
    rtcIntersect1(scene, &ic, &rh);
    return rh.hit.geomID != RTC_INVALID_GEOMETRY_ID;
}

/* Parts 2 and 3 on the object of params in mode `mode`, posed a third into
 * its clip; with a frame (levels of detail: params' tolerance), for its
 * camera, and part 1 on the levels the frame traced into *lf (the bakes in
 * b, per asset mesh, give the base edges). want_open: the unmatched
 * micro-edges a crack-free tessellation has, or UINT64_MAX: count them
 * from the frame's levels. */
static seam_figures check_object(const mr_asset *a, mr_dmm_params params, double tolerance_px,
                                 const mr_geom_frame *frame, mr_dmm_bake *const *b,
                                 level_figures *lf, uint64_t want_open)
{
    seam_figures sf = {.want_unmatched = want_open};
    const mr_kind *ops = &mr_kind_dmm;
    const mr_dmm_mode mode = params.mode;
    mr_object_desc o = {.kind = &mr_kind_dmm, .params = &params, .tolerance_px = tolerance_px};
    mr_geom *g = NULL;
    mr_pose *pose = NULL;
    mr_error err = {0};
    if (ops->create(a, &o, &(mr_kind_context){.cache_dir = NULL, .threads = 0}, &g, &err) < 0)
        fail_msg("create: %s", err.msg);
    /* a frame a third into the clip: limbs bent, so seams are not planar */
    mr_pose_desc pd = {.has_clip = a->clip_count > 0, .clip_index = 0, .speed = 1, .loop = true};
    assert_int_equal(mr_pose_new(a, &pose, &err), MR_OK);
    double t = a->clip_count ? a->clips[0].duration / 3 : 0;
    assert_int_equal(mr_pose_eval(pose, a, &pd, t, &err), MR_OK);
    mr_mat4 id = mr_mat4_identity();
    if (ops->update(g, frame, pose, &id, 2, &err) < 0)
        fail_msg("update: %s", err.msg);
    if (want_open == UINT64_MAX) { /* part 1 on the frame's levels */
        const uint8_t *info = mr_dmm_frame_tri_info(g);
        sf.want_unmatched = 0;
        for (size_t i = 0, t0 = 0; i < a->mesh_count; i++) {
            if (!b[i])
                continue;
            mr_dmm_bake frame_bake = *b[i];
            frame_bake.tri_info = (uint8_t *)info + t0;
            sf.want_unmatched += check_levels(&frame_bake, lf);
            t0 += b[i]->base_triangle_count;
        }
    }
    mr_trimesh m;
    if (ops->tessellate(g, &m, &err) < 0)
        fail_msg("tessellate: %s", err.msg);

    /* 2. cracks in the tessellation */
    welded w = weld(&m);
    size_t ne = 0;
    micro_edge *e = micro_edges(&m, &w, &ne);
    uint64_t once = 0;
    for (size_t i = 0, j; i < ne; i = j) {
        for (j = i; j < ne && e[j].lo == e[i].lo && e[j].hi == e[i].hi; j++)
            ;
        once += j - i == 1;
    }
    print_message("mode %d: %u micro-triangles, %llu unmatched micro-edges (open base edges give "
                  "%llu)\n",
                  (int)mode, m.triangle_count, (unsigned long long)once,
                  (unsigned long long)sf.want_unmatched);
    sf.unmatched = once;

    /* 3. rays at every micro-edge along a base edge, from both sides,
     * through the tessellation-free traversal */
    RTCDevice dev = rtcNewDevice(NULL);
    RTCScene scene = rtcNewScene(dev);
    rtcSetSceneFlags(scene, RTC_SCENE_FLAG_ROBUST);
    if (ops->attach(g, dev, scene, 0, RTC_BUILD_QUALITY_MEDIUM, &err) < 0)
        fail_msg("attach: %s", err.msg);
    ops->commit(g);
    rtcCommitScene(scene);
    float offset = 1e-3f * diagonal(&m);
    uint64_t rays = 0, leaks = 0;
    for (size_t i = 0, j; i < ne; i = j) {
        for (j = i; j < ne && e[j].lo == e[i].lo && e[j].hi == e[i].hi; j++)
            ;
        if (j - i != 2 || w.dups[e[i].lo] < 2 || w.dups[e[i].hi] < 2)
            continue; /* inside a base triangle, or not a two-sided edge */
        mr_vec3 n = mr_v3_add(unit_normal(&m, e[i].tri), unit_normal(&m, e[i + 1].tri));
        float len = mr_v3_len(n);
        if (!(len > 0.1f))
            continue; /* a knife edge: no side to aim from */
        n = mr_v3_scale(n, 1.0f / len);
        mr_vec3 mid = mr_v3_scale(mr_v3_add(vtx(&m, e[i].va), vtx(&m, e[i].vb)), 0.5f);
        for (int side = -1; side <= 1; side += 2) {
            mr_vec3 org = mr_v3_add(mid, mr_v3_scale(n, (float)side * offset));
            rays++;
            if (!hits(scene, org, mr_v3_scale(n, (float)-side)))
                leaks++;
        }
    }
    print_message("mode %d: %llu rays at base-edge micro-edges, %llu leaked\n", (int)mode,
                  (unsigned long long)rays, (unsigned long long)leaks);
    sf.rays = rays;
    sf.leaks = leaks;

    rtcReleaseScene(scene);
    ops->free(g);
    rtcReleaseDevice(dev);
    free(e);
    free(w.id);
    free(w.dups);
    mr_trimesh_free(&m);
    mr_pose_free(pose);
    return sf;
}

static seam_figures check_mode(const mr_asset *a, mr_dmm_mode mode, uint64_t want_open)
{
    return check_object(a, adaptive_desc(mode), 0, NULL, NULL, NULL, want_open);
}

/* The subject: the rig refined once. */
static mr_asset *subject(void)
{
    mr_refine_params rp = {.rounds = 1, .amplitude = 0.004f, .frequency = 12.0f, .octaves = 2};
    return bcn_load_refined(&rp);
}

/* The bake the kind makes of it (same parameters, deterministic). */
static mr_dmm_bake_params subject_bake(bool adaptive)
{
    mr_dmm_bake_params bp = mr_dmm_bake_params_default();
    bp.level = LEVEL;
    bp.adaptive = adaptive;
    bp.target_ratio = BASE_RATIO;
    return bp;
}

static void test_adaptive_levels_are_watertight(void **state)
{
    (void)state;
    mr_asset *a = subject();
    mr_dmm_bake_params bp = subject_bake(true);
    uint64_t open = 0;
    mr_error err = {0};
    level_figures lf = {.fewest_mixed = UINT64_MAX, .fewest_levels = UINT_MAX};
    for (size_t i = 0; i < a->mesh_count; i++) {
        if (a->meshes[i].triangle_count == 0)
            continue;
        mr_dmm_bake *b = NULL;
        if (mr_dmm_bake_run(&a->meshes[i], &bp, &b, &err) != MR_OK)
            fail_msg("bake: %s", err.msg);
        open += check_levels(b, &lf);
        mr_dmm_bake_free(b);
    }
    HARD_CHECK("other", lf.fewest_levels, ">=", 2, "levels the adaptive bake uses, fewest in a mesh");
    HARD_CHECK("other", lf.fewest_mixed, ">", 0,
               "base edges joining two levels, fewest in a mesh (%llu shared edges in all)",
               (unsigned long long)lf.edges);
    HARD_CHECK("other", lf.far_apart, "==", 0, "shared base edges joining levels more than 1 apart");
    HARD_CHECK("other", lf.decimation_wrong, "==", 0,
               "base-edge sides decimated though not the finer, or finer and not decimated");
    const mr_dmm_mode modes[2] = {MR_DMM_BASE, MR_DMM_INTERPOLATED};
    for (int k = 0; k < 2; k++) {
        const char *name = k ? "interpolated" : "base";
        seam_figures sf = check_mode(a, modes[k], open);
        HARD_CHECK("leaks", (double)sf.unmatched - (double)sf.want_unmatched, "==", 0,
                   "%s: cracks, micro-edges used once beyond the open base edges' %llu", name,
                   (unsigned long long)sf.want_unmatched);
        HARD_CHECK("leaks", sf.leaks, "==", 0, "%s: rays at base-edge micro-edges that leaked (of %llu)",
                   name, (unsigned long long)sf.rays);
        HARD_CHECK("other", sf.rays, ">", 1000, "%s: rays at base-edge micro-edges", name);
    }
    mr_asset_free(a);
}

/* Levels of detail: the bake at level 4 everywhere ("uniform"), a frame
 * of 640x360 with the camera in front of the dancer at 6, 3 and 1.5 times
 * its height, tolerance 1 px: each base triangle at its own level. */
static void test_lod_levels_are_watertight(void **state)
{
    (void)state;
    mr_asset *a = subject();
    mr_dmm_bake_params bp = subject_bake(false);
    mr_error err = {0};
    mr_dmm_bake **b = calloc(a->mesh_count, sizeof *b);
    assert_non_null(b);
    mr_vec3 lo = mr_v3(INFINITY, INFINITY, INFINITY), hi = mr_v3(-INFINITY, -INFINITY, -INFINITY);
    for (size_t i = 0; i < a->mesh_count; i++) {
        const mr_mesh *m = &a->meshes[i];
        for (uint32_t v = 0; v < m->vertex_count; v++) {
            mr_vec3 p = mr_v3(m->positions[3 * v], m->positions[3 * v + 1], m->positions[3 * v + 2]);
            lo = mr_v3_min(lo, p);
            hi = mr_v3_max(hi, p);
        }
        if (m->triangle_count && mr_dmm_bake_run(m, &bp, &b[i], &err) != MR_OK)
            fail_msg("bake: %s", err.msg);
    }
    mr_vec3 centre = mr_v3_scale(mr_v3_add(lo, hi), 0.5f);
    float height = hi.y - lo.y;
    level_figures lf = {.fewest_mixed = UINT64_MAX, .fewest_levels = UINT_MAX};
    uint64_t rays = 0, leaks = 0, cracks = 0;
    const float away[3] = {6, 3, 1.5f};
    for (int k = 0; k < 2; k++)
        for (int d = 0; d < 3; d++) {
            mr_dmm_params p = adaptive_desc(k ? MR_DMM_INTERPOLATED : MR_DMM_BASE);
            p.levels = MR_DMM_LEVELS_UNIFORM;
            mr_geom_frame f = {.width = 640, .height = 360,
                               .camera = {mr_v3_add(centre, mr_v3(0, 0, away[d] * height)),
                                          mr_quat_identity(), 0.7f}};
            print_message("%s, camera %.1f heights away:\n", k ? "interpolated" : "base", away[d]);
            seam_figures sf = check_object(a, p, 1.0, &f, b, &lf, UINT64_MAX);
            cracks += (uint64_t)llabs((long long)sf.unmatched - (long long)sf.want_unmatched);
            rays += sf.rays;
            leaks += sf.leaks;
        }
    HARD_CHECK("other", lf.mixed, ">", 1000, "levels of detail: base edges joining two levels, "
               "over the frames (%llu shared edges)", (unsigned long long)lf.edges);
    HARD_CHECK("other", lf.far_apart, "==", 0, "shared base edges joining levels more than 1 apart");
    HARD_CHECK("other", lf.decimation_wrong, "==", 0,
               "base-edge sides decimated though not the finer, or finer and not decimated");
    HARD_CHECK("leaks", cracks, "==", 0, "levels of detail: cracks, micro-edges used once beyond "
               "the open base edges'");
    HARD_CHECK("leaks", leaks, "==", 0, "levels of detail: rays at base-edge micro-edges that "
               "leaked (of %llu)", (unsigned long long)rays);
    for (size_t i = 0; i < a->mesh_count; i++)
        mr_dmm_bake_free(b[i]);
    free(b);
    mr_asset_free(a);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_adaptive_levels_are_watertight),
        cmocka_unit_test(test_lod_levels_are_watertight),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
