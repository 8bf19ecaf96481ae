/*
 * test_skin.c - pose evaluation, clip sampling and linear blend skinning on a
 * hand-built two-bone fixture whose results are worked out by hand below, plus
 * tangents moved with it, influence renormalisation and thread-count
 * independence on a real model.
 *
 * Tolerance: 1e-5 absolute unless stated. Every checked value is O(1) and goes
 * through a handful of float32 operations (two 4x4 products, a weighted sum, a
 * normalisation), each rounding by at most 2^-24 relative, so errors stay
 * around 1e-6; 1e-5 leaves a margin while still catching any wrong term.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <cmocka.h>

#include "anim/pose.h"
#include "asset/asset.h"

#define TOL 1e-5
#define PI_F 3.14159265358979f
#define FBX_MODEL "/usr/share/assimp/models/FBX/animation_with_skeleton.fbx"
#define ZAE_MODEL "/usr/share/assimp/models/Collada/human.zae"

static void near(double got, double want, double tol, const char *what)
{
    if (!(fabs(got - want) <= tol))
        fail_msg("%s: expected %.9g, got %.9g (tol %g)", what, want, got, tol);
}

static void near3(const float *got, double x, double y, double z, const char *what)
{
    near(got[0], x, TOL, what);
    near(got[1], y, TOL, what);
    near(got[2], z, TOL, what);
}

static mr_mat4 translate(float x, float y, float z)
{
    mr_mat4 m = mr_mat4_identity();
    m.m[3] = x;
    m.m[7] = y;
    m.m[11] = z;
    return m;
}

static mr_mat4 rot_z(float radians)
{
    return mr_mat4_from_trs(mr_v3(0, 0, 0), mr_quat_from_axis_angle(mr_v3(0, 0, 1), radians),
                            mr_v3(1, 1, 1));
}

/*
 * The fixture. Nodes: 0 "root" (places the mesh, identity), 1 "bone0" child
 * of root at the origin, 2 "bone1" child of bone0 at x = 1. Bind pose = rest
 * pose, so inverse_bind(bone0) = I and inverse_bind(bone1) = T(-1,0,0).
 *
 *   vertex  position    normal    influences
 *   0       (0,0,0)     (0,0,1)   bone0 1
 *   1       (1,0,0)     (0,0,1)   bone0 .5, bone1 .5
 *   2       (2,0,0)     (0,1,0)   bone1 1
 *   3       (2,1,0)     (0,0,1)   bone1 1
 *   4       (1.5,0,0)   (0,1,0)   bone0 .5, bone1 .5
 *   5       (0,1,0)     (0,0,1)   none (rigid: follows root)
 */
static mr_asset *make_fixture(void)
{
    static const float pos[] = {0, 0, 0, 1, 0, 0, 2, 0, 0, 2, 1, 0, 1.5f, 0, 0, 0, 1, 0};
    static const float nrm[] = {0, 0, 1, 0, 0, 1, 0, 1, 0, 0, 0, 1, 0, 1, 0, 0, 0, 1};
    static const uint32_t idx[] = {0, 1, 5, 1, 2, 3, 1, 4, 3};
    mr_asset *a = NULL;
    mr_error err = {0};
    int rc = mr_asset_from_mesh("root", pos, nrm, 6, idx, 3, &a, &err);
    if (rc != MR_OK)
        fail_msg("mr_asset_from_mesh: %s", err.msg);

    mr_node *nodes = realloc(a->nodes, 3 * sizeof *nodes);
    assert_non_null(nodes);
    a->nodes = nodes;
    a->node_count = 3;
    nodes[1] = (mr_node){strdup("bone0"), 0, mr_mat4_identity()};
    nodes[2] = (mr_node){strdup("bone1"), 1, translate(1, 0, 0)};

    mr_mesh *m = &a->meshes[0];
    m->joint_count = 2;
    m->joint_nodes = malloc(2 * sizeof(int));
    m->inverse_bind = malloc(2 * sizeof(mr_mat4));
    m->joints = calloc(6 * MR_MAX_INFLUENCES, sizeof(uint16_t));
    m->weights = calloc(6 * MR_MAX_INFLUENCES, sizeof(float));
    assert_true(m->joint_nodes && m->inverse_bind && m->joints && m->weights);
    m->joint_nodes[0] = 1;
    m->joint_nodes[1] = 2;
    m->inverse_bind[0] = mr_mat4_identity();
    m->inverse_bind[1] = translate(-1, 0, 0);
    /* vertex: (joint, weight) pairs, through the importer's own rule */
    static const uint32_t vj[6][2] = {{0, 0}, {0, 1}, {1, 0}, {1, 0}, {0, 1}, {0, 0}};
    static const float vw[6][2] = {{1, 0}, {.5f, .5f}, {1, 0}, {1, 0}, {.5f, .5f}, {0, 0}};
    for (int v = 0; v < 6; v++)
        mr_influences_normalize(vj[v], vw[v], 2, &m->joints[v * MR_MAX_INFLUENCES],
                                &m->weights[v * MR_MAX_INFLUENCES]);
    return a;
}

