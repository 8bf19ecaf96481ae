/* renderer.c - per-job frame loop: pose, deform, refit/build, trace (renderer.h). */
#include "render/renderer.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <unistd.h>
#include <string.h>
#include <sys/resource.h>

#include "kinds/kind.h"
#include "render/checkpoint.h"
#include "render/device.h"
#include "render/exr.h"
#include "render/integrator.h"
#include "render/reference.h"
#include "util/clock.h"
#include "util/murmur3.h"

typedef struct object_state {
    const mr_object_desc *desc;
    const mr_asset *asset;
    const mr_kind *kind;
    mr_geom *geom;
    mr_pose *pose;
    bool animated;   /* pose changes from frame to frame */
    bool view_dependent; /* its level of detail follows the camera (kind.h has_lod) */
    bool posed_once;
    size_t stepped;  /* SEQUENTIAL kinds: frames 0..stepped-1 have been applied */
    char *checkpoints; /* the kind's folder when it keeps checkpoints there (checkpoint.h) */
    uint32_t checkpoint_every;
} object_state;

struct mr_renderer {
    mr_device *dev;
    const mr_job *job;
    mr_renderer_options opt;
    size_t object_count;
    object_state *objects;
    mr_shade_object *shade;
    unsigned *id_object;  /* Embree geometry id -> object index */
    unsigned id_count;
    RTCScene scene;
    bool dynamic; /* animated: Embree's dynamic-scene settings (fast LOW builds) */
    bool refit;   /* dynamic and refitting between frames (not force_rebuild) */
    bool built;
    /* camera from an asset's camera node */
    const mr_asset *cam_asset;
    const mr_camera_info *cam_info;
    int cam_node;
    mr_pose *cam_pose;
    const object_state *cam_driver; /* object whose pose moves the camera's asset */
    const mr_kind **stat_kinds; /* the job's kinds that report stats fields, each once */
    size_t stat_kind_count;
    bool reported_once;           /* a frame carried the kinds' creation figures */
    float *crypto_ids[MR_CRYPTO_LAYERS]; /* Cryptomatte id of each object's name, its asset's */
    /* Reference passes (the job's "reference"; reference.h): each pass's
     * job, renderer and film, set up at the first frame rendered (their
     * time is the pass's, not derive's); none when no object asks. */
    bool reference;               /* some object asks */
    bool passes_ready;
    mr_asset **assets;            /* a copy of the borrowed array, for the passes' renderers */
    size_t pass_count;
    struct pass {
        mr_reference_pass pass;
        mr_renderer *renderer;
        mr_film *film;
    } passes[MR_REFERENCE_TYPES];
};

uint64_t mr_peak_rss_bytes(void)
{
    struct rusage ru;
    if (getrusage(RUSAGE_SELF, &ru) != 0)
        return 0;
    return (uint64_t)ru.ru_maxrss * 1024u; /* Linux reports KiB */
}

static const mr_pose_desc *pose_for_frame(const mr_object_desc *d, size_t frame)
{
    if (d->pose_count == 0)
        return NULL;
    if (d->pose_count == 1)
        return &d->poses[0];
    return &d->poses[frame < d->pose_count ? frame : d->pose_count - 1];
}

static bool object_is_animated(const mr_object_desc *d, size_t frame_count)
{
    if (frame_count >= 2 && d->kind->frame_order == MR_FRAMES_SEQUENTIAL)
        return true;
    if (frame_count >= 2 && d->kind->animated && d->params && d->kind->animated(d->params))
        return true;
    if (frame_count < 2 || d->pose_count == 0)
        return false;
    if (d->pose_count > 1)
        return true;
    return d->poses[0].has_clip && !d->poses[0].has_time;
}

static void passes_free(mr_renderer *r)
{
    for (size_t p = 0; p < r->pass_count; p++) {
        mr_renderer_free(r->passes[p].renderer);
        mr_film_free(r->passes[p].film);
        mr_reference_pass_clear(&r->passes[p].pass);
    }
    r->pass_count = 0;
    r->passes_ready = false;
}

