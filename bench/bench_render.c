/*
 * bench_render.c - the foundation benchmarks (make bench). Not a test: it
 * prints figures, it never fails on a time.
 *
 * Everything is measured side by side in one run, interleaved, and reported
 * as medians over repeats, because a 2-core machine's timings are noisy:
 *  1. primary-ray throughput of microray's renderer (shading and AOVs
 *     included, shadows off, 1 sample) against a bare Embree loop tracing
 *     the same pixel-centre rays (mr_camera_rays) through the same
 *     triangles (the renderer's exact reference of the frame,
 *     mr_renderer_tessellate) on the same number of threads
 *     (mr_parallel_for; an Embree device of the bench's own), for the
 *     static human and the skinned dancer;
 *  2. per-frame BVH refit against a full rebuild with the same fast (LOW
 *     quality) builder for the skinned example, and what the refitted tree
 *     costs in trace time.
 * EXR encoding is bench_encode.c. Only the public API (microray.h), the
 * server's job reader and Embree itself.
 *
 * usage: bench_render [--repeats N] [--threads N]   (run from the repository root)
 */
#include <float.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <embree3/rtcore.h>

#include "files.h"
#include "job_json.h"
#include "microray.h"
#include "bench_util.h"

static int repeats = 5;
static unsigned threads = 0;

static void die(const char *what, const char *msg)
{
    fprintf(stderr, "bench: %s: %s\n", what, msg);
    exit(1);
}

typedef struct loaded_job {
    mr_job *job;
    mr_asset **assets;
} loaded_job;

static loaded_job load_job(const char *path)
{
    loaded_job lj = {0};
    char *text;
    size_t len;
    mr_error err = {0};
    mr_job_error jerr = {0};
    if (mr_file_read(path, MR_JOB_MAX_BYTES, &text, &len, &err) < 0)
        die(path, err.msg);
    if (mr_job_parse(text, len, &lj.job, &jerr) < 0)
        die(path, jerr.message);
    free(text);
    lj.assets = calloc(lj.job->asset_count, sizeof *lj.assets);
    for (size_t i = 0; i < lj.job->asset_count; i++)
        if (mr_asset_load(lj.job->assets[i].path, &lj.assets[i], &err) < 0)
            die(lj.job->assets[i].path, err.msg);
    return lj;
}

static void free_job(loaded_job *lj)
{
    for (size_t i = 0; i < lj->job->asset_count; i++)
        mr_asset_free(lj->assets[i]);
    free(lj->assets);
    mr_job_free(lj->job);
}

/* ---- bare Embree loop -------------------------------------------------- */

typedef struct bare_ctx {
    RTCScene scene;
    mr_camera_rays cam;
    int width, height, tiles_x;
    atomic_ullong hits;
} bare_ctx;

static void bare_tiles(void *p, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    bare_ctx *c = p;
    unsigned long long hits = 0;
    for (size_t tile = begin; tile < end; tile++) {
        int x0 = (int)(tile % (size_t)c->tiles_x) * 16, y0 = (int)(tile / (size_t)c->tiles_x) * 16;
        for (int y = y0; y < y0 + 16 && y < c->height; y++)
            for (int x = x0; x < x0 + 16 && x < c->width; x++) {
                mr_vec3 d = mr_camera_rays_dir(&c->cam, (float)x + 0.5f, (float)y + 0.5f);
                struct RTCIntersectContext ictx;
                rtcInitIntersectContext(&ictx);
                struct RTCRayHit rh;
                rh.ray = (struct RTCRay){.org_x = c->cam.origin.x, .org_y = c->cam.origin.y,
                                         .org_z = c->cam.origin.z, .dir_x = d.x, .dir_y = d.y,
                                         .dir_z = d.z, .tnear = 0, .tfar = FLT_MAX, .mask = ~0u};
                rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
                rtcIntersect1(c->scene, &ictx, &rh);
                hits += rh.hit.geomID != RTC_INVALID_GEOMETRY_ID;
            }
    }
    atomic_fetch_add(&c->hits, hits);
}

