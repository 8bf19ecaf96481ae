/*
 * bench_dmm.c - displaced micro-mesh benchmarks (issue 4, paper 000). Not a
 * test: it prints figures, it never fails on a time.
 *
 * Scene: the skinned-walk example's dancer (X/BCN_Epileptic.X, a real rig
 * and clip) made detailed by refine.h (2 Loop rounds + gradient-noise
 * detail, 82k triangles), baked to DMMs with 1/16 of its triangles as base
 * triangles (~5k, the paper's figure), traced
 * with primary rays only (1 sample, no shadows), as the paper's Table 1.
 * For each level, five renderers run the same frames interleaved (frame f in
 * every mode before frame f + 1), so their timings are side by side (the
 * DMMs with their default, smooth normals):
 *   tess-b  mode tessellated, deformation base   (pre-tessellated baseline)
 *   base    mode base         (skinned base mesh, prism bounds: Alg. 2/4)
 *   tess-i  mode tessellated, deformation interpolated
 *   interp  mode interpolated (interpolated matrices, Bezier bounds: Alg. 1/3)
 *   truth   the detailed mesh skinned directly with LBS (ground truth)
 * Reported per level: median trace time per frame and ratios; accuracy of
 * each tessellation-free mode against its own tessellation (must be exact up
 * to intersector rounding) and of both deformations against the ground
 * truth (coverage, depth RMS / diagonal, mean normal error, stray pixels);
 * the bake's own accuracy in the rest pose, where no deformation differs
 * (the same figures against the detailed mesh, its normals taken both as
 * its facets and as its smooth vertex normals, for the DMM's flat and its
 * smooth normals); per-frame acceleration
 * update (pose + BVH) of the DMM against the pre-tessellated refit; bytes
 * per micro-triangle.
 *
 * Configurations are levels 2..5 (every base triangle at that level) and
 * "4a": adaptive levels up to 4 (each base triangle at the level matching
 * the detail's density, dmm_bake.h).
 *
 * usage: bench_dmm [--frames N] [--levels 2,3,4a,...]  (run from the repository root)
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "asset/asset.h"
#include "asset/refine.h"
#include "files.h"
#include "kinds/dmm/dmm_bake.h"
#include "kinds/dmm/dmm_encode.h"
#include "kinds/dmm/dmm_kind.h"
#include "kinds/dmm/micromesh.h"
#include "kinds/mesh/mesh_kind.h"
#include "job_json.h"
#include "render/compare.h"
#include "render/renderer.h"
#include "util/clock.h"
#include "util/parallel.h"
#include "bench_util.h"

#define JOB_PATH "examples/skinned-walk.json"
#define MODES 5
#define MAX_FRAMES 64

static const char *const MODE_NAME[MODES] = {"tess-b", "base", "tess-i", "interp", "truth"};

static void die(const char *what, const char *msg)
{
    fprintf(stderr, "bench_dmm: %s: %s\n", what, msg);
    exit(1);
}

static mr_job *load_job(void)
{
    char *text;
    size_t len;
    mr_error err = {0};
    mr_job_error jerr = {0};
    mr_job *job = NULL;
    if (mr_file_read(JOB_PATH, MR_JOB_MAX_BYTES, &text, &len, &err) < 0)
        die(JOB_PATH, err.msg);
    if (mr_job_parse(text, len, &job, &jerr) < 0)
        die(JOB_PATH, jerr.message);
    free(text);
    job->output.width = 480;
    job->output.height = 270;
    job->output.spp = 1;
    job->output.shadows = false;
    return job;
}

/* The dancer with surface detail: 2 Loop rounds, noise of 0.4 % of its
 * height at a few bumps per limb. */
static mr_asset *detailed_dancer(const char *path)
{
    mr_error err = {0};
    mr_asset *a = NULL, *r = NULL;
    if (mr_asset_load(path, &a, &err) < 0)
        die(path, err.msg);
    mr_refine_params p = {.rounds = 2, .amplitude = 0.006f, .frequency = 12.0f, .octaves = 3,
                          .seed = 1};
    if (mr_refine_asset(a, &p, &r, &err) < 0)
        die("refine", err.msg);
    mr_asset_free(a);
    return r;
}

/* A bake configuration: largest level, and whether levels are adaptive. */
typedef struct config {
    unsigned level;
    bool adaptive;
} config;

