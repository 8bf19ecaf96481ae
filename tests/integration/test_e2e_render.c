/*
 * test_e2e_render.c - end to end through the real binary: `microrayd render`
 * on the real skinned example and on small jobs, frames read back with
 * OpenEXR, `microrayd compare`, and bad input answered with clear errors.
 *
 * Needs MR_SOURCE_DIR (repository root) and MR_BUILD_DIR (where microrayd
 * is); scripts/run-tests.sh sets both.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <cJSON.h>
#include <dirent.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <fcntl.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include "render/exr.h"
#include "../support/film_fixture.h"

static char src_dir[2048], bin[2200], tmp_dir[256];

static char *slurp(const char *path)
{
    FILE *f = fopen(path, "rb");
    if (!f)
        return NULL;
    fseek(f, 0, SEEK_END);
    long n = ftell(f);
    fseek(f, 0, SEEK_SET);
    char *s = malloc((size_t)n + 1);
    assert_non_null(s);
    size_t got = fread(s, 1, (size_t)n, f);
    s[got] = '\0';
    fclose(f);
    return s;
}

/* Runs `microrayd ARGS`, stdout/stderr into files in tmp_dir; returns the exit status. */
static int microrayd(const char *args, char **out, char **err)
{
    char cmd[8192], o[512], e[512];
    snprintf(o, sizeof o, "%s/stdout", tmp_dir);
    snprintf(e, sizeof e, "%s/stderr", tmp_dir);
    snprintf(cmd, sizeof cmd, "cd '%s' && '%s' %s >'%s' 2>'%s'", src_dir, bin, args, o, e);
    int st = system(cmd);
    assert_true(WIFEXITED(st));
    if (out)
        *out = slurp(o);
    if (err)
        *err = slurp(e);
    return WEXITSTATUS(st);
}

static mr_film *read_frame(const char *dir, int frame)
{
    char path[1024];
    snprintf(path, sizeof path, "%s/%04d.exr", dir, frame);
    mr_film *f = NULL;
    mr_error err = {0};
    if (mr_exr_read_file(path, &f, NULL, &err) < 0)
        fail_msg("%s", err.msg);
    return f;
}

static size_t count_lines_with(const char *text, const char *needle)
{
    size_t n = 0;
    for (const char *p = text; (p = strstr(p, needle)); p += strlen(needle))
        n++;
    return n;
}

