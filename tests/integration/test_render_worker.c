/*
 * test_render_worker.c - renders run in a worker process the daemon keeps
 * (server/render_proc.h, issue 12), so that a job cannot take the daemon
 * down with it. Against the real daemon on loopback, each test kills,
 * crashes or starves the render worker as a job would and checks that
 *   - the daemon keeps answering (/healthz at once) and its store is intact;
 *   - a frame in progress counts one failed attempt, with how the worker
 *     ended, and the job goes on in a new worker to a complete result;
 *   - a death while the job is being prepared fails the job, saying so;
 *   - a worker killed while idle is replaced when the next job comes;
 *   - a job that surely needs more than --job-memory-mb is refused at
 *     submission; a worker over --worker-memory-mb is killed and the frame
 *     fails as over a limit (not retried);
 *   - a frame over --frame-timeout is killed and fails, once;
 *   - a cancel kills the worker at once, and the next job gets a new one.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include <signal.h>
#include <string.h>

#include "child.h"
#include "daemon_fixture.h"
#include "util/clock.h"

static daemon_proc D;

/* A job of slow frames, so a test can act inside a frame: the dancer
 * filling a 640x360 film (its every pixel traced: a renderer leaves the
 * film outside the scene's projected box untraced) at `samples` samples a
 * pixel (64: about 0.9 s each here, set-up included, 512: about 6 s). */
static char *slow_job(int frames, int samples, const char *extra)
{
    char *s = malloc(4096);
    snprintf(s, 4096,
             "{\"name\":\"rw\",%s\"assets\":{\"d\":{\"path\":\"/usr/share/assimp/models/X/BCN_Epileptic.X\"}},"
             "\"objects\":[{\"asset\":\"d\",\"pose\":{\"clip\":0}}],"
             "\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0.2,1.2],\"target\":[0,0,-0.1]}]},"
             "\"frames\":{\"fps\":4,\"start\":0,\"end\":%g},"
             "\"output\":{\"width\":640,\"height\":360,\"samples\":%d}}",
             extra ? extra : "", (frames - 1) / 4.0, samples);
    return s;
}

static void assert_healthy(void)
{
    double t0 = mr_now();
    http_result h = http(&D, "GET", "/healthz", NULL, 0, NULL);
    assert_int_equal(h.status, 200);
    http_free(&h);
    assert_true(mr_now() - t0 < 1.0);
}

/* Polls the job until one of its frames is running (the worker is inside
 * a frame, past importing and preparing). */
static void wait_frame_running(const char *id)
{
    char path[128];
    snprintf(path, sizeof path, "/v1/jobs/%s", id);
    for (int i = 0; i < 3000; i++) {
        http_result r = http(&D, "GET", path, NULL, 0, NULL);
        bool running = r.status == 200 && strstr(r.body, "\"state\":\"running\",\"retries\"");
        http_free(&r);
        if (running)
            return;
        fx_sleep_ms(10);
    }
    fail_msg("job %s: no frame started within 30 s", id);
}

static cJSON *frame_state(cJSON *job, int index)
{
    cJSON *f = cJSON_GetArrayItem(cJSON_GetObjectItem(job, "frame_states"), index);
    assert_non_null(f);
    return f;
}

static bool process_gone(pid_t pid)
{
    char path[64];
    snprintf(path, sizeof path, "/proc/%d/stat", (int)pid);
    FILE *f = fopen(path, "r");
    if (!f)
        return true;
    char state = '?';
    int n = fscanf(f, "%*d %*s %c", &state);
    fclose(f);
    return n == 1 && state == 'Z';
}

/* A worker killed inside a frame (SIGKILL: what the kernel's OOM killer
 * does; then SIGSEGV: a crash) costs that frame one attempt each; the job
 * completes in new workers, every frame once. */
