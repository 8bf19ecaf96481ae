/*
 * test_svo_instances.c - hard cases of the svo kind's instancing, through
 * the real Embree scene the renderer builds (kind.h ops: create, update,
 * attach, commit, normal): every method with instances at the origin, far
 * from it (1e5), mirrored, and of zero scale; a one-voxel asset; a pose
 * that throws voxels beyond MR_MAX_COORDINATE; the job's thread count used
 * as given, also beyond the machine's cores, with identical hits; a rigid
 * cast with a level of detail the same through Embree, one ray or a
 * packet at a time, as every piece walked in turn (the dancer).
 *
 * The asset is a unit cube voxelised at depth 4 (voxels of 1/16, a little
 * more since the voxel cube is padded); rays come straight at each
 * instance's +z face from outside. Tolerances:
 *  - hit distance: the voxel surface of a surface voxelisation lies between
 *    the mesh face and one voxel outside it (conservative cells); resampling
 *    aligns the deformed boxes to the world octree's grid, which moves them
 *    out by up to one more cell (resize: half a cell of the level above;
 *    emit: a cell of the box's level), so the hit is within 2.5 voxels
 *    outside the face (+1e-3 for rounding);
 *    at 1e5 the float spacing is 0.0078 and Embree's ray transform adds a
 *    few ulps, so 0.02 is allowed there;
 *  - the shading normal of a +z face hit points along +z within 45 degrees
 *    (octahedral normals of the voxels on the face; the cube's edge voxels
 *    take the nearest triangle's normal, which may be a side's).
 * Each case reports its figures for `make hard` (hard_report.h).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "asset/asset.h"
#include "kinds/kind.h"
#include "kinds/svo/svo_kind.h"
#include "kinds/svo/svo_trace.h"
#include "render/camera.h"
#include "util/parallel.h"

#define HARD_KIND "svo"
#define DANCER "/usr/share/assimp/models/X/BCN_Epileptic.X"
#include "../support/hard_report.h"
#include "../support/kind_stat_fixture.h"

static mr_asset *cube(float half)
{
    static const float c[8][3] = {{-1, -1, -1}, {1, -1, -1}, {1, 1, -1}, {-1, 1, -1},
                                  {-1, -1, 1},  {1, -1, 1},  {1, 1, 1},  {-1, 1, 1}};
    static const uint32_t idx[36] = {0, 2, 1, 0, 3, 2, 4, 5, 6, 4, 6, 7, 0, 1, 5, 0, 5, 4,
                                     1, 2, 6, 1, 6, 5, 2, 3, 7, 2, 7, 6, 3, 0, 4, 3, 4, 7};
    float p[24];
    for (int i = 0; i < 8; i++)
        for (int k = 0; k < 3; k++)
            p[i * 3 + k] = c[i][k] * half;
    mr_asset *a = NULL;
    mr_error err = {0};
    assert_int_equal(mr_asset_from_mesh("cube", p, NULL, 8, idx, 12, &a, &err), MR_OK);
    return a;
}

typedef struct scene {
    RTCDevice device;
    RTCScene scene;
    const mr_kind *ops;
    mr_geom *g;
    mr_object_desc desc;
    mr_svo_params params; /* desc.params */
} scene;

/* frame: NULL (no camera: every leaf is selected, the cast has no level
 * of detail), or the frame the object is updated for; tolerance_px its
 * "tolerance_px" (0: none). */
static void build_frame(scene *s, const mr_asset *a, mr_svo_method method, unsigned depth,
                        const mr_mat4 *instances, size_t n, unsigned threads, const mr_geom_frame *frame,
                        double tolerance_px)
{
    memset(s, 0, sizeof *s);
    s->desc.kind = &mr_kind_svo;
    s->desc.params = &s->params;
    s->desc.transform = mr_mat4_identity();
    s->desc.color = mr_v3(0.8f, 0.8f, 0.8f);
    s->desc.tolerance_px = tolerance_px;
    s->params = (mr_svo_params){.depth = depth, .method = method, .delta = 1, .cull = true,
                                .instance_count = n};
    s->params.instances = calloc(n, sizeof *s->params.instances);
    for (size_t k = 0; k < n; k++)
        s->params.instances[k].transform = instances[k];
    mr_error err = {0};
    s->ops = mr_kind_find("svo");
    assert_non_null(s->ops);
    s->device = rtcNewDevice(NULL);
    s->scene = rtcNewScene(s->device);
    rtcSetSceneFlags(s->scene, RTC_SCENE_FLAG_ROBUST);
    if (s->ops->create(a, &s->desc, &(mr_kind_context){.cache_dir = NULL, .threads = 0}, &s->g, &err) < 0)
        fail_msg("create: %s", err.msg);
    assert_int_equal(s->ops->geometry_ids(s->g), method == MR_SVO_RIGID ? n : 1);
    if (s->ops->attach(s->g, s->device, s->scene, 0, RTC_BUILD_QUALITY_MEDIUM, &err) < 0)
        fail_msg("attach: %s", err.msg);
    if (s->ops->update(s->g, frame, NULL, &s->desc.transform, threads, &err) < 0)
        fail_msg("update: %s", err.msg);
    s->ops->commit(s->g);
    rtcCommitScene(s->scene);
    assert_int_equal(rtcGetDeviceError(s->device), RTC_ERROR_NONE);
}

