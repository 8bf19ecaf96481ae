/*
 * daemon_fixture.h - runs the real microrayd on an ephemeral loopback port
 * with a temporary data directory, and a tiny libcurl client for tests.
 * Header-only: each test program includes it once.
 */
#ifndef MR_TEST_DAEMON_FIXTURE_H
#define MR_TEST_DAEMON_FIXTURE_H

#include <cJSON.h>
#include <curl/curl.h>
#include <dirent.h>
#include <sqlite3.h>
#include <signal.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/types.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "microray.h"

typedef struct daemon_proc {
    pid_t pid;
    unsigned port;
    char data[512];
    char log[600];
    char base[64];
} daemon_proc;

/* fx_root: a second, writable asset root of every daemon (fx_tmp/root),
 * for tests that plant files where jobs may name them. fx_daemon_exe: the
 * binary daemon_start runs as `serve` (empty: the build's microrayd). */
static char fx_src_dir[2048], fx_build_dir[2048], fx_tmp[256], fx_root[300], fx_daemon_exe[2100];

static inline void fx_init_dirs(void)
{
    const char *s = getenv("MR_SOURCE_DIR"), *b = getenv("MR_BUILD_DIR");
    snprintf(fx_src_dir, sizeof fx_src_dir, "%s", s ? s : ".");
    snprintf(fx_build_dir, sizeof fx_build_dir, "%s", b ? b : "build");
    snprintf(fx_tmp, sizeof fx_tmp, "/tmp/microray-daemon-XXXXXX");
    if (!mkdtemp(fx_tmp))
        fail_msg("mkdtemp failed");
    snprintf(fx_root, sizeof fx_root, "%s/root", fx_tmp);
    if (mkdir(fx_root, 0755) != 0)
        fail_msg("cannot create %s", fx_root);
}

/* Teardown's end: removes fx_tmp (a message if it cannot) and releases
 * libcurl; whether the directory is gone. */
static inline bool fx_cleanup_dirs(void)
{
    char cmd[400];
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", fx_tmp);
    bool removed = system(cmd) == 0;
    if (!removed)
        print_message("could not remove %s\n", fx_tmp);
    curl_global_cleanup();
    return removed;
}

/* cmocka group set-up and teardown of a test that runs no daemon of its
 * own: the directories alone (fx_init_dirs, fx_cleanup_dirs). */
static inline int fx_dirs_setup(void **state)
{
    (void)state;
    fx_init_dirs();
    return 0;
}

static inline int fx_dirs_teardown(void **state)
{
    (void)state;
    return fx_cleanup_dirs() ? 0 : -1;
}

/* The daemon's database in data_dir passes sqlite's integrity check (read
 * with a connection of its own, the daemon stopped or not). */
static inline void fx_assert_store_intact(const char *data_dir)
{
    char db_path[700];
    snprintf(db_path, sizeof db_path, "%s/microray.sqlite", data_dir);
    sqlite3 *db = NULL;
    assert_int_equal(sqlite3_open_v2(db_path, &db, SQLITE_OPEN_READONLY, NULL), SQLITE_OK);
    sqlite3_stmt *s = NULL;
    assert_int_equal(sqlite3_prepare_v2(db, "PRAGMA integrity_check", -1, &s, NULL), SQLITE_OK);
    assert_int_equal(sqlite3_step(s), SQLITE_ROW);
    assert_string_equal((const char *)sqlite3_column_text(s, 0), "ok");
    sqlite3_finalize(s);
    sqlite3_close(db);
}

static inline void fx_sleep_ms(int ms)
{
    struct timespec ts = {ms / 1000, (long)(ms % 1000) * 1000000L};
    nanosleep(&ts, NULL);
}

/* Starts microrayd serve with data directory data_name (inside fx_tmp) and
 * the extra arguments of the NULL-terminated list extra (may be NULL). */