static void test_worker_death_mid_frame_is_retried(void **state)
{
    (void)state;
    char *job = slow_job(2, 64, "\"max_retries\":2,"), id[64];
    fx_submit(&D, job, id);
    free(job);
    const int sigs[2] = {SIGKILL, SIGSEGV};
    for (int k = 0; k < 2; k++) {
        wait_frame_running(id);
        pid_t worker = fx_render_worker_pid(&D);
        assert_int_equal(kill(worker, sigs[k]), 0);
        assert_healthy();
        /* up to 30 s: a liveness wait, not a timing (a sanitizer build's
         * worker under a loaded machine took over 2 s to be replaced) */
        for (int i = 0; i < 3000 && fx_render_worker_pid(&D) == worker; i++)
            fx_sleep_ms(10);
        assert_true(fx_render_worker_pid(&D) != worker); /* a new worker took over */
    }
    cJSON *j = fx_wait_job(&D, id, 300);
    assert_string_equal(cJSON_GetObjectItem(j, "state")->valuestring, "succeeded");
    assert_int_equal(cJSON_GetObjectItem(cJSON_GetObjectItem(j, "frames"), "done")->valueint, 2);
    /* both deaths landed in frame 0 (the slow one): two failed attempts */
    cJSON *f0 = frame_state(j, 0);
    assert_int_equal(cJSON_GetObjectItem(f0, "retries")->valueint, 2);
    assert_int_equal(cJSON_GetObjectItem(frame_state(j, 1), "retries")->valueint, 0);
    cJSON_Delete(j);
    char *log = fx_slurp(D.log, NULL);
    assert_non_null(log);
    /* a sanitizer build's worker catches SIGSEGV itself, reports and
     * exits: "ended unexpectedly (exit 1)" there */
    const char *segv = MR_SANITIZED ? "while rendering frame 0"
                                    : "the render worker was killed by SIGSEGV while rendering frame 0";
    bool said = strstr(log, "the render worker was killed by SIGKILL (out of memory?) while "
                            "rendering frame 0") && strstr(log, segv);
    free(log);
    if (!said)
        fail_msg("the daemon log (%s) does not say how the worker died", D.log);
    fx_assert_store_intact(D.data);
}

/* Killed while the job is prepared (stopped before it could import, then
 * killed): the job fails saying where, and the next job renders. */
static void test_worker_death_while_preparing_fails_the_job(void **state)
{
    (void)state;
    pid_t worker = fx_render_worker_pid(&D);
    assert_int_equal(kill(worker, SIGSTOP), 0);
    char *job = slow_job(1, 64, NULL), id[64];
    fx_submit(&D, job, id);
    free(job);
    /* the daemon has handed it the job: it is running */
    char path[128];
    snprintf(path, sizeof path, "/v1/jobs/%s", id);
    for (int i = 0; i < 500; i++) {
        http_result r = http(&D, "GET", path, NULL, 0, NULL);
        bool running = strstr(r.body, "\"state\":\"running\"") != NULL;
        http_free(&r);
        if (running)
            break;
        fx_sleep_ms(10);
    }
    assert_int_equal(kill(worker, SIGKILL), 0);
    cJSON *j = fx_wait_job(&D, id, 60);
    assert_string_equal(cJSON_GetObjectItem(j, "state")->valuestring, "failed");
    const char *why = cJSON_GetObjectItem(j, "error")->valuestring;
    if (!strstr(why, "the render worker was killed by SIGKILL") || !strstr(why, "while preparing the job"))
        fail_msg("error: %s", why);
    cJSON_Delete(j);
    assert_healthy();
    char *quick = fx_small_job(0, 64, NULL);
    fx_submit(&D, quick, id);
    free(quick);
    j = fx_wait_job(&D, id, 60);
    assert_string_equal(cJSON_GetObjectItem(j, "state")->valuestring, "succeeded");
    cJSON_Delete(j);
}

/* A worker killed while idle (the OOM killer picks a big idle worker
 * too) is replaced when the next job comes: the job renders, no attempt
 * lost. */
