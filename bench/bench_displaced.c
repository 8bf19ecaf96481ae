/*
 * bench_displaced.c - the displaced kind (paper 003, issue 14) side by side
 * in one run: the thesis' Table 6.1 scenes (a plane of 2 faces, a sphere of
 * 960 faces, examples/models) at ranges 8 .. 512, traced
 *   tf        tessellation-free (the D-BVH traversal),
 *   tess      the same micro-triangles as Embree triangles (build and trace
 *             reported apart),
 *   march N   fixed-step ray marching with N = 64, 300, 1000 steps,
 * for the procedural source (tiling and blending of crackedground_1-6.jpg,
 * the thesis' case: range = subdivisions per lattice square) and for the
 * height texture itself (range = texels per unit: the image's mip levels).
 * Per row: median trace ms of interleaved repeats, primary Mrays/s, the
 * error against tess (coverage %, depth RMS / diagonal, holes), and bytes
 * (microray's geometry + Embree's). Then tf against tess alone at 640x360
 * (the goal's ratio: at 160x90 the frame's fixed costs move it towards 1),
 * and the cost of a new 4096^2 height texture: creating the object
 * (pyramid) and its first frame's bounds.
 * Not a test: it prints figures and never fails on a time.
 *
 * usage: bench_displaced [--quick] [--edit] [--ratios] [--size WxH] [--repeats N]
 *   --edit: only the texture edit's cost
 *   --ratios: only tf against tess at 640x360
 * (run from the repository root)
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "bench_util.h"
#include "job_json.h"
#include "microray.h"

#define EXAMPLE "/usr/share/assimp/models/IRRMesh/crackedground_1-6.jpg"
#define MAX_REPEATS 9

static int width = 160, height = 90, repeats = 3;

typedef struct run {
    mr_job *job;
    mr_asset *assets[2];
    mr_renderer *r;
    mr_film *film;
    double create_s;
    double trace[MAX_REPEATS];
    mr_frame_stats st;
    bool ok;
    char err[1200];
} run;

/* One device per method: Embree's memory monitor counts per device, so
 * each row's bytes are its own renderer's. */
static mr_device *devs[5], *dev;

static void run_free(run *x)
{
    mr_renderer_free(x->r);
    mr_film_free(x->film);
    for (int k = 0; k < 2; k++)
        mr_asset_free(x->assets[k]);
    mr_job_free(x->job);
    memset(x, 0, sizeof *x);
}

/* A job of the mesh with the displaced block `block`, camera looking at it. */
static bool run_open(run *x, mr_device *d, const char *mesh, const char *block, const char *cam)
{
    memset(x, 0, sizeof *x);
    char json[2048];
    snprintf(json, sizeof json,
             "{\"assets\": {\"m\": {\"path\": \"%s\"}, \"t\": {\"path\": \"%s\"}},"
             " \"objects\": [{\"asset\": \"m\", \"kind\": \"displaced\", \"displaced\": %s}],"
             " \"camera\": {\"yfov\": 40, \"path\": [%s]}, \"frames\": {\"times\": [0]},"
             " \"output\": {\"width\": %d, \"height\": %d, \"samples\": 1, \"shadows\": false}}",
             mesh, EXAMPLE, block, cam, width, height);
    mr_job_error je;
    mr_error err = {0};
    if (mr_job_parse(json, strlen(json), &x->job, &je) != MR_OK) {
        snprintf(x->err, sizeof x->err, "%s: %s", je.pointer, je.message);
        return false;
    }
    for (size_t k = 0; k < 2; k++)
        if (mr_asset_load(x->job->assets[k].path, &x->assets[k], &err) != MR_OK) {
            snprintf(x->err, sizeof x->err, "%s", err.msg);
            return false;
        }
    double t0 = mr_now();
    if (mr_renderer_new(d, x->job, x->assets, NULL, &x->r, &err) != MR_OK ||
        mr_film_new(width, height, &x->film, &err) != MR_OK) {
        snprintf(x->err, sizeof x->err, "%s", err.msg);
        return false;
    }
    x->create_s = mr_now() - t0;
    x->ok = true;
    return true;
}

static void run_frame(run *x, int rep)
{
    mr_error err = {0};
    if (!x->ok)
        return;
    if (mr_renderer_render(x->r, 0, x->film, &x->st, &err) != MR_OK) {
        snprintf(x->err, sizeof x->err, "%s", err.msg);
        x->ok = false;
        return;
    }
    x->trace[rep] = x->st.trace_s;
}

