/*
 * test_dmm_accuracy.c - issue 4's accuracy contract, end to end through the
 * real binary: for every example job with a dmm object in a
 * tessellation-free mode (base or interpolated), render every frame as the
 * example asks and again with those objects switched to mode "tessellated"
 * with the same deformation (the exact reference: the same micro-triangles
 * as Embree triangles), read both back with OpenEXR and compare per frame.
 *
 * Tolerances. The two renders hit bit-identical micro-vertices (one
 * evaluation function); only the ray/triangle arithmetic differs (Embree's
 * intersector vs the watertight test), so depths agree to float rounding of
 * t: well below the bound of 1e-5 of the scene diagonal, which is
 * asserted. Coverage must be identical: a pixel centre hit by one and missed
 * by the other would be a hole in the bounds or the traversal. The one
 * exception float arithmetic allows is a ray through a silhouette micro-edge
 * exactly, which both intersectors may decide differently; at most
 * MAX_EDGE_PIXELS such pixels per frame are tolerated and reported.
 *
 * Renders at a quarter of the example's resolution and 1 sample to keep the
 * test short; every frame of every example still runs.
 *
 * Needs MR_SOURCE_DIR and MR_BUILD_DIR (scripts/run-tests.sh sets both).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <cJSON.h>
#include <dirent.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>
#include <unistd.h>

#include "files.h"
#include "job_json.h"
#include "render/compare.h"
#include "render/exr.h"

#define MAX_EDGE_PIXELS 2
#define DEPTH_BOUND 1e-5

static char src_dir[2048], bin[2200], tmp_dir[256];

static void write_json(const char *path, const cJSON *j)
{
    char *text = cJSON_Print(j);
    FILE *f = fopen(path, "wb");
    assert_non_null(f);
    fputs(text, f);
    fclose(f);
    free(text);
}

static void render(const char *job, const char *out)
{
    char cmd[8192];
    snprintf(cmd, sizeof cmd, "cd '%s' && '%s' render '%s' --out '%s' --quiet", src_dir, bin, job,
             out);
    int st = system(cmd);
    assert_true(WIFEXITED(st));
    assert_int_equal(WEXITSTATUS(st), 0);
}

/* Switches every tessellation-free dmm object of job to its tessellation;
 * returns how many it switched. */
static int to_reference(cJSON *job)
{
    int switched = 0;
    cJSON *o;
    cJSON_ArrayForEach(o, cJSON_GetObjectItem(job, "objects"))
    {
        cJSON *dmm = cJSON_GetObjectItem(o, "dmm"), *mode = cJSON_GetObjectItem(dmm, "mode");
        if (!cJSON_IsString(mode) || !strcmp(mode->valuestring, "tessellated"))
            continue;
        const char *deform = !strcmp(mode->valuestring, "interpolated") ? "interpolated" : "base";
        cJSON_DeleteItemFromObject(dmm, "deformation");
        cJSON_AddStringToObject(dmm, "deformation", deform);
        cJSON_ReplaceItemInObject(dmm, "mode", cJSON_CreateString("tessellated"));
        switched++;
    }
    return switched;
}

static void shrink(cJSON *job)
{
    cJSON *out = cJSON_GetObjectItem(job, "output");
    int w = cJSON_GetObjectItem(out, "width")->valueint,
        h = cJSON_GetObjectItem(out, "height")->valueint;
    cJSON_ReplaceItemInObject(out, "width", cJSON_CreateNumber(w / 4 > 16 ? w / 4 : 16));
    cJSON_ReplaceItemInObject(out, "height", cJSON_CreateNumber(h / 4 > 16 ? h / 4 : 16));
    cJSON_DeleteItemFromObject(out, "samples");
    cJSON_AddNumberToObject(out, "samples", 1);
}