void mr_renderer_free(mr_renderer *r)
{
    if (!r)
        return;
    if (r->scene)
        rtcReleaseScene(r->scene);
    for (size_t i = 0; i < r->object_count; i++) {
        if (r->objects[i].geom)
            r->objects[i].kind->free(r->objects[i].geom);
        mr_pose_free(r->objects[i].pose);
        free(r->objects[i].checkpoints);
    }
    mr_pose_free(r->cam_pose);
    passes_free(r);
    free(r->assets);
    free(r->stat_kinds);
    for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
        free(r->crypto_ids[l]);
    free(r->objects);
    free(r->shade);
    free(r->id_object);
    free(r);
}

static int setup_camera_node(mr_renderer *r, mr_asset *const *assets, mr_error *err)
{
    const mr_camera_desc *cd = &r->job->camera;
    const mr_asset *a = assets[cd->node_asset];
    int ci = mr_asset_find_camera(a, cd->node_name);
    int node = -1;
    if (ci >= 0) {
        node = a->cameras[ci].node;
    } else {
        node = mr_asset_find_node(a, cd->node_name);
    }
    if (ci < 0 && node < 0) {
        char names[256] = "";
        size_t used = 0;
        for (size_t i = 0; i < a->camera_count && used + 1 < sizeof names; i++) {
            int n = snprintf(names + used, sizeof names - used, "%s'%s'", i ? ", " : "", a->cameras[i].name);
            used += n > 0 ? (size_t)n : 0;
        }
        return mr_error_set(err, MR_ERR_NOT_FOUND,
                            "/camera/node/name: asset '%s' has no camera or node named '%s' (cameras: %s)",
                            r->job->assets[cd->node_asset].name, cd->node_name,
                            a->camera_count ? names : "none");
    }
    r->cam_asset = a;
    r->cam_info = ci >= 0 ? &a->cameras[ci] : NULL;
    r->cam_node = node;
    for (size_t i = 0; i < r->object_count; i++)
        if (r->objects[i].asset == a) {
            r->cam_driver = &r->objects[i];
            break;
        }
    return mr_pose_new(a, &r->cam_pose, err);
}

size_t mr_job_memory_default(void)
{
    long pages = sysconf(_SC_PHYS_PAGES), page = sysconf(_SC_PAGESIZE);
    return pages > 0 && page > 0 ? (size_t)pages * (size_t)page / 2 : (size_t)4 << 30;
}

