/*
 * displaced_fixture.h - the harness the displaced-kind tests share
 * (tests/unit/test_displaced.c, tests/hard/test_displaced_hard.c,
 * tests/hard/test_displaced_seams.c): meshes with texture coordinates and
 * height textures made in memory, a displaced object created, posed and
 * attached to a real Embree scene through the kind's own ops, its exact
 * tessellation (the kind's tessellate), and check_ray: the ray traced
 * through Embree (which calls the kind's traversal for every base triangle
 * whose box the ray meets) against the brute force over every
 * micro-triangle of the tessellation with the same watertight test. Both
 * must agree exactly: hit or miss, and t bit for bit (the micro-vertices
 * are the same floats, the test is the same function). Header-only,
 * included once per test program after cmocka.h.
 */
#ifndef MR_TEST_DISPLACED_FIXTURE_H
#define MR_TEST_DISPLACED_FIXTURE_H

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "anim/pose.h"
#include "asset/asset.h"
#include "asset/image.h"
#include "kinds/displaced/displaced_kind.h"
#include "kinds/kind.h"
#include "math/watertight.h"
#include "render/device.h"
#include "util/simd.h"
#include "rng_fixture.h"

/* A one-mesh asset with texture coordinates (uvs: 2 per vertex). */
static inline mr_asset *dfx_mesh(const float *pos, const float *nrm, const float *uvs, uint32_t nv,
                                 const uint32_t *idx, uint32_t nt)
{
    mr_asset *a = NULL;
    mr_error err;
    if (mr_asset_from_mesh("dfx", pos, nrm, nv, idx, nt, &a, &err) != MR_OK)
        fail_msg("dfx_mesh: %s", err.msg);
    a->meshes[0].uvs = malloc((size_t)nv * 2 * sizeof(float));
    assert_non_null(a->meshes[0].uvs);
    memcpy(a->meshes[0].uvs, uvs, (size_t)nv * 2 * sizeof(float));
    if (nrm)
        memcpy(a->meshes[0].normals, nrm, (size_t)nv * 3 * sizeof(float));
    return a;
}

/* A w x h texture of the given type, sample (x, y) (picture row y) from f. */
static inline mr_asset *dfx_texture(uint32_t w, uint32_t h, mr_sample_type type,
                                    double (*f)(uint32_t x, uint32_t y, void *user), void *user)
{
    mr_image *img = NULL;
    mr_error err;
    if (mr_image_new(w, h, type, &img, &err) != MR_OK)
        fail_msg("dfx_texture: %s", err.msg);
    for (uint32_t y = 0; y < h; y++)
        for (uint32_t x = 0; x < w; x++) {
            double v = f(x, y, user);
            size_t k = (size_t)y * w + x;
            if (type == MR_SAMPLE_U8)
                ((uint8_t *)img->samples)[k] = (uint8_t)v;
            else if (type == MR_SAMPLE_U16)
                ((uint16_t *)img->samples)[k] = (uint16_t)v;
            else
                ((float *)img->samples)[k] = (float)v;
        }
    mr_asset *a = NULL;
    if (mr_asset_from_image("memory:texture", img, &a, &err) != MR_OK)
        fail_msg("dfx_texture: %s", err.msg);
    return a;
}

/* Random 8-bit samples (user: a uint64_t seed). */
static inline double dfx_noise(uint32_t x, uint32_t y, void *user)
{
    (void)x, (void)y;
    return rnd(user) & 0xff;
}

typedef struct dfx {
    mr_asset *assets[2]; /* the mesh, the texture (borrowed) */
    mr_displaced_params par;
    mr_object_desc desc;
    mr_geom *geom;
    mr_pose *pose;
    mr_device *dev;
    RTCScene scene;
    mr_trimesh tess;
    uint64_t rays, hits;
} dfx;

/* Default parameters with a texture (asset 1) of the given scale. */
static inline void dfx_params(dfx *f, float scale, float offset)
{
    mr_params_defaults(mr_kind_params(&mr_kind_displaced), &f->par);
    f->par.texture = 2;
    f->par.scale = scale;
    f->par.offset = offset;
}

/* Creates, poses (pose_desc may be NULL: rest pose; transform may be NULL)
 * and attaches the object, and tessellates it. */
