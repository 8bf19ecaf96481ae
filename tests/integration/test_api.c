/*
 * test_api.c - the service as render-farm users expect it (issue 19), on
 * the real microrayd on an ephemeral loopback port: frame states after a
 * cancel, the job list's pagination, the drain of a stopping daemon
 * (/readyz 503 while the frame in progress finishes), and the API's
 * further routes and headers.
 */
#define _GNU_SOURCE /* strcasestr */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <arpa/inet.h>
#include <cJSON.h>
#include <netinet/in.h>
#include <poll.h>
#include <pthread.h>
#include <pty.h>
#include <sys/socket.h>

#include "../support/bad_jobs.h"
#include "daemon_fixture.h"

static daemon_proc D;

static const char *state_of(cJSON *j) { return cJSON_GetObjectItem(j, "state")->valuestring; }

static void post_ok(const daemon_proc *d, const char *path, long want)
{
    http_result r = http(d, "POST", path, "", 0, NULL);
    if (r.status != want)
        fail_msg("POST %s: %ld, want %ld: %s", path, r.status, want, r.body);
    http_free(&r);
}

/* Waits (at most 30 s) until no frame of the job is running. */
static int wait_no_running_frame(const daemon_proc *d, const char *id)
{
    int running = 0;
    for (int i = 0; i < 300 && (running = fx_running_frames(d, id)) > 0; i++)
        fx_sleep_ms(100);
    return running;
}

/* A canceled job keeps no frame "running": the frame the cancel cut off
 * goes back to pending (without counting a failed attempt). Before the
 * fix it stayed running forever. The worker is held inside a frame
 * (SIGSTOP) when the cancel comes, so the cancel always cuts one off. */
static void test_cancel_releases_running_frame(void **state)
{
    (void)state;
    char *job = fx_small_job(400, 240, NULL), id[64], path[128];
    fx_submit(&D, job, id);
    free(job);
    fx_wait_frames_done(&D, id, 1);
    pid_t worker = fx_freeze_worker_in_frame(&D, id);
    snprintf(path, sizeof path, "/v1/jobs/%s/cancel", id);
    post_ok(&D, path, 202);
    kill(worker, SIGCONT); /* killed by the cancel already, or now */
    cJSON *j = fx_wait_job(&D, id, 30);
    assert_string_equal(state_of(j), "canceled");
    cJSON_Delete(j);
    assert_int_equal(wait_no_running_frame(&D, id), 0);
    /* and the cut-off frame counted no failed attempt */
    snprintf(path, sizeof path, "/v1/jobs/%s", id);
    http_result r = http(&D, "GET", path, NULL, 0, NULL);
    j = cJSON_Parse(r.body);
    const cJSON *f;
    cJSON_ArrayForEach(f, cJSON_GetObjectItem(j, "frame_states"))
        assert_int_equal(cJSON_GetObjectItem(f, "retries")->valueint, 0);
    cJSON_Delete(j);
    http_free(&r);
}

/* SIGTERM drains: while the frame in progress finishes, /readyz answers
 * 503 with Retry-After, reads are served and new work is refused with 503;
 * then the daemon exits 0 and the job resumes at the next start. The
 * worker is held in its frame (SIGSTOP) so the drain lasts until the test
 * lets it go. */
