/*
 * bench_scaling.c - how each cost grows with its work (issue 17,
 * "Scaling"), measured in one run: frame time against triangle count
 * (mesh and dmm, 10^4 to 10^7) and against resolution (640x360 to
 * 3840x2160), with the renderer's accounted memory and the process' peak
 * resident memory, and next to each table the growth exponent fitted to
 * it (least squares of log cost against log work: 1 is linear, 0 is
 * flat); first the machine's limits: its copy bandwidth, and the time a
 * cache line takes from one core to another. The svo instance-count sweep
 * (1 to ~10^5) is bench_svo d; its exponent is printed there. Not a test:
 * it prints figures, it never fails on a time.
 *
 * Scenes: the skinned dancer of the examples (BCN_Epileptic.X, its clip)
 * made detailed by Loop rounds (refine.h), shadows on, 1 sample, 2
 * threads (all cores). Triangle counts: the mesh kind at 1-4 rounds, then
 * 4 and 8 dancers of 4 rounds side by side; the dmm kind (interpolated,
 * base triangles 1/16 of the 2-round dancer) at levels 0-5, then 2 dancers
 * at level 5. Every run renders a first frame (import, derived data, first
 * build: reported apart) and then FRAMES frames along the clip, medians.
 *
 * usage: bench_scaling   (run from the repository root)
 */
#include <math.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "job_json.h"
#include "microray.h"
#include "bench_util.h"

#define MODEL "/usr/share/assimp/models/X/BCN_Epileptic.X"
#define FRAMES 3
#define MAX_ROWS 8
#define MIB (1024.0 * 1024.0)

static void die(const char *what, const char *msg)
{
    fprintf(stderr, "bench_scaling: %s: %s\n", what, msg);
    exit(1);
}

/* A job of `copies` dancers of `rounds` Loop rounds in a row along x,
 * each with its own clip offset, as `kind` (with its fields), at w x h. */
static mr_job *dancers_job(int rounds, int copies, const char *kind, const char *fields, int w, int h)
{
    char objects[4096] = "";
    size_t used = 0;
    for (int k = 0; k < copies; k++)
        used += (size_t)snprintf(objects + used, sizeof objects - used,
                                 "%s{\"asset\":\"d\",\"kind\":\"%s\"%s,\"pose\":{\"clip\":0,\"offset\":%g},"
                                 "\"transform\":{\"translation\":[%g,0,0]}}",
                                 k ? "," : "", kind, fields, 0.37 * k, 0.9 * (k - 0.5 * (copies - 1)));
    char json[8192];
    const int n = snprintf(
        json, sizeof json,
        "{\"assets\":{\"d\":{\"path\":\"" MODEL "\",\"refine\":{\"rounds\":%d,\"amplitude\":0.006,"
        "\"frequency\":12,\"octaves\":3,\"seed\":1}}},\"objects\":[%s],"
        "\"lights\":[{\"direction\":[-0.4,-0.8,-0.6],\"color\":[1,1,1],\"intensity\":1}],"
        "\"camera\":{\"yfov\":40,\"path\":[{\"t\":0,\"position\":[0,1.0,5.4],\"target\":[0,0.9,0]}]},"
        "\"frames\":{\"times\":[0.05,0.45,0.85,1.25]},"
        "\"output\":{\"width\":%d,\"height\":%d,\"samples\":1,\"shadows\":true}}",
        rounds, objects, w, h);
    if (n < 0 || (size_t)n >= sizeof json)
        die("job", "too long");
    mr_job *job = NULL;
    mr_job_error jerr = {0};
    if (mr_job_parse(json, (size_t)n, &job, &jerr) < 0)
        die(jerr.pointer, jerr.message);
    return job;
}

typedef struct row {
    double work;                 /* triangles (micro-triangles for dmm) or pixels */
    double first_s;              /* renderer set-up (derived data) and the first frame */
    double pose_ms, bvh_ms, trace_ms, frame_ms, mrays;
    double accounted_mib;        /* geometry + Embree's BVH, as the renderer counts them */
    double touched_gbs;          /* geometry + BVH bytes / frame time: what the frame moves
                                    at the least when it touches all of its geometry */
    double peak_mib;             /* the process' peak resident memory during the run, above
                                    what it held before (freed memory handed back first) */
    double pixels_hit;
} row;

