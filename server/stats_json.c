/*
 * stats_json.c - per-frame and per-job statistics as JSON (stats_json.h),
 * written and read by the frame-stats field table (render/frame_stats.h):
 * no field is named here. A frame is its table fields in table order (a
 * group's fields nested in the group's object), then its extras; a job
 * adds totals and medians of the "seconds" group and a few job figures.
 *
 * Every builder collects the results of its cJSON calls in `ok`: a call
 * that fails for want of memory leaves its field out, and a document with a
 * field or a frame missing must never pass for complete. (cJSON's Add
 * functions return NULL on failure, also when given a NULL parent.)
 */
#include "stats_json.h"

#include <cJSON.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

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

/* Whether an optional group has something to report for this frame: one
 * of its integer fields is non-zero. */
static bool group_present(const mr_stat_group *g, const mr_frame_stats *f)
{
    if (!g->optional)
        return true;
    for (size_t i = 0; i < mr_frame_stat_field_count; i++) {
        const mr_stat_field *fd = &mr_frame_stat_fields[i];
        bool integer = fd->type == MR_STAT_INT || fd->type == MR_STAT_U32 || fd->type == MR_STAT_U64;
        if (fd->group == g && integer && mr_frame_stat_number(f, fd) != 0)
            return true;
    }
    return false;
}

static bool add_field(cJSON *o, const mr_stat_field *fd, const mr_frame_stats *f)
{
    switch (fd->type) {
    case MR_STAT_FRAME_FILE: {
        char name[MR_FRAME_NAME_MAX];
        mr_frame_file_name((size_t)f->frame, name);
        return cJSON_AddStringToObject(o, fd->name, name) != NULL;
    }
    case MR_STAT_BVH:
        return cJSON_AddStringToObject(o, fd->name, mr_bvh_update_name(f->bvh)) != NULL;
    case MR_STAT_CACHE_RESULT:
        return cJSON_AddStringToObject(o, fd->name, mr_frame_cache_result(f)) != NULL;
    default:
        return cJSON_AddNumberToObject(o, fd->name, mr_frame_stat_number(f, fd)) != NULL;
    }
}

/* One error entry ({"reference": ..., figures}) added to array a. */
static bool add_error_entry(cJSON *a, const mr_frame_error *e)
{
    cJSON *o = cJSON_CreateObject();
    bool ok = o && cJSON_AddItemToArray(a, o);
    if (!ok) {
        cJSON_Delete(o);
        return false;
    }
    for (size_t i = 0; i < mr_frame_error_field_count && ok; i++) {
        const mr_stat_field *fd = &mr_frame_error_fields[i];
        ok = fd->type == MR_STAT_REFERENCE
                 ? cJSON_AddStringToObject(o, fd->name, mr_reference_name(e->reference)) != NULL
                 : cJSON_AddNumberToObject(o, fd->name, mr_frame_error_number(e, fd)) != NULL;
    }
    return ok;
}