static const char *config_name(config c)
{
    static const char *const uniform[] = {"0", "1", "2", "3", "4", "5"},
                             *const adaptive[] = {"0a", "1a", "2a", "3a", "4a", "5a"};
    return c.adaptive ? adaptive[c.level] : uniform[c.level];
}

/* What the bake report measured of a configuration. */
typedef struct bake_figures {
    uint64_t micro;       /* micro-triangles (after decimation) */
    uint64_t stored;      /* bytes of the encodings: level bytes + records */
} bake_figures;

typedef struct level_result {
    config cfg;
    uint64_t micro;
    double trace_ms[MODES], update_ms[MODES];
    mr_compare_result self[2];  /* base vs tess-b, interp vs tess-i (worst frame) */
    double truth_cov[4], truth_depth[4], truth_normal[4]; /* mean over frames, modes 0..3 */
    size_t truth_strays[4];                               /* summed over frames */
    double bytes_dmm_stored, bytes_dmm_resident, bytes_tess;
} level_result;

static void worst(mr_compare_result *acc, const mr_compare_result *c, bool first)
{
    if (first || c->coverage_pct > acc->coverage_pct)
        acc->coverage_pct = c->coverage_pct;
    if (first || c->depth_max > acc->depth_max)
        acc->depth_max = c->depth_max;
    if (first || c->depth_rmse > acc->depth_rmse)
        acc->depth_rmse = c->depth_rmse;
    if (first || c->hit_one > acc->hit_one)
        acc->hit_one = c->hit_one;
}

/* Each mode gets its own device, so Embree's memory monitor counts only
 * that mode's BVH. */
static level_result run_level(mr_job *job, mr_asset *dancer, config cfg, bake_figures bake,
                              int frames)
{
    level_result res = {.cfg = cfg};
    mr_object_desc *o = &job->objects[0];
    mr_device *dev[MODES] = {0};
    mr_renderer *r[MODES] = {0};
    mr_film *film[MODES] = {0};
    mr_error err = {0};
    mr_asset *assets[1] = {dancer};
    /* each mode's parameters live as long as its renderer; the job's own
     * kind and parameters are put back before returning (mr_job_free owns
     * them) */
    const mr_kind *job_kind = o->kind;
    void *job_params = o->params;
    mr_dmm_params params[MODES];
    for (int m = 0; m < MODES; m++) {
        params[m] = (mr_dmm_params){.level = cfg.level,
                                    .levels = cfg.adaptive ? MR_DMM_LEVELS_ADAPTIVE
                                                           : MR_DMM_LEVELS_UNIFORM,
                                    .base_ratio = 0.0625f,
                                    .mode = m == 1   ? MR_DMM_BASE
                                            : m == 3 ? MR_DMM_INTERPOLATED
                                                     : MR_DMM_TESSELLATED,
                                    .deform = m >= 2 ? MR_DMM_DEFORM_INTERPOLATED
                                                     : MR_DMM_DEFORM_BASE,
                                    .normals = MR_DMM_NORMALS_SMOOTH};
        o->kind = m == 4 ? &mr_kind_mesh : &mr_kind_dmm;
        o->params = m == 4 ? NULL : &params[m];
        if (mr_device_new(0, &dev[m], &err) < 0 ||
            mr_renderer_new(dev[m], job, assets, NULL, &r[m], &err) < 0 ||
            mr_film_new(job->output.width, job->output.height, &film[m], &err) < 0)
            die(MODE_NAME[m], err.msg);
    }
    double trace[MODES][MAX_FRAMES], update[MODES][MAX_FRAMES];
    int n = 0;
    size_t step = job->frame_count / (size_t)frames;
    step = step ? step : 1;
    mr_frame_stats st[MODES];
    for (size_t f = step / 2; f < job->frame_count && n < frames; f += step, n++) {
        for (int m = 0; m < MODES; m++) {
            if (mr_renderer_render(r[m], f, film[m], &st[m], &err) < 0)
                die(MODE_NAME[m], err.msg);
            trace[m][n] = st[m].trace_s * 1e3;
            update[m][n] = (st[m].pose_s + st[m].bvh_s) * 1e3;
        }
        /* one diagonal for all comparisons: the ground truth's */
        double diag = st[4].scene_diagonal;
        mr_compare_result c;
        for (int k = 0; k < 2; k++) {
            if (mr_film_compare(film[2 * k], film[2 * k + 1], diag, &c, &err) < 0)
                die("compare", err.msg);
            worst(&res.self[k], &c, n == 0);
        }
        for (int m = 0; m < 4; m++) {
            if (mr_film_compare(film[4], film[m], diag, &c, &err) < 0)
                die("compare", err.msg);
            res.truth_cov[m] += c.coverage_pct / frames;
            res.truth_depth[m] += c.depth_rmse / frames;
            res.truth_normal[m] += c.normal_mean_deg / frames;
            mr_compare_result st_c;
            if (mr_film_compare(film[m], film[4], diag, &st_c, &err) < 0)
                die("compare", err.msg);
            res.truth_strays[m] += st_c.strays;
        }
    }
    /* the first frame builds every BVH; the update figures are refits */
    for (int m = 0; m < MODES; m++) {
        res.trace_ms[m] = median(trace[m], n);
        res.update_ms[m] = n > 1 ? median(update[m] + 1, n - 1) : update[m][0];
    }
    res.micro = st[0].triangles;
    if (res.micro != bake.micro)
        die("bench", "the renderer and the bake report disagree on the micro-triangle count");
    res.bytes_dmm_stored = ((double)bake.stored + (double)st[1].bvh_bytes) / (double)res.micro;
    res.bytes_dmm_resident =
        (double)(st[1].geometry_bytes + st[1].bvh_bytes) / (double)res.micro;
    res.bytes_tess = (double)(st[0].geometry_bytes + st[0].bvh_bytes) / (double)res.micro;
    for (int m = 0; m < MODES; m++) {
        mr_film_free(film[m]);
        mr_renderer_free(r[m]);
        mr_device_free(dev[m]);
    }
    o->kind = job_kind;
    o->params = job_params;
    return res;
}