static inline void daemon_start_args(daemon_proc *d, const char *data_name, const char *const *extra)
{
    memset(d, 0, sizeof *d);
    snprintf(d->data, sizeof d->data, "%s/%s", fx_tmp, data_name);
    snprintf(d->log, sizeof d->log, "%s/%s.log", fx_tmp, data_name);
    char port_file[600], bin[2100];
    snprintf(port_file, sizeof port_file, "%s/%s.port", fx_tmp, data_name);
    unlink(port_file);
    if (fx_daemon_exe[0])
        snprintf(bin, sizeof bin, "%s", fx_daemon_exe);
    else
        snprintf(bin, sizeof bin, "%s/microrayd", fx_build_dir);
    d->pid = fork();
    if (d->pid == 0) {
        /* both to the log: a daemon left running by a failed test must
         * not hold the test's output open */
        FILE *log = freopen(d->log, "a", stderr);
        FILE *out = freopen(d->log, "a", stdout);
        (void)log, (void)out;
        const char *argv[64] = {"microrayd", "serve", "--listen", "127.0.0.1:0", "--data", d->data,
                                "--asset-root", "/usr/share/assimp/models", "--asset-root", fx_root,
                                "--threads", "2", "--port-file", port_file};
        size_t n = 14;
        for (size_t i = 0; extra && extra[i] && n + 1 < sizeof argv / sizeof *argv; i++)
            argv[n++] = extra[i];
        argv[n] = NULL;
        execv(bin, (char *const *)argv);
        _exit(127);
    }
    for (int i = 0; i < 300; i++) { /* up to 30 s: ASan builds start slowly */
        FILE *f = fopen(port_file, "r");
        if (f) {
            int ok = fscanf(f, "%u", &d->port);
            fclose(f);
            if (ok == 1 && d->port) {
                snprintf(d->base, sizeof d->base, "http://127.0.0.1:%u", d->port);
                return;
            }
        }
        int st;
        if (waitpid(d->pid, &st, WNOHANG) == d->pid)
            fail_msg("microrayd exited during start (see %s)", d->log);
        fx_sleep_ms(100);
    }
    fail_msg("microrayd did not start within 30 s (see %s)", d->log);
}

/* The pid of the daemon's render worker process (a child running
 * `render-worker`), waiting up to 30 s for one; fails the test if none. */
static inline pid_t fx_render_worker_pid(const daemon_proc *d)
{
    for (int i = 0; i < 600; i++) {
        /* the worker is a child of a worker thread, not of the main one:
         * look at every task's children */
        char path[400], dir[64];
        snprintf(dir, sizeof dir, "/proc/%d/task", (int)d->pid);
        DIR *td = opendir(dir);
        struct dirent *e;
        while (td && (e = readdir(td))) {
            if (e->d_name[0] == '.')
                continue;
            snprintf(path, sizeof path, "/proc/%d/task/%s/children", (int)d->pid, e->d_name);
            FILE *f = fopen(path, "r");
            int child;
            while (f && fscanf(f, "%d", &child) == 1) {
                char cmd[64], line[256] = "";
                snprintf(cmd, sizeof cmd, "/proc/%d/cmdline", child);
                FILE *c = fopen(cmd, "r");
                size_t n = c ? fread(line, 1, sizeof line - 1, c) : 0;
                if (c)
                    fclose(c);
                /* argv is NUL-separated: "microrayd\0render-worker\0..." */
                size_t first = strnlen(line, n);
                if (first + 1 < n && !strcmp(line + first + 1, "render-worker")) {
                    fclose(f);
                    closedir(td);
                    return child;
                }
            }
            if (f)
                fclose(f);
        }
        if (td)
            closedir(td);
        fx_sleep_ms(50);
    }
    fail_msg("the daemon (pid %d) has no render worker", (int)d->pid);
    return -1;
}

static inline void daemon_start(daemon_proc *d, const char *data_name) { daemon_start_args(d, data_name, NULL); }

/* SIGTERM (graceful) or SIGKILL; returns the exit status or -signal. */
static inline int daemon_stop(daemon_proc *d, int sig)
{
    kill(d->pid, sig);
    int st = 0;
    waitpid(d->pid, &st, 0);
    d->pid = 0;
    return WIFEXITED(st) ? WEXITSTATUS(st) : -WTERMSIG(st);
}

typedef struct http_result {
    long status;
    char *body;
    size_t len;
    char content_type[128];
    char location[256];
    char etag[128], vary[128], disposition[256]; /* those headers, "" when absent */
    char head[8192]; /* every header line of the (last) response, as received */
    size_t head_len;
} http_result;

