/*
 * pose.c - clip sampling and pose evaluation (see pose.h).
 *
 * A pose starts from every node's rest local transform. A clip channel
 * replaces the local transform of its node by T * R * S built from the
 * sampled keys; a component (translation, rotation or scale) that the channel
 * has no keys for keeps its rest value, decomposed once per node in
 * mr_pose_new. Nodes that no channel touches keep their rest matrix
 * unchanged (not recomposed), so rest poses are exact and shear survives.
 * Joint overrides then replace whole local matrices, and globals are composed
 * parent before child (the order asset.h guarantees).
 *
 * Sampling: keys are strictly increasing in time (the importer enforces it).
 * Positions and scales interpolate linearly, rotations by shortest-path slerp;
 * before the first key and after the last the end key holds.
 */
#include "anim/pose.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* mr_pose is the public head of this block; mr_pose_new is the only way to
 * make one, so mr_pose_free and mr_pose_eval may cast back. */
typedef struct pose_impl {
    mr_pose pub;
    const mr_asset *asset; /* the asset the rest decomposition was taken from */
    mr_vec3 *rest_t;
    mr_quat *rest_r;
    mr_vec3 *rest_s;
} pose_impl;

int mr_pose_new(const mr_asset *asset, mr_pose **out, mr_error *err)
{
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "mr_pose_new: out is NULL");
    *out = NULL;
    if (!asset)
        return mr_error_set(err, MR_ERR_INVALID, "mr_pose_new: asset is NULL");
    size_t n = asset->node_count;
    pose_impl *p = calloc(1, sizeof *p);
    if (!p)
        goto nomem;
    p->asset = asset;
    p->pub.node_count = n;
    if (n > 0) {
        p->pub.local = malloc(n * sizeof(mr_mat4));
        p->pub.global = malloc(n * sizeof(mr_mat4));
        p->rest_t = malloc(n * sizeof(mr_vec3));
        p->rest_r = malloc(n * sizeof(mr_quat));
        p->rest_s = malloc(n * sizeof(mr_vec3));
        if (!p->pub.local || !p->pub.global || !p->rest_t || !p->rest_r || !p->rest_s)
            goto nomem;
    }
    for (size_t i = 0; i < n; i++) {
        /* A zero scale axis (to_trs returns false) leaves identity rotation
         * and the measured scale: a channel that animates only some
         * components of such a node then rebuilds it degenerate, as the file
         * asked. */
        mr_mat4_to_trs(&asset->nodes[i].local, &p->rest_t[i], &p->rest_r[i], &p->rest_s[i]);
    }
    int rc = mr_pose_eval(&p->pub, asset, NULL, 0.0, err);
    if (rc < 0) {
        mr_pose_free(&p->pub);
        return rc;
    }
    *out = &p->pub;
    return MR_OK;
nomem:
    mr_pose_free(p ? &p->pub : NULL);
    return mr_error_set(err, MR_ERR_NOMEM, "mr_pose_new: out of memory for %zu nodes", n);
}

void mr_pose_free(mr_pose *pose)
{
    if (!pose)
        return;
    pose_impl *p = (pose_impl *)pose;
    free(p->pub.local);
    free(p->pub.global);
    free(p->rest_t);
    free(p->rest_r);
    free(p->rest_s);
    free(p);
}

double mr_pose_clip_time(const mr_clip *clip, const mr_pose_desc *desc, double frame_time)
{
    double t;
    bool loop = true;
    if (desc) {
        t = desc->has_time ? desc->time : desc->offset + desc->speed * frame_time;
        loop = desc->loop;
    } else {
        t = frame_time;
    }
    double d = clip ? clip->duration : 0.0;
    if (!isfinite(t) || !(d > 0.0) || !isfinite(d))
        return 0.0;
    if (loop) {
        t = fmod(t, d);
        if (t < 0.0)
            t += d;
        /* -tiny + d rounds to d, which is outside [0, d): take the float
         * just below d, the time the wrap came from. */
        if (t >= d)
            t = nextafter(d, 0.0);
        return t;
    }
    return t < 0.0 ? 0.0 : (t > d ? d : t);
}

