/*
 * test_sequential_daemon.c - the frame-order contract of a kind whose frame
 * N needs frames 0..N-1 (a simulation; core/kinds/kind.h) honoured by the
 * real daemon (issue 11): resumed after kill -9 of the daemon, and retried
 * after the render worker died mid-frame, the job's frames are bit for bit
 * those of an uninterrupted run; and by the one-shot renderer's --frames
 * (issue 18): parts rendered apart are the whole run's frames.
 *
 * The kind is tests/support/sphere_kind.h, registered by this program
 * alone: the program is its own daemon and render worker. Run as
 * `test_sequential_daemon serve ...` (or `render`, `render-worker`,
 * `import-worker`)
 * it registers the kind and runs that microrayd command; the daemon's
 * children exec /proc/self/exe, this program again. Without arguments it
 * runs the tests, starting itself as the daemon.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include <signal.h>
#include <string.h>

#include "daemon_fixture.h"
#include "../support/film_fixture.h"
#include "import_worker.h"
#include "render/exr.h"
#include "render_cmd.h"
#include "render_proc.h"
#include "../support/sphere_kind.h"

#define FRAMES 8

static daemon_proc D;

/* The sphere's scale after frame n depends on every frame before it
 * (sphere_kind.h), so a frame rendered without replaying its predecessors
 * comes out at another size. 64 samples make a frame last long enough to
 * be interrupted. */
static const char *JOB =
    "{\"name\":\"seq\",\"max_retries\":3,"
    "\"assets\":{\"a\":{\"path\":\"/usr/share/assimp/models/X/BCN_Epileptic.X\"}},"
    "\"objects\":[{\"asset\":\"a\",\"kind\":\"test_sphere\",\"test_sphere\":{\"radius\":0.8}}],"
    "\"lights\":[{\"direction\":[-0.4,-0.8,-0.6],\"color\":[1,1,1],\"intensity\":1}],"
    "\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0,4],\"target\":[0,0,0]}]},"
    "\"frames\":{\"fps\":4,\"start\":0,\"end\":1.75},"
    "\"output\":{\"width\":480,\"height\":270,\"samples\":64}}";

static void test_resume_and_retry_replay_the_simulation(void **state)
{
    (void)state;
    /* the uninterrupted run */
    daemon_start(&D, "reference");
    char ref_id[64];
    fx_submit(&D, JOB, ref_id);
    cJSON *j = fx_wait_job(&D, ref_id, 300);
    assert_string_equal(cJSON_GetObjectItem(j, "state")->valuestring, "succeeded");
    cJSON_Delete(j);
    mr_film *ref[FRAMES];
    for (int k = 0; k < FRAMES; k++)
        ref[k] = fx_read_frame(&D, ref_id, k);
    /* the simulation moves: consecutive frames differ (else equal frames
     * below would prove nothing) */
    size_t n = (size_t)ref[0]->width * (size_t)ref[0]->height;
    for (int k = 1; k < FRAMES; k++)
        assert_true(memcmp(ref[k - 1]->r, ref[k]->r, n * sizeof(float)) != 0);
    assert_int_equal(daemon_stop(&D, SIGTERM), 0);

    /* the same job: the daemon killed after two frames (the restart
     * resumes it at frame 2 or 3 in a fresh worker), then the worker killed
     * inside a later frame (the retry starts another fresh worker) */
    daemon_start(&D, "interrupted");
    char id[64];
    fx_submit(&D, JOB, id);
    fx_wait_frames_done(&D, id, 2);
    assert_int_equal(daemon_stop(&D, SIGKILL), -SIGKILL);
    daemon_start(&D, "interrupted");
    fx_wait_frame_running_from(&D, id, 4);
    assert_int_equal(kill(fx_render_worker_pid(&D), SIGKILL), 0);
    j = fx_wait_job(&D, id, 300);
    assert_string_equal(cJSON_GetObjectItem(j, "state")->valuestring, "succeeded");
    int retried = 0;
    cJSON *f;
    cJSON_ArrayForEach(f, cJSON_GetObjectItem(j, "frame_states"))
        retried += cJSON_GetObjectItem(f, "retries")->valueint;
    assert_true(retried >= 1); /* the worker's death cost a frame an attempt */
    cJSON_Delete(j);
    for (int k = 0; k < FRAMES; k++) {
        mr_film *got = fx_read_frame(&D, id, k);
        char what[64];
        snprintf(what, sizeof what, "frame %d against the uninterrupted run's", k);
        fx_assert_same_pixels(got, ref[k], what);
        mr_film_free(got);
        mr_film_free(ref[k]);
    }
    assert_int_equal(daemon_stop(&D, SIGTERM), 0);
    char *log = fx_slurp(D.log, NULL);
    assert_non_null(log);
    if (!strstr(log, "resuming 1 job") || !strstr(log, "the render worker was killed by SIGKILL"))
        fail_msg("the daemon log lacks the resume or the worker's death:\n%s", log);
    free(log);
    fx_assert_store_intact(D.data);
}