static inline size_t fx_collect(char *p, size_t size, size_t n, void *user)
{
    http_result *r = user;
    size_t add = size * n;
    char *nb = realloc(r->body, r->len + add + 1);
    if (!nb)
        return 0;
    memcpy(nb + r->len, p, add);
    r->body = nb;
    r->len += add;
    r->body[r->len] = '\0';
    return add;
}

/* Copies the value of header line p (of len bytes) into out when its name is `name`. */
static inline void fx_header_value(const char *p, size_t len, const char *name, char *out, size_t size)
{
    size_t nl = strlen(name);
    if (len > nl + 2 && strncasecmp(p, name, nl) == 0 && p[nl] == ':') {
        const char *v = p + nl + 1, *e = p + len;
        while (v < e && *v == ' ')
            v++;
        while (e > v && (e[-1] == '\r' || e[-1] == '\n'))
            e--;
        snprintf(out, size, "%.*s", (int)(e - v), v);
    }
}

static inline size_t fx_header(char *p, size_t size, size_t n, void *user)
{
    http_result *r = user;
    size_t len = size * n;
    if (len >= 5 && !strncmp(p, "HTTP/", 5))
        r->head_len = 0; /* a new response (after a 100 Continue, say) */
    if (r->head_len + len < sizeof r->head) {
        memcpy(r->head + r->head_len, p, len);
        r->head_len += len;
        r->head[r->head_len] = '\0';
    }
    fx_header_value(p, len, "Location", r->location, sizeof r->location);
    fx_header_value(p, len, "ETag", r->etag, sizeof r->etag);
    fx_header_value(p, len, "Vary", r->vary, sizeof r->vary);
    fx_header_value(p, len, "Content-Disposition", r->disposition, sizeof r->disposition);
    return len;
}

/* One request with the NULL-terminated request headers ("Name: value";
 * headers may be NULL). */
static inline http_result http_headers(const daemon_proc *d, const char *method, const char *path,
                                const void *body, size_t body_len, const char *const *headers)
{
    http_result r = {0};
    r.body = calloc(1, 1);
    char url[512];
    assert_true((size_t)snprintf(url, sizeof url, "%s%s", d->base, path) < sizeof url);
    CURL *c = curl_easy_init();
    struct curl_slist *h = NULL;
    for (size_t i = 0; headers && headers[i]; i++)
        h = curl_slist_append(h, headers[i]);
    h = curl_slist_append(h, "Expect:");
    curl_easy_setopt(c, CURLOPT_URL, url);
    curl_easy_setopt(c, CURLOPT_CUSTOMREQUEST, method);
    if (!strcmp(method, "HEAD")) /* headers only: no body will come */
        curl_easy_setopt(c, CURLOPT_NOBODY, 1L);
    curl_easy_setopt(c, CURLOPT_HTTPHEADER, h);
    curl_easy_setopt(c, CURLOPT_WRITEFUNCTION, fx_collect);
    curl_easy_setopt(c, CURLOPT_WRITEDATA, &r);
    curl_easy_setopt(c, CURLOPT_HEADERFUNCTION, fx_header);
    curl_easy_setopt(c, CURLOPT_HEADERDATA, &r);
    curl_easy_setopt(c, CURLOPT_TIMEOUT, 60L);
    if (body) {
        curl_easy_setopt(c, CURLOPT_POSTFIELDS, body);
        curl_easy_setopt(c, CURLOPT_POSTFIELDSIZE_LARGE, (curl_off_t)body_len);
    }
    CURLcode rc = curl_easy_perform(c);
    if (rc != CURLE_OK)
        fail_msg("%s %s: %s", method, path, curl_easy_strerror(rc));
    curl_easy_getinfo(c, CURLINFO_RESPONSE_CODE, &r.status);
    char *ct = NULL;
    curl_easy_getinfo(c, CURLINFO_CONTENT_TYPE, &ct);
    snprintf(r.content_type, sizeof r.content_type, "%s", ct ? ct : "");
    curl_slist_free_all(h);
    curl_easy_cleanup(c);
    return r;
}