/* Renders the job (assets: the one dancer asset) and fills r. */
static void measure(const mr_job *job, mr_asset *asset, const char *cache, row *r)
{
    mr_error err = {0};
    mr_device *dev = NULL;
    mr_renderer *ren = NULL;
    mr_film *film = NULL;
    mr_asset *assets[1] = {asset};
    mr_renderer_options opt = {.cache_dir = cache};
    mr_heap_release();
    bench_peak_reset();
    const double before = bench_rss_now();
    const double t0 = mr_now();
    if (mr_device_new(0, &dev, &err) < 0 || mr_renderer_new(dev, job, assets, &opt, &ren, &err) < 0 ||
        mr_film_new(job->output.width, job->output.height, &film, &err) < 0)
        die("renderer", err.msg);
    mr_frame_stats st;
    if (mr_renderer_render(ren, 0, film, &st, &err) < 0)
        die("first frame", err.msg);
    r->first_s = mr_now() - t0;
    double pose[FRAMES], bvh[FRAMES], trace[FRAMES], frame[FRAMES], mrays[FRAMES];
    for (int f = 0; f < FRAMES; f++) {
        if (mr_renderer_render(ren, (size_t)f + 1, film, &st, &err) < 0)
            die("frame", err.msg);
        pose[f] = st.pose_s * 1e3;
        bvh[f] = st.bvh_s * 1e3;
        trace[f] = st.trace_s * 1e3;
        frame[f] = (st.pose_s + st.bvh_s + st.trace_s) * 1e3;
        mrays[f] = st.mrays_per_s;
    }
    r->pose_ms = median(pose, FRAMES);
    r->bvh_ms = median(bvh, FRAMES);
    r->trace_ms = median(trace, FRAMES);
    r->frame_ms = median(frame, FRAMES);
    r->mrays = median(mrays, FRAMES);
    r->accounted_mib = (double)(st.geometry_bytes + st.bvh_bytes) / MIB;
    r->touched_gbs = (double)(st.geometry_bytes + st.bvh_bytes) / (r->frame_ms * 1e-3) * 1e-9;
    size_t hit = 0;
    for (size_t i = 0; i < (size_t)job->output.width * (size_t)job->output.height; i++)
        hit += film->object_id[i] != 0;
    r->pixels_hit = (double)hit;
    mr_film_free(film);
    mr_renderer_free(ren);
    mr_device_free(dev);
    r->peak_mib = (bench_peak_rss() - before) / MIB;
}

/* ---- the machine's memory bandwidth: what a frame that touches all its
 * geometry (skinning, refit) is measured against */

typedef struct copy_ctx {
    unsigned char *src, *dst;
    size_t block;
} copy_ctx;

static void copy_blocks(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    const copy_ctx *c = vctx;
    for (size_t b = begin; b < end; b++)
        memcpy(c->dst + b * c->block, c->src + b * c->block, c->block);
}

/* Copy bandwidth on every core (bytes read + written per second; median of
 * 5 copies of 512 MiB, buffers touched first). */
static double copy_bandwidth(void)
{
    const size_t bytes = (size_t)512 << 20, block = (size_t)1 << 20;
    copy_ctx c = {malloc(bytes), malloc(bytes), block};
    if (!c.src || !c.dst)
        die("bandwidth", "out of memory");
    memset(c.src, 1, bytes);
    memset(c.dst, 2, bytes);
    double gbs[5];
    for (int i = 0; i < 5; i++) {
        const double t0 = mr_now();
        mr_parallel_for(0, bytes / block, 1, copy_blocks, &c);
        gbs[i] = 2.0 * (double)bytes / (mr_now() - t0) * 1e-9;
    }
    free(c.src);
    free(c.dst);
    return median(gbs, 5);
}

static double machine_gbs;

/* ---- how far apart the cores are: the time a cache line written on one
 * core takes to reach another, which every loop pays that hands its data
 * from one thread to the next (core/util/parallel.c keeps each thread on
 * its own share for that) */

#define PING_ROUNDS 200000

static _Alignas(64) atomic_int ping_flag;

static void *pong(void *arg)
{
    (void)arg;
    for (int i = 0; i < PING_ROUNDS; i++) {
        while (atomic_load_explicit(&ping_flag, memory_order_acquire) != 1)
            ;
        atomic_store_explicit(&ping_flag, 0, memory_order_release);
    }
    return NULL;
}

