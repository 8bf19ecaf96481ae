/*
 * bench_svo.c - sparse voxel octree deformation benchmarks (issue 5, paper
 * 004, Willcocks, chapter 3). Not a test: it prints figures and never fails
 * on a time. Timings are medians over frames on a shared 2-core machine.
 *
 * Everything goes through the public API (microray.h) and the job parser,
 * as a user's jobs do: the kind's phases and counts are the frames' svo_*
 * stats fields (svo_pose_s, svo_select_s, svo_emit_s, svo_rebuild_s,
 * svo_deformed, svo_selected, svo_cells, svo_octree_bytes, svo_voxels,
 * svo_build_s; README "stats.json"), coverage comes from rendered films.
 *
 *  a. The thesis' sweep (3.4, Figs. 20-28, Tables 2-3): shear and twist
 *     0.2 .. 12.8 and uniform scale of a low-resolution human, solid voxels
 *     at depth 7 (the thesis' human: 33,720 voxels). The human is the
 *     dancer (BCN_Epileptic.X) in its rest pose, taken from the renderer
 *     (mr_renderer_tessellate) and written as a glTF whose skin is a chain
 *     of TWIST_JOINTS joints up its height: a twist by a radians is the
 *     joint overrides turning each joint by a / (joints - 1) about the
 *     vertical axis (so a voxel at height y turns by a (y - y0) / H, to
 *     within the linear blend of two neighbouring joints and the 8-bit
 *     weights); shear and scale are the instance's transform matrix. Each
 *     amount is one frame per method (direct, resize, emit) seen from far
 *     along -z through a very narrow field of view (nearly orthographic)
 *     with pixels of a quarter voxel; error = |coverage XOR direct| /
 *     |direct| and diff = (|coverage| - |direct|) / |direct| from the
 *     films' object ids, cells per voxel = svo_cells / svo_selected.
 *     This used to run the deformation field of tests/support/svo_sweep.h
 *     on the kind's internals and rasterise boxes and octree keys itself;
 *     the figures differ from those in three ways: the twist is a skin
 *     (one blended matrix per voxel) instead of the exact field at each
 *     voxel's two corners, the voxels are the rest pose's rather than bind
 *     space's, and the rebuilt octree is the renderer's (2 levels below the
 *     source, the old measurement allowed 10). The shape of the result is
 *     what is compared with the thesis.
 *  b. Per-frame cost on the dancer voxelised at depths 8, 10, 12, over
 *     frames of its clip, on 2 threads and 1: every leaf selected (delta
 *     1e-6 pixels, no culling: the view selects everything) and resampled
 *     with resize and with emit, then screen-space selection for one
 *     camera (1280 x 720, 3 heights away, delta 1). The resample's split
 *     into cell emission and rebuild (radix sort, compaction, octree build)
 *     is the kind's own (svo_emit_s, svo_rebuild_s); it used to be timed
 *     by regenerating the cells and sorting them again apart.
 *  c. Memory per voxel: the shared octree (a rigid object's geometry bytes
 *     per voxel) and a rebuilt one (svo_octree_bytes per output voxel),
 *     against Embree triangles (a static mesh job of the dancer refined by
 *     Loop rounds: geometry and BVH bytes per triangle). The old bench
 *     built Embree triangles from the voxels' exposed faces, which needs
 *     the octree's leaves: no public API shows them, so that column is
 *     gone; per primitive the comparison stands.
 *  d. Instances: the thesis deformed 10^6 instances of 6 models in 33.8 ms
 *     per frame (GTX 260). N = 1, 2, 4, ... posed dancers (depth 8, resize,
 *     each its own clip offset and turn) on a grid framed by a 1280 x 720
 *     camera: one frame's update and build (the renderer's pose_s + bvh_s),
 *     the largest N within 33.8 ms, then doubling on to 2^20, the time or a
 *     memory budget. The renderer rebuilds one octree per instance (the
 *     thesis and the old bench: one world octree for all); jobs hold at most
 *     INSTANCES_PER_JOB instances (the job document's size cap), so a larger
 *     N is rendered as several jobs of the same frame, their times summed.
 *
 * usage: bench_svo [--quick] [--only abcd]  (--quick: the sweep on surface
 * voxels at depth 6, depths 8 and 10 only, a shorter instance series;
 * --only: the parts to run, b and c together; other arguments are ignored:
 * make bench passes the same ones to every benchmark)
 */
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "job_json.h"
#include "microray.h"
#include "bench_util.h"

#define MODEL "/usr/share/assimp/models/X/BCN_Epileptic.X"
#define THESIS_MS 33.8
#define WIDTH 1280
#define HEIGHT 720
#define YFOV_DEG 45.0
#define MAX_FRAMES 8
#define TWIST_JOINTS 129
#define INSTANCES_PER_JOB 65536u

static const double GIB = 1024.0 * 1024.0 * 1024.0;
static char cache_root[512]; /* fresh per run: voxelisations are timed, then loaded */

static void die(const char *what, const char *msg)
{
    fprintf(stderr, "bench_svo: %s: %s\n", what, msg);
    exit(1);
}

/* ---- text of jobs */

typedef struct text {
    char *s;
    size_t len, cap;
} text;

static void put(text *t, const char *fmt, ...)
{
    for (;;) {
        va_list ap;
        va_start(ap, fmt);
        int n = vsnprintf(t->s ? t->s + t->len : NULL, t->s ? t->cap - t->len : 0, fmt, ap);
        va_end(ap);
        if (n < 0)
            die("text", "format");
        if (t->s && t->len + (size_t)n < t->cap) {
            t->len += (size_t)n;
            return;
        }
        t->cap = (t->cap + (size_t)n + 1) * 2;
        if (!(t->s = realloc(t->s, t->cap)))
            die("text", "out of memory");
    }
}

static mr_job *parse(text *t)
{
    mr_job *job = NULL;
    mr_job_error jerr = {0};
    if (mr_job_parse(t->s, t->len, &job, &jerr) < 0)
        die(jerr.pointer, jerr.message);
    free(t->s);
    *t = (text){0};
    return job;
}

/* ---- one renderer of one job */

typedef struct run {
    mr_job *job;
    mr_device *dev;
    mr_renderer *r;
    mr_film *film;
} run;

/* threads 0: all cores; budget 0: none. Returns MR_OK or the failure. */
static int open_run(run *x, mr_job *job, mr_asset *asset, unsigned threads, size_t budget,
                    mr_error *err)
{
    mr_asset *assets[1] = {asset};
    mr_renderer_options opt = {.cache_dir = cache_root, .memory_budget = budget};
    memset(x, 0, sizeof *x);
    x->job = job;
    int rc;
    if ((rc = mr_device_new(threads, &x->dev, err)) < 0 ||
        (rc = mr_renderer_new(x->dev, job, assets, &opt, &x->r, err)) < 0 ||
        (rc = mr_film_new(job->output.width, job->output.height, &x->film, err)) < 0)
        return rc;
    return MR_OK;
}

