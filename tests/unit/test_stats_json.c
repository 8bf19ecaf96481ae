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
 *
 * Also: the field table itself (groups consecutive, names unique, every
 * member of mr_frame_stats but the extras covered exactly once), reading a
 * frame back from its text, extras (written after the table's fields, in
 * stats.json too; bad, taken, repeated and surplus names refused), and
 * schemas/openapi.yaml's frame-stats schemas being what the table gives
 * (`make openapi` writes them).
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
#include "stats_openapi.h"
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
    "\t\t\t\t\"derive\":\t0,\n"
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
    "\t\t\t\"scene_diagonal\":\t0.10000000149011612,\n"
    "\t\t\t\"speckle_pct\":\t33.333333333333336\n"
    "\t\t}, {\n"
    "\t\t\t\"frame\":\t2,\n"
    "\t\t\t\"time\":\t2,\n"
    "\t\t\t\"file\":\t\"0002.exr\",\n"
    "\t\t\t\"seconds\":\t{\n"
    "\t\t\t\t\"load\":\t0,\n"
    "\t\t\t\t\"derive\":\t0,\n"
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
    "\t\t\t\"speckle_pct\":\t0,\n"
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
    "\t\t\t\"derive\":\t0,\n"
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
    "\t\t\t\"derive\":\t0,\n"
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
    char *s = NULL;
    mr_error err = {0};
    assert_int_equal(mr_stats_to_json(&job, &stats, 1, &s, &err), MR_OK);
    expect_text(s, JOB_FROM_1);
    free(s);
}

static size_t type_size(mr_stat_type t)
{
    switch (t) {
    case MR_STAT_INT: return sizeof(int);
    case MR_STAT_U32: return sizeof(uint32_t);
    case MR_STAT_U64: return sizeof(uint64_t);
    case MR_STAT_F32: return sizeof(float);
    case MR_STAT_F64: return sizeof(double);
    case MR_STAT_BVH: return sizeof(mr_bvh_update);
    default: return 0; /* derived: stored nowhere */
    }
}

static int by_offset(const void *a, const void *b)
{
    const mr_stat_field *x = *(const mr_stat_field *const *)a, *y = *(const mr_stat_field *const *)b;
    return (x->offset > y->offset) - (x->offset < y->offset);
}

static void test_field_table(void **state)
{
    (void)state;
    const mr_stat_field *stored[64];
    size_t n = 0;
    for (size_t i = 0; i < mr_frame_stat_field_count; i++) {
        const mr_stat_field *f = &mr_frame_stat_fields[i];
        assert_non_null(f->name);
        assert_non_null(f->unit);
        assert_non_null(f->description);
        /* a group's fields are consecutive: the writer opens each group once */
        for (size_t j = 0; j + 1 < i; j++)
            if (f->group && mr_frame_stat_fields[j].group == f->group)
                assert_ptr_equal(mr_frame_stat_fields[i - 1].group, f->group);
        for (size_t j = 0; j < i; j++)
            if (mr_frame_stat_fields[j].group == f->group && !strcmp(mr_frame_stat_fields[j].name, f->name))
                fail_msg("field '%s' appears twice in its group", f->name);
        if (type_size(f->type)) {
            assert_true(n < 64);
            stored[n++] = f;
        }
    }
    /* Every member before the extras is one field's, exactly: sorted by
     * offset, each starts where the last one ended (up to padding). */
    qsort(stored, n, sizeof *stored, by_offset);
    size_t end = 0;
    for (size_t i = 0; i < n; i++) {
        if (stored[i]->offset < end || stored[i]->offset >= end + 8)
            fail_msg("field '%s' at byte %zu: the member before it ends at %zu (a member without a "
                     "table row, or two rows on one member)", stored[i]->name, stored[i]->offset, end);
        end = stored[i]->offset + type_size(stored[i]->type);
    }
    assert_true(end <= offsetof(mr_frame_stats, extra_count) &&
                end + 8 > offsetof(mr_frame_stats, extra_count));

    /* the same for an error entry: every member of mr_frame_error one row's */
    n = 0;
    for (size_t i = 0; i < mr_frame_error_field_count; i++) {
        const mr_stat_field *f = &mr_frame_error_fields[i];
        assert_null(f->group);
        for (size_t j = 0; j < i; j++)
            assert_string_not_equal(mr_frame_error_fields[j].name, f->name);
        assert_true(n < 64);
        stored[n++] = f;
    }
    qsort(stored, n, sizeof *stored, by_offset);
    end = 0;
    for (size_t i = 0; i < n; i++) {
        size_t size = stored[i]->type == MR_STAT_REFERENCE ? sizeof(mr_reference_type)
                                                           : type_size(stored[i]->type);
        if (stored[i]->offset < end || stored[i]->offset >= end + 8)
            fail_msg("error field '%s' at byte %zu: the member before it ends at %zu",
                     stored[i]->name, stored[i]->offset, end);
        end = stored[i]->offset + size;
    }
    assert_true(end <= sizeof(mr_frame_error) && end + 8 > sizeof(mr_frame_error));
}

