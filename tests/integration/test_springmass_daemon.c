/*
 * test_springmass_daemon.c - a spring-mass job (issue 15: a simulation
 * inside a render job) through the real microrayd: resumed after kill -9 of
 * the daemon, and retried after its render worker was killed mid-frame,
 * every frame is bit for bit the uninterrupted run's; the frames after each
 * interruption were reached from a checkpoint of the simulation in
 * DATA/springmass/ (their stats say which), not from frame 0; and the
 * checkpoints are where the worker's sandbox lets it write. (Bit for bit
 * needs the renderer to build a resumed scene's tree at frame 0 too: a
 * tree built at the resumed frame picked the other triangle for a ray
 * exactly on a shared edge, 1 pixel of 76,800.)
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include <signal.h>
#include <string.h>

#include "daemon_fixture.h"
#include "../support/film_fixture.h"
#include "render/exr.h"

#define FRAMES 10

static daemon_proc D;

/* A real model pinned at its feet and pressed by a probe; 32 samples at
 * 320x240 make a frame last long enough to be interrupted. A checkpoint
 * every 2 frames. */
static const char *JOB =
    "{\"name\":\"springmass-resume\",\"max_retries\":3,"
    "\"assets\":{\"w\":{\"path\":\"/usr/share/assimp/models/PLY/Wuson.ply\"}},"
    "\"objects\":[{\"asset\":\"w\",\"kind\":\"springmass\",\"springmass\":{\"nodes\":3000,"
    "\"checkpoint_every\":2,\"pins\":[{\"box_max\":[1,0.2,2]}],"
    "\"probes\":[{\"radius\":0.35,\"path\":[{\"t\":0,\"position\":[0,1.9,0]},"
    "{\"t\":0.4,\"position\":[0,1.05,0.3]}]}]}}],"
    "\"lights\":[{\"direction\":[-0.4,-0.8,-0.6],\"color\":[1,1,1],\"intensity\":1}],"
    "\"camera\":{\"path\":[{\"t\":0,\"position\":[4,1.5,1],\"target\":[0,0.7,0]}]},"
    "\"frames\":{\"fps\":24,\"start\":0,\"end\":0.375},"
    "\"output\":{\"width\":320,\"height\":240,\"samples\":32}}";

/* The frame's "replay" stats: frames replayed and the checkpoint replay
 * started from (both 0 when it was rendered in order). */
static void frame_replay(const char *id, int k, int *frames, int *checkpoint)
{
    char path[160];
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/%d/stats", id, k);
    http_result r = http(&D, "GET", path, NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    cJSON *j = cJSON_Parse(r.body);
    http_free(&r);
    assert_non_null(j);
    const cJSON *rep = cJSON_GetObjectItem(j, "replay");
    *frames = rep ? cJSON_GetObjectItem(rep, "frames")->valueint : 0;
    *checkpoint = rep ? cJSON_GetObjectItem(rep, "checkpoint")->valueint : 0;
    /* the kind's own fields reach the HTTP stats */
    assert_non_null(cJSON_GetObjectItem(j, "simulate_s"));
    assert_true(cJSON_GetObjectItem(j, "sim_nodes")->valuedouble > 2800);
    cJSON_Delete(j);
}

static void test_resume_and_retry(void **state)
{
    (void)state;
    daemon_start(&D, "reference");
    char ref_id[64];
    fx_submit(&D, JOB, ref_id);
    cJSON *j = fx_wait_job(&D, ref_id, 600);
    assert_string_equal(cJSON_GetObjectItem(j, "state")->valuestring, "succeeded");
    cJSON_Delete(j);
    mr_film *ref[FRAMES];
    for (int k = 0; k < FRAMES; k++)
        ref[k] = fx_read_frame(&D, ref_id, k);
    size_t n = (size_t)ref[0]->width * (size_t)ref[0]->height;
    for (int k = 1; k < FRAMES; k++)
        assert_true(memcmp(ref[k - 1]->z, ref[k]->z, n * sizeof(float)) != 0); /* it moves */
    for (int k = 0; k < FRAMES; k++) {
        int frames, checkpoint;
        frame_replay(ref_id, k, &frames, &checkpoint);
        assert_int_equal(frames, 0); /* in order: nothing replayed */
    }
    assert_int_equal(daemon_stop(&D, SIGTERM), 0);

    /* the same job: the daemon killed after 3 frames, then the worker
     * killed inside a later frame */
    daemon_start(&D, "interrupted");
    char id[64];
    fx_submit(&D, JOB, id);
    fx_wait_frames_done(&D, id, 3);
    assert_int_equal(daemon_stop(&D, SIGKILL), -SIGKILL);
    daemon_start(&D, "interrupted");
    fx_wait_frame_running_from(&D, id, 6);
    assert_int_equal(kill(fx_render_worker_pid(&D), SIGKILL), 0);
    j = fx_wait_job(&D, id, 600);
    assert_string_equal(cJSON_GetObjectItem(j, "state")->valuestring, "succeeded");
    int retried = 0;
    cJSON *f;
    cJSON_ArrayForEach(f, cJSON_GetObjectItem(j, "frame_states"))
        retried += cJSON_GetObjectItem(f, "retries")->valueint;
    assert_true(retried >= 1);
    cJSON_Delete(j);
    for (int k = 0; k < FRAMES; k++) {
        mr_film *got = fx_read_frame(&D, id, k);
        char what[64];
        snprintf(what, sizeof what, "frame %d against the uninterrupted run's", k);
        fx_assert_same_pixels(got, ref[k], what);
        mr_film_free(got);
        mr_film_free(ref[k]);
    }
    /* the two fresh workers started from checkpoints, never from frame 0 */
    int from_checkpoint = 0, replayed_total = 0;
    for (int k = 0; k < FRAMES; k++) {
        int frames, checkpoint;
        frame_replay(id, k, &frames, &checkpoint);
        if (checkpoint) {
            from_checkpoint++;
            assert_true(checkpoint <= k && checkpoint % 2 == 0);
            assert_int_equal(frames, k - checkpoint);
        } else {
            assert_int_equal(frames, 0);
        }
        replayed_total += frames;
    }
    assert_true(from_checkpoint >= 2);
    assert_true(replayed_total <= 2 * 1); /* at most one frame each time (every 2) */
    /* where the sandbox lets the worker write: DATA/springmass/ */
    char dir[700], cmd[800];
    snprintf(dir, sizeof dir, "%s/springmass", D.data);
    snprintf(cmd, sizeof cmd, "test $(ls %s/*.mrckpt | wc -l) -eq 5", dir);
    assert_int_equal(system(cmd), 0);
    assert_int_equal(daemon_stop(&D, SIGTERM), 0);
    char *log = fx_slurp(D.log, NULL);
    assert_non_null(log);
    if (!strstr(log, "resuming 1 job") || !strstr(log, "the render worker was killed by SIGKILL"))
        fail_msg("the daemon log lacks the resume or the worker's death:\n%s", log);
    free(log);
    fx_assert_store_intact(D.data);
}

static int setup(void **state)
{
    (void)state;
    fx_init_dirs();
    return 0;
}

static int teardown(void **state)
{
    (void)state;
    if (D.pid > 0 && kill(D.pid, 0) == 0)
        daemon_stop(&D, SIGKILL);
    return fx_cleanup_dirs() ? 0 : -1;
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_resume_and_retry),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