static mr_joint_override override_of(const char *joint, mr_mat4 local)
{
    return (mr_joint_override){(char *)joint, local};
}

/* bone1 bent 90 degrees about +Z at its joint (x = 1). */
static void test_two_bone_skinning(void **state)
{
    (void)state;
    mr_asset *a = make_fixture();
    mr_pose *pose = NULL;
    mr_error err = {0};
    assert_int_equal(mr_pose_new(a, &pose, &err), MR_OK);

    mr_mat4 t1 = translate(1, 0, 0), r90 = rot_z(PI_F / 2);
    mr_mat4 bent = mr_mat4_mul(&t1, &r90);
    mr_joint_override ov = override_of("bone1", bent);
    mr_pose_desc desc = {.joint_count = 1, .joints = &ov, .loop = true};
    assert_int_equal(mr_pose_eval(pose, a, &desc, 0.0, &err), MR_OK);

    float p[18], n[18];
    mr_skin_mesh(a, 0, pose, NULL, p, n, 1);
    /*
     * K0 = global(bone0) * IB0 = I.
     * K1 = global(bone1) * IB1 = T(1,0,0) Rz(90) T(-1,0,0): rotates about (1,0,0).
     * v0 = (0,0,0), K0                  -> (0,0,0)
     * v1 = (1,0,0) is on the pivot: both -> (1,0,0)
     * v2 = (2,0,0), K1: Rz90 (1,0,0) = (0,1,0), +x1 -> (1,1,0)
     * v3 = (2,1,0), K1: Rz90 (1,1,0) = (-1,1,0), +x1 -> (0,1,0)
     * v4 = (1.5,0,0), half K0 (1.5,0,0) + half K1 (1,0.5,0) -> (1.25,0.25,0)
     *      (the linear-blend "collapse" towards the pivot)
     * v5 rigid to root (identity)        -> (0,1,0)
     */
    near3(&p[0], 0, 0, 0, "v0");
    near3(&p[3], 1, 0, 0, "v1");
    near3(&p[6], 1, 1, 0, "v2");
    near3(&p[9], 0, 1, 0, "v3");
    near3(&p[12], 1.25, 0.25, 0, "v4");
    near3(&p[15], 0, 1, 0, "v5");
    /*
     * Normals: (0,0,1) is the rotation axis, it stays (0,0,1) everywhere.
     * v2: Rz90 (0,1,0) = (-1,0,0).
     * v4: blend B = (I + K1)/2, linear part 0.5 [[1,-1,0],[1,1,0],[0,0,2]].
     *     Its cofactor (det * inverse transpose) is proportional to
     *     [[1,-1,0],[1,1,0],[0,0,..]], so (0,1,0) -> (-1,1,0)/sqrt2: the normal
     *     turns 45 degrees, halfway, as the blended surface does.
     */
    near3(&n[0], 0, 0, 1, "n0");
    near3(&n[3], 0, 0, 1, "n1");
    near3(&n[6], -1, 0, 0, "n2");
    near3(&n[9], 0, 0, 1, "n3");
    near3(&n[12], -M_SQRT1_2, M_SQRT1_2, 0, "n4");
    near3(&n[15], 0, 0, 1, "n5");

    /* object_transform applies after skinning: T(0,0,5) lifts every vertex. */
    mr_mat4 lift = translate(0, 0, 5);
    mr_skin_mesh(a, 0, pose, &lift, p, n, 1);
    near3(&p[6], 1, 1, 5, "v2 lifted");
    near3(&p[12], 1.25, 0.25, 5, "v4 lifted");
    near3(&p[15], 0, 1, 5, "v5 lifted");
    near3(&n[12], -M_SQRT1_2, M_SQRT1_2, 0, "n4 lifted");

    /* The rest pose reproduces the bind pose: every vertex where it was. */
    assert_int_equal(mr_pose_eval(pose, a, NULL, 0.0, &err), MR_OK);
    mr_skin_mesh(a, 0, pose, NULL, p, n, 1);
    for (int i = 0; i < 18; i++) {
        near(p[i], a->meshes[0].positions[i], TOL, "rest position");
        near(n[i], a->meshes[0].normals[i], TOL, "rest normal");
    }
    mr_pose_free(pose);
    mr_asset_free(a);
}