static void test_skinned_example_renders_and_moves(void **state)
{
    (void)state;
    char args[1024], out_dir[512];
    snprintf(out_dir, sizeof out_dir, "%s/walk", tmp_dir);
    snprintf(args, sizeof args, "render examples/skinned-walk.json --out '%s'", out_dir);
    char *err = NULL;
    int rc = microrayd(args, NULL, &err);
    if (rc != 0)
        fail_msg("render exited %d: %s", rc, err);
    /* One progress line per frame. */
    assert_int_equal(count_lines_with(err, "frame "), 49);
    free(err);

    char path[1024];
    snprintf(path, sizeof path, "%s/stats.json", out_dir);
    char *text = slurp(path);
    assert_non_null(text);
    cJSON *stats = cJSON_Parse(text);
    assert_non_null(stats);
    assert_int_equal(cJSON_GetObjectItem(stats, "frames_done")->valueint, 49);
    cJSON *frames = cJSON_GetObjectItem(stats, "frames");
    assert_int_equal(cJSON_GetArraySize(frames), 49);
    /* The first frame builds the BVH, later ones refit it (animated scene). */
    assert_string_equal(cJSON_GetObjectItem(cJSON_GetArrayItem(frames, 0), "bvh")->valuestring, "build");
    assert_string_equal(cJSON_GetObjectItem(cJSON_GetArrayItem(frames, 1), "bvh")->valuestring, "refit");
    cJSON *f1 = cJSON_GetArrayItem(frames, 1);
    assert_true(cJSON_GetObjectItem(f1, "triangles")->valuedouble == 5126);
    /* 2 samples a pixel and a shadow ray per light (2) a hit: at least the
     * hit pixels' samples, at most every pixel's samples and their shadow
     * rays (pixels outside the character's projected box are misses
     * without a ray) */
    mr_film *frame1 = read_frame(out_dir, 1);
    double hits = 0;
    for (size_t i = 0; i < (size_t)frame1->width * frame1->height; i++)
        hits += frame1->object_id[i] != 0;
    mr_film_free(frame1);
    double rays = cJSON_GetObjectItem(f1, "rays")->valuedouble;
    assert_true(hits > 1000 && rays >= hits * 2 && rays <= 960.0 * 540 * 2 * 3);
    assert_true(cJSON_GetObjectItem(cJSON_GetObjectItem(f1, "bytes"), "bvh")->valuedouble > 0);
    cJSON_Delete(stats);
    free(text);

    /* Consecutive frames differ, and only where the character is: a pixel
     * whose centre ray missed in both frames may change colour only through
     * its jittered samples, so it must touch a pixel that hit something. */
    for (int k = 0; k + 1 < 49; k += 8) {
        mr_film *a = read_frame(out_dir, k), *b = read_frame(out_dir, k + 1);
        int w = a->width, h = a->height;
        size_t changed = 0, changed_background = 0, hit = 0;
        for (int y = 0; y < h; y++)
            for (int x = 0; x < w; x++) {
                size_t i = (size_t)y * w + x;
                bool differs = a->z[i] != b->z[i] || a->object_id[i] != b->object_id[i] || a->r[i] != b->r[i];
                changed += differs;
                hit += a->object_id[i] != 0;
                if (!differs || a->object_id[i] || b->object_id[i])
                    continue;
                bool near_geometry = false;
                for (int dy = -1; dy <= 1; dy++)
                    for (int dx = -1; dx <= 1; dx++) {
                        int xx = x + dx, yy = y + dy;
                        if (xx >= 0 && yy >= 0 && xx < w && yy < h) {
                            size_t j = (size_t)yy * w + xx;
                            near_geometry |= a->object_id[j] || b->object_id[j];
                        }
                    }
                changed_background += !near_geometry;
            }
        assert_true(hit > 1000);
        assert_true(changed > 100);
        assert_int_equal(changed_background, 0);
        mr_film_free(a);
        mr_film_free(b);
    }
}

static void render_small(const char *name, int threads)
{
    char args[1024];
    snprintf(args, sizeof args, "render tests/data/skinned-small.json --out '%s/%s' --threads %d --quiet",
             tmp_dir, name, threads);
    char *err = NULL;
    int rc = microrayd(args, NULL, &err);
    if (rc != 0)
        fail_msg("render exited %d: %s", rc, err);
    free(err);
}

static void test_same_pixels_for_1_and_2_threads(void **state)
{
    (void)state;
    render_small("t1", 1);
    render_small("t2", 2);
    char d1[512], d2[512];
    snprintf(d1, sizeof d1, "%s/t1", tmp_dir);
    snprintf(d2, sizeof d2, "%s/t2", tmp_dir);
    for (int k = 0; k < 4; k++) {
        mr_film *a = read_frame(d1, k), *b = read_frame(d2, k);
        assert_int_equal(a->width, 192);
        assert_int_equal(a->height, 108);
        fx_assert_same_pixels(a, b, "1 and 2 threads");
        mr_film_free(a);
        mr_film_free(b);
    }
    /* 0.5 .. 1.25 s at 4 fps is exactly 4 frames: no fifth file. */
    char path[1024];
    snprintf(path, sizeof path, "%s/0004.exr", d1);
    assert_int_not_equal(access(path, F_OK), 0);
}

/* Another writer of the same output (a second render into DIR, an
 * interrupted one's leftovers) holds the names the one-shot renderer used to
 * write through ("0000.exr.tmp", "stats.json.tmp") and keeps writing after
 * this render is done: the frame and stats.json must stay this render's. */
