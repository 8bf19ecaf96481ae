/*
 * test_stats_json.c - the per-frame and per-job statistics documents
 * (server/stats_json.c): stats.json, the stored per-frame object (which is
 * also the HTTP frame stats and the "frame" event) and the frames the HTTP
 * job stats rebuild from stored text.
 *
 * The documents are compared byte for byte with texts recorded before the
 * frame-stats fields became one table, so a change in the order of fields,
 * their nesting or how numbers print shows at once. Values were picked to
 * print differently under any careless conversion: 0.1 (not a binary
 * fraction), 1/3 (17 significant digits), 2^40 + 1 rays (beyond 32 bits)
 * and a float diagonal (printed as the double it widens to).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "stats_json.h"
#include "../support/stats_fixture.h"

/* ---- recorded documents --------------------------------------------------- */

static const char JOB_FROM_1[] =
    "{\n"
    "\t\"job\":\t\"golden \\\"walk\\\"\",\n"
    "\t\"software\":\t\"microray " MR_VERSION_STRING "\",\n"
    "\t\"threads\":\t2,\n"
    "\t\"width\":\t192,\n"
    "\t\"height\":\t108,\n"
    "\t\"samples\":\t3,\n"
    "\t\"frames_total\":\t4,\n"
    "\t\"frames_done\":\t2,\n"
    "\t\"frames\":\t[{\n"
    "\t\t\t\"frame\":\t1,\n"
    "\t\t\t\"time\":\t0.75,\n"
    "\t\t\t\"file\":\t\"0001.exr\",\n"
    "\t\t\t\"seconds\":\t{\n"
    "\t\t\t\t\"load\":\t0,\n"
    "\t\t\t\t\"pose\":\t0.33333333333333331,\n"
    "\t\t\t\t\"bvh\":\t0.1,\n"
    "\t\t\t\t\"trace\":\t2.5e-07,\n"
    "\t\t\t\t\"encode\":\t12345.678,\n"
    "\t\t\t\t\"total\":\t0.001\n"
    "\t\t\t},\n"
    "\t\t\t\"bvh\":\t\"refit\",\n"
    "\t\t\t\"rays\":\t1099511627777,\n"
    "\t\t\t\"mrays_per_s\":\t0,\n"
    "\t\t\t\"triangles\":\t4294967296,\n"
    "\t\t\t\"bytes\":\t{\n"
    "\t\t\t\t\"geometry\":\t1,\n"
    "\t\t\t\t\"bvh\":\t0,\n"
    "\t\t\t\t\"peak_rss\":\t123456789012\n"
    "\t\t\t},\n"
    "\t\t\t\"scene_diagonal\":\t0.10000000149011612\n"
    "\t\t}, {\n"
    "\t\t\t\"frame\":\t2,\n"
    "\t\t\t\"time\":\t2,\n"
    "\t\t\t\"file\":\t\"0002.exr\",\n"
    "\t\t\t\"seconds\":\t{\n"
    "\t\t\t\t\"load\":\t0,\n"
    "\t\t\t\t\"pose\":\t0,\n"
    "\t\t\t\t\"bvh\":\t0,\n"
    "\t\t\t\t\"trace\":\t0,\n"
    "\t\t\t\t\"encode\":\t0,\n"
    "\t\t\t\t\"total\":\t0\n"
    "\t\t\t},\n"
    "\t\t\t\"bvh\":\t\"none\",\n"
    "\t\t\t\"rays\":\t0,\n"
    "\t\t\t\"mrays_per_s\":\t0,\n"
    "\t\t\t\"triangles\":\t0,\n"
    "\t\t\t\"bytes\":\t{\n"
    "\t\t\t\t\"geometry\":\t0,\n"
    "\t\t\t\t\"bvh\":\t0,\n"
    "\t\t\t\t\"peak_rss\":\t0\n"
    "\t\t\t},\n"
    "\t\t\t\"scene_diagonal\":\t0,\n"
    "\t\t\t\"cache\":\t{\n"
    "\t\t\t\t\"result\":\t\"hit\",\n"
    "\t\t\t\t\"assets_cached\":\t3,\n"
    "\t\t\t\t\"assets_loaded\":\t0,\n"
    "\t\t\t\t\"saved_s\":\t2\n"
    "\t\t\t}\n"
    "\t\t}],\n"
    "\t\"totals\":\t{\n"
    "\t\t\"seconds\":\t{\n"
    "\t\t\t\"load\":\t0,\n"
    "\t\t\t\"pose\":\t0.33333333333333331,\n"
    "\t\t\t\"bvh\":\t0.1,\n"
    "\t\t\t\"trace\":\t2.5e-07,\n"
    "\t\t\t\"encode\":\t12345.678,\n"
    "\t\t\t\"total\":\t0.001\n"
    "\t\t},\n"
    "\t\t\"rays\":\t1099511627777,\n"
    "\t\t\"peak_rss_bytes\":\t123456789012\n"
    "\t},\n"
    "\t\"medians\":\t{\n"
    "\t\t\"seconds\":\t{\n"
    "\t\t\t\"load\":\t0,\n"
    "\t\t\t\"pose\":\t0.16666666666666666,\n"
    "\t\t\t\"bvh\":\t0.05,\n"
    "\t\t\t\"trace\":\t1.25e-07,\n"
    "\t\t\t\"encode\":\t6172.839,\n"
    "\t\t\t\"total\":\t0.0005\n"
    "\t\t},\n"
    "\t\t\"mrays_per_s\":\t0\n"
    "\t}\n"
    "}";

/* ---- tests ---------------------------------------------------------------- */

static void test_frame_documents(void **state)
{
    (void)state;
    static const char *const want[] = {FRAME0, FRAME1, FRAME2};
    for (int i = 0; i < 3; i++) {
        mr_frame_stats f = frame_fixture(i);
        char *s = mr_frame_stats_json(&f);
        expect_text(s, want[i]);
        free(s);
    }
}

static void test_job_document(void **state)
{
    (void)state;
    mr_frame_stats frames[3] = {frame_fixture(0), frame_fixture(1), frame_fixture(2)};
    mr_job job = job_fixture();
    mr_job_stats stats = {.frame_count = 3, .frames = frames, .threads = 2};
    char *s = mr_stats_to_json(&job, &stats, 1);
    expect_text(s, JOB_FROM_1);
    free(s);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_frame_documents),
        cmocka_unit_test(test_job_document),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