int mr_renderer_new(mr_device *dev, const mr_job *job, mr_asset *const *assets,
                    const mr_renderer_options *opt, mr_renderer **out, mr_error *err)
{
    int rc = MR_OK;
    *out = NULL;
    mr_renderer *r = calloc(1, sizeof *r);
    if (!r)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory creating the renderer");
    r->dev = dev;
    r->job = job;
    if (opt)
        r->opt = *opt;
    r->object_count = job->object_count;
    r->objects = calloc(job->object_count, sizeof *r->objects);
    r->shade = calloc(job->object_count, sizeof *r->shade);
    r->stat_kinds = calloc(job->object_count ? job->object_count : 1, sizeof *r->stat_kinds);
    for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
        r->crypto_ids[l] = calloc(job->object_count ? job->object_count : 1, sizeof(float));
    if (!r->objects || !r->shade || !r->stat_kinds || !r->crypto_ids[0] || !r->crypto_ids[1]) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory creating the renderer");
        goto fail;
    }
    for (size_t i = 0; i < job->object_count; i++) {
        char buf[32];
        r->crypto_ids[MR_CRYPTO_OBJECT][i] =
            mr_cryptomatte_id(mr_crypto_name(job, MR_CRYPTO_OBJECT, i, buf));
        r->crypto_ids[MR_CRYPTO_ASSET][i] =
            mr_cryptomatte_id(mr_crypto_name(job, MR_CRYPTO_ASSET, job->objects[i].asset, buf));
    }
    uint64_t triangles = 0;
    for (size_t i = 0; i < job->object_count; i++) {
        if (!job->objects[i].kind) {
            rc = mr_error_set(err, MR_ERR_INVALID, "/objects/%zu/kind: no geometry kind", i);
            goto fail;
        }
        if (object_is_animated(&job->objects[i], job->frame_count))
            r->dynamic = true;
        const mr_kind *k = job->objects[i].kind;
        bool known = false;
        for (size_t j = 0; j < r->stat_kind_count && !known; j++)
            known = r->stat_kinds[j] == k;
        if (k->stat_count && k->frame_stats && !known)
            r->stat_kinds[r->stat_kind_count++] = k;
        triangles += assets[job->objects[i].asset]->triangle_count;
    }
    if (triangles > MR_MAX_JOB_TRIANGLES) {
        rc = mr_error_set(err, MR_ERR_LIMIT, "/objects: %zu objects hold %llu triangles in all, more than the %u a job may have",
                          job->object_count, (unsigned long long)triangles, MR_MAX_JOB_TRIANGLES);
        goto fail;
    }
    r->refit = r->dynamic && !r->opt.force_rebuild;

    RTCDevice rtc = mr_device_embree(dev);
    r->scene = rtcNewScene(rtc);
    if (!r->scene) {
        rc = mr_device_check(dev, "rtcNewScene", err);
        if (rc == MR_OK)
            rc = mr_error_set(err, MR_ERR_EMBREE, "Embree could not create a scene");
        goto fail;
    }
    /* The refit recipe: DYNAMIC + LOW on the scene, REFIT on the geometry.
     * ROBUST makes the triangle test watertight: without it, rays that run
     * exactly along a shared edge (e.g. a sphere's meridian seen head on)
     * slip between the two triangles (tests/unit/test_render.c). */
    rtcSetSceneFlags(r->scene, RTC_SCENE_FLAG_ROBUST |
                                   (r->dynamic ? RTC_SCENE_FLAG_DYNAMIC : RTC_SCENE_FLAG_NONE));
    rtcSetSceneBuildQuality(r->scene, r->dynamic ? RTC_BUILD_QUALITY_LOW : RTC_BUILD_QUALITY_MEDIUM);

    for (size_t i = 0; i < job->object_count; i++) {
        object_state *o = &r->objects[i];
        o->desc = &job->objects[i];
        o->asset = assets[o->desc->asset];
        o->kind = o->desc->kind; /* never NULL: checked above */
        if (mr_asset_is_image(o->asset)) {
            rc = mr_error_set(err, MR_ERR_INVALID,
                              "/objects/%zu/asset: \"%s\" is an image (%s), not a model; images "
                              "are named by a kind's parameters (a height texture)",
                              i, job->assets[o->desc->asset].name, o->asset->path);
            goto fail;
        }
        o->animated = object_is_animated(o->desc, job->frame_count);
        o->view_dependent = o->kind->has_lod && o->desc->tolerance_px > 0 && job->frame_count >= 2;
        for (size_t k = 0; k < o->desc->pose_count && !o->kind->self_posed; k++)
            if ((rc = mr_pose_desc_check(o->asset, &o->desc->poses[k], err)) < 0) {
                if (o->desc->pose_count == 1)
                    mr_error_prefix(err, "/objects/%zu/pose: ", i);
                else
                    mr_error_prefix(err, "/objects/%zu/pose/%zu: ", i, k);
                goto fail;
            }
        if ((rc = mr_pose_new(o->asset, &o->pose, err)) < 0)
            goto fail;
        /* the kind's folder of derived data, for create only */
        char *cache_dir = NULL;
        if ((rc = mr_kind_cache_dir(o->kind, r->opt.cache_dir, &cache_dir, err)) < 0)
            goto fail;
        mr_kind_context ctx = {.cache_dir = cache_dir, .threads = mr_device_threads(dev),
                               .memory_budget = r->opt.memory_budget,
                               .assets = (const mr_asset *const *)assets,
                               .asset_count = job->asset_count};
        rc = o->kind->create(o->asset, o->desc, &ctx, &o->geom, err);
        if (rc == MR_OK && mr_checkpoint_kept(o->kind, o->geom, cache_dir)) {
            o->checkpoints = cache_dir;
            o->checkpoint_every = o->kind->checkpoint_every(o->geom);
            cache_dir = NULL;
        }
        free(cache_dir);
        if (rc < 0) {
            if (o->kind->self_posed) /* its errors name the pose fields under the object */
                mr_error_prefix(err, "/objects/%zu/", i);
            goto fail;
        }
        /* Animated geometry refits (REFIT) or, for comparison, rebuilds with
         * the same fast builder the dynamic scene uses (LOW). */
        enum RTCBuildQuality quality = !(r->dynamic && o->animated) ? RTC_BUILD_QUALITY_MEDIUM
                                       : r->refit                   ? RTC_BUILD_QUALITY_REFIT
                                                                    : RTC_BUILD_QUALITY_LOW;
        uint32_t ids = o->kind->geometry_ids ? o->kind->geometry_ids(o->geom) : 1;
        /* The cap before the realloc: a refused object must leave id_object
         * as it was (mr_renderer_free frees it once). */
        if ((uint64_t)r->id_count + ids > UINT32_MAX / 2) {
            rc = mr_error_set(err, MR_ERR_LIMIT,
                              "/objects/%zu: %u Embree geometries would bring the scene to %llu, more "
                              "than the %u a scene may have",
                              i, ids, (unsigned long long)r->id_count + ids, UINT32_MAX / 2);
            goto fail;
        }
        if (ids) {
            unsigned *grown = realloc(r->id_object, ((size_t)r->id_count + ids) * sizeof *grown);
            if (!grown) {
                rc = mr_error_set(err, MR_ERR_NOMEM, "/objects/%zu: out of memory for %u Embree geometries", i, ids);
                goto fail;
            }
            r->id_object = grown;
        }
        for (uint32_t k = 0; k < ids; k++)
            r->id_object[r->id_count + k] = (unsigned)i;
        if ((rc = o->kind->attach(o->geom, rtc, r->scene, r->id_count, quality, err)) < 0)
            goto fail;
        r->shade[i] = (mr_shade_object){o->kind, o->geom, o->desc->color, r->id_count};
        r->id_count += ids;
    }
    if (job->camera.source == MR_CAMERA_SOURCE_NODE && (rc = setup_camera_node(r, assets, err)) < 0)
        goto fail;
    if ((rc = mr_device_check(dev, "scene setup", err)) < 0)
        goto fail;
    if ((r->reference = mr_job_has_reference(job))) {
        if (!(r->assets = malloc((job->asset_count ? job->asset_count : 1) * sizeof *r->assets))) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory creating the renderer");
            goto fail;
        }
        memcpy(r->assets, assets, job->asset_count * sizeof *r->assets);
    }
    *out = r;
    return MR_OK;