/* The baker's report in the rest pose (issue 4 part 1): what a DMM of each
 * level costs and how far its surface is from the detailed mesh. */
static void bake_report(const mr_asset *dancer, const config *cfg, int count, bake_figures *out)
{
    printf("Bake (rest pose, all meshes): size and distance of the DMM surface to the detailed "
           "mesh (relative to the rest-pose bounding-box diagonal):\n\n"
           "| level | base tris | micro-tris | bytes | bits/micro-tri | RMS distance | max "
           "distance | unmatched %% | quantisation max | bake s |\n"
           "|---|---|---|---|---|---|---|---|---|---|\n");
    float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (size_t i = 0; i < dancer->mesh_count; i++)
        for (uint32_t v = 0; v < dancer->meshes[i].vertex_count; v++)
            for (int k = 0; k < 3; k++) {
                float x = dancer->meshes[i].positions[v * 3 + k];
                lo[k] = x < lo[k] ? x : lo[k];
                hi[k] = x > hi[k] ? x : hi[k];
            }
    mr_umesh_topology topo;
    mr_error terr = {0};
    if (mr_umesh_topology_init(&topo, MR_UMESH_MAX_LEVEL, &terr) < 0)
        die("topology", terr.msg);
    double diag = sqrt((double)(hi[0] - lo[0]) * (hi[0] - lo[0]) +
                       (double)(hi[1] - lo[1]) * (hi[1] - lo[1]) +
                       (double)(hi[2] - lo[2]) * (hi[2] - lo[2]));
    for (int l = 0; l < count; l++) {
        uint64_t base = 0, micro = 0, bytes = 0, samples = 0, unmatched = 0, vertices = 0;
        double sum2 = 0, worst = 0, quant = 0, t0 = mr_now();
        for (size_t i = 0; i < dancer->mesh_count; i++) {
            mr_dmm_bake_params bp = mr_dmm_bake_params_default();
            bp.level = cfg[l].level;
            bp.adaptive = cfg[l].adaptive;
            bp.target_ratio = 0.0625f;
            mr_dmm_bake *b = NULL;
            mr_dmm_encoded *enc = NULL;
            mr_dmm_encode_stats es;
            mr_error err = {0};
            uint8_t bits[MR_UMESH_MAX_LEVEL + 1];
            mr_dmm_default_bits(bits);
            if (mr_dmm_bake_run(&dancer->meshes[i], &bp, &b, &err) < 0 ||
                mr_dmm_encode(b->level, bits, b->base_triangle_count, b->tri_info, b->displacements, &enc, &es,
                              &err) < 0)
                die("bake", err.msg);
            base += b->base_triangle_count;
            for (uint32_t t = 0; t < b->base_triangle_count; t++) {
                micro += topo.count[mr_dmm_info_level(b->tri_info[t])]
                                   [mr_dmm_info_decimate(b->tri_info[t])];
                vertices += mr_umesh_vertex_count(mr_dmm_info_level(b->tri_info[t]));
            }
            unmatched += b->fallback_count;
            bytes += (uint64_t)enc->triangle_count + enc->records_bytes;
            sum2 += b->rms_distance * b->rms_distance * (double)b->sample_count;
            samples += b->sample_count;
            worst = b->max_distance > worst ? b->max_distance : worst;
            quant = es.max_error > quant ? es.max_error : quant;
            mr_dmm_encoded_free(enc);
            mr_dmm_bake_free(b);
        }
        out[l] = (bake_figures){.micro = micro, .stored = bytes};
        printf("| %s | %llu | %llu | %llu | %.2f | %.2e | %.2e | %.3f | %.2e | %.2f |\n",
               config_name(cfg[l]),
               (unsigned long long)base, (unsigned long long)micro, (unsigned long long)bytes,
               8.0 * (double)bytes / (double)micro, sqrt(sum2 / (double)samples) / diag,
               worst / diag, 100.0 * (double)unmatched / (double)vertices, quant / diag,
               mr_now() - t0);
    }
    mr_umesh_topology_free(&topo);
    printf("\n");
}

