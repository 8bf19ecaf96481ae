/*
 * render_cmd.c - one-shot render and compare commands (render_cmd.h).
 *
 * render: the job file is parsed and validated exactly as the daemon does;
 * relative asset paths are resolved against the job file's directory. Each
 * frame is written as DIR/NNNN.exr through a temporary file and a rename,
 * and DIR/stats.json is rewritten after every frame, so an interrupted run
 * leaves only complete files behind. With --cache DIR, kinds that derive
 * data from an asset (bakes, voxelisations) keep it in DIR/<kind>/ and
 * reuse it (mr_renderer_options.cache_dir). With --png each frame also
 * gets DIR/NNNN.png, its 8-bit sRGB preview (microray.h, "PNG previews"),
 * and the run ends with DIR/contact-sheet.png, from thumbnails made while
 * each film was in memory (no EXR is read back).
 */
#include "render_cmd.h"
#include "usage.h"

#include <cJSON.h>
#include <dirent.h>
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "files.h"
#include "job_json.h"
#include "microray.h"
#include "stats_json.h"
#include "worker.h"

/* Exit codes shared by microrayd's one-shot commands (README). */
enum { EXIT_OK = 0, EXIT_RENDER = 1, EXIT_USAGE = 2, EXIT_INVALID_INPUT = 3, EXIT_IO = 4 };

/* The exit status for a failure: whose fault it was decides, not where it
 * happened. Input that is wrong, broken or too big is the caller's (3);
 * files that cannot be read or written are the environment's (4); the rest
 * (out of memory, Embree) is ours (1). */
static int exit_status(int rc)
{
    switch (rc) {
    case MR_OK: return EXIT_OK;
    case MR_ERR_IO: return EXIT_IO;
    case MR_ERR_INVALID:
    case MR_ERR_FORMAT:
    case MR_ERR_LIMIT:
    case MR_ERR_NOT_FOUND: return EXIT_INVALID_INPUT;
    default: return EXIT_RENDER;
    }
}

typedef struct render_out {
    const char *dir;
    const mr_job *job;
    bool quiet;
    double stats_written; /* mr_now() of the last stats.json write */
    /* --frames: the frames to render (NULL: all) and the statistics file
     * of this part of the job (stats.json for a whole run) */
    const uint8_t *wanted;
    char stats_name[96];
    uint8_t *rendered;    /* per frame: rendered in this run */
    /* --png: previews beside the EXRs, and the contact sheet's thumbnails */
    bool png;
    size_t sheet_count;
    size_t sheet_index[MR_SHEET_MAX_FRAMES];
    mr_image8 thumbs[MR_SHEET_MAX_FRAMES]; /* px NULL: that frame is not done */
} render_out;

/* DIR/NNNN.png and, when frame index is on the contact sheet, its
 * thumbnail; the seconds go to the frame's "png_s" (and its encode_s). */
static int write_preview(render_out *o, size_t index, const mr_film *film, mr_frame_stats *st,
                         mr_error *err)
{
    char name[MR_FRAME_NAME_MAX], path[4200];
    mr_frame_preview_name(index, name);
    snprintf(path, sizeof path, "%s/%s", o->dir, name);
    double t0 = mr_now();
    int rc = mr_png_write_film(path, film, err);
    for (size_t i = 0; i < o->sheet_count && rc == MR_OK; i++)
        if (o->sheet_index[i] == index) {
            mr_image8_free(&o->thumbs[i]);
            rc = mr_preview_thumbnail(film, &o->thumbs[i], err);
        }
    double seconds = mr_now() - t0;
    st->encode_s += seconds;
    if (rc == MR_OK)
        rc = mr_frame_stats_add_extra(st, "png_s", "s", seconds, err);
    return rc;
}

/* DIR/contact-sheet.png of the thumbnails made (cells of frames that did
 * not finish are drawn as such). */