/* Median round trip (ns) of a flag passed back and forth between two
 * threads, 5 runs of PING_ROUNDS; 0 on one core, where the two would take
 * turns on it. */
static double ping_pong_ns(void)
{
    if (mr_cpu_count() < 2)
        return 0;
    double ns[5];
    for (int r = 0; r < 5; r++) {
        atomic_store(&ping_flag, 0);
        pthread_t t;
        if (pthread_create(&t, NULL, pong, NULL) != 0)
            return 0;
        const double t0 = mr_now();
        for (int i = 0; i < PING_ROUNDS; i++) {
            atomic_store_explicit(&ping_flag, 1, memory_order_release);
            while (atomic_load_explicit(&ping_flag, memory_order_acquire) != 0)
                ;
        }
        ns[r] = (mr_now() - t0) / PING_ROUNDS * 1e9;
        pthread_join(t, NULL);
    }
    return median(ns, 5);
}

/* The growth exponent of one field of the rows against their work. */
static double growth(const row *rows, int n, size_t field_offset)
{
    double x[MAX_ROWS], y[MAX_ROWS];
    for (int i = 0; i < n; i++) {
        x[i] = rows[i].work;
        y[i] = *(const double *)((const char *)&rows[i] + field_offset);
    }
    return bench_growth(x, y, n);
}

#define GROWTH(rows, n, field) growth(rows, n, offsetof(row, field))

static void print_table(const char *work_name, const row *rows, int n)
{
    printf("| %s | set-up + first frame s | pose ms | BVH ms | trace ms | frame ms | Mrays/s | pixels hit | "
           "geometry + BVH MiB | its GB/s | peak RSS growth MiB |\n|---|---|---|---|---|---|---|---|---|---|---|\n",
           work_name);
    for (int i = 0; i < n; i++) {
        const row *r = &rows[i];
        printf("| %.0f | %.2f | %.2f | %.2f | %.2f | %.2f | %.2f | %.0f | %.1f | %.2f | %.0f |\n", r->work,
               r->first_s, r->pose_ms, r->bvh_ms, r->trace_ms, r->frame_ms, r->mrays, r->pixels_hit,
               r->accounted_mib, r->touched_gbs, r->peak_mib);
    }
    printf("\nGrowth exponents (cost ~ %s^b, least squares over the rows): set-up + first frame b = %.2f, pose "
           "%.2f, BVH %.2f, trace %.2f, frame %.2f, geometry + BVH memory %.2f, peak RSS %.2f.\n\n",
           work_name, GROWTH(rows, n, first_s), GROWTH(rows, n, pose_ms), GROWTH(rows, n, bvh_ms),
           GROWTH(rows, n, trace_ms), GROWTH(rows, n, frame_ms), GROWTH(rows, n, accounted_mib),
           GROWTH(rows, n, peak_mib));
}

/* The dancer asset of `rounds` Loop rounds, as the jobs describe it. */
static mr_asset *load_dancer(int rounds)
{
    mr_job *job = dancers_job(rounds, 1, "mesh", "", 64, 36);
    mr_asset *a = bench_load_asset(&job->assets[0], 0);
    mr_job_free(job);
    return a;
}

static void triangles_mesh(const char *cache)
{
    static const int rounds[] = {1, 2, 3, 4, 4, 4}, copies[] = {1, 1, 1, 1, 4, 8};
    row rows[MAX_ROWS];
    int n = 0;
    mr_asset *asset = NULL;
    for (int i = 0; i < 6; i++) {
        if (i == 0 || rounds[i] != rounds[i - 1]) {
            mr_asset_free(asset);
            asset = load_dancer(rounds[i]);
        }
        mr_job *job = dancers_job(rounds[i], copies[i], "mesh", "", 640, 360);
        measure(job, asset, cache, &rows[n]);
        rows[n].work = (double)copies[i] * (double)mr_asset_triangle_count(asset);
        n++;
        mr_job_free(job);
    }
    mr_asset_free(asset);
    printf("### Frame time against triangles: mesh\n\nThe skinned dancer refined by 1-4 Loop rounds, "
           "then 4 and 8 dancers of 4 rounds; 640x360, shadows on, 2 threads; medians of %d frames "
           "after the first. Every frame skins every vertex and refits the BVH.\n\n",
           FRAMES);
    print_table("triangles", rows, n);
}