static void test_render_owns_its_temporaries(void **state)
{
    (void)state;
    char dir[512], held[2][600];
    snprintf(dir, sizeof dir, "%s/shared-out", tmp_dir);
    assert_int_equal(mkdir(dir, 0755), 0);
    snprintf(held[0], sizeof held[0], "%s/0000.exr.tmp", dir);
    snprintf(held[1], sizeof held[1], "%s/stats.json.tmp", dir);
    FILE *other[2];
    for (int i = 0; i < 2; i++)
        assert_non_null(other[i] = fopen(held[i], "w"));
    render_small("shared-out", 2);
    for (int i = 0; i < 2; i++) {
        fputs("the other writer's bytes", other[i]);
        fclose(other[i]);
    }
    mr_film *f = read_frame(dir, 0);
    assert_int_equal(f->width, 192);
    mr_film_free(f);
    char path[700];
    snprintf(path, sizeof path, "%s/stats.json", dir);
    char *text = slurp(path);
    assert_non_null(text);
    cJSON *stats = cJSON_Parse(text);
    if (!stats)
        fail_msg("stats.json is not JSON: %.60s", text);
    assert_int_equal(cJSON_GetObjectItem(stats, "frames_done")->valueint, 4);
    cJSON_Delete(stats);
    free(text);
}

/* What a killed render left (a temporary no writer holds) of the files a
 * render writes is removed when the next one starts; a live writer's
 * temporary (its lock held) and other files' are not. */
static void test_render_removes_abandoned_temporaries(void **state)
{
    (void)state;
    char dir[512], path[3][600];
    snprintf(dir, sizeof dir, "%s/abandoned-out", tmp_dir);
    assert_int_equal(mkdir(dir, 0755), 0);
    snprintf(path[0], sizeof path[0], "%s/0000.exr.tmpAb12Cd", dir); /* a killed writer's */
    snprintf(path[1], sizeof path[1], "%s/0001.exr.tmpLive01", dir); /* a live writer's */
    snprintf(path[2], sizeof path[2], "%s/notes.txt.tmpAb12Cd", dir); /* not the render's */
    int fd[3];
    for (int i = 0; i < 3; i++) {
        fd[i] = open(path[i], O_WRONLY | O_CREAT | O_TRUNC, 0644);
        assert_true(fd[i] >= 0);
        assert_int_equal(write(fd[i], "half", 4), 4);
    }
    assert_int_equal(flock(fd[1], LOCK_EX), 0);
    close(fd[0]), close(fd[2]);
    render_small("abandoned-out", 2);
    struct stat st;
    assert_int_not_equal(stat(path[0], &st), 0);
    assert_int_equal(stat(path[1], &st), 0);
    assert_int_equal(stat(path[2], &st), 0);
    close(fd[1]);
}

/* stats.json is an output of the job: when it cannot be written at the end,
 * the command fails (exit 4, I/O) naming it, though every frame rendered. */
static void test_render_fails_without_stats_json(void **state)
{
    (void)state;
    char dir[512], blocker[600], inner[700];
    snprintf(dir, sizeof dir, "%s/no-stats", tmp_dir);
    assert_int_equal(mkdir(dir, 0755), 0);
    snprintf(blocker, sizeof blocker, "%s/stats.json", dir); /* a non-empty directory: no rename onto it */
    assert_int_equal(mkdir(blocker, 0755), 0);
    snprintf(inner, sizeof inner, "%s/keep", blocker);
    FILE *f = fopen(inner, "w");
    assert_non_null(f);
    fclose(f);
    char args[1024], *err = NULL;
    snprintf(args, sizeof args, "render tests/data/skinned-small.json --out '%s' --quiet", dir);
    int rc = microrayd(args, NULL, &err);
    if (rc != 4)
        fail_msg("render exited %d, want 4: %s", rc, err);
    assert_non_null(strstr(err, "stats.json"));
    free(err);
    mr_film *frame3 = read_frame(dir, 3); /* the frames themselves are complete */
    mr_film_free(frame3);
}