static double extra(const mr_frame_stats *st, const char *name)
{
    for (uint32_t k = 0; k < st->extra_count; k++)
        if (!strcmp(st->extras[k].name, name))
            return st->extras[k].value;
    return 0;
}

static void row(const char *scene, int range, const char *method, run *x, run *ref)
{
    if (!x->ok) {
        printf("| %s | %d | %s | %s | | | | | |\n", scene, range, method, x->err[0] ? x->err : "skipped");
        return;
    }
    double t = median(x->trace, repeats) * 1e3;
    double mrays = x->st.rays / (t * 1e-3) * 1e-6;
    char cov[32] = "ref", dep[32] = "", holes[32] = "", level[32];
    double depth_rmse = 0; /* the reference's own */
    bool measured = x == ref;  /* an error against a reference that ran */
    if (ref && ref->ok && ref != x) {
        mr_compare_result c;
        mr_error err;
        if (mr_film_compare(x->film, ref->film, ref->st.scene_diagonal, &c, &err) == MR_OK) {
            snprintf(cov, sizeof cov, "%.3f", c.coverage_pct);
            snprintf(dep, sizeof dep, "%.1e", c.depth_rmse);
            snprintf(holes, sizeof holes, "%zu", c.holes);
            depth_rmse = c.depth_rmse;
            measured = true;
        }
    }
    snprintf(level, sizeof level, "%d", range);
    /* against this range's own tessellation: methods compare within a range
     * (a range whose tessellation did not run has no error to plot) */
    if (measured)
        bench_point("displaced", scene, method, level, t, "depth RMS / diagonal", depth_rmse, true);
    double bytes = (double)x->st.geometry_bytes + (double)x->st.bvh_bytes;
    printf("| %s | %d | %s | %.1f | %.2f | %s | %s | %s | %.2f |", scene, range, method, t, mrays,
           cov, dep, holes, bytes / 1048576.0);
    if (!strcmp(method, "tess"))
        printf(" build %.0f ms |\n", x->create_s * 1e3);
    else
        printf(" nodes/ray %.0f |\n", extra(&x->st, "displaced_nodes") / (double)x->st.rays);
}

static const char *CAM_PLANE = "{\"t\": 0, \"position\": [0, 1.4, 2.4], \"target\": [0, 0, 0]}";
static const char *CAM_SPHERE = "{\"t\": 0, \"position\": [0, 0.6, 3.6], \"target\": [0, 0, 0]}";

/* Methods of the table, as the object's "displaced" block has them. */
static const char *const METHOD_FIELDS[] = {"\"method\": \"tessellation_free\"",
                                            "\"method\": \"tessellated\"",
                                            "\"method\": \"raymarch\", \"steps\": 64",
                                            "\"method\": \"raymarch\", \"steps\": 300",
                                            "\"method\": \"raymarch\", \"steps\": 1000"};

/* The object's "displaced" block: the example as a procedural source at
 * range, or as a height texture at mip level range (texels per unit:
 * 400 / 2^range), with method m of METHOD_FIELDS. */
static void displaced_block(char *block, size_t n, bool procedural, int range, int m)
{
    char src[256];
    if (procedural)
        snprintf(src, sizeof src,
                 "\"procedural\": {\"example\": \"t\", \"scale\": 1, \"seed\": 7}, "
                 "\"range\": %d", range);
    else
        snprintf(src, sizeof src, "\"texture\": \"t\", \"level\": %d", range);
    snprintf(block, n, "{%s, \"scale\": 0.1, %s}", src, METHOD_FIELDS[m]);
}

static void table(const char *scene, const char *mesh, const char *cam, bool procedural,
                  const int *ranges, int nranges, int tess_max)
{
    static const char *METHODS[] = {"tf", "tess", "march 64", "march 300", "march 1000"};
    for (int ri = 0; ri < nranges; ri++) {
        int range = ranges[ri];
        run x[5];
        for (int m = 0; m < 5; m++) {
            char block[512];
            displaced_block(block, sizeof block, procedural, range, m);
            if (m == 1 && range > tess_max) {
                memset(&x[m], 0, sizeof x[m]);
                snprintf(x[m].err, sizeof x[m].err, "not run (over %d: minutes and GBs)", tess_max);
                continue;
            }
            run_open(&x[m], devs[m], mesh, block, cam);
        }
        for (int rep = 0; rep < repeats; rep++)
            for (int m = 0; m < 5; m++)
                run_frame(&x[m], rep);
        int shown = procedural ? range : (int)ceil(400.0 / (1 << range));
        for (int m = 0; m < 5; m++)
            row(scene, shown, METHODS[m], &x[m], &x[1]);
        for (int m = 0; m < 5; m++)
            run_free(&x[m]);
        fflush(stdout);
    }
}