static void build_threads(scene *s, const mr_asset *a, mr_svo_method method, unsigned depth,
                          const mr_mat4 *instances, size_t n, unsigned threads)
{
    build_frame(s, a, method, depth, instances, n, threads, NULL, 0);
}

static void build(scene *s, const mr_asset *a, mr_svo_method method, unsigned depth,
                  const mr_mat4 *instances, size_t n)
{
    build_threads(s, a, method, depth, instances, n, 2);
}

static void release(scene *s)
{
    s->ops->free(s->g);
    rtcReleaseScene(s->scene);
    rtcReleaseDevice(s->device);
    free(s->params.instances);
}

/* The ray org + t dir, t in [0, tfar], through the scene one at a time
 * (rtcIntersect1) into rh. */
static void trace1(const scene *s, mr_vec3 org, mr_vec3 dir, float tfar, struct RTCRayHit *rh)
{
    memset(rh, 0, sizeof *rh);
    rh->ray.org_x = org.x, rh->ray.org_y = org.y, rh->ray.org_z = org.z;
    rh->ray.dir_x = dir.x, rh->ray.dir_y = dir.y, rh->ray.dir_z = dir.z;
    rh->ray.tfar = tfar;
    rh->ray.mask = 0xffffffffu;
    rh->hit.geomID = RTC_INVALID_GEOMETRY_ID;
    rh->hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
    struct RTCIntersectContext ctx;
    rtcInitIntersectContext(&ctx);
    rtcIntersect1(s->scene, &ctx, rh);
}

/* A ray down -z at (x, y) from z0; returns the hit t (or INFINITY). */
static float shoot(const scene *s, float x, float y, float z0, struct RTCRayHit *rh)
{
    trace1(s, mr_v3(x, y, z0), mr_v3(0, 0, -1), FLT_MAX, rh);
    return rh->hit.geomID == RTC_INVALID_GEOMETRY_ID ? INFINITY : rh->ray.tfar;
}

static mr_mat4 translate_scale(float tx, float ty, float tz, float sx, float sy, float sz)
{
    return mr_mat4_from_trs(mr_v3(tx, ty, tz), mr_quat_identity(), mr_v3(sx, sy, sz));
}