static inline void dfx_open(dfx *f, mr_asset *mesh, mr_asset *tex, const mr_pose_desc *pose_desc,
                            const mr_mat4 *transform, double time)
{
    mr_error err = {0};
    f->assets[0] = mesh;
    f->assets[1] = tex;
    f->desc = (mr_object_desc){.params = &f->par, .kind = &mr_kind_displaced};
    mr_kind_context ctx = {.assets = (const mr_asset *const *)f->assets, .asset_count = 2,
                           .threads = 2};
    if (mr_kind_displaced.create(mesh, &f->desc, &ctx, &f->geom, &err) != MR_OK)
        fail_msg("create: %s", err.msg);
    if (mr_pose_new(mesh, &f->pose, &err) != MR_OK ||
        mr_pose_eval(f->pose, mesh, pose_desc, time, &err) != MR_OK)
        fail_msg("pose: %s", err.msg);
    mr_mat4 id = mr_mat4_identity();
    mr_geom_frame fr = {0};
    if (mr_kind_displaced.update(f->geom, &fr, f->pose, transform ? transform : &id, 2, &err) !=
        MR_OK)
        fail_msg("update: %s", err.msg);
    if (!f->dev && mr_device_new(2, &f->dev, &err) != MR_OK)
        fail_msg("device: %s", err.msg);
    f->scene = rtcNewScene(mr_device_embree(f->dev));
    rtcSetSceneFlags(f->scene, RTC_SCENE_FLAG_ROBUST);
    if (mr_kind_displaced.attach(f->geom, mr_device_embree(f->dev), f->scene, 0,
                                 RTC_BUILD_QUALITY_MEDIUM, &err) != MR_OK)
        fail_msg("attach: %s", err.msg);
    mr_kind_displaced.commit(f->geom);
    rtcCommitScene(f->scene);
    if (mr_kind_displaced.tessellate(f->geom, &f->tess, &err) != MR_OK)
        fail_msg("tessellate: %s", err.msg);
}

/* A new pose of the same object (skinned bases; transform may be NULL):
 * update, refit, tessellate. */
static inline void dfx_repose(dfx *f, const mr_pose_desc *pose_desc, const mr_mat4 *transform, double time)
{
    mr_error err = {0};
    mr_mat4 id = mr_mat4_identity();
    mr_geom_frame fr = {0};
    if (mr_pose_eval(f->pose, f->assets[0], pose_desc, time, &err) != MR_OK ||
        mr_kind_displaced.update(f->geom, &fr, f->pose, transform ? transform : &id, 2, &err) != MR_OK)
        fail_msg("repose: %s", err.msg);
    mr_kind_displaced.commit(f->geom);
    rtcCommitScene(f->scene);
    mr_trimesh_free(&f->tess);
    if (mr_kind_displaced.tessellate(f->geom, &f->tess, &err) != MR_OK)
        fail_msg("tessellate: %s", err.msg);
}

static inline void dfx_close(dfx *f)
{
    if (f->scene)
        rtcReleaseScene(f->scene);
    f->scene = NULL;
    mr_kind_displaced.free(f->geom);
    f->geom = NULL;
    mr_pose_free(f->pose);
    f->pose = NULL;
    mr_trimesh_free(&f->tess);
}

static inline mr_vec3 dfx_vertex(const mr_trimesh *m, uint32_t i)
{
    return mr_v3(m->positions[(size_t)i * 3], m->positions[(size_t)i * 3 + 1],
                 m->positions[(size_t)i * 3 + 2]);
}

/* Closest hit of the ray with the tessellation, by brute force. */
static inline bool dfx_brute(const dfx *f, mr_vec3 o, mr_vec3 d, float tmin, float tmax, float *t)
{
    mr_wt_ray r = mr_wt_ray_setup(o, d);
    bool hit = false;
    for (uint32_t k = 0; k < f->tess.triangle_count; k++) {
        const uint32_t *tri = f->tess.indices + (size_t)k * 3;
        mr_wt_hit h;
        if (mr_wt_intersect(&r, dfx_vertex(&f->tess, tri[0]), dfx_vertex(&f->tess, tri[1]),
                            dfx_vertex(&f->tess, tri[2]), tmin, tmax, &h)) {
            tmax = h.t;
            hit = true;
        }
    }
    *t = tmax;
    return hit;
}

