/* stats_json.c - per-frame and per-job statistics as JSON (stats_json.h). */
#include "stats_json.h"

#include <cJSON.h>
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

/* One frame's statistics as a cJSON object (NULL when out of memory). */
static cJSON *frame_json(const mr_frame_stats *f)
{
    cJSON *o = cJSON_CreateObject();
    cJSON_AddNumberToObject(o, "frame", f->frame);
    cJSON_AddNumberToObject(o, "time", f->time);
    char name[MR_FRAME_NAME_MAX];
    mr_frame_file_name((size_t)f->frame, name);
    cJSON_AddStringToObject(o, "file", name);
    cJSON *s = cJSON_AddObjectToObject(o, "seconds");
#define ADD(n) cJSON_AddNumberToObject(s, #n, f->n##_s);
    TIMINGS(ADD)
#undef ADD
    cJSON_AddStringToObject(o, "bvh", mr_bvh_update_name(f->bvh));
    cJSON_AddNumberToObject(o, "rays", (double)f->rays);
    cJSON_AddNumberToObject(o, "mrays_per_s", f->mrays_per_s);
    cJSON_AddNumberToObject(o, "triangles", (double)f->triangles);
    cJSON *b = cJSON_AddObjectToObject(o, "bytes");
    cJSON_AddNumberToObject(b, "geometry", (double)f->geometry_bytes);
    cJSON_AddNumberToObject(b, "bvh", (double)f->bvh_bytes);
    cJSON_AddNumberToObject(b, "peak_rss", (double)f->peak_rss_bytes);
    cJSON_AddNumberToObject(o, "scene_diagonal", f->scene_diagonal);
    if (f->assets_cached || f->assets_loaded) {
        cJSON *c = cJSON_AddObjectToObject(o, "cache");
        cJSON_AddStringToObject(c, "result", f->assets_loaded ? (f->assets_cached ? "partial" : "miss") : "hit");
        cJSON_AddNumberToObject(c, "assets_cached", f->assets_cached);
        cJSON_AddNumberToObject(c, "assets_loaded", f->assets_loaded);
        cJSON_AddNumberToObject(c, "saved_s", f->load_saved_s);
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

char *mr_stats_to_json(const mr_job *job, const mr_job_stats *stats, size_t first)
{
    size_t n = stats->frame_count > first ? stats->frame_count - first : 0;
    const mr_frame_stats *fr = stats->frames + first;
    double *tmp = malloc((n ? n : 1) * sizeof *tmp);
    cJSON *root = cJSON_CreateObject();
    if (!tmp || !root) {
        free(tmp);
        cJSON_Delete(root);
        return NULL;
    }
    cJSON_AddStringToObject(root, "job", job->name);
    cJSON_AddStringToObject(root, "software", "microray " MR_VERSION_STRING);
    cJSON_AddNumberToObject(root, "threads", stats->threads);
    cJSON_AddNumberToObject(root, "width", job->output.width);
    cJSON_AddNumberToObject(root, "height", job->output.height);
    cJSON_AddNumberToObject(root, "samples", job->output.spp);
    cJSON_AddNumberToObject(root, "frames_total", (double)job->frame_count);
    cJSON_AddNumberToObject(root, "frames_done", (double)n);

    cJSON *frames = cJSON_AddArrayToObject(root, "frames");
    for (size_t i = 0; i < n; i++)
        cJSON_AddItemToArray(frames, frame_json(&fr[i]));

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
        cJSON_AddNumberToObject(ts, #name, sum);                                                   \
        cJSON_AddNumberToObject(ms, #name, median(tmp, n));                                        \
    }
    TIMINGS(ADD)
#undef ADD
    cJSON_AddNumberToObject(tot, "rays", (double)rays);
    for (size_t i = 0; i < n; i++)
        tmp[i] = fr[i].mrays_per_s;
    cJSON_AddNumberToObject(med, "mrays_per_s", median(tmp, n));
    uint64_t peak = 0;
    for (size_t i = 0; i < n; i++)
        peak = fr[i].peak_rss_bytes > peak ? fr[i].peak_rss_bytes : peak;
    cJSON_AddNumberToObject(tot, "peak_rss_bytes", (double)peak);

    char *out = cJSON_Print(root);
    cJSON_Delete(root);
    free(tmp);
    return out;
}
