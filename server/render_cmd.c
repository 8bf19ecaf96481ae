/*
 * render_cmd.c - one-shot render and compare commands (render_cmd.h).
 *
 * render: the job file is parsed and validated exactly as the daemon does;
 * relative asset paths are resolved against the job file's directory. Each
 * frame is written as DIR/NNNN.exr through a temporary file and a rename,
 * and DIR/stats.json is rewritten after every frame, so an interrupted run
 * leaves only complete files behind. With --cache DIR, kinds that derive
 * data from an asset (bakes, voxelisations) keep it in DIR/<kind>/ and
 * reuse it (mr_renderer_options.cache_dir).
 */
#include "render_cmd.h"

#include <cJSON.h>
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
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
} render_out;

static int write_frame(void *user, size_t index, const mr_film *film, mr_frame_stats *st, mr_error *err)
{
    render_out *o = user;
    char name[MR_FRAME_NAME_MAX], path[4200];
    mr_frame_file_name(index, name);
    snprintf(path, sizeof path, "%s/%s", o->dir, name);
    mr_exr_meta meta = {.frame = (int)index, .time = st->time, .render_seconds = st->total_s,
                        .scene_diagonal = st->scene_diagonal};
    snprintf(meta.job, sizeof meta.job, "%s", o->job->name);
    double t0 = mr_now();
    uint8_t *data = NULL;
    size_t size = 0;
    int rc = mr_exr_write_memory(&data, &size, film, &o->job->output.exr, &meta, err);
    if (rc == MR_OK)
        rc = mr_fs_write_atomic(path, data, size, "frame", err);
    free(data);
    st->encode_s = mr_now() - t0;
    return rc;
}

/* stats.json holds every frame so far; rewriting it after each frame would
 * make a long job quadratic (and fsync-bound), so it is rewritten at most
 * every MR_STATS_INTERVAL seconds and once more when the job ends. */
#define MR_STATS_INTERVAL 2.0

/* Rewrites DIR/stats.json; on failure the previous one stays (never one
 * with frames missing) and err says why, naming the file. */
static int write_stats(render_out *o, const mr_job_stats *stats, mr_error *err)
{
    char *json = NULL;
    char path[4200];
    snprintf(path, sizeof path, "%s/stats.json", o->dir);
    int rc = mr_stats_to_json(o->job, stats, 0, &json, err);
    if (rc < 0)
        mr_error_prefix(err, "%s: ", path);
    else
        rc = mr_fs_write_atomic(path, json, strlen(json), "stats.json", err);
    free(json);
    o->stats_written = mr_now();
    return rc;
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
    fprintf(stderr, "usage: microrayd render JOB.json --out DIR [--threads N] [--cache DIR] "
                    "[--job-memory-mb N] [--quiet]\n"
                    "  --cache DIR  keep derived data (bakes, voxelisations) in DIR/<kind>/ "
                    "(created if missing)\n"
                    "               and reuse it (default: derive it again every time)\n"
                    "  --job-memory-mb N  what the job's geometry may hold (default: half of "
                    "the machine's memory)\n");
}

int mr_cmd_render(int argc, char **argv)
{
    const char *job_path = NULL, *out_dir = NULL, *cache_dir = NULL;
    unsigned threads = 0;
    size_t memory_budget = mr_job_memory_default();
    bool quiet = false;
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
        } else if (!strcmp(argv[i], "--quiet")) {
            quiet = true;
        } else if (argv[i][0] == '-' || job_path) {
            usage_render();
            return EXIT_USAGE;
        } else {
            job_path = argv[i];
        }
    }
    if (!job_path || !out_dir) {
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
    if ((rc = resolve_asset_paths(job, job_path, &err)) < 0 || (rc = mr_fs_make_dirs(out_dir, "output directory", &err)) < 0 ||
        (rc = mr_device_new(threads, &dev, &err)) < 0) {
        fprintf(stderr, "microrayd: %s\n", err.msg);
        status = exit_status(rc);
        goto done;
    }
    render_out out = {.dir = out_dir, .job = job, .quiet = quiet, .stats_written = mr_now()};
    mr_worker_io io = {.user = &out, .frame_done = write_frame, .progress = report_progress,
                       .cache_dir = cache_dir, .memory_budget = memory_budget};
    if ((rc = mr_worker_run(dev, job, &io, &stats, &err)) < 0) {
        fprintf(stderr, "microrayd: %s: %s\n", job_path, err.msg);
        status = exit_status(rc);
        /* keep the figures of the frames that did finish */
        if (stats.frame_count > 0 && write_stats(&out, &stats, &err) < 0)
            fprintf(stderr, "microrayd: warning: %s\n", err.msg);
    } else if ((rc = write_stats(&out, &stats, &err)) < 0) {
        /* every frame rendered, but stats.json, an output of the job, is not
         * there or not up to date */
        fprintf(stderr, "microrayd: %s\n", err.msg);
        status = exit_status(rc);
    }
done:
    mr_job_stats_free(&stats);
    mr_device_free(dev);
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
        fprintf(stderr, "usage: microrayd compare A.exr B.exr [--diagonal D]\n");
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