/* The same loop with packets of 8 neighbouring pixels of a row
 * (rtcIntersect8): issue 17's baseline. The renderer itself issues 16-wide
 * packets, 8 columns of 2 rows (integrator.c), which Embree traces faster
 * here (a loop like this one in 8x2 packets: 5.6 ms a frame against 6.9 on
 * static-human, 2026-12-03). */
static void bare_tiles8(void *p, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    bare_ctx *c = p;
    unsigned long long hits = 0;
    for (size_t tile = begin; tile < end; tile++) {
        int x0 = (int)(tile % (size_t)c->tiles_x) * 16, y0 = (int)(tile / (size_t)c->tiles_x) * 16;
        for (int y = y0; y < y0 + 16 && y < c->height; y++)
            for (int x = x0; x < x0 + 16 && x < c->width; x += 8) {
                RTC_ALIGN(32) int valid[8];
                struct RTCRayHit8 rh;
                for (int i = 0; i < 8; i++) {
                    int xi = x + i < c->width ? x + i : x;
                    mr_vec3 d = mr_camera_rays_dir(&c->cam, (float)xi + 0.5f, (float)y + 0.5f);
                    valid[i] = x + i < c->width ? -1 : 0;
                    rh.ray.org_x[i] = c->cam.origin.x;
                    rh.ray.org_y[i] = c->cam.origin.y;
                    rh.ray.org_z[i] = c->cam.origin.z;
                    rh.ray.dir_x[i] = d.x;
                    rh.ray.dir_y[i] = d.y;
                    rh.ray.dir_z[i] = d.z;
                    rh.ray.tnear[i] = 0;
                    rh.ray.tfar[i] = FLT_MAX;
                    rh.ray.time[i] = 0;
                    rh.ray.mask[i] = ~0u;
                    rh.ray.id[i] = 0;
                    rh.ray.flags[i] = 0;
                    rh.hit.geomID[i] = RTC_INVALID_GEOMETRY_ID;
                }
                struct RTCIntersectContext ictx;
                rtcInitIntersectContext(&ictx);
                ictx.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
                rtcIntersect8(valid, c->scene, &ictx, &rh);
                for (int i = 0; i < 8; i++)
                    hits += valid[i] && rh.hit.geomID[i] != RTC_INVALID_GEOMETRY_ID;
            }
    }
    atomic_fetch_add(&c->hits, hits);
}

/* The job's geometry as the renderer's last frame posed it (its exact
 * triangle reference, mr_renderer_tessellate), as one plain Embree
 * triangle scene. */
static RTCScene bare_scene(RTCDevice rtc, const mr_renderer *r, const mr_job *job, uint64_t *tris)
{
    RTCScene scene = rtcNewScene(rtc);
    rtcSetSceneFlags(scene, RTC_SCENE_FLAG_ROBUST);
    *tris = 0;
    mr_error err = {0};
    for (size_t o = 0; o < job->object_count; o++) {
        mr_trimesh tm;
        if (mr_renderer_tessellate(r, o, &tm, &err) < 0)
            die("bare scene", err.msg);
        RTCGeometry geom = rtcNewGeometry(rtc, RTC_GEOMETRY_TYPE_TRIANGLE);
        float *v = rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                           3 * sizeof(float), tm.vertex_count);
        uint32_t *ix = rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                               3 * sizeof(uint32_t), tm.triangle_count);
        memcpy(v, tm.positions, (size_t)tm.vertex_count * 3 * sizeof(float));
        memcpy(ix, tm.indices, (size_t)tm.triangle_count * 3 * sizeof(uint32_t));
        rtcCommitGeometry(geom);
        rtcAttachGeometry(scene, geom);
        rtcReleaseGeometry(geom);
        *tris += tm.triangle_count;
        mr_trimesh_free(&tm);
    }
    rtcCommitScene(scene);
    return scene;
}