static int write_contact_sheet(render_out *o, mr_error *err)
{
    int tw, th;
    mr_preview_thumb_size(o->job->output.width, o->job->output.height, &tw, &th);
    mr_image8 sheet;
    uint8_t *data = NULL;
    size_t size = 0;
    char path[4200];
    snprintf(path, sizeof path, "%s/contact-sheet.png", o->dir);
    int rc = mr_contact_sheet_new(o->sheet_count, tw, th, &sheet, err);
    for (size_t i = 0; i < o->sheet_count && rc == MR_OK; i++)
        if (o->thumbs[i].px)
            rc = mr_contact_sheet_put(&sheet, i, &o->thumbs[i], err);
    if (rc == MR_OK)
        rc = mr_png_encode(&sheet, &data, &size, err);
    if (rc == MR_OK)
        rc = mr_fs_write_atomic(path, data, size, "contact sheet", err);
    free(data);
    mr_image8_free(&sheet);
    return rc;
}

static int write_frame(void *user, size_t index, const mr_film *film, mr_frame_stats *st, mr_error *err)
{
    render_out *o = user;
    char name[MR_FRAME_NAME_MAX], path[4200];
    mr_frame_file_name(index, name);
    snprintf(path, sizeof path, "%s/%s", o->dir, name);
    mr_exr_meta meta;
    mr_exr_meta_for_frame(&meta, o->job, st);
    double t0 = mr_now();
    uint8_t *data = NULL;
    size_t size = 0;
    int rc = mr_exr_write_memory(&data, &size, film, &o->job->output.exr, &meta, err);
    if (rc == MR_OK)
        rc = mr_fs_write_atomic(path, data, size, "frame", err);
    free(data);
    st->encode_s = mr_now() - t0;
    if (rc == MR_OK && o->png)
        rc = write_preview(o, index, film, st, err);
    if (rc == MR_OK)
        o->rendered[index] = 1;
    return rc;
}

static bool render_wanted(void *user, size_t index)
{
    render_out *o = user;
    return !o->wanted || o->wanted[index];
}

/* What a run killed inside a write (SIGKILL, or Ctrl-C while a frame is
 * synced) left of the files this run writes: their temporaries that no
 * live writer holds (mr_fs_atomic_abandoned), removed before it renders.
 * Only this run's files': a part of the job (--frames) leaves the other
 * parts' alone. */
static void remove_stale_temporaries(const render_out *o)
{
    DIR *d = opendir(o->dir);
    struct dirent *e;
    while (d && (e = readdir(d)) != NULL) {
        char base[256];
        if (!mr_fs_atomic_abandoned(dirfd(d), e->d_name, base, sizeof base))
            continue;
        bool ours = !strcmp(base, o->stats_name) || (!o->wanted && !strcmp(base, "contact-sheet.png"));
        for (size_t i = 0; !ours && i < o->job->frame_count; i++) {
            if (o->wanted && !o->wanted[i])
                continue;
            char name[MR_FRAME_NAME_MAX];
            mr_frame_file_name(i, name);
            ours = !strcmp(base, name);
            if (!ours && o->png) {
                mr_frame_preview_name(i, name);
                ours = !strcmp(base, name);
            }
        }
        if (ours)
            unlinkat(dirfd(d), e->d_name, 0);
    }
    if (d)
        closedir(d);
}

/* stats.json holds every frame so far; rewriting it after each frame would
 * make a long job quadratic (and fsync-bound), so it is rewritten at most
 * every MR_STATS_INTERVAL seconds and once more when the job ends. */
#define MR_STATS_INTERVAL 2.0

/* Rewrites DIR/stats.json (or, for a part of the job, its own statistics
 * file) with the frames rendered so far; on failure the previous one stays
 * (never one with frames missing) and err says why, naming the file. */