static void test_read_back(void **state)
{
    (void)state;
    static const char *const text[] = {FRAME0, FRAME1, FRAME2};
    for (int i = 0; i < 3; i++) {
        cJSON *o = cJSON_Parse(text[i]);
        assert_non_null(o);
        mr_frame_stats want = frame_fixture(i), got;
        mr_frame_stats_from_json(o, (size_t)i, &got);
        cJSON_Delete(o);
        for (size_t k = 0; k < mr_frame_stat_field_count; k++) {
            const mr_stat_field *f = &mr_frame_stat_fields[k];
            if (mr_frame_stat_number(&got, f) != mr_frame_stat_number(&want, f))
                fail_msg("frame %d: %s read back as %.17g, written as %.17g", i, f->name,
                         mr_frame_stat_number(&got, f), mr_frame_stat_number(&want, f));
        }
        char *again = mr_frame_stats_json(&got);
        expect_text(again, text[i]);
        free(again);
    }
}

static void test_extras(void **state)
{
    (void)state;
    mr_frame_stats f = frame_fixture(0);
    mr_error err = {0};
    assert_int_equal(mr_frame_stats_add_extra(&f, "simulate_s", "s", 0.02, &err), MR_OK);
    assert_int_equal(mr_frame_stats_add_extra(&f, "springs", "count", 1200, &err), MR_OK);
    /* names the frame object already has, twice the same, not [a-z0-9_]+ */
    static const char *const bad[] = {"rays", "seconds", "cache", "simulate_s", "", "Load", "a-b", NULL};
    for (int i = 0; i < 8; i++)
        assert_int_equal(mr_frame_stats_add_extra(&f, bad[i], "s", 1, &err), MR_ERR_INVALID);
    assert_int_equal(f.extra_count, 2);

    char want[sizeof FRAME0 + 64];
    snprintf(want, sizeof want, "%.*s,\"simulate_s\":0.02,\"springs\":1200}", (int)strlen(FRAME0) - 1, FRAME0);
    char *s = mr_frame_stats_json(&f);
    expect_text(s, want);
    free(s);

    /* stats.json: the frame's entry carries them; totals and medians do not */
    mr_frame_stats frames[2] = {f, frame_fixture(1)};
    mr_job job = job_fixture();
    mr_job_stats stats = {.frame_count = 2, .frames = frames, .threads = 2};
    assert_int_equal(mr_stats_to_json(&job, &stats, 0, &s, &err), MR_OK);
    cJSON *doc = cJSON_Parse(s);
    free(s);
    assert_non_null(doc);
    cJSON *f0 = cJSON_GetArrayItem(cJSON_GetObjectItem(doc, "frames"), 0);
    assert_true(cJSON_GetObjectItem(f0, "simulate_s")->valuedouble == 0.02);
    assert_true(cJSON_GetObjectItem(f0, "springs")->valuedouble == 1200);
    assert_null(cJSON_GetObjectItem(cJSON_GetArrayItem(cJSON_GetObjectItem(doc, "frames"), 1), "springs"));
    cJSON_Delete(doc);

    static char names[MR_FRAME_EXTRAS_MAX + 1][16]; /* borrowed by the stats: static */
    for (int i = 0; i <= MR_FRAME_EXTRAS_MAX; i++)
        snprintf(names[i], sizeof names[i], "e%d", i);
    mr_frame_stats full = frame_fixture(1);
    for (int i = 0; i < MR_FRAME_EXTRAS_MAX; i++)
        assert_int_equal(mr_frame_stats_add_extra(&full, names[i], "", i, &err), MR_OK);
    assert_int_equal(mr_frame_stats_add_extra(&full, names[MR_FRAME_EXTRAS_MAX], "", 9, &err), MR_ERR_LIMIT);
}

