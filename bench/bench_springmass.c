/*
 * bench_springmass.c - the spring-mass kind (paper 001, issue 15) against
 * its goals (make bench). Not a test: it prints figures, it never fails on
 * a time.
 *
 * The paper's setting: about 20,000 nodes simulating a detailed surface of
 * about 50,000 faces (assimp's Wuson, 3,732 triangles, refined by the
 * job's "refine" twice: 59,712), 15 steps per frame, pinned at its feet and
 * pressed by a probe. Each mapping renders the same frames in its own
 * renderer, interleaved frame by frame with the others and with the
 * undeformed mesh (kind "mesh", the same refined asset and camera), on the
 * given threads (default 2). Figures are medians over frames 2.. of the
 * kind's own stats fields (simulate_s / sim_steps: ms per step; map_s: ms
 * per mapping) and of the frame's seconds (pose + bvh + trace: a whole
 * frame without encoding). A 32^3 grid (32,768 nodes filling a unit cube)
 * gives ms per step against Projective Dynamics' 3.1 ms per iteration.
 * Then the parallel loop's workers (issue 15): a short loop's cost per
 * call, and the step and the curvature mapping on 1 and 2 threads with
 * threads started per call (mr_parallel_use_pool(false), the way before)
 * and on the pool, interleaved frame by frame.
 *
 * usage: bench_springmass [--frames N] [--threads N]   (run from the repository root)
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "bench_util.h"
#include "job_json.h"
#include "microray.h"

static int frames = 14;
static unsigned threads = 2;

static void die(const char *what, const char *msg)
{
    fprintf(stderr, "bench_springmass: %s: %s\n", what, msg);
    exit(1);
}

static const char *const MAPPINGS[] = {"one_to_one", "triangle_basis", "triangle_basis_curvature", "trilinear"};
#define RUNS 5 /* the four mappings and the undeformed mesh */

typedef struct series {
    double step_ms[256], substeps[256], sub_ms[256], map_ms[256], frame_ms[256], pose_ms[256], bvh_ms[256], trace_ms[256];
    int n;
    double nodes;
} series;

static double extra(const mr_frame_stats *st, const char *name)
{
    for (uint32_t i = 0; i < st->extra_count; i++)
        if (!strcmp(st->extras[i].name, name))
            return st->extras[i].value;
    return 0;
}

static mr_job *parse(const char *text)
{
    mr_job *job = NULL;
    mr_job_error e;
    if (mr_job_parse(text, strlen(text), &job, &e) < 0)
        die(e.pointer, e.message);
    return job;
}

/* Renders frames 0..frames-1 of each job, interleaved, into its series. */
static void run_interleaved(mr_device *dev, mr_job **jobs, mr_asset **assets, int count, series *out)
{
    mr_renderer *r[RUNS];
    mr_film *film[RUNS];
    mr_error err;
    for (int k = 0; k < count; k++) {
        if (mr_renderer_new(dev, jobs[k], &assets[k], NULL, &r[k], &err) < 0 ||
            mr_film_new(jobs[k]->output.width, jobs[k]->output.height, &film[k], &err) < 0)
            die("renderer", err.msg);
        memset(&out[k], 0, sizeof out[k]);
    }
    for (int f = 0; f < frames; f++)
        for (int k = 0; k < count; k++) {
            mr_frame_stats st;
            if (mr_renderer_render(r[k], (size_t)f, film[k], &st, &err) < 0)
                die("render", err.msg);
            if (f < 2)
                continue; /* the first builds, the second may still warm caches */
            series *s = &out[k];
            double steps = extra(&st, "sim_steps");
            s->step_ms[s->n] = steps > 0 ? extra(&st, "simulate_s") / steps * 1e3 : 0;
            s->substeps[s->n] = extra(&st, "sim_substeps");
            s->sub_ms[s->n] = s->substeps[s->n] > 0 ? s->step_ms[s->n] / s->substeps[s->n] : 0;
            s->map_ms[s->n] = extra(&st, "map_s") * 1e3;
            s->pose_ms[s->n] = st.pose_s * 1e3;
            s->bvh_ms[s->n] = st.bvh_s * 1e3;
            s->trace_ms[s->n] = st.trace_s * 1e3;
            s->frame_ms[s->n] = (st.pose_s + st.bvh_s + st.trace_s) * 1e3;
            s->nodes = extra(&st, "sim_nodes");
            s->n++;
        }
    for (int k = 0; k < count; k++) {
        mr_film_free(film[k]);
        mr_renderer_free(r[k]);
    }
}

