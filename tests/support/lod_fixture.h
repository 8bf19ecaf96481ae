/*
 * lod_fixture.h - what the level-of-detail tests share (issue 16,
 * "tolerance_px"): an example job read for a test (resized, with reference
 * passes, its asset paths made absolute), a renderer over it and its
 * frames. Include after <cmocka.h>; failures end the test with the
 * library's message.
 */
#ifndef MR_TEST_LOD_FIXTURE_H
#define MR_TEST_LOD_FIXTURE_H

#include <cJSON.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "film_fixture.h"
#include "job_json.h"
#include "kinds/svo/voxelize.h" /* mr_tri_closest_point */
#include "microray.h"

/* Vertex v of pos (3 floats a vertex), in double. */
static inline void lod_point(const float *pos, uint32_t v, double out[3])
{
    for (int c = 0; c < 3; c++)
        out[c] = pos[3 * (size_t)v + c];
}

/* Brute force: the distance from p to the nearest of the nt triangles idx
 * over pos (what a level's error is checked against). */
static inline double lod_brute_distance(const float *pos, const uint32_t *idx, uint32_t nt,
                                        const double p[3])
{
    double best = INFINITY;
    for (uint32_t t = 0; t < nt; t++) {
        double a[3], b[3], c[3], w[3];
        lod_point(pos, idx[3 * t], a);
        lod_point(pos, idx[3 * t + 1], b);
        lod_point(pos, idx[3 * t + 2], c);
        best = fmin(best, mr_tri_closest_point(p, a, b, c, w));
    }
    return sqrt(best);
}

/* examples/<name>.json (below $MR_SOURCE_DIR, else the current folder) at
 * width x height with "reference": true, asset paths relative to the
 * examples folder made absolute: for the test to change further and print
 * (cJSON_PrintUnformatted; free with cJSON_free). */
static inline cJSON *lod_example(const char *name, int width, int height)
{
    const char *dir = getenv("MR_SOURCE_DIR");
    dir = dir ? dir : ".";
    char path[1024];
    snprintf(path, sizeof path, "%s/examples/%s.json", dir, name);
    uint8_t *text = NULL;
    size_t n = 0;
    mr_error err;
    if (mr_fs_read_capped(path, 1 << 20, &text, &n, "example", &err) != MR_OK)
        fail_msg("%s", err.msg);
    cJSON *o = cJSON_ParseWithLength((const char *)text, n);
    free(text);
    if (!o)
        fail_msg("%s: not JSON", path);
    cJSON *out = cJSON_GetObjectItem(o, "output");
    cJSON_ReplaceItemInObject(out, "width", cJSON_CreateNumber(width));
    cJSON_ReplaceItemInObject(out, "height", cJSON_CreateNumber(height));
    cJSON_AddBoolToObject(o, "reference", true);
    cJSON *asset;
    cJSON_ArrayForEach(asset, cJSON_GetObjectItem(o, "assets")) {
        const char *p = cJSON_GetStringValue(cJSON_GetObjectItem(asset, "path"));
        if (p && p[0] != '/') {
            char full[2048];
            snprintf(full, sizeof full, "%s/examples/%s", dir, p);
            cJSON_ReplaceItemInObject(asset, "path", cJSON_CreateString(full));
        }
    }
    return o;
}

/* Imports the assets of job json in its order into assets[max] (refined
 * where the job says "refine"), as the daemon would; returns how many. */
static inline size_t lod_load_assets(const char *json, mr_asset **assets, size_t max)
{
    mr_job *job;
    mr_job_error je;
    mr_error err;
    if (mr_job_parse(json, strlen(json), &job, &je) != MR_OK)
        fail_msg("job: %s at %s", je.message, je.pointer);
    if (job->asset_count > max)
        fail_msg("the job has %zu assets, more than %zu", job->asset_count, max);
    for (size_t i = 0; i < job->asset_count; i++) {
        mr_asset *plain = NULL;
        if (mr_asset_load(job->assets[i].path, &plain, &err) != MR_OK)
            fail_msg("%s", err.msg);
        assets[i] = plain;
        if (job->assets[i].refine) {
            mr_refine_params rp = job->assets[i].refine_params;
            rp.threads = 2;
            if (mr_refine_asset(plain, &rp, &assets[i], &err) != MR_OK)
                fail_msg("refine %s: %s", job->assets[i].path, err.msg);
            mr_asset_free(plain);
        }
    }
    size_t n = job->asset_count;
    mr_job_free(job);
    return n;
}

/* A job rendered by a renderer of its own on a device of its own. */
typedef struct lod_run {
    mr_job *job;
    mr_device *dev;
    mr_renderer *r;
} lod_run;

/* Parses json and opens a renderer over assets (the job's assets in its
 * order, imported by the caller: they outlive the run) with opt (NULL:
 * the defaults) on `threads` threads. */
static inline void lod_open(lod_run *x, const char *json, mr_asset *const *assets,
                            const mr_renderer_options *opt, unsigned threads)
{
    mr_job_error je;
    mr_error err;
    if (mr_job_parse(json, strlen(json), &x->job, &je) != MR_OK)
        fail_msg("job: %s at %s", je.message, je.pointer);
    if (mr_device_new(threads, &x->dev, &err) != MR_OK ||
        mr_renderer_new(x->dev, x->job, assets, opt, &x->r, &err) != MR_OK)
        fail_msg("%s", err.msg);
}

static inline void lod_close(lod_run *x)
{
    mr_renderer_free(x->r);
    mr_device_free(x->dev);
    mr_job_free(x->job);
}

/* Frame `index` of the run into a new film (the caller frees it). */
static inline mr_film *lod_frame(lod_run *x, size_t index, mr_frame_stats *st)
{
    mr_film *f;
    mr_error err;
    if (mr_film_new(x->job->output.width, x->job->output.height, &f, &err) != MR_OK ||
        mr_renderer_render(x->r, index, f, st, &err) != MR_OK)
        fail_msg("frame %zu: %s", index, err.msg);
    return f;
}

/* Frame `index` of job json rendered alone on one thread, by a renderer of
 * its own with no frame before it, has the pixels of `kept` (the same
 * frame rendered in sequence on two threads); frees kept. */
static inline void lod_assert_frame_alone(const char *json, mr_asset *const *assets, size_t index,
                                          mr_film *kept)
{
    lod_run y;
    lod_open(&y, json, assets, NULL, 1);
    mr_frame_stats st;
    mr_film *alone = lod_frame(&y, index, &st);
    fx_assert_same_pixels(kept, alone, "a frame rendered alone on one thread");
    mr_film_free(alone);
    mr_film_free(kept);
    lod_close(&y);
}

#endif /* MR_TEST_LOD_FIXTURE_H */