/* The one-shot renderer's --frames (issue 18) on the simulated kind: the
 * parts of the job rendered apart, in any order, are bit for bit the
 * frames of one whole run (each part replays the frames before it). */
static void test_frame_ranges_replay_the_simulation(void **state)
{
    (void)state;
    char job[400], whole[400], parts[400], cmd[2000];
    snprintf(job, sizeof job, "%s/seq.json", fx_tmp);
    snprintf(whole, sizeof whole, "%s/seq-whole", fx_tmp);
    snprintf(parts, sizeof parts, "%s/seq-parts", fx_tmp);
    FILE *f = fopen(job, "w");
    assert_non_null(f);
    fputs(JOB, f);
    fclose(f);
    /* this program is the renderer too (main) */
    snprintf(cmd, sizeof cmd, "/proc/%d/exe render '%s' --out '%s' --quiet", (int)getpid(), job, whole);
    assert_int_equal(system(cmd), 0);
    static const char *const specs[] = {"5-7", "0,2", "1", "3-4"};
    for (size_t k = 0; k < sizeof specs / sizeof *specs; k++) {
        snprintf(cmd, sizeof cmd, "/proc/%d/exe render '%s' --out '%s' --quiet --frames %s",
                 (int)getpid(), job, parts, specs[k]);
        assert_int_equal(system(cmd), 0);
    }
    for (int k = 0; k < FRAMES; k++) {
        char a[700], b[700];
        snprintf(a, sizeof a, "%s/%04d.exr", whole, k);
        snprintf(b, sizeof b, "%s/%04d.exr", parts, k);
        mr_film *fa = NULL, *fb = NULL;
        mr_error err;
        if (mr_exr_read_file(a, &fa, NULL, &err) < 0 || mr_exr_read_file(b, &fb, NULL, &err) < 0)
            fail_msg("%s", err.msg);
        char what[64];
        snprintf(what, sizeof what, "frame %d rendered in a part", k);
        fx_assert_same_pixels(fb, fa, what);
        mr_film_free(fa);
        mr_film_free(fb);
    }
}

static int setup(void **state)
{
    (void)state;
    fx_init_dirs();
    /* the daemon is this program (see main) */
    snprintf(fx_daemon_exe, sizeof fx_daemon_exe, "/proc/self/exe");
    return 0;
}

static int teardown(void **state)
{
    (void)state;
    if (D.pid > 0 && kill(D.pid, 0) == 0) /* left running by a failed test */
        daemon_stop(&D, SIGKILL);
    return fx_cleanup_dirs() ? 0 : -1;
}

int main(int argc, char **argv)
{
    if (argc >= 2) { /* the daemon and its children: microrayd with the test kind */
        mr_error err;
        if (mr_kind_register(&test_sphere_kind, &err) < 0) {
            fprintf(stderr, "%s\n", err.msg);
            return 1;
        }
        if (!strcmp(argv[1], "serve"))
            return mr_cmd_serve(argc - 2, argv + 2);
        if (!strcmp(argv[1], "render"))
            return mr_cmd_render(argc - 2, argv + 2);
        if (!strcmp(argv[1], "render-worker"))
            return mr_cmd_render_worker(argc - 2, argv + 2);
        if (!strcmp(argv[1], "import-worker"))
            return mr_cmd_import_worker(argc - 2, argv + 2);
        return 2;
    }
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_resume_and_retry_replay_the_simulation),
        cmocka_unit_test(test_frame_ranges_replay_the_simulation),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