static void check_methods(void **state)
{
    (void)state;
    const float half = 0.5f;
    mr_asset *a = cube(half);
    const float voxel = 2 * half * 1.01f / 16; /* depth 4, padded cube */
    mr_mat4 inst[4] = {
        translate_scale(0, 0, 0, 1, 1, 1),
        translate_scale(1e5f, -1e5f, 0, 1, 1, 1),
        translate_scale(5, 0, 0, -1, 1, 1), /* mirrored in x */
        translate_scale(-5, 0, 0, 0, 0, 0), /* zero scale: nothing to see */
    };
    const mr_svo_method methods[] = {MR_SVO_RIGID, MR_SVO_DIRECT, MR_SVO_RESIZE, MR_SVO_EMIT};
    /* the hit's depth below the face, in voxels (allowed: 2.5 + rounding), and
     * above it (allowed: rounding), over methods and instances */
    double below = -INFINITY, above = -INFINITY, below_far = -INFINITY, above_far = -INFINITY;
    int bad_normal = 0, phantom = 0;
    for (size_t m = 0; m < 4; m++) {
        scene s;
        build(&s, a, methods[m], 4, inst, 4);
        for (size_t k = 0; k < 3; k++) {
            float cx = inst[k].m[3], cy = inst[k].m[7];
            float z0 = 10.0f;
            struct RTCRayHit rh;
            float t = shoot(&s, cx + 0.1f, cy + 0.05f, z0, &rh);
            float face = z0 - half;
            float tol = k == 1 ? 0.02f : 1e-3f;
            if (!(t >= face - voxel * 2.5f - tol && t <= face + tol))
                print_error("method %zu instance %zu: hit at t %g, face at %g (voxel %g)\n", m, k,
                            (double)t, (double)face, (double)voxel);
            /* t >= face - 2.5 voxel - tol and t <= face + tol, as margins */
            double *lo = k == 1 ? &below_far : &below, *hi = k == 1 ? &above_far : &above;
            *lo = hard_max(*lo, (double)((face - voxel * 2.5f - tol) - t));
            *hi = hard_max(*hi, (double)(t - (face + tol)));
            unsigned prim = methods[m] == MR_SVO_RIGID ? rh.hit.instID[0] : rh.hit.primID;
            if (methods[m] == MR_SVO_RIGID)
                assert_int_equal(rh.hit.instID[0], k); /* the instance, by id */
            else if (methods[m] != MR_SVO_DIRECT)      /* a piece of the instance's octree */
                assert_int_equal(s.ops->id_primitive(s.g, prim), k);
            mr_vec3 n = mr_v3_normalize_or(s.ops->normal(s.g, prim, rh.hit.u, rh.hit.v,
                                                          mr_v3(rh.hit.Ng_x, rh.hit.Ng_y, rh.hit.Ng_z)),
                                           mr_v3(0, 0, 0));
            if (!(n.z > 0.7f))
                print_error("method %zu instance %zu: normal (%g, %g, %g)\n", m, k, (double)n.x,
                            (double)n.y, (double)n.z);
            HARD_EXPECT(bad_normal, n.z > 0.7f);
            /* Geometric normal: facing the ray, world space. */
            mr_vec3 ng = mr_v3(rh.hit.Ng_x, rh.hit.Ng_y, rh.hit.Ng_z);
            HARD_EXPECT(bad_normal, ng.z > 0);
            /* A ray beside the instance misses it. */
            HARD_EXPECT(phantom, isinf(shoot(&s, cx + 2.0f, cy, z0, &rh)) || fabsf(rh.ray.tfar - face) > 1.0f);
        }
        /* The zero-scale instance has no volume: no hit, no crash. */
        struct RTCRayHit rh;
        float t = shoot(&s, -5.0f + 0.1f, 0.05f, 10.0f, &rh);
        HARD_EXPECT(phantom, isinf(t));
        release(&s);
    }
    HARD_CHECK("error", below, "<=", 0,
               "hits deeper than 2.5 voxels + 1e-3 below the +z face, worst excess (4 methods, instances at the "
               "origin and mirrored)");
    HARD_CHECK("error", above, "<=", 0, "hits above the +z face by more than 1e-3, worst excess");
    HARD_CHECK("error", below_far, "<=", 0, "at 1e5: hits deeper than 2.5 voxels + 0.02 below the face, worst excess");
    HARD_CHECK("error", above_far, "<=", 0, "at 1e5: hits above the face by more than 0.02, worst excess");
    HARD_CHECK("other", bad_normal, "==", 0, "shading normals more than 45 deg off +z, or ng not facing the ray (of 24)");
    HARD_CHECK("other", phantom, "==", 0, "hits beside an instance or on the zero-scale one (of 16 rays)");
    mr_asset_free(a);
}

/* Octrees are traced as pieces (svo_kind.c: the rigid octree's subtrees,
 * resize and emit octrees' octree_prim), with Embree's tree over them.
 * Every ray gets through Embree
 * exactly the hit of the instance octree's whole walk (mr_svo_intersect):
 * the same t bit for bit and the same leaf. Where two pieces hold hits at
 * one t the kind keeps the one the whole walk meets first, whatever order
 * Embree visits them in; such ties need a ray on a face between two
 * pieces, exactly in the walk's arithmetic, which a resampled octree's
 * grid (not dyadic) rarely offers (none in 8 frames of svo-skinned): the
 * rays here run down each axis on the piece boundaries that happen to be
 * floats exactly, where neighbouring leaves of two pieces tie. The order
 * itself is test_svo_trace's test_subtrees. The cases: each method at
 * depth 6; the rigid octree at depth 8, where its pieces lie a level
 * deeper (svo_kind.c RIGID_SUBTREE_LEVEL; every 8th plane and ray of it,
 * its pieces are many); resize 1e5 from the origin, where a float step is
 * 1/64 and the pieces' boxes (made from their cells when a ray asks,
 * prim_box) must still hold their leaves. */