/* Tangents (asset.h mr_mesh.tangents) move with the blended matrix and are
 * made orthogonal to the moved normal: bone1 bent 90 degrees as above,
 * every vertex's tangent +x. */
static void test_tangents(void **state)
{
    (void)state;
    mr_asset *a = make_fixture();
    mr_mesh *m = &a->meshes[0];
    m->tangents = calloc(6 * 4, sizeof(float));
    assert_non_null(m->tangents);
    for (int v = 0; v < 6; v++) {
        m->tangents[v * 4] = 1;
        m->tangents[v * 4 + 3] = v == 3 ? -1.0f : 1.0f; /* handedness: not moved */
    }
    mr_pose *pose = NULL;
    mr_error err = {0};
    assert_int_equal(mr_pose_new(a, &pose, &err), MR_OK);
    mr_mat4 t1 = translate(1, 0, 0), r90 = rot_z(PI_F / 2);
    mr_mat4 bent = mr_mat4_mul(&t1, &r90);
    mr_joint_override ov = override_of("bone1", bent);
    mr_pose_desc desc = {.joint_count = 1, .joints = &ov, .loop = true};
    assert_int_equal(mr_pose_eval(pose, a, &desc, 0.0, &err), MR_OK);
    float p[18], n[18], t[18], p2[18], n2[18];
    mr_skin_mesh_tangents(a, 0, pose, NULL, p, n, t, 1);
    /* positions and normals are mr_skin_mesh's, bit for bit */
    mr_skin_mesh(a, 0, pose, NULL, p2, n2, 1);
    assert_memory_equal(p, p2, sizeof p);
    assert_memory_equal(n, n2, sizeof n);
    /*
     * v0, v5: K0 = I and rigid: (1,0,0). v2, v3: Rz90 (1,0,0) = (0,1,0).
     * v1: B = (I + K1)/2, linear part 0.5 [[1,-1,0],[1,1,0],[0,0,2]]:
     *     (1,0,0) -> (0.5,0.5,0), unit (1,1,0)/sqrt2; its normal (0,0,1)
     *     is orthogonal to it already. v4: the same, and its normal
     *     (-1,1,0)/sqrt2 is too (the blend turns both by 45 degrees).
     */
    near3(&t[0], 1, 0, 0, "t0");
    near3(&t[3], M_SQRT1_2, M_SQRT1_2, 0, "t1");
    near3(&t[6], 0, 1, 0, "t2");
    near3(&t[9], 0, 1, 0, "t3");
    near3(&t[12], M_SQRT1_2, M_SQRT1_2, 0, "t4");
    near3(&t[15], 1, 0, 0, "t5");
    /* a scale that does not keep angles: the tangent is fitted to the
     * normal again (Gram-Schmidt), unit and orthogonal to it */
    mr_mat4 shear = mr_mat4_identity();
    shear.m[1] = 0.8f; /* x += 0.8 y */
    shear.m[6] = 0.5f; /* y += 0.5 z */
    mr_skin_mesh_tangents(a, 0, pose, &shear, p, n, t, 1);
    /* v0: S (1,0,0) = (1,0,0), its normal S^-T (0,0,1) = (0,0,1); v2:
     * S Rz90 (1,0,0) = S (0,1,0) = (0.8,1,0), normal S^-T (-1,0,0) =
     * (-1,0.8,-0.4), orthogonal to it already: (0.8,1,0)/sqrt(1.64) */
    near3(&t[0], 1, 0, 0, "sheared t0");
    near3(&t[6], 0.8 / sqrt(1.64), 1 / sqrt(1.64), 0, "sheared t2");
    for (int v = 0; v < 6; v++) {
        double len = sqrt((double)t[v * 3] * t[v * 3] + (double)t[v * 3 + 1] * t[v * 3 + 1] +
                          (double)t[v * 3 + 2] * t[v * 3 + 2]);
        near(len, 1, TOL, "sheared tangent length");
        near(t[v * 3] * n[v * 3] + t[v * 3 + 1] * n[v * 3 + 1] + t[v * 3 + 2] * n[v * 3 + 2], 0, TOL,
             "sheared tangent . normal");
    }
    /* a mesh without tangents leaves the buffer alone */
    free(m->tangents);
    m->tangents = NULL;
    memset(t, 0x7f, sizeof t);
    mr_skin_mesh_tangents(a, 0, pose, NULL, p, n, t, 1);
    for (int i = 0; i < 18; i++)
        assert_true(t[i] == t[0] && t[0] > 1e30f);
    mr_pose_free(pose);
    mr_asset_free(a);
}