/* Index of the last key with time <= t, given keys[0].time < t < keys[n-1].time. */
#define KEY_SEARCH(keys, n, t, out)                     \
    do {                                                \
        size_t lo_ = 0, hi_ = (n) - 1;                  \
        while (hi_ - lo_ > 1) {                         \
            size_t mid_ = lo_ + (hi_ - lo_) / 2;        \
            if ((keys)[mid_].time <= (t))               \
                lo_ = mid_;                             \
            else                                        \
                hi_ = mid_;                             \
        }                                               \
        (out) = lo_;                                    \
    } while (0)

static mr_vec3 sample_vec(const mr_vec3_key *k, size_t n, double t, mr_vec3 rest)
{
    if (n == 0)
        return rest;
    if (t <= k[0].time)
        return k[0].value;
    if (t >= k[n - 1].time)
        return k[n - 1].value;
    size_t i;
    KEY_SEARCH(k, n, t, i);
    float u = (float)((t - k[i].time) / (k[i + 1].time - k[i].time));
    return mr_v3_lerp(k[i].value, k[i + 1].value, u);
}

static mr_quat sample_quat(const mr_quat_key *k, size_t n, double t, mr_quat rest)
{
    if (n == 0)
        return rest;
    if (t <= k[0].time)
        return k[0].value;
    if (t >= k[n - 1].time)
        return k[n - 1].value;
    size_t i;
    KEY_SEARCH(k, n, t, i);
    float u = (float)((t - k[i].time) / (k[i + 1].time - k[i].time));
    return mr_quat_slerp(k[i].value, k[i + 1].value, u);
}

/* Lists the clip names into buf for a "not found" message, truncated. */
static void list_clips(const mr_asset *asset, char *buf, size_t size)
{
    size_t used = 0;
    buf[0] = '\0';
    for (size_t i = 0; i < asset->clip_count && used + 1 < size; i++) {
        int w = snprintf(buf + used, size - used, "%s'%s'", i ? ", " : "",
                         asset->clips[i].name ? asset->clips[i].name : "");
        if (w < 0)
            break;
        used += (size_t)w;
    }
    if (used >= size && size > 4)
        memcpy(buf + size - 4, "...", 4);
    if (asset->clip_count == 0)
        snprintf(buf, size, "none");
}

/* Checks every name and index desc refers to against asset, and finds its
 * clip (NULL when it has none). */
static int resolve_desc(const mr_asset *asset, const mr_pose_desc *desc, const mr_clip **clip_out,
                        mr_error *err)
{
    const mr_clip *clip = NULL;
    size_t n = asset->node_count;
    if (desc && desc->has_clip) {
        int ci = desc->clip_name ? mr_asset_find_clip(asset, desc->clip_name) : desc->clip_index;
        if (ci < 0 || (size_t)ci >= asset->clip_count) {
            char names[300];
            list_clips(asset, names, sizeof names);
            if (desc->clip_name)
                return mr_error_set(err, MR_ERR_NOT_FOUND,
                                    "%s: no clip named '%s' (clips: %s)", asset->path,
                                    desc->clip_name, names);
            return mr_error_set(err, MR_ERR_NOT_FOUND,
                                "%s: no clip with index %d (%zu clips: %s)", asset->path,
                                desc->clip_index, asset->clip_count, names);
        }
        clip = &asset->clips[ci];
        for (size_t c = 0; c < clip->channel_count; c++)
            if (clip->channels[c].node < 0 || (size_t)clip->channels[c].node >= n)
                return mr_error_set(err, MR_ERR_INVALID, "%s: clip '%s' channel %zu names node %d",
                                    asset->path, clip->name ? clip->name : "", c,
                                    clip->channels[c].node);
    }
    if (desc && desc->joint_count > 0 && !desc->joints)
        return mr_error_set(err, MR_ERR_INVALID, "mr_pose_eval: joint overrides are NULL");
    for (size_t j = 0; desc && j < desc->joint_count; j++) {
        const mr_joint_override *o = &desc->joints[j];
        if (!o->joint || mr_asset_find_node(asset, o->joint) < 0)
            return mr_error_set(err, MR_ERR_NOT_FOUND, "%s: no joint (node) named '%s'",
                                asset->path, o->joint ? o->joint : "(null)");
        if (!mr_mat4_is_finite(&o->local))
            return mr_error_set(err, MR_ERR_INVALID, "joint '%s': non-finite transform",
                                o->joint);
    }
    *clip_out = clip;
    return MR_OK;
}