static void check_pieces_whole_walk(void **state)
{
    (void)state;
    mr_asset *a = cube(0.5f);
    const mr_mat4 one = mr_mat4_identity(), far = translate_scale(1e5f, -3e4f, 2e5f, 1, 1, 1);
    const struct {
        mr_svo_method method;
        unsigned depth, every; /* every k-th plane and ray */
        const mr_mat4 *where;
    } cases[] = {{MR_SVO_RIGID, 6, 1, &one},  {MR_SVO_RESIZE, 6, 1, &one}, {MR_SVO_EMIT, 6, 1, &one},
                 {MR_SVO_RIGID, 8, 8, &one},  {MR_SVO_RESIZE, 6, 1, &far}};
    int wrong = 0;
    unsigned long rays = 0, hits = 0, ties = 0;
    uint32_t fewest = UINT32_MAX, deepest = 0;
    for (int m = 0; m < (int)(sizeof cases / sizeof cases[0]); m++) {
        scene s;
        build(&s, a, cases[m].method, cases[m].depth, cases[m].where, 1);
        uint32_t pieces;
        const mr_svo *o = mr_svo_kind_octree(s.g, 0, &pieces);
        assert_non_null(o);
        fewest = pieces < fewest ? pieces : fewest;
        /* the pieces' level: the one whose subtrees are as many */
        mr_svo_subtree *st = NULL;
        uint32_t n = 0, level = 0;
        mr_error err = {0};
        for (level = 6; level > 0; level--) {
            assert_int_equal(mr_svo_subtrees(o, level, &st, &n, &err), MR_OK);
            if (n == pieces)
                break;
            free(st);
            st = NULL;
        }
        assert_true(level > 0);
        deepest = level > deepest ? level : deepest;
        const unsigned every = cases[m].every;
        const double org[3] = {o->origin.x, o->origin.y, o->origin.z}, cell = ldexp(o->size, -(int)level);
        for (int a0 = 0; a0 < 3; a0++)           /* the boundary's axis */
            for (int along = 0; along < 3; along++) { /* the ray's */
                if (along == a0)
                    continue;
                const int other = 3 - a0 - along;
                for (uint32_t K = every; K < (1u << level); K += every) {
                    const double plane = org[a0] + K * cell;
                    if ((double)(float)plane != plane)
                        continue; /* not a float: no ray lies on it */
                    for (int j = (int)every; j < 64; j += (int)every)
                        for (int sign = 0; sign < 2; sign++) {
                            float p[3], d[3] = {0, 0, 0};
                            p[a0] = (float)plane;
                            p[other] = (float)(org[other] + o->size * j / 64.0);
                            p[along] = sign ? (float)(org[along] - 1.0) : (float)(org[along] + o->size + 1.0);
                            d[along] = sign ? 1.0f : -1.0f;
                            struct RTCRayHit rh;
                            const mr_vec3 ov = mr_v3(p[0], p[1], p[2]), dv = mr_v3(d[0], d[1], d[2]);
                            trace1(&s, ov, dv, INFINITY, &rh);
                            mr_svo_hit whole;
                            const bool w = mr_svo_intersect(o, ov, dv, 0.0f, INFINITY, &whole);
                            rays++;
                            HARD_EXPECT(wrong, w == (rh.hit.geomID != RTC_INVALID_GEOMETRY_ID));
                            if (!w || rh.hit.geomID == RTC_INVALID_GEOMETRY_ID)
                                continue;
                            hits++;
                            const uint32_t u = (uint32_t)rh.hit.u, leaf = (u & 0xffffu) << 16 | (uint32_t)rh.hit.v;
                            const bool same = memcmp(&rh.ray.tfar, &whole.t, sizeof whole.t) == 0 && leaf == whole.leaf;
                            if (!same)
                                print_error("case %d: ray on plane %d = %a along %d: hit t %a leaf %u, whole walk t %a "
                                            "leaf %u\n", m, a0, plane, along, (double)rh.ray.tfar, leaf,
                                            (double)whole.t, whole.leaf);
                            HARD_EXPECT(wrong, same);
                            unsigned holding = 0;
                            for (uint32_t i = 0; i < n; i++) {
                                mr_svo_hit h;
                                holding += mr_svo_intersect_subtree(o, &st[i], ov, dv, 0.0f, INFINITY, &h) &&
                                           h.t == whole.t;
                            }
                            ties += holding > 1;
                        }
                }
            }
        free(st);
        release(&s);
    }
    print_message("[ pieces   ] %lu rays, %lu hits, %lu with hits at one t in two pieces; >= %u pieces, down to "
                  "level %u\n", rays, hits, ties, fewest, deepest);
    assert_true(fewest > 1);   /* traced as pieces at all */
    assert_int_equal(deepest, 6); /* the rigid octree's pieces at level 6 among them */
    assert_true(ties > 100);   /* and the rays do tie */
    HARD_CHECK("other", wrong, "==", 0, "rays whose hit through Embree is not the whole walk's (t, leaf), of %lu",
               rays);
    mr_asset_free(a);
}

/* A rigid cast with a level of detail ("tolerance_px") through Embree's
 * tree over the octree's pieces hits what walking every piece in turn
 * gives (mr_svo_kind_cast), bit for bit (t, leaf or node, level), traced
 * one ray at a time and sixteen at a time: a hit cannot depend on which
 * pieces Embree calls for a ray, nor in what order. The dancer (thin limbs:
 * pieces' boxes much smaller than their cells), the camera off the
 * octree's axes, near and far. Before the cut cells were clipped to their
 * pieces' boxes, 1,143 of these 58,880 rays differed (and in
 * examples/lod-svo.json one pixel changed with the packet shape). */
