/*
 * bench_svo_render.c - sparse voxel octree instances through the renderer
 * (issue 5, paper 004), side by side with the same character rendered as
 * skinned triangles. Not a test: it prints figures, it never fails on a
 * time. (bench_svo measures the voxel pipeline itself: the thesis' sweeps,
 * deformation and rebuild rates, memory against Embree triangles.)
 *
 * Scene: the skinned-walk example's dancer (X/BCN_Epileptic.X, real rig
 * and clip) seen from the front at 640 x 360, primary rays only (1 sample,
 * no shadows), frames spread over the whole clip. For each depth, six
 * renderers run the same frames interleaved (frame f in every mode before
 * frame f + 1):
 *   mesh    the skinned triangles (the reference)
 *   rigid   the shared octree as Embree instances (rest pose: its accuracy
 *           is measured against a rest-pose mesh, rendered alongside)
 *   direct, resize, emit   deformed every frame (deform.h)
 *   rigid t1   rigid cast to the level of detail of "tolerance_px": 1
 *           (svo_trace.h, mr_svo_lod), measured as rigid
 * Reported per mode: median per-frame update (pose, selection, deformation,
 * resampling), Embree build and trace times, primary Mrays/s, voxels traced,
 * worst coverage / depth / normal error and holes against the reference.
 * Then: how many instances the renderer deforms and rebuilds (resize,
 * depth 8) within the thesis' 33.8 ms per frame, instances on a grid seen
 * from afar, each with its own clip offset, at 1280x720, 640x360 (issue
 * 17's measure) and 320x180 (each job's frames rendered twice, the second
 * pass timed: its steady state, not its first frames' page faults); and
 * skeleton extraction
 * (chapter 5) on real models: bones, thinness error (eq. 5.7.1), time.
 *
 * Only the public API (microray.h) and the job parser: the kind's phases
 * and creation figures come from the frames' svo_* stats fields (README,
 * stats.json). The skeleton table used to call the extraction directly and
 * also printed the contraction's graph vertices and iterations; those are
 * internals of the extraction that no user sees, so they are gone, and its
 * time (svo_skeleton_s) now includes skinning the asset to the new bones.
 *
 * usage: bench_svo_render [--frames N] [--depths 8,10,12] [--quick]
 * (run from the repository root; voxelised octrees are cached in
 * $TMPDIR/microray-bench-svo/svo so each depth is voxelised once)
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

#include "job_json.h"
#include "microray.h"
#include "bench_util.h"

#define MODEL "/usr/share/assimp/models/X/BCN_Epileptic.X"
#define MODES 6
#define RIGID_LOD 5 /* rigid cast to the level of detail of "tolerance_px": 1 */
#define MAX_FRAMES 32
#define BUDGET_S 0.0338

static const char *const MODE_NAME[MODES] = {"mesh", "rigid", "direct", "resize", "emit", "rigid t1"};
static char cache_dir[512]; /* the renderers' cache root: octrees in cache_dir/svo */
static size_t job_budget;   /* the jobs' memory budget (renderer option) */

static void die(const char *what, const char *msg)
{
    fprintf(stderr, "bench_svo_render: %s: %s\n", what, msg);
    exit(1);
}

/* A job for one mode: kind fields, pose or rest, the given frame times. */
static mr_job *make_job(const char *object, const double *times, int frames, int width,
                        int height, const char *camera)
{
    /* the object (up to 65,536 instances) and the camera, plus the rest */
    size_t cap = strlen(object) + strlen(camera) + 8192;
    char *text = malloc(cap), *ts = malloc(4096);
    if (!text || !ts)
        die("job", "out of memory");
    ts[0] = 0;
    for (int f = 0; f < frames; f++)
        snprintf(ts + strlen(ts), 4096 - strlen(ts), "%s%.9g", f ? "," : "", times[f]);
    int n = snprintf(text, cap,
                     "{\"assets\":{\"d\":{\"path\":\"" MODEL "\"}},\"objects\":[%s],"
                     "\"lights\":[{\"direction\":[-0.4,-0.8,-0.6]}],"
                     "\"camera\":{\"yfov\":40,\"path\":[%s]},"
                     "\"frames\":{\"times\":[%s]},"
                     "\"output\":{\"width\":%d,\"height\":%d,\"samples\":1,\"shadows\":false}}",
                     object, camera, ts, width, height);
    if (n < 0 || (size_t)n >= cap)
        die("job", "too long");
    mr_job *job = NULL;
    mr_job_error jerr = {0};
    if (mr_job_parse(text, (size_t)n, &job, &jerr) < 0)
        die(jerr.pointer, jerr.message);
    free(text);
    free(ts);
    return job;
}