int mr_pose_desc_check(const mr_asset *asset, const mr_pose_desc *desc, mr_error *err)
{
    const mr_clip *clip;
    return resolve_desc(asset, desc, &clip, err);
}

int mr_pose_eval(mr_pose *pose, const mr_asset *asset, const mr_pose_desc *desc,
                 double frame_time, mr_error *err)
{
    if (!pose || !asset)
        return mr_error_set(err, MR_ERR_INVALID, "mr_pose_eval: pose or asset is NULL");
    pose_impl *p = (pose_impl *)pose;
    if (p->asset != asset || pose->node_count != asset->node_count)
        return mr_error_set(err, MR_ERR_INVALID,
                            "mr_pose_eval: the pose was made for another asset");
    size_t n = asset->node_count;
    for (size_t i = 0; i < n; i++) {
        int parent = asset->nodes[i].parent;
        if (parent >= (int)i || parent < -1)
            return mr_error_set(err, MR_ERR_INVALID,
                                "mr_pose_eval: node %zu ('%s') has parent %d, not an earlier node",
                                i, asset->nodes[i].name, parent);
    }

    /* Resolve every name first so a failing call leaves the pose untouched. */
    const mr_clip *clip = NULL;
    int rc = resolve_desc(asset, desc, &clip, err);
    if (rc < 0)
        return rc;

    for (size_t i = 0; i < n; i++)
        pose->local[i] = asset->nodes[i].local;
    if (clip) {
        double t = mr_pose_clip_time(clip, desc, frame_time);
        for (size_t c = 0; c < clip->channel_count; c++) {
            const mr_channel *ch = &clip->channels[c];
            size_t ni = (size_t)ch->node;
            if (ch->position_count == 0 && ch->rotation_count == 0 && ch->scale_count == 0)
                continue;
            mr_vec3 tr = sample_vec(ch->positions, ch->position_count, t, p->rest_t[ni]);
            mr_quat r = sample_quat(ch->rotations, ch->rotation_count, t, p->rest_r[ni]);
            mr_vec3 s = sample_vec(ch->scales, ch->scale_count, t, p->rest_s[ni]);
            pose->local[ni] = mr_mat4_from_trs(tr, r, s);
        }
    }
    for (size_t j = 0; desc && j < desc->joint_count; j++) {
        int ni = mr_asset_find_node(asset, desc->joints[j].joint);
        pose->local[ni] = desc->joints[j].local;
    }
    for (size_t i = 0; i < n; i++) {
        int parent = asset->nodes[i].parent;
        pose->global[i] = parent < 0 ? pose->local[i]
                                     : mr_mat4_mul(&pose->global[parent], &pose->local[i]);
    }
    return MR_OK;
}

void mr_pose_desc_clear(mr_pose_desc *p)
{
    if (!p)
        return;
    free(p->clip_name);
    if (p->joints)
        for (size_t i = 0; i < p->joint_count; i++)
            free(p->joints[i].joint);
    free(p->joints);
    *p = (mr_pose_desc){0};
}