/* The ray through the kind (Embree + its traversal); *ng: the normal the
 * renderer shades the hit by (the kind's normal op, given Embree's
 * geometric normal). */
static inline bool dfx_trace_uv(const dfx *f, mr_vec3 o, mr_vec3 d, float tmin, float tmax,
                                float *t, mr_vec3 *ng, float uv[2])
{
    struct RTCIntersectContext ic;
    rtcInitIntersectContext(&ic);
    struct RTCRayHit rh;
    memset(&rh, 0, sizeof rh);
    rh.ray.org_x = o.x, rh.ray.org_y = o.y, rh.ray.org_z = o.z;
    rh.ray.dir_x = d.x, rh.ray.dir_y = d.y, rh.ray.dir_z = d.z;
    rh.ray.tnear = tmin;
    rh.ray.tfar = tmax;
    rh.ray.mask = 0xffffffffu;
    rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
    rtcIntersect1(f->scene, &ic, &rh);
    *t = rh.ray.tfar;
    if (uv)
        uv[0] = rh.hit.u, uv[1] = rh.hit.v;
    bool hit = rh.hit.geomID != RTC_INVALID_GEOMETRY_ID;
    if (ng)
        *ng = hit ? mr_kind_displaced.normal(f->geom, rh.hit.primID, rh.hit.u, rh.hit.v,
                                             mr_v3(rh.hit.Ng_x, rh.hit.Ng_y, rh.hit.Ng_z))
                  : mr_v3(0, 0, 0);
    return hit;
}

/* dfx_trace without the hit's (u, v). */
static inline bool dfx_trace(const dfx *f, mr_vec3 o, mr_vec3 d, float tmin, float tmax, float *t,
                             mr_vec3 *ng)
{
    return dfx_trace_uv(f, o, d, tmin, tmax, t, ng, NULL);
}

/* The occlusion query through the kind. */
static inline bool dfx_occluded(const dfx *f, mr_vec3 o, mr_vec3 d, float tmin, float tmax)
{
    struct RTCIntersectContext ic;
    rtcInitIntersectContext(&ic);
    struct RTCRay r;
    memset(&r, 0, sizeof r);
    r.org_x = o.x, r.org_y = o.y, r.org_z = o.z;
    r.dir_x = d.x, r.dir_y = d.y, r.dir_z = d.z;
    r.tnear = tmin;
    r.tfar = tmax;
    r.mask = 0xffffffffu;
    rtcOccluded1(f->scene, &ic, &r);
    return r.tfar < 0;
}

/* A packet of 8 rays from o along d[0 .. 8), every lane valid, not yet
 * traced. */
static inline void dfx_packet_rays(mr_vec3 o, const mr_vec3 d[8], float tmin, float tmax,
                                   int valid[8], struct RTCRayHit8 *rh)
{
    memset(rh, 0, sizeof *rh);
    for (int k = 0; k < 8; k++) {
        valid[k] = -1;
        rh->ray.org_x[k] = o.x, rh->ray.org_y[k] = o.y, rh->ray.org_z[k] = o.z;
        rh->ray.dir_x[k] = d[k].x, rh->ray.dir_y[k] = d[k].y, rh->ray.dir_z[k] = d[k].z;
        rh->ray.tnear[k] = tmin;
        rh->ray.tfar[k] = tmax;
        rh->ray.mask[k] = 0xffffffffu;
        rh->hit.geomID[k] = RTC_INVALID_GEOMETRY_ID;
    }
}

/* The ray traced inside a packet of 8 (rtcIntersect8: Embree hands the
 * kind's callback the packet, whose rays the kind traverses together,
 * dtrace.h): lane 0 the ray itself, lane 1 the same ray again, lanes 2..7
 * rays from the same origin turned slightly (1e-2 .. 1e-6 of the
 * direction), as a camera's neighbouring pixels are; and inside a packet
 * of 16. Each lane must get what it gets alone: hit or miss, t, normal and
 * (u, v) bit for bit, and the same verdict as an occlusion packet
 * (rtcOccluded8). Returns how many lanes differ. */