/* One request; header may be NULL ("Name: value"). */
static inline http_result http(const daemon_proc *d, const char *method, const char *path, const void *body,
                        size_t body_len, const char *header)
{
    const char *headers[] = {header, NULL};
    return http_headers(d, method, path, body, body_len, headers);
}

static inline void http_free(http_result *r) { free(r->body); }

/* The value of response header name (case-insensitive; the first of
 * several) into out; false ("" in out) when absent. */
static inline bool fx_header_get(const http_result *r, const char *name, char *out, size_t size)
{
    out[0] = '\0';
    for (const char *p = r->head; *p;) {
        const char *e = strchr(p, '\n');
        size_t len = e ? (size_t)(e - p + 1) : strlen(p);
        fx_header_value(p, len, name, out, size);
        if (out[0])
            return true;
        p += len;
    }
    return false;
}

static inline char *fx_slurp(const char *path, size_t *len)
{
    FILE *f = fopen(path, "rb");
    if (!f)
        return NULL;
    fseek(f, 0, SEEK_END);
    long n = ftell(f);
    fseek(f, 0, SEEK_SET);
    char *s = malloc((size_t)n + 1);
    size_t got = fread(s, 1, (size_t)n, f);
    s[got] = '\0';
    fclose(f);
    if (len)
        *len = got;
    return s;
}

/* Runs cmd through sh; its standard output in *out (malloc'ed; out may be
 * NULL), the exit status (128 + signal when killed). */
static inline int fx_run(const char *cmd, char **out)
{
    char file[600], full[16384];
    snprintf(file, sizeof file, "%s/run.out", fx_tmp);
    if (snprintf(full, sizeof full, "%s > '%s'", cmd, file) >= (int)sizeof full)
        fail_msg("command too long: %.200s...", cmd);
    int st = system(full);
    if (out)
        *out = fx_slurp(file, NULL);
    return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
}

/* The small skinned job with a different output size per test, so jobs never
 * share an idempotency or cache story by accident. */
static inline char *fx_small_job(int frames_end_q, int width, const char *extra)
{
    char *s = malloc(4096);
    snprintf(s, 4096,
             "{\"name\":\"t\",%s\"assets\":{\"d\":{\"path\":\"/usr/share/assimp/models/X/BCN_Epileptic.X\"}},"
             "\"objects\":[{\"asset\":\"d\",\"pose\":{\"clip\":0}}],"
             "\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0.2,4.3],\"target\":[0,0,-0.1]}]},"
             "\"frames\":{\"fps\":4,\"start\":0,\"end\":%g},"
             "\"output\":{\"width\":%d,\"height\":%d,\"samples\":1}}",
             extra ? extra : "", frames_end_q / 4.0, width, width * 9 / 16);
    return s;
}

static inline void fx_submit(const daemon_proc *d, const char *job, char id[64])
{
    http_result r = http(d, "POST", "/v1/jobs", job, strlen(job), NULL);
    if (r.status != 202)
        fail_msg("submit: %ld %s", r.status, r.body);
    cJSON *j = cJSON_Parse(r.body);
    assert_non_null(j);
    snprintf(id, 64, "%s", cJSON_GetObjectItem(j, "id")->valuestring);
    char want[256];
    snprintf(want, sizeof want, "/v1/jobs/%s", id);
    assert_string_equal(r.location, want);
    cJSON_Delete(j);
    http_free(&r);
}

/* Polls GET /v1/jobs/{id} until the job reaches a terminal state. */
static inline cJSON *fx_wait_job(const daemon_proc *d, const char *id, int timeout_s)
{
    char path[128];
    snprintf(path, sizeof path, "/v1/jobs/%s", id);
    char last[4096] = "";
    for (int i = 0; i < timeout_s * 10; i++) {
        http_result r = http(d, "GET", path, NULL, 0, NULL);
        assert_int_equal(r.status, 200);
        cJSON *j = cJSON_Parse(r.body);
        snprintf(last, sizeof last, "%s", r.body);
        http_free(&r);
        assert_non_null(j);
        const char *st = cJSON_GetObjectItem(j, "state")->valuestring;
        if (!strcmp(st, "succeeded") || !strcmp(st, "failed") || !strcmp(st, "canceled"))
            return j;
        cJSON_Delete(j);
        fx_sleep_ms(100);
    }
    fail_msg("job %s did not finish in %d s; last seen: %s (daemon log %s)", id, timeout_s, last,
             d->log);
    return NULL;
}