#define PAPER_JOB                                                                                  \
    "{\"name\":\"bench-springmass\",\"assets\":{\"w\":{\"path\":\"/usr/share/assimp/models/PLY/Wuson.ply\","  \
    "\"refine\":{\"rounds\":2,\"amplitude\":0.002}}},"                                             \
    "\"objects\":[{\"asset\":\"w\",\"kind\":\"%s\"%s}],"                                           \
    "\"lights\":[{\"direction\":[-0.4,-0.8,-0.6],\"intensity\":1}],"                               \
    "\"camera\":{\"path\":[{\"t\":0,\"position\":[3.2,1.6,2.2],\"target\":[0,0.6,0]}]},"           \
    "\"frames\":{\"fps\":24,\"start\":0,\"end\":10},"                                              \
    "\"output\":{\"width\":960,\"height\":540,\"samples\":1,\"shadows\":true}}"

#define SM_BLOCK                                                                                   \
    ",\"springmass\":{\"nodes\":20000,\"stiffness\":250,\"steps_per_frame\":15,\"mapping\":\"%s\","  \
    "\"checkpoint_every\":0,\"pins\":[{\"box_max\":[1,0.2,2]}],"                                   \
    "\"probes\":[{\"radius\":0.35,\"path\":[{\"t\":0,\"position\":[0,1.9,0]},"                     \
    "{\"t\":0.5,\"position\":[0,1.3,0.3]}]}]}"

#define CUBE_JOB                                                                                   \
    "{\"name\":\"bench-cube\",\"assets\":{\"c\":{\"path\":\"/usr/share/assimp/models/OBJ/box.obj\"}}," \
    "\"objects\":[{\"asset\":\"c\",\"kind\":\"springmass\",\"springmass\":{\"spacing\":%.9g,"      \
    "\"stiffness\":300,\"mapping\":\"trilinear\",\"checkpoint_every\":0,"                          \
    "\"pins\":[{\"box_max\":[1,-0.45,1]}],"                                                        \
    "\"probes\":[{\"radius\":0.2,\"path\":[{\"t\":0,\"position\":[0,0.75,0]},"                     \
    "{\"t\":0.5,\"position\":[0.1,0.62,0]}]}]}}],"                                                 \
    "\"lights\":[{\"direction\":[-0.4,-0.8,-0.6],\"intensity\":1}],"                               \
    "\"camera\":{\"path\":[{\"t\":0,\"position\":[2,1.5,2.5],\"target\":[0,0,0]}]},"               \
    "\"frames\":{\"fps\":24,\"start\":0,\"end\":10},"                                              \
    "\"output\":{\"width\":320,\"height\":240,\"samples\":1}}"

/* The work in a step and a mapping, apart from other processes on the
 * machine: one thread, a 16x9 film (tracing all but free), the process's
 * CPU seconds per frame split by the kind's own wall-clock fractions. */
static void work_per_step(mr_job *job, mr_asset *asset, double *step_ms, double *map_ms)
{
    mr_error err;
    mr_device *one = NULL;
    mr_renderer *r = NULL;
    mr_film *film = NULL;
    job->output.width = 16;
    job->output.height = 9;
    job->output.spp = 1;
    if (mr_device_new(1, &one, &err) < 0 || mr_renderer_new(one, job, &asset, NULL, &r, &err) < 0 ||
        mr_film_new(16, 9, &film, &err) < 0)
        die("renderer", err.msg);
    double steps_ms[256], maps_ms[256];
    int n = 0;
    for (int f = 0; f < frames; f++) {
        mr_frame_stats st;
        double c0 = bench_cpu_now();
        if (mr_renderer_render(r, (size_t)f, film, &st, &err) < 0)
            die("render", err.msg);
        double cpu = bench_cpu_now() - c0, wall = st.total_s, steps = extra(&st, "sim_steps");
        if (f < 2 || !(wall > 0) || !(steps > 0))
            continue;
        steps_ms[n] = cpu * extra(&st, "simulate_s") / wall / steps * 1e3;
        maps_ms[n++] = cpu * extra(&st, "map_s") / wall * 1e3;
    }
    *step_ms = median(steps_ms, n);
    *map_ms = median(maps_ms, n);
    mr_film_free(film);
    mr_renderer_free(r);
    mr_device_free(one);
}

static double med(const double *v, int n)
{
    double tmp[256];
    memcpy(tmp, v, (size_t)n * sizeof *v);
    return median(tmp, n);
}

static double wall_now(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + t.tv_nsec * 1e-9;
}

/* ---- the parallel loop's workers: the pool against threads per call */