static void close_run(run *x)
{
    mr_film_free(x->film);
    mr_renderer_free(x->r);
    mr_device_free(x->dev);
    mr_job_free(x->job);
    memset(x, 0, sizeof *x);
}

static void render(run *x, size_t f, mr_frame_stats *st)
{
    mr_error err = {0};
    if (mr_renderer_render(x->r, f, x->film, st, &err) < 0)
        die("render", err.msg);
}

/* ---- the dancer's rest-pose triangles and their bounds */

typedef struct shape {
    double lo[3], hi[3], c[3];
    double H; /* height (y) */
    double S; /* the voxel cube's edge: the largest extent, as voxelize.h pads it */
} shape;

static void rest_triangles(mr_asset *asset, mr_trimesh *m, shape *sh)
{
    text t = {0};
    put(&t, "{\"assets\":{\"d\":{\"path\":\"" MODEL "\"}},\"objects\":[{\"asset\":\"d\"}],"
            "\"camera\":{\"path\":[{\"t\":0,\"position\":[0,1,5],\"target\":[0,1,0]}]},"
            "\"frames\":{\"times\":[0]},\"output\":{\"width\":8,\"height\":8,\"samples\":1}}");
    run x;
    mr_error err = {0};
    mr_frame_stats st;
    if (open_run(&x, parse(&t), asset, 2, 0, &err) < 0)
        die("rest pose", err.msg);
    render(&x, 0, &st);
    if (mr_renderer_tessellate(x.r, 0, m, &err) < 0)
        die("tessellate", err.msg);
    close_run(&x);
    for (int a = 0; a < 3; a++) {
        sh->lo[a] = INFINITY;
        sh->hi[a] = -INFINITY;
    }
    for (uint32_t i = 0; i < m->vertex_count; i++)
        for (int a = 0; a < 3; a++) {
            sh->lo[a] = fmin(sh->lo[a], m->positions[3 * i + a]);
            sh->hi[a] = fmax(sh->hi[a], m->positions[3 * i + a]);
        }
    sh->S = 0;
    for (int a = 0; a < 3; a++) {
        sh->c[a] = 0.5 * (sh->lo[a] + sh->hi[a]);
        sh->S = fmax(sh->S, sh->hi[a] - sh->lo[a]);
    }
    sh->S *= 1.0 + 1.0 / 512;
    sh->H = sh->hi[1] - sh->lo[1];
}

/* ---- a. the sweep */

/* The rest-pose dancer as a glTF 2.0 file (dir/twist.gltf + twist.bin) with
 * a skin of `joints` joints j0..j<joints-1> stacked up its height through
 * its centre: joint k sits at height y0 + k h (h = H / (joints - 1)); a
 * vertex at height y is weighted between the two joints around it,
 * linearly. */
static void write_twist_asset(const mr_trimesh *m, const shape *sh, unsigned joints,
                              const char *dir, char *path, size_t path_size)
{
    const uint32_t nv = m->vertex_count, nt = m->triangle_count;
    const double h = sh->H / (joints - 1);
    const size_t pos_bytes = (size_t)nv * 12, jnt_bytes = (size_t)nv * 8,
                 wgt_bytes = (size_t)nv * 16, idx_bytes = (size_t)nt * 12,
                 ibm_bytes = (size_t)joints * 64;
    const size_t total = pos_bytes + jnt_bytes + wgt_bytes + idx_bytes + ibm_bytes;
    uint8_t *bin = calloc(1, total);
    if (!bin)
        die("twist asset", "out of memory");
    uint8_t *at = bin;
    memcpy(at, m->positions, pos_bytes);
    at += pos_bytes;
    uint16_t *jnt = (uint16_t *)at;
    float *wgt = (float *)(at + jnt_bytes);
    for (uint32_t i = 0; i < nv; i++) {
        double u = (m->positions[3 * i + 1] - sh->lo[1]) / h;
        u = fmin(fmax(u, 0.0), (double)(joints - 1));
        unsigned k = (unsigned)u < joints - 2 ? (unsigned)u : joints - 2;
        float w = (float)(u - k);
        jnt[4 * i] = (uint16_t)k;
        jnt[4 * i + 1] = (uint16_t)(k + 1);
        wgt[4 * i] = 1.0f - w;
        wgt[4 * i + 1] = w;
    }
    at += jnt_bytes + wgt_bytes;
    memcpy(at, m->indices, idx_bytes);
    at += idx_bytes;
    float *ibm = (float *)at; /* column-major inverses of translations */
    for (unsigned k = 0; k < joints; k++) {
        float *q = ibm + 16 * k;
        q[0] = q[5] = q[10] = q[15] = 1;
        q[12] = (float)-sh->c[0];
        q[13] = (float)-(sh->lo[1] + k * h);
        q[14] = (float)-sh->c[2];
    }
    char bin_path[600];
    snprintf(bin_path, sizeof bin_path, "%s/twist.bin", dir);
    mr_error err = {0};
    if (mr_fs_write_atomic(bin_path, bin, total, "twist asset", &err) < 0)
        die("twist asset", err.msg);
    free(bin);

    text t = {0};
    put(&t, "{\"asset\":{\"version\":\"2.0\",\"generator\":\"microray bench_svo\"},\"scene\":0,"
            "\"scenes\":[{\"nodes\":[0,%u]}],\"nodes\":[", joints);
    for (unsigned k = 0; k < joints; k++) {
        put(&t, "{\"name\":\"j%u\",\"translation\":[%.9g,%.9g,%.9g]", k, k ? 0.0 : sh->c[0],
            k ? h : sh->lo[1], k ? 0.0 : sh->c[2]);
        if (k + 1 < joints)
            put(&t, ",\"children\":[%u]", k + 1);
        put(&t, "},");
    }
    put(&t, "{\"name\":\"body\",\"mesh\":0,\"skin\":0}],\"skins\":[{\"skeleton\":0,"
            "\"inverseBindMatrices\":4,\"joints\":[");
    for (unsigned k = 0; k < joints; k++)
        put(&t, "%s%u", k ? "," : "", k);
    put(&t, "]}],\"meshes\":[{\"name\":\"body\",\"primitives\":[{\"attributes\":{\"POSITION\":0,"
            "\"JOINTS_0\":1,\"WEIGHTS_0\":2},\"indices\":3}]}],"
            "\"buffers\":[{\"uri\":\"twist.bin\",\"byteLength\":%zu}],\"bufferViews\":[", total);
    const size_t len[5] = {pos_bytes, jnt_bytes, wgt_bytes, idx_bytes, ibm_bytes};
    size_t off = 0;
    for (int v = 0; v < 5; v++) {
        put(&t, "%s{\"buffer\":0,\"byteOffset\":%zu,\"byteLength\":%zu}", v ? "," : "", off, len[v]);
        off += len[v];
    }
    put(&t, "],\"accessors\":["
            "{\"bufferView\":0,\"componentType\":5126,\"count\":%u,\"type\":\"VEC3\","
            "\"min\":[%.9g,%.9g,%.9g],\"max\":[%.9g,%.9g,%.9g]},"
            "{\"bufferView\":1,\"componentType\":5123,\"count\":%u,\"type\":\"VEC4\"},"
            "{\"bufferView\":2,\"componentType\":5126,\"count\":%u,\"type\":\"VEC4\"},"
            "{\"bufferView\":3,\"componentType\":5125,\"count\":%u,\"type\":\"SCALAR\"},"
            "{\"bufferView\":4,\"componentType\":5126,\"count\":%u,\"type\":\"MAT4\"}]}",
        nv, sh->lo[0], sh->lo[1], sh->lo[2], sh->hi[0], sh->hi[1], sh->hi[2], nv, nv, 3 * nt,
        joints);
    snprintf(path, path_size, "%s/twist.gltf", dir);
    if (mr_fs_write_atomic(path, t.s, t.len, "twist asset", &err) < 0)
        die("twist asset", err.msg);
    free(t.s);
}