/* Polls until at least n frames of the job are done (at most 30 s). */
static inline void fx_wait_frames_done(const daemon_proc *d, const char *id, int n)
{
    char path[128];
    snprintf(path, sizeof path, "/v1/jobs/%s", id);
    int done = 0;
    for (int i = 0; i < 1500 && done < n; i++) {
        http_result r = http(d, "GET", path, NULL, 0, NULL);
        cJSON *j = cJSON_Parse(r.body);
        assert_non_null(j);
        done = cJSON_GetObjectItem(cJSON_GetObjectItem(j, "frames"), "done")->valueint;
        cJSON_Delete(j);
        http_free(&r);
        if (done < n)
            fx_sleep_ms(20);
    }
    if (done < n)
        fail_msg("job %s: %d frames done after 30 s, waited for %d", id, done, n);
}

/* How many of the job's frames the daemon says are running. */
static inline int fx_running_frames(const daemon_proc *d, const char *id)
{
    char path[128];
    snprintf(path, sizeof path, "/v1/jobs/%s", id);
    http_result r = http(d, "GET", path, NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    cJSON *j = cJSON_Parse(r.body);
    assert_non_null(j);
    int running = 0;
    const cJSON *f;
    cJSON_ArrayForEach(f, cJSON_GetObjectItem(j, "frame_states"))
        running += !strcmp(cJSON_GetObjectItem(f, "state")->valuestring, "running");
    cJSON_Delete(j);
    http_free(&r);
    return running;
}

/* Stops (SIGSTOP) the daemon's render worker while it is inside a frame of
 * job id (the store says a frame is running), trying again until it is:
 * the worker then stays in that frame until SIGCONT, so what happens to a
 * frame in progress can be tested without racing it. The job must have
 * frames left to render. Returns the worker's pid. */
static inline pid_t fx_freeze_worker_in_frame(const daemon_proc *d, const char *id)
{
    for (int i = 0; i < 1000; i++) {
        pid_t pid = fx_render_worker_pid(d);
        kill(pid, SIGSTOP);
        /* a frame result the worker sent just before it stopped is stored
         * by then (the store's word is then final until SIGCONT) */
        fx_sleep_ms(100);
        if (fx_running_frames(d, id) > 0)
            return pid;
        kill(pid, SIGCONT);
        fx_sleep_ms(10);
    }
    fail_msg("the render worker of job %s was never caught inside a frame", id);
    return -1;
}

/* Frame k of job id as the daemon d stored it, read back by OpenEXR. */
static inline mr_film *fx_read_frame(const daemon_proc *d, const char *id, int k)
{
    char path[800];
    snprintf(path, sizeof path, "%s/frames/%s/%04d.exr", d->data, id, k);
    mr_film *f = NULL;
    mr_error err;
    if (mr_exr_read_file(path, &f, NULL, &err) < 0)
        fail_msg("%s: %s", path, err.msg);
    return f;
}

/* Polls the job until a frame with index >= min is running (60 s at most). */
static inline void fx_wait_frame_running_from(const daemon_proc *d, const char *id, int min)
{
    char path[128];
    snprintf(path, sizeof path, "/v1/jobs/%s", id);
    for (int i = 0; i < 6000; i++) {
        http_result r = http(d, "GET", path, NULL, 0, NULL);
        cJSON *j = cJSON_Parse(r.body);
        http_free(&r);
        assert_non_null(j);
        cJSON *f;
        bool found = false;
        cJSON_ArrayForEach(f, cJSON_GetObjectItem(j, "frame_states"))
            found |= cJSON_GetObjectItem(f, "index")->valueint >= min &&
                     !strcmp(cJSON_GetObjectItem(f, "state")->valuestring, "running");
        cJSON_Delete(j);
        if (found)
            return;
        fx_sleep_ms(10);
    }
    fail_msg("job %s: no frame from %d on started within 60 s", id, min);
}

#endif
