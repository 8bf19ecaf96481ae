/*
 * jobs.c - following a job and downloading its frames (see jobs.h).
 *
 * The client keeps its own view of the job: the state, the frame count and
 * one state byte per frame. Snapshots (GET /v1/jobs/{id}) replace the view;
 * stream events update it one frame at a time. Comparing old and new frame
 * states is what turns either source into "frame 12 done" lines and
 * downloads, so a frame is reported and downloaded once however it was
 * learned about, and nothing from the server is trusted to be in range.
 */
#include "jobs.h"
#include "progress.h"
#include "sse.h"

#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define MAX_FRAMES 1000000        /* the job format allows 100,000 */
#define POLL_INTERVAL_S 0.5
#define POLL_GIVE_UP_S 60.0       /* server unreachable this long while polling: give up */

enum { FS_UNKNOWN = 0, FS_PENDING, FS_RUNNING, FS_DONE, FS_FAILED };

/* Why an event handler stopped the stream (any nonzero value stops it). */
enum { STOP_TERMINAL = 1, STOP_FATAL = 2, STOP_BROKEN = 3 };

typedef struct follow {
    mrc_http *http;
    const char *id;
    const mrc_follow_opts *opts;
    mrc_progress prog;

    char state[16];
    char job_error[512];
    int total;               /* frames.total, 0 while unknown */
    int done, failed;        /* what the bar shows */
    unsigned char *fstate;   /* [total] FS_* */
    unsigned char *fetched;  /* [total] downloaded in this run */
    bool have_states;        /* fstate came from a snapshot's frame_states */
    int downloaded;
    int64_t downloaded_bytes;

    mrc_sse sse;
    char last_event_id[64];  /* of the stream so far: a dropped stream resumes after it */
    int events;              /* events the current stream brought */
    bool synced;             /* re-read the job once the stream was open */
    mrc_error fatal;         /* why a callback stopped everything */
} follow;

static bool is_terminal(const char *state)
{
    return strcmp(state, "succeeded") == 0 || strcmp(state, "failed") == 0 ||
           strcmp(state, "canceled") == 0;
}

static int frame_state_parse(const char *s)
{
    if (!s)
        return FS_UNKNOWN;
    if (strcmp(s, "pending") == 0 || strcmp(s, "queued") == 0)
        return FS_PENDING;
    if (strcmp(s, "running") == 0)
        return FS_RUNNING;
    if (strcmp(s, "done") == 0 || strcmp(s, "succeeded") == 0)
        return FS_DONE;
    if (strcmp(s, "failed") == 0)
        return FS_FAILED;
    return FS_UNKNOWN;
}

/* "seconds" of a frame: a number, or an object with "total". */
static double frame_seconds(const cJSON *frame)
{
    const cJSON *s = cJSON_GetObjectItemCaseSensitive(frame, "seconds");
    if (cJSON_IsNumber(s))
        return mrc_json_num(frame, "seconds", -1.0);
    if (cJSON_IsObject(s))
        return mrc_json_num(s, "total", -1.0);
    return -1.0;
}

static int set_total(follow *f, int total, mrc_error *err)
{
    if (total == f->total && (total == 0 || f->fstate))
        return 0;
    unsigned char *s = calloc((size_t)total + 1, 1), *d = calloc((size_t)total + 1, 1);
    if (!s || !d) {
        free(s);
        free(d);
        return mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
    }
    int keep = f->total < total ? f->total : total;
    if (f->fstate)
        memcpy(s, f->fstate, (size_t)keep);
    if (f->fetched)
        memcpy(d, f->fetched, (size_t)keep);
    free(f->fstate);
    free(f->fetched);
    f->fstate = s;
    f->fetched = d;
    f->total = total;
    return 0;
}

static void recount(follow *f)
{
    if (!f->have_states)
        return;
    f->done = f->failed = 0;
    for (int i = 0; i < f->total; i++) {
        f->done += f->fstate[i] == FS_DONE;
        f->failed += f->fstate[i] == FS_FAILED;
    }
}

static void set_state(follow *f, const char *state)
{
    char clean[sizeof f->state];
    mrc_sanitize(clean, sizeof clean, state);
    if (!clean[0] || strcmp(clean, f->state) == 0)
        return;
    snprintf(f->state, sizeof f->state, "%s", clean);
    /* on a terminal the bar shows the state; a log gets a line (the end
     * of the job gets its own summary) */
    if (!f->opts->tty && !is_terminal(f->state))
        mrc_progress_message(&f->prog, "job %s %s", f->id, f->state);
}

/* ---- downloads ------------------------------------------------------------ */