typedef enum deformation { SHEAR = 0, TWIST, SCALE } deformation;
static const char *const DEFORMATION[] = {"shear", "twist", "scale"};
enum { DIRECT = 0, RESIZE, EMIT, METHODS };
static const char *const METHOD[METHODS] = {"direct", "resize", "emit"};

typedef struct sweep_setup {
    mr_asset *asset; /* the twist asset */
    const char *path;
    shape sh;
    unsigned depth;
    const char *voxelize;
    double radius; /* largest distance of a vertex from the vertical axis through the centre */
} sweep_setup;

/* The instance matrix (row-major) of a shear or scale; identity for twist. */
static void sweep_matrix(const sweep_setup *s, deformation d, double a, double m[12])
{
    memset(m, 0, 12 * sizeof *m);
    m[0] = m[5] = m[10] = 1;
    if (d == SHEAR) { /* x' = x + a (y - y0): the top moves a heights sideways */
        m[1] = a;
        m[3] = -a * s->sh.lo[1];
    } else if (d == SCALE) { /* about the centre */
        for (int k = 0; k < 3; k++) {
            m[5 * k] = a;
            m[4 * k + 3] = s->sh.c[k] * (1 - a);
        }
    }
}

/* One amount: the three methods' frames and their coverage. */
typedef struct sweep_result {
    uint64_t direct_px, px[METHODS], missing[METHODS], extra[METHODS];
    double cells[METHODS], selected[METHODS], out[METHODS];
    bool clipped; /* something was hit on the frame's border */
} sweep_result;

static void sweep_point(const sweep_setup *s, deformation d, double a, sweep_result *res)
{
    memset(res, 0, sizeof *res);
    double m[12];
    sweep_matrix(s, d, a, m);
    /* the frame: the deformed rest box (twist: the axis' circle), plus a
     * margin for boxes around turned voxels and cells rounded outwards */
    const double voxel = s->sh.S / (double)(1u << s->depth);
    double lo[2] = {INFINITY, INFINITY}, hi[2] = {-INFINITY, -INFINITY};
    for (int c = 0; c < 8; c++) {
        const double p[3] = {c & 1 ? s->sh.hi[0] : s->sh.lo[0], c & 2 ? s->sh.hi[1] : s->sh.lo[1],
                             c & 4 ? s->sh.hi[2] : s->sh.lo[2]};
        for (int r = 0; r < 2; r++) {
            double q = m[4 * r] * p[0] + m[4 * r + 1] * p[1] + m[4 * r + 2] * p[2] + m[4 * r + 3];
            lo[r] = fmin(lo[r], q);
            hi[r] = fmax(hi[r], q);
        }
    }
    if (d == TWIST) {
        lo[0] = s->sh.c[0] - s->radius;
        hi[0] = s->sh.c[0] + s->radius;
    }
    const double margin = voxel * (d == SHEAR ? 4 + 2 * a : d == SCALE ? 6 * fmax(a, 1) : 6);
    for (int r = 0; r < 2; r++) {
        lo[r] -= margin;
        hi[r] += margin;
    }
    double px = voxel / 4; /* the thesis renders every amount at one resolution */
    while ((ceil((hi[0] - lo[0]) / px)) * (ceil((hi[1] - lo[1]) / px)) > (double)(1u << 24) ||
           ceil((hi[0] - lo[0]) / px) > MR_MAX_RESOLUTION || ceil((hi[1] - lo[1]) / px) > MR_MAX_RESOLUTION)
        px *= 2;
    const int w = (int)ceil((hi[0] - lo[0]) / px), h = (int)ceil((hi[1] - lo[1]) / px);
    const double cx = lo[0] + 0.5 * w * px, cy = lo[1] + 0.5 * h * px;
    const double dist = 1000.0 * fmax(w * px, h * px);
    const double yfov = 2.0 * atan(0.5 * h * px / dist) * 180.0 / M_PI;
    uint8_t *direct = NULL;
    for (int k = 0; k < METHODS; k++) {
        text t = {0};
        put(&t, "{\"assets\":{\"t\":{\"path\":\"%s\"}},\"objects\":[{\"asset\":\"t\","
                "\"kind\":\"svo\",\"svo\":{\"depth\":%u,\"voxelize\":\"%s\",\"method\":\"%s\","
                "\"instances\":[{\"transform\":{\"matrix\":[",
            s->path, s->depth, s->voxelize, METHOD[k]);
        for (int i = 0; i < 12; i++)
            put(&t, "%.9g,", m[i]);
        put(&t, "0,0,0,1]}}]}");
        if (d == TWIST) {
            const double step = a / (TWIST_JOINTS - 1);
            const double hs = s->sh.H / (TWIST_JOINTS - 1);
            put(&t, ",\"pose\":{\"joints\":{\"j0\":{\"translation\":[%.9g,%.9g,%.9g]}",
                s->sh.c[0], s->sh.lo[1], s->sh.c[2]);
            for (unsigned j = 1; j < TWIST_JOINTS; j++)
                put(&t, ",\"j%u\":{\"translation\":[0,%.9g,0],\"rotation\":[0,%.9g,0,%.9g]}", j,
                    hs, sin(0.5 * step), cos(0.5 * step));
            put(&t, "}}");
        }
        put(&t, "}],\"camera\":{\"yfov\":%.9g,\"path\":[{\"t\":0,\"position\":[%.9g,%.9g,%.9g],"
                "\"target\":[%.9g,%.9g,%.9g]}]},\"frames\":{\"times\":[0]},"
                "\"output\":{\"width\":%d,\"height\":%d,\"samples\":1,\"shadows\":false}}",
            yfov, cx, cy, s->sh.c[2] + dist, cx, cy, s->sh.c[2], w, h);
        run x;
        mr_error err = {0};
        mr_frame_stats st;
        if (open_run(&x, parse(&t), s->asset, 0, 0, &err) < 0)
            die("sweep", err.msg);
        render(&x, 0, &st);
        res->cells[k] = frame_extra(&st, "svo_cells");
        res->selected[k] = frame_extra(&st, "svo_selected");
        res->out[k] = (double)st.triangles;
        const size_t n = (size_t)w * (size_t)h;
        const uint32_t *id = x.film->object_id;
        for (int y = 0; y < h; y++)
            res->clipped |= id[(size_t)y * w] || id[(size_t)y * w + w - 1];
        for (int i = 0; i < w; i++)
            res->clipped |= id[i] || id[(size_t)(h - 1) * w + i];
        if (k == DIRECT) {
            if (!(direct = malloc(n)))
                die("sweep", "out of memory");
            for (size_t i = 0; i < n; i++)
                res->direct_px += (direct[i] = id[i] != 0);
        } else {
            for (size_t i = 0; i < n; i++) {
                const bool hit = id[i] != 0;
                res->px[k] += hit;
                res->missing[k] += direct[i] && !hit;
                res->extra[k] += !direct[i] && hit;
            }
        }
        close_run(&x);
    }
    free(direct);
}