static inline int dfx_packet_check(const dfx *f, mr_vec3 o, mr_vec3 d, float tmin, float tmax)
{
    static const float TURN[8][3] = {{0, 0, 0},         {0, 0, 0},          {1e-2f, 0, 0},
                                     {0, -1e-3f, 0},    {0, 0, 1e-4f},      {-1e-5f, 1e-5f, 0},
                                     {0, 1e-6f, -1e-6f}, {3e-3f, 2e-3f, -1e-3f}};
    float len = mr_v3_len(d);
    RTC_ALIGN(32) int valid[8];
    struct RTCRayHit8 rh;
    mr_vec3 dk[8];
    for (int k = 0; k < 8; k++)
        dk[k] = mr_v3_add(d, mr_v3_scale(mr_v3(TURN[k][0], TURN[k][1], TURN[k][2]), len));
    dfx_packet_rays(o, dk, tmin, tmax, valid, &rh);
    struct RTCIntersectContext ic;
    rtcInitIntersectContext(&ic);
    ic.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
    struct RTCRay8 occ = rh.ray; /* the same rays as an occlusion packet */
    rtcIntersect8(valid, f->scene, &ic, &rh);
    rtcOccluded8(valid, f->scene, &ic, &occ);
    /* The same rays in a packet of 16 (rtcIntersect16, as the renderer
     * traces: the kind's widest paths, cell_test16 and the other AVX-512
     * ones where the CPU has it), lanes 8..15 the eight again with every
     * other one invalid (a NaN direction the kind must not read), on the
     * CPU's paths and again capped at AVX2 (mr_simd_cap_avx2). */
    RTC_ALIGN(64) int valid16[16];
    struct RTCRayHit16 r16[2];
    memset(r16, 0, sizeof r16);
    for (int k = 0; k < 16; k++) {
        const mr_vec3 dd = dk[k & 7];
        valid16[k] = k < 8 || (k & 1) ? -1 : 0;
        r16[0].ray.org_x[k] = o.x, r16[0].ray.org_y[k] = o.y, r16[0].ray.org_z[k] = o.z;
        r16[0].ray.dir_x[k] = valid16[k] ? dd.x : NAN;
        r16[0].ray.dir_y[k] = dd.y, r16[0].ray.dir_z[k] = dd.z;
        r16[0].ray.tnear[k] = tmin;
        r16[0].ray.tfar[k] = tmax;
        r16[0].ray.mask[k] = 0xffffffffu;
        r16[0].hit.geomID[k] = RTC_INVALID_GEOMETRY_ID;
    }
    r16[1] = r16[0];
    for (int cap = 0; cap < 2; cap++) {
        mr_simd_cap_avx2(cap == 1);
        rtcIntersect16(valid16, f->scene, &ic, &r16[cap]);
    }
    mr_simd_cap_avx2(false);
    int bad = 0;
    for (int k = 0; k < 8; k++) {
        float t, uv[2] = {0, 0};
        mr_vec3 ng = mr_v3(0, 0, 0);
        bool h = dfx_trace_uv(f, o, dk[k], tmin, tmax, &t, &ng, uv);
        for (int q = 0; q < 4; q++) { /* lane k and k + 8, each way */
            const int lane = k + 8 * (q & 1);
            const struct RTCRayHit16 *r = &r16[q >> 1];
            if (!valid16[lane])
                continue;
            const bool hq = r->hit.geomID[lane] != RTC_INVALID_GEOMETRY_ID;
            const mr_vec3 ngq = mr_v3(r->hit.Ng_x[lane], r->hit.Ng_y[lane], r->hit.Ng_z[lane]);
            const float uvq[2] = {r->hit.u[lane], r->hit.v[lane]};
            if (h == hq && (!h || (t == r->ray.tfar[lane] && !memcmp(&ng, &ngq, sizeof ng) &&
                                   !memcmp(uv, uvq, sizeof uv))))
                continue;
            print_error("16-packet lane %d%s: alone %s t %.9g, in the packet %s t %.9g\n", lane,
                        q >> 1 ? " (AVX2)" : "", h ? "hit" : "miss", t, hq ? "hit" : "miss",
                        r->ray.tfar[lane]);
            bad++;
        }
        bool hp = rh.hit.geomID[k] != RTC_INVALID_GEOMETRY_ID;
        mr_vec3 ngp = mr_v3(rh.hit.Ng_x[k], rh.hit.Ng_y[k], rh.hit.Ng_z[k]);
        const float uvp[2] = {rh.hit.u[k], rh.hit.v[k]};
        bool occluded = occ.tfar[k] < 0;
        if (occluded != dfx_occluded(f, o, dk[k], tmin, tmax)) {
            print_error("packet lane %d: occluded alone and in the packet differ\n", k);
            bad++;
            continue;
        }
        if (h == hp && (!h || (t == rh.ray.tfar[k] && !memcmp(&ng, &ngp, sizeof ng) &&
                               !memcmp(uv, uvp, sizeof uv))))
            continue;
        print_error("packet lane %d (ray o (%.9g %.9g %.9g) d (%.9g %.9g %.9g)): alone %s t %.9g "
                    "normal (%.9g %.9g %.9g), in the packet %s t %.9g normal (%.9g %.9g %.9g)\n",
                    k, o.x, o.y, o.z, dk[k].x, dk[k].y, dk[k].z, h ? "hit" : "miss", t, ng.x, ng.y,
                    ng.z, hp ? "hit" : "miss", rh.ray.tfar[k], ngp.x, ngp.y, ngp.z);
        bad++;
    }
    return bad;
}