static void check_lod_pieces_any_order(void **state)
{
    (void)state;
    mr_asset *a = NULL;
    mr_error err = {0};
    if (mr_asset_load(DANCER, &a, &err) != MR_OK)
        fail_msg("%s", err.msg);
    const mr_mat4 one = mr_mat4_identity();
    enum { W = 160, H = 90, FILM_W = 96, FILM_H = 54 };
    const struct {
        unsigned depth;
        float distance, tolerance_px;
    } cases[] = {{8, 3.0f, 2.0f}, {10, 3.0f, 1.0f}, {10, 10.0f, 2.0f}, {11, 4.0f, 1.0f}};
    int wrong = 0, later = 0;
    unsigned long rays = 0, hits = 0, cut = 0;
    for (int m = 0; m < (int)(sizeof cases / sizeof cases[0]); m++) {
        const float d = cases[m].distance;
        const mr_camera_key key = {.position = mr_v3(0.55f * d, 0.4f * d, 0.75f * d), .has_target = true,
                                   .target = mr_v3(0.0f, -0.1f, -0.1f)};
        const mr_geom_frame frame = {.camera = {.position = key.position,
                                                .rotation = mr_camera_key_rotation(&key, mr_v3(0, 1, 0)),
                                                .yfov = (float)(40.0 * M_PI / 180.0)},
                                     .width = FILM_W, .height = FILM_H};
        scene s;
        build_frame(&s, a, MR_SVO_RIGID, cases[m].depth, &one, 1, 2, &frame, cases[m].tolerance_px);
        uint32_t pieces;
        const mr_svo *o = mr_svo_kind_octree(s.g, 0, &pieces);
        assert_non_null(o);
        assert_true(pieces > 1);
        for (int y0 = 0; y0 < H; y0 += 4)
            for (int x0 = 0; x0 < W; x0 += 4) {
                /* a 4 x 4 tile of rays: one packet, and each ray alone */
                struct RTCRayHit16 packet;
                memset(&packet, 0, sizeof packet);
                _Alignas(64) int valid[16];
                mr_vec3 dir[16];
                for (int i = 0; i < 16; i++) {
                    dir[i] = mr_camera_ray_dir(&frame.camera, W, H, x0 + (i & 3) + 0.5, y0 + (i >> 2) + 0.5);
                    valid[i] = -1;
                    packet.ray.org_x[i] = key.position.x, packet.ray.org_y[i] = key.position.y;
                    packet.ray.org_z[i] = key.position.z;
                    packet.ray.dir_x[i] = dir[i].x, packet.ray.dir_y[i] = dir[i].y, packet.ray.dir_z[i] = dir[i].z;
                    packet.ray.tfar[i] = INFINITY;
                    packet.ray.mask[i] = 0xffffffffu;
                    packet.hit.geomID[i] = packet.hit.instID[0][i] = RTC_INVALID_GEOMETRY_ID;
                }
                struct RTCIntersectContext ctx;
                rtcInitIntersectContext(&ctx);
                ctx.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
                rtcIntersect16(valid, s.scene, &ctx, &packet);
                for (int i = 0; i < 16; i++) {
                    struct RTCRayHit rh;
                    trace1(&s, key.position, dir[i], INFINITY, &rh);
                    mr_svo_hit want;
                    const bool w = mr_svo_kind_cast(s.g, 0, key.position, dir[i], &want);
                    rays++;
                    /* no holes: the leaves' hit, if any, is not nearer */
                    mr_svo_hit leaves;
                    if (mr_svo_intersect(o, key.position, dir[i], 0.0f, INFINITY, &leaves))
                        HARD_EXPECT(later, w && want.t <= leaves.t);
                    const bool one_hit = rh.hit.geomID != RTC_INVALID_GEOMETRY_ID,
                               packet_hit = packet.hit.geomID[i] != RTC_INVALID_GEOMETRY_ID;
                    HARD_EXPECT(wrong, w == one_hit && w == packet_hit);
                    if (!w || !one_hit || !packet_hit)
                        continue;
                    hits++;
                    const uint32_t want_u = (want.leaf >> 16) | want.level << 16, want_v = want.leaf & 0xffffu;
                    const bool same = memcmp(&rh.ray.tfar, &want.t, sizeof want.t) == 0 &&
                                      memcmp(&packet.ray.tfar[i], &want.t, sizeof want.t) == 0 &&
                                      (uint32_t)rh.hit.u == want_u && (uint32_t)rh.hit.v == want_v &&
                                      (uint32_t)packet.hit.u[i] == want_u && (uint32_t)packet.hit.v[i] == want_v;
                    if (!same && wrong < 8)
                        print_error("case %d, ray (%d, %d): pieces in turn t %a level %u; one ray t %a level %u, "
                                    "packet t %a level %u\n", m, x0 + (i & 3), y0 + (i >> 2), (double)want.t,
                                    want.level, (double)rh.ray.tfar, (uint32_t)rh.hit.u >> 16,
                                    (double)packet.ray.tfar[i], (uint32_t)packet.hit.u[i] >> 16);
                    HARD_EXPECT(wrong, same);
                    cut += want.leaf >= o->leaf_count;
                }
            }
        release(&s);
    }
    print_message("[ lod      ] %lu rays, %lu hits, %lu of them on nodes cut by the level of detail\n", rays, hits,
                  cut);
    assert_true(cut > hits / 4); /* the level of detail cuts (measured: 1,481 of 2,403 hits) */
    HARD_CHECK("leaks", later, "==", 0,
               "rays the cast with a level of detail misses or hits later than the leaves (of %lu)", rays);
    HARD_CHECK("other", wrong, "==", 0,
               "rays whose hit through Embree (one ray, or a 16-ray packet) is not every piece's in turn (t, leaf, "
               "level), of %lu", rays);
    mr_asset_free(a);
}