static void test_compare_command(void **state)
{
    (void)state;
    char args[2048], *out = NULL;
    snprintf(args, sizeof args, "compare '%s/t1/0000.exr' '%s/t2/0000.exr'", tmp_dir, tmp_dir);
    assert_int_equal(microrayd(args, &out, NULL), 0);
    cJSON *j = cJSON_Parse(out);
    assert_non_null(j);
    assert_true(cJSON_GetObjectItem(j, "coverage_error_pct")->valuedouble == 0);
    assert_true(cJSON_GetObjectItem(j, "depth_max")->valuedouble == 0);
    assert_true(cJSON_GetObjectItem(j, "holes")->valuedouble == 0);
    assert_true(cJSON_GetObjectItem(j, "psnr_rgb_db")->valuedouble == 999);
    cJSON_Delete(j);
    free(out);
    /* Different frames: the character moved, so coverage and depth differ. */
    snprintf(args, sizeof args, "compare '%s/t1/0000.exr' '%s/t1/0003.exr'", tmp_dir, tmp_dir);
    assert_int_equal(microrayd(args, &out, NULL), 0);
    j = cJSON_Parse(out);
    assert_non_null(j);
    assert_true(cJSON_GetObjectItem(j, "coverage_error_pct")->valuedouble > 0);
    assert_true(cJSON_GetObjectItem(j, "psnr_rgb_db")->valuedouble < 999);
    cJSON_Delete(j);
    free(out);
}

/* A glTF camera node instead of a path: Cameras.gltf places a perspective
 * camera (yfov 0.7) at (0.5, 0.5, 3) looking down -Z at a unit square
 * through the origin tilted by theta about X, with theta from the node's
 * quaternion (-0.383, 0, 0, 0.92375), about 45.03 degrees. The centre ray
 * meets it at y = 0.5, z = -0.5 tan(theta), with normal (0, sin, cos).
 * Tolerance 1e-4: float intersection at distance ~3. */
static void test_camera_from_gltf_node(void **state)
{
    (void)state;
    char args[1024], dir[512];
    snprintf(dir, sizeof dir, "%s/camnode", tmp_dir);
    snprintf(args, sizeof args, "render tests/data/camera-node.json --out '%s' --quiet", dir);
    char *err = NULL;
    int rc = microrayd(args, NULL, &err);
    if (rc != 0)
        fail_msg("render exited %d: %s", rc, err);
    free(err);
    mr_film *f = read_frame(dir, 0);
    size_t c = 32 * 65 + 32;
    assert_int_equal(f->object_id[c], 1);
    double theta = 2 * atan2(0.383, 0.92375);
    if (fabs(f->z[c] - (3 + 0.5 * tan(theta))) > 1e-4 || fabs(f->ny[c] - sin(theta)) > 1e-4 ||
        fabs(f->nz[c] - cos(theta)) > 1e-4)
        fail_msg("centre z %g n (%g %g %g)", f->z[c], f->nx[c], f->ny[c], f->nz[c]);
    /* the square spans x in [0, 1] around the camera's x = 0.5: symmetric coverage */
    size_t left = 0, right = 0;
    for (int y = 0; y < 65; y++)
        for (int x = 0; x < 65; x++)
            if (f->object_id[y * 65 + x])
                x < 32 ? left++ : x > 32 ? right++ : 0;
    assert_true(left > 100);
    assert_true(left == right);
    mr_film_free(f);
}

static void expect_failure(const char *args, int status, const char *needle)
{
    char *err = NULL;
    int rc = microrayd(args, NULL, &err);
    if (rc != status || !err || !strstr(err, needle))
        fail_msg("`microrayd %s`: exit %d (want %d), stderr: %s (want '%s')", args, rc, status,
                 err ? err : "", needle);
    free(err);
}