static int download_frame(follow *f, int index, mrc_error *err)
{
    char path[256], dest[4096];
    const char *ext = f->opts->png ? "png" : "exr";
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/%d%s", f->id, index, f->opts->png ? ".png" : "");
    int n = snprintf(dest, sizeof dest, "%s/%04d.%s", f->opts->out_dir, index, ext);
    if (n < 0 || (size_t)n >= sizeof dest)
        return mrc_fail(err, MRC_EXIT_LOCAL, "%s: path too long", f->opts->out_dir);
    int64_t bytes = 0;
    int rc = mrc_http_download(f->http, path, dest, &bytes, err);
    if (rc < 0)
        return rc;
    f->fetched[index] = 1;
    f->downloaded++;
    f->downloaded_bytes += bytes;
    return 0;
}

static int download_done_frames(follow *f, mrc_error *err)
{
    if (!f->opts->out_dir)
        return 0;
    for (int i = 0; i < f->total; i++) {
        if (f->fstate[i] == FS_DONE && !f->fetched[i]) {
            int rc = download_frame(f, i, err);
            if (rc < 0)
                return rc;
        }
    }
    return 0;
}

/* The job's file `what` ("stats", "contact-sheet.png") into DIR/name. */
static int download_job_file(follow *f, const char *what, const char *name, mrc_error *err)
{
    char path[256], dest[4096];
    snprintf(path, sizeof path, "/v1/jobs/%s/%s", f->id, what);
    int n = snprintf(dest, sizeof dest, "%s/%s", f->opts->out_dir, name);
    if (n < 0 || (size_t)n >= sizeof dest)
        return mrc_fail(err, MRC_EXIT_LOCAL, "%s: path too long", f->opts->out_dir);
    return mrc_http_download(f->http, path, dest, NULL, err);
}

/* stats.json, and with --png the contact sheet; once a frame is done. */
static int download_job_files(follow *f, mrc_error *err)
{
    int rc = download_job_file(f, "stats", "stats.json", err);
    if (rc == 0 && f->opts->png)
        rc = download_job_file(f, "contact-sheet.png", "contact-sheet.png", err);
    return rc;
}

/* ---- the view ------------------------------------------------------------- */

/* A frame changed state (from an event or a snapshot diff): report it and
 * download it if it just finished. */
static int frame_changed(follow *f, int index, int st, double seconds, const char *error,
                         mrc_error *err)
{
    int old = f->fstate[index];
    f->fstate[index] = (unsigned char)st;
    if (old == st)
        return 0;
    /* incremental (a snapshot recounts afterwards): recounting per frame
     * would be quadratic when many frames change at once */
    f->done += (st == FS_DONE) - (old == FS_DONE);
    f->failed += (st == FS_FAILED) - (old == FS_FAILED);
    if (st == FS_DONE) {
        if (!f->opts->tty) {
            char secs[32] = "";
            if (seconds >= 0.0)
                mrc_format_seconds(secs, sizeof secs, seconds);
            mrc_progress_message(&f->prog, "frame %d done%s%s (%d/%d)", index, secs[0] ? " in " : "",
                                 secs, f->done, f->total);
        }
        if (f->opts->out_dir && !f->fetched[index])
            return download_frame(f, index, err);
    } else if (st == FS_FAILED) {
        char msg[400];
        mrc_sanitize(msg, sizeof msg, error ? error : "no reason given");
        mrc_progress_message(&f->prog, "frame %d failed: %s", index, msg);
    }
    return 0;
}

/* Replaces the view by a GET /v1/jobs/{id} answer. Frames finished before
 * the first snapshot are not announced (they are old news) but are
 * downloaded like any other. */
