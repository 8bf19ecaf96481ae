/*
 * test_stats_http.c - the daemon's statistics over HTTP: GET
 * /v1/jobs/{id}/frames/{n}/stats and GET /v1/jobs/{id}/stats.
 *
 * A data directory is filled through the store the way the workers fill it
 * (three frames done, their stats written by the stats writer, the job
 * ended so no worker touches it), then the real microrayd serves it. The
 * answers are compared byte for byte with the documents recorded before the
 * frame-stats fields became one table: the frame stats are the stored
 * text as it is, the job stats rebuild their totals and medians from it.
 * A second job's frames carry extras (a kind's own fields, as the renderer
 * appends them): they reach both answers, in place after the table's
 * fields, and leave the totals and medians alone.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include "daemon_fixture.h"
#include "stats_json.h"
#include "store.h"
#include "../support/stats_fixture.h"

static daemon_proc D;

static const char JOB_DOC[] =
    "{\"name\": \"skinned-small\","
    " \"assets\": {\"dancer\": {\"path\": \"/usr/share/assimp/models/X/BCN_Epileptic.X\"}},"
    " \"objects\": [{\"asset\": \"dancer\", \"pose\": {\"clip\": 0}}],"
    " \"camera\": {\"path\": [{\"t\": 0.0, \"position\": [0.0, 0.2, 4.3], \"target\": [0.0, 0.0, -0.1]}]},"
    " \"frames\": {\"fps\": 4, \"start\": 0.5, \"end\": 1.25},"
    " \"output\": {\"width\": 192, \"height\": 108, \"samples\": 3}}";

/* What GET /v1/jobs/{id}/stats answers for the stored frames 0..2 of
 * frame_fixture (threads: the daemon's --threads 2). */
static const char JOB_STATS[] =
    "{\"job\":\"skinned-small\",\"software\":\"microray " MR_VERSION_STRING "\",\"threads\":2,"
    "\"width\":192,\"height\":108,\"samples\":3,\"frames_total\":4,\"frames_done\":3,\"frames\":["
    FRAME0_TEXT "," FRAME1_TEXT "," FRAME2_TEXT "],"
    "\"totals\":{\"seconds\":{\"load\":0.25,\"derive\":0.0625,\"pose\":0.33433333333333332,\"bvh\":0.103,"
    "\"trace\":0.11000025,\"encode\":12345.878,\"total\":0.361},\"rays\":1099513213988,"
    "\"peak_rss_bytes\":123456789012},"
    "\"medians\":{\"seconds\":{\"load\":0,\"derive\":0,\"pose\":0.001,\"bvh\":0.003,\"trace\":2.5e-07,"
    "\"encode\":0.2,\"total\":0.001},\"mrays_per_s\":0}}\n";

/* Stores a job of four frames whose frames 0..2 are done with the given
 * stats texts, and ends it (canceled) so that no worker picks it up. */
static void store_job(const char *data_dir, char *const stats[3], char id[MR_JOB_ID_LEN + 1])
{
    mr_store *st = NULL;
    mr_error err = {0};
    bool existing = false;
    if (mr_store_open(data_dir, &st, &err) < 0 ||
        mr_store_job_create(st, JOB_DOC, strlen(JOB_DOC), "skinned-small", 4, 0, 2, NULL, NULL, id,
                            &existing, &err) < 0)
        fail_msg("%s", err.msg);
    static const char exr[] = "not an EXR: never read here";
    for (size_t i = 0; i < 3; i++)
        if (mr_store_frame_done(st, id, i, exr, sizeof exr, stats[i], &err) < 0)
            fail_msg("%s", err.msg);
    if (mr_store_job_set_state(st, id, MR_JOB_CANCELED, NULL, &err) < 0)
        fail_msg("%s", err.msg);
    mr_store_close(st);
}

static void get_ok(const char *path, const char *want)
{
    http_result r = http(&D, "GET", path, NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    expect_text(r.body, want);
    http_free(&r);
}

/* The two jobs of the data directory and their stored frame texts. */
static char job_plain[MR_JOB_ID_LEN + 1], job_extras[MR_JOB_ID_LEN + 1];
static char *text_plain[3], *text_extras[3];

static void test_recorded_documents(void **state)
{
    (void)state;
    char path[128];
    static const char *const want[] = {FRAME0, FRAME1, FRAME2};
    for (int i = 0; i < 3; i++) {
        expect_text(text_plain[i], want[i]);
        snprintf(path, sizeof path, "/v1/jobs/%s/frames/%d/stats", job_plain, i);
        get_ok(path, want[i]);
    }
    snprintf(path, sizeof path, "/v1/jobs/%s/stats", job_plain);
    get_ok(path, JOB_STATS);
}

static void test_extras_reach_http(void **state)
{
    (void)state;
    char path[128];
    for (int i = 0; i < 3; i++) {
        assert_non_null(strstr(text_extras[i], ",\"simulate_s\":"));
        snprintf(path, sizeof path, "/v1/jobs/%s/frames/%d/stats", job_extras, i);
        get_ok(path, text_extras[i]);
    }
    snprintf(path, sizeof path, "/v1/jobs/%s/stats", job_extras);
    http_result r = http(&D, "GET", path, NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    /* each frame entry is the stored text, extras in place ... */
    for (int i = 0; i < 3; i++)
        if (!strstr(r.body, text_extras[i]))
            fail_msg("frame %d is not in the job stats as stored:\n%s\n%s", i, text_extras[i], r.body);
    /* ... and the job figures are those of the same frames without extras */
    assert_non_null(strstr(JOB_STATS, ",\"totals\":"));
    assert_non_null(strstr(r.body, ",\"totals\":"));
    assert_string_equal(strstr(r.body, ",\"totals\":"), strstr(JOB_STATS, ",\"totals\":"));
    http_free(&r);
}

static int setup(void **state)
{
    (void)state;
    (void)fx_slurp; /* the fixture's, unused here */
    fx_init_dirs();
    curl_global_init(CURL_GLOBAL_DEFAULT);
    char data[600];
    snprintf(data, sizeof data, "%s/data", fx_tmp);
    for (int i = 0; i < 3; i++) {
        mr_frame_stats f = frame_fixture(i);
        text_plain[i] = mr_frame_stats_json(&f);
        /* what a kind reports through the renderer: a phase and a counter */
        if (mr_frame_stats_add_extra(&f, "simulate_s", "s", 0.125 * (i + 1), NULL) < 0 ||
            mr_frame_stats_add_extra(&f, "springs", "count", 40000 + i, NULL) < 0)
            return -1;
        text_extras[i] = mr_frame_stats_json(&f);
        if (!text_plain[i] || !text_extras[i])
            return -1;
    }
    store_job(data, text_plain, job_plain);
    store_job(data, text_extras, job_extras);
    daemon_start(&D, "data");
    return 0;
}

static int teardown(void **state)
{
    (void)state;
    int st = daemon_stop(&D, SIGTERM);
    for (int i = 0; i < 3; i++) {
        free(text_plain[i]);
        free(text_extras[i]);
    }
    curl_global_cleanup();
    char cmd[300];
    snprintf(cmd, sizeof cmd, "rm -rf %s", fx_tmp);
    return system(cmd) == 0 && st == 0 ? 0 : -1;
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_recorded_documents),
        cmocka_unit_test(test_extras_reach_http),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