static int write_stats(render_out *o, const mr_job_stats *stats, mr_error *err)
{
    char *json = NULL;
    char path[4200];
    snprintf(path, sizeof path, "%s/%s", o->dir, o->stats_name);
    /* the frames this run rendered, in order (a range need not start at 0) */
    mr_frame_stats *fs = malloc((stats->frame_count ? stats->frame_count : 1) * sizeof *fs);
    if (!fs)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", path);
    size_t n = 0;
    for (size_t i = 0; i < stats->frame_count; i++)
        if (o->rendered[i])
            fs[n++] = stats->frames[i];
    mr_job_stats part = {.frame_count = n, .frames = fs, .threads = stats->threads};
    int rc = mr_stats_to_json(o->job, &part, 0, &json, err);
    free(fs);
    if (rc < 0)
        mr_error_prefix(err, "%s: ", path);
    else
        rc = mr_fs_write_atomic(path, json, strlen(json), "stats.json", err);
    free(json);
    o->stats_written = mr_now();
    return rc;
}

/* --frames A-B, A, or a list of both ("0-9,20,30-31"): wanted[i] = 1 for
 * each frame named. Frames count from 0; a range must not run backwards and
 * must lie inside the job (frame_count frames). On a bad spec, a message
 * naming the flag in msg and false. */
static bool parse_frames(const char *spec, size_t frame_count, uint8_t *wanted, char *msg,
                         size_t msg_size)
{
    const char *p = spec;
    if (!*p) {
        snprintf(msg, msg_size, "--frames wants frame numbers or ranges, e.g. 0-9 or 0-9,20");
        return false;
    }
    while (*p) {
        char *end;
        unsigned long a, b;
        if (*p < '0' || *p > '9' || (a = strtoul(p, &end, 10), end == p)) {
            snprintf(msg, msg_size, "--frames '%s': expected a frame number at '%s'", spec, p);
            return false;
        }
        b = a;
        p = end;
        if (*p == '-') {
            p++;
            if (*p < '0' || *p > '9' || (b = strtoul(p, &end, 10), end == p)) {
                snprintf(msg, msg_size, "--frames '%s': a range needs its last frame", spec);
                return false;
            }
            p = end;
        }
        if (b < a) {
            snprintf(msg, msg_size, "--frames '%s': the range %lu-%lu runs backwards", spec, a, b);
            return false;
        }
        if (b >= frame_count) {
            snprintf(msg, msg_size, "--frames '%s': frame %lu is not in the job (its frames are "
                     "0-%zu)", spec, b, frame_count - 1);
            return false;
        }
        for (unsigned long f = a; f <= b; f++)
            wanted[f] = 1;
        if (*p == ',' && p[1])
            p++;
        else if (*p) {
            snprintf(msg, msg_size, "--frames '%s': unexpected '%c'", spec, *p);
            return false;
        }
    }
    return true;
}

static void report_progress(void *user, size_t index, const mr_job_stats *stats)
{
    render_out *o = user;
    const mr_frame_stats *f = &stats->frames[index];
    if (!o->quiet)
        fprintf(stderr,
                "frame %zu/%zu t=%.3fs %.3fs (pose %.3f %s %.3f trace %.3f encode %.3f) %.1f Mrays/s\n",
                index + 1, o->job->frame_count, f->time, f->total_s, f->pose_s,
                mr_bvh_update_name(f->bvh), f->bvh_s, f->trace_s, f->encode_s, f->mrays_per_s);
    /* the last one is written once the job ends (mr_cmd_render), where a
     * failure can still fail the command */
    mr_error err;
    if (index + 1 < o->job->frame_count && mr_now() - o->stats_written >= MR_STATS_INTERVAL &&
        write_stats(o, stats, &err) < 0)
        fprintf(stderr, "microrayd: warning: %s\n", err.msg);
}