static int apply_snapshot(follow *f, const cJSON *job, bool announce, mrc_error *err)
{
    int rc = 0;
    const cJSON *frames = cJSON_GetObjectItemCaseSensitive(job, "frames");
    const cJSON *states = cJSON_GetObjectItemCaseSensitive(job, "frame_states");
    int total = (int)mrc_json_int(frames, "total", f->total, 0, MAX_FRAMES);
    if (cJSON_IsArray(states) && total == 0)
        total = cJSON_GetArraySize(states) < MAX_FRAMES ? cJSON_GetArraySize(states) : MAX_FRAMES;
    rc = set_total(f, total, err);
    if (rc < 0)
        return rc;

    const char *error = mrc_json_str(job, "error");
    if (error)
        mrc_sanitize(f->job_error, sizeof f->job_error, error);
    /* before the frames, so a log reads "running" before "frame 0 done" */
    const char *state = mrc_json_str(job, "state");
    if (state)
        set_state(f, state);

    if (cJSON_IsArray(states)) {
        f->have_states = true;
        int pos = 0;
        const cJSON *fr;
        cJSON_ArrayForEach(fr, states) {
            int index = (int)mrc_json_int(fr, "index", pos, 0, MAX_FRAMES);
            pos++;
            if (index < 0 || index >= f->total)
                continue;
            int st = frame_state_parse(mrc_json_str(fr, "state"));
            if (st == FS_UNKNOWN)
                continue;
            if (!announce) {
                f->fstate[index] = (unsigned char)st;
                continue;
            }
            rc = frame_changed(f, index, st, frame_seconds(fr), mrc_json_str(fr, "error"), err);
            if (rc < 0)
                return rc;
        }
        recount(f);
    } else if (cJSON_IsObject(frames)) {
        f->done = (int)mrc_json_int(frames, "done", f->done, 0, MAX_FRAMES);
        f->failed = (int)mrc_json_int(frames, "failed", f->failed, 0, MAX_FRAMES);
        /* without per-frame states, a finished job's frames are all there */
        if (state && strcmp(state, "succeeded") == 0)
            for (int i = 0; i < f->total; i++)
                f->fstate[i] = FS_DONE;
    }
    return download_done_frames(f, err);
}

static int get_snapshot(follow *f, bool announce, mrc_error *err)
{
    char path[256];
    snprintf(path, sizeof path, "/v1/jobs/%s", f->id);
    cJSON *job = NULL;
    int rc = mrc_http_get_json(f->http, path, &job, err);
    if (rc == 0)
        rc = apply_snapshot(f, job, announce, err);
    cJSON_Delete(job);
    return rc;
}

/* ---- the event stream ----------------------------------------------------- */

static int on_event(const char *event, const char *data, size_t len, void *user)
{
    follow *f = user;
    f->events++;
    cJSON *doc = cJSON_ParseWithLength(data, len);
    int rc = 0;
    if (!cJSON_IsObject(doc)) {
        rc = 0; /* a keep-alive or something newer than us: not worth breaking over */
        goto cleanup;
    }
    if (strcmp(event, "state") == 0) {
        const char *error = mrc_json_str(doc, "error");
        if (error)
            mrc_sanitize(f->job_error, sizeof f->job_error, error);
        const cJSON *frames = cJSON_GetObjectItemCaseSensitive(doc, "frames");
        if (cJSON_IsObject(frames) && f->total == 0) {
            int total = (int)mrc_json_int(frames, "total", 0, 0, MAX_FRAMES);
            if (set_total(f, total, &f->fatal) < 0) {
                rc = STOP_FATAL;
                goto cleanup;
            }
        }
        const char *state = mrc_json_str(doc, "state");
        if (state)
            set_state(f, state);
        if (!f->synced) {
            /* frames that finished between the first snapshot and the
             * subscription are in no event: read the job again now */
            f->synced = true;
            mrc_error serr = {0};
            if (get_snapshot(f, true, &serr) < 0 && serr.code != MRC_EXIT_SERVER) {
                f->fatal = serr; /* a download could not be written, or was refused */
                rc = STOP_FATAL;
                goto cleanup;
            }
        }
        if (is_terminal(f->state))
            rc = STOP_TERMINAL;
    } else if (strcmp(event, "frame") == 0 || strcmp(event, "frame_failed") == 0) {
        /* "index", or "frame" when the event carries the frame's stats.json entry */
        int index = (int)mrc_json_int(doc, "index", -1, 0, MAX_FRAMES);
        if (index < 0)
            index = (int)mrc_json_int(doc, "frame", -1, 0, MAX_FRAMES);
        if (index < 0 || index >= f->total)
            goto cleanup;
        const char *error = mrc_json_str(doc, "error");
        int st = frame_state_parse(mrc_json_str(doc, "state"));
        if (st == FS_UNKNOWN)
            st = (strcmp(event, "frame_failed") == 0 || error) ? FS_FAILED : FS_DONE;
        if (st == FS_FAILED && cJSON_IsFalse(cJSON_GetObjectItemCaseSensitive(doc, "gave_up"))) {
            /* the server tries the frame again: a note, not a failure */
            char msg[400];
            mrc_sanitize(msg, sizeof msg, error ? error : "no reason given");
            mrc_progress_message(&f->prog, "frame %d failed, retrying: %s", index, msg);
            st = FS_PENDING;
        }
        if (frame_changed(f, index, st, frame_seconds(doc), error, &f->fatal) < 0) {
            rc = STOP_FATAL;
            goto cleanup;
        }
    }
    mrc_progress_update(&f->prog, f->done, f->failed, f->total, f->state, false);
cleanup:
    cJSON_Delete(doc);
    return rc;
}