static void test_bad_input_is_answered(void **state)
{
    (void)state;
    char args[2048], path[512];
    snprintf(args, sizeof args, "render tests/data/invalid-job.json --out '%s/bad'", tmp_dir);
    expect_failure(args, 3, "/output/width");
    snprintf(args, sizeof args, "render tests/data/missing-asset.json --out '%s/bad'", tmp_dir);
    expect_failure(args, 4, "/assets/ghost/path");
    snprintf(args, sizeof args, "render tests/data/broken-model.json --out '%s/bad'", tmp_dir);
    expect_failure(args, 3, "/assets/bad/path");
    snprintf(args, sizeof args, "render tests/data/no-such-job.json --out '%s/bad'", tmp_dir);
    expect_failure(args, 4, "no-such-job.json");
    /* a FIFO would block a plain open() forever */
    snprintf(path, sizeof path, "%s/job.fifo", tmp_dir);
    assert_int_equal(mkfifo(path, 0600), 0);
    snprintf(args, sizeof args, "render '%s' --out '%s/bad'", path, tmp_dir);
    expect_failure(args, 4, "not a regular file");
    expect_failure("render", 2, "usage");
    expect_failure("frobnicate", 2, "unknown command");
    snprintf(args, sizeof args, "render tests/data/bad-clip.json --out '%s/badclip'", tmp_dir);
    expect_failure(args, 3, "/objects/0/pose/2: ");
    /* names are checked before the first frame: nothing was written */
    snprintf(path, sizeof path, "%s/badclip/0000.exr", tmp_dir);
    assert_int_not_equal(access(path, F_OK), 0);
    /* an svo instance naming a bone the extracted skeleton does not have */
    snprintf(args, sizeof args, "render tests/data/bad-svo-bone.json --out '%s/badbone'", tmp_dir);
    expect_failure(args, 3, "/objects/0/svo/instances/1/pose: ");
    snprintf(path, sizeof path, "%s/badbone/0000.exr", tmp_dir);
    assert_int_not_equal(access(path, F_OK), 0);
    expect_failure("compare examples/skinned-walk.json examples/skinned-walk.json", 3, "skinned-walk.json");
}

static void write_text(const char *path, const char *text)
{
    FILE *f = fopen(path, "w");
    assert_non_null(f);
    fputs(text, f);
    assert_int_equal(fclose(f), 0);
}

/* An asset with "refine": rendered from the refined mesh (4x the 5126
 * triangles after one round); over the triangle cap, a clear error naming
 * the asset's "refine" before any frame. */