static void bench_throughput(mr_device *dev, const char *job_path, int width, int height)
{
    loaded_job lj = load_job(job_path);
    mr_job *job = lj.job;
    job->output.width = width;
    job->output.height = height;
    job->output.spp = 1;
    job->output.shadows = false;
    job->frame_count = 1; /* frame 0 only: a static scene for both sides */

    mr_error err = {0};
    mr_renderer *r = NULL;
    mr_film *film = NULL, *first = NULL;
    /* the same work as the bare loops: a ray for every pixel */
    mr_renderer_options every = {.trace_every_pixel = true};
    if (mr_renderer_new(dev, job, lj.assets, &every, &r, &err) < 0 ||
        mr_film_new(width, height, &film, &err) < 0 || mr_film_new(width, height, &first, &err) < 0)
        die(job_path, err.msg);
    uint64_t tris;
    mr_frame_stats st0;
    if (mr_renderer_render(r, 0, film, &st0, &err) < 0) /* poses frame 0 */
        die(job_path, err.msg);
    char cfg[32];
    snprintf(cfg, sizeof cfg, "threads=%u", mr_device_threads(dev));
    RTCDevice rtc = rtcNewDevice(cfg);
    if (!rtc)
        die("embree", "rtcNewDevice failed");
    RTCScene bare = bare_scene(rtc, r, job, &tris);
    mr_camera cam = mr_camera_path_eval(&job->camera.path, job->frame_times[0]);
    bare_ctx bc = {.scene = bare, .cam = mr_camera_rays_setup(&cam, width, height),
                   .width = width, .height = height, .tiles_x = (width + 15) / 16};
    atomic_init(&bc.hits, 0);

    /* the bare loops take a row of tiles at a time, as the renderer does
     * (mr_trace_frame: a counter shared by both cores once a run) */
    size_t tiles = (size_t)bc.tiles_x * ((height + 15) / 16), run = (size_t)bc.tiles_x;
    double ours[64], fresh[64], base[64], base8[64];
    mr_frame_stats st;
    uint64_t rays = 0;
    for (int i = 0; i < repeats; i++) {
        /* a film that knows nothing of its contents (a job's first frame:
         * every pixel written), and after a bare loop the same frame again
         * into the film that rendered it before (a later frame: the
         * background it holds is not written again) */
        mr_film_clear(first);
        if (mr_renderer_render(r, 0, first, &st, &err) < 0)
            die(job_path, err.msg);
        fresh[i] = (double)st.rays / st.trace_s * 1e-6;
        double t0 = mr_now();
        mr_parallel_for(mr_device_threads(dev), tiles, run, bare_tiles, &bc);
        base[i] = (double)width * height / (mr_now() - t0) * 1e-6;
        if (mr_renderer_render(r, 0, film, &st, &err) < 0)
            die(job_path, err.msg);
        ours[i] = (double)st.rays / st.trace_s * 1e-6;
        rays = st.rays;
        t0 = mr_now();
        mr_parallel_for(mr_device_threads(dev), tiles, run, bare_tiles8, &bc);
        base8[i] = (double)width * height / (mr_now() - t0) * 1e-6;
    }
    double mo = median(ours, repeats), mf = median(fresh, repeats), mb = median(base, repeats),
           m8 = median(base8, repeats);
    printf("| %-14s | %9llu | %4dx%-4d | %8.2f | %8.2f | %11.2f | %5.2f | %12.2f | %5.2f | %5.2f |\n",
           job->name, (unsigned long long)tris, width, height, mo, mf, mb, mo / mb, m8, mo / m8, mf / m8);
    /* Same rays, same answers: both bare loops ran `repeats` times. */
    size_t our_hits = 0;
    for (size_t i = 0; i < (size_t)width * height; i++)
        our_hits += film->object_id[i] != 0;
    if (2 * our_hits * (size_t)repeats != (size_t)atomic_load(&bc.hits))
        printf("  (note: renderer hit %zu pixels, bare loops %llu in %d runs each)\n", our_hits,
               (unsigned long long)atomic_load(&bc.hits), repeats);
    if (rays != (uint64_t)width * height)
        printf("  (note: renderer traced %llu rays for %d pixels)\n", (unsigned long long)rays, width * height);
    rtcReleaseScene(bare);
    rtcReleaseDevice(rtc);
    mr_film_free(film);
    mr_film_free(first);
    mr_renderer_free(r);
    free_job(&lj);
}