/* Explicit joint overrides replace the local transform of the named node
 * and propagate to its children; unknown joints are named in the error. */
static void test_joint_override(void **state)
{
    (void)state;
    mr_asset *a = make_fixture();
    mr_pose *pose = NULL;
    mr_error err = {0};
    assert_int_equal(mr_pose_new(a, &pose, &err), MR_OK);

    /* bone0 rotated 90 degrees about Z at the origin: bone1 (at x = 1 in
     * bone0's space) lands at (0,1,0); the whole arm turns rigidly. */
    mr_joint_override ov = override_of("bone0", rot_z(PI_F / 2));
    mr_pose_desc desc = {.joint_count = 1, .joints = &ov, .loop = true};
    assert_int_equal(mr_pose_eval(pose, a, &desc, 0.0, &err), MR_OK);
    near(pose->global[2].m[3], 0, TOL, "bone1 x");
    near(pose->global[2].m[7], 1, TOL, "bone1 y");
    for (int i = 0; i < 16; i++)
        near(pose->local[1].m[i], ov.local.m[i], 0, "override copied exactly");
    float p[18];
    mr_skin_mesh(a, 0, pose, NULL, p, NULL, 2);
    near3(&p[6], 0, 2, 0, "v2 = Rz90 (2,0,0)");
    near3(&p[12], 0, 1.5, 0, "v4 = Rz90 (1.5,0,0)");

    /* Unknown joint: MR_ERR_NOT_FOUND naming it, pose left as it was. */
    mr_mat4 before = pose->global[2];
    mr_joint_override bad[2] = {override_of("bone0", mr_mat4_identity()),
                                override_of("no_such_bone", mr_mat4_identity())};
    desc.joints = bad;
    desc.joint_count = 2;
    assert_int_equal(mr_pose_eval(pose, a, &desc, 0.0, &err), MR_ERR_NOT_FOUND);
    assert_non_null(strstr(err.msg, "no_such_bone"));
    assert_memory_equal(&before, &pose->global[2], sizeof before);

    /* A non-finite override is refused rather than poisoning the frame. */
    mr_mat4 nan_m = mr_mat4_identity();
    nan_m.m[3] = NAN;
    mr_joint_override nan_ov = override_of("bone1", nan_m);
    desc.joints = &nan_ov;
    desc.joint_count = 1;
    assert_int_equal(mr_pose_eval(pose, a, &desc, 0.0, &err), MR_ERR_INVALID);
    mr_pose_free(pose);
    mr_asset_free(a);
}

/* Adds a clip "bend" to the fixture: bone1 keys at t = 0 and t = 1,
 * position (1,0,0) -> (3,0,0), rotation 0 -> 90 degrees about Z, no scale
 * keys; duration 2, so (1, 2] lies after the last key. */