fail:
    mr_renderer_free(r);
    return rc;
}

static int camera_for_frame(mr_renderer *r, size_t index, double t, mr_camera *cam, mr_error *err)
{
    const mr_camera_desc *cd = &r->job->camera;
    if (cd->source == MR_CAMERA_SOURCE_PATH) {
        *cam = mr_camera_path_eval(&cd->path, t);
        return MR_OK;
    }
    const mr_pose_desc *pd = r->cam_driver ? pose_for_frame(r->cam_driver->desc, index) : NULL;
    int rc = mr_pose_eval(r->cam_pose, r->cam_asset, pd, t, err);
    if (rc < 0)
        return rc;
    /* A camera that no node carries sits in the asset's root space. */
    mr_mat4 g = r->cam_node >= 0 ? r->cam_pose->global[r->cam_node] : mr_mat4_identity();
    mr_vec3 pos = mr_v3(0, 0, 0), look = mr_v3(0, 0, -1), up = mr_v3(0, 1, 0);
    float yfov = (float)(MR_DEFAULT_YFOV_DEG * M_PI / 180); /* a plain node has no lens */
    if (r->cam_info) {
        pos = r->cam_info->position;
        look = r->cam_info->look_at;
        up = r->cam_info->up;
        if (r->cam_info->yfov > 0 && r->cam_info->yfov < 3.14159f)
            yfov = r->cam_info->yfov;
    }
    cam->position = mr_mat4_point(&g, pos);
    cam->rotation = mr_quat_look_rotation(mr_mat4_dir(&g, look), mr_mat4_dir(&g, up));
    cam->yfov = yfov;
    return MR_OK;
}

/* Poses object i for frame->index and lets its kind update. */
static int update_object(mr_renderer *r, object_state *o, size_t i, const mr_geom_frame *frame,
                         mr_error *err)
{
    int rc;
    if (!o->kind->self_posed &&
        (rc = mr_pose_eval(o->pose, o->asset, pose_for_frame(o->desc, frame->index), frame->time,
                           err)) < 0)
        return mr_error_prefix(err, "/objects/%zu/pose: ", i);
    rc = o->kind->update(o->geom, frame, o->kind->self_posed ? NULL : o->pose,
                         &o->desc->transform, mr_device_threads(r->dev), err);
    if (rc < 0 && o->kind->self_posed) /* its errors name fields under the object, as in create */
        mr_error_prefix(err, "/objects/%zu/", i);
    return rc;
}

/* After frames 0..o->stepped-1: a checkpoint when one is due (checkpoint.h).
 * A checkpoint that cannot be written costs a later resume some replay,
 * never this frame. */