/* About half a microsecond of arithmetic per item. */
static void busy_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    volatile double *sink = ctx;
    double x = 1.0;
    for (size_t i = begin; i < end; i++)
        for (int k = 0; k < 400; k++)
            x = x * 1.0000001 + 1e-9;
    *sink += x;
}

/* Microseconds per call of a loop of 64 half-microsecond items on
 * `loop_threads` threads: what starting the workers costs a short loop. */
static void loop_overhead(void)
{
    enum { CALLS = 300, REPEATS = 9 };
    double us[2][3][REPEATS];
    volatile double sink = 0;
    for (int r = 0; r < REPEATS; r++)
        for (int pool = 0; pool < 2; pool++)
            for (unsigned t = 1; t <= 2; t++) {
                mr_parallel_use_pool(pool);
                double t0 = wall_now();
                for (int c = 0; c < CALLS; c++)
                    mr_parallel_for(t, 64, 1, busy_range, (void *)&sink);
                us[pool][t][r] = (wall_now() - t0) / CALLS * 1e6;
            }
    mr_parallel_use_pool(true);
    printf("\nthe parallel loop: a loop of 64 items of ~0.5 us, us per call (median of %d x %d calls): "
           "1 thread %.1f; 2 threads started per call %.1f, on the pool %.1f\n",
           REPEATS, CALLS, median(us[1][1], REPEATS), median(us[0][2], REPEATS), median(us[1][2], REPEATS));
}

/* The curvature-corrected job and the 32^3 cube, each on 1 and 2
 * threads, with threads started per call and on the pool: 8 renderers
 * (a 16x9 film: tracing all but free) interleaved frame by frame, wall
 * clock of the kind's own phases. */
static void pool_against_per_call(mr_job *curv, mr_asset *wuson, mr_job *cube, mr_asset *box)
{
    enum { CONFIGS = 8 };
    mr_device *dev[3] = {NULL, NULL, NULL};
    mr_renderer *r[CONFIGS];
    mr_film *film = NULL;
    mr_error err;
    mr_job *jobs[2] = {curv, cube};
    mr_asset *assets[2] = {wuson, box};
    for (int k = 0; k < 2; k++) {
        jobs[k]->output.width = 16;
        jobs[k]->output.height = 9;
        jobs[k]->output.spp = 1;
    }
    if (mr_device_new(1, &dev[1], &err) < 0 || mr_device_new(2, &dev[2], &err) < 0 ||
        mr_film_new(16, 9, &film, &err) < 0)
        die("device", err.msg);
    /* config: job (k / 4), pool ((k / 2) % 2), threads (1 + k % 2) */
    for (int k = 0; k < CONFIGS; k++)
        if (mr_renderer_new(dev[1 + k % 2], jobs[k / 4], &assets[k / 4], NULL, &r[k], &err) < 0)
            die("renderer", err.msg);
    int n = 0, count = frames + 12;
    static double step_ms[CONFIGS][256], map_ms[CONFIGS][256];
    for (int f = 0; f < count; f++) {
        for (int k = 0; k < CONFIGS; k++) {
            mr_parallel_use_pool((k / 2) % 2);
            mr_frame_stats st;
            if (mr_renderer_render(r[k], (size_t)f, film, &st, &err) < 0)
                die("render", err.msg);
            if (f < 2)
                continue;
            double steps = extra(&st, "sim_steps");
            step_ms[k][n] = steps > 0 ? extra(&st, "simulate_s") / steps * 1e3 : 0;
            map_ms[k][n] = extra(&st, "map_s") * 1e3;
        }
        n += f >= 2;
    }
    mr_parallel_use_pool(true);
    printf("\nworkers started per call (before issue 15's pool) against the pool, wall clock, medians over %d frames "
           "interleaved (16x9 film):\n\n",
           n);
    printf("| workers | threads | ms/step | ms/mapping (curvature) | 32^3 ms/step |\n|---|---|---|---|---|\n");
    for (int k = 0; k < 4; k++)
        printf("| %s | %d | %.3f | %.3f | %.3f |\n", k / 2 ? "pool" : "per call", 1 + k % 2, med(step_ms[k], n),
               med(map_ms[k], n), med(step_ms[k + 4], n));
    for (int k = 0; k < CONFIGS; k++)
        mr_renderer_free(r[k]);
    mr_film_free(film);
    mr_device_free(dev[1]);
    mr_device_free(dev[2]);
}