/* The traversal against the brute force for one ray, alone and in a packet
 * (dfx_packet_check): returns 0 when they agree (and counts the ray), else
 * prints the case and returns 1. */
static inline int dfx_check_ray(dfx *f, mr_vec3 o, mr_vec3 d, float tmin, float tmax)
{
    float tt, tb;
    bool ht = dfx_trace(f, o, d, tmin, tmax, &tt, NULL);
    bool hb = dfx_brute(f, o, d, tmin, tmax, &tb);
    bool occ = dfx_occluded(f, o, d, tmin, tmax);
    int packet = dfx_packet_check(f, o, d, tmin, tmax);
    f->rays++;
    f->hits += hb;
    if (ht == hb && (!hb || tt == tb) && occ == hb && !packet)
        return 0;
    print_error("ray o (%.9g %.9g %.9g) d (%.9g %.9g %.9g) [%g, %g]: traversal %s t %.9g, brute "
                "force %s t %.9g, occluded %d\n",
                o.x, o.y, o.z, d.x, d.y, d.z, tmin, tmax, ht ? "hit" : "miss", tt,
                hb ? "hit" : "miss", tb, occ);
    return 1;
}

/* The bounding box of the tessellation. */
static inline void dfx_bounds(const dfx *f, mr_vec3 *lo, mr_vec3 *hi)
{
    *lo = mr_v3(INFINITY, INFINITY, INFINITY);
    *hi = mr_v3(-INFINITY, -INFINITY, -INFINITY);
    for (uint32_t i = 0; i < f->tess.vertex_count; i++) {
        *lo = mr_v3_min(*lo, dfx_vertex(&f->tess, i));
        *hi = mr_v3_max(*hi, dfx_vertex(&f->tess, i));
    }
}

/* n rays from random points around the object's box towards random points
 * inside it (and a fifth of them towards micro-vertices, which are the
 * hardest: edges and corners); returns the number of disagreements. */
static inline int dfx_random_rays(dfx *f, uint64_t *seed, int n)
{
    mr_vec3 lo, hi;
    dfx_bounds(f, &lo, &hi);
    mr_vec3 c = mr_v3_scale(mr_v3_add(lo, hi), 0.5f), e = mr_v3_sub(hi, lo);
    float r = mr_v3_len(e) + 1e-3f;
    int bad = 0;
    for (int k = 0; k < n; k++) {
        mr_vec3 o = mr_v3_add(c, mr_v3_scale(rnd_unit(seed), r * rndf(seed, 0.7f, 2.0f)));
        mr_vec3 target;
        if (k % 5 == 0 && f->tess.vertex_count)
            target = dfx_vertex(&f->tess, rnd(seed) % f->tess.vertex_count);
        else
            target = mr_v3(lo.x + e.x * rndf(seed, 0, 1), lo.y + e.y * rndf(seed, 0, 1),
                           lo.z + e.z * rndf(seed, 0, 1));
        mr_vec3 d = mr_v3_sub(target, o);
        if (mr_v3_len(d) == 0)
            continue;
        bad += dfx_check_ray(f, o, d, 0.0f, INFINITY);
    }
    return bad;
}

#endif