static void checkpoint_due(object_state *o)
{
    if (o->checkpoints && o->stepped % o->checkpoint_every == 0) {
        mr_error ignored;
        mr_checkpoint_store(o->checkpoints, o->kind, o->geom, o->stepped, &ignored);
    }
}

/* The frame-order contract (kind.h): a SEQUENTIAL object about to show
 * frame `index` must have applied exactly frames 0..index-1. A frame out of
 * order (resumed job, retry, frame range) restores the newest checkpoint
 * at or before it (or rewinds) and replays the updates in between,
 * untraced, so the result is the uninterrupted run's. */
static int replay_to(mr_renderer *r, object_state *o, size_t i, size_t index, mr_frame_stats *st,
                     mr_error *err)
{
    int rc;
    if (o->stepped == index)
        return MR_OK;
    size_t from = o->stepped > index ? 0 : o->stepped;
    if (o->checkpoints)
        for (size_t m = index - index % o->checkpoint_every; m > from; m -= o->checkpoint_every) {
            mr_error miss;
            if (mr_checkpoint_load(o->checkpoints, o->kind, o->geom, m, &miss) == MR_OK) {
                o->stepped = m;
                st->replay_checkpoint = (uint32_t)m;
                break;
            }
        }
    if (o->stepped > index) {
        if ((rc = o->kind->rewind(o->geom, err)) < 0)
            return mr_error_prefix(err, "/objects/%zu: ", i);
        o->stepped = 0;
    }
    while (o->stepped < index) {
        size_t k = o->stepped;
        mr_geom_frame f = {.index = k, .time = r->job->frame_times[k],
                           .width = r->job->output.width, .height = r->job->output.height};
        if ((rc = camera_for_frame(r, k, f.time, &f.camera, err)) < 0 ||
            (rc = update_object(r, o, i, &f, err)) < 0)
            return rc;
        o->stepped = k + 1;
        st->replay_frames++;
        checkpoint_due(o);
    }
    return MR_OK;
}

/* The kinds' own per-frame fields (kind.h stats), each combined over the
 * job's objects of its kind (summed, or the largest: mr_kind_stat.combine),
 * as the frame's extras; creation figures (MR_STAT_ONCE) only on the
 * renderer's first frame. */
static int kind_stats(mr_renderer *r, mr_frame_stats *st, mr_error *err)
{
    for (size_t s = 0; s < r->stat_kind_count; s++) {
        const mr_kind *k = r->stat_kinds[s];
        double sum[MR_FRAME_EXTRAS_MAX] = {0}, v[MR_FRAME_EXTRAS_MAX];
        bool first = true;
        for (size_t j = 0; j < r->object_count; j++) {
            if (r->objects[j].kind != k)
                continue;
            k->frame_stats(r->objects[j].geom, v);
            for (size_t f = 0; f < k->stat_count; f++) {
                if (k->stats[f].combine == MR_STAT_MAX)
                    sum[f] = first ? v[f] : fmax(sum[f], v[f]);
                else
                    sum[f] += v[f];
            }
            first = false;
        }
        for (size_t f = 0; f < k->stat_count; f++) {
            double value = k->stats[f].combine == MR_STAT_ONCE && r->reported_once ? 0 : sum[f];
            int rc = mr_frame_stats_add_extra(st, k->stats[f].name, k->stats[f].unit, value, err);
            if (rc < 0)
                return mr_error_prefix(err, "kind \"%s\" stats: ", k->name);
        }
    }
    return MR_OK;
}

/* Each object's level of detail (kind.h lod), the first MR_FRAME_LOD_MAX. */
static void object_lods(const mr_renderer *r, mr_frame_stats *st)
{
    for (size_t j = 0; j < r->object_count && st->lod_count < MR_FRAME_LOD_MAX; j++) {
        const object_state *o = &r->objects[j];
        mr_object_lod *l = &st->lod[st->lod_count];
        if (o->kind->lod && o->kind->lod(o->geom, &l->level, &l->error_px)) {
            l->object = (uint32_t)j;
            st->lod_count++;
        }
    }
}

/* Poses and deforms for frame `index` whatever moves (everything the first
 * time), replaying sequential kinds as needed; *changed: something did. */