/* Relative asset paths are relative to the job file. */
static int resolve_asset_paths(mr_job *job, const char *job_path, mr_error *err)
{
    char *dir = mr_fs_dir_of(job_path);
    if (!dir)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    int rc = MR_OK;
    for (size_t i = 0; i < job->asset_count && rc == MR_OK; i++) {
        char *p = job->assets[i].path;
        if (!p) {
            rc = mr_error_set(err, MR_ERR_INVALID,
                              "/assets/%s/id: uploaded assets are stored by the daemon; the one-shot "
                              "renderer needs a \"path\"", job->assets[i].name);
            break;
        }
        if (p[0] == '/')
            continue;
        size_t n = strlen(dir) + strlen(p) + 2;
        char *abs = malloc(n);
        if (!abs) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory");
            break;
        }
        snprintf(abs, n, "%s/%s", dir, p);
        free(p);
        job->assets[i].path = abs;
    }
    free(dir);
    return rc;
}

static void usage_render(void)
{
    mr_usage_command_print(stderr, "render");
}

int mr_cmd_render(int argc, char **argv)
{
    mr_heap_keep_freed();
    const char *job_path = NULL, *out_dir = NULL, *cache_dir = NULL, *frames_spec = NULL;
    unsigned threads = 0;
    size_t memory_budget = mr_job_memory_default();
    bool quiet = false, png = false, prepare = false;
    for (int i = 0; i < argc; i++) {
        if (!strcmp(argv[i], "--out") && i + 1 < argc) {
            out_dir = argv[++i];
        } else if (!strcmp(argv[i], "--threads") && i + 1 < argc) {
            char *end;
            long v = strtol(argv[++i], &end, 10);
            if (*end || v < 1 || v > MR_MAX_THREADS) {
                fprintf(stderr, "microrayd: --threads wants an integer in 1..%d\n", MR_MAX_THREADS);
                return EXIT_USAGE;
            }
            threads = (unsigned)v;
        } else if (!strcmp(argv[i], "--cache") && i + 1 < argc) {
            cache_dir = argv[++i];
            if (!cache_dir[0]) {
                fprintf(stderr, "microrayd: --cache wants a directory\n");
                return EXIT_USAGE;
            }
        } else if (!strcmp(argv[i], "--job-memory-mb") && i + 1 < argc) {
            char *end;
            long v = strtol(argv[++i], &end, 10);
            if (*end || v < 1 || v > (1L << 24)) {
                fprintf(stderr, "microrayd: --job-memory-mb wants an integer in 1..%ld\n", 1L << 24);
                return EXIT_USAGE;
            }
            memory_budget = (size_t)v << 20;
        } else if (!strcmp(argv[i], "--frames") && i + 1 < argc) {
            frames_spec = argv[++i];
        } else if (!strcmp(argv[i], "--prepare")) {
            prepare = true;
        } else if (!strcmp(argv[i], "--quiet")) {
            quiet = true;
        } else if (!strcmp(argv[i], "--png")) {
            png = true;
        } else if (argv[i][0] == '-' || job_path) {
            usage_render();
            return EXIT_USAGE;
        } else {
            job_path = argv[i];
        }
    }
    if (!job_path || !out_dir || (prepare && (frames_spec || png))) {
        usage_render();
        return EXIT_USAGE;
    }

    int status = EXIT_OK;
    char *text = NULL;
    size_t len = 0;
    mr_job *job = NULL;
    mr_device *dev = NULL;
    mr_job_stats stats = {0};
    mr_error err = {0};
    mr_job_error jerr = {0};
    uint8_t *wanted = NULL, *rendered = NULL;

    int rc;
    if ((rc = mr_file_read(job_path, MR_JOB_MAX_BYTES, &text, &len, &err)) < 0) {
        fprintf(stderr, "microrayd: %s\n", err.msg);
        status = exit_status(rc);
        goto done;
    }
    if ((rc = mr_job_parse(text, len, &job, &jerr)) < 0) {
        fprintf(stderr, "microrayd: %s: invalid job at '%s': %s\n", job_path, jerr.pointer, jerr.message);
        status = exit_status(rc);
        goto done;
    }
    char pointer[512];
    if ((rc = mr_job_check_memory(job, memory_budget, pointer, &err)) < 0) {
        fprintf(stderr, "microrayd: %s: invalid job at '%s': %s\n", job_path, pointer, err.msg);
        status = exit_status(rc);
        goto done;
    }
    if ((rc = resolve_asset_paths(job, job_path, &err)) < 0 || (rc = mr_fs_make_dirs(out_dir, "output directory", &err)) < 0 ||
        (rc = mr_device_new(threads, &dev, &err)) < 0) {
        fprintf(stderr, "microrayd: %s\n", err.msg);
        status = exit_status(rc);
        goto done;
    }
    rendered = calloc(job->frame_count, 1);
    if (!rendered || (frames_spec && !(wanted = calloc(job->frame_count, 1)))) {
        fprintf(stderr, "microrayd: out of memory\n");
        status = EXIT_RENDER;
        goto done;
    }
    render_out out = {.dir = out_dir, .job = job, .quiet = quiet, .stats_written = mr_now(),
                      .png = png, .wanted = wanted, .rendered = rendered};
    snprintf(out.stats_name, sizeof out.stats_name, "stats.json");
    if (prepare) {
        /* no frame wanted: the assets are imported and each kind derives
         * its data into --cache, for the parts that follow */
        wanted = rendered;
        out.wanted = wanted;
    } else if (frames_spec) {
        char msg[512];
        if (strlen(frames_spec) > 64 || !parse_frames(frames_spec, job->frame_count, wanted, msg,
                                                      sizeof msg)) {
            fprintf(stderr, "microrayd: %s\n", strlen(frames_spec) > 64 ? "--frames: at most 64 "
                    "characters (ranges, not a list of every frame)" : msg);
            status = EXIT_USAGE;
            goto done;
        }
        /* each part of a job its own statistics file; stats-merge makes
         * stats.json of them */
        snprintf(out.stats_name, sizeof out.stats_name, "stats.frames-%s.json", frames_spec);
    }
    if (png)
        out.sheet_count = mr_contact_sheet_frames(job->frame_count, out.sheet_index);
    if (!prepare)
        remove_stale_temporaries(&out);
    mr_worker_io io = {.user = &out, .frame_done = write_frame, .progress = report_progress,
                       .wanted = render_wanted, .cache_dir = cache_dir,
                       .memory_budget = memory_budget};
    if ((rc = mr_worker_run(dev, job, &io, &stats, &err)) < 0) {
        fprintf(stderr, "microrayd: %s: %s\n", job_path, err.msg);
        status = exit_status(rc);
        /* keep the figures of the frames that did finish */
        if (stats.frame_count > 0 && write_stats(&out, &stats, &err) < 0)
            fprintf(stderr, "microrayd: warning: %s\n", err.msg);
    } else if (prepare) {
        /* what the set-up cost, for whoever split the job (a cluster task's log) */
        printf("{\"load_s\":%.6f,\"assets_loaded\":%u,\"derive_s\":%.6f}\n", stats.load_s,
               stats.assets_loaded, stats.derive_s);
    } else if ((rc = write_stats(&out, &stats, &err)) < 0) {
        /* every frame rendered, but stats.json, an output of the job, is not
         * there or not up to date */
        fprintf(stderr, "microrayd: %s\n", err.msg);
        status = exit_status(rc);
    }
    /* also after a failure: the frames that finished, the others as such
     * (a part of the job has no sheet of its own) */
    if (png && !frames_spec && stats.frame_count > 0 && (rc = write_contact_sheet(&out, &err)) < 0) {
        fprintf(stderr, "microrayd: %s/contact-sheet.png: %s\n", out_dir, err.msg);
        if (status == EXIT_OK)
            status = exit_status(rc);
    }
    for (size_t i = 0; i < out.sheet_count; i++)
        mr_image8_free(&out.thumbs[i]);
done:
    mr_job_stats_free(&stats);
    mr_device_free(dev);
    mr_job_free(job);
    if (wanted != rendered)
        free(wanted);
    free(rendered);
    free(text);
    return status;
}