static void triangles_dmm(const char *cache)
{
    static const int levels[] = {0, 1, 2, 3, 4, 5, 5}, copies[] = {1, 1, 1, 1, 1, 1, 2};
    row rows[MAX_ROWS];
    int n = 0;
    mr_asset *asset = load_dancer(2);
    const double base = (double)mr_asset_triangle_count(asset) / 16.0;
    for (int i = 0; i < 7; i++) {
        char fields[160];
        snprintf(fields, sizeof fields,
                 ",\"dmm\":{\"level\":%d,\"base_ratio\":0.0625,\"mode\":\"interpolated\"}", levels[i]);
        mr_job *job = dancers_job(2, copies[i], "dmm", fields, 640, 360);
        measure(job, asset, cache, &rows[n]);
        rows[n].work = copies[i] * base * pow(4.0, levels[i]);
        n++;
        mr_job_free(job);
    }
    mr_asset_free(asset);
    printf("### Frame time against triangles: dmm\n\nThe 2-round dancer as displaced micro-meshes "
           "(interpolated, base triangles 1/16 of it: about %.0f), micro-triangles = base x 4^level "
           "at levels 0-5, then 2 dancers at level 5; 640x360, shadows on, 2 threads; medians of %d "
           "frames after the first (which bakes, or reads the bake from the cache).\n\n",
           base, FRAMES);
    print_table("micro-triangles", rows, n);
}

static void resolution(const char *cache)
{
    static const int size[][2] = {{640, 360}, {1280, 720}, {1920, 1080}, {2560, 1440}, {3840, 2160}};
    const char *kinds[2] = {"mesh", "dmm"};
    const char *fields[2] = {"", ",\"dmm\":{\"level\":3,\"base_ratio\":0.0625,\"mode\":\"interpolated\"}"};
    mr_asset *asset = load_dancer(2);
    for (int k = 0; k < 2; k++) {
        row rows[MAX_ROWS];
        int n = 0;
        for (int i = 0; i < 5; i++) {
            mr_job *job = dancers_job(2, 1, kinds[k], fields[k], size[i][0], size[i][1]);
            measure(job, asset, cache, &rows[n]);
            rows[n].work = (double)size[i][0] * size[i][1];
            n++;
            mr_job_free(job);
        }
        printf("### Frame time against resolution: %s\n\nThe 2-round dancer (%s), 640x360 to "
               "3840x2160, shadows on, 2 threads; medians of %d frames after the first.\n\n",
               kinds[k], k ? "dmm level 3, interpolated" : "82k triangles", FRAMES);
        print_table("pixels", rows, n);
    }
    mr_asset_free(asset);
}

int main(void)
{
    const char *tmp = getenv("TMPDIR");
    char cache[4096];
    snprintf(cache, sizeof cache, "%s/microray-bench-scaling-XXXXXX", tmp && *tmp ? tmp : "/tmp");
    if (!mkdtemp(cache))
        die("cache", "cannot make a temporary folder");
    const double t0 = mr_now();
    machine_gbs = copy_bandwidth();
    const double ping = ping_pong_ns();
    printf("\n## Scaling (issue 17): how each cost grows with its work, %u threads\n\n"
           "The machine copies %.1f GB/s (bytes read + written, every core, memcpy of 512 MiB). "
           "\"its GB/s\" below is a frame's geometry + BVH bytes over its frame time: the least "
           "it moves when every frame touches all of its geometry (skinning, refit); near the "
           "copy rate the machine's memory, not the algorithm, sets the pace.\n\n",
           mr_cpu_count(), machine_gbs);
    if (ping > 0)
        printf("A flag passed back and forth between two threads takes %.0f ns a round trip: a cache "
               "line written on one core reaches the other in about %.0f ns. A loop that hands its "
               "data from one thread to the other pays that per line, which is why each thread of "
               "a parallel loop takes its own share of the items first (core/util/parallel.c).\n\n",
               ping, ping / 2);
    triangles_mesh(cache);
    triangles_dmm(cache);
    resolution(cache);
    char cmd[4200];
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", cache);
    if (system(cmd) != 0)
        fprintf(stderr, "bench_scaling: could not remove %s\n", cache);
    printf("(bench_scaling: %.0f s)\n", mr_now() - t0);
    return 0;
}