typedef struct mode_run {
    mr_job *job;
    mr_device *dev;
    mr_renderer *r;
    mr_film *film;
    double update[MAX_FRAMES], bvh[MAX_FRAMES], trace[MAX_FRAMES], mrays[MAX_FRAMES];
    double build_s; /* svo_build_s of the first frame: voxelisation or cache load */
    uint64_t voxels;
    uint64_t bytes;       /* bytes.geometry + bytes.bvh */
    double shared;        /* svo_shared_bytes */
    double scratch;       /* svo_scratch_bytes */
    double worst_cov, worst_depth, worst_normal;
    size_t worst_holes;
} mode_run;

static void open_run(mode_run *m, mr_job *job, mr_asset *asset)
{
    mr_error err = {0};
    mr_asset *assets[1] = {asset};
    mr_renderer_options opt = {.cache_dir = cache_dir, .memory_budget = job_budget};
    m->job = job;
    if (mr_device_new(0, &m->dev, &err) < 0 || mr_renderer_new(m->dev, job, assets, &opt, &m->r, &err) < 0 ||
        mr_film_new(job->output.width, job->output.height, &m->film, &err) < 0)
        die("renderer", err.msg);
}

static void close_run(mode_run *m)
{
    mr_film_free(m->film);
    mr_renderer_free(m->r);
    mr_device_free(m->dev);
    mr_job_free(m->job);
}

static void render(mode_run *m, size_t f, mr_frame_stats *st)
{
    mr_error err = {0};
    if (mr_renderer_render(m->r, f, m->film, st, &err) < 0)
        die("render", err.msg);
    m->update[f] = st->pose_s;
    m->bvh[f] = st->bvh_s;
    m->trace[f] = st->trace_s;
    m->mrays[f] = st->mrays_per_s;
    m->voxels = st->triangles;
    m->bytes = st->geometry_bytes + st->bvh_bytes;
    for (uint32_t i = 0; i < st->extra_count; i++) {
        if (f == 0 && !strcmp(st->extras[i].name, "svo_build_s"))
            m->build_s = st->extras[i].value;
        if (!strcmp(st->extras[i].name, "svo_scratch_bytes"))
            m->scratch = st->extras[i].value;
        if (!strcmp(st->extras[i].name, "svo_shared_bytes"))
            m->shared = st->extras[i].value;
    }
}

static void accumulate(mode_run *m, const mr_film *ref, double diag)
{
    mr_compare_result c;
    mr_error err = {0};
    if (mr_film_compare(m->film, ref, diag, &c, &err) < 0)
        die("compare", err.msg);
    m->worst_cov = fmax(m->worst_cov, c.coverage_pct);
    m->worst_depth = fmax(m->worst_depth, c.depth_rmse);
    m->worst_normal = fmax(m->worst_normal, c.normal_mean_deg);
    if (c.holes > m->worst_holes)
        m->worst_holes = c.holes;
}

static const char *FRONT = "{\"t\":0,\"position\":[0,0.2,4.3],\"target\":[0,0,-0.1]}";