static int update_objects(mr_renderer *r, size_t index, const mr_geom_frame *frame, mr_frame_stats *st,
                          bool *changed, mr_error *err)
{
    int rc;
    *changed = false;
    for (size_t i = 0; i < r->object_count; i++) {
        object_state *o = &r->objects[i];
        if (o->posed_once && !o->animated && !o->view_dependent && !r->opt.force_rebuild)
            continue;
        if (!o->posed_once || o->animated) {
            if (o->kind->frame_order == MR_FRAMES_SEQUENTIAL &&
                (rc = replay_to(r, o, i, index, st, err)) < 0)
                return rc;
            if ((rc = update_object(r, o, i, frame, err)) < 0)
                return rc;
            o->stepped = index + 1;
            checkpoint_due(o);
        } else if (o->view_dependent) {
            /* only the camera moved: the scene changes only if the object's
             * level (or what it selects) does */
            mr_geom_frame view = *frame;
            view.view_only = true;
            if ((rc = o->kind->update(o->geom, &view, o->kind->self_posed ? NULL : o->pose,
                                      &o->desc->transform, mr_device_threads(r->dev), err)) < 0)
                return rc;
            *changed |= o->kind->commit(o->geom);
            continue;
        }
        o->kind->commit(o->geom);
        o->posed_once = true;
        *changed = true;
    }
    return MR_OK;
}

static int reference_passes(mr_renderer *r, size_t index, const mr_film *film,
                            const mr_camera *camera, mr_frame_stats *st, mr_error *err);

/* Frame `index` into film; camera: the frame's camera when given (a
 * reference pass renders with the frame's own), else the job's. */