static void test_refined_asset_renders(void **state)
{
    (void)state;
    char job[600], args[2048], dir[600], *err = NULL;
    snprintf(job, sizeof job, "%s/refine.json", tmp_dir);
    write_text(job, "{\"assets\": {\"dancer\": {\"path\": "
                    "\"/usr/share/assimp/models/X/BCN_Epileptic.X\", \"refine\": {\"rounds\": 1, "
                    "\"amplitude\": 0.01, \"frequency\": 20}}},"
                    "\"objects\": [{\"asset\": \"dancer\", \"pose\": {\"clip\": 0}}],"
                    "\"camera\": {\"path\": [{\"t\": 0, \"position\": [0, 0.2, 4.3], "
                    "\"target\": [0, 0, -0.1]}]},"
                    "\"frames\": {\"times\": [0.5]}, \"output\": {\"width\": 192, \"height\": 108}}");
    snprintf(dir, sizeof dir, "%s/refined", tmp_dir);
    snprintf(args, sizeof args, "render '%s' --out '%s' --quiet", job, dir);
    int rc = microrayd(args, NULL, &err);
    if (rc != 0)
        fail_msg("render exited %d: %s", rc, err);
    free(err);
    char path[700];
    snprintf(path, sizeof path, "%s/stats.json", dir);
    char *text = slurp(path);
    assert_non_null(text);
    cJSON *stats = cJSON_Parse(text);
    assert_non_null(stats);
    cJSON *f0 = cJSON_GetArrayItem(cJSON_GetObjectItem(stats, "frames"), 0);
    assert_true(cJSON_GetObjectItem(f0, "triangles")->valuedouble == 4 * 5126);
    cJSON_Delete(stats);
    free(text);
    mr_film *f = read_frame(dir, 0);
    size_t hit = 0;
    for (size_t i = 0; i < (size_t)f->width * f->height; i++)
        hit += f->object_id[i] != 0;
    assert_true(hit > 200);
    mr_film_free(f);

    /* 182^2 * 2 = 66248 triangles; 4 rounds would give 16959488 > 2^24. */
    snprintf(path, sizeof path, "%s/grid.obj", tmp_dir);
    FILE *g = fopen(path, "w");
    assert_non_null(g);
    for (int y = 0; y <= 182; y++)
        for (int x = 0; x <= 182; x++)
            fprintf(g, "v %d %d 0\n", x, y);
    for (int y = 0; y < 182; y++)
        for (int x = 0; x < 182; x++) {
            int a = y * 183 + x + 1;
            fprintf(g, "f %d %d %d\nf %d %d %d\n", a, a + 1, a + 184, a, a + 184, a + 183);
        }
    assert_int_equal(fclose(g), 0);
    write_text(job, "{\"assets\": {\"grid\": {\"path\": \"grid.obj\", \"refine\": {\"rounds\": 4}}},"
                    "\"objects\": [{\"asset\": \"grid\"}],"
                    "\"camera\": {\"path\": [{\"t\": 0, \"position\": [91, 91, 300], "
                    "\"target\": [91, 91, 0]}]}, \"frames\": {\"times\": [0]}}");
    snprintf(args, sizeof args, "render '%s' --out '%s/overcap'", job, tmp_dir);
    expect_failure(args, 3, "/assets/grid/refine: 4 rounds would turn the 66248 triangles");
    snprintf(path, sizeof path, "%s/overcap/0000.exr", tmp_dir);
    assert_int_not_equal(access(path, F_OK), 0);
}

/* Renders tests/data/<jobs[0]>.json and <jobs[1]>.json (the same scene as
 * triangles) and returns each one's isolated dark pixels per frame. */
static void speckles_of(const char *const jobs[2], double pct[2][2])
{
    for (int k = 0; k < 2; k++) {
        char args[1024];
        snprintf(args, sizeof args, "render tests/data/%s.json --out '%s/%s' --quiet", jobs[k],
                 tmp_dir, jobs[k]);
        char *err = NULL;
        if (microrayd(args, NULL, &err) != 0)
            fail_msg("render %s: %s", jobs[k], err);
        free(err);
        char dir[600];
        snprintf(dir, sizeof dir, "%s/%s", tmp_dir, jobs[k]);
        for (int f = 0; f < 2; f++) {
            mr_film *film = read_frame(dir, f);
            mr_speckle_result s;
            mr_film_speckles(film, &s);
            assert_true(s.interior > 1000); /* the character: ~2,000+ interior pixels */
            pct[k][f] = s.speckle_pct;
            mr_film_free(film);
        }
    }
}

/* Voxel shadow acne (issue 13): the dancer as an emit octree at depth 9
 * and as triangles, same camera, light and pose, two frames. Before voxel
 * surfaces were lit by their shading normals and their shadow rays left
 * the staircase (kind.h surface_step), the octree had 9.1 % and 5.9 %
 * isolated dark pixels against the triangles' 1.9 % and 1.5 % (4.7x and
 * 3.9x); then 3.4 % and 3.0 % (1.8x and 2.0x); since triangle meshes start
 * shadow rays on the surface their normals describe (kind.h
 * shading_point), the triangles have 1.54 % and 1.36 %, the octree 2.74 %
 * and 2.73 % (1.77x and 2.01x). Since shadow rays leave by the size of the
 * voxel hit, silhouette voxels shade edge-on, coarse voxels by their
 * leaves' mean normal and emit's cells fit its boxes: 2.06 % and 2.20 %
 * (1.34x and 1.62x). The bound, 1.9x per frame, fails on the previous
 * figures (2.01x) and leaves room for the noise of a changed pose or
 * voxelisation (35 dark pixels of ~1,600 here); issue 13's goal is 1.2x. */
