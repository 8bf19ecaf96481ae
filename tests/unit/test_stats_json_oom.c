/*
 * test_stats_json_oom.c - stats.json and the per-frame statistics
 * (server/stats_json.h) when memory runs out: every allocation cJSON makes
 * for a document fails once, in turn (cJSON_InitHooks with the real
 * allocator behind a counter), and each attempt must either report the
 * failure (MR_ERR_NOMEM, no document) or produce exactly the document of a
 * run without failures: never one with frames or fields left out.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <cJSON.h>
#include <stdlib.h>
#include <string.h>

#include "stats_json.h"

/* The allocation to fail (1-based; 0: none) and how many were made. */
static size_t fail_at, allocations;

static void *counting_malloc(size_t size)
{
    if (++allocations == fail_at)
        return NULL;
    return malloc(size);
}

static void hooks_fail_at(size_t k)
{
    fail_at = k;
    allocations = 0;
    cJSON_Hooks h = {.malloc_fn = counting_malloc, .free_fn = free};
    cJSON_InitHooks(&h);
}

static void hooks_reset(void) { cJSON_InitHooks(NULL); }

/* Frames 1 and up ran reference passes: seconds.reference, error entries
 * (frame 2 one, the others two) and so the job's error summary. */
static mr_frame_stats frame(int i)
{
    mr_frame_stats f = {.frame = i, .time = 0.25 * i, .pose_s = 0.01 * i, .bvh_s = 0.02,
                        .bvh = i ? MR_BVH_REFIT : MR_BVH_BUILD, .trace_s = 0.1 + i,
                        .encode_s = 0.03, .total_s = 0.2 + i, .rays = 1000u + (uint64_t)i,
                        .mrays_per_s = 12.5, .triangles = 5126, .geometry_bytes = 4096,
                        .bvh_bytes = 8192, .peak_rss_bytes = 1u << 20, .scene_diagonal = 2.5f,
                        .assets_loaded = i == 0, .load_s = i == 0 ? 0.5 : 0};
    if (i > 0) {
        f.reference_s = 0.05 * i;
        f.error_count = i == 2 ? 1 : 2;
        f.errors[0] = (mr_frame_error){MR_REFERENCE_TESSELLATED, 0, 0, 1e-7, 2e-7, 0.01, 140, 0.5, 0};
        f.errors[1] = (mr_frame_error){MR_REFERENCE_GROUND_TRUTH, 0.5 * i, (uint64_t)i, 1e-3, 1e-2,
                                       3.0, 40 - i, 0.6, 1.5};
    }
    return f;
}

static void test_stats_out_of_memory(void **state)
{
    (void)state;
    mr_frame_stats frames[4];
    for (int i = 0; i < 4; i++)
        frames[i] = frame(i);
    mr_job job = {.name = "oom", .frame_count = 4,
                  .output = {.width = 64, .height = 36, .spp = 1}};
    mr_job_stats stats = {.frame_count = 4, .frames = frames, .threads = 2};
    mr_error err = {0};

    char *want = NULL;
    hooks_fail_at(0);
    assert_int_equal(mr_stats_to_json(&job, &stats, 0, &want, &err), MR_OK);
    size_t total = allocations;
    hooks_reset();
    assert_non_null(want);
    cJSON *doc = cJSON_Parse(want);
    assert_non_null(doc);
    assert_int_equal(cJSON_GetArraySize(cJSON_GetObjectItem(doc, "frames")), 4);
    assert_non_null(cJSON_GetObjectItem(doc, "error"));
    cJSON_Delete(doc);
    assert_true(total > 20);

    size_t reported = 0;
    for (size_t k = 1; k <= total; k++) {
        char *got = (char *)&err; /* must come back NULL on failure */
        err = (mr_error){0};
        hooks_fail_at(k);
        int rc = mr_stats_to_json(&job, &stats, 0, &got, &err);
        hooks_reset();
        if (rc == MR_OK) {
            if (!got || strcmp(got, want) != 0)
                fail_msg("allocation %zu of %zu failed, yet success was reported with a "
                         "different document:\n%s", k, total, got ? got : "(null)");
        } else {
            assert_int_equal(rc, MR_ERR_NOMEM);
            assert_int_equal(err.code, MR_ERR_NOMEM);
            assert_non_null(strstr(err.msg, "out of memory"));
            assert_null(got);
            reported++;
        }
        if (rc == MR_OK)
            free(got);
    }
    /* every allocation is needed for the document: each failure is reported */
    assert_int_equal(reported, total);
    free(want);
}

static void test_frame_stats_out_of_memory(void **state)
{
    (void)state;
    for (int i = 0; i < 2; i++) { /* with the cache group; with error entries */
        mr_frame_stats f = frame(i);
        hooks_fail_at(0);
        char *want = mr_frame_stats_json(&f);
        size_t total = allocations;
        hooks_reset();
        assert_non_null(want);
        assert_non_null(strstr(want, i ? "\"error\"" : "\"cache\""));
        for (size_t k = 1; k <= total; k++) {
            hooks_fail_at(k);
            char *got = mr_frame_stats_json(&f);
            hooks_reset();
            if (got && strcmp(got, want) != 0)
                fail_msg("allocation %zu of %zu failed, yet a frame came back: %s", k, total, got);
            free(got);
        }
        free(want);
    }
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_stats_out_of_memory),
        cmocka_unit_test(test_frame_stats_out_of_memory),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