static void check_example(const char *name, int *checked)
{
    char path[4096];
    snprintf(path, sizeof path, "%s/examples/%s", src_dir, name);
    char *text = NULL;
    size_t len = 0;
    mr_error err = {0};
    if (mr_file_read(path, MR_JOB_MAX_BYTES, &text, &len, &err) != MR_OK)
        fail_msg("%s: %s", path, err.msg);
    cJSON *job = cJSON_Parse(text);
    free(text);
    assert_non_null(job);
    shrink(job);
    char a_job[600], b_job[600], a_out[4200], b_out[4200];
    snprintf(a_job, sizeof a_job, "%s/free.json", tmp_dir);
    snprintf(b_job, sizeof b_job, "%s/reference.json", tmp_dir);
    snprintf(a_out, sizeof a_out, "%s/free-%s", tmp_dir, name);
    snprintf(b_out, sizeof b_out, "%s/reference-%s", tmp_dir, name);
    write_json(a_job, job);
    int switched = to_reference(job);
    write_json(b_job, job);
    cJSON_Delete(job);
    if (switched == 0)
        return;
    render(a_job, a_out);
    render(b_job, b_out);
    int frames = 0;
    size_t edge_pixels = 0;
    double worst_depth = 0;
    for (int f = 0;; f++) {
        char fa[4300], fb[4300];
        snprintf(fa, sizeof fa, "%s/%04d.exr", a_out, f);
        snprintf(fb, sizeof fb, "%s/%04d.exr", b_out, f);
        if (access(fb, F_OK) != 0)
            break;
        mr_film *a = NULL, *b = NULL;
        mr_exr_meta ma, mb;
        assert_int_equal(mr_exr_read_file(fa, &a, &ma, &err), MR_OK);
        assert_int_equal(mr_exr_read_file(fb, &b, &mb, &err), MR_OK);
        mr_compare_result c;
        /* the tessellation's diagonal: the tighter (user-geometry boxes are
         * conservative, so the tessellation-free scene box is larger) */
        assert_int_equal(mr_film_compare(b, a, mb.scene_diagonal, &c, &err), MR_OK);
        if (c.hit_one > MAX_EDGE_PIXELS || !(c.depth_max < DEPTH_BOUND))
            fail_msg("%s frame %d: %zu pixels hit by one render only, depth max %.3g of the "
                     "diagonal (bounds %d, %.0e)",
                     name, f, c.hit_one, c.depth_max, MAX_EDGE_PIXELS, DEPTH_BOUND);
        assert_true(c.hit_both > 0);
        edge_pixels += c.hit_one;
        worst_depth = c.depth_max > worst_depth ? c.depth_max : worst_depth;
        mr_film_free(a);
        mr_film_free(b);
        frames++;
    }
    assert_true(frames > 0);
    printf("%s: %d frames, tessellation-free vs tessellated: %zu edge pixels in all, depth max "
           "%.2e of the diagonal\n",
           name, frames, edge_pixels, worst_depth);
    (*checked)++;
}

static void test_examples_match_their_tessellation(void **state)
{
    (void)state;
    char dir_path[4096];
    snprintf(dir_path, sizeof dir_path, "%s/examples", src_dir);
    DIR *d = opendir(dir_path);
    assert_non_null(d);
    struct dirent *e;
    int checked = 0;
    while ((e = readdir(d)))
        if (strstr(e->d_name, ".json"))
            check_example(e->d_name, &checked);
    closedir(d);
    /* the examples include a static and a skinned tessellation-free dmm */
    assert_true(checked >= 2);
}

int main(void)
{
    const char *s = getenv("MR_SOURCE_DIR"), *b = getenv("MR_BUILD_DIR");
    snprintf(src_dir, sizeof src_dir, "%s", s ? s : ".");
    snprintf(bin, sizeof bin, "%s/microrayd", b ? b : "build");
    if (bin[0] != '/') {
        char cwd[1024];
        if (getcwd(cwd, sizeof cwd))
            snprintf(bin, sizeof bin, "%s/%s/microrayd", cwd, b ? b : "build");
    }
    snprintf(tmp_dir, sizeof tmp_dir, "/tmp/mr-dmm-accuracy-XXXXXX");
    if (!mkdtemp(tmp_dir))
        return 1;
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_examples_match_their_tessellation),
    };
    int rc = cmocka_run_group_tests(tests, NULL, NULL);
    char cmd[512];
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", tmp_dir);
    if (system(cmd) != 0)
        rc = rc ? rc : 1;
    return rc;
}