static void test_voxel_acne(void **state)
{
    (void)state;
    const char *const jobs[2] = {"svo-acne", "svo-acne-triangles"};
    double pct[2][2];
    speckles_of(jobs, pct);
    for (int f = 0; f < 2; f++) {
        print_message("[ acne     ] frame %d: voxels %.3f %%, triangles %.3f %% (%.2fx)\n", f,
                      pct[0][f], pct[1][f], pct[0][f] / pct[1][f]);
        assert_true(pct[0][f] <= 1.9 * pct[1][f]);
    }
}

/* --frames (issue 18): parts of a job rendered apart give the frames of
 * one whole run, bit for bit (an animated mesh, a deformed octree, a
 * skinned displaced micro-mesh; the
 * daemon's resume covers a simulated kind: test_sequential_daemon, and
 * the renderer replays it the same way); their statistics files join into a
 * stats.json of every frame; bad ranges are refused naming the flag. */
static void test_frame_ranges(void **state)
{
    (void)state;
    static const struct {
        const char *job, *parts[3];
        int frames;
    } cases[] = {
        {"tests/data/skinned-small.json", {"2-3", "0", "1"}, 4},
        {"tests/data/svo-acne.json", {"1", "0", NULL}, 2},
        {"tests/data/dmm-small.json", {"1-2", "0", NULL}, 3},
    };
    for (size_t c = 0; c < sizeof cases / sizeof *cases; c++) {
        char whole[512], parts[512], args[2048];
        snprintf(whole, sizeof whole, "%s/ranges-whole-%zu", tmp_dir, c);
        snprintf(parts, sizeof parts, "%s/ranges-parts-%zu", tmp_dir, c);
        snprintf(args, sizeof args, "render %s --out '%s' --quiet", cases[c].job, whole);
        assert_int_equal(microrayd(args, NULL, NULL), 0);
        for (int p = 0; p < 3 && cases[c].parts[p]; p++) {
            snprintf(args, sizeof args, "render %s --out '%s' --quiet --frames %s", cases[c].job,
                     parts, cases[c].parts[p]);
            assert_int_equal(microrayd(args, NULL, NULL), 0);
        }
        snprintf(args, sizeof args, "stats-merge '%s' %s", parts, cases[c].job);
        assert_int_equal(microrayd(args, NULL, NULL), 0);
        for (int k = 0; k < cases[c].frames; k++) {
            mr_film *a = read_frame(whole, k), *b = read_frame(parts, k);
            char what[600];
            snprintf(what, sizeof what, "%s frame %d rendered apart", cases[c].job, k);
            fx_assert_same_pixels(a, b, what);
            mr_film_free(a);
            mr_film_free(b);
        }
        char path[600];
        snprintf(path, sizeof path, "%s/stats.json", parts);
        char *stats = slurp(path);
        assert_non_null(stats);
        for (int k = 0; k < cases[c].frames; k++) {
            char file[32];
            snprintf(file, sizeof file, "\"%04d.exr\"", k);
            assert_non_null(strstr(stats, file));
        }
        char done[64];
        snprintf(done, sizeof done, "\"frames_done\":\t%d", cases[c].frames);
        if (!strstr(stats, done))
            fail_msg("merged stats.json lacks %s", done);
        free(stats);
    }
    /* a part missing: stats-merge writes what there is and says which */
    char args[1024], *err = NULL, dir[512];
    snprintf(dir, sizeof dir, "%s/ranges-missing", tmp_dir);
    snprintf(args, sizeof args, "render tests/data/skinned-small.json --out '%s' --quiet --frames 0,2-3", dir);
    assert_int_equal(microrayd(args, NULL, NULL), 0);
    snprintf(args, sizeof args, "stats-merge '%s' tests/data/skinned-small.json", dir);
    assert_int_equal(microrayd(args, NULL, &err), 1);
    assert_non_null(strstr(err, "1 of 4 frames have no statistics (frames 1)"));
    free(err);
    static const struct {
        const char *spec, *says;
    } bad[] = {
        {"3-1", "--frames '3-1': the range 3-1 runs backwards"},
        {"0-4", "--frames '0-4': frame 4 is not in the job (its frames are 0-3)"},
        {"x", "--frames 'x': expected a frame number at 'x'"},
        {"1-", "--frames '1-': a range needs its last frame"},
        {"1;2", "--frames '1;2': unexpected ';'"},
    };
    for (size_t b = 0; b < sizeof bad / sizeof *bad; b++) {
        snprintf(args, sizeof args, "render tests/data/skinned-small.json --out '%s/bad' --frames '%s'",
                 tmp_dir, bad[b].spec);
        assert_int_equal(microrayd(args, NULL, &err), 2);
        if (!strstr(err, bad[b].says))
            fail_msg("--frames %s: %s", bad[b].spec, err);
        free(err);
    }
}