static void test_idle_worker_death_is_replaced(void **state)
{
    (void)state;
    pid_t worker = fx_render_worker_pid(&D);
    assert_true(worker > 0);
    assert_int_equal(kill(worker, SIGKILL), 0);
    for (int i = 0; i < 3000 && !process_gone(worker); i++)
        fx_sleep_ms(10);
    assert_true(process_gone(worker));
    char *quick = fx_small_job(0, 72, NULL), id[64];
    fx_submit(&D, quick, id);
    free(quick);
    cJSON *j = fx_wait_job(&D, id, 60);
    if (strcmp(cJSON_GetObjectItem(j, "state")->valuestring, "succeeded") != 0)
        fail_msg("the job after an idle worker's death: %s (%s)", cJSON_GetObjectItem(j, "state")->valuestring,
                 cJSON_GetObjectItem(j, "error")->valuestring);
    assert_int_equal(cJSON_GetObjectItem(frame_state(j, 0), "retries")->valueint, 0);
    cJSON_Delete(j);
    assert_true(fx_render_worker_pid(&D) != worker);
    assert_healthy();
}

/* A cancel kills the worker at once (well within a second, mid-frame of
 * a frame that takes seconds); no frame of the job is stored after it. */
static void test_cancel_kills_the_worker(void **state)
{
    (void)state;
    char *job = slow_job(2, 512, NULL), id[64];
    fx_submit(&D, job, id);
    free(job);
    wait_frame_running(id);
    pid_t worker = fx_render_worker_pid(&D);
    char path[128];
    snprintf(path, sizeof path, "/v1/jobs/%s/cancel", id);
    double t0 = mr_now();
    http_result r = http(&D, "POST", path, NULL, 0, NULL);
    assert_int_equal(r.status, 202);
    http_free(&r);
    while (!process_gone(worker) && mr_now() - t0 < 5)
        fx_sleep_ms(5);
    double gone = mr_now() - t0;
    print_message("[ cancel   ] worker gone %.3f s after the cancel was answered\n", gone);
    assert_true(process_gone(worker));
    assert_true(gone < 1.0);
    cJSON *j = fx_wait_job(&D, id, 30);
    assert_string_equal(cJSON_GetObjectItem(j, "state")->valuestring, "canceled");
    assert_int_equal(cJSON_GetObjectItem(cJSON_GetObjectItem(j, "frames"), "done")->valueint, 0);
    cJSON_Delete(j);
    assert_healthy();
}

/* The memory limits. --job-memory-mb: a job whose objects surely need
 * more (100,000 svo instances: their matrices alone) is refused at
 * submission, 422 naming the field, before anything is imported.
 * --worker-memory-mb: a worker that grows past it is killed; the frame
 * fails as over a limit, once (retrying would only repeat it), and the
 * daemon goes on. */
static void test_memory_limits(void **state)
{
    (void)state;
    daemon_proc saved = D;
    const char *extra[] = {"--job-memory-mb", "16", "--worker-memory-mb", "160", NULL};
    daemon_start_args(&D, "memory", extra);
    size_t cap = 100000 * 3 + 4096;
    char *crowd = malloc(cap);
    int n = snprintf(crowd, cap,
                     "{\"assets\":{\"d\":{\"path\":\"/usr/share/assimp/models/X/BCN_Epileptic.X\"}},"
                     "\"objects\":[{\"asset\":\"d\",\"kind\":\"svo\",\"svo\":{\"depth\":8,"
                     "\"method\":\"rigid\",\"instances\":[");
    for (int i = 0; i < 100000; i++)
        n += snprintf(crowd + n, cap - (size_t)n, i ? ",{}" : "{}");
    snprintf(crowd + n, cap - (size_t)n, "]}}],\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0,9],"
             "\"target\":[0,0,0]}]},\"frames\":{\"fps\":1,\"start\":0,\"end\":0},"
             "\"output\":{\"width\":64,\"height\":64}}");
    http_result r = http(&D, "POST", "/v1/jobs", crowd, strlen(crowd), NULL);
    free(crowd);
    if (r.status != 422 || !strstr(r.body, "\"pointer\":\"/objects/0/svo/instances\"") ||
        !strstr(r.body, "over the job memory budget of 16.0 MiB"))
        fail_msg("the crowd: %ld %s", r.status, r.body);
    http_free(&r);

    /* 4096 x 2304: a film of 4096 x 2304 x 40 bytes (377 MB) */
    char *job = fx_small_job(0, 4096, "\"max_retries\":3,"), id[64];
    fx_submit(&D, job, id);
    free(job);
    cJSON *j = fx_wait_job(&D, id, 120);
    assert_string_equal(cJSON_GetObjectItem(j, "state")->valuestring, "failed");
    char *text = cJSON_PrintUnformatted(j);
    if (!strstr(text, "the render worker used more than 160.0 MiB of memory"))
        fail_msg("job: %s", text);
    free(text);
    cJSON_Delete(j);
    assert_healthy();
    fx_assert_store_intact(D.data);
    assert_int_equal(daemon_stop(&D, SIGTERM), 0);
    D = saved;
}