/* tf against tess alone at a larger frame (no marching, whose 1000 steps
 * would take minutes there): at 160x90 the frame's fixed costs weigh on
 * both and move their ratio towards 1 (the plane at 200 texels per unit:
 * 0.44-0.45 there, 0.27-0.29 at 640x360). Procedural ranges above
 * tess_max have no tessellation to compare with and no row. */
static void ratio_table(const char *scene, const char *mesh, const char *cam, bool procedural,
                        const int *ranges, int nranges, int tess_max)
{
    for (int ri = 0; ri < nranges; ri++) {
        const int range = ranges[ri];
        if (range > tess_max && procedural)
            continue;
        run x[2];
        for (int m = 0; m < 2; m++) {
            char block[512];
            displaced_block(block, sizeof block, procedural, range, m);
            run_open(&x[m], devs[m], mesh, block, cam);
        }
        for (int rep = 0; rep < repeats; rep++)
            for (int m = 0; m < 2; m++)
                run_frame(&x[m], rep);
        const int shown = procedural ? range : (int)ceil(400.0 / (1 << range));
        if (x[0].ok && x[1].ok) {
            const double tf = median(x[0].trace, repeats), tess = median(x[1].trace, repeats);
            printf("| %s | %d | %.2f | %.2f | **%.2f** |\n", scene, shown, tf * 1e3, tess * 1e3, tess / tf);
        } else {
            printf("| %s | %d | %s | | |\n", scene, shown, x[0].ok ? x[1].err : x[0].err);
        }
        for (int m = 0; m < 2; m++)
            run_free(&x[m]);
        fflush(stdout);
    }
}

/* A new 4096^2 height texture: the object's creation (pyramid) against a
 * 1x1 texture's, and the first frame's bounds. */
static void edit_cost(void)
{
    const int N = 4096;
    char path[256];
    snprintf(path, sizeof path, "%s/microray-bench-4096.png", getenv("TMPDIR") ? getenv("TMPDIR") : "/tmp");
    mr_image8 img = {.width = N, .height = N, .channels = 3, .px = malloc((size_t)N * N * 3)};
    uint32_t s = 1;
    for (size_t k = 0; k < (size_t)N * N * 3; k++) {
        s = s * 1664525u + 1013904223u;
        img.px[k] = (uint8_t)(s >> 24);
    }
    uint8_t *png = NULL;
    size_t size = 0;
    mr_error err;
    if (mr_png_encode(&img, &png, &size, &err) != MR_OK ||
        mr_fs_write_atomic(path, png, size, "bench", &err) != MR_OK) {
        printf("edit cost: %s\n", err.msg);
        free(img.px);
        free(png);
        return;
    }
    free(img.px);
    free(png);
    double create[MAX_REPEATS], create_cpu[MAX_REPEATS], bounds[MAX_REPEATS];
    for (int rep = 0; rep < repeats; rep++) {
        run x;
        char json[1024];
        snprintf(json, sizeof json,
                 "{\"assets\": {\"m\": {\"path\": \"examples/models/plane.obj\"}, \"t\": {\"path\": \"%s\"}},"
                 " \"objects\": [{\"asset\": \"m\", \"kind\": \"displaced\", \"displaced\": {\"texture\": \"t\"}}],"
                 " \"camera\": {\"path\": [%s]}, \"frames\": {\"times\": [0]},"
                 " \"output\": {\"width\": 64, \"height\": 36}}", path, CAM_PLANE);
        memset(&x, 0, sizeof x);
        mr_job_error je;
        if (mr_job_parse(json, strlen(json), &x.job, &je) != MR_OK ||
            mr_asset_load(x.job->assets[0].path, &x.assets[0], &err) != MR_OK ||
            mr_asset_load(x.job->assets[1].path, &x.assets[1], &err) != MR_OK) {
            printf("edit cost: could not load\n");
            run_free(&x);
            return;
        }
        double t0 = mr_now(), c0 = bench_cpu_now();
        if (mr_renderer_new(dev, x.job, x.assets, NULL, &x.r, &err) != MR_OK) {
            printf("edit cost: %s\n", err.msg);
            run_free(&x);
            return;
        }
        create[rep] = mr_now() - t0;
        create_cpu[rep] = bench_cpu_now() - c0;
        mr_film_new(64, 36, &x.film, &err);
        mr_renderer_render(x.r, 0, x.film, &x.st, &err);
        bounds[rep] = extra(&x.st, "displaced_bounds_s");
        run_free(&x);
    }
    remove(path);
    printf("\nA new 4096x4096 height texture (16.8 M texels, 8-bit): object creation (min/max "
           "pyramid of any size, %d repeats, median) %.1f ms wall, %.1f ms CPU on %u threads; "
           "first frame's bounds %.3f ms.\n",
           repeats, median(create, repeats) * 1e3, median(create_cpu, repeats) * 1e3,
           mr_device_threads(dev), median(bounds, repeats) * 1e3);
}