static void add_clip(mr_asset *a)
{
    a->clips = calloc(1, sizeof *a->clips);
    assert_non_null(a->clips);
    a->clip_count = 1;
    mr_clip *c = &a->clips[0];
    c->name = strdup("bend");
    c->duration = 2.0;
    c->channels = calloc(1, sizeof *c->channels);
    c->channel_count = 1;
    mr_channel *ch = &c->channels[0];
    ch->node = 2;
    ch->position_count = 2;
    ch->positions = malloc(2 * sizeof *ch->positions);
    ch->positions[0] = (mr_vec3_key){0.0, mr_v3(1, 0, 0)};
    ch->positions[1] = (mr_vec3_key){1.0, mr_v3(3, 0, 0)};
    ch->rotation_count = 2;
    ch->rotations = malloc(2 * sizeof *ch->rotations);
    ch->rotations[0] = (mr_quat_key){0.0, mr_quat_identity()};
    ch->rotations[1] = (mr_quat_key){1.0, mr_quat_from_axis_angle(mr_v3(0, 0, 1), PI_F / 2)};
}

/* Sampled local of bone1 at clip time t (explicit time). */
static mr_mat4 sample_at(mr_pose *pose, const mr_asset *a, double t, bool loop)
{
    mr_error err = {0};
    mr_pose_desc desc = {.has_clip = true, .clip_name = "bend", .has_time = true, .time = t,
                         .loop = loop};
    int rc = mr_pose_eval(pose, a, &desc, 123.0 /* ignored: explicit time */, &err);
    if (rc != MR_OK)
        fail_msg("mr_pose_eval: %s", err.msg);
    return pose->local[2];
}

static void check_local(mr_mat4 m, double tx, double angle_deg, double scale, const char *what)
{
    double c = cos(angle_deg * M_PI / 180) * scale, s = sin(angle_deg * M_PI / 180) * scale;
    near(m.m[3], tx, TOL, what);
    near(m.m[7], 0, TOL, what);
    near(m.m[0], c, TOL, what);
    near(m.m[1], -s, TOL, what);
    near(m.m[4], s, TOL, what);
    near(m.m[5], c, TOL, what);
    near(m.m[10], scale, TOL, what);
}

static void test_clip_sampling(void **state)
{
    (void)state;
    mr_asset *a = make_fixture();
    /* Rest scale 2 on bone1: the clip has no scale keys, so the sampled
     * local must keep it (decomposed from the rest matrix at mr_pose_new). */
    mr_mat4 s2 = mr_mat4_from_trs(mr_v3(1, 0, 0), mr_quat_identity(), mr_v3(2, 2, 2));
    a->nodes[2].local = s2;
    add_clip(a);
    mr_pose *pose = NULL;
    mr_error err = {0};
    assert_int_equal(mr_pose_new(a, &pose, &err), MR_OK);

    /* t = 0.25: position lerps to 1 + 0.25 * 2 = 1.5; slerp gives 22.5 degrees. */
    check_local(sample_at(pose, a, 0.25, true), 1.5, 22.5, 2, "t=0.25");
    /* t = 0.5: slerp midpoint of 0 and 90 degrees is 45 degrees (nlerp would
     * also give 45 here; at t = 0.25 above they part: nlerp gives 21.6). */
    check_local(sample_at(pose, a, 0.5, true), 2.0, 45, 2, "t=0.5");
    /* Key times themselves. */
    check_local(sample_at(pose, a, 0.0, true), 1.0, 0, 2, "t=0");
    check_local(sample_at(pose, a, 1.0, true), 3.0, 90, 2, "t=1");
    /* After the last key (inside the 2 s clip): the last key holds. */
    check_local(sample_at(pose, a, 1.5, true), 3.0, 90, 2, "t=1.5 after keys");
    /* Clamped (loop off) before the start and after the end. */
    check_local(sample_at(pose, a, -3.0, false), 1.0, 0, 2, "clamp before");
    check_local(sample_at(pose, a, 7.0, false), 3.0, 90, 2, "clamp after");
    /* Looped: 2.25 and -1.75 wrap to 0.25. */
    check_local(sample_at(pose, a, 2.25, true), 1.5, 22.5, 2, "wrap 2.25");
    check_local(sample_at(pose, a, -1.75, true), 1.5, 22.5, 2, "wrap -1.75");

    /* Clip time from the frame time: offset + speed * frame_time. */
    const mr_clip *c = &a->clips[0];
    mr_pose_desc d = {.has_clip = true, .speed = 0.5, .offset = 0.25, .loop = true};
    near(mr_pose_clip_time(c, &d, 4.0), 0.25, 1e-12, "0.25 + 0.5*4 = 2.25 -> 0.25");
    d.loop = false;
    near(mr_pose_clip_time(c, &d, 4.0), 2.0, 0, "clamped to the duration");
    near(mr_pose_clip_time(c, &d, -4.0), 0.0, 0, "clamped to 0");
    d.loop = true;
    /* A tiny negative time wraps to just below the duration, never to it. */
    double w = mr_pose_clip_time(c, &(mr_pose_desc){.has_time = true, .time = -1e-300,
                                                     .loop = true}, 0);
    assert_true(w < 2.0 && w > 1.999);
    mr_clip zero = {.duration = 0};
    near(mr_pose_clip_time(&zero, &d, 3.0), 0.0, 0, "zero duration -> 0");
    near(mr_pose_clip_time(c, &(mr_pose_desc){.has_time = true, .time = NAN}, 0), 0, 0, "NaN");

    /* Channels, then overrides: an override on the animated node wins. */
    mr_joint_override ov = override_of("bone1", mr_mat4_identity());
    mr_pose_desc both = {.has_clip = true, .clip_index = 0, .has_time = true, .time = 0.5,
                         .loop = true, .joint_count = 1, .joints = &ov};
    assert_int_equal(mr_pose_eval(pose, a, &both, 0, &err), MR_OK);
    assert_memory_equal(&pose->local[2], &ov.local, sizeof ov.local);

    /* Unknown clip names and indices: MR_ERR_NOT_FOUND listing the clips. */
    mr_pose_desc bad = {.has_clip = true, .clip_name = "walk", .loop = true};
    assert_int_equal(mr_pose_eval(pose, a, &bad, 0, &err), MR_ERR_NOT_FOUND);
    assert_non_null(strstr(err.msg, "walk"));
    assert_non_null(strstr(err.msg, "bend"));
    bad.clip_name = NULL;
    bad.clip_index = 3;
    assert_int_equal(mr_pose_eval(pose, a, &bad, 0, &err), MR_ERR_NOT_FOUND);
    assert_non_null(strstr(err.msg, "bend"));
    bad.clip_index = -1;
    assert_int_equal(mr_pose_eval(pose, a, &bad, 0, &err), MR_ERR_NOT_FOUND);

    /* A pose only works with the asset it was made for. */
    mr_asset *other = make_fixture();
    assert_int_equal(mr_pose_eval(pose, other, NULL, 0, &err), MR_ERR_INVALID);
    mr_asset_free(other);
    mr_pose_free(pose);
    mr_asset_free(a);
}

