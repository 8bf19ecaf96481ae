/*
 * test_soak.c - 1,000 small jobs through one real daemon (issue 12, "a
 * soak"): every one succeeds in the same render worker, and the open file
 * descriptors and resident memory of the daemon and of its render worker
 * stay flat from after a warm-up (the first 100 jobs: the
 * scene cache filled, sqlite's page cache and the allocator's arenas grown)
 * to the end. Each job is one 32x18 frame of the dancer, so the run is
 * about HTTP, the store, the workers and the per-job setup, which is where
 * leaks would pile up.
 *
 * Bounds: descriptors exactly flat (+2 for a connection libmicrohttpd may
 * still be closing); resident memory within 32 MiB of the warm-up figure
 * (measured here: a few MiB of drift; a leak of a frame's film, 2.3 KB,
 * per job would not show, but one of its EXR buffer or a job record per
 * job, 10-100 KB, would pass the bound). Sanitizer builds keep freed memory
 * in quarantine, so there the memory figure is reported, not checked.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <cJSON.h>
#include <dirent.h>
#include <stdbool.h>

#include "daemon_fixture.h"
#include "microray.h"

#define JOBS 1000
#define WARMUP 100

static daemon_proc D;

static int setup(void **state)
{
    (void)state;
    curl_global_init(CURL_GLOBAL_DEFAULT);
    fx_init_dirs();
    const char *const args[] = {"--quiet", NULL};
    daemon_start_args(&D, "soak", args);
    return 0;
}

static int teardown(void **state)
{
    (void)state;
    int rc = daemon_stop(&D, SIGTERM);
    fx_cleanup_dirs();
    return rc == 0 ? 0 : -1;
}

static int open_fds(pid_t pid)
{
    char path[64];
    snprintf(path, sizeof path, "/proc/%d/fd", (int)pid);
    DIR *d = opendir(path);
    assert_non_null(d);
    int n = 0;
    struct dirent *e;
    while ((e = readdir(d)) != NULL)
        n += e->d_name[0] != '.';
    closedir(d);
    return n;
}

static long rss_kb(pid_t pid)
{
    char path[64], line[256];
    snprintf(path, sizeof path, "/proc/%d/status", (int)pid);
    FILE *f = fopen(path, "r");
    assert_non_null(f);
    long kb = -1;
    while (fgets(line, sizeof line, f))
        if (sscanf(line, "VmRSS: %ld kB", &kb) == 1)
            break;
    fclose(f);
    return kb;
}

/* Submits jobs [from, to) and waits until all of them succeeded. */
static void run_jobs(int from, int to, char (*ids)[40])
{
    for (int k = from; k < to; k++) {
        char job[1024];
        snprintf(job, sizeof job,
                 "{\"name\":\"soak-%d\",\"assets\":{\"d\":{\"path\":"
                 "\"/usr/share/assimp/models/X/BCN_Epileptic.X\"}},"
                 "\"objects\":[{\"asset\":\"d\",\"pose\":{\"clip\":0}}],"
                 "\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0.2,4.3],\"target\":[0,0,-0.1]}]},"
                 "\"frames\":{\"times\":[%g]},\"output\":{\"width\":32,\"height\":18}}",
                 k, (double)(k % 10) * 0.1);
        http_result r = http(&D, "POST", "/v1/jobs", job, strlen(job), NULL);
        if (r.status != 202)
            fail_msg("job %d: %ld %s", k, r.status, r.body);
        cJSON *j = cJSON_Parse(r.body);
        snprintf(ids[k], 40, "%s", cJSON_GetObjectItem(j, "id")->valuestring);
        cJSON_Delete(j);
        http_free(&r);
    }
    for (int k = from; k < to; k++) {
        char path[80];
        snprintf(path, sizeof path, "/v1/jobs/%s", ids[k]);
        for (int tries = 0;; tries++) {
            http_result r = http(&D, "GET", path, NULL, 0, NULL);
            assert_int_equal(r.status, 200);
            cJSON *j = cJSON_Parse(r.body);
            http_free(&r);
            const char *s = cJSON_GetObjectItem(j, "state")->valuestring;
            bool done = !strcmp(s, "succeeded");
            if (!done && (!strcmp(s, "failed") || !strcmp(s, "canceled")))
                fail_msg("job %d ended %s", k, s);
            cJSON_Delete(j);
            if (done)
                break;
            if (tries > 6000)
                fail_msg("job %d did not finish", k);
            fx_sleep_ms(10);
        }
    }
}

static void test_thousand_jobs(void **state)
{
    (void)state;
    static char ids[JOBS][40];
    double t0 = mr_now();
    run_jobs(0, WARMUP, ids);
    /* the daemon, and the render worker that rendered every job */
    pid_t worker = fx_render_worker_pid(&D);
    int fds0 = open_fds(D.pid), wfds0 = open_fds(worker);
    long rss0 = rss_kb(D.pid), wrss0 = rss_kb(worker);
    run_jobs(WARMUP, JOBS, ids);
    assert_int_equal(fx_render_worker_pid(&D), worker); /* the same worker throughout */
    int fds1 = open_fds(D.pid), wfds1 = open_fds(worker);
    long rss1 = rss_kb(D.pid), wrss1 = rss_kb(worker);
    print_message("[ soak     ] %d jobs in %.1f s; after %d: daemon %d fds, %ld KiB resident, "
                  "render worker %d fds, %ld KiB; after %d: daemon %d fds, %ld KiB, worker %d "
                  "fds, %ld KiB\n",
                  JOBS, mr_now() - t0, WARMUP, fds0, rss0, wfds0, wrss0, JOBS, fds1, rss1, wfds1,
                  wrss1);
    assert_true(fds1 <= fds0 + 2);
    assert_true(wfds1 <= wfds0 + 2);
#if !defined(__SANITIZE_ADDRESS__)
    assert_true(rss1 - rss0 < 32 * 1024);
    assert_true(wrss1 - wrss0 < 32 * 1024);
#endif
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_thousand_jobs),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