/* A job file read and parsed as the daemon would; false after saying why. */
static bool load_job(const char *path, char **text, mr_job **job, int *status)
{
    size_t len = 0;
    mr_error err = {0};
    mr_job_error jerr = {0};
    int rc = mr_file_read(path, MR_JOB_MAX_BYTES, text, &len, &err);
    if (rc < 0) {
        fprintf(stderr, "microrayd: %s\n", err.msg);
        *status = exit_status(rc);
        return false;
    }
    if ((rc = mr_job_parse(*text, len, job, &jerr)) < 0) {
        fprintf(stderr, "microrayd: %s: invalid job at '%s': %s\n", path, jerr.pointer, jerr.message);
        *status = exit_status(rc);
        return false;
    }
    return true;
}

int mr_cmd_plan(int argc, char **argv)
{
    if (argc != 1) {
        mr_usage_command_print(stderr, "plan");
        return EXIT_USAGE;
    }
    char *text = NULL;
    mr_job *job = NULL;
    int status = EXIT_OK;
    if (load_job(argv[0], &text, &job, &status)) {
        cJSON *o = cJSON_CreateObject();
        cJSON_AddStringToObject(o, "name", job->name ? job->name : "");
        cJSON_AddNumberToObject(o, "frames", (double)job->frame_count);
        cJSON_AddNumberToObject(o, "max_retries", job->max_retries);
        cJSON_AddNumberToObject(o, "width", job->output.width);
        cJSON_AddNumberToObject(o, "height", job->output.height);
        cJSON *refs = cJSON_AddArrayToObject(o, "references");
        unsigned passes = 0;
        mr_error err = {0};
        if (mr_job_reference_passes(job, &passes, &err) < 0)
            status = EXIT_RENDER;
        for (int t = 0; t < MR_REFERENCE_TYPES; t++)
            if (passes & (1u << t))
                cJSON_AddItemToArray(refs, cJSON_CreateString(mr_reference_name(t)));
        char *out = cJSON_PrintUnformatted(o);
        if (out)
            printf("%s\n", out);
        else
            status = EXIT_RENDER;
        free(out);
        cJSON_Delete(o);
    }
    mr_job_free(job);
    free(text);
    return status;
}