int main(int argc, char **argv)
{
    for (int i = 1; i + 1 < argc; i += 2) {
        if (!strcmp(argv[i], "--frames"))
            frames = atoi(argv[i + 1]);
        else if (!strcmp(argv[i], "--threads"))
            threads = (unsigned)atoi(argv[i + 1]);
    }
    if (frames < 4 || frames > 200)
        frames = 14;
    mr_error err;
    mr_device *dev = NULL;
    if (mr_device_new(threads, &dev, &err) < 0)
        die("device", err.msg);
    char text[4096], block[1024];
    mr_job *jobs[RUNS];
    mr_asset *assets[RUNS];
    for (int k = 0; k < 4; k++) {
        snprintf(block, sizeof block, SM_BLOCK, MAPPINGS[k]);
        snprintf(text, sizeof text, PAPER_JOB, "springmass", block);
        jobs[k] = parse(text);
    }
    snprintf(text, sizeof text, PAPER_JOB, "mesh", "");
    jobs[4] = parse(text);
    mr_asset *refined = bench_load_asset(&jobs[0]->assets[0], threads);
    for (int k = 0; k < RUNS; k++)
        assets[k] = refined;
    series s[RUNS];
    run_interleaved(dev, jobs, assets, RUNS, s);
    printf("\nspring-mass (paper 001): %.0f nodes, %zu faces (Wuson refined), 15 steps per frame, %u threads,\n"
           "960x540 1 spp with shadows; medians over frames 2..%d, the four mappings and the undeformed\n"
           "mesh rendered interleaved\n\n",
           s[0].nodes, mr_asset_triangle_count(refined), threads, frames - 1);
    printf("| mapping | ms/step | substeps | ms/substep | ms/mapping | pose ms | refit ms | trace ms | frame ms | frame / undeformed |\n");
    printf("|---|---|---|---|---|---|---|---|---|---|\n");
    double undeformed = med(s[4].frame_ms, s[4].n);
    for (int k = 0; k < 4; k++)
        printf("| %s | %.3f | %.0f | %.3f | %.3f | %.2f | %.2f | %.2f | %.2f | %.2f |\n", MAPPINGS[k],
               med(s[k].step_ms, s[k].n), med(s[k].substeps, s[k].n), med(s[k].sub_ms, s[k].n),
               med(s[k].map_ms, s[k].n),
               med(s[k].pose_ms, s[k].n), med(s[k].bvh_ms, s[k].n), med(s[k].trace_ms, s[k].n),
               med(s[k].frame_ms, s[k].n), med(s[k].frame_ms, s[k].n) / undeformed);
    printf("| undeformed mesh | | | | | %.2f | %.2f | %.2f | %.2f | 1.00 |\n", med(s[4].pose_ms, s[4].n),
           med(s[4].bvh_ms, s[4].n), med(s[4].trace_ms, s[4].n), undeformed);
    printf("\ngoals: <= 1.0 ms per step, <= 2.0 ms per curvature-corrected mapping, a frame within 2x of the\n"
           "undeformed mesh's (the paper, 2005 GPU: 2.22 ms per step, 6.67 / 5.26 ms per mapping with /\n"
           "without curvature correction)\n");
    printf("\nthe work (one thread, CPU time, apart from the machine's other load): ");
    for (int k = 0; k < 4; k++) {
        double step_ms, map_ms;
        work_per_step(jobs[k], refined, &step_ms, &map_ms);
        printf("%s%s %.3f ms/step %.3f ms/mapping", k ? "; " : "", MAPPINGS[k], step_ms, map_ms);
    }
    printf("\n");

    /* 32^3 nodes: a unit cube at spacing 1/32.5 (32 lattice points inside per axis) */
    snprintf(text, sizeof text, CUBE_JOB, 1.0 / 32.5);
    mr_job *cube = parse(text);
    mr_asset *box = bench_load_asset(&cube->assets[0], threads);
    loop_overhead();
    pool_against_per_call(jobs[2], refined, cube, box);
    for (int k = 0; k < RUNS; k++)
        mr_job_free(jobs[k]);
    mr_asset_free(refined);
    cube->output.width = 320; /* the cube's own run below: its job's film */
    cube->output.height = 240;
    series c;
    run_interleaved(dev, &cube, &box, 1, &c);
    double cube_work, cube_map;
    work_per_step(cube, box, &cube_work, &cube_map);
    printf("\n32^3 grid: %.0f nodes filling a unit cube, %u threads: %.3f ms per step (%.0f substeps, %.3f ms "
           "each; one thread's CPU time: %.3f ms per step); Projective Dynamics: 3.1 ms per iteration for ~16k "
           "vertices (CPU)\n",
           c.nodes, threads, med(c.step_ms, c.n), med(c.substeps, c.n), med(c.sub_ms, c.n), cube_work);
    mr_job_free(cube);
    mr_asset_free(box);
    mr_device_free(dev);
    return 0;
}