static void bench_refit(mr_device *dev, const char *job_path, size_t frames)
{
    loaded_job lj = load_job(job_path);
    mr_job *job = lj.job;
    if (frames > job->frame_count)
        frames = job->frame_count;
    job->output.spp = 1;
    mr_error err = {0};
    mr_renderer *refit = NULL, *rebuild = NULL;
    mr_renderer_options opt = {.force_rebuild = true};
    mr_film *film = NULL;
    if (mr_renderer_new(dev, job, lj.assets, NULL, &refit, &err) < 0 ||
        mr_renderer_new(dev, job, lj.assets, &opt, &rebuild, &err) < 0 ||
        mr_film_new(job->output.width, job->output.height, &film, &err) < 0)
        die(job_path, err.msg);
    double bvh_refit[1024], bvh_rebuild[1024], trace_refit[1024], trace_rebuild[1024];
    size_t n = 0;
    mr_frame_stats st;
    for (size_t f = 0; f < frames && n < 1024; f++) {
        if (mr_renderer_render(refit, f, film, &st, &err) < 0)
            die(job_path, err.msg);
        if (f == 0)
            continue; /* frame 0 builds in both */
        bvh_refit[n] = st.bvh_s;
        trace_refit[n] = st.trace_s;
        if (mr_renderer_render(rebuild, f, film, &st, &err) < 0)
            die(job_path, err.msg);
        bvh_rebuild[n] = st.bvh_s;
        trace_rebuild[n] = st.trace_s;
        n++;
    }
    double mr = median(bvh_refit, (int)n), mb = median(bvh_rebuild, (int)n);
    double tr = median(trace_refit, (int)n), tb = median(trace_rebuild, (int)n);
    printf("| %-14s | %8llu | %6zu | %9.3f | %9.3f | %5.1fx | %9.2f | %9.2f |\n", job->name,
           (unsigned long long)st.triangles, n, mr * 1e3, mb * 1e3, mb / mr, tr * 1e3, tb * 1e3);
    mr_film_free(film);
    mr_renderer_free(refit);
    mr_renderer_free(rebuild);
    free_job(&lj);
}

int main(int argc, char **argv)
{
    for (int i = 1; i < argc; i++)
        if (!strcmp(argv[i], "--repeats") && i + 1 < argc)
            repeats = atoi(argv[++i]);
        else if (!strcmp(argv[i], "--threads") && i + 1 < argc)
            threads = (unsigned)atoi(argv[++i]);
    if (repeats < 1 || repeats > 64)
        repeats = 5;
    mr_device *dev = NULL;
    mr_error err = {0};
    if (mr_device_new(threads, &dev, &err) < 0)
        die("device", err.msg);
    printf("microray %s benchmarks: %u threads, medians of %d runs\n\n", MR_VERSION_STRING,
           mr_device_threads(dev), repeats);

    printf("Primary rays, 1 spp, no shadows (Mrays/s; ratio goal >= 0.9; microray: a later frame into "
           "its film, new film: a film that knows nothing of its contents, as a job's first frame)\n\n");
    printf("| scene          | triangles | size      | microray | new film | bare 1-ray  | ratio | bare 8-packet | ratio | new film ratio |\n");
    printf("|----------------|-----------|-----------|----------|----------|-------------|-------|--------------|-------|----------------|\n");
    bench_throughput(dev, "examples/static-human.json", 1280, 720);
    bench_throughput(dev, "examples/skinned-walk.json", 1280, 720);

    printf("\nBVH per frame, skinned example (ms; frames 1..N, frame 0 builds in both)\n\n");
    printf("| scene          | triangles | frames | refit     | rebuild   | speedup | trace refit | trace rebuild |\n");
    printf("|----------------|-----------|--------|-----------|-----------|---------|-------------|---------------|\n");
    bench_refit(dev, "examples/skinned-walk.json", 49);
    mr_device_free(dev);
    return 0;
}