static int render_frame(mr_renderer *r, size_t index, mr_film *film, mr_frame_stats *st,
                        const mr_camera *camera, mr_error *err)
{
    const mr_job *job = r->job;
    int rc;
    if (index >= job->frame_count)
        return mr_error_set(err, MR_ERR_INVALID, "frame %zu out of range (job has %zu)", index,
                            job->frame_count);
    if (film->width != job->output.width || film->height != job->output.height)
        return mr_error_set(err, MR_ERR_INVALID, "film is %dx%d, job wants %dx%d", film->width,
                            film->height, job->output.width, job->output.height);
    double t = job->frame_times[index];
    memset(st, 0, sizeof *st);
    st->frame = (int)index;
    st->time = t;
    double t0 = mr_now();

    mr_geom_frame frame = {.index = index, .time = t, .width = film->width, .height = film->height};
    if (camera)
        frame.camera = *camera;
    else if ((rc = camera_for_frame(r, index, t, &frame.camera, err)) < 0)
        return rc;

    /* An animated scene's tree is built at frame 0 and refitted after
     * that; its topology decides which of two triangles sharing an edge a
     * ray exactly on that edge hits. A renderer that starts at a later
     * frame (a resumed job, a retry in a new render worker) builds its tree
     * at frame 0 as well, so its hits are the uninterrupted run's bit for
     * bit (tests/integration/test_springmass_daemon.c). */
    if (r->refit && !r->built && index != 0) {
        mr_geom_frame first = {.index = 0, .time = job->frame_times[0], .width = film->width,
                               .height = film->height};
        if ((rc = camera_for_frame(r, 0, first.time, &first.camera, err)) < 0)
            return rc;
        bool ignored;
        if ((rc = update_objects(r, 0, &first, st, &ignored, err)) < 0)
            return rc;
        rtcCommitScene(r->scene);
        r->built = true;
        if ((rc = mr_device_check(r->dev, "rtcCommitScene", err)) < 0)
            return rc;
    }
    /* Pose and deform whatever moves (everything on the first frame). */
    bool changed = false;
    if ((rc = update_objects(r, index, &frame, st, &changed, err)) < 0)
        return rc;
    double t1 = mr_now();
    st->pose_s = t1 - t0;

    if (changed || !r->built) {
        st->bvh = r->built && r->refit ? MR_BVH_REFIT : MR_BVH_BUILD;
        rtcCommitScene(r->scene);
        r->built = true;
        if ((rc = mr_device_check(r->dev, "rtcCommitScene", err)) < 0)
            return rc;
    }
    double t2 = mr_now();
    st->bvh_s = t2 - t1;

    struct RTCBounds b;
    rtcGetSceneBounds(r->scene, &b);
    float dx = b.upper_x - b.lower_x, dy = b.upper_y - b.lower_y, dz = b.upper_z - b.lower_z;
    float diag = sqrtf(dx * dx + dy * dy + dz * dz);
    if (!(diag > 0) || !isfinite(diag))
        diag = 1.0f;
    st->scene_diagonal = diag;

    mr_trace_setup ts = {
        .scene = r->scene,
        .objects = r->shade,
        .object_count = r->object_count,
        .id_object = r->id_object,
        .id_count = r->id_count,
        .lights = job->lights,
        .light_count = job->light_count,
        .ambient = job->ambient,
        .background = job->background,
        .background_alpha = job->background_alpha,
        .spp = job->output.spp,
        .shadows = job->output.shadows,
        .seed = job->output.seed,
        .frame = (uint32_t)index,
        .aovs = film->aovs,
        .crypto_ids = {r->crypto_ids[0], r->crypto_ids[1]},
        .shadow_bias = 1e-4f * diag,
        .threads = mr_device_threads(r->dev),
        .cancel = r->opt.cancel,
        .trace_every_pixel = r->opt.trace_every_pixel,
    };
    ts.camera = frame.camera;
    film->has_camera = true;
    film->camera_to_world = mr_mat4_from_trs(frame.camera.position, frame.camera.rotation,
                                             mr_v3(1, 1, 1));
    film->yfov = frame.camera.yfov;
    mr_vec3 cp = ts.camera.position;
    if (!(fabsf(cp.x) <= MR_MAX_COORDINATE && fabsf(cp.y) <= MR_MAX_COORDINATE && fabsf(cp.z) <= MR_MAX_COORDINATE))
        return mr_error_set(err, MR_ERR_INVALID, "/camera: frame %zu puts the camera at (%g, %g, %g), beyond %g",
                            index, (double)cp.x, (double)cp.y, (double)cp.z, MR_MAX_COORDINATE);
    bool cancelled = false;
    st->rays = mr_trace_frame(&ts, film, &cancelled);
    if (cancelled)
        return mr_error_set(err, MR_ERR_CANCELLED, "frame %zu cancelled", index);
    double t3 = mr_now();
    st->trace_s = t3 - t2;
    st->mrays_per_s = st->trace_s > 0 ? (double)st->rays / st->trace_s * 1e-6 : 0;

    for (size_t i = 0; i < r->object_count; i++) {
        st->triangles += r->objects[i].kind->primitives(r->objects[i].geom);
        st->geometry_bytes += r->objects[i].kind->memory(r->objects[i].geom);
    }
    int64_t eb = mr_device_embree_bytes(r->dev);
    st->bvh_bytes = eb > 0 ? (uint64_t)eb : 0;
    st->peak_rss_bytes = mr_peak_rss_bytes();
    st->total_s = t3 - t0;
    /* one pass over the film, outside the frame's timings */
    mr_speckle_result sp;
    mr_film_speckles(film, &sp);
    st->speckle_pct = sp.speckle_pct;
    if ((rc = kind_stats(r, st, err)) < 0)
        return rc;
    object_lods(r, st);
    r->reported_once = true;
    if (r->reference) {
        /* after the frame's own figures: never part of them */
        double t4 = mr_now();
        rc = reference_passes(r, index, film, &frame.camera, st, err);
        st->reference_s = mr_now() - t4;
        if (rc < 0)
            return rc;
    }
    return MR_OK;
}

int mr_renderer_render(mr_renderer *r, size_t index, mr_film *film, mr_frame_stats *st, mr_error *err)
{
    return render_frame(r, index, film, st, NULL, err);
}

/* The renderers of the job's reference passes (reference.h), once; all or
 * none (a frame that fails here tries again from scratch). */
static int passes_setup(mr_renderer *r, mr_error *err)
{
    for (int t = 0; t < MR_REFERENCE_TYPES; t++) {
        struct pass *p = &r->passes[r->pass_count];
        bool present;
        int rc = mr_reference_pass_init(r->job, (mr_reference_type)t, &p->pass, &present, err);
        if (rc == MR_OK && present) {
            r->pass_count++;
            if ((rc = mr_renderer_new(r->dev, &p->pass.job, r->assets, &r->opt, &p->renderer, err)) < 0 ||
                (rc = mr_job_film_new(&p->pass.job, &p->film, err)) < 0)
                mr_error_prefix(err, "%s reference pass: ", mr_reference_name(p->pass.type));
        }
        if (rc < 0) {
            passes_free(r);
            return rc;
        }
    }
    r->passes_ready = true;
    return MR_OK;
}