/* An asset small enough for one voxel: depth 1 has 8 cells; a single
 * triangle in one corner cell still renders, in every method. */
static void check_tiny(void **state)
{
    (void)state;
    const float p[9] = {0, 0, 0, 1, 0, 0, 0, 1, 0};
    const uint32_t idx[3] = {0, 1, 2};
    mr_asset *a = NULL;
    mr_error err = {0};
    assert_int_equal(mr_asset_from_mesh("tri", p, NULL, 3, idx, 1, &a, &err), MR_OK);
    mr_mat4 id = mr_mat4_identity();
    const mr_svo_method methods[] = {MR_SVO_RIGID, MR_SVO_DIRECT, MR_SVO_RESIZE, MR_SVO_EMIT};
    int missed = 0;
    for (size_t m = 0; m < 4; m++) {
        scene s;
        build(&s, a, methods[m], 1, &id, 1);
        struct RTCRayHit rh;
        HARD_EXPECT(missed, !isinf(shoot(&s, 0.25f, 0.25f, 5.0f, &rh)));
        release(&s);
    }
    HARD_CHECK("leaks", missed, "==", 0, "rays at the one-voxel asset that missed it (one per method)");
    mr_asset_free(a);
}

/* A pose that scales voxels past MR_MAX_COORDINATE (two chained joints
 * scaled by 1e9 each: every single value passes the job parser) fails the
 * frame in every method, as it does for meshes, instead of handing Embree
 * boxes it would silently drop. */
static void check_far_pose_refused(void **state)
{
    (void)state;
    mr_asset *a = NULL;
    mr_error err = {0};
    assert_int_equal(mr_asset_load("/usr/share/assimp/models/X/BCN_Epileptic.X", &a, &err), MR_OK);
    /* the root and its child above the first joint of the first skinned
     * mesh: every joint below them is scaled by 1e18 */
    int joint = -1;
    for (size_t m = 0; m < a->mesh_count && joint < 0; m++)
        if (a->meshes[m].joint_count > 0)
            joint = a->meshes[m].joint_nodes[0];
    assert_true(joint > 0);
    while (a->nodes[joint].parent > 0)
        joint = a->nodes[joint].parent;
    assert_int_equal(a->nodes[joint].parent, 0);
    const mr_mat4 huge = mr_mat4_from_trs(mr_v3(0, 0, 0), mr_quat_identity(), mr_v3(1e9f, 1e9f, 1e9f));
    mr_joint_override ov[2] = {{a->nodes[0].name, huge}, {a->nodes[joint].name, huge}};
    mr_pose_desc pose = {.clip_index = -1, .joint_count = 2, .joints = ov};
    const mr_svo_method methods[] = {MR_SVO_RIGID, MR_SVO_DIRECT, MR_SVO_RESIZE, MR_SVO_EMIT};
    int wrong = 0;
    for (size_t m = 0; m < 4; m++) {
        mr_svo_params params = {.depth = 5, .method = methods[m], .delta = 1, .cull = true};
        mr_object_desc desc = {.kind = &mr_kind_svo, .params = &params, .transform = mr_mat4_identity(),
                               .color = mr_v3(0.8f, 0.8f, 0.8f), .pose_count = 1, .poses = &pose};
        const mr_kind *ops = &mr_kind_svo;
        mr_geom *g = NULL;
        RTCDevice dev = rtcNewDevice(NULL);
        RTCScene sc = rtcNewScene(dev);
        if (ops->create(a, &desc, &(mr_kind_context){.cache_dir = NULL, .threads = 0}, &g, &err) < 0 ||
            ops->attach(g, dev, sc, 0, RTC_BUILD_QUALITY_MEDIUM, &err) < 0)
            fail_msg("setup: %s", err.msg);
        int rc = ops->update(g, NULL, NULL, &desc.transform, 2, &err);
        if (methods[m] == MR_SVO_RIGID) {
            /* rigid instances keep the rest pose: nothing moves far */
            HARD_EXPECT(wrong, rc == MR_OK);
        } else {
            HARD_EXPECT(wrong, rc == MR_ERR_INVALID && strstr(err.msg, "beyond"));
        }
        ops->free(g);
        rtcReleaseScene(sc);
        rtcReleaseDevice(dev);
    }
    HARD_CHECK("other", wrong, "==", 0,
               "methods not refusing a pose beyond MR_MAX_COORDINATE (saying \"beyond\"), or rigid refusing it (of 4)");
    mr_asset_free(a);
}