/* The bake's own accuracy: every level in the rest pose (where the base
 * and interpolated deformations are the identity alike, so only the bake
 * and its encoding differ from the detailed mesh), tessellated (the same
 * micro-triangles the tessellation-free modes hit), against the detailed
 * mesh with its smooth vertex normals and with its facets' normals. A DMM
 * carries no normals: its micro-triangles are shaded by their own, so as
 * it converges to the detailed surface its normals converge to the
 * detail's facets, not to the detail's interpolated vertex normals. */
static void rest_accuracy(mr_job *job, mr_asset *dancer, const config *cfg, int count, int frames)
{
    mr_object_desc *o = &job->objects[0];
    const mr_kind *job_kind = o->kind;
    void *job_params = o->params;
    size_t job_poses = o->pose_count;
    o->pose_count = 0;
    o->kind = &mr_kind_mesh;
    o->params = NULL;
    mr_error err = {0};
    mr_device *dev = NULL;
    if (mr_device_new(0, &dev, &err) < 0)
        die("device", err.msg);
    /* the detailed mesh in the rest pose, world space, by its facets */
    mr_geom *mg = NULL;
    mr_kind_context kc = {0};
    mr_mat4 identity = mr_mat4_identity();
    mr_geom_frame gf = {0};
    mr_trimesh tm;
    if (mr_kind_mesh.create(dancer, o, &kc, &mg, &err) < 0 ||
        mr_kind_mesh.update(mg, &gf, NULL, &identity, 0, &err) < 0 ||
        mr_kind_mesh.tessellate(mg, &tm, &err) < 0)
        die("rest mesh", err.msg);
    mr_kind_mesh.free(mg);
    mr_asset *facets = NULL;
    if (mr_asset_faceted("facets", tm.positions, tm.vertex_count, tm.indices, tm.triangle_count,
                         &facets, &err) < 0)
        die("facets", err.msg);
    mr_trimesh_free(&tm);
    mr_asset *smooth_assets[1] = {dancer}, *facet_assets[1] = {facets};
    int w = job->output.width, h = job->output.height;
    mr_renderer *smooth = NULL, *flat = NULL;
    if (mr_renderer_new(dev, job, smooth_assets, NULL, &smooth, &err) < 0 ||
        mr_renderer_new(dev, job, facet_assets, NULL, &flat, &err) < 0)
        die("rest truth", err.msg);
    mr_film *ts[MAX_FRAMES], *tf[MAX_FRAMES];
    size_t index[MAX_FRAMES];
    int n = 0;
    size_t step = job->frame_count / (size_t)frames;
    step = step ? step : 1;
    double floor_deg = 0, diag = 1;
    for (size_t f = step / 2; f < job->frame_count && n < frames; f += step, n++) {
        mr_frame_stats st;
        index[n] = f;
        if (mr_film_new(w, h, &ts[n], &err) < 0 || mr_film_new(w, h, &tf[n], &err) < 0 ||
            mr_renderer_render(smooth, f, ts[n], &st, &err) < 0 ||
            mr_renderer_render(flat, f, tf[n], &st, &err) < 0)
            die("rest truth", err.msg);
        diag = st.scene_diagonal;
        mr_compare_result c;
        if (mr_film_compare(tf[n], ts[n], diag, &c, &err) < 0)
            die("compare", err.msg);
        floor_deg += c.normal_mean_deg / frames;
    }
    mr_renderer_free(smooth);
    mr_renderer_free(flat);
    printf("\nThe bake alone: rest pose, tessellated, against the detailed mesh (mean over %d "
           "views; the detail's own facets differ from its smooth normals by %.2f deg):\n\n"
           "| level | coverage %% | depth RMS | flat normals vs facets deg | flat vs smooth deg | "
           "smooth normals vs smooth deg | strays |\n|---|---|---|---|---|---|---|\n",
           n, floor_deg);
    o->kind = &mr_kind_dmm;
    for (int l = 0; l < count; l++) {
        /* the same micro-triangles with flat normals and with smooth ones */
        mr_dmm_params params[2];
        mr_renderer *r[2] = {NULL, NULL};
        mr_film *film[2] = {NULL, NULL};
        for (int k = 0; k < 2; k++) {
            params[k] = (mr_dmm_params){.level = cfg[l].level,
                                        .levels = cfg[l].adaptive ? MR_DMM_LEVELS_ADAPTIVE
                                                                  : MR_DMM_LEVELS_UNIFORM,
                                        .base_ratio = 0.0625f,
                                        .mode = MR_DMM_TESSELLATED,
                                        .deform = MR_DMM_DEFORM_INTERPOLATED,
                                        .normals = k ? MR_DMM_NORMALS_SMOOTH
                                                     : MR_DMM_NORMALS_GEOMETRIC};
            o->params = &params[k];
            if (mr_renderer_new(dev, job, smooth_assets, NULL, &r[k], &err) < 0 ||
                mr_film_new(w, h, &film[k], &err) < 0)
                die("rest dmm", err.msg);
        }
        double cov = 0, depth = 0, nf = 0, nfs = 0, ns = 0;
        size_t strays = 0;
        for (int k = 0; k < n; k++) {
            mr_frame_stats st;
            mr_compare_result c;
            if (mr_renderer_render(r[0], index[k], film[0], &st, &err) < 0 ||
                mr_renderer_render(r[1], index[k], film[1], &st, &err) < 0 ||
                mr_film_compare(tf[k], film[0], diag, &c, &err) < 0)
                die("rest dmm", err.msg);
            cov += c.coverage_pct / n;
            depth += c.depth_rmse / n;
            nf += c.normal_mean_deg / n;
            if (mr_film_compare(ts[k], film[0], diag, &c, &err) < 0)
                die("compare", err.msg);
            nfs += c.normal_mean_deg / n;
            if (mr_film_compare(ts[k], film[1], diag, &c, &err) < 0)
                die("compare", err.msg);
            ns += c.normal_mean_deg / n;
            if (mr_film_compare(film[0], ts[k], diag, &c, &err) < 0)
                die("compare", err.msg);
            strays += c.strays;
        }
        printf("| %s | %.3f | %.2e | %.2f | %.2f | %.2f | %zu |\n", config_name(cfg[l]), cov, depth,
               nf, nfs, ns, strays);
        fflush(stdout);
        for (int k = 0; k < 2; k++) {
            mr_film_free(film[k]);
            mr_renderer_free(r[k]);
        }
    }
    printf("\n");
    for (int k = 0; k < n; k++) {
        mr_film_free(ts[k]);
        mr_film_free(tf[k]);
    }
    mr_asset_free(facets);
    mr_device_free(dev);
    o->kind = job_kind;
    o->params = job_params;
    o->pose_count = job_poses;
}

