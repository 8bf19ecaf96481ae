/* stats_json.c - per-frame and per-job statistics as JSON (stats_json.h). */
#include "stats_json.h"

#include <cJSON.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* The per-frame timings, in the order they appear in "seconds". */
#define TIMINGS(X) X(load) X(pose) X(bvh) X(trace) X(encode) X(total)

static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* Median of n values (mean of the middle two for even n); sorts v. */
static double median(double *v, size_t n)
{
    if (n == 0)
        return 0;
    qsort(v, n, sizeof *v, cmp_double);
    return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

/* Each builder below collects the results of its cJSON calls in `ok`: a
 * call that fails for want of memory leaves its field out, and a document
 * with a field or a frame missing must never pass for complete. (cJSON's
 * Add functions return NULL on failure, also when given a NULL parent.) */

/* One frame's statistics as a cJSON object; NULL when out of memory. */
static cJSON *frame_json(const mr_frame_stats *f)
{
    cJSON *o = cJSON_CreateObject();
    bool ok = o != NULL;
    ok &= cJSON_AddNumberToObject(o, "frame", f->frame) != NULL;
    ok &= cJSON_AddNumberToObject(o, "time", f->time) != NULL;
    char name[MR_FRAME_NAME_MAX];
    mr_frame_file_name((size_t)f->frame, name);
    ok &= cJSON_AddStringToObject(o, "file", name) != NULL;
    cJSON *s = cJSON_AddObjectToObject(o, "seconds");
#define ADD(n) ok &= cJSON_AddNumberToObject(s, #n, f->n##_s) != NULL;
    TIMINGS(ADD)
#undef ADD
    ok &= cJSON_AddStringToObject(o, "bvh", mr_bvh_update_name(f->bvh)) != NULL;
    ok &= cJSON_AddNumberToObject(o, "rays", (double)f->rays) != NULL;
    ok &= cJSON_AddNumberToObject(o, "mrays_per_s", f->mrays_per_s) != NULL;
    ok &= cJSON_AddNumberToObject(o, "triangles", (double)f->triangles) != NULL;
    cJSON *b = cJSON_AddObjectToObject(o, "bytes");
    ok &= cJSON_AddNumberToObject(b, "geometry", (double)f->geometry_bytes) != NULL;
    ok &= cJSON_AddNumberToObject(b, "bvh", (double)f->bvh_bytes) != NULL;
    ok &= cJSON_AddNumberToObject(b, "peak_rss", (double)f->peak_rss_bytes) != NULL;
    ok &= cJSON_AddNumberToObject(o, "scene_diagonal", f->scene_diagonal) != NULL;
    if (f->assets_cached || f->assets_loaded) {
        cJSON *c = cJSON_AddObjectToObject(o, "cache");
        ok &= cJSON_AddStringToObject(c, "result", f->assets_loaded ? (f->assets_cached ? "partial" : "miss") : "hit") != NULL;
        ok &= cJSON_AddNumberToObject(c, "assets_cached", f->assets_cached) != NULL;
        ok &= cJSON_AddNumberToObject(c, "assets_loaded", f->assets_loaded) != NULL;
        ok &= cJSON_AddNumberToObject(c, "saved_s", f->load_saved_s) != NULL;
    }
    if (!ok) {
        cJSON_Delete(o);
        return NULL;
    }
    return o;
}

char *mr_frame_stats_json(const mr_frame_stats *f)
{
    cJSON *o = frame_json(f);
    char *s = o ? cJSON_PrintUnformatted(o) : NULL;
    cJSON_Delete(o);
    return s;
}

int mr_stats_to_json(const mr_job *job, const mr_job_stats *stats, size_t first, char **out,
                     mr_error *err)
{
    *out = NULL;
    size_t n = stats->frame_count > first ? stats->frame_count - first : 0;
    const mr_frame_stats *fr = stats->frames + first;
    double *tmp = malloc((n ? n : 1) * sizeof *tmp);
    cJSON *root = cJSON_CreateObject();
    bool ok = tmp && root;
    if (!ok)
        goto done;
    ok &= cJSON_AddStringToObject(root, "job", job->name) != NULL;
    ok &= cJSON_AddStringToObject(root, "software", "microray " MR_VERSION_STRING) != NULL;
    ok &= cJSON_AddNumberToObject(root, "threads", stats->threads) != NULL;
    ok &= cJSON_AddNumberToObject(root, "width", job->output.width) != NULL;
    ok &= cJSON_AddNumberToObject(root, "height", job->output.height) != NULL;
    ok &= cJSON_AddNumberToObject(root, "samples", job->output.spp) != NULL;
    ok &= cJSON_AddNumberToObject(root, "frames_total", (double)job->frame_count) != NULL;
    ok &= cJSON_AddNumberToObject(root, "frames_done", (double)n) != NULL;

    cJSON *frames = cJSON_AddArrayToObject(root, "frames");
    ok &= frames != NULL;
    for (size_t i = 0; i < n && ok; i++) {
        cJSON *f = frame_json(&fr[i]);
        if (!f || !cJSON_AddItemToArray(frames, f)) {
            cJSON_Delete(f);
            ok = false;
        }
    }
    if (!ok)
        goto done;

    cJSON *tot = cJSON_AddObjectToObject(root, "totals");
    cJSON *ts = cJSON_AddObjectToObject(tot, "seconds");
    cJSON *med = cJSON_AddObjectToObject(root, "medians");
    cJSON *ms = cJSON_AddObjectToObject(med, "seconds");
    uint64_t rays = 0;
    for (size_t i = 0; i < n; i++)
        rays += fr[i].rays;
#define ADD(name)                                                                                  \
    {                                                                                              \
        double sum = 0;                                                                            \
        for (size_t i = 0; i < n; i++)                                                             \
            sum += tmp[i] = fr[i].name##_s;                                                        \
        ok &= cJSON_AddNumberToObject(ts, #name, sum) != NULL;                                     \
        ok &= cJSON_AddNumberToObject(ms, #name, median(tmp, n)) != NULL;                          \
    }
    TIMINGS(ADD)
#undef ADD
    ok &= cJSON_AddNumberToObject(tot, "rays", (double)rays) != NULL;
    for (size_t i = 0; i < n; i++)
        tmp[i] = fr[i].mrays_per_s;
    ok &= cJSON_AddNumberToObject(med, "mrays_per_s", median(tmp, n)) != NULL;
    uint64_t peak = 0;
    for (size_t i = 0; i < n; i++)
        peak = fr[i].peak_rss_bytes > peak ? fr[i].peak_rss_bytes : peak;
    ok &= cJSON_AddNumberToObject(tot, "peak_rss_bytes", (double)peak) != NULL;
    if (ok)
        ok = (*out = cJSON_Print(root)) != NULL;
done:
    cJSON_Delete(root);
    free(tmp);
    if (!ok)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory writing the statistics of %zu frames",
                            n);
    return MR_OK;
}