static int on_stream_data(const char *data, size_t len, void *user)
{
    follow *f = user;
    int rc = mrc_sse_feed(&f->sse, data, len);
    if (rc < 0)
        return STOP_BROKEN;
    return rc;
}

static int on_stream_tick(void *user)
{
    follow *f = user;
    mrc_progress_update(&f->prog, f->done, f->failed, f->total, f->state, false);
    return 0;
}

static void sleep_seconds(double s)
{
    struct timespec ts = {(time_t)s, (long)((s - (double)(time_t)s) * 1e9)};
    while (nanosleep(&ts, &ts) != 0 && errno == EINTR) {
    }
}

/* One stream: 0 terminal state, 1 poll instead, 2 resume (it dropped or
 * ended early after an event with an id), negative fatal (err filled). */
static int follow_stream_once(follow *f, mrc_error *err)
{
    char path[256];
    snprintf(path, sizeof path, "/v1/jobs/%s/events", f->id);
    mrc_error serr = {0};
    mrc_sse_init(&f->sse, on_event, f);
    f->events = 0;
    int rc = mrc_http_stream(f->http, path, f->last_event_id, on_stream_data, on_stream_tick, f,
                             &serr);
    if (f->sse.last_id[0])
        snprintf(f->last_event_id, sizeof f->last_event_id, "%s", f->sse.last_id);
    mrc_sse_free(&f->sse);
    if (f->fatal.code == MRC_EXIT_SERVER) {
        /* a frame download failed because the server is unavailable: like a
         * broken stream, poll (which tolerates an outage) instead of giving up */
        mrc_progress_message(&f->prog, "microray: download failed (%s); polling instead", f->fatal.msg);
        f->fatal = (mrc_error){0};
        return 1;
    }
    if (f->fatal.code) { /* a local failure inside an event handler (e.g. disk full) */
        *err = f->fatal;
        return -err->code;
    }
    if (is_terminal(f->state))
        return 0;
    /* dropped (the connection broke, or the server ended the stream before
     * a final state): resume after the last event; refused (an HTTP error)
     * or malformed: poll */
    bool dropped = rc == 0 || (rc < 0 && serr.code == MRC_EXIT_SERVER && f->events > 0);
    if (dropped && f->last_event_id[0])
        return 2;
    /* rc == 1 without a terminal state or a fatal error: the parser gave up */
    const char *why = rc < 0 ? serr.msg : rc == 1 ? "malformed event stream"
                                                  : "the server ended it early";
    mrc_progress_message(&f->prog, "microray: event stream unavailable (%s); polling instead", why);
    return 1;
}

/* Consecutive resumptions of a dropped stream that brought no event
 * before the client polls instead. */
#define STREAM_RESUMES 3

/* 0: the job reached a terminal state; 1: the stream is of no further use
 * (poll instead); negative: a fatal error (err filled). A stream that
 * drops or ends early is resumed after its last event (Last-Event-ID: the
 * daemon sends the frame events missed meanwhile). */
static int follow_stream(follow *f, mrc_error *err)
{
    for (int fruitless = 0;;) {
        int rc = follow_stream_once(f, err);
        if (rc != 2)
            return rc;
        fruitless = f->events > 0 ? 0 : fruitless + 1;
        if (fruitless >= STREAM_RESUMES)
            break;
        sleep_seconds(POLL_INTERVAL_S);
    }
    mrc_progress_message(&f->prog, "microray: event stream keeps dropping; polling instead");
    return 1;
}

static int follow_poll(follow *f, mrc_error *err)
{
    double failing_since = 0.0;
    while (!is_terminal(f->state)) {
        sleep_seconds(POLL_INTERVAL_S);
        mrc_error perr = {0};
        int rc = get_snapshot(f, true, &perr);
        if (rc < 0 && perr.code == MRC_EXIT_SERVER) {
            /* a restarting daemon is normal (crash recovery): keep trying a while */
            double now = mrc_now();
            if (failing_since == 0.0) {
                failing_since = now;
                mrc_progress_message(&f->prog, "microray: %s; retrying", perr.msg);
            } else if (now - failing_since > POLL_GIVE_UP_S) {
                *err = perr;
                return rc;
            }
        } else if (rc < 0) {
            *err = perr;
            return rc;
        } else {
            failing_since = 0.0;
        }
        mrc_progress_update(&f->prog, f->done, f->failed, f->total, f->state, true);
    }
    return 0;
}