/* A frame of a job with "reference": seconds.reference (optional: only
 * where it is non-zero) and one error entry per reference pass, written
 * after the table's fields and before the extras, read back, and the
 * job's "error" summary: medians and worst frames per reference. */
static mr_frame_stats reference_fixture(int i)
{
    mr_frame_stats f = frame_fixture(i);
    f.reference_s = 0.5 + i;
    f.error_count = 2;
    f.errors[0] = (mr_frame_error){MR_REFERENCE_TESSELLATED, 0, 0, 1e-7 * i, 2.5e-7, 0.125,
                                   MR_PSNR_IDENTICAL, 0.25, 0};
    f.errors[1] = (mr_frame_error){MR_REFERENCE_GROUND_TRUTH, 1.0 + i, (uint64_t)(3 * i), 0.001,
                                   0.01 * (3 - i), 2.5, 40.0 - i, 1.0 / 3.0, 0.5 * i};
    f.lod_count = 2;
    f.lod[0] = (mr_object_lod){0, 7, 0.75};
    f.lod[1] = (mr_object_lod){3, 0, 0};
    return f;
}

static void test_reference_errors(void **state)
{
    (void)state;
    mr_frame_stats f = reference_fixture(1);
    mr_error err = {0};
    assert_int_equal(mr_frame_stats_add_extra(&f, "simulate_s", "s", 0.02, &err), MR_OK);
    /* "error" and "lod" are the entries' keys: no extra may take them */
    assert_int_equal(mr_frame_stats_add_extra(&f, "error", "", 1, &err), MR_ERR_INVALID);
    assert_int_equal(mr_frame_stats_add_extra(&f, "lod", "", 1, &err), MR_ERR_INVALID);
    char *s = mr_frame_stats_json(&f);
    static const char want[] =
        "{\"frame\":1,\"time\":0.75,\"file\":\"0001.exr\",\"seconds\":{\"load\":0,\"derive\":0,"
        "\"pose\":0.33333333333333331,\"bvh\":0.1,\"trace\":2.5e-07,\"encode\":12345.678,\"total\":0.001,"
        "\"reference\":1.5},"
        "\"bvh\":\"refit\",\"rays\":1099511627777,\"mrays_per_s\":0,\"triangles\":4294967296,"
        "\"bytes\":{\"geometry\":1,\"bvh\":0,\"peak_rss\":123456789012},"
        "\"scene_diagonal\":0.10000000149011612,\"speckle_pct\":33.333333333333336,"
        "\"error\":[{\"reference\":\"tessellated\",\"coverage_error_pct\":0,\"holes\":0,"
        "\"depth_rmse\":1e-07,\"depth_max\":2.5e-07,\"normal_mean_deg\":0.125,\"psnr_rgb_db\":999,"
        "\"speckle_pct\":0.25,\"surface_px\":0},{\"reference\":\"ground_truth\",\"coverage_error_pct\":2,"
        "\"holes\":3,\"depth_rmse\":0.001,\"depth_max\":0.02,\"normal_mean_deg\":2.5,\"psnr_rgb_db\":39,"
        "\"speckle_pct\":0.33333333333333331,\"surface_px\":0.5}],"
        "\"lod\":[{\"object\":0,\"level\":7,\"error_px\":0.75},{\"object\":3,\"level\":0,"
        "\"error_px\":0}],\"simulate_s\":0.02}";
    expect_text(s, want);

    /* read back: the table's fields and the entries */
    cJSON *o = cJSON_Parse(s);
    free(s);
    assert_non_null(o);
    mr_frame_stats got;
    mr_frame_stats_from_json(o, 1, &got);
    cJSON_Delete(o);
    assert_true(got.reference_s == 1.5);
    assert_int_equal(got.error_count, 2);
    assert_int_equal(got.lod_count, 2);
    assert_memory_equal(got.lod, f.lod, sizeof f.lod[0] * 2);
    for (int k = 0; k < 2; k++)
        for (size_t i = 0; i < mr_frame_error_field_count; i++) {
            const mr_stat_field *fd = &mr_frame_error_fields[i];
            if (mr_frame_error_number(&got.errors[k], fd) != mr_frame_error_number(&f.errors[k], fd))
                fail_msg("entry %d: %s read back as %.17g", k, fd->name,
                         mr_frame_error_number(&got.errors[k], fd));
        }

    /* the job: seconds.reference in totals and medians, and the summary;
     * frame 0 without a reference pass counts in neither */
    mr_frame_stats frames[4] = {frame_fixture(0), reference_fixture(1), reference_fixture(2),
                                reference_fixture(3)};
    frames[3].error_count = 1; /* frame 3: no ground truth */
    mr_job job = job_fixture();
    mr_job_stats stats = {.frame_count = 4, .frames = frames, .threads = 2};
    assert_int_equal(mr_stats_to_json(&job, &stats, 0, &s, &err), MR_OK);
    cJSON *doc = cJSON_Parse(s);
    free(s);
    assert_non_null(doc);
    assert_null(cJSON_GetObjectItem(cJSON_GetObjectItem(cJSON_GetArrayItem(cJSON_GetObjectItem(doc, "frames"), 0), "seconds"), "reference"));
    assert_null(cJSON_GetObjectItem(cJSON_GetArrayItem(cJSON_GetObjectItem(doc, "frames"), 0), "error"));
    cJSON *tot = cJSON_GetObjectItem(cJSON_GetObjectItem(doc, "totals"), "seconds");
    cJSON *med = cJSON_GetObjectItem(cJSON_GetObjectItem(doc, "medians"), "seconds");
    assert_true(cJSON_GetObjectItem(tot, "reference")->valuedouble == 1.5 + 2.5 + 3.5);
    assert_true(cJSON_GetObjectItem(med, "reference")->valuedouble == 2.0); /* of 0, 1.5, 2.5, 3.5 */
    cJSON *errors = cJSON_GetObjectItem(doc, "error");
    cJSON *tess = cJSON_GetObjectItem(errors, "tessellated"), *truth = cJSON_GetObjectItem(errors, "ground_truth");
    assert_int_equal(cJSON_GetObjectItem(tess, "frames")->valueint, 3);
    assert_int_equal(cJSON_GetObjectItem(truth, "frames")->valueint, 2);
    cJSON *tm = cJSON_GetObjectItem(tess, "medians"), *gm = cJSON_GetObjectItem(truth, "medians"),
          *gw = cJSON_GetObjectItem(truth, "worst");
    assert_true(cJSON_GetObjectItem(tm, "depth_rmse")->valuedouble == 2e-7);
    assert_true(cJSON_GetObjectItem(gm, "coverage_error_pct")->valuedouble == 2.5); /* of 2, 3 */
    /* worst: the highest, psnr the lowest; the first frame of equals */
    cJSON *w = cJSON_GetObjectItem(gw, "coverage_error_pct");
    assert_int_equal(cJSON_GetObjectItem(w, "frame")->valueint, 2);
    assert_true(cJSON_GetObjectItem(w, "value")->valuedouble == 3.0);
    w = cJSON_GetObjectItem(gw, "depth_max");
    assert_int_equal(cJSON_GetObjectItem(w, "frame")->valueint, 1);
    w = cJSON_GetObjectItem(gw, "psnr_rgb_db");
    assert_int_equal(cJSON_GetObjectItem(w, "frame")->valueint, 2);
    assert_true(cJSON_GetObjectItem(w, "value")->valuedouble == 38.0);
    w = cJSON_GetObjectItem(gw, "speckle_pct");
    assert_int_equal(cJSON_GetObjectItem(w, "frame")->valueint, 1);
    cJSON_Delete(doc);

    /* without any reference pass the job has no "error" and no seconds.reference */
    mr_frame_stats plain[2] = {frame_fixture(0), frame_fixture(1)};
    stats = (mr_job_stats){.frame_count = 2, .frames = plain, .threads = 2};
    assert_int_equal(mr_stats_to_json(&job, &stats, 0, &s, &err), MR_OK);
    assert_null(strstr(s, "\"error\""));
    assert_null(strstr(s, "\"reference\""));
    free(s);
}

static void test_openapi_current(void **state)
{
    (void)state;
    const char *src = getenv("MR_SOURCE_DIR");
    char path[4096];
    snprintf(path, sizeof path, "%s/schemas/openapi.yaml", src ? src : ".");
    bool stale = true;
    mr_error err = {0};
    if (mr_stats_openapi_update(path, false, &stale, &err) < 0)
        fail_msg("%s", err.msg);
    if (stale)
        fail_msg("%s: the frame-stats schemas differ from the field table in core/render/frame_stats.c: "
                 "run `make openapi`", path);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_frame_documents),
        cmocka_unit_test(test_job_document),
        cmocka_unit_test(test_field_table),
        cmocka_unit_test(test_read_back),
        cmocka_unit_test(test_extras),
        cmocka_unit_test(test_reference_errors),
        cmocka_unit_test(test_openapi_current),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