/* --frame-timeout: a frame that takes longer is killed with its worker
 * and fails as over the limit, once. The limit holds for the job's
 * preparation too: with a limit of 1 s and the dancer as the asset, a
 * sanitized worker on a loaded machine (two busy loops beside the test)
 * prepared for over 1 s, a box of 6 faces as well, and the job failed in
 * its preparation. So the limit is 5 s, the asset the box (a sanitized
 * one-shot render of it takes 0.4 s here, 0.7 s beside the two busy
 * loops) and the frame far slower: the box
 * filling a 1280x720 film at 1024 samples a pixel (about 39 s here). */
static void test_frame_timeout(void **state)
{
    (void)state;
    daemon_proc saved = D;
    const char *extra[] = {"--frame-timeout", "5", NULL};
    daemon_start_args(&D, "timeout", extra);
    const char *job = "{\"name\":\"rw\",\"max_retries\":3,"
                      "\"assets\":{\"b\":{\"path\":\"/usr/share/assimp/models/OBJ/box.obj\"}},"
                      "\"objects\":[{\"asset\":\"b\"}],\"camera\":{\"path\":[{\"t\":0,"
                      "\"position\":[0.4,0.3,1.3],\"target\":[0,0,0]}]},\"frames\":{\"times\":[0]},"
                      "\"output\":{\"width\":1280,\"height\":720,\"samples\":1024}}";
    char id[64];
    fx_submit(&D, job, id);
    double t0 = mr_now();
    cJSON *j = fx_wait_job(&D, id, 120);
    assert_string_equal(cJSON_GetObjectItem(j, "state")->valuestring, "failed");
    cJSON *f0 = frame_state(j, 0);
    const char *why = cJSON_GetStringValue(cJSON_GetObjectItem(f0, "error"));
    if (!why || !strstr(why, "frame 0 took longer than 5 s (the daemon's --frame-timeout)")) {
        char *text = cJSON_PrintUnformatted(j);
        fail_msg("frame 0's error is not the timeout's; the job: %s", text);
    }
    assert_int_equal(cJSON_GetObjectItem(f0, "retries")->valueint, 1); /* not retried */
    cJSON_Delete(j);
    print_message("[ timeout  ] job failed %.2f s after submission\n", mr_now() - t0);
    assert_healthy();
    assert_int_equal(daemon_stop(&D, SIGTERM), 0);
    D = saved;
}

static int setup(void **state)
{
    (void)state;
    fx_init_dirs();
    daemon_start(&D, "data");
    return 0;
}

static int teardown(void **state)
{
    (void)state;
    assert_int_equal(daemon_stop(&D, SIGTERM), 0);
    fx_assert_store_intact(D.data);
    return fx_cleanup_dirs() ? 0 : -1;
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_worker_death_mid_frame_is_retried),
        cmocka_unit_test(test_worker_death_while_preparing_fails_the_job),
        cmocka_unit_test(test_idle_worker_death_is_replaced),
        cmocka_unit_test(test_cancel_kills_the_worker),
        cmocka_unit_test(test_memory_limits),
        cmocka_unit_test(test_frame_timeout),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