static void part_a(bool quick)
{
    const unsigned depth = quick ? 6 : 7;
    sweep_setup s = {.depth = depth, .voxelize = quick ? "surface" : "solid"};
    mr_asset *bcn = NULL;
    mr_error err = {0};
    if (mr_asset_load(MODEL, &bcn, &err) < 0)
        die(MODEL, err.msg);
    mr_trimesh m;
    rest_triangles(bcn, &m, &s.sh);
    mr_asset_free(bcn);
    for (uint32_t i = 0; i < m.vertex_count; i++)
        s.radius = fmax(s.radius, hypot(m.positions[3 * i] - s.sh.c[0],
                                        m.positions[3 * i + 2] - s.sh.c[2]));
    char path[600];
    write_twist_asset(&m, &s.sh, TWIST_JOINTS, cache_root, path, sizeof path);
    mr_trimesh_free(&m);
    s.path = path;
    if (mr_asset_load(path, &s.asset, &err) < 0)
        die(path, err.msg);

    sweep_result rest;
    sweep_point(&s, SCALE, 1.0, &rest);
    printf("\n## SVO deformation (paper 004)\n\n### a. Resampling sweep (thesis 3.4, Figs. 20-28)\n\n"
           "The dancer's rest pose (BCN_Epileptic.X, %.2f units tall) as a glTF skinned to a chain "
           "of %d joints up its height, %s voxels at depth %u: %.0f voxels (the thesis' human: "
           "33,720). Frames along -z from %.0f heights away (nearly orthographic), pixel = 1/4 "
           "voxel. error = |coverage XOR direct| / |direct|; diff = (|coverage| - |direct|) / "
           "|direct| (the thesis' subtraction); cells per voxel emitted before compaction (Figs. "
           "27-28); out = voxels of the rebuilt octree (2 levels below the source). Shear: the "
           "instance matrix, the top moves by amount heights; twist: joint overrides, amount "
           "radians over the height; scale: the instance matrix about the centre.\n\n",
           s.sh.H, TWIST_JOINTS, s.voxelize, depth, rest.selected[DIRECT], 1000.0);
    printf("| deformation | amount | direct px | resize error | resize diff | emit error | emit "
           "diff | emit missing px | resize cells/voxel | emit cells/voxel | resize out | emit out "
           "|\n|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    const double scales[] = {0.37, 0.5, 1.0, 1.3, 2.0, 3.7};
    bool clipped = false;
    for (int d = 0; d < 3; d++) {
        const int count = d < 2 ? 7 : (int)(sizeof scales / sizeof *scales);
        for (int i = 0; i < count; i++) {
            const double amount = d < 2 ? 0.2 * (double)(1 << i) : scales[i];
            sweep_result r;
            sweep_point(&s, (deformation)d, amount, &r);
            const double dpx = r.direct_px ? (double)r.direct_px : 1.0;
            printf("| %s | %.2f | %llu |", DEFORMATION[d], amount, (unsigned long long)r.direct_px);
            for (int k = RESIZE; k <= EMIT; k++)
                printf(" %.4f | %+.4f |", (double)(r.missing[k] + r.extra[k]) / dpx,
                       ((double)r.px[k] - (double)r.direct_px) / dpx);
            printf(" %llu | %.2f | %.2f | %.0f | %.0f |%s\n", (unsigned long long)r.missing[EMIT],
                   r.cells[RESIZE] / fmax(r.selected[RESIZE], 1), r.cells[EMIT] / fmax(r.selected[EMIT], 1),
                   r.out[RESIZE], r.out[EMIT], r.clipped ? " (clipped)" : "");
            clipped |= r.clipped;
            fflush(stdout);
        }
    }
    if (clipped)
        printf("\n(clipped: some voxels reached the frame's border; those amounts undercount)\n");
    mr_asset_free(s.asset);
}

/* ---- b, c. per-frame cost and memory per depth */

/* An svo job over the dancer's clip: frames spread over it, seen from
 * `camera` (a path key's fields) at w x h; svo_fields inside "svo". */
static mr_job *clip_job(const char *svo_fields, bool posed, const char *camera, int w, int h,
                        int frames, double duration)
{
    text t = {0};
    put(&t, "{\"assets\":{\"d\":{\"path\":\"" MODEL "\"}},\"objects\":[{\"asset\":\"d\","
            "\"kind\":\"svo\",\"svo\":{%s}%s}],\"camera\":{\"yfov\":%g,\"path\":[{\"t\":0,%s}]},"
            "\"frames\":{\"times\":[",
        svo_fields, posed ? ",\"pose\":{\"clip\":0}" : "", YFOV_DEG, camera);
    for (int f = 0; f < frames; f++)
        put(&t, "%s%.9g", f ? "," : "", (f + 0.5) * duration / frames);
    put(&t, "]},\"output\":{\"width\":%d,\"height\":%d,\"samples\":1,\"shadows\":false}}", w, h);
    return parse(&t);
}

/* Per run and frame, what bench tables show. */
typedef struct phase {
    double select_ms[MAX_FRAMES], mvox_s[MAX_FRAMES], resample_ms[MAX_FRAMES],
        mcells_s[MAX_FRAMES], rebuild_ms[MAX_FRAMES], cells[MAX_FRAMES], out[MAX_FRAMES],
        selected[MAX_FRAMES], deformed[MAX_FRAMES];
    double octree_bytes; /* first frame */
    double first_select_ms, first_resample_ms; /* the run's first frame (the untimed pass's) */
    const char *skipped; /* why the run did not run, or NULL */
} phase;

static void record(phase *p, int f, const mr_frame_stats *st)
{
    const double sel = frame_extra(st, "svo_select_s");
    const double res = frame_extra(st, "svo_emit_s") + frame_extra(st, "svo_rebuild_s");
    p->select_ms[f] = sel * 1e3;
    p->deformed[f] = frame_extra(st, "svo_deformed");
    p->selected[f] = frame_extra(st, "svo_selected");
    p->mvox_s[f] = sel > 0 ? p->deformed[f] / sel * 1e-6 : 0;
    p->resample_ms[f] = res * 1e3;
    p->cells[f] = frame_extra(st, "svo_cells");
    p->mcells_s[f] = res > 0 ? p->cells[f] / res * 1e-6 : 0;
    p->rebuild_ms[f] = frame_extra(st, "svo_rebuild_s") * 1e3;
    p->out[f] = (double)st->triangles;
    if (f == 0)
        p->octree_bytes = frame_extra(st, "svo_octree_bytes");
}

typedef struct depth_row {
    unsigned depth, threads;
    double voxels;
    int frames;
    phase every[2], cam; /* resize, emit over every leaf; resize for the camera */
} depth_row;

typedef struct memory_row {
    unsigned depth;
    double voxels, voxelise_s, load_s, shared_bytes, rebuilt_bytes, rebuilt_voxels;
} memory_row;

static double med(const double *v, int n)
{
    double c[MAX_FRAMES];
    memcpy(c, v, (size_t)n * sizeof *c);
    return median(c, n);
}

static void print_phase_cells(const phase *p, int n)
{
    if (p->skipped) {
        printf("| %s | | | | ", p->skipped);
        return;
    }
    printf("| %.1f | %.1f | %.1f | %.0f | %.0f ", med(p->resample_ms, n), med(p->mcells_s, n),
           med(p->rebuild_ms, n), med(p->cells, n), med(p->out, n));
}

static void part_bc(bool quick)
{
    const unsigned depths[3] = {8, 10, 12};
    const int ndepth = quick ? 2 : 3;
    const int frames_full = quick ? 3 : 5;
    depth_row rows[6];
    memory_row mem[3];
    int nrows = 0;
    double emit_ratio = 30; /* emit cells per voxel, refined by the previous depth */
    const double budget = fmin(6.0 * GIB, 0.5 * bench_mem_available());
    mr_asset *asset = NULL;
    mr_error err = {0};
    if (mr_asset_load(MODEL, &asset, &err) < 0)
        die(MODEL, err.msg);
    if (mr_asset_clip_count(asset) < 1)
        die(MODEL, "no clip");
    const double duration = mr_asset_clip_duration(asset, 0);
    mr_trimesh m;
    shape sh;
    rest_triangles(asset, &m, &sh);
    mr_trimesh_free(&m);
    char cam[256]; /* 3 heights in front */
    snprintf(cam, sizeof cam, "\"position\":[%.9g,%.9g,%.9g],\"target\":[%.9g,%.9g,%.9g]",
             sh.c[0], sh.c[1], sh.c[2] + 3 * sh.H, sh.c[0], sh.c[1], sh.c[2]);

    for (int di = 0; di < ndepth; di++) {
        const unsigned depth = depths[di];
        memory_row *mrow = &mem[di];
        memset(mrow, 0, sizeof *mrow);
        mrow->depth = depth;
        /* the shared octree: a rigid object voxelises it (into the fresh
         * cache) and holds only it */
        {
            char f[128];
            snprintf(f, sizeof f, "\"depth\":%u,\"method\":\"rigid\"", depth);
            run x;
            mr_frame_stats st;
            if (open_run(&x, clip_job(f, false, cam, 64, 36, 1, duration), asset, 0, 0, &err) < 0)
                die("voxelise", err.msg);
            render(&x, 0, &st);
            mrow->voxels = frame_extra(&st, "svo_voxels");
            mrow->voxelise_s = frame_extra(&st, "svo_build_s");
            mrow->shared_bytes = (double)st.geometry_bytes / mrow->voxels;
            close_run(&x);
        }
        const double voxels = mrow->voxels;
        /* big frames cost seconds: fewer of them (the bench stays within ~5 minutes) */
        const int frames = voxels > 4e6 ? 1 : voxels > 4e5 ? 3 : frames_full;
        /* frames of the jobs: a job of one timed frame gets a second, the
         * untimed pass's (a frame rendered again at the same time is not
         * deformed again) */
        const int job_frames = frames == 1 ? 2 : frames;
        const bool fits[2] = {8.0 * voxels * 48.0 < budget, emit_ratio * voxels * 48.0 < budget};
        for (int ti = 0; ti < 2; ti++) {
            const unsigned threads = ti == 0 ? 2 : 1;
            /* depth 12 resamples for tens of seconds: on 2 threads only */
            const bool big = voxels > 4e6 && threads == 1;
            depth_row *row = &rows[nrows++];
            memset(row, 0, sizeof *row);
            row->depth = depth;
            row->threads = threads;
            row->voxels = voxels;
            row->frames = frames;
            run every[2] = {0}, camera = {0};
            for (int k = 0; k < 2; k++) {
                row->every[k].skipped = !fits[k] ? "skipped (memory)" : big ? "2 threads only (time)" : NULL;
                if (row->every[k].skipped)
                    continue;
                char f[160];
                snprintf(f, sizeof f, "\"depth\":%u,\"method\":\"%s\",\"delta\":1e-6,\"cull\":false",
                         depth, k ? "emit" : "resize");
                if (open_run(&every[k], clip_job(f, true, cam, 64, 36, job_frames, duration), asset,
                             threads, (size_t)budget, &err) < 0)
                    die("every leaf", err.msg);
            }
            char f[128];
            snprintf(f, sizeof f, "\"depth\":%u,\"method\":\"resize\"", depth);
            if (open_run(&camera, clip_job(f, true, cam, WIDTH, HEIGHT, job_frames, duration), asset,
                         threads, (size_t)budget, &err) < 0)
                die("camera", err.msg);
            /* Two passes over the frames, interleaved, the second timed.
             * A run's first frames fault its workspace in, and frame 1's
             * cells can outgrow frame 0's: on two threads at depth 10 the
             * selection of frames 0-2 took 40 / 69 / 28 ms, and the
             * one-thread runs after them found the heap those had freed
             * and looked faster than two threads. The timed pass is each
             * run's steady state, what a clip's later frames see; the
             * untimed pass's first frame is shown apart. The untimed pass
             * renders the job's frames [0, frames), the timed one its last
             * `frames`; fr is the slot in either. */
            for (int pass = 0; pass < 2; pass++)
                for (int fr = 0; fr < frames; fr++) {
                    const int jf = (pass ? job_frames - frames : 0) + fr; /* the job's frame */
                    mr_frame_stats st;
                    for (int k = 0; k < 2; k++) {
                        phase *ph = &row->every[k];
                        if (ph->skipped)
                            continue;
                        if (mr_renderer_render(every[k].r, (size_t)jf, every[k].film, &st, &err) < 0) {
                            if (err.code != MR_ERR_LIMIT)
                                die("every leaf", err.msg);
                            ph->skipped = "skipped (memory budget)";
                            close_run(&every[k]);
                            continue;
                        }
                        if (pass == 0) {
                            if (fr == 0) {
                                ph->first_select_ms = frame_extra(&st, "svo_select_s") * 1e3;
                                ph->first_resample_ms = (frame_extra(&st, "svo_emit_s") +
                                                         frame_extra(&st, "svo_rebuild_s")) * 1e3;
                                if (k == 0 && ti == 0) /* the cache is read by the first frame */
                                    mrow->load_s = frame_extra(&st, "svo_build_s");
                            }
                            continue;
                        }
                        record(ph, fr, &st);
                        if (k == 0 && fr == 0 && ti == 0) {
                            mrow->rebuilt_bytes = ph->octree_bytes / fmax((double)st.triangles, 1);
                            mrow->rebuilt_voxels = (double)st.triangles;
                        }
                        if (k == 1 && fr == 0 && ti == 0)
                            emit_ratio = fmax(emit_ratio * 0.5, ph->cells[0] / fmax(ph->selected[0], 1) * 1.2);
                    }
                    render(&camera, (size_t)jf, &st);
                    if (pass == 1)
                        record(&row->cam, fr, &st);
                }
            for (int k = 0; k < 2; k++)
                if (every[k].r)
                    close_run(&every[k]);
            close_run(&camera);
        }
    }
    mr_asset_free(asset);

    printf("\n### b. Per-frame cost on the dancer (clip of %.2f s)\n\n", duration);
    printf("| depth | voxels | voxelise s (all cores) | cache load s | shared bytes/voxel |\n"
           "|---|---|---|---|---|\n");
    for (int i = 0; i < ndepth; i++)
        printf("| %u | %.0f | %.2f | %.3f | %.2f |\n", mem[i].depth, mem[i].voxels,
               mem[i].voxelise_s, mem[i].load_s, mem[i].shared_bytes);
    printf("\nEvery leaf (delta 1e-6 px, no culling; median over the clip's frames, timed on a "
           "second pass over them; rebuilt octree "
           "depth = source + 2). select: selection + deformation (svo_select_s), Mvox/s = voxels "
           "deformed per second. Resample columns: total ms (svo_emit_s + svo_rebuild_s), "
           "Mcells/s, rebuild = radix sort + compaction + octree build (svo_rebuild_s; the rest "
           "is cell emission), cells (svo_cells) and output voxels. Memory budget %.1f GiB.\n\n",
           budget / GIB);
    printf("| depth | threads | voxels | select ms | Mvox/s | resize ms | resize Mcells/s | resize "
           "rebuild ms | resize cells | resize out | emit ms | emit Mcells/s | emit rebuild ms | "
           "emit cells | emit out |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    for (int i = 0; i < nrows; i++) {
        const depth_row *r = &rows[i];
        const phase *sel = !r->every[0].skipped ? &r->every[0] : !r->every[1].skipped ? &r->every[1] : NULL;
        printf("| %u | %u | %.0f ", r->depth, r->threads, r->voxels);
        if (sel)
            printf("| %.1f | %.1f ", med(sel->select_ms, r->frames), med(sel->mvox_s, r->frames));
        else
            printf("| | ");
        for (int k = 0; k < 2; k++)
            print_phase_cells(&r->every[k], r->frames);
        printf("|\n");
    }
    printf("\nA run's first frame (the untimed pass's frame 0), 2 threads, ms:");
    const char *sep = "";
    for (int i = 0; i < nrows; i++) {
        const depth_row *r = &rows[i];
        if (r->threads != 2 || (r->every[0].skipped && r->every[1].skipped))
            continue;
        printf("%s depth %u select %.1f", sep, r->depth,
               !r->every[0].skipped ? r->every[0].first_select_ms : r->every[1].first_select_ms);
        for (int k = 0; k < 2; k++)
            if (!r->every[k].skipped)
                printf(", %s %.1f", k ? "emit" : "resize", r->every[k].first_resample_ms);
        sep = ";";
    }
    printf(".\n");
    printf("\nCamera %dx%d, %.0f deg vertical, 3 character heights in front, screen-space "
           "selection at delta 1 with frustum culling, resize:\n\n| depth | threads | selected "
           "| deformed | select ms | resize ms |\n|---|---|---|---|---|---|\n",
           WIDTH, HEIGHT, YFOV_DEG);
    for (int i = 0; i < nrows; i++) {
        const depth_row *r = &rows[i];
        printf("| %u | %u | %.0f | %.0f | %.2f | %.2f |\n", r->depth, r->threads,
               med(r->cam.selected, r->frames), med(r->cam.deformed, r->frames),
               med(r->cam.select_ms, r->frames), med(r->cam.resample_ms, r->frames));
    }

    /* c. against Embree triangles of the dancer made detailed */
    printf("\n### c. Memory per primitive\n\nshared = a rigid object's geometry bytes per voxel "
           "(the octree: nodes, leaves, palette); rebuilt = svo_octree_bytes per output voxel "
           "(resize, every leaf, first frame). Embree triangles: the dancer refined by Loop "
           "rounds as a static mesh job (MEDIUM BVH, like the renderer's static scenes): "
           "geometry (vertex, normal, index arrays) + Embree's BVH bytes per triangle.\n\n"
           "| depth | voxels | shared B/voxel | rebuilt B/voxel |\n|---|---|---|---|\n");
    for (int i = 0; i < ndepth; i++)
        printf("| %u | %.0f | %.2f | %.2f |\n", mem[i].depth, mem[i].voxels, mem[i].shared_bytes,
               mem[i].rebuilt_bytes);
    printf("\n| Loop rounds | triangles | Embree B/triangle | of which BVH | / shared B/voxel (depth "
           "10) |\n|---|---|---|---|---|\n");
    mr_asset *base = NULL;
    if (mr_asset_load(MODEL, &base, &err) < 0)
        die(MODEL, err.msg);
    const double shared10 = ndepth > 1 ? mem[1].shared_bytes : mem[0].shared_bytes;
    for (unsigned rounds = 2; rounds <= (quick ? 2u : 4u); rounds++) {
        mr_refine_params rp = {.rounds = rounds, .threads = 2};
        mr_asset *fine = NULL;
        if (mr_refine_asset(base, &rp, &fine, &err) < 0)
            die("refine", err.msg);
        text t = {0};
        put(&t, "{\"assets\":{\"d\":{\"path\":\"" MODEL "\"}},\"objects\":[{\"asset\":\"d\"}],"
                "\"camera\":{\"path\":[{\"t\":0,%s}]},\"frames\":{\"times\":[0]},"
                "\"output\":{\"width\":64,\"height\":36,\"samples\":1}}", cam);
        run x;
        mr_frame_stats st;
        if (open_run(&x, parse(&t), fine, 2, 0, &err) < 0)
            die("triangles", err.msg);
        render(&x, 0, &st);
        const double tris = (double)st.triangles;
        const double b = (double)(st.geometry_bytes + st.bvh_bytes) / tris;
        printf("| %u | %.0f | %.1f | %.1f | %.1f |\n", rounds, tris, b, (double)st.bvh_bytes / tris,
               b / shared10);
        close_run(&x);
        mr_asset_free(fine);
    }
    mr_asset_free(base);
}

/* ---- d. instances */

typedef struct inst_frame {
    double update_ms, build_ms, pose_s, select_s, resample_s, selected, cells, out;
} inst_frame;

/* One frame of instances [first, first + count) of the grid of n (side x
 * side, `spacing` apart, each turned and offset in its clip by a hash of
 * its index), seen by the grid's camera. False when the job passed the
 * memory budget (the kind refuses the frame). */
static bool grid_job_frame(mr_asset *asset, const shape *sh, double duration, size_t n,
                           size_t first, size_t count, double time, size_t budget, inst_frame *out)
{
    const size_t side = (size_t)ceil(sqrt((double)n));
    const double spacing = 2.0, H = sh->H;
    text t = {0};
    put(&t, "{\"assets\":{\"d\":{\"path\":\"" MODEL "\"}},\"objects\":[{\"asset\":\"d\","
            "\"kind\":\"svo\",\"svo\":{\"depth\":8,\"method\":\"resize\",\"instances\":[");
    for (size_t i = first; i < first + count; i++) {
        const double gx = ((double)(i % side) - 0.5 * (double)(side - 1)) * spacing;
        const double gz = ((double)(i / side) - 0.5 * (double)(side - 1)) * spacing;
        uint64_t hsh = (uint64_t)i * 0x9e3779b97f4a7c15ull;
        hsh ^= hsh >> 29;
        const double ang = (double)(hsh % 6283) * 1e-3;
        const double offset = (double)((hsh >> 16) % 1000) * 1e-3 * duration;
        put(&t, "%s{\"transform\":{\"translation\":[%.6g,%.6g,%.6g],\"rotation\":[0,%.6g,0,%.6g]},"
                "\"pose\":{\"clip\":0,\"offset\":%.6g}}",
            i > first ? "," : "", gx, -sh->lo[1], gz, sin(0.5 * ang), cos(0.5 * ang), offset);
    }
    /* frame the grid: radius of the ground square plus a character */
    const double radius = 0.5 * sqrt(2.0) * (double)side * spacing + H;
    const double dist = fmax(3 * H, radius / sin(0.5 * YFOV_DEG * M_PI / 180));
    put(&t, "]}}],\"camera\":{\"yfov\":%g,\"path\":[{\"t\":0,\"position\":[0,%.9g,%.9g],"
            "\"target\":[0,%.9g,0]}]},\"frames\":{\"times\":[%.9g]},"
            "\"output\":{\"width\":%d,\"height\":%d,\"samples\":1,\"shadows\":false}}",
        YFOV_DEG, 0.5 * H + 0.5 * dist, 0.866 * dist, 0.5 * H, time, WIDTH, HEIGHT);
    run x;
    mr_error err = {0};
    mr_frame_stats st;
    if (open_run(&x, parse(&t), asset, 2, budget, &err) < 0 ||
        mr_renderer_render(x.r, 0, x.film, &st, &err) < 0) {
        if (err.code != MR_ERR_LIMIT)
            die("instances", err.msg);
        close_run(&x);
        return false;
    }
    out->update_ms += st.pose_s * 1e3;
    out->build_ms += st.bvh_s * 1e3;
    out->pose_s += frame_extra(&st, "svo_pose_s");
    out->select_s += frame_extra(&st, "svo_select_s");
    out->resample_s += frame_extra(&st, "svo_emit_s") + frame_extra(&st, "svo_rebuild_s");
    out->selected += frame_extra(&st, "svo_selected");
    out->cells += frame_extra(&st, "svo_cells");
    out->out += (double)st.triangles;
    close_run(&x);
    return true;
}

static void part_d(double deadline)
{
    mr_asset *asset = NULL;
    mr_error err = {0};
    if (mr_asset_load(MODEL, &asset, &err) < 0)
        die(MODEL, err.msg);
    const double duration = mr_asset_clip_duration(asset, 0);
    mr_trimesh m;
    shape sh;
    rest_triangles(asset, &m, &sh);
    mr_trimesh_free(&m);
    const double budget = fmin(8.0 * GIB, 0.6 * bench_mem_available());
    const size_t n_max = 1u << 20;
    printf("\n### d. Instances (thesis: 10^6 instances of 6 models, 33.8 ms per frame, GTX 260)\n\n"
           "The dancer at depth 8 per instance, method resize, each with its own clip offset and a "
           "turn about y, on a square grid 2 units apart, the camera (%dx%d, %.0f deg) 30 deg above "
           "the grid framing all of it; screen-space selection at delta 1 with frustum culling, "
           "instances in parallel on 2 threads, each resampled into its own world octree. ms = "
           "the renderer's update (pose_s) and Embree build (bvh_s) of one frame; the phase "
           "columns are svo_*_s summed over instances (thread seconds). N above %u: several jobs "
           "of %u instances rendering the same frame, times summed. Memory budget %.1f GiB.\n\n",
           WIDTH, HEIGHT, YFOV_DEG, INSTANCES_PER_JOB, INSTANCES_PER_JOB, budget / GIB);
    printf("| N | selected | voxels/instance | update ms | build ms | total ms | pose s | select s "
           "| resample s | cells | out voxels | peak RSS MiB | bytes/instance | marginal "
           "bytes/instance |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    mr_heap_release(); /* what earlier parts freed does not count */
    const bool reset = bench_peak_reset();
    const double base_rss = bench_rss_now();
    double fit_n[64], fit_ms[64], fit_bytes[64];
    int fit_rows = 0;
    size_t fit = 0, last_n = 0;
    double first_ms = 0, last_bytes = 0, last_marginal = 0, last_peak = base_rss;
    inst_frame last = {0};
    const char *stop = "N = 2^20";
    for (size_t n = 1; n <= n_max; n *= 2) {
        /* large N: one frame each, so the series reaches far within its time */
        const int repeats = n <= 16 ? 3 : 1;
        double upd[3], bld[3], tot[3], wall0 = mr_now();
        inst_frame fr = {0};
        bool refused = false;
        for (int rep = 0; rep < repeats && !refused; rep++) {
            fr = (inst_frame){0};
            for (size_t first = 0; first < n && !refused; first += INSTANCES_PER_JOB) {
                size_t count = n - first < INSTANCES_PER_JOB ? n - first : INSTANCES_PER_JOB;
                refused = !grid_job_frame(asset, &sh, duration, n, first, count, rep / 30.0,
                                          (size_t)budget, &fr);
            }
            upd[rep] = fr.update_ms;
            bld[rep] = fr.build_ms;
            tot[rep] = fr.update_ms + fr.build_ms;
        }
        if (refused) {
            printf("| %zu | the job's memory budget refused the frame | | | | | | | | | | | | |\n", n);
            stop = "the job's memory budget";
            break;
        }
        const double total = median(tot, repeats), peak = bench_peak_rss();
        /* peak RSS grows with the frame's transient buffers and the per-instance state; the
         * marginal cost of the last doubling is what scales (a job holds at most
         * INSTANCES_PER_JOB at once) */
        const double held = (double)(n < INSTANCES_PER_JOB ? n : INSTANCES_PER_JOB);
        /* (Linux updates VmHWM lazily: a few pages below the RSS read
         * after the reset read as 0) */
        const double bytes = fmax(peak - base_rss, 0) / held;
        const double marginal = n > 1 && last_n < INSTANCES_PER_JOB
                                    ? fmax(peak - last_peak, 0) / (held - (double)last_n)
                                    : bytes;
        printf("| %zu | %.0f | %.1f | %.2f | %.2f | %.2f | %.3f | %.3f | %.3f | %.0f | %.0f | %.0f | "
               "%.0f | %.0f |\n",
               n, fr.selected, fr.selected / (double)n, median(upd, repeats), median(bld, repeats),
               total, fr.pose_s, fr.select_s, fr.resample_s, fr.cells, fr.out, peak / (1024.0 * 1024.0),
               bytes, marginal);
        fflush(stdout);
        fit_n[fit_rows] = (double)n;
        fit_ms[fit_rows] = total;
        fit_bytes[fit_rows++] = fmax(peak - base_rss, 0);
        if (total <= THESIS_MS)
            fit = n;
        if (n == 1)
            first_ms = total;
        last_n = n;
        last_bytes = bytes;
        last_marginal = marginal;
        last_peak = peak;
        last = fr;
        if (base_rss + 2.0 * (peak - base_rss) > budget && n * 2 <= n_max) {
            stop = "memory budget";
            break;
        }
        /* the next doubling takes about twice this one's wall time (jobs
         * parsed, instances posed, frames traced) */
        const double wall = (mr_now() - wall0) / repeats;
        const int next_repeats = 2 * n <= 16 ? 3 : 1;
        if (mr_now() + 2.2 * wall * next_repeats > deadline && n * 2 <= n_max) {
            stop = "the bench's time budget";
            break;
        }
    }
    const int half = fit_rows / 2;
    printf("\nGrowth exponents (cost ~ N^b, least squares): total ms b = %.2f over all rows, %.2f over "
           "the larger half (N >= %.0f); peak RSS growth b = %.2f, %.2f.\n",
           bench_growth(fit_n, fit_ms, fit_rows), bench_growth(fit_n + half, fit_ms + half, fit_rows - half),
           fit_rows > half ? fit_n[half] : 0.0, bench_growth(fit_n, fit_bytes, fit_rows),
           bench_growth(fit_n + half, fit_bytes + half, fit_rows - half));
    printf("\nPer instance at N = %zu, thread time: pose and skin matrices %.1f us (svo_pose_s / "
           "N), selection %.1f us (svo_select_s / N; most instances far, a few voxels each).\n",
           last_n, last.pose_s / (double)last_n * 1e6, last.select_s / (double)last_n * 1e6);
    const double per = last_marginal > 0 ? last_marginal : last_bytes;
    const double n24 = per > 0 ? (24.0 * GIB - (last_peak - base_rss)) / per +
                                     (double)(last_n < INSTANCES_PER_JOB ? last_n : INSTANCES_PER_JOB)
                               : 0.0;
    char fits[64];
    if (fit)
        snprintf(fits, sizeof fits, "%zu", fit);
    else
        snprintf(fits, sizeof fits, "none (N = 1 takes %.1f ms)", first_ms);
    printf("\nLargest N within %.1f ms per frame: %s. Stopped at N = %zu (%s). %.0f bytes of peak "
           "RSS growth per instance held (average), %.0f per added instance (marginal); one job "
           "holding all its instances, 24 GiB would run out near N = %.3g (extrapolated linearly "
           "at the marginal cost).\n",
           THESIS_MS, fits, last_n, stop, last_bytes, last_marginal, n24);
    if (!reset)
        printf("(The peak RSS could not be reset: figures include the earlier parts' peak.)\n");
    mr_asset_free(asset);
}

static void remove_cache(void)
{
    char dir[600];
    mr_error err = {0};
    snprintf(dir, sizeof dir, "%s/svo", cache_root);
    if (mr_fs_remove_dir(dir, &err) < 0 || mr_fs_remove_dir(cache_root, &err) < 0)
        fprintf(stderr, "bench_svo: %s\n", err.msg);
}

int main(int argc, char **argv)
{
    bool quick = false;
    const char *only = "abcd";
    for (int i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--quick") == 0)
            quick = true;
        else if (strcmp(argv[i], "--only") == 0 && i + 1 < argc)
            only = argv[++i];
    }
    const char *tmp = getenv("TMPDIR");
    snprintf(cache_root, sizeof cache_root, "%s/microray-bench-svo-XXXXXX", tmp && *tmp ? tmp : "/tmp");
    if (!mkdtemp(cache_root))
        die(cache_root, "cannot make the cache folder");
    double t0 = mr_now();
    if (strchr(only, 'a'))
        part_a(quick);
    if (strchr(only, 'b') || strchr(only, 'c'))
        part_bc(quick);
    /* part d doubles N while the next frame fits in its share of the ~5 minutes */
    if (strchr(only, 'd'))
        part_d(mr_now() + (quick ? 45.0 : 110.0));
    remove_cache();
    printf("\n(bench_svo: %.0f s)\n", mr_now() - t0);
    return 0;
}