#define PART_PREFIX "stats.frames-"

int mr_cmd_stats_merge(int argc, char **argv)
{
    if (argc != 2) {
        mr_usage_command_print(stderr, "stats-merge");
        return EXIT_USAGE;
    }
    const char *dir = argv[0];
    char *text = NULL;
    mr_job *job = NULL;
    int status = EXIT_OK;
    DIR *d = NULL;
    cJSON **docs = NULL;
    size_t ndocs = 0;
    if (!load_job(argv[1], &text, &job, &status))
        goto done;
    /* per frame: the object of the newest part file that has it (a retried
     * part rewrote its file) */
    cJSON **frame = calloc(job->frame_count, sizeof *frame);
    double *frame_mtime = calloc(job->frame_count, sizeof *frame_mtime);
    if (!frame || !frame_mtime || !(d = opendir(dir))) {
        fprintf(stderr, "microrayd: %s: %s\n", dir, d || !frame || !frame_mtime ? "out of memory"
                                                                                : strerror(errno));
        status = d ? EXIT_RENDER : EXIT_IO;
        free(frame);
        free(frame_mtime);
        goto done;
    }
    double threads = 0;
    struct dirent *e;
    while ((e = readdir(d)) != NULL) {
        size_t n = strlen(e->d_name);
        if (strncmp(e->d_name, PART_PREFIX, strlen(PART_PREFIX)) != 0 || n < 5 ||
            strcmp(e->d_name + n - 5, ".json") != 0)
            continue;
        char path[4200], *json = NULL;
        size_t len;
        mr_error err = {0};
        struct stat st;
        snprintf(path, sizeof path, "%s/%s", dir, e->d_name);
        if (stat(path, &st) != 0 || mr_file_read(path, (size_t)256 << 20, &json, &len, &err) < 0) {
            fprintf(stderr, "microrayd: %s: %s\n", path, err.msg[0] ? err.msg : strerror(errno));
            status = EXIT_IO;
            continue;
        }
        cJSON *doc = cJSON_Parse(json);
        free(json);
        cJSON **grown = realloc(docs, (ndocs + 1) * sizeof *docs);
        if (!doc || !grown) {
            fprintf(stderr, "microrayd: %s: %s\n", path, doc ? "out of memory" : "not JSON");
            cJSON_Delete(doc);
            if (grown)
                docs = grown;
            status = doc ? EXIT_RENDER : EXIT_INVALID_INPUT;
            continue;
        }
        docs = grown;
        docs[ndocs++] = doc;
        const cJSON *t = cJSON_GetObjectItemCaseSensitive(doc, "threads");
        if (cJSON_IsNumber(t) && t->valuedouble > threads)
            threads = t->valuedouble;
        double mtime = (double)st.st_mtim.tv_sec + 1e-9 * (double)st.st_mtim.tv_nsec;
        const cJSON *f;
        cJSON_ArrayForEach(f, cJSON_GetObjectItemCaseSensitive(doc, "frames")) {
            const cJSON *idx = cJSON_GetObjectItemCaseSensitive(f, "frame");
            if (!cJSON_IsNumber(idx) || idx->valuedouble < 0 ||
                idx->valuedouble >= (double)job->frame_count)
                continue;
            size_t k = (size_t)idx->valuedouble;
            if (!frame[k] || mtime >= frame_mtime[k]) {
                frame[k] = (cJSON *)f;
                frame_mtime[k] = mtime;
            }
        }
    }
    size_t n = 0, missing = 0;
    char missing_list[256] = "";
    for (size_t k = 0; k < job->frame_count; k++) {
        if (frame[k]) {
            frame[n++] = frame[k];
        } else if (missing++ < 8) {
            size_t at = strlen(missing_list);
            snprintf(missing_list + at, sizeof missing_list - at, "%s%zu", at ? ", " : "", k);
        }
    }
    free(frame_mtime);
    cJSON *root = NULL;
    mr_error err = {0};
    char *out = NULL, path[4200];
    snprintf(path, sizeof path, "%s/stats.json", dir);
    int rc = mr_stats_from_frames(job, frame, n, threads >= 1 ? (unsigned)threads : 1, &root, &err);
    if (rc == MR_OK && !(out = cJSON_Print(root)))
        rc = mr_error_set(&err, MR_ERR_NOMEM, "out of memory");
    if (rc == MR_OK)
        rc = mr_fs_write_atomic(path, out, strlen(out), "stats.json", &err);
    if (rc < 0) {
        fprintf(stderr, "microrayd: %s: %s\n", path, err.msg);
        status = exit_status(rc);
    } else if (missing) {
        fprintf(stderr, "microrayd: %s: %zu of %zu frames have no statistics (frames %s%s)\n", path,
                missing, job->frame_count, missing_list, missing > 8 ? ", ..." : "");
        if (status == EXIT_OK)
            status = EXIT_RENDER;
    }
    free(out);
    cJSON_Delete(root);
    free(frame);
done:
    if (d)
        closedir(d);
    for (size_t i = 0; i < ndocs; i++)
        cJSON_Delete(docs[i]);
    free(docs);
    mr_job_free(job);
    free(text);
    return status;
}