/* The importer's influence rule: drop NaN / negative / zero weights, merge
 * repeated joints, keep the 8 largest, renormalise to sum 1. */
static void test_weights_renormalised(void **state)
{
    (void)state;
    uint16_t j[MR_MAX_INFLUENCES];
    float w[MR_MAX_INFLUENCES];
    /* Two influences summing to 0.4: renormalised to 0.5 / 0.5. */
    const uint32_t j2[] = {3, 7};
    const float w2[] = {0.2f, 0.2f};
    assert_int_equal(mr_influences_normalize(j2, w2, 2, j, w), 2);
    near(w[0], 0.5, 1e-7, "w0");
    near(w[1], 0.5, 1e-7, "w1");
    assert_int_equal(j[0], 3); /* equal weights: file order */
    assert_int_equal(j[1], 7);

    /* Twelve raw entries: joint 1 twice (0.05 + 0.3 = 0.35, the largest),
     * a NaN, a negative and a zero weight, and more than 8 valid joints. */
    const uint32_t jj[] = {1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 1};
    const float ww[] = {0.05f, 0.01f, NAN, 0.2f, -0.5f, 0.1f, 0.09f, 0.08f,
                        0.07f, 0.06f, 0.0f, 0.3f};
    /* Valid after merging: j1 .35, j4 .2, j6 .1, j7 .09, j8 .08, j9 .07,
     * j10 .06, j2 .01 -> exactly 8, sum 0.96; a ninth (j12 below) at 0.005
     * must be the one dropped. */
    uint32_t jj9[13];
    float ww9[13];
    memcpy(jj9, jj, sizeof jj);
    memcpy(ww9, ww, sizeof ww);
    jj9[12] = 12;
    ww9[12] = 0.005f;
    int kept = mr_influences_normalize(jj9, ww9, 13, j, w);
    assert_int_equal(kept, MR_MAX_INFLUENCES);
    const uint16_t want_j[] = {1, 4, 6, 7, 8, 9, 10, 2};
    const double want_w[] = {0.35, 0.2, 0.1, 0.09, 0.08, 0.07, 0.06, 0.01};
    double sum = 0;
    for (int k = 0; k < MR_MAX_INFLUENCES; k++) {
        assert_int_equal(j[k], want_j[k]);
        near(w[k], want_w[k] / 0.96, 1e-6, "renormalised weight");
        sum += w[k];
    }
    near(sum, 1.0, 1e-6, "sum of weights");

    /* Nothing usable: rigid (0 kept, all weights 0). */
    const uint32_t jb[] = {0, 1};
    const float wb[] = {NAN, -1.0f};
    assert_int_equal(mr_influences_normalize(jb, wb, 2, j, w), 0);
    for (int k = 0; k < MR_MAX_INFLUENCES; k++)
        assert_true(w[k] == 0.0f);
    /* A long list goes through the heap path with the same rule. */
    uint32_t many_j[200];
    float many_w[200];
    for (int i = 0; i < 200; i++) {
        many_j[i] = (uint32_t)i;
        many_w[i] = (float)(i + 1);
    }
    assert_int_equal(mr_influences_normalize(many_j, many_w, 200, j, w), 8);
    assert_int_equal(j[0], 199);
    assert_int_equal(j[7], 192);
    near(w[0], 200.0 / (200 + 199 + 198 + 197 + 196 + 195 + 194 + 193), 1e-6, "heap path");
}