static void run_depth(mr_asset *asset, unsigned depth, const double *times, int frames)
{
    mode_run run[MODES] = {0}, rest_ref = {0};
    char obj[512];
    for (int m = 0; m < MODES; m++) {
        if (m == 0)
            snprintf(obj, sizeof obj, "{\"asset\":\"d\",\"pose\":{\"clip\":0}}");
        else
            snprintf(obj, sizeof obj,
                     "{\"asset\":\"d\",\"kind\":\"svo\",\"pose\":{\"clip\":0},"
                     "\"svo\":{\"depth\":%u,\"method\":\"%s\"}%s}",
                     depth, m == RIGID_LOD ? "rigid" : MODE_NAME[m], m == RIGID_LOD ? ",\"tolerance_px\":1" : "");
        open_run(&run[m], make_job(obj, times, frames, 640, 360, FRONT), asset);
    }
    open_run(&rest_ref, make_job("{\"asset\":\"d\"}", times, frames, 640, 360, FRONT), asset);
    for (int f = 0; f < frames; f++) {
        mr_frame_stats st;
        for (int m = 0; m < MODES; m++)
            render(&run[m], (size_t)f, &st);
        render(&rest_ref, (size_t)f, &st);
        double diag = st.scene_diagonal;
        for (int m = 2; m < MODES; m++)
            if (m != RIGID_LOD)
                accumulate(&run[m], run[0].film, diag);
        accumulate(&run[1], rest_ref.film, diag);
        accumulate(&run[RIGID_LOD], rest_ref.film, diag);
    }
    printf("\ndepth %u (%d frames over the clip, 640x360, primary rays)\n", depth, frames);
    printf("  %-8s %10s %9s %9s %9s %11s %9s %9s %9s %8s %7s %6s %8s\n", "mode", "update ms", "bvh ms",
           "trace ms", "Mrays/s", "voxels", "B/voxel", "-shared", "scratch", "cover %", "depth", "holes",
           "build s");
    double mesh_trace = median(run[0].trace, frames);
    for (int m = 0; m < MODES; m++) {
        mode_run *r = &run[m];
        double up = median(r->update, frames) * 1e3, bvh = median(r->bvh, frames) * 1e3,
               tr = median(r->trace, frames), mr = median(r->mrays, frames);
        if (m == 0)
            printf("  %-8s %10.2f %9.2f %9.2f %9.2f %11llu %9s %9s %9s %8s %7s %6s\n", MODE_NAME[m], up,
                   bvh, tr * 1e3, mr, (unsigned long long)r->voxels, "-", "-", "-", "ref", "-", "-");
        else {
            const double v = r->voxels ? (double)r->voxels : 1.0;
            const double own = ((double)r->bytes - r->shared) / v;
            printf("  %-8s %10.2f %9.2f %9.2f %9.2f %11llu %9.1f %9.1f %9.1f %8.2f %7.1e %6zu %8.2f   trace "
                   "x%.1f of mesh\n",
                   MODE_NAME[m], up, bvh, tr * 1e3, mr, (unsigned long long)r->voxels, (double)r->bytes / v,
                   own, r->scratch / v, r->worst_cov, r->worst_depth, r->worst_holes, r->build_s,
                   mesh_trace > 0 ? tr / mesh_trace : 0.0);
        }
    }
    /* the report's curves: a frame's update, build and trace against the
     * coverage error to the skinned triangles (rigid, measured against the
     * rest pose, is left out) */
    char level[16];
    snprintf(level, sizeof level, "%u", depth);
    for (int m = 0; m < MODES; m++) {
        if (m == 1 || m == RIGID_LOD)
            continue;
        double frame_ms = (median(run[m].update, frames) + median(run[m].bvh, frames) +
                           median(run[m].trace, frames)) * 1e3;
        bench_point("svo", "dancer against its skinned triangles", m ? MODE_NAME[m] : "triangles",
                    level, frame_ms, "worst coverage error %", m ? run[m].worst_cov : 0.0, false);
    }
    for (int m = 0; m < MODES; m++)
        close_run(&run[m]);
    close_run(&rest_ref);
}

/* Instances on a grid seen from afar (each a few pixels to a few dozen
 * tall), each with its own clip offset: update + build per frame; -1 when
 * the frame passed the job's memory budget (each instance holds its own
 * world octree). */