int main(int argc, char **argv)
{
    bool quick = false, edit_only = false, ratios_only = false;
    for (int i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--quick"))
            quick = true;
        else if (!strcmp(argv[i], "--edit"))
            edit_only = true;
        else if (!strcmp(argv[i], "--ratios"))
            ratios_only = true;
        else if (!strcmp(argv[i], "--size") && i + 1 < argc)
            sscanf(argv[++i], "%dx%d", &width, &height);
        else if (!strcmp(argv[i], "--repeats") && i + 1 < argc)
            repeats = atoi(argv[++i]);
    }
    if (repeats < 1 || repeats > MAX_REPEATS)
        repeats = 3;
    mr_error err;
    for (int m = 0; m < 5; m++)
        if (mr_device_new(0, &devs[m], &err) != MR_OK) {
            fprintf(stderr, "bench_displaced: %s\n", err.msg);
            return 1;
        }
    dev = devs[0];
    if (edit_only) {
        edit_cost();
        for (int m = 0; m < 5; m++)
            mr_device_free(devs[m]);
        return 0;
    }
    static const int PR[] = {8, 16, 64, 128, 256, 512}, PRQ[] = {8, 64};
    static const int TL[] = {5, 4, 3, 2, 1, 0}, TLQ[] = {3, 0};
    const int *pr = quick ? PRQ : PR, *tl = quick ? TLQ : TL;
    int n = quick ? 2 : 6;
    if (!ratios_only) {
        printf("\n## Displaced surfaces (paper 003, Table 6.1 side by side), %dx%d primary rays, "
               "%u threads, medians of %d interleaved repeats\n\n", width, height,
               mr_device_threads(dev), repeats);
        printf("| scene | range | method | trace ms | Mrays/s | coverage %% | depth RMS | holes | MiB | |\n");
        printf("|---|---|---|---|---|---|---|---|---|---|\n");
        table("plane, procedural", "examples/models/plane.obj", CAM_PLANE, true, pr, n, 128);
        table("sphere, procedural", "examples/models/sphere960.obj", CAM_SPHERE, true, pr, n, 128);
        table("plane, texture", "examples/models/plane.obj", CAM_PLANE, false, tl, n, 99);
        table("sphere, texture", "examples/models/sphere960.obj", CAM_SPHERE, false, tl, n, 99);
    }
    const int small_w = width, small_h = height;
    width = 640;
    height = 360;
    printf("\n## tf against tess at %dx%d (issue 14's goal: tf at least 0.35 of tess's Mrays/s), "
           "medians of %d interleaved repeats\n\n", width, height, repeats);
    printf("| scene | range | tf ms | tess ms | tess / tf |\n|---|---|---|---|---|\n");
    ratio_table("plane, procedural", "examples/models/plane.obj", CAM_PLANE, true, pr, n, 128);
    ratio_table("sphere, procedural", "examples/models/sphere960.obj", CAM_SPHERE, true, pr, n, 128);
    ratio_table("plane, texture", "examples/models/plane.obj", CAM_PLANE, false, tl, n, 99);
    ratio_table("sphere, texture", "examples/models/sphere960.obj", CAM_SPHERE, false, tl, n, 99);
    width = small_w;
    height = small_h;
    if (!ratios_only)
        edit_cost();
    for (int m = 0; m < 5; m++)
        mr_device_free(devs[m]);
    return 0;
}