/* Same frame on 1, 2 and all threads: bit-identical. The FBX mesh (2464
 * vertices) is smaller than one work chunk, so it is tiled 8 times (with its
 * real skin) to make 19712 vertices = 5 chunks; human.zae covers the rigid
 * path with 14517 vertices. */
static void test_thread_independence(void **state)
{
    (void)state;
    mr_asset *a = NULL;
    mr_error err = {0};
    if (mr_asset_load(FBX_MODEL, &a, &err) != MR_OK)
        fail_msg("%s", err.msg);
    mr_mesh *m = &a->meshes[0];
    assert_true(m->joint_count > 0);
    const int tiles = 8;
    size_t nv = m->vertex_count, big = nv * tiles;
    float *pos = malloc(big * 3 * sizeof(float)), *nrm = malloc(big * 3 * sizeof(float));
    uint16_t *jo = malloc(big * MR_MAX_INFLUENCES * sizeof(uint16_t));
    float *we = malloc(big * MR_MAX_INFLUENCES * sizeof(float));
    assert_true(pos && nrm && jo && we);
    for (int t = 0; t < tiles; t++) {
        for (size_t i = 0; i < nv * 3; i++) /* offset tiles so they differ */
            pos[t * nv * 3 + i] = m->positions[i] + (float)t * 0.37f;
        memcpy(nrm + t * nv * 3, m->normals, nv * 3 * sizeof(float));
        memcpy(jo + t * nv * MR_MAX_INFLUENCES, m->joints, nv * MR_MAX_INFLUENCES * sizeof(uint16_t));
        memcpy(we + t * nv * MR_MAX_INFLUENCES, m->weights, nv * MR_MAX_INFLUENCES * sizeof(float));
    }
    free(m->positions);
    free(m->normals);
    free(m->joints);
    free(m->weights);
    m->positions = pos;
    m->normals = nrm;
    m->joints = jo;
    m->weights = we;
    m->vertex_count = (uint32_t)big; /* triangles keep indexing the first tile */

    mr_pose *pose = NULL;
    assert_int_equal(mr_pose_new(a, &pose, &err), MR_OK);
    mr_pose_desc desc = {.has_clip = true, .clip_index = 0, .has_time = true, .time = 0.4,
                         .loop = true};
    assert_int_equal(mr_pose_eval(pose, a, &desc, 0, &err), MR_OK);
    mr_mat4 obj = mr_mat4_from_trs(mr_v3(1, 2, 3), mr_quat_from_axis_angle(mr_v3(1, 1, 0), 0.3f),
                                   mr_v3(1, 2, 0.5f));
    size_t bytes = big * 3 * sizeof(float);
    float *p1 = malloc(bytes), *n1 = malloc(bytes), *p2 = malloc(bytes), *n2 = malloc(bytes);
    assert_true(p1 && n1 && p2 && n2);
    mr_skin_mesh(a, 0, pose, &obj, p1, n1, 1);
    memset(p2, 0xff, bytes);
    memset(n2, 0xff, bytes);
    mr_skin_mesh(a, 0, pose, &obj, p2, n2, 2);
    assert_memory_equal(p1, p2, bytes);
    assert_memory_equal(n1, n2, bytes);
    mr_skin_mesh(a, 0, pose, &obj, p2, n2, 0);
    assert_memory_equal(p1, p2, bytes);
    assert_memory_equal(n1, n2, bytes);
    /* and the pose really moved something: Bone.005 is animated */
    int moved = 0;
    for (size_t i = 0; i < nv && !moved; i++) {
        mr_vec3 r = mr_mat4_point(&obj, mr_mat4_point(&pose->global[m->node],
                                  mr_v3(pos[i * 3], pos[i * 3 + 1], pos[i * 3 + 2])));
        moved = fabsf(r.x - p1[i * 3]) + fabsf(r.y - p1[i * 3 + 1]) + fabsf(r.z - p1[i * 3 + 2]) > 1.0f;
    }
    assert_true(moved);
    free(p1);
    free(n1);
    free(p2);
    free(n2);
    mr_pose_free(pose);
    mr_asset_free(a);

    /* Rigid path on a static model. */
    if (mr_asset_load(ZAE_MODEL, &a, &err) != MR_OK)
        fail_msg("%s", err.msg);
    assert_int_equal(mr_pose_new(a, &pose, &err), MR_OK);
    m = &a->meshes[0];
    bytes = (size_t)m->vertex_count * 3 * sizeof(float);
    p1 = malloc(bytes), n1 = malloc(bytes), p2 = malloc(bytes), n2 = malloc(bytes);
    float *t1 = malloc(bytes), *t2 = malloc(bytes);
    assert_true(p1 && n1 && p2 && n2 && t1 && t2 && m->tangents);
    mr_skin_mesh_tangents(a, 0, pose, &obj, p1, n1, t1, 1);
    mr_skin_mesh_tangents(a, 0, pose, &obj, p2, n2, t2, 2);
    assert_memory_equal(p1, p2, bytes);
    assert_memory_equal(n1, n2, bytes);
    assert_memory_equal(t1, t2, bytes);
    free(t1);
    free(t2);
    free(p1);
    free(n1);
    free(p2);
    free(n2);
    mr_pose_free(pose);
    mr_asset_free(a);
}