/* A renderer's scene as a surface probe (mr_surface_probe): one ray of the
 * frame's camera per call. */
typedef struct scene_probe {
    mr_surface_probe probe;
    RTCScene scene;
    mr_camera_rays rays;
    mr_vec3 forward;
} scene_probe;

static double probe_depth(void *ctx, double px, double py)
{
    const scene_probe *sp = ctx;
    mr_vec3 d = mr_camera_rays_dir(&sp->rays, (float)px, (float)py);
    struct RTCRayHit rh = {.ray = {.org_x = sp->rays.origin.x, .org_y = sp->rays.origin.y,
                                   .org_z = sp->rays.origin.z, .dir_x = d.x, .dir_y = d.y,
                                   .dir_z = d.z, .tnear = 0, .tfar = INFINITY, .mask = ~0u},
                           .hit = {.geomID = RTC_INVALID_GEOMETRY_ID}};
    struct RTCIntersectContext ctx1;
    rtcInitIntersectContext(&ctx1);
    rtcIntersect1(sp->scene, &ctx1, &rh);
    return rh.hit.geomID == RTC_INVALID_GEOMETRY_ID ? -1.0 : rh.ray.tfar * mr_v3_dot(d, sp->forward);
}

static scene_probe probe_of(const mr_renderer *r, const mr_camera *camera, const mr_film *film)
{
    scene_probe sp = {.scene = r->scene,
                      .rays = mr_camera_rays_setup(camera, film->width, film->height),
                      .forward = mr_quat_rotate(camera->rotation, mr_v3(0, 0, -1))};
    return sp;
}

/* Renders frame `index` through every reference pass with the frame's
 * camera and compares the frame's film with each: one error entry per
 * pass (the reference's scene diagonal is the unit of depth: a
 * tessellation's box is the tighter, user geometry's boxes are
 * conservative). */
static int reference_passes(mr_renderer *r, size_t index, const mr_film *film,
                            const mr_camera *camera, mr_frame_stats *st, mr_error *err)
{
    int rc;
    if (!r->passes_ready && (rc = passes_setup(r, err)) < 0)
        return rc;
    for (size_t i = 0; i < r->pass_count; i++) {
        struct pass *p = &r->passes[i];
        const char *name = mr_reference_name(p->pass.type);
        mr_frame_stats ref;
        mr_compare_result c;
        if ((rc = render_frame(p->renderer, index, p->film, &ref, camera, err)) < 0)
            return mr_error_prefix(err, "%s reference pass: ", name);
        /* both scenes are posed for this frame: surface_px looks between
         * pixel centres */
        scene_probe main = probe_of(r, camera, film), other = probe_of(p->renderer, camera, film);
        main.probe = (mr_surface_probe){probe_depth, &main};
        other.probe = (mr_surface_probe){probe_depth, &other};
        if ((rc = mr_film_compare_probed(film, p->film, ref.scene_diagonal, &main.probe,
                                         &other.probe, &c, err)) < 0)
            return mr_error_prefix(err, "%s reference pass: ", name);
        st->errors[st->error_count++] = (mr_frame_error){
            .reference = p->pass.type,
            .coverage_error_pct = c.coverage_pct,
            .holes = c.holes,
            .depth_rmse = c.depth_rmse,
            .depth_max = c.depth_max,
            .normal_mean_deg = c.normal_mean_deg,
            .psnr_rgb_db = c.psnr_rgb,
            .speckle_pct = ref.speckle_pct,
            .surface_px = c.surface_px,
        };
    }
    return MR_OK;
}

int mr_renderer_tessellate(const mr_renderer *r, size_t object, mr_trimesh *out, mr_error *err)
{
    *out = (mr_trimesh){0};
    if (object >= r->object_count)
        return mr_error_set(err, MR_ERR_INVALID, "object %zu out of range (job has %zu)", object,
                            r->object_count);
    const object_state *o = &r->objects[object];
    if (!o->kind->tessellate)
        return mr_error_set(err, MR_ERR_INVALID, "/objects/%zu: kind \"%s\" has no triangle "
                            "reference", object, o->kind->name);
    int rc = o->kind->tessellate(o->geom, out, err);
    return rc < 0 ? mr_error_prefix(err, "/objects/%zu: ", object) : MR_OK;
}
