/*
 * main.c - `microray`, the command-line client of the microrayd render
 * daemon: argument parsing, --help, and the commands that are one or two
 * requests (status, list, cancel, retry, delete, upload, health). Following
 * a job and downloading frames live in jobs.c, HTTP in api.c.
 *
 * Output contract: stdout carries only what scripts capture (a job or
 * asset id, the status and list tables, JSON with --json); progress,
 * confirmations and errors go to stderr; the exit code says what happened
 * (see usage() and docs/client.md).
 */
#include "api.h"
#include "client.h"
#include "cluster.h"
#include "jobs.h"
#include "usage.h"

#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include <curl/curl.h>

#define JOB_FILE_LIMIT ((size_t)64 << 20) /* far above the daemon's cap, which answers 413 */
#define MAX_POSITIONAL 4

static int usage_error(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
static int usage_error(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    fputs("microray: ", stderr);
    vfprintf(stderr, fmt, ap);
    fputs("\nTry 'microray --help'.\n", stderr);
    va_end(ap);
    return MRC_EXIT_USAGE;
}

/* ---- command-line parsing ------------------------------------------------- */

typedef struct cmd_args {
    const char *pos[MAX_POSITIONAL];
    int npos;
    const char *out, *idem, *state, *limit, *name;
    bool wait, json, png, errors;
} cmd_args;

/* Where the value of an option of the usage table goes. */
static bool *option_flag(cmd_args *a, const char *name)
{
    return !strcmp(name, "--wait") ? &a->wait : !strcmp(name, "--json") ? &a->json
           : !strcmp(name, "--png")    ? &a->png
           : !strcmp(name, "--errors") ? &a->errors
                                       : NULL;
}

static const char **option_value(cmd_args *a, const char *name)
{
    return !strcmp(name, "--out")               ? &a->out
           : !strcmp(name, "--idempotency-key") ? &a->idem
           : !strcmp(name, "--state")           ? &a->state
           : !strcmp(name, "--limit")           ? &a->limit
           : !strcmp(name, "--name")            ? &a->name
                                                : NULL;
}

/* Parses one command's arguments against its options in the usage table
 * (usage.h). "--name VALUE" and "--name=VALUE" both work; after "--"
 * everything is positional. */
static int parse_command_args(int argc, char **argv, const mr_usage_command *c, int min_pos,
                              int max_pos, cmd_args *a)
{
    bool options_done = false;
    for (int i = 0; i < argc; i++) {
        const char *arg = argv[i];
        if (!options_done && strcmp(arg, "--") == 0) {
            options_done = true;
            continue;
        }
        if (!options_done && arg[0] == '-' && arg[1] != '\0') {
            const char *eq = strchr(arg, '=');
            char name[64];
            snprintf(name, sizeof name, "%.*s", (int)(eq ? (size_t)(eq - arg) : strlen(arg)), arg);
            const mr_usage_flag *f = mrc_usage_flag_find(c, name);
            if (!f)
                return usage_error("unknown option '%s' for %s", arg, c->name);
            if (!f->arg) {
                bool *flag = option_flag(a, name);
                if (eq)
                    return usage_error("option '%s' takes no value", arg);
                if (flag)
                    *flag = true;
            } else {
                const char **value = option_value(a, name);
                if (!eq && i + 1 >= argc)
                    return usage_error("option '%s' needs a value", arg);
                const char *v = eq ? eq + 1 : argv[++i];
                if (value)
                    *value = v;
            }
            continue;
        }
        if (a->npos >= max_pos)
            return usage_error("unexpected argument '%s'", arg);
        a->pos[a->npos++] = arg;
    }
    if (a->npos < min_pos)
        return usage_error("%s", min_pos == 1 ? "missing argument (see --help)"
                                              : "missing arguments (see --help)");
    return 0;
}

/* Global options may stand anywhere: they are taken out of argv here. The
 * value of a command option is skipped so "--out --quiet" stays an error
 * of the command, not a silent global flag. */
typedef struct globals {
    const char *server;
    const char *token_file;
    bool quiet, help, version;
} globals;

static int take_globals(int argc, char **argv, globals *g, char **rest, int *nrest)
{
    *nrest = 0;
    for (int i = 1; i < argc; i++) {
        const char *arg = argv[i];
        if (strcmp(arg, "--") == 0) {
            while (i < argc)
                rest[(*nrest)++] = argv[i++];
            break;
        }
        if (strcmp(arg, "--server") == 0) {
            if (i + 1 >= argc)
                return usage_error("%s needs a URL", arg);
            g->server = argv[++i];
        } else if (strncmp(arg, "--server=", 9) == 0) {
            g->server = arg + 9;
        } else if (strcmp(arg, "--token-file") == 0) {
            if (i + 1 >= argc)
                return usage_error("%s needs a file", arg);
            g->token_file = argv[++i];
        } else if (strncmp(arg, "--token-file=", 13) == 0) {
            g->token_file = arg + 13;
        } else if (strcmp(arg, "--quiet") == 0 || strcmp(arg, "-q") == 0) {
            g->quiet = true;
        } else if (strcmp(arg, "--help") == 0 || strcmp(arg, "-h") == 0) {
            g->help = true;
        } else if (strcmp(arg, "--version") == 0 || strcmp(arg, "-V") == 0) {
            g->version = true;
        } else {
            rest[(*nrest)++] = argv[i];
            if (mrc_usage_takes_value(arg) && i + 1 < argc)
                rest[(*nrest)++] = argv[++i];
        }
    }
    return 0;
}

static int check_id(const char *id)
{
    if (!mrc_valid_id(id))
        return usage_error("'%s' is not a job id", id);
    return 0;
}

static bool stderr_is_terminal(void)
{
    const char *term = getenv("TERM");
    return isatty(STDERR_FILENO) && !(term && strcmp(term, "dumb") == 0);
}

/* The token of --token-file (its first line), else $MICRORAY_TOKEN. */
static int set_token(mrc_http *http, const char *file, mrc_error *err)
{
    if (!file)
        return mrc_http_set_token(http, getenv("MICRORAY_TOKEN"), err);
    char *text = NULL;
    size_t len = 0;
    int rc = mrc_read_file(file, 4096, &text, &len, err);
    if (rc)
        return rc;
    text[strcspn(text, "\r\n")] = '\0';
    rc = mrc_http_set_token(http, text, err);
    free(text);
    return rc;
}

/* ---- commands ------------------------------------------------------------- */

static void print_json(const cJSON *doc)
{
    char *text = cJSON_Print(doc); /* re-serialised: control characters come out escaped */
    if (text) {
        puts(text);
        free(text);
    }
}

/* GET /v1/jobs/{id} printed as JSON (--json of status, wait, submit --wait). */
static int print_job_json(mrc_http *h, const char *id, mrc_error *err)
{
    char path[256];
    snprintf(path, sizeof path, "/v1/jobs/%s", id);
    mrc_response resp = {0};
    cJSON *job = NULL;
    int rc = mrc_http_json(h, "GET", path, NULL, 0, NULL, NULL, &resp, &job, err);
    if (rc == 0 && job)
        print_json(job);
    cJSON_Delete(job);
    mrc_response_free(&resp);
    return rc;
}

/* Ctrl-C while following a job: the job goes on on the server; say how to
 * follow it again (the text is made before the signal can come: only
 * write() and _exit() run in the handler). */
static char interrupt_text[1024];
static size_t interrupt_len;

static void on_interrupt(int sig)
{
    (void)sig;
    ssize_t w = write(STDERR_FILENO, interrupt_text, interrupt_len);
    (void)w;
    _exit(130);
}

static void arm_interrupt(const char *id, const char *out)
{
    int n = snprintf(interrupt_text, sizeof interrupt_text,
                     "\nmicroray: interrupted; job %s goes on on the server. Follow it again with:\n"
                     "  microray wait %s%s%s\n"
                     "or stop it with: microray cancel %s\n",
                     id, id, out ? " --out " : "", out ? out : "", id);
    interrupt_len = n > 0 && (size_t)n < sizeof interrupt_text ? (size_t)n : 0;
    signal(SIGINT, on_interrupt);
}

/* Follows job id (submit --wait, wait): progress, downloads, and with
 * --json the job as it ended on stdout. */
static int follow_job(mrc_http *h, const char *id, const cmd_args *a, bool quiet, mrc_error *err)
{
    mrc_follow_opts opts = {.out_dir = a->out, .quiet = quiet, .tty = stderr_is_terminal(),
                            .png = a->png};
    arm_interrupt(id, a->out);
    int rc = mrc_job_wait(h, id, &opts, err);
    signal(SIGINT, SIG_DFL);
    if (a->json && (rc == 0 || rc == -MRC_EXIT_JOB_FAILED)) {
        mrc_error jerr = {0};
        int jrc = print_job_json(h, id, &jerr);
        if (jrc < 0) {
            *err = jerr;
            rc = jrc;
        }
    }
    return rc;
}

static int cmd_submit(mrc_http *h, const cmd_args *a, bool quiet, mrc_error *err)
{
    int rc = 0;
    char *body = NULL;
    size_t len = 0;
    mrc_response resp = {0};
    cJSON *doc = NULL;
    char id[520]; /* sid is at most 128 characters (mrc_valid_id) */

    rc = mrc_read_file(a->pos[0], JOB_FILE_LIMIT, &body, &len, err);
    if (rc < 0)
        goto cleanup;
    rc = mrc_http_json(h, "POST", "/v1/jobs", body, len, "application/json", a->idem, &resp, &doc,
                       err);
    if (rc < 0)
        goto cleanup;
    /* the id from the body, else the last segment of Location */
    const char *sid = mrc_json_str(doc, "id");
    if (!sid && resp.location[0]) {
        const char *slash = strrchr(resp.location, '/');
        sid = slash ? slash + 1 : resp.location;
    }
    if (!sid || !mrc_valid_id(sid)) {
        rc = mrc_fail(err, MRC_EXIT_SERVER, "the server accepted the job but sent no usable job id");
        goto cleanup;
    }
    snprintf(id, sizeof id, "%s", sid);
    bool follow = a->wait || a->out;
    if (!a->json)
        printf("%s\n", id);
    else if (!follow)
        print_json(doc); /* with --wait: the job as it ended, below */
    fflush(stdout);
    if (follow)
        rc = follow_job(h, id, a, quiet, err);
cleanup:
    cJSON_Delete(doc);
    mrc_response_free(&resp);
    free(body);
    return rc;
}

static const char *safe_str(char *dst, size_t size, const cJSON *obj, const char *key)
{
    const char *s = mrc_json_str(obj, key);
    mrc_sanitize(dst, size, s && s[0] ? s : "-");
    return dst;
}

/* One row of the error table: the frame's columns (or blanks, for its
 * second reference) and the figures of one error entry. */
static void print_error_row(const char *frame_cols, const cJSON *e)
{
    char ref[24];
    safe_str(ref, sizeof ref, e, "reference");
    printf("%s  %-12s  %8.3f  %5lld  %10.3e  %10.3e  %7.3f  %7.2f  %7.3f  %7.2f\n", frame_cols, ref,
           mrc_json_num(e, "coverage_error_pct", 0), mrc_json_int(e, "holes", 0, 0, 1LL << 52),
           mrc_json_num(e, "depth_rmse", 0), mrc_json_num(e, "depth_max", 0),
           mrc_json_num(e, "normal_mean_deg", 0), mrc_json_num(e, "psnr_rgb_db", 0),
           mrc_json_num(e, "speckle_pct", 0), mrc_json_num(e, "surface_px", 0));
}

/* status --errors: the job's stats (GET /v1/jobs/ID/stats) as a table of
 * time against error, a row per frame and reference it was compared with,
 * then per reference its medians, its worst values and the frames they
 * came from; --json prints the stats document. */
static int cmd_status_errors(mrc_http *h, const cmd_args *a, mrc_error *err)
{
    char path[256];
    snprintf(path, sizeof path, "/v1/jobs/%s/stats", a->pos[0]);
    cJSON *stats = NULL;
    int rc = mrc_http_get_json(h, path, &stats, err);
    if (rc < 0)
        goto cleanup;
    if (a->json) {
        print_json(stats);
        goto cleanup;
    }
    const cJSON *summary = cJSON_GetObjectItemCaseSensitive(stats, "error");
    if (!cJSON_IsObject(summary) || !summary->child) {
        printf("no reference passes: the job's frames done so far (%lld) were not compared with a "
               "reference (submit it with \"reference\": true)\n",
               mrc_json_int(stats, "frames_done", 0, 0, 1LL << 40));
        goto cleanup;
    }
    printf("%5s  %7s  %5s  %-12s  %8s  %5s  %10s  %10s  %7s  %7s  %7s  %7s\n", "frame", "total s",
           "ref s", "reference", "cover %", "holes", "depth rmse", "depth max", "normal", "PSNR dB",
           "speck %", "surf px");
    const cJSON *fr;
    cJSON_ArrayForEach(fr, cJSON_GetObjectItemCaseSensitive(stats, "frames")) {
        const cJSON *secs = cJSON_GetObjectItemCaseSensitive(fr, "seconds"), *e;
        char cols[64];
        snprintf(cols, sizeof cols, "%5lld  %7.3f  %5.2f", mrc_json_int(fr, "frame", -1, -1, 1LL << 40),
                 mrc_json_num(secs, "total", 0), mrc_json_num(secs, "reference", 0));
        bool first = true;
        cJSON_ArrayForEach(e, cJSON_GetObjectItemCaseSensitive(fr, "error")) {
            print_error_row(first ? cols : "                     ", e);
            first = false;
        }
        if (first)
            printf("%s  (not compared)\n", cols);
    }
    const cJSON *ref;
    cJSON_ArrayForEach(ref, summary) {
        const cJSON *med = cJSON_GetObjectItemCaseSensitive(ref, "medians");
        const cJSON *worst = cJSON_GetObjectItemCaseSensitive(ref, "worst");
        char name[24];
        mrc_sanitize(name, sizeof name, ref->string ? ref->string : "?");
        cJSON *row = cJSON_Duplicate(med, true), *values = cJSON_CreateObject();
        if (row && values && cJSON_AddStringToObject(row, "reference", name) &&
            cJSON_AddStringToObject(values, "reference", name)) {
            char cols[64];
            snprintf(cols, sizeof cols, "%-21s", "median");
            print_error_row(cols, row);
            /* the worst value of each figure, and the frame it came from */
            static const char *const figures[] = {"coverage_error_pct", "holes", "depth_rmse",
                                                  "depth_max", "normal_mean_deg", "psnr_rgb_db",
                                                  "speckle_pct", "surface_px"};
            enum { FIGURES = sizeof figures / sizeof figures[0] };
            long long at[FIGURES];
            for (int k = 0; k < FIGURES; k++) {
                const cJSON *w = cJSON_GetObjectItemCaseSensitive(worst, figures[k]);
                cJSON_AddNumberToObject(values, figures[k], mrc_json_num(w, "value", 0));
                at[k] = mrc_json_int(w, "frame", -1, -1, 1LL << 40);
            }
            snprintf(cols, sizeof cols, "%-21s", "worst");
            print_error_row(cols, values);
            printf("%-21s  %-12s  %8lld  %5lld  %10lld  %10lld  %7lld  %7lld  %7lld  %7lld\n",
                   "  at frame", "", at[0], at[1], at[2], at[3], at[4], at[5], at[6], at[7]);
        }
        cJSON_Delete(row);
        cJSON_Delete(values);
    }
cleanup:
    cJSON_Delete(stats);
    return rc;
}

static int cmd_status(mrc_http *h, const cmd_args *a, mrc_error *err)
{
    char path[256], name[128], state[32], when[64], error[512];
    if (a->errors)
        return cmd_status_errors(h, a, err);
    snprintf(path, sizeof path, "/v1/jobs/%s", a->pos[0]);
    cJSON *job = NULL;
    int rc = mrc_http_get_json(h, path, &job, err);
    if (rc < 0)
        goto cleanup;
    if (a->json) {
        print_json(job);
        goto cleanup;
    }
    const cJSON *frames = cJSON_GetObjectItemCaseSensitive(job, "frames");
    long long total = mrc_json_int(frames, "total", 0, 0, 1LL << 40);
    long long done = mrc_json_int(frames, "done", 0, 0, 1LL << 40);
    long long failed = mrc_json_int(frames, "failed", 0, 0, 1LL << 40);
    const cJSON *raw_states = cJSON_GetObjectItemCaseSensitive(job, "frame_states");
    const cJSON *states = cJSON_IsArray(raw_states) ? raw_states : NULL;
    long long running = 0, pending = 0;
    const cJSON *fr;
    cJSON_ArrayForEach(fr, states) {
        const char *st = mrc_json_str(fr, "state");
        running += st && strcmp(st, "running") == 0;
        pending += st && strcmp(st, "pending") == 0;
    }

    char clean_id[160];
    mrc_sanitize(clean_id, sizeof clean_id, a->pos[0]);
    printf("id        %s\n", clean_id);
    printf("name      %s\n", safe_str(name, sizeof name, job, "name"));
    printf("state     %s\n", safe_str(state, sizeof state, job, "state"));
    printf("priority  %lld\n", mrc_json_int(job, "priority", 0, -(1LL << 40), 1LL << 40));
    printf("frames    %lld/%lld done", done, total);
    if (failed)
        printf(", %lld failed", failed);
    if (states)
        printf(", %lld running, %lld pending", running, pending);
    printf("\n");
    if (cJSON_IsNumber(cJSON_GetObjectItemCaseSensitive(job, "max_retries")))
        printf("retries   up to %lld per frame\n", mrc_json_int(job, "max_retries", 0, 0, 1LL << 40));
    mrc_format_time_field(when, sizeof when, job, "created");
    printf("created   %s\n", when);
    mrc_format_time_field(when, sizeof when, job, "started");
    printf("started   %s\n", when);
    mrc_format_time_field(when, sizeof when, job, "finished");
    printf("finished  %s\n", when);
    if (mrc_json_str(job, "error") && mrc_json_str(job, "error")[0])
        printf("error     %s\n", safe_str(error, sizeof error, job, "error"));

    /* the frames that need attention */
    int shown = 0, more = 0;
    cJSON_ArrayForEach(fr, states) {
        const char *st = mrc_json_str(fr, "state");
        bool bad = st && strcmp(st, "failed") == 0;
        long long retries = mrc_json_int(fr, "retries", 0, 0, 1LL << 40);
        if (!bad && !(retries > 0 && mrc_json_str(fr, "error")))
            continue;
        if (shown == 20) {
            more++;
            continue;
        }
        if (shown++ == 0)
            printf("frames with errors:\n");
        printf("  %6lld  %-7s  %lld retr%s  %s\n", mrc_json_int(fr, "index", -1, -1, 1LL << 40),
               bad ? "failed" : st ? (strcmp(st, "done") == 0 ? "done" : "retried") : "?", retries,
               retries == 1 ? "y" : "ies", safe_str(error, sizeof error, fr, "error"));
    }
    if (more)
        printf("  ... and %d more\n", more);
cleanup:
    cJSON_Delete(job);
    return rc;
}

/* One table row of a job of the list. */
static void print_job_row(const cJSON *job)
{
    char id[40], name[64], state[16], frames_col[48], created[64];
    safe_str(id, sizeof id, job, "id");
    safe_str(name, sizeof name, job, "name");
    if (strlen(name) > 20)
        memcpy(name + 17, "...", 4);
    safe_str(state, sizeof state, job, "state");
    const cJSON *frames = cJSON_GetObjectItemCaseSensitive(job, "frames");
    long long failed = mrc_json_int(frames, "failed", 0, 0, 1LL << 40);
    int n = snprintf(frames_col, sizeof frames_col, "%lld/%lld",
                     mrc_json_int(frames, "done", 0, 0, 1LL << 40),
                     mrc_json_int(frames, "total", 0, 0, 1LL << 40));
    if (failed && n > 0 && (size_t)n < sizeof frames_col)
        snprintf(frames_col + n, sizeof frames_col - (size_t)n, " (%lld!)", failed);
    mrc_format_time_field(created, sizeof created, job, "created");
    printf("%-32s  %-20s  %-9s  %4lld  %-13s  %s\n", id, name, state,
           mrc_json_int(job, "priority", 0, -999, 9999), frames_col, created);
}

/* list: GET /v1/jobs page by page (the server's "next" cursor) until the
 * last page, or until --limit jobs were shown. */
static int cmd_list(mrc_http *h, const cmd_args *a, mrc_error *err)
{
    static const char *const valid[] = {"queued", "running", "succeeded", "failed", "canceled", NULL};
    if (a->state) {
        bool ok = false;
        for (const char *const *v = valid; *v; v++)
            ok = ok || strcmp(a->state, *v) == 0;
        if (!ok)
            return -usage_error(
                "--state '%s': expected queued, running, succeeded, failed or canceled", a->state);
    }
    long long wanted = 0; /* 0: every job */
    if (a->limit) {
        char *end = NULL;
        wanted = strtoll(a->limit, &end, 10);
        if (!*a->limit || *end || wanted < 1 || wanted > 1000000)
            return -usage_error("--limit '%s': expected a number of jobs, 1 or more", a->limit);
    }
    char name_q[800] = "";
    if (a->name) {
        if (!a->name[0] || strlen(a->name) > 256)
            return -usage_error("%s", "--name: 1 to 256 bytes");
        char *enc = curl_easy_escape(NULL, a->name, 0);
        if (!enc)
            return mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
        snprintf(name_q, sizeof name_q, "&name=%s", enc);
        curl_free(enc);
    }
    cJSON *all = a->json ? cJSON_CreateArray() : NULL;
    if (a->json && !all)
        return mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
    char cursor[64] = "";
    long long shown = 0;
    int rc = 0;
    for (;;) {
        long long page = 1000;
        if (wanted && wanted - shown < page)
            page = wanted - shown;
        char path[1024];
        snprintf(path, sizeof path, "/v1/jobs?limit=%lld%s%s%s%s%s", page, a->state ? "&state=" : "",
                 a->state ? a->state : "", name_q, cursor[0] ? "&cursor=" : "", cursor);
        mrc_response resp = {0};
        cJSON *doc = NULL;
        rc = mrc_http_json(h, "GET", path, NULL, 0, NULL, NULL, &resp, &doc, err);
        mrc_response_free(&resp);
        if (rc < 0)
            break;
        const cJSON *jobs = cJSON_GetObjectItemCaseSensitive(doc, "jobs");
        if (!cJSON_IsArray(jobs)) {
            cJSON_Delete(doc);
            rc = mrc_fail(err, MRC_EXIT_SERVER, "GET %s: the answer has no \"jobs\" array", path);
            break;
        }
        const cJSON *job;
        cJSON_ArrayForEach(job, jobs) {
            if (all) {
                cJSON *copy = cJSON_Duplicate(job, true);
                if (!copy || !cJSON_AddItemToArray(all, copy)) {
                    cJSON_Delete(copy);
                    rc = mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
                    break;
                }
            } else {
                if (shown == 0)
                    printf("%-32s  %-20s  %-9s  %4s  %-13s  %s\n", "ID", "NAME", "STATE", "PRI",
                           "FRAMES", "CREATED");
                print_job_row(job);
            }
            shown++;
        }
        const char *next = mrc_json_str(doc, "next");
        bool more = rc == 0 && next && next[0] && strlen(next) < sizeof cursor &&
                    strspn(next, "0123456789") == strlen(next) && (!wanted || shown < wanted);
        if (more)
            snprintf(cursor, sizeof cursor, "%s", next);
        cJSON_Delete(doc);
        if (!more)
            break;
    }
    if (rc == 0 && all) {
        cJSON *doc = cJSON_CreateObject();
        if (!doc || !cJSON_AddItemToObject(doc, "jobs", all)) {
            cJSON_Delete(doc);
            cJSON_Delete(all);
            return mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
        }
        print_json(doc);
        cJSON_Delete(doc);
        return 0;
    }
    cJSON_Delete(all);
    if (rc == 0 && shown == 0)
        printf("no jobs\n");
    return rc;
}

/* cancel and retry: POST /v1/jobs/{id}/<action>, report the new state */
static int cmd_action(mrc_http *h, const char *action, const cmd_args *a, bool quiet,
                      mrc_error *err)
{
    char path[256], state[32];
    snprintf(path, sizeof path, "/v1/jobs/%s/%s", a->pos[0], action);
    mrc_response resp = {0};
    cJSON *doc = NULL;
    int rc = mrc_http_json(h, "POST", path, NULL, 0, NULL, NULL, &resp, &doc, err);
    if (rc == 0 && a->json)
        print_json(doc);
    if (rc == 0 && !quiet) {
        safe_str(state, sizeof state, doc, "state");
        if (strcmp(action, "retry") == 0)
            fprintf(stderr, "job %s: %lld frame%s requeued, state %s\n", a->pos[0],
                    mrc_json_int(doc, "frames_requeued", 0, 0, 1LL << 40),
                    mrc_json_int(doc, "frames_requeued", 0, 0, 1LL << 40) == 1 ? "" : "s", state);
        else
            fprintf(stderr, "job %s: cancel requested, state %s\n", a->pos[0], state);
    }
    cJSON_Delete(doc);
    mrc_response_free(&resp);
    return rc;
}

static int cmd_delete(mrc_http *h, const cmd_args *a, bool quiet, mrc_error *err)
{
    char path[256];
    snprintf(path, sizeof path, "/v1/jobs/%s", a->pos[0]);
    mrc_response resp = {0};
    int rc = mrc_http_request(h, "DELETE", path, NULL, 0, NULL, NULL, &resp, err);
    if (rc == 0)
        rc = mrc_http_check(&resp, err);
    if (rc == 0 && a->json) {
        char clean[160];
        mrc_sanitize(clean, sizeof clean, a->pos[0]);
        cJSON *o = cJSON_CreateObject();
        cJSON_AddStringToObject(o, "id", clean);
        cJSON_AddBoolToObject(o, "deleted", true);
        print_json(o);
        cJSON_Delete(o);
    }
    if (rc == 0 && !quiet)
        fprintf(stderr, "job %s deleted\n", a->pos[0]);
    mrc_response_free(&resp);
    return rc;
}

static int cmd_upload(mrc_http *h, const cmd_args *a, bool quiet, mrc_error *err)
{
    mrc_response resp = {0};
    cJSON *doc = NULL;
    int rc = mrc_http_upload(h, "/v1/assets", a->pos[0], &resp, err);
    if (rc == 0)
        rc = mrc_http_check(&resp, err);
    if (rc < 0)
        goto cleanup;
    doc = cJSON_ParseWithLength(resp.body.data ? resp.body.data : "", resp.body.len);
    const char *id = mrc_json_str(doc, "id");
    /* an asset id is a SHA-256 in hex; anything else would break the job */
    bool ok = id && strlen(id) == 64 && strspn(id, "0123456789abcdefABCDEF") == 64;
    if (!ok) {
        rc = mrc_fail(err, MRC_EXIT_SERVER, "POST /v1/assets: the answer has no asset id");
        goto cleanup;
    }
    if (a->json)
        print_json(doc);
    else
        printf("%s\n", id);
    fflush(stdout);
    if (!quiet) {
        char size[32];
        mrc_format_bytes(size, sizeof size, mrc_json_num(doc, "size", 0.0));
        const cJSON *existed = cJSON_GetObjectItemCaseSensitive(doc, "existed");
        fprintf(stderr, "%s: %s %s\n", a->pos[0], size,
                cJSON_IsTrue(existed) || resp.status == 200 ? "already stored on the server"
                                                            : "stored");
    }
cleanup:
    cJSON_Delete(doc);
    mrc_response_free(&resp);
    return rc;
}

static int cmd_health(mrc_http *h, const cmd_args *a, mrc_error *err)
{
    mrc_response resp = {0};
    long ready = 0;
    int rc = mrc_http_request(h, "GET", "/healthz", NULL, 0, NULL, NULL, &resp, err);
    if (rc == 0)
        rc = mrc_http_check(&resp, err);
    if (rc < 0)
        goto cleanup;
    if (!a->json)
        printf("healthz  ok\n");
    rc = mrc_http_request(h, "GET", "/readyz", NULL, 0, NULL, NULL, &resp, err);
    if (rc < 0)
        goto cleanup;
    ready = resp.status;
    if (a->json) {
        cJSON *o = cJSON_CreateObject();
        cJSON_AddStringToObject(o, "healthz", "ok");
        cJSON_AddStringToObject(o, "readyz", ready == 200 ? "ready" : "not ready");
        cJSON_AddNumberToObject(o, "readyz_status", (double)ready);
        print_json(o);
        cJSON_Delete(o);
    } else if (ready == 200) {
        printf("readyz   ready\n");
    } else {
        printf("readyz   not ready (%ld)\n", ready);
    }
    if (ready != 200) {
        mrc_http_check(&resp, err);
        rc = -err->code;
    }
cleanup:
    fflush(stdout);
    mrc_response_free(&resp);
    return rc;
}

/* fetch: the frames and stats.json into --out; with --json what came. */
static int cmd_fetch(mrc_http *h, const cmd_args *a, bool quiet, mrc_error *err)
{
    mrc_follow_opts opts = {.out_dir = a->out, .quiet = quiet, .tty = stderr_is_terminal(),
                            .png = a->png};
    mrc_fetch_result res = {0};
    int rc = mrc_job_fetch(h, a->pos[0], &opts, &res, err);
    if (rc == 0 && a->json) {
        char clean[160];
        mrc_sanitize(clean, sizeof clean, a->pos[0]);
        cJSON *o = cJSON_CreateObject();
        cJSON_AddStringToObject(o, "id", clean);
        cJSON_AddStringToObject(o, "state", res.state);
        cJSON_AddStringToObject(o, "out", a->out);
        cJSON_AddNumberToObject(o, "frames_fetched", res.fetched);
        cJSON_AddNumberToObject(o, "bytes", (double)res.bytes);
        cJSON_AddNumberToObject(o, "frames_done", res.done);
        cJSON_AddNumberToObject(o, "frames_total", res.total);
        cJSON_AddBoolToObject(o, "png", a->png);
        print_json(o);
        cJSON_Delete(o);
    }
    return rc;
}

/* ---- main ----------------------------------------------------------------- */

int main(int argc, char **argv)
{
    int code = 0;
    char **rest = NULL;
    int nrest = 0;
    mrc_http *http = NULL;
    mrc_error err = {0};
    globals g = {0};
    cmd_args a = {0};
    bool curl_ready = false;

    /* writing to a closed pipe (microray list | head) must end in an
     * error code, not a signal */
    signal(SIGPIPE, SIG_IGN);

    rest = calloc((size_t)argc + 1, sizeof *rest);
    if (!rest) {
        fprintf(stderr, "microray: out of memory\n");
        return MRC_EXIT_LOCAL;
    }
    code = take_globals(argc, argv, &g, rest, &nrest);
    if (code)
        goto cleanup;
    if (g.help) {
        /* with a command: that command's usage, on stdout, exit 0 */
        char name[64] = "";
        if (nrest > 0)
            snprintf(name, sizeof name, "%s%s%s", rest[0],
                     nrest > 1 && !strcmp(rest[0], "cluster") ? " " : "",
                     nrest > 1 && !strcmp(rest[0], "cluster") ? rest[1] : "");
        const mr_usage_command *c = mrc_usage_find(name);
        if (c) {
            fputs("usage:\n", stdout);
            mrc_usage_command_print(stdout, c);
        } else {
            mrc_usage_all(stdout);
        }
        goto cleanup;
    }
    if (g.version) {
        curl_version_info_data *cv = curl_version_info(CURLVERSION_NOW);
        printf("microray %s (libcurl %s, cJSON %s)\n", MRC_VERSION, cv ? cv->version : "?",
               cJSON_Version());
        goto cleanup;
    }
    if (nrest == 0) {
        mrc_usage_all(stderr);
        code = MRC_EXIT_USAGE;
        goto cleanup;
    }
    const char *cmd = rest[0];
    int cargc = nrest - 1;
    char **cargv = rest + 1;
    if (strcmp(cmd, "cluster") == 0) { /* a batch scheduler, not a daemon: no HTTP */
        code = mrc_cluster_main(cargc, cargv, g.quiet);
        goto cleanup;
    }
    if (strcmp(cmd, "help") == 0) {
        const mr_usage_command *c = cargc > 0 ? mrc_usage_find(cargv[0]) : NULL;
        if (c) {
            fputs("usage:\n", stdout);
            mrc_usage_command_print(stdout, c);
        } else {
            mrc_usage_all(stdout);
        }
        goto cleanup;
    }
    if (strcmp(cmd, "man") == 0) { /* the manual page, from the usage table (make man) */
        mrc_usage_man(stdout);
        goto cleanup;
    }
    if (strcmp(cmd, "completion") == 0) { /* bash completion, from the usage table */
        mrc_usage_completion(stdout);
        goto cleanup;
    }
    const mr_usage_command *spec = mrc_usage_find(cmd);
    if (!spec) {
        code = usage_error("unknown command '%s'", cmd);
        goto cleanup;
    }
    int pos = spec->args[0] ? 1 : 0; /* ID, FILE or JOB.json, or nothing */
    code = parse_command_args(cargc, cargv, spec, pos, pos, &a);
    if (code)
        goto cleanup;
    if (strcmp(cmd, "fetch") == 0 && !a.out) {
        code = usage_error("%s", "fetch needs --out DIR");
        goto cleanup;
    }
    if (a.png && !a.out) {
        code = usage_error("%s", "--png needs --out DIR");
        goto cleanup;
    }
    if ((a.out && !a.out[0]) || (a.idem && !a.idem[0])) {
        code = usage_error("%s", "empty option value");
        goto cleanup;
    }
    if (a.idem) {
        /* it becomes a header line: no CR/LF smuggling, printable ASCII only */
        for (const char *p = a.idem; *p; p++) {
            if ((unsigned char)*p < 0x21 || (unsigned char)*p > 0x7e || strlen(a.idem) > 200) {
                code = usage_error("%s", "--idempotency-key: 1..200 printable ASCII characters");
                goto cleanup;
            }
        }
    }
    if (strcmp(cmd, "submit") != 0 && strcmp(cmd, "upload") != 0 && strcmp(cmd, "list") != 0 &&
        strcmp(cmd, "health") != 0) {
        code = check_id(a.pos[0]);
        if (code)
            goto cleanup;
    }

    const char *server = g.server;
    if (!server) {
        server = getenv("MICRORAY_SERVER");
        if (!server || !server[0])
            server = MRC_DEFAULT_SERVER;
    }
    if (curl_global_init(CURL_GLOBAL_DEFAULT) != CURLE_OK) {
        fprintf(stderr, "microray: cannot initialise libcurl\n");
        code = MRC_EXIT_LOCAL;
        goto cleanup;
    }
    curl_ready = true;
    int rc = mrc_http_open(server, &http, &err);
    if (rc == 0)
        rc = set_token(http, g.token_file, &err);
    if (rc == 0) {
        if (strcmp(cmd, "submit") == 0)
            rc = cmd_submit(http, &a, g.quiet, &err);
        else if (strcmp(cmd, "status") == 0)
            rc = cmd_status(http, &a, &err);
        else if (strcmp(cmd, "list") == 0)
            rc = cmd_list(http, &a, &err);
        else if (strcmp(cmd, "fetch") == 0)
            rc = cmd_fetch(http, &a, g.quiet, &err);
        else if (strcmp(cmd, "wait") == 0)
            rc = follow_job(http, a.pos[0], &a, g.quiet, &err);
        else if (strcmp(cmd, "cancel") == 0 || strcmp(cmd, "retry") == 0)
            rc = cmd_action(http, cmd, &a, g.quiet, &err);
        else if (strcmp(cmd, "delete") == 0)
            rc = cmd_delete(http, &a, g.quiet, &err);
        else if (strcmp(cmd, "upload") == 0)
            rc = cmd_upload(http, &a, g.quiet, &err);
        else
            rc = cmd_health(http, &a, &err);
    }
    if (rc < 0) {
        code = -rc;
        /* usage errors found late (a bad --state) were already printed */
        if (err.code)
            fprintf(stderr, "microray: %s\n", err.msg);
        if (code == MRC_EXIT_USAGE && err.code)
            fputs("Try 'microray --help'.\n", stderr);
    }
    if (code == 0 && (fflush(stdout) != 0 || ferror(stdout))) {
        fprintf(stderr, "microray: cannot write to standard output\n");
        code = MRC_EXIT_LOCAL;
    }
cleanup:
    mrc_http_close(http);
    if (curl_ready)
        curl_global_cleanup();
    free(rest);
    return code;
}