static double instances_frame_s(mr_asset *asset, unsigned n, int frames, int width, int height,
                                uint64_t *voxels)
{
    size_t cap = (size_t)n * 160 + 1024;
    char *obj = malloc(cap);
    if (!obj)
        die("instances", "out of memory");
    unsigned side = (unsigned)ceil(sqrt((double)n));
    size_t at = (size_t)snprintf(obj, cap,
                                 "{\"asset\":\"d\",\"kind\":\"svo\",\"pose\":{\"clip\":0},"
                                 "\"svo\":{\"depth\":8,\"method\":\"resize\",\"instances\":[");
    for (unsigned k = 0; k < n; k++)
        at += (size_t)snprintf(obj + at, cap - at,
                               "%s{\"transform\":{\"translation\":[%g,0,%g]},"
                               "\"pose\":{\"clip\":0,\"offset\":%g}}",
                               k ? "," : "", 2.0 * (k % side) - side, -2.0 * (k / side),
                               0.37 * k);
    snprintf(obj + at, cap - at, "]}}");
    char cam[256];
    snprintf(cam, sizeof cam, "{\"t\":0,\"position\":[0,%g,%g],\"target\":[0,0,%g]}",
             0.8 * side + 2, 1.2 * side + 4, -1.0 * side);
    double times[MAX_FRAMES];
    for (int f = 0; f < frames; f++)
        times[f] = 0.1 * f;
    mode_run r = {0};
    open_run(&r, make_job(obj, times, frames, width, height, cam), asset);
    /* the frames twice, the second pass timed: a job's first frames fault
     * its workers' selection and resampling arrays in (64 instances at
     * 640x360: 151 ms for frame 0, 115-122 for the frames after it) */
    double t[MAX_FRAMES];
    for (int pass = 0; pass < 2; pass++)
        for (int f = 0; f < frames; f++) {
            mr_frame_stats st;
            mr_error err = {0};
            if (mr_renderer_render(r.r, (size_t)f, r.film, &st, &err) < 0) {
                if (err.code != MR_ERR_LIMIT)
                    die("instances", err.msg);
                close_run(&r);
                free(obj);
                return -1;
            }
            t[f] = st.pose_s + st.bvh_s;
            *voxels = st.triangles;
        }
    close_run(&r);
    free(obj);
    return median(t, frames);
}

/* Chapter 5 on real models, the kind's defaults (omega 2^-min(depth, 5)):
 * a one-frame job per model and depth with "skeleton": true, whose first
 * frame reports the extraction (svo_bones, svo_thinness_pct,
 * svo_skeleton_s: contraction, bones and skinning the asset to them). */
static void skeletons(void)
{
    static const char *const models[] = {"/usr/share/assimp/models/Collada/human.zae",
                                         "/usr/share/assimp/models/OBJ/spider.obj",
                                         "/usr/share/assimp/models/OBJ/WusonOBJ.obj", MODEL};
    printf("\nskeleton extraction (chapter 5; surface voxels, default omega, 2 threads; time "
           "includes skinning to the bones)\n");
    printf("  %-14s %6s %9s %6s %11s %9s\n", "model", "depth", "voxels", "bones", "thinness %",
           "time s");
    for (size_t i = 0; i < sizeof models / sizeof *models; i++)
        for (unsigned depth = 7; depth <= 8; depth++) {
            char text[1024];
            int n = snprintf(text, sizeof text,
                             "{\"assets\":{\"m\":{\"path\":\"%s\"}},\"objects\":[{\"asset\":\"m\","
                             "\"kind\":\"svo\",\"svo\":{\"depth\":%u,\"method\":\"rigid\","
                             "\"skeleton\":true}}],\"camera\":{\"path\":[{\"t\":0,"
                             "\"position\":[0,0,10],\"target\":[0,0,0]}]},\"frames\":{\"times\":[0]},"
                             "\"output\":{\"width\":16,\"height\":16,\"samples\":1}}",
                             models[i], depth);
            mr_job *job = NULL;
            mr_job_error jerr = {0};
            if (mr_job_parse(text, (size_t)n, &job, &jerr) < 0)
                die(jerr.pointer, jerr.message);
            mr_asset *a = NULL;
            mr_error err = {0};
            if (mr_asset_load(models[i], &a, &err) < 0)
                die(models[i], err.msg);
            mode_run r = {0};
            mr_device *dev = NULL;
            mr_asset *assets[1] = {a};
            mr_frame_stats st;
            /* no cache: the voxels are built anew, as the extraction's input */
            if (mr_device_new(2, &dev, &err) < 0 ||
                mr_renderer_new(dev, job, assets, NULL, &r.r, &err) < 0 ||
                mr_film_new(16, 16, &r.film, &err) < 0 || mr_renderer_render(r.r, 0, r.film, &st, &err) < 0)
                die(models[i], err.msg);
            const char *name = strrchr(models[i], '/') + 1;
            printf("  %-14s %6u %9.0f %6.0f %11.3f %9.2f\n", name, depth,
                   frame_extra(&st, "svo_voxels"), frame_extra(&st, "svo_bones"),
                   frame_extra(&st, "svo_thinness_pct"), frame_extra(&st, "svo_skeleton_s"));
            r.dev = dev;
            r.job = job;
            close_run(&r);
            mr_asset_free(a);
        }
}