static void follow_free(follow *f)
{
    free(f->fstate);
    free(f->fetched);
}

static int prepare_out_dir(const mrc_follow_opts *opts, mrc_error *err)
{
    return opts->out_dir ? mrc_mkdirs(opts->out_dir, err) : 0;
}

int mrc_job_wait(mrc_http *h, const char *id, const mrc_follow_opts *opts, mrc_error *err)
{
    int rc = 0;
    follow f = {.http = h, .id = id, .opts = opts};
    mrc_progress_init(&f.prog, stderr, opts->tty, opts->quiet);

    rc = prepare_out_dir(opts, err);
    if (rc < 0)
        goto cleanup;
    rc = get_snapshot(&f, false, err);
    if (rc < 0)
        goto cleanup;
    mrc_progress_update(&f.prog, f.done, f.failed, f.total, f.state, true);
    if (!is_terminal(f.state)) {
        rc = follow_stream(&f, err);
        if (rc < 0)
            goto cleanup;
        if (rc == 1) {
            rc = follow_poll(&f, err);
            if (rc < 0)
                goto cleanup;
        }
        /* the final word on every frame (and on the job's error), and
         * frames the stream may not have mentioned */
        rc = get_snapshot(&f, true, err);
        if (rc < 0)
            goto cleanup;
    }
    mrc_progress_update(&f.prog, f.done, f.failed, f.total, f.state, true);
    if (opts->out_dir && f.done > 0) {
        rc = download_job_files(&f, err);
        if (rc < 0)
            goto cleanup;
    }
    mrc_progress_finish(&f.prog);

    char took[32];
    mrc_format_seconds(took, sizeof took, mrc_progress_elapsed(&f.prog));
    if (strcmp(f.state, "succeeded") == 0) {
        if (!opts->quiet) {
            if (opts->out_dir)
                fprintf(stderr, "job %s succeeded: %d/%d frames in %s, written to %s\n", id, f.done,
                        f.total, took, opts->out_dir);
            else
                fprintf(stderr, "job %s succeeded: %d/%d frames in %s\n", id, f.done, f.total, took);
        }
        rc = 0;
    } else if (strcmp(f.state, "canceled") == 0) {
        rc = mrc_fail(err, MRC_EXIT_JOB_FAILED, "job %s was canceled (%d/%d frames done)", id,
                      f.done, f.total);
    } else {
        rc = mrc_fail(err, MRC_EXIT_JOB_FAILED, "job %s failed: %s (%d/%d frames done, %d failed)",
                      id, f.job_error[0] ? f.job_error : "no reason given", f.done, f.total,
                      f.failed);
    }
cleanup:
    mrc_progress_finish(&f.prog);
    follow_free(&f);
    return rc;
}

int mrc_job_fetch(mrc_http *h, const char *id, const mrc_follow_opts *opts, mrc_fetch_result *out,
                  mrc_error *err)
{
    int rc = 0;
    follow f = {.http = h, .id = id, .opts = opts};
    /* the fetch reports only its summary; progress lines would be noise */
    mrc_follow_opts quiet = *opts;
    quiet.quiet = true;
    f.opts = &quiet;
    mrc_progress_init(&f.prog, stderr, opts->tty, true);

    rc = prepare_out_dir(opts, err);
    if (rc < 0)
        goto cleanup;
    rc = get_snapshot(&f, false, err);
    if (rc < 0)
        goto cleanup;
    if (f.done > 0) {
        rc = download_job_files(&f, err);
        if (rc < 0)
            goto cleanup;
    }
    if (!opts->quiet) {
        char size[32];
        mrc_format_bytes(size, sizeof size, (double)f.downloaded_bytes);
        if (f.done > 0)
            fprintf(stderr, "fetched %d frame%s%s (%s) and stats.json%s into %s; job %s: %d/%d frames done\n",
                    f.downloaded, f.downloaded == 1 ? "" : "s", opts->png ? " as PNG previews" : "",
                    size, opts->png ? ", contact-sheet.png" : "", opts->out_dir,
                    f.state[0] ? f.state : "?", f.done, f.total);
        else
            fprintf(stderr, "nothing to fetch yet: job %s is %s, 0/%d frames done\n", id,
                    f.state[0] ? f.state : "?", f.total);
    }
cleanup:
    if (out) {
        snprintf(out->state, sizeof out->state, "%s", f.state);
        out->fetched = f.downloaded;
        out->bytes = f.downloaded_bytes;
        out->done = f.done;
        out->total = f.total;
    }
    follow_free(&f);
    return rc;
}
