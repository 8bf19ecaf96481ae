/*
 * test_worker.c - the worker (server/worker.h) on real jobs, the real
 * importer and Embree: which JSON pointer an asset failure names. The
 * import reports the step that failed (cache.h mr_asset_stage) and the
 * worker points at the asset's "path" for the file, at its "refine" for the
 * refinement, whatever the messages say: here the file itself is called
 * "refine: ..." (relative to a temporary working directory), which a
 * worker matching the message text would take for a refine failure.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "job_json.h"
#include "worker.h"

static char tmp_dir[64], old_cwd[4096];

static int setup(void **state)
{
    (void)state;
    snprintf(tmp_dir, sizeof tmp_dir, "/tmp/mr-worker-XXXXXX");
    if (!mkdtemp(tmp_dir) || !getcwd(old_cwd, sizeof old_cwd))
        return -1;
    return chdir(tmp_dir);
}

static int teardown(void **state)
{
    (void)state;
    char cmd[128];
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", tmp_dir);
    return chdir(old_cwd) == 0 && system(cmd) == 0 ? 0 : -1;
}

static int no_frames(void *user, size_t index, const mr_film *film, mr_frame_stats *st,
                     mr_error *err)
{
    (void)user, (void)film, (void)st;
    return mr_error_set(err, MR_ERR_INVALID, "frame %zu: no frame should be rendered", index);
}

/* Runs a one-asset job (asset "m" at path, refined `rounds` times) that
 * must fail before any frame, and returns the worker's error. */
static mr_error run_job(const char *path, unsigned rounds)
{
    char json[1024];
    snprintf(json, sizeof json,
             "{\"assets\":{\"m\":{\"path\":\"%s\",\"refine\":{\"rounds\":%u}}},"
             "\"objects\":[{\"asset\":\"m\"}],"
             "\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0,3],\"target\":[0,0,0]}]},"
             "\"frames\":{\"times\":[0]},\"output\":{\"width\":8,\"height\":8}}",
             path, rounds);
    mr_job *job = NULL;
    mr_job_error jerr = {0};
    if (mr_job_parse(json, strlen(json), &job, &jerr) < 0)
        fail_msg("job: %s: %s", jerr.pointer, jerr.message);
    mr_device *dev = NULL;
    mr_error err = {0};
    if (mr_device_new(1, &dev, &err) < 0)
        fail_msg("device: %s", err.msg);
    mr_worker_io io = {.frame_done = no_frames};
    mr_job_stats stats;
    assert_true(mr_worker_run(dev, job, &io, &stats, &err) < 0);
    mr_job_stats_free(&stats);
    mr_device_free(dev);
    mr_job_free(job);
    return err;
}

static void write_grid(const char *path, int n)
{
    FILE *f = fopen(path, "w");
    assert_non_null(f);
    for (int y = 0; y <= n; y++)
        for (int x = 0; x <= n; x++)
            fprintf(f, "v %d %d 0\n", x, y);
    for (int y = 0; y < n; y++)
        for (int x = 0; x < n; x++) {
            int a = y * (n + 1) + x + 1, b = a + 1, d = a + n + 1, e = d + 1;
            fprintf(f, "f %d %d %d\nf %d %d %d\n", a, b, e, a, e, d);
        }
    assert_int_equal(fclose(f), 0);
}

/* A missing file is the asset's "path", even with "refine" set and a
 * message that starts with "refine: ". */
static void test_missing_file_points_at_path(void **state)
{
    (void)state;
    mr_error err = run_job("refine: missing.obj", 1);
    assert_int_equal(err.code, MR_ERR_IO);
    const char *want = "/assets/m/path: refine: missing.obj: ";
    if (strncmp(err.msg, want, strlen(want)) != 0)
        fail_msg("error '%s', want it to start with '%s'", err.msg, want);
}

/* A refinement over the triangle cap is the asset's "refine" (66248
 * triangles x 4^4 > MR_MAX_ASSET_TRIANGLES), named so once. */
static void test_refine_failure_points_at_refine(void **state)
{
    (void)state;
    write_grid("refine: grid.obj", 182);
    mr_error err = run_job("refine: grid.obj", 4);
    assert_int_equal(err.code, MR_ERR_LIMIT);
    const char *want = "/assets/m/refine: 4 rounds would turn the 66248 triangles of refine: grid.obj";
    if (strncmp(err.msg, want, strlen(want)) != 0)
        fail_msg("error '%s', want it to start with '%s'", err.msg, want);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_missing_file_points_at_path),
        cmocka_unit_test(test_refine_failure_points_at_refine),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