int main(int argc, char **argv)
{
    int frames = 5;
    config cfg[8] = {{2, false}, {3, false}, {4, false}, {5, false}, {4, true}};
    int count = 5;
    for (int i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--frames") == 0 && i + 1 < argc) {
            frames = atoi(argv[++i]);
        } else if (strcmp(argv[i], "--levels") == 0 && i + 1 < argc) {
            count = 0;
            for (char *s = argv[++i]; *s && count < 8; s++)
                if (*s >= '0' && *s <= '5')
                    cfg[count++] = (config){(unsigned)(*s - '0'), s[1] == 'a'};
        } else {
            fprintf(stderr, "usage: bench_dmm [--frames N] [--levels 2,3,4a,...]\n");
            return 2;
        }
    }
    if (frames < 1 || frames > MAX_FRAMES)
        frames = 5;
    mr_job *job = load_job();
    mr_asset *dancer = detailed_dancer(job->assets[0].path);
    uint64_t detail = 0;
    for (size_t i = 0; i < dancer->mesh_count; i++)
        detail += dancer->meshes[i].triangle_count;
    printf("\n## Displaced micro-meshes (paper 000): %s refined to %llu triangles, 1/16 as base "
           "triangles, %dx%d primary rays, %d frames, %u threads\n\n",
           JOB_PATH, (unsigned long long)detail, job->output.width, job->output.height, frames,
           mr_cpu_count());
    bake_figures bake[8];
    bake_report(dancer, cfg, count, bake);
    rest_accuracy(job, dancer, cfg, count, frames);
    level_result res[8];
    for (int i = 0; i < count; i++) {
        res[i] = run_level(job, dancer, cfg[i], bake[i], frames);
        fflush(stdout);
    }
    printf("Trace time per frame (median, ms) and ratios, side by side:\n\n");
    printf("| level | micro-tris | tess-b | base | tess-i | interp | truth | base/tess-b | "
           "interp/tess-i | interp/base |\n|---|---|---|---|---|---|---|---|---|---|\n");
    for (int i = 0; i < count; i++) {
        const level_result *x = &res[i];
        printf("| %s | %llu | %.1f | %.1f | %.1f | %.1f | %.1f | %.2f | %.2f | %.2f |\n",
               config_name(x->cfg), (unsigned long long)x->micro, x->trace_ms[0], x->trace_ms[1],
               x->trace_ms[2], x->trace_ms[3], x->trace_ms[4], x->trace_ms[1] / x->trace_ms[0],
               x->trace_ms[3] / x->trace_ms[2], x->trace_ms[3] / x->trace_ms[1]);
    }
    printf("\nTessellation-free vs its own tessellation (worst frame; diagonal-relative depth):\n\n"
           "| level | base: pixels differing | base: depth max | interp: pixels differing | "
           "interp: depth max |\n|---|---|---|---|---|\n");
    for (int i = 0; i < count; i++)
        printf("| %s | %zu | %.2e | %zu | %.2e |\n", config_name(res[i].cfg), res[i].self[0].hit_one,
               res[i].self[0].depth_max, res[i].self[1].hit_one, res[i].self[1].depth_max);
    printf("\nError against the detailed mesh skinned with LBS (mean over frames; strays: "
           "pixels hit more than one pixel away from the truth's silhouette, summed):\n\n"
           "| level | base: coverage %% | base: depth RMS | base: normal deg | base: strays | "
           "interp: coverage %% | interp: depth RMS | interp: normal deg | interp: strays "
           "|\n|---|---|---|---|---|---|---|---|---|\n");
    for (int i = 0; i < count; i++)
        printf("| %s | %.3f | %.2e | %.2f | %zu | %.3f | %.2e | %.2f | %zu |\n",
               config_name(res[i].cfg), res[i].truth_cov[1], res[i].truth_depth[1],
               res[i].truth_normal[1], res[i].truth_strays[1], res[i].truth_cov[3],
               res[i].truth_depth[3], res[i].truth_normal[3], res[i].truth_strays[3]);
    printf("\nPer-frame acceleration update (pose + BVH refit, median ms) and memory:\n\n"
           "| level | tess-b | base | interp | base/tess-b | DMM stored B/micro-tri | DMM "
           "resident B/micro-tri | tessellated B/micro-tri |\n|---|---|---|---|---|---|---|---|\n");
    for (int i = 0; i < count; i++)
        printf("| %s | %.2f | %.3f | %.3f | 1/%.0f | %.2f | %.2f | %.1f |\n", config_name(res[i].cfg),
               res[i].update_ms[0], res[i].update_ms[1], res[i].update_ms[3],
               res[i].update_ms[0] / res[i].update_ms[1], res[i].bytes_dmm_stored,
               res[i].bytes_dmm_resident, res[i].bytes_tess);
    mr_asset_free(dancer);
    mr_job_free(job);
    return 0;
}