int main(int argc, char **argv)
{
    int frames = 6;
    bool quick = false;
    unsigned depths[8] = {8, 10, 12}, depth_count = 3;
    for (int i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--frames") && i + 1 < argc) {
            frames = atoi(argv[++i]);
        } else if (!strcmp(argv[i], "--depths") && i + 1 < argc) {
            depth_count = 0;
            for (char *s = strtok(argv[++i], ","); s && depth_count < 8; s = strtok(NULL, ","))
                depths[depth_count++] = (unsigned)atoi(s);
        } else if (!strcmp(argv[i], "--quick")) {
            quick = true;
        }
    }
    if (quick) {
        frames = 3;
        depth_count = 1;
    }
    if (frames < 1 || frames > MAX_FRAMES)
        die("--frames", "1..32");
    const char *tmp = getenv("TMPDIR");
    snprintf(cache_dir, sizeof cache_dir, "%s/microray-bench-svo", tmp && *tmp ? tmp : "/tmp");
    mkdir(cache_dir, 0755);
    job_budget = (size_t)fmin(8.0 * (1u << 30), 0.6 * bench_mem_available());

    mr_asset *asset = NULL;
    mr_error err = {0};
    if (mr_asset_load(MODEL, &asset, &err) < 0)
        die(MODEL, err.msg);
    double dur = mr_asset_clip_count(asset) ? mr_asset_clip_duration(asset, 0) : 1.0;
    double times[MAX_FRAMES];
    for (int f = 0; f < frames; f++)
        times[f] = dur * (f + 0.5) / frames;
    printf("bench_svo_render: sparse voxel octree instances against skinned triangles\n");
    printf("voxels: the primitives traced (rigid: the shared octree's leaves; direct: the deformed boxes; "
           "resize, emit: the rebuilt octree's leaves). B/voxel: (bytes.geometry + bytes.bvh) / voxels; "
           "-shared: the same without svo_shared_bytes (the source octree and its side data, once per "
           "object); scratch: svo_scratch_bytes / voxels (the workers' selection and resampling arrays, "
           "kept between frames)\n");
    for (unsigned d = 0; d < depth_count; d++)
        run_depth(asset, depths[d], times, frames);

    /* The grid's camera backs away as it grows, so instances shrink on
     * screen: the voxels selected stay near the screen's pixel count (times
     * the depth complexity: no occlusion culling) while the per-instance
     * work (pose, matrices, root selection) grows with N. */
    /* 640 x 360: issue 17's measure (>= 64 instances within 33.8 ms) */
    const int res[3][2] = {{1280, 720}, {640, 360}, {320, 180}};
    for (int ri = 0; ri < 3; ri++) {
        printf("\ninstances deformed and rebuilt per frame (resize, depth 8, %dx%d, grid seen "
               "from afar, own clip offsets; update + build, median of 3 frames rendered "
               "twice, the second time timed)\n",
               res[ri][0], res[ri][1]);
        unsigned best = 0;
        for (unsigned n = 1; n <= (quick ? 16u : 65536u); n *= 4) {
            uint64_t voxels = 0;
            double s = instances_frame_s(asset, n, 3, res[ri][0], res[ri][1], &voxels);
            if (s < 0) {
                printf("  %6u instances: over the jobs' memory budget of %.1f GiB\n", n,
                       (double)job_budget / (1u << 30));
                break;
            }
            printf("  %6u instances: %9.2f ms per frame, %9llu voxels%s\n", n, s * 1e3,
                   (unsigned long long)voxels, s <= BUDGET_S ? "" : "  (over 33.8 ms)");
            if (s <= BUDGET_S)
                best = n;
            if (s > 30 * BUDGET_S)
                break;
        }
        printf("  largest power of four within the thesis' 33.8 ms: %u instance%s (thesis: 10^6 "
               "instances of 6 models on a GTX 260)\n",
               best, best == 1 ? "" : "s");
    }
    skeletons();
    mr_asset_free(asset);
    return 0;
}
