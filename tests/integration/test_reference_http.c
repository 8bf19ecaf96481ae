/*
 * test_reference_http.c - a job with "reference": true through the real
 * daemon (a render worker renders it, the daemon stores each frame's stats
 * and rebuilds the job's from them) and the client's table of it.
 *
 *  - GET /v1/jobs/{id}/stats: every frame carries its error entries (a dmm
 *    object: "tessellated" and "ground_truth") and seconds.reference, the
 *    totals and medians hold seconds.reference, and the job's "error"
 *    summary counts the frames and gives medians and worst frames equal to
 *    the frames' figures; the tessellated reference of the exact dmm
 *    traversal shows coverage error 0 and no holes;
 *  - GET /v1/jobs/{id}/frames/{n}/stats: the same entries;
 *  - `microray status --errors ID` prints a row per frame and reference
 *    (frame, total seconds, reference seconds, the figures) and each
 *    reference's median and worst rows and the worst frames, with --json the stats
 *    document; for a job without references it says there are none;
 *  - a bad "reference" is refused with 422 naming /reference.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <math.h>

#include "daemon_fixture.h"

static daemon_proc D;
static char JOB[64], PLAIN[64];

static const char DMM_JOB[] =
    "{\"name\":\"ref\",\"reference\":true,"
    "\"assets\":{\"d\":{\"path\":\"/usr/share/assimp/models/X/BCN_Epileptic.X\"}},"
    "\"objects\":[{\"asset\":\"d\",\"kind\":\"dmm\",\"dmm\":{\"level\":2,\"base_ratio\":0.25,"
    "\"mode\":\"base\"},\"pose\":{\"clip\":0}}],"
    "\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0.2,4.3],\"target\":[0,0,-0.1]}]},"
    "\"frames\":{\"fps\":4,\"start\":0,\"end\":0.5},"
    "\"output\":{\"width\":160,\"height\":90,\"samples\":1}}";

static cJSON *get_json(const char *path)
{
    http_result r = http(&D, "GET", path, NULL, 0, NULL);
    if (r.status != 200)
        fail_msg("GET %s: %ld %s", path, r.status, r.body);
    cJSON *j = cJSON_Parse(r.body);
    http_free(&r);
    assert_non_null(j);
    return j;
}

static const cJSON *at(const cJSON *o, const char *key)
{
    const cJSON *v = cJSON_GetObjectItemCaseSensitive(o, key);
    if (!v)
        fail_msg("no \"%s\"", key);
    return v;
}

static void test_http_stats(void **state)
{
    (void)state;
    char path[256];
    snprintf(path, sizeof path, "/v1/jobs/%s/stats", JOB);
    cJSON *stats = get_json(path);
    assert_int_equal(at(stats, "frames_done")->valueint, 3);
    double worst_cov = 0;
    int worst_frame = -1;
    const cJSON *fr;
    cJSON_ArrayForEach(fr, at(stats, "frames")) {
        assert_true(at(at(fr, "seconds"), "reference")->valuedouble > 0);
        const cJSON *errors = at(fr, "error");
        assert_int_equal(cJSON_GetArraySize(errors), 2);
        const cJSON *tess = cJSON_GetArrayItem(errors, 0), *truth = cJSON_GetArrayItem(errors, 1);
        assert_string_equal(at(tess, "reference")->valuestring, "tessellated");
        assert_string_equal(at(truth, "reference")->valuestring, "ground_truth");
        assert_true(at(tess, "coverage_error_pct")->valuedouble == 0);
        assert_int_equal(at(tess, "holes")->valueint, 0);
        assert_true(at(tess, "depth_max")->valuedouble < 1e-5);
        double cov = at(truth, "coverage_error_pct")->valuedouble;
        if (worst_frame < 0 || cov > worst_cov) {
            worst_cov = cov;
            worst_frame = at(fr, "frame")->valueint;
        }
    }
    assert_non_null(at(at(at(stats, "totals"), "seconds"), "reference"));
    assert_non_null(at(at(at(stats, "medians"), "seconds"), "reference"));
    const cJSON *truth = at(at(stats, "error"), "ground_truth");
    assert_int_equal(at(truth, "frames")->valueint, 3);
    const cJSON *w = at(at(truth, "worst"), "coverage_error_pct");
    assert_int_equal(at(w, "frame")->valueint, worst_frame);
    assert_true(at(w, "value")->valuedouble == worst_cov);
    assert_int_equal(at(at(at(stats, "error"), "tessellated"), "frames")->valueint, 3);
    cJSON_Delete(stats);

    snprintf(path, sizeof path, "/v1/jobs/%s/frames/1/stats", JOB);
    cJSON *frame = get_json(path);
    assert_int_equal(cJSON_GetArraySize(at(frame, "error")), 2);
    cJSON_Delete(frame);
}

/* Runs the client with args; its standard output (malloc'ed). */
static char *client(const char *args, int *exit_code)
{
    char cmd[4096], out[600];
    snprintf(out, sizeof out, "%s/client.out", fx_tmp);
    snprintf(cmd, sizeof cmd, "'%s/microray' --server %s %s >'%s' 2>&1", fx_build_dir, D.base, args,
             out);
    int st = system(cmd);
    *exit_code = WIFEXITED(st) ? WEXITSTATUS(st) : -1;
    char *text = fx_slurp(out, NULL);
    assert_non_null(text);
    return text;
}