int mr_cmd_compare(int argc, char **argv)
{
    const char *paths[2] = {NULL, NULL};
    double diagonal = 0;
    int npaths = 0;
    for (int i = 0; i < argc; i++) {
        if (!strcmp(argv[i], "--diagonal") && i + 1 < argc) {
            char *end;
            diagonal = strtod(argv[++i], &end);
            if (*end || !(diagonal > 0) || diagonal > 1e30) {
                fprintf(stderr, "microrayd: --diagonal wants a positive number\n");
                return EXIT_USAGE;
            }
        } else if (argv[i][0] != '-' && npaths < 2) {
            paths[npaths++] = argv[i];
        } else {
            npaths = -1;
            break;
        }
    }
    if (npaths != 2) {
        mr_usage_command_print(stderr, "compare");
        return EXIT_USAGE;
    }
    int status = EXIT_OK;
    mr_film *film[2] = {NULL, NULL};
    mr_exr_meta meta[2];
    mr_error err = {0};
    int rc;
    for (int i = 0; i < 2; i++)
        if ((rc = mr_exr_read_file(paths[i], &film[i], &meta[i], &err)) < 0) {
            fprintf(stderr, "microrayd: %s\n", err.msg);
            status = exit_status(rc);
            goto done;
        }
    /* The unit of depth error: given, else the reference's (B), else A's. */
    if (diagonal <= 0)
        diagonal = meta[1].scene_diagonal > 0 ? meta[1].scene_diagonal : meta[0].scene_diagonal;
    if (!(diagonal > 0))
        diagonal = 1.0;
    mr_compare_result r;
    if ((rc = mr_film_compare(film[0], film[1], diagonal, &r, &err)) < 0) {
        fprintf(stderr, "microrayd: %s\n", err.msg);
        status = exit_status(rc);
        goto done;
    }
    cJSON *o = cJSON_CreateObject();
    cJSON_AddStringToObject(o, "a", paths[0]);
    cJSON_AddStringToObject(o, "b", paths[1]);
    cJSON_AddNumberToObject(o, "width", film[0]->width);
    cJSON_AddNumberToObject(o, "height", film[0]->height);
    cJSON_AddNumberToObject(o, "scene_diagonal", diagonal);
    cJSON_AddNumberToObject(o, "pixels_hit_either", (double)r.hit_either);
    cJSON_AddNumberToObject(o, "pixels_hit_both", (double)r.hit_both);
    cJSON_AddNumberToObject(o, "coverage_error_pct", r.coverage_pct);
    cJSON_AddNumberToObject(o, "depth_rmse", r.depth_rmse);
    cJSON_AddNumberToObject(o, "depth_max", r.depth_max);
    cJSON_AddNumberToObject(o, "normal_mean_deg", r.normal_mean_deg);
    cJSON_AddNumberToObject(o, "normal_max_deg", r.normal_max_deg);
    cJSON_AddNumberToObject(o, "surface_px", r.surface_px);
    cJSON_AddNumberToObject(o, "holes", (double)r.holes);
    cJSON_AddNumberToObject(o, "strays", (double)r.strays);
    mr_speckle_result sa, sb;
    mr_film_speckles(film[0], &sa);
    mr_film_speckles(film[1], &sb);
    cJSON_AddNumberToObject(o, "speckle_pct_a", sa.speckle_pct);
    cJSON_AddNumberToObject(o, "speckle_pct_b", sb.speckle_pct);
    cJSON_AddNumberToObject(o, "speckles_a", (double)sa.speckles);
    cJSON_AddNumberToObject(o, "speckles_b", (double)sb.speckles);
    cJSON_AddNumberToObject(o, "psnr_rgb_db", r.psnr_rgb);
    char *s = cJSON_Print(o);
    if (s)
        printf("%s\n", s);
    free(s);
    cJSON_Delete(o);
done:
    mr_film_free(film[0]);
    mr_film_free(film[1]);
    return status;
}