/* count emit instances inst[0 .. count), every leaf selected (no camera). */
static mr_svo_params emit_instances(size_t count, mr_svo_instance *inst)
{
    return (mr_svo_params){.depth = 5, .method = MR_SVO_EMIT, .delta = 1, .cull = true,
                           .instance_count = count, .instances = inst};
}

/* The job's memory budget (issue 12: 100,000 emit instances at 64x64 grew
 * past 23 GB and took the daemon down). What every instance surely holds is
 * refused before anything per instance is allocated; what the view makes
 * an instance hold is counted as the frame is built, and the frame fails
 * once the count passes the budget, holding at most one instance per
 * worker beyond it. */
static void check_memory_budget(void **state)
{
    (void)state;
    mr_asset *a = cube(0.5f);
    mr_error err = {0};
    const mr_kind *ops = &mr_kind_svo;
    enum { MANY = 100000, SOME = 400 };
    mr_svo_instance *inst = calloc(MANY, sizeof *inst);
    for (size_t k = 0; k < MANY; k++)
        inst[k].transform = translate_scale((float)(k % 20) * 2, (float)(k / 20) * 2, 0, 1, 1, 1);

    /* 100,000 rigid instances need ~70 MB of matrices and Embree
     * instances: refused by a 16 MiB budget at create, accepted by 1 GiB. */
    mr_svo_params params = {.depth = 4, .method = MR_SVO_RIGID, .delta = 1, .cull = true,
                            .instance_count = MANY, .instances = inst};
    mr_object_desc desc = {.kind = ops, .params = &params, .transform = mr_mat4_identity(),
                           .color = mr_v3(0.8f, 0.8f, 0.8f)};
    mr_geom *g = NULL;
    mr_kind_context ctx = {.memory_budget = (size_t)16 << 20};
    assert_int_equal(ops->create(a, &desc, &ctx, &g, &err), MR_ERR_LIMIT);
    assert_null(g);
    if (!strstr(err.msg, "svo/instances: 100000 instances") || !strstr(err.msg, "16.0 MiB"))
        fail_msg("%s", err.msg);
    ctx.memory_budget = (size_t)1 << 30;
    if (ops->create(a, &desc, &ctx, &g, &err) < 0)
        fail_msg("create: %s", err.msg);
    ops->free(g);

    /* Emit instances, every leaf selected (no camera), all alike: with no
     * budget, 200 and 400 of them give what one holds and what the object
     * holds besides (the shared octree); then a budget of a quarter
     * stops the frame. */
    size_t all[2];
    for (int run = 0; run < 2; run++) {
        params = emit_instances(SOME / 2 * (size_t)(run + 1), inst);
        ctx.memory_budget = 0;
        if (ops->create(a, &desc, &ctx, &g, &err) < 0 ||
            ops->update(g, NULL, NULL, &desc.transform, 2, &err) < 0)
            fail_msg("unlimited: %s", err.msg);
        all[run] = ops->memory(g);
        ops->free(g);
    }
    /* instances at other places resample into octrees of other sizes, so
     * the split is approximate: what is not per instance is at least 0 */
    size_t per_instance = (all[1] - all[0]) / (SOME / 2);
    size_t fixed = all[1] > SOME * per_instance ? all[1] - SOME * per_instance : 0;
    /* how far apart the instances' sizes lie: the object's bytes with
     * each instance alone, the largest less the smallest (no instance is
     * larger than the mean by more than that) */
    size_t alone_min = SIZE_MAX, alone_max = 0;
    for (size_t k = 0; k < SOME; k++) {
        params = emit_instances(1, inst + k);
        if (ops->create(a, &desc, &ctx, &g, &err) < 0 || ops->update(g, NULL, NULL, &desc.transform, 2, &err) < 0)
            fail_msg("instance %zu alone: %s", k, err.msg);
        const size_t m = ops->memory(g);
        alone_min = m < alone_min ? m : alone_min;
        alone_max = m > alone_max ? m : alone_max;
        ops->free(g);
    }
    const size_t spread = alone_max - alone_min;
    params = emit_instances(SOME, inst);
    size_t budget = all[1] / 4;
    ctx.memory_budget = budget;
    if (ops->create(a, &desc, &ctx, &g, &err) < 0)
        fail_msg("create under a budget: %s", err.msg);
    assert_int_equal(ops->update(g, NULL, NULL, &desc.transform, 2, &err), MR_ERR_LIMIT);
    if (!strstr(err.msg, "svo/instances: 400 instances hold more than the job's memory budget"))
        fail_msg("%s", err.msg);
    /* two workers: each may finish one instance past the budget, an
     * instance at most the mean and the spread of their sizes (a bound by
     * the mean alone failed once in twelve runs, by 1 KB) */
    size_t held = ops->memory(g);
    print_message("[ budget   ] %zu of %zu bytes held at a %zu-byte budget (%zu per instance, spread %zu, "
                  "%zu besides)\n", held, all[1], budget, per_instance, spread, fixed);
    HARD_CHECK("other", held, "<=", fixed + budget + 2 * (per_instance + spread),
               "bytes held when the frame stops at a budget of %zu (the budget, what the object holds besides, "
               "2 of the largest instances)", budget);
    ops->free(g);
    free(inst);
    mr_asset_free(a);
}