static void test_client_table(void **state)
{
    (void)state;
    char args[256];
    int code;
    snprintf(args, sizeof args, "status --errors %s", JOB);
    char *out = client(args, &code);
    print_message("%s", out);
    assert_int_equal(code, 0);
    /* the header, a row per frame and reference, the medians, the worst */
    assert_non_null(strstr(out, "frame  total s  ref s  reference"));
    assert_non_null(strstr(out, "cover %"));
    int tess = 0, truth = 0;
    for (const char *p = out; (p = strstr(p, "tessellated ")); p++)
        tess++;
    for (const char *p = out; (p = strstr(p, "ground_truth ")); p++)
        truth++;
    assert_int_equal(tess, 3 + 2); /* three frames, the median and worst rows */
    assert_int_equal(truth, 3 + 2);
    assert_non_null(strstr(out, "\nmedian "));
    assert_non_null(strstr(out, "\nworst "));
    assert_non_null(strstr(out, "\n  at frame "));
    /* frame 0's row: its index, then its two figures' rows */
    const char *row = strstr(out, "\n    0  ");
    assert_non_null(row);
    free(out);

    snprintf(args, sizeof args, "status --errors --json %s", JOB);
    out = client(args, &code);
    assert_int_equal(code, 0);
    cJSON *doc = cJSON_Parse(out);
    assert_non_null(doc);
    assert_non_null(cJSON_GetObjectItem(doc, "error"));
    cJSON_Delete(doc);
    free(out);

    snprintf(args, sizeof args, "status --errors %s", PLAIN);
    out = client(args, &code);
    assert_int_equal(code, 0);
    assert_non_null(strstr(out, "no reference passes"));
    free(out);
}

static void test_bad_reference(void **state)
{
    (void)state;
    char *job = fx_small_job(1, 48, "\"reference\":\"yes\",");
    http_result r = http(&D, "POST", "/v1/jobs", job, strlen(job), NULL);
    free(job);
    assert_int_equal(r.status, 422);
    cJSON *j = cJSON_Parse(r.body);
    assert_non_null(j);
    assert_string_equal(cJSON_GetObjectItem(j, "pointer")->valuestring, "/reference");
    cJSON_Delete(j);
    http_free(&r);
}

static int setup(void **state)
{
    (void)state;
    fx_init_dirs();
    curl_global_init(CURL_GLOBAL_DEFAULT);
    daemon_start(&D, "data");
    fx_submit(&D, DMM_JOB, JOB);
    char *plain = fx_small_job(1, 64, NULL);
    fx_submit(&D, plain, PLAIN);
    free(plain);
    const char *ids[2] = {JOB, PLAIN};
    for (int i = 0; i < 2; i++) {
        cJSON *j = fx_wait_job(&D, ids[i], 300);
        if (strcmp(cJSON_GetObjectItem(j, "state")->valuestring, "succeeded") != 0) {
            char *text = cJSON_Print(j);
            fprintf(stderr, "job %s did not succeed: %s\n", ids[i], text);
            free(text);
            cJSON_Delete(j);
            return -1;
        }
        cJSON_Delete(j);
    }
    return 0;
}

static int teardown(void **state)
{
    (void)state;
    int st = daemon_stop(&D, SIGTERM);
    curl_global_cleanup();
    char cmd[300];
    snprintf(cmd, sizeof cmd, "rm -rf %s", fx_tmp);
    return system(cmd) == 0 && st == 0 ? 0 : -1;
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_http_stats),
        cmocka_unit_test(test_client_table),
        cmocka_unit_test(test_bad_reference),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