/* Bad arguments never crash; a missing pose writes the mesh as it is. */
static void test_skin_bad_input(void **state)
{
    (void)state;
    mr_asset *a = make_fixture();
    float p[18], n[18];
    mr_skin_mesh(NULL, 0, NULL, NULL, p, n, 1);
    mr_skin_mesh(a, 7, NULL, NULL, p, n, 1);
    mr_skin_mesh(a, 0, NULL, NULL, NULL, n, 1);
    mr_skin_mesh(a, 0, NULL, NULL, p, n, 1);
    for (int i = 0; i < 18; i++)
        near(p[i], a->meshes[0].positions[i], 0, "mesh-space copy without a pose");
    /* A joint index beyond joint_count is ignored, not dereferenced. */
    a->meshes[0].joints[2 * MR_MAX_INFLUENCES] = 999;
    mr_pose *pose = NULL;
    mr_error err = {0};
    assert_int_equal(mr_pose_new(a, &pose, &err), MR_OK);
    mr_skin_mesh(a, 0, pose, NULL, p, n, 1);
    near3(&p[6], 2, 0, 0, "vertex with only a bad joint stays rigid");
    mr_pose_free(pose);
    assert_int_equal(mr_pose_new(NULL, &pose, &err), MR_ERR_INVALID);
    assert_true(err.msg[0] != '\0');
    mr_asset_free(a);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_two_bone_skinning),
        cmocka_unit_test(test_tangents),
        cmocka_unit_test(test_joint_override),
        cmocka_unit_test(test_clip_sampling),
        cmocka_unit_test(test_weights_renormalised),
        cmocka_unit_test(test_thread_independence),
        cmocka_unit_test(test_skin_bad_input),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