/* The kind works on the job's thread count (what the renderer passes to
 * update), not on the machine's cores: it used to size and cap its workers
 * by mr_cpu_count(), so a job given more threads than cores ran on fewer.
 * Observable without timing: resampling sorts its keys in one block per
 * thread (deform.c pk_sort_run: blocks of at least 32768 keys, at most 64),
 * each block with its own histogram in the worker's workspace, which
 * svo_scratch_bytes counts. One instance is resampled on all the threads, so going
 * from C (the cores) to 2C threads doubles those histograms. The traced
 * voxels are the same for 1, C and 2C threads, bit for bit. */
static void check_threads_beyond_cores(void **state)
{
    (void)state;
    const unsigned cores = mr_cpu_count();
    if (2 * cores > 64)
        skip(); /* the sort's block cap: more threads could not show */
    mr_asset *a = cube(0.5f);
    const mr_mat4 id = mr_mat4_identity();
    const unsigned threads[3] = {1, cores, 2 * cores};
    enum { N = 24 };
    double scratch[3];
    static struct RTCRayHit hits[3][N * N];
    for (int i = 0; i < 3; i++) {
        scene s;
        build_threads(&s, a, MR_SVO_RESIZE, 7, &id, 1, threads[i]);
        /* enough keys for 2C blocks (the leaves alone are fewer) */
        assert_true(s.ops->primitives(s.g) >= 2ull * cores * 32768u);
        scratch[i] = fx_kind_stat(s.ops, s.g, "svo_scratch_bytes");
        for (int y = 0; y < N; y++)
            for (int x = 0; x < N; x++)
                shoot(&s, -0.6f + 1.2f * (x + 0.5f) / N, -0.6f + 1.2f * (y + 0.37f) / N, 10.0f,
                      &hits[i][y * N + x]);
        release(&s);
    }
    HARD_CHECK("other", scratch[2], ">", scratch[1],
               "scratch bytes with %u threads (more than with %u, the cores: the update used them all)", threads[2],
               threads[1]);
    size_t hit = 0, differ = 0;
    for (int i = 1; i < 3; i++)
        for (int k = 0; k < N * N; k++) {
            const struct RTCRayHit *p = &hits[0][k], *q = &hits[i][k];
            HARD_EXPECT(differ, p->hit.geomID == q->hit.geomID && p->hit.primID == q->hit.primID &&
                                    !memcmp(&p->ray.tfar, &q->ray.tfar, sizeof(float)) &&
                                    !memcmp(&p->hit.u, &q->hit.u, sizeof(float)) &&
                                    !memcmp(&p->hit.v, &q->hit.v, sizeof(float)));
            hit += i == 1 && p->hit.geomID != RTC_INVALID_GEOMETRY_ID;
        }
    HARD_CHECK("other", differ, "==", 0, "rays whose hit (id, t, u, v bits) differs from 1 thread's, with %u and %u "
               "threads (of %d)", threads[1], threads[2], 2 * N * N);
    HARD_CHECK("other", hit, ">", N * N / 2, "rays that hit the cube (of %d)", N * N); /* it fills most of the grid */
    mr_asset_free(a);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(check_methods),
        cmocka_unit_test(check_pieces_whole_walk),
        cmocka_unit_test(check_lod_pieces_any_order),
        cmocka_unit_test(check_tiny),
        cmocka_unit_test(check_far_pose_refused),
        cmocka_unit_test(check_threads_beyond_cores),
        cmocka_unit_test(check_memory_budget),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