/* One frame's statistics as a cJSON object; NULL when out of memory. */
static cJSON *frame_json(const mr_frame_stats *f)
{
    cJSON *o = cJSON_CreateObject();
    bool ok = o != NULL;
    const mr_stat_group *group = NULL;
    cJSON *into = o; /* the object of the current group, NULL while one is skipped */
    for (size_t i = 0; i < mr_frame_stat_field_count && ok; i++) {
        const mr_stat_field *fd = &mr_frame_stat_fields[i];
        if (fd->group != group) {
            group = fd->group;
            bool present = !group || group_present(group, f);
            into = !group ? o : present ? cJSON_AddObjectToObject(o, group->name) : NULL;
            ok = !present || into != NULL;
        }
        bool skipped = (fd->flags & MR_STAT_OPTIONAL) && mr_frame_stat_number(f, fd) == 0;
        if (into && ok && !skipped)
            ok = add_field(into, fd, f);
    }
    if (f->error_count && ok) {
        cJSON *errors = cJSON_AddArrayToObject(o, "error");
        ok = errors != NULL;
        for (uint32_t i = 0; i < f->error_count && i < MR_REFERENCE_TYPES && ok; i++)
            ok = add_error_entry(errors, &f->errors[i]);
    }
    if (f->lod_count && ok) {
        cJSON *lods = cJSON_AddArrayToObject(o, "lod");
        ok = lods != NULL;
        for (uint32_t i = 0; i < f->lod_count && i < MR_FRAME_LOD_MAX && ok; i++) {
            cJSON *e = cJSON_CreateObject();
            ok = e && cJSON_AddItemToArray(lods, e) &&
                 cJSON_AddNumberToObject(e, "object", f->lod[i].object) &&
                 cJSON_AddNumberToObject(e, "level", f->lod[i].level) &&
                 cJSON_AddNumberToObject(e, "error_px", f->lod[i].error_px);
        }
    }
    for (uint32_t i = 0; i < f->extra_count && i < MR_FRAME_EXTRAS_MAX && ok; i++)
        ok = cJSON_AddNumberToObject(o, f->extras[i].name, f->extras[i].value) != NULL;
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

void mr_frame_stats_from_json(const cJSON *o, size_t index, mr_frame_stats *f)
{
    memset(f, 0, sizeof *f);
    for (size_t i = 0; i < mr_frame_stat_field_count; i++) {
        const mr_stat_field *fd = &mr_frame_stat_fields[i];
        const cJSON *in = fd->group ? cJSON_GetObjectItemCaseSensitive(o, fd->group->name) : o;
        const cJSON *v = cJSON_GetObjectItemCaseSensitive(in, fd->name);
        if (fd->type == MR_STAT_BVH) {
            for (int u = MR_BVH_NONE; u <= MR_BVH_REFIT; u++)
                if (cJSON_IsString(v) && !strcmp(v->valuestring, mr_bvh_update_name(u)))
                    mr_frame_stat_set_number(f, fd, u);
        } else if (cJSON_IsNumber(v)) {
            mr_frame_stat_set_number(f, fd, v->valuedouble);
        }
    }
    const cJSON *entry;
    cJSON_ArrayForEach(entry, cJSON_GetObjectItemCaseSensitive(o, "error"))
    {
        if (f->error_count == MR_REFERENCE_TYPES || !cJSON_IsObject(entry))
            break;
        mr_frame_error *e = &f->errors[f->error_count++];
        for (size_t i = 0; i < mr_frame_error_field_count; i++) {
            const mr_stat_field *fd = &mr_frame_error_fields[i];
            const cJSON *v = cJSON_GetObjectItemCaseSensitive(entry, fd->name);
            if (fd->type == MR_STAT_REFERENCE) {
                for (int t = 0; t < MR_REFERENCE_TYPES; t++)
                    if (cJSON_IsString(v) && !strcmp(v->valuestring, mr_reference_name(t)))
                        mr_frame_error_set_number(e, fd, t);
            } else if (cJSON_IsNumber(v)) {
                mr_frame_error_set_number(e, fd, v->valuedouble);
            }
        }
    }
    cJSON_ArrayForEach(entry, cJSON_GetObjectItemCaseSensitive(o, "lod"))
    {
        const cJSON *obj = cJSON_GetObjectItemCaseSensitive(entry, "object"),
                    *level = cJSON_GetObjectItemCaseSensitive(entry, "level"),
                    *px = cJSON_GetObjectItemCaseSensitive(entry, "error_px");
        if (f->lod_count == MR_FRAME_LOD_MAX || !cJSON_IsNumber(obj) || !cJSON_IsNumber(level) ||
            !cJSON_IsNumber(px) || !(obj->valuedouble >= 0 && obj->valuedouble < MR_MAX_OBJECTS) ||
            !(level->valuedouble >= 0 && level->valuedouble <= UINT32_MAX))
            break;
        f->lod[f->lod_count++] = (mr_object_lod){.object = (uint32_t)obj->valuedouble,
                                                 .level = (uint32_t)level->valuedouble,
                                                 .error_px = px->valuedouble};
    }
    f->frame = (int)index;
}

/* Whether any of the n frames has a non-zero value of fd. */
static bool any_frame_has(const mr_frame_stats *fr, size_t n, const mr_stat_field *fd)
{
    for (size_t i = 0; i < n; i++)
        if (mr_frame_stat_number(&fr[i], fd) != 0)
            return true;
    return false;
}

/* The error entry of reference t of frame f, or NULL. */
static const mr_frame_error *frame_error(const mr_frame_stats *f, int t)
{
    for (uint32_t i = 0; i < f->error_count && i < MR_REFERENCE_TYPES; i++)
        if ((int)f->errors[i].reference == t)
            return &f->errors[i];
    return NULL;
}

/* The job's "error" object: per reference any frame was compared with,
 * {"frames": how many, "medians": {figure: median}, "worst": {figure:
 * {"frame", "value"}}} (worst: the highest, the lowest for LOWER_WORSE
 * figures; the first such frame). tmp holds n doubles. */
static bool add_job_errors(cJSON *root, const mr_frame_stats *fr, size_t n, double *tmp)
{
    cJSON *all = NULL;
    bool ok = true;
    for (int t = 0; t < MR_REFERENCE_TYPES && ok; t++) {
        size_t count = 0;
        for (size_t i = 0; i < n; i++)
            count += frame_error(&fr[i], t) != NULL;
        if (!count)
            continue;
        if (!all && !(all = cJSON_AddObjectToObject(root, "error")))
            return false;
        cJSON *ref = cJSON_AddObjectToObject(all, mr_reference_name(t));
        ok = cJSON_AddNumberToObject(ref, "frames", (double)count) != NULL;
        cJSON *med = cJSON_AddObjectToObject(ref, "medians"), *worst = cJSON_AddObjectToObject(ref, "worst");
        ok = ok && med && worst;
        for (size_t k = 0; k < mr_frame_error_field_count && ok; k++) {
            const mr_stat_field *fd = &mr_frame_error_fields[k];
            if (fd->type == MR_STAT_REFERENCE)
                continue;
            bool lower_worse = fd->flags & MR_STAT_LOWER_WORSE;
            size_t m = 0;
            int worst_frame = 0;
            double worst_value = 0;
            for (size_t i = 0; i < n; i++) {
                const mr_frame_error *e = frame_error(&fr[i], t);
                if (!e)
                    continue;
                double v = mr_frame_error_number(e, fd);
                if (!m || (lower_worse ? v < worst_value : v > worst_value)) {
                    worst_value = v;
                    worst_frame = fr[i].frame;
                }
                tmp[m++] = v;
            }
            cJSON *w = cJSON_AddObjectToObject(worst, fd->name);
            ok = cJSON_AddNumberToObject(med, fd->name, median(tmp, m)) != NULL && w &&
                 cJSON_AddNumberToObject(w, "frame", worst_frame) != NULL &&
                 cJSON_AddNumberToObject(w, "value", worst_value) != NULL;
        }
    }
    return ok;
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
    for (size_t k = 0; k < mr_frame_stat_field_count; k++) {
        const mr_stat_field *fd = &mr_frame_stat_fields[k];
        if (fd->group != &mr_stat_group_seconds ||
            ((fd->flags & MR_STAT_OPTIONAL) && !any_frame_has(fr, n, fd)))
            continue;
        double sum = 0;
        for (size_t i = 0; i < n; i++)
            sum += tmp[i] = mr_frame_stat_number(&fr[i], fd);
        ok &= cJSON_AddNumberToObject(ts, fd->name, sum) != NULL;
        ok &= cJSON_AddNumberToObject(ms, fd->name, median(tmp, n)) != NULL;
    }
    ok &= cJSON_AddNumberToObject(tot, "rays", (double)rays) != NULL;
    for (size_t i = 0; i < n; i++)
        tmp[i] = fr[i].mrays_per_s;
    ok &= cJSON_AddNumberToObject(med, "mrays_per_s", median(tmp, n)) != NULL;
    uint64_t peak = 0;
    for (size_t i = 0; i < n; i++)
        peak = fr[i].peak_rss_bytes > peak ? fr[i].peak_rss_bytes : peak;
    ok &= cJSON_AddNumberToObject(tot, "peak_rss_bytes", (double)peak) != NULL;
    ok = ok && add_job_errors(root, fr, n, tmp);
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

int mr_stats_from_frames(const mr_job *job, cJSON *const *frames, size_t n, unsigned threads,
                         cJSON **out, mr_error *err)
{
    *out = NULL;
    mr_frame_stats *fs = calloc(n ? n : 1, sizeof *fs);
    char *text = NULL;
    cJSON *root = NULL;
    if (!fs)
        goto oom;
    for (size_t i = 0; i < n; i++) {
        const cJSON *index = cJSON_GetObjectItemCaseSensitive(frames[i], "frame");
        mr_frame_stats_from_json(frames[i], cJSON_IsNumber(index) ? (size_t)index->valuedouble : i,
                                 &fs[i]);
    }
    mr_job_stats stats = {.frame_count = n, .frames = fs, .threads = threads};
    int rc = mr_stats_to_json(job, &stats, 0, &text, err);
    if (rc < 0) {
        free(fs);
        return rc;
    }
    if (!(root = cJSON_Parse(text)))
        goto oom;
    /* The frames list shows the given objects exactly (with the fields the
     * table does not hold: kinds' extras, the daemon's cache figures); the
     * regenerated entries only fill in what they lack. */
    cJSON *arr = cJSON_GetObjectItemCaseSensitive(root, "frames");
    size_t i = 0;
    for (cJSON *gen = arr ? arr->child : NULL; gen && i < n; gen = gen->next, i++)
        for (const cJSON *kv = frames[i]->child; kv; kv = kv->next) {
            if (!kv->string)
                continue;
            cJSON *dup = cJSON_Duplicate(kv, true);
            bool added = dup && (cJSON_HasObjectItem(gen, kv->string)
                                     ? cJSON_ReplaceItemInObjectCaseSensitive(gen, kv->string, dup)
                                     : cJSON_AddItemToObject(gen, kv->string, dup));
            if (!added) {
                cJSON_Delete(dup);
                goto oom;
            }
        }
    free(fs);
    free(text);
    *out = root;
    return MR_OK;
oom:
    cJSON_Delete(root);
    free(fs);
    free(text);
    return mr_error_set(err, MR_ERR_NOMEM, "out of memory gathering the statistics of %zu frames", n);
}