static void test_readyz_503_while_stopping(void **state)
{
    (void)state;
    daemon_proc saved = D;
    daemon_start(&D, "drain");
    char *job = fx_small_job(200, 160, NULL), id[64], path[128], value[64];
    fx_submit(&D, job, id);
    fx_wait_frames_done(&D, id, 1);
    pid_t worker = fx_freeze_worker_in_frame(&D, id);
    kill(D.pid, SIGTERM);
    /* the daemon takes the signal asynchronously: wait for the drain */
    http_result r = {0};
    for (int i = 0; i < 300; i++) {
        r = http(&D, "GET", "/readyz", NULL, 0, NULL);
        if (r.status == 503)
            break;
        http_free(&r);
        fx_sleep_ms(20);
    }
    assert_int_equal(r.status, 503);
    assert_true(fx_header_get(&r, "Retry-After", value, sizeof value));
    assert_true(atoi(value) >= 1);
    assert_non_null(strstr(r.content_type, "application/problem+json"));
    http_free(&r);
    /* reads go on */
    snprintf(path, sizeof path, "/v1/jobs/%s", id);
    r = http(&D, "GET", path, NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    http_free(&r);
    r = http(&D, "GET", "/healthz", NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    http_free(&r);
    /* new work does not */
    r = http(&D, "POST", "/v1/jobs", job, strlen(job), NULL);
    assert_int_equal(r.status, 503);
    assert_true(fx_header_get(&r, "Retry-After", value, sizeof value));
    http_free(&r);
    free(job);
    /* the frame finishes, the daemon ends */
    kill(worker, SIGCONT);
    assert_int_equal(daemon_stop(&D, 0), 0);
    /* the job was left queued with its finished frames, and resumes */
    daemon_start(&D, "drain");
    cJSON *j = fx_wait_job(&D, id, 120);
    assert_string_equal(state_of(j), "succeeded");
    cJSON_Delete(j);
    assert_int_equal(daemon_stop(&D, SIGTERM), 0);
    D = saved;
}

/* GET /v1/jobs pages: limit (it was ignored: every job came back), the
 * cursor of the next page in "next" and in a Link header, state and name
 * filters; RFC 3339 times beside the numbers. */
static void test_job_list_pages(void **state)
{
    (void)state;
    char ids[3][64];
    for (int i = 0; i < 3; i++) {
        char extra[64];
        snprintf(extra, sizeof extra, "\"name\":\"page-%c\",", i == 1 ? 'b' : 'a');
        char *job = fx_small_job(0, 32 + 8 * i, NULL);
        /* fx_small_job names every job "t": give these their own */
        char *named = malloc(strlen(job) + 64);
        snprintf(named, strlen(job) + 64, "{%s%s", extra, job + strlen("{\"name\":\"t\","));
        fx_submit(&D, named, ids[i]);
        free(named);
        free(job);
    }
    http_result r = http(&D, "GET", "/v1/jobs?limit=2&name=page-a", NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    cJSON *doc = cJSON_Parse(r.body);
    cJSON *jobs = cJSON_GetObjectItem(doc, "jobs");
    assert_int_equal(cJSON_GetArraySize(jobs), 2);
    assert_string_equal(cJSON_GetObjectItem(cJSON_GetArrayItem(jobs, 0), "id")->valuestring, ids[2]);
    assert_string_equal(cJSON_GetObjectItem(cJSON_GetArrayItem(jobs, 1), "id")->valuestring, ids[0]);
    /* the filter leaves nothing more: no next page */
    assert_true(cJSON_IsNull(cJSON_GetObjectItem(doc, "next")));
    cJSON_Delete(doc);
    http_free(&r);

    r = http(&D, "GET", "/v1/jobs?limit=1", NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    doc = cJSON_Parse(r.body);
    jobs = cJSON_GetObjectItem(doc, "jobs");
    assert_int_equal(cJSON_GetArraySize(jobs), 1);
    cJSON *first = cJSON_GetArrayItem(jobs, 0);
    assert_string_equal(cJSON_GetObjectItem(first, "id")->valuestring, ids[2]);
    /* "2025-01-31T09:05:03.250Z" beside the number */
    const char *at = cJSON_GetObjectItem(first, "created_at")->valuestring;
    assert_int_equal(strlen(at), 24);
    assert_true(at[4] == '-' && at[10] == 'T' && at[19] == '.' && at[23] == 'Z');
    assert_true(cJSON_IsNull(cJSON_GetObjectItem(first, "finished_at")) ||
                cJSON_IsString(cJSON_GetObjectItem(first, "finished_at")));
    const char *next = cJSON_GetObjectItem(doc, "next")->valuestring;
    char link[512], want[512], path[256];
    assert_true(fx_header_get(&r, "Link", link, sizeof link));
    snprintf(want, sizeof want, "</v1/jobs?limit=1&cursor=%s>; rel=\"next\"", next);
    assert_string_equal(link, want);
    snprintf(path, sizeof path, "/v1/jobs?limit=1&cursor=%s", next);
    cJSON_Delete(doc);
    http_free(&r);
    r = http(&D, "GET", path, NULL, 0, NULL);
    doc = cJSON_Parse(r.body);
    assert_string_equal(cJSON_GetObjectItem(cJSON_GetArrayItem(cJSON_GetObjectItem(doc, "jobs"), 0), "id")->valuestring,
                        ids[1]);
    cJSON_Delete(doc);
    http_free(&r);

    /* the client follows the pages (a page of 1 here) or stops at --limit */
    char cmd[4096], log[600];
    snprintf(log, sizeof log, "%s/list.txt", fx_tmp);
    snprintf(cmd, sizeof cmd, "'%s/microray' --server %s list --limit 2 --json >'%s' 2>&1", fx_build_dir,
             D.base, log);
    assert_int_equal(system(cmd), 0);
    char *text = fx_slurp(log, NULL);
    doc = cJSON_Parse(text);
    assert_int_equal(cJSON_GetArraySize(cJSON_GetObjectItem(doc, "jobs")), 2);
    cJSON_Delete(doc);
    free(text);
    snprintf(cmd, sizeof cmd, "'%s/microray' --server %s list --name page-a >'%s' 2>&1", fx_build_dir,
             D.base, log);
    assert_int_equal(system(cmd), 0);
    text = fx_slurp(log, NULL);
    assert_non_null(strstr(text, ids[0]));
    assert_non_null(strstr(text, ids[2]));
    assert_null(strstr(text, ids[1]));
    free(text);

    /* each a 400 whose problem document is JSON, quoting the bytes sent
     * (not UTF-8 in the last ones) as \xHH */
    static const char *const bad[] = {"/v1/jobs?limit=0",    "/v1/jobs?limit=1001",  "/v1/jobs?limit=x",
                                      "/v1/jobs?cursor=abc", "/v1/jobs?state=done",  "/v1/jobs?name=",
                                      "/v1/jobs?cursor=%ff%fe", "/v1/jobs?limit=%ff", "/v1/jobs?state=%c3"};
    for (size_t i = 0; i < sizeof bad / sizeof *bad; i++) {
        r = http(&D, "GET", bad[i], NULL, 0, NULL);
        if (r.status != 400)
            fail_msg("GET %s: %ld, want 400", bad[i], r.status);
        cJSON *problem = cJSON_Parse(r.body);
        if (!problem || !cJSON_IsString(cJSON_GetObjectItem(problem, "detail")))
            fail_msg("GET %s: the problem is not JSON: %s", bad[i], r.body);
        for (const unsigned char *b = (const unsigned char *)r.body; *b; b++)
            if (*b >= 0x80) /* (cJSON takes any bytes in strings; these messages are ASCII) */
                fail_msg("GET %s: byte 0x%02X in the problem, not UTF-8 text", bad[i], *b);
        if (strstr(bad[i], "%ff") && !strstr(cJSON_GetObjectItem(problem, "detail")->valuestring, "\\xFF"))
            fail_msg("GET %s: the detail does not quote the byte: %s", bad[i], r.body);
        cJSON_Delete(problem);
        http_free(&r);
    }
}

/* The client's progress bar on a terminal of 40 columns: every redraw
 * fits in 39 (it had 50 and more: the terminal wrapped it and every redraw
 * left a line behind). The client runs on a real pseudo-terminal. */
static void test_progress_bar_fits_narrow_terminal(void **state)
{
    (void)state;
    char job_path[512];
    snprintf(job_path, sizeof job_path, "%s/narrow.json", fx_tmp);
    char *job = fx_small_job(23, 96, NULL); /* 24 frames: many redraws */
    FILE *f = fopen(job_path, "w");
    fputs(job, f);
    fclose(f);
    free(job);
    struct winsize ws = {.ws_row = 24, .ws_col = 40};
    int master = -1;
    pid_t pid = forkpty(&master, NULL, NULL, &ws);
    assert_true(pid >= 0);
    if (pid == 0) {
        setenv("TERM", "xterm", 1);
        unsetenv("COLUMNS");
        char bin[2200];
        snprintf(bin, sizeof bin, "%s/microray", fx_build_dir);
        execl(bin, "microray", "--server", D.base, "submit", job_path, "--wait", (char *)NULL);
        _exit(127);
    }
    size_t len = 0, cap = 1 << 16;
    char *out = malloc(cap);
    for (;;) {
        if (len + 4096 > cap)
            out = realloc(out, cap *= 2);
        ssize_t n = read(master, out + len, 4096);
        if (n <= 0) /* EIO once the client is gone */
            break;
        len += (size_t)n;
    }
    out[len] = '\0';
    close(master);
    int st = 0;
    waitpid(pid, &st, 0);
    if (!WIFEXITED(st) || WEXITSTATUS(st) != 0)
        fail_msg("microray exited %d: %s", WEXITSTATUS(st), out);
    /* every redraw of the bar, between carriage returns and newlines */
    int redraws = 0;
    for (char *seg = out; *seg;) {
        size_t n = strcspn(seg, "\r\n");
        bool bar = n > 0 && strstr(seg, " frames") && strstr(seg, " frames") < seg + n &&
                   strncmp(seg, "job ", 4) != 0;
        if (bar) {
            redraws++;
            if (n > 39)
                fail_msg("a redraw of %zu columns on a 40-column terminal: '%.*s'", n, (int)n, seg);
        }
        seg += n;
        seg += strspn(seg, "\r\n");
    }
    assert_true(redraws >= 2);
    free(out);
}

/* The line of README.md that starts with prefix (after a newline), up to
 * the first of stop_at (a comment, a '&') with trailing blanks cut; fails
 * the test when there is none. */
static void readme_line(const char *readme, const char *prefix, const char *stop_at, char *out,
                        size_t size)
{
    char needle[256];
    snprintf(needle, sizeof needle, "\n%s", prefix);
    const char *p = strstr(readme, needle);
    if (!p)
        fail_msg("README.md has no line starting with '%s'", prefix);
    p++;
    size_t n = strcspn(p, stop_at);
    while (n && p[n - 1] == ' ')
        n--;
    snprintf(out, size, "%.*s", (int)n, p);
}

/* The README's quick start, run as written against the daemon it says to
 * start: the curl submission answers 202 and the client's prints a job id.
 * (The examples name models by server-side path: a daemon without the
 * asset root refused them, and the README did not say so.) */
static void test_readme_quick_start(void **state)
{
    (void)state;
    char path[2200], serve[512], curl[512], client[512], cmd[8192];
    snprintf(path, sizeof path, "%s/README.md", fx_src_dir);
    char *readme = fx_slurp(path, NULL);
    assert_non_null(readme);
    readme_line(readme, "build/microrayd serve --asset-root", "&#\n", serve, sizeof serve);
    readme_line(readme, "curl -si -X POST --data-binary @examples/", "#\n", curl, sizeof curl);
    readme_line(readme, "build/microray submit examples/skinned-walk.json", "#\n", client,
                sizeof client);
    free(readme);
    /* the daemon as the quick start starts it, on a free port and a data
     * directory of the test's (later options win) */
    daemon_proc q = {0};
    snprintf(q.data, sizeof q.data, "%s/quick", fx_tmp);
    snprintf(q.log, sizeof q.log, "%s/quick.log", fx_tmp);
    char port_file[600];
    snprintf(port_file, sizeof port_file, "%s/quick.port", fx_tmp);
    q.pid = fork();
    if (q.pid == 0) {
        FILE *l = freopen(q.log, "a", stderr);
        (void)l;
        if (chdir(fx_src_dir) != 0)
            _exit(127);
        snprintf(cmd, sizeof cmd, "exec '%s/microrayd'%s --listen 127.0.0.1:0 --data '%s' --port-file '%s'",
                 fx_build_dir, serve + strlen("build/microrayd"), q.data, port_file);
        execl("/bin/sh", "sh", "-c", cmd, (char *)NULL);
        _exit(127);
    }
    for (int i = 0; i < 300 && !q.port; i++) {
        FILE *f = fopen(port_file, "r");
        if (f) {
            if (fscanf(f, "%u", &q.port) != 1)
                q.port = 0;
            fclose(f);
        }
        if (!q.port)
            fx_sleep_ms(100);
    }
    assert_true(q.port > 0);
    snprintf(q.base, sizeof q.base, "http://127.0.0.1:%u", q.port);
    /* curl as written, the port swapped in */
    char *at = strstr(curl, "127.0.0.1:8470");
    assert_non_null(at);
    snprintf(cmd, sizeof cmd, "cd '%s' && %.*s127.0.0.1:%u%s", fx_src_dir, (int)(at - curl), curl, q.port,
             at + strlen("127.0.0.1:8470"));
    FILE *p = popen(cmd, "r");
    char head[256] = "";
    assert_non_null(fgets(head, sizeof head, p));
    pclose(p);
    if (!strstr(head, " 202"))
        fail_msg("%s answered: %s", cmd, head);
    /* the client as written, the server from the environment */
    snprintf(cmd, sizeof cmd, "cd '%s' && MICRORAY_SERVER=%s '%s/microray'%s", fx_src_dir, q.base,
             fx_build_dir, client + strlen("build/microray"));
    p = popen(cmd, "r");
    char id[128] = "";
    assert_non_null(fgets(id, sizeof id, p));
    assert_int_equal(pclose(p), 0);
    assert_int_equal(strspn(id, "0123456789abcdef"), 32);
    assert_int_equal(daemon_stop(&q, SIGKILL), -SIGKILL); /* its jobs need not finish */
}

/* The one rule for a refused job, over the whole table of malformed jobs
 * (tests/support/bad_jobs.h): 400 malformed-json when the body is not one
 * JSON text, 422 invalid-job for every other problem, with the table's
 * pointer, every problem in "errors", and a type that resolves to a page
 * the daemon serves. (Before, width 8193 was 400 but the pixel cap 422,
 * svo depth 13 was 400 but solid depth 11 422.) */
static void test_status_rule_over_malformed_table(void **state)
{
    (void)state;
    size_t n = sizeof BAD / sizeof BAD[0], failures = 0;
    for (size_t i = 0; i < n; i++) {
        size_t len = strlen(BAD[i].json);
        char *body = malloc(len + 1);
        for (size_t k = 0; k <= len; k++)
            body[k] = BAD[i].json[k] == '\'' ? '"' : BAD[i].json[k];
        http_result r = http(&D, "POST", "/v1/jobs", body, len, NULL);
        free(body);
        bool syntax = bad_job_is_syntax(&BAD[i]);
        long want = syntax ? 400 : 422;
        const char *slug = syntax ? "/problems/malformed-json" : "/problems/invalid-job";
        cJSON *doc = cJSON_Parse(r.body);
        const cJSON *type = cJSON_GetObjectItem(doc, "type"), *ptr = cJSON_GetObjectItem(doc, "pointer"),
                    *errors = cJSON_GetObjectItem(doc, "errors");
        const char *got_ptr = cJSON_IsString(ptr) ? ptr->valuestring : "";
        const cJSON *first = cJSON_GetArrayItem(errors, 0);
        bool ok = r.status == want && strstr(r.content_type, "application/problem+json") &&
                  cJSON_IsString(type) && !strcmp(type->valuestring, slug) &&
                  !strcmp(got_ptr, BAD[i].pointer) &&
                  (syntax ? errors == NULL
                          : cJSON_GetArraySize(errors) >= 1 &&
                                !strcmp(cJSON_GetObjectItem(first, "pointer")->valuestring, BAD[i].pointer));
        if (!ok) {
            failures++;
            print_error("case %zu: %s\n  want %ld %s at '%s'\n  got  %ld %s\n", i, BAD[i].json, want,
                        slug, BAD[i].pointer, r.status, r.body);
        }
        cJSON_Delete(doc);
        http_free(&r);
    }
    assert_int_equal(failures, 0);
    /* the examples of the issue */
    static const char *const cases[][2] = {
        {"\"output\":{\"width\":8193,\"height\":16}", "/output/width"},
        {"\"output\":{\"width\":8192,\"height\":8192}", "/output"},
    };
    for (size_t i = 0; i < 2; i++) {
        char *job = fx_small_job(0, 32, NULL), body[4096];
        /* replace the output block */
        char *out = strstr(job, "\"output\"");
        snprintf(body, sizeof body, "%.*s%s}", (int)(out - job), job, cases[i][0]);
        free(job);
        http_result r = http(&D, "POST", "/v1/jobs", body, strlen(body), NULL);
        if (r.status != 422 || !strstr(r.body, cases[i][1]))
            fail_msg("%s: %ld %s", cases[i][0], r.status, r.body);
        http_free(&r);
    }
    /* the types resolve */
    static const char *const pages[] = {"/problems/malformed-json", "/problems/invalid-job",
                                        "/problems/not-found", "/problems/unavailable"};
    for (size_t i = 0; i < sizeof pages / sizeof *pages; i++) {
        http_result r = http(&D, "GET", pages[i], NULL, 0, NULL);
        assert_int_equal(r.status, 200);
        assert_non_null(strstr(r.content_type, "text/html"));
        assert_non_null(strstr(r.body, "<h1>"));
        http_free(&r);
    }
    http_result r = http(&D, "GET", "/problems/no-such-thing", NULL, 0, NULL);
    assert_int_equal(r.status, 404);
    http_free(&r);
}

/* Whether s is UTF-8 text (RFC 3629: no overlongs, surrogates or bytes
 * above U+10FFFF's). */
static bool utf8_text(const char *str)
{
    const unsigned char *s = (const unsigned char *)str;
    while (*s) {
        const unsigned b = *s;
        const unsigned need = b < 0x80 ? 0 : b >= 0xC2 && b <= 0xDF ? 1 : b >= 0xE0 && b <= 0xEF ? 2 : b >= 0xF0 && b <= 0xF4 ? 3 : 4;
        if (need == 4)
            return false;
        unsigned cp = need ? b & (0x3Fu >> need) : b;
        for (unsigned k = 1; k <= need; k++) {
            if ((s[k] & 0xC0) != 0x80)
                return false;
            cp = cp << 6 | (s[k] & 0x3F);
        }
        if ((need == 2 && (cp < 0x800 || (cp >= 0xD800 && cp <= 0xDFFF))) || (need == 3 && (cp < 0x10000 || cp > 0x10FFFF)))
            return false;
        s += need + 1;
    }
    return true;
}

/* POST /v1/jobs?dry_run=1 validates and estimates without queuing, and
 * reports every problem it finds, not only the first. */
static void test_dry_run(void **state)
{
    (void)state;
    http_result r = http(&D, "GET", "/v1/jobs?limit=1000", NULL, 0, NULL);
    cJSON *doc = cJSON_Parse(r.body);
    int before = cJSON_GetArraySize(cJSON_GetObjectItem(doc, "jobs"));
    cJSON_Delete(doc);
    http_free(&r);

    char *job = fx_small_job(7, 160, NULL);
    r = http(&D, "POST", "/v1/jobs?dry_run=1", job, strlen(job), NULL);
    free(job);
    if (r.status != 200)
        fail_msg("dry run: %ld %s", r.status, r.body);
    doc = cJSON_Parse(r.body);
    assert_true(cJSON_IsTrue(cJSON_GetObjectItem(doc, "valid")));
    assert_int_equal(cJSON_GetObjectItem(doc, "frames")->valueint, 8);
    assert_int_equal(cJSON_GetObjectItem(doc, "width")->valueint, 160);
    assert_true(cJSON_GetObjectItem(doc, "camera_rays")->valuedouble == 8.0 * 160 * 90 * 1);
    cJSON *mem = cJSON_GetObjectItem(doc, "memory");
    /* the default passes: rgba, z, n, id = 10 float planes */
    assert_true(cJSON_GetObjectItem(mem, "film")->valuedouble == 160.0 * 90 * 10 * 4);
    cJSON *asset = cJSON_GetArrayItem(cJSON_GetObjectItem(doc, "assets"), 0);
    struct stat st;
    assert_int_equal(stat("/usr/share/assimp/models/X/BCN_Epileptic.X", &st), 0);
    assert_true(cJSON_GetObjectItem(asset, "bytes")->valuedouble == (double)st.st_size);
    assert_int_equal(cJSON_GetArraySize(cJSON_GetObjectItem(doc, "references")), 0);
    /* a mesh derives nothing without levels of detail */
    assert_int_equal(cJSON_GetArraySize(cJSON_GetObjectItem(doc, "derived")), 0);
    cJSON_Delete(doc);
    http_free(&r);
    /* with "tolerance_px" it derives its levels */
    job = fx_small_job(7, 160, "\"tolerance_px\":1,");
    r = http(&D, "POST", "/v1/jobs?dry_run=1", job, strlen(job), NULL);
    free(job);
    doc = cJSON_Parse(r.body);
    cJSON *derived = cJSON_GetObjectItem(doc, "derived");
    assert_int_equal(cJSON_GetArraySize(derived), 1);
    assert_string_equal(cJSON_GetObjectItem(cJSON_GetArrayItem(derived, 0), "pointer")->valuestring, "/objects/0");
    assert_string_equal(cJSON_GetObjectItem(cJSON_GetArrayItem(derived, 0), "kind")->valuestring, "mesh");
    cJSON_Delete(doc);
    http_free(&r);
    /* with reference passes: a mesh is its own tessellation, no ground truth */
    job = fx_small_job(7, 160, "\"reference\":true,");
    r = http(&D, "POST", "/v1/jobs?dry_run=1", job, strlen(job), NULL);
    free(job);
    assert_int_equal(r.status, 200);
    doc = cJSON_Parse(r.body);
    cJSON *refs = cJSON_GetObjectItem(doc, "references");
    assert_int_equal(cJSON_GetArraySize(refs), 1);
    assert_string_equal(cJSON_GetArrayItem(refs, 0)->valuestring, "tessellated");
    cJSON_Delete(doc);
    http_free(&r);

    /* three independent problems: the parser's two and a missing asset */
    static const char bad[] =
        "{\"assets\":{\"a\":{\"path\":\"X/no-such.x\"},\"b\":{\"path\":\"X/BCN_Epileptic.X\"}},"
        "\"objects\":[{\"asset\":\"b\",\"color\":[1,2]}],"
        "\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0,5],\"target\":[0,0,0]}]},"
        "\"frames\":{\"end\":1},\"output\":{\"samples\":0}}";
    r = http(&D, "POST", "/v1/jobs?dry_run=1", bad, strlen(bad), NULL);
    assert_int_equal(r.status, 422);
    doc = cJSON_Parse(r.body);
    cJSON *errors = cJSON_GetObjectItem(doc, "errors");
    assert_int_equal(cJSON_GetArraySize(errors), 2); /* the parser stops the check before assets */
    assert_string_equal(cJSON_GetObjectItem(cJSON_GetArrayItem(errors, 0), "pointer")->valuestring,
                        "/objects/0/color");
    assert_string_equal(cJSON_GetObjectItem(cJSON_GetArrayItem(errors, 1), "pointer")->valuestring,
                        "/output/samples");
    assert_string_equal(cJSON_GetObjectItem(doc, "pointer")->valuestring, "/objects/0/color");
    cJSON_Delete(doc);
    http_free(&r);
    /* with the parser satisfied, each asset that does not resolve is one problem */
    static const char assets[] =
        "{\"assets\":{\"a\":{\"path\":\"X/no-such.x\"},\"b\":{\"path\":\"../etc/passwd\"},"
        "\"c\":{\"path\":\"X/BCN_Epileptic.X\"}},\"objects\":[{\"asset\":\"c\"}],"
        "\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0,5],\"target\":[0,0,0]}]},"
        "\"frames\":{\"end\":1}}";
    r = http(&D, "POST", "/v1/jobs?dry_run=true", assets, strlen(assets), NULL);
    assert_int_equal(r.status, 422);
    doc = cJSON_Parse(r.body);
    errors = cJSON_GetObjectItem(doc, "errors");
    assert_int_equal(cJSON_GetArraySize(errors), 2);
    assert_string_equal(cJSON_GetObjectItem(cJSON_GetArrayItem(errors, 0), "pointer")->valuestring,
                        "/assets/a/path");
    assert_string_equal(cJSON_GetObjectItem(cJSON_GetArrayItem(errors, 1), "pointer")->valuestring,
                        "/assets/b/path");
    cJSON_Delete(doc);
    http_free(&r);
    /* a model file over the cap (a sparse file: no disk used) is a problem
     * of the submission, naming its path, not a job that fails on import */
    char big[400];
    snprintf(big, sizeof big, "%s/huge.obj", fx_root);
    FILE *bf = fopen(big, "wb");
    assert_non_null(bf);
    assert_int_equal(fseeko(bf, (off_t)MR_MAX_ASSET_FILE_BYTES, SEEK_SET), 0);
    assert_int_equal(fputc('\n', bf), '\n');
    fclose(bf);
    static const char huge[] =
        "{\"assets\":{\"h\":{\"path\":\"huge.obj\"}},\"objects\":[{\"asset\":\"h\"}],"
        "\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0,5],\"target\":[0,0,0]}]},\"frames\":{\"end\":0}}";
    r = http(&D, "POST", "/v1/jobs?dry_run=1", huge, strlen(huge), NULL);
    assert_int_equal(r.status, 422);
    doc = cJSON_Parse(r.body);
    errors = cJSON_GetObjectItem(doc, "errors");
    assert_string_equal(cJSON_GetObjectItem(cJSON_GetArrayItem(errors, 0), "pointer")->valuestring,
                        "/assets/h/path");
    assert_non_null(strstr(cJSON_GetObjectItem(cJSON_GetArrayItem(errors, 0), "detail")->valuestring,
                           "expected a model file of at most"));
    cJSON_Delete(doc);
    http_free(&r);
    unlink(big);

    /* a problem's message cut to its size inside a two-byte character (a
     * path of 300 of them) is still UTF-8 text */
    char *long_path = malloc(8192);
    size_t lp = (size_t)snprintf(long_path, 8192, "{\"assets\":{\"a\":{\"path\":\"a");
    for (int k = 0; k < 300; k++)
        lp += (size_t)snprintf(long_path + lp, 8192 - lp, "\xc3\xa9");
    snprintf(long_path + lp, 8192 - lp, ".obj\"}},\"objects\":[{\"asset\":\"a\"}],\"camera\":{\"path\":"
             "[{\"t\":0,\"position\":[0,0,5],\"target\":[0,0,0]}]},\"frames\":{\"end\":0}}");
    r = http(&D, "POST", "/v1/jobs?dry_run=1", long_path, strlen(long_path), NULL);
    free(long_path);
    assert_int_equal(r.status, 422);
    if (!utf8_text(r.body))
        fail_msg("the 422 for a long path is not UTF-8 text");
    http_free(&r);

    /* a value the API does not name is refused, never read as absent: a
     * bare ?dry_run (which libmicrohttpd hands over without a value) once
     * queued the job */
    static const char *const not_a_value[] = {"/v1/jobs?dry_run=maybe", "/v1/jobs?dry_run",
                                              "/v1/jobs?dry_run=", "/v1/jobs?x=1&dry_run"};
    job = fx_small_job(7, 160, NULL);
    for (size_t k = 0; k < sizeof not_a_value / sizeof *not_a_value; k++) {
        r = http(&D, "POST", not_a_value[k], job, strlen(job), NULL);
        assert_int_equal(r.status, 400);
        http_free(&r);
    }
    free(job);

    /* nothing was queued */
    r = http(&D, "GET", "/v1/jobs?limit=1000", NULL, 0, NULL);
    doc = cJSON_Parse(r.body);
    assert_int_equal(cJSON_GetArraySize(cJSON_GetObjectItem(doc, "jobs")), before);
    cJSON_Delete(doc);
    http_free(&r);
}

/* A job's frames as a collection: the list (state, size, seconds, links),
 * every finished frame and stats.json in one streamed tar that tar(1)
 * reads, and a frame's EXR with ETag, Cache-Control: immutable, 304 and
 * byte ranges; OPTIONS answers with Allow. */
static void test_frames_collection_and_caching(void **state)
{
    (void)state;
    char *job = fx_small_job(3, 64, NULL), id[64], path[256], value[256];
    fx_submit(&D, job, id);
    free(job);
    cJSON *j = fx_wait_job(&D, id, 120);
    assert_string_equal(state_of(j), "succeeded");
    cJSON_Delete(j);

    /* the frames, each with its file's size */
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/0", id);
    http_result exr0 = http(&D, "GET", path, NULL, 0, NULL);
    assert_int_equal(exr0.status, 200);
    snprintf(path, sizeof path, "/v1/jobs/%s/frames", id);
    http_result r = http(&D, "GET", path, NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    cJSON *doc = cJSON_Parse(r.body);
    cJSON *frames = cJSON_GetObjectItem(doc, "frames");
    assert_int_equal(cJSON_GetArraySize(frames), 4);
    cJSON *f0 = cJSON_GetArrayItem(frames, 0);
    assert_string_equal(cJSON_GetObjectItem(f0, "state")->valuestring, "done");
    assert_true(cJSON_GetObjectItem(f0, "bytes")->valuedouble == (double)exr0.len);
    assert_true(cJSON_GetObjectItem(f0, "seconds")->valuedouble > 0);
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/0.png", id);
    assert_string_equal(cJSON_GetObjectItem(cJSON_GetObjectItem(f0, "links"), "png")->valuestring, path);
    cJSON_Delete(doc);
    http_free(&r);
    snprintf(path, sizeof path, "/v1/jobs/%s/frames?state=failed", id);
    r = http(&D, "GET", path, NULL, 0, NULL);
    doc = cJSON_Parse(r.body);
    assert_int_equal(cJSON_GetArraySize(cJSON_GetObjectItem(doc, "frames")), 0);
    cJSON_Delete(doc);
    http_free(&r);

    /* the archive: tar(1) lists and extracts it; its frames are the files */
    snprintf(path, sizeof path, "/v1/jobs/%s/frames.tar", id);
    r = http(&D, "GET", path, NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    assert_string_equal(r.content_type, "application/x-tar");
    assert_true(fx_header_get(&r, "Content-Length", value, sizeof value));
    assert_true((size_t)atoll(value) == r.len);
    char tar_path[600], dir[600], cmd[2000];
    snprintf(tar_path, sizeof tar_path, "%s/frames.tar", fx_tmp);
    snprintf(dir, sizeof dir, "%s/untar", fx_tmp);
    FILE *f = fopen(tar_path, "wb");
    fwrite(r.body, 1, r.len, f);
    fclose(f);
    http_free(&r);
    snprintf(cmd, sizeof cmd, "mkdir -p '%s' && tar -xf '%s' -C '%s'", dir, tar_path, dir);
    assert_int_equal(system(cmd), 0);
    for (int k = 0; k < 4; k++) {
        char file[700];
        snprintf(file, sizeof file, "%s/%04d.exr", dir, k);
        size_t len = 0;
        char *bytes = fx_slurp(file, &len);
        assert_non_null(bytes);
        snprintf(path, sizeof path, "/v1/jobs/%s/frames/%d", id, k);
        http_result fr = http(&D, "GET", path, NULL, 0, NULL);
        assert_true(len == fr.len && memcmp(bytes, fr.body, len) == 0);
        http_free(&fr);
        free(bytes);
    }
    char stats_file[700];
    snprintf(stats_file, sizeof stats_file, "%s/stats.json", dir);
    char *text = fx_slurp(stats_file, NULL);
    doc = cJSON_Parse(text);
    assert_int_equal(cJSON_GetArraySize(cJSON_GetObjectItem(doc, "frames")), 4);
    cJSON_Delete(doc);
    free(text);

    /* caching and ranges */
    char etag[128], header[256];
    assert_true(fx_header_get(&exr0, "ETag", etag, sizeof etag));
    assert_true(fx_header_get(&exr0, "Cache-Control", value, sizeof value));
    assert_non_null(strstr(value, "immutable"));
    assert_true(fx_header_get(&exr0, "Accept-Ranges", value, sizeof value));
    assert_string_equal(value, "bytes");
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/0", id);
    snprintf(header, sizeof header, "If-None-Match: %s", etag);
    r = http(&D, "GET", path, NULL, 0, header);
    assert_int_equal(r.status, 304);
    assert_int_equal(r.len, 0);
    http_free(&r);
    r = http(&D, "GET", path, NULL, 0, "Range: bytes=0-99");
    assert_int_equal(r.status, 206);
    assert_true(r.len == 100 && memcmp(r.body, exr0.body, 100) == 0);
    assert_true(fx_header_get(&r, "Content-Range", value, sizeof value));
    char want[96];
    snprintf(want, sizeof want, "bytes 0-99/%zu", exr0.len);
    assert_string_equal(value, want);
    http_free(&r);
    r = http(&D, "GET", path, NULL, 0, "Range: bytes=-10");
    assert_int_equal(r.status, 206);
    assert_true(r.len == 10 && memcmp(r.body, exr0.body + exr0.len - 10, 10) == 0);
    http_free(&r);
    snprintf(header, sizeof header, "Range: bytes=%zu-", exr0.len);
    r = http(&D, "GET", path, NULL, 0, header);
    assert_int_equal(r.status, 416);
    assert_true(fx_header_get(&r, "Content-Range", value, sizeof value));
    snprintf(want, sizeof want, "bytes */%zu", exr0.len);
    assert_string_equal(value, want);
    http_free(&r);
    const char *if_range[] = {"Range: bytes=0-99", "If-Range: \"another\"", NULL};
    r = http_headers(&D, "GET", path, NULL, 0, if_range);
    assert_int_equal(r.status, 200);
    assert_true(r.len == exr0.len);
    http_free(&r);
    http_free(&exr0);

    /* OPTIONS and Allow */
    snprintf(path, sizeof path, "/v1/jobs/%s", id);
    r = http(&D, "OPTIONS", path, NULL, 0, NULL);
    assert_int_equal(r.status, 204);
    assert_true(fx_header_get(&r, "Allow", value, sizeof value));
    assert_string_equal(value, "GET, HEAD, DELETE, OPTIONS");
    http_free(&r);
    r = http(&D, "OPTIONS", "/v2/nothing", NULL, 0, NULL);
    assert_int_equal(r.status, 404);
    http_free(&r);
    r = http(&D, "PUT", "/v1/jobs", "{}", 2, NULL);
    assert_int_equal(r.status, 405);
    assert_true(fx_header_get(&r, "Allow", value, sizeof value));
    assert_string_equal(value, "POST, GET, HEAD, OPTIONS");
    http_free(&r);
}

/* The ids of the "frame" events of an event stream's text, in order. */
static int frame_event_ids(const char *text, long long *ids, int max)
{
    int n = 0;
    for (const char *p = text; (p = strstr(p, "id: ")) && n < max; p += 4) {
        long long id = atoll(p + 4);
        const char *nl = strchr(p, '\n');
        if (nl && !strncmp(nl + 1, "event: frame\n", 13))
            ids[n++] = id;
    }
    return n;
}

/* Event streams carry ids (the job's frames done, in order) and a stream
 * resumed with Last-Event-ID gets the frame events it missed, then the
 * state (whose id is the last frame's). */
static void test_event_stream_resumes(void **state)
{
    (void)state;
    char *job = fx_small_job(5, 48, NULL), id[64], path[160];
    fx_submit(&D, job, id);
    free(job);
    snprintf(path, sizeof path, "/v1/jobs/%s/events", id);
    /* live: every frame event, ids 1..6 in order, and the final state */
    http_result r = http(&D, "GET", path, NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    long long ids[16];
    int n = frame_event_ids(r.body, ids, 16);
    cJSON *j = fx_wait_job(&D, id, 60);
    cJSON_Delete(j);
    /* the stream began after the submission: frames done before it are not
     * events of it, the later ones are, numbered in order */
    for (int i = 1; i < n; i++)
        assert_true(ids[i] == ids[i - 1] + 1);
    assert_true(n == 0 || ids[n - 1] == 6);
    assert_non_null(strstr(r.body, "id: 6\nevent: state\n"));
    http_free(&r);

    /* resumed after the second frame: frames 3..6, then the state */
    r = http(&D, "GET", path, NULL, 0, "Last-Event-ID: 2");
    assert_int_equal(r.status, 200);
    n = frame_event_ids(r.body, ids, 16);
    assert_int_equal(n, 4);
    for (int i = 0; i < 4; i++)
        assert_true(ids[i] == 3 + i);
    assert_non_null(strstr(r.body, "id: 6\nevent: state\n"));
    assert_non_null(strstr(r.body, "\"state\":\"succeeded\""));
    http_free(&r);
    /* from the start: all six; the same with the query parameter */
    snprintf(path, sizeof path, "/v1/jobs/%s/events?last_event_id=0", id);
    r = http(&D, "GET", path, NULL, 0, NULL);
    assert_int_equal(frame_event_ids(r.body, ids, 16), 6);
    http_free(&r);
    /* a fresh stream of a finished job: its state, nothing replayed */
    snprintf(path, sizeof path, "/v1/jobs/%s/events", id);
    r = http(&D, "GET", path, NULL, 0, NULL);
    assert_int_equal(frame_event_ids(r.body, ids, 16), 0);
    assert_non_null(strstr(r.body, "id: 6\nevent: state\n"));
    http_free(&r);
    r = http(&D, "GET", path, NULL, 0, "Last-Event-ID: seven");
    assert_int_equal(r.status, 400);
    http_free(&r);
}

/* A loopback receiver of notifications: answers its first request 500
 * (so the daemon must retry), the later ones 204, keeping each body and
 * its X-Microray-Attempt. */
typedef struct receiver {
    int fd;
    unsigned port;
    pthread_t thread;
    pthread_mutex_t mu;
    int count;
    char bodies[4][2048];
    int attempts[4];
} receiver;

static void *receiver_main(void *arg)
{
    receiver *rv = arg;
    for (;;) {
        int c = accept(rv->fd, NULL, NULL);
        if (c < 0)
            return NULL; /* shut down */
        char buf[8192];
        size_t len = 0;
        char *body = NULL;
        long want = -1;
        while (len < sizeof buf - 1) {
            ssize_t n = read(c, buf + len, sizeof buf - 1 - len);
            if (n <= 0)
                break;
            len += (size_t)n;
            buf[len] = '\0';
            char *end = strstr(buf, "\r\n\r\n");
            if (end && want < 0) {
                const char *cl = strcasestr(buf, "Content-Length:");
                want = cl ? atol(cl + 15) : 0;
                body = end + 4;
            }
            if (body && (long)(buf + len - body) >= want)
                break;
        }
        pthread_mutex_lock(&rv->mu);
        int k = rv->count++;
        if (k < 4 && body) {
            snprintf(rv->bodies[k], sizeof rv->bodies[k], "%s", body);
            const char *a = strcasestr(buf, "X-Microray-Attempt:");
            rv->attempts[k] = a ? atoi(a + 19) : 0;
        }
        pthread_mutex_unlock(&rv->mu);
        const char *answer = k == 0 ? "HTTP/1.1 500 Not Now\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
                                    : "HTTP/1.1 204 No Content\r\nConnection: close\r\n\r\n";
        ssize_t w = write(c, answer, strlen(answer));
        (void)w;
        close(c);
    }
}

/* A socket listening on a free loopback port: its descriptor, the port. */
static int loopback_listen(unsigned *port)
{
    int fd = socket(AF_INET, SOCK_STREAM, 0);
    struct sockaddr_in a = {.sin_family = AF_INET, .sin_addr.s_addr = htonl(INADDR_LOOPBACK)};
    socklen_t al = sizeof a;
    assert_int_equal(bind(fd, (struct sockaddr *)&a, sizeof a), 0);
    assert_int_equal(listen(fd, 16), 0);
    getsockname(fd, (struct sockaddr *)&a, &al);
    *port = ntohs(a.sin_port);
    return fd;
}

static void receiver_start(receiver *rv)
{
    memset(rv, 0, sizeof *rv);
    pthread_mutex_init(&rv->mu, NULL);
    rv->fd = loopback_listen(&rv->port);
    pthread_create(&rv->thread, NULL, receiver_main, rv);
}

static int receiver_count(receiver *rv)
{
    pthread_mutex_lock(&rv->mu);
    int n = rv->count;
    pthread_mutex_unlock(&rv->mu);
    return n;
}

static void receiver_stop(receiver *rv)
{
    shutdown(rv->fd, SHUT_RDWR);
    close(rv->fd);
    pthread_join(rv->thread, NULL);
    pthread_mutex_destroy(&rv->mu);
}

/* A receiver that takes connections and never answers: how many it took,
 * and the most it held open at once (a connection the client closed, on
 * its timeout, no longer counts). */
typedef struct silent {
    int fd;
    unsigned port;
    pthread_t thread;
    pthread_mutex_t mu;
    int taken, most_open;
    int held[16];
} silent;

static void *silent_main(void *arg)
{
    silent *sv = arg;
    for (;;) {
        int c = accept(sv->fd, NULL, NULL);
        if (c < 0)
            return NULL; /* shut down */
        pthread_mutex_lock(&sv->mu);
        int open = 1;
        for (int k = 0; k < sv->taken && k < 16; k++) {
            struct pollfd p = {.fd = sv->held[k], .events = POLLRDHUP};
            open += poll(&p, 1, 0) == 0; /* nothing: the client still waits */
        }
        if (sv->taken < 16)
            sv->held[sv->taken] = c;
        else
            close(c);
        sv->taken++;
        if (open > sv->most_open)
            sv->most_open = open;
        pthread_mutex_unlock(&sv->mu);
    }
}

static void silent_start(silent *sv)
{
    memset(sv, 0, sizeof *sv);
    pthread_mutex_init(&sv->mu, NULL);
    sv->fd = loopback_listen(&sv->port);
    pthread_create(&sv->thread, NULL, silent_main, sv);
}

static void silent_stop(silent *sv)
{
    shutdown(sv->fd, SHUT_RDWR);
    close(sv->fd);
    pthread_join(sv->thread, NULL);
    for (int k = 0; k < sv->taken && k < 16; k++)
        close(sv->held[k]);
    pthread_mutex_destroy(&sv->mu);
}

/* A job's notify URL gets its final state POSTed, retried with backoff
 * after a failed attempt (the receiver answers the first one 500). */
static void test_notify_on_completion(void **state)
{
    (void)state;
    receiver rv;
    receiver_start(&rv);
    char extra[128], id[64];
    snprintf(extra, sizeof extra, "\"notify\":\"http://127.0.0.1:%u/hook?x=1\",", rv.port);
    char *job = fx_small_job(1, 48, extra);
    fx_submit(&D, job, id);
    free(job);
    cJSON *j = fx_wait_job(&D, id, 60);
    assert_string_equal(state_of(j), "succeeded");
    cJSON_Delete(j);
    /* the retry comes after 1 s; the bound is the backoff's total, not a timing */
    for (int i = 0; i < 600 && receiver_count(&rv) < 2; i++)
        fx_sleep_ms(100);
    receiver_stop(&rv);
    assert_int_equal(rv.count, 2);
    for (int k = 0; k < 2; k++) {
        assert_int_equal(rv.attempts[k], k + 1);
        cJSON *b = cJSON_Parse(rv.bodies[k]);
        assert_non_null(b);
        assert_string_equal(cJSON_GetObjectItem(b, "id")->valuestring, id);
        assert_string_equal(cJSON_GetObjectItem(b, "state")->valuestring, "succeeded");
        assert_int_equal(cJSON_GetObjectItem(cJSON_GetObjectItem(b, "frames"), "done")->valueint, 2);
        assert_true(cJSON_IsString(cJSON_GetObjectItem(b, "finished_at")));
        cJSON_Delete(b);
    }
    /* three jobs whose receiver never answers: their deliveries are in
     * flight at once (each job a second or two after the other, well
     * within the 10 s an attempt waits), not one after another's timeout
     * (one at a time, each delivery behind a silent one came 10 s late) */
    silent sv;
    silent_start(&sv);
    char ids[3][64];
    snprintf(extra, sizeof extra, "\"notify\":\"http://127.0.0.1:%u/silent\",", sv.port);
    for (int k = 0; k < 3; k++) {
        job = fx_small_job(0, 40 + 8 * k, extra);
        fx_submit(&D, job, ids[k]);
        free(job);
    }
    int taken = 0;
    for (int i = 0; i < 600 && taken < 3; i++) {
        fx_sleep_ms(100);
        pthread_mutex_lock(&sv.mu);
        taken = sv.taken;
        pthread_mutex_unlock(&sv.mu);
    }
    const int most_open = sv.most_open;
    silent_stop(&sv);
    assert_int_equal(taken >= 3, 1);
    if (most_open < 2)
        fail_msg("the silent receiver held at most %d connection at once: deliveries one at a time", most_open);

    /* a URL that is not http(s) is refused at submission */
    job = fx_small_job(1, 48, "\"notify\":\"file:///etc/passwd\",");
    http_result r = http(&D, "POST", "/v1/jobs", job, strlen(job), NULL);
    free(job);
    assert_int_equal(r.status, 422);
    assert_non_null(strstr(r.body, "\"pointer\":\"/notify\""));
    http_free(&r);
}

/* The value of the metric line that starts with name (labels included)
 * in text; -1 when there is none. */
static double metric(const char *text, const char *name)
{
    for (const char *p = text; (p = strstr(p, name)); p++)
        if ((p == text || p[-1] == '\n') && p[strlen(name)] == ' ')
            return atof(p + strlen(name) + 1);
    return -1;
}

/* /metrics: queue depth, busy workers, build info, the daemon's process
 * (resident memory, descriptors, CPU) and its render worker's, responses
 * counted for every status class. */
static void test_metrics(void **state)
{
    (void)state;
    http_result r = http(&D, "GET", "/healthz", NULL, 0, NULL);
    http_free(&r);
    r = http(&D, "GET", "/v2/nothing", NULL, 0, NULL);
    http_free(&r);
    r = http(&D, "GET", "/metrics", NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    static const char *const names[] = {"microray_queue_jobs", "microray_queue_frames", "microray_workers",
                                        "microray_workers_busy", "microray_build_info{version=\"",
                                        "process_cpu_seconds_total", "process_resident_memory_bytes",
                                        "process_open_fds", "process_max_fds", "process_start_time_seconds",
                                        "microray_worker_resident_memory_bytes{slot=\"0\"}"};
    for (size_t i = 0; i < sizeof names / sizeof *names; i++)
        if (!strstr(r.body, names[i]))
            fail_msg("/metrics has no %s:\n%s", names[i], r.body);
    assert_true(metric(r.body, "microray_workers") == 1);
    assert_true(metric(r.body, "process_resident_memory_bytes") > 1e6);
    assert_true(metric(r.body, "process_open_fds") >= 3);
    assert_true(metric(r.body, "microray_worker_resident_memory_bytes{slot=\"0\"}") > 1e6);
    assert_true(metric(r.body, "microray_http_responses_total{class=\"2xx\"}") >= 1);
    assert_true(metric(r.body, "microray_http_responses_total{class=\"4xx\"}") >= 1);
    assert_true(metric(r.body, "microray_http_responses_total{class=\"3xx\"}") >= 0);
    http_free(&r);
}

static int setup(void **state)
{
    (void)state;
    curl_global_init(CURL_GLOBAL_DEFAULT);
    fx_init_dirs();
    daemon_start(&D, "data");
    return 0;
}

static int teardown(void **state)
{
    (void)state;
    int st = daemon_stop(&D, SIGTERM);
    if (!fx_cleanup_dirs())
        return -1;
    return st == 0 ? 0 : -1;
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_cancel_releases_running_frame),
        cmocka_unit_test(test_readyz_503_while_stopping),
        cmocka_unit_test(test_job_list_pages),
        cmocka_unit_test(test_progress_bar_fits_narrow_terminal),
        cmocka_unit_test(test_readme_quick_start),
        cmocka_unit_test(test_status_rule_over_malformed_table),
        cmocka_unit_test(test_dry_run),
        cmocka_unit_test(test_frames_collection_and_caching),
        cmocka_unit_test(test_event_stream_resumes),
        cmocka_unit_test(test_notify_on_completion),
        cmocka_unit_test(test_metrics),
    };
    return cmocka_run_group_tests_name("api", tests, setup, teardown);
}