/* Displaced micro-mesh acne (issue 13): the dmm examples' dancer (refined,
 * level 3, 1/16 base triangles, interpolated) and the same refined dancer
 * as triangles, two frames of the dmm-skinned camera and clip. Before the
 * bake's search was bounded (stray micro-triangles beside the body and a
 * broken dark line at the waist) and while micro-triangles were shaded by
 * their own facets, the DMM had 2.10 % and 2.00 % isolated dark pixels
 * against the triangles' 1.22 % and 0.97 % (1.7x and 2.1x; 2.16 % and
 * 1.90 % with "matrix" normals); now 1.19 % and 1.10 % (0.97x and 1.13x).
 * The bound, 1.4x per frame, fails on either old cause and leaves room for
 * a changed bake or pose; issue 13's goal is 1.2x on the median. */
static void test_dmm_acne(void **state)
{
    (void)state;
    const char *const jobs[2] = {"dmm-acne", "dmm-acne-triangles"};
    double pct[2][2];
    speckles_of(jobs, pct);
    for (int f = 0; f < 2; f++) {
        print_message("[ acne     ] frame %d: dmm %.3f %%, triangles %.3f %% (%.2fx)\n", f,
                      pct[0][f], pct[1][f], pct[0][f] / pct[1][f]);
        assert_true(pct[0][f] <= 1.4 * pct[1][f]);
    }
}

static int setup(void **state)
{
    (void)state;
    const char *s = getenv("MR_SOURCE_DIR"), *b = getenv("MR_BUILD_DIR");
    snprintf(src_dir, sizeof src_dir, "%s", s ? s : ".");
    snprintf(bin, sizeof bin, "%s/microrayd", b ? b : "build");
    snprintf(tmp_dir, sizeof tmp_dir, "/tmp/microray-e2e-XXXXXX");
    return mkdtemp(tmp_dir) ? 0 : -1;
}

static int teardown(void **state)
{
    (void)state;
    char cmd[512];
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", tmp_dir);
    return system(cmd) == 0 ? 0 : -1;
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_skinned_example_renders_and_moves),
        cmocka_unit_test(test_same_pixels_for_1_and_2_threads),
        cmocka_unit_test(test_render_owns_its_temporaries),
        cmocka_unit_test(test_render_removes_abandoned_temporaries),
        cmocka_unit_test(test_render_fails_without_stats_json),
        cmocka_unit_test(test_compare_command),
        cmocka_unit_test(test_camera_from_gltf_node),
        cmocka_unit_test(test_bad_input_is_answered),
        cmocka_unit_test(test_refined_asset_renders),
        cmocka_unit_test(test_voxel_acne),
        cmocka_unit_test(test_frame_ranges),
        cmocka_unit_test(test_dmm_acne),
    };
    return cmocka_run_group_tests_name("e2e_render", tests, setup, teardown);
}
