/*
 * bench_svo.c - sparse voxel octree deformation benchmarks (issue 5, paper
 * 004, Willcocks, chapter 3 and 5). Not a test: it prints figures and never
 * fails on a time. Timings are medians over frames (and repeats) on a shared
 * 2-core machine.
 *
 *  a. The thesis' sweep (3.4, Figs. 20-28, Tables 2-3): shear and twist
 *     0.2 .. 12.8 and uniform scale of a low-resolution human (the BCN
 *     character, solid voxels at depth 7: 36,591 voxels, the thesis had
 *     33,720): coverage error of resize and emit against the direct boxes
 *     and cells emitted per voxel (tests/support/svo_sweep.h).
 *  b. Per-frame cost on the BCN character voxelised at depths 8, 10, 12,
 *     over frames of its clip, on 2 threads and 1: selection + deformation
 *     of every leaf, resample with resize and with emit (cells per second;
 *     the rebuild - radix sort + compaction + octree build - timed apart on
 *     the same cells), and screen-space selection for one camera (1280 x 720,
 *     3 heights away, delta 1).
 *  c. Memory per voxel: the shared octree and a rebuilt one, against Embree
 *     triangles of the same voxels (their exposed faces, TRIANGLE geometry,
 *     MEDIUM quality like the renderer; Embree's bytes from its memory
 *     monitor plus the vertex and index buffers).
 *  d. Instances: the thesis deformed 10^6 instances of 6 models in 33.8 ms
 *     per frame (GTX 260). N = 1, 2, 4, ... posed BCN instances (depth 8,
 *     each its own clip offset, poses by mr_pose_eval) on a grid framed by a
 *     1280 x 720 camera: select (delta 1) + one resize into a world octree
 *     per frame; the largest N within 33.8 ms; then doubling on to 2^20 or a
 *     memory budget, bytes per instance and where 24 GiB would end.
 *
 * usage: bench_svo [--quick] [--only abcd]  (--quick: the sweep on surface
 * voxels at depth 6, depths 8 and 10 only, a shorter instance series;
 * --only: the parts to run, b and c together; other arguments are ignored:
 * make bench passes the same ones to every benchmark)
 */
#include <embree3/rtcore.h>
#include <math.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <unistd.h>

#include "anim/pose.h"
#include "render/renderer.h"
#include "util/clock.h"
#include "util/radix_sort.h"
#include "kinds/svo/svo_build.h"
#include "util/parallel.h"
#include "../tests/support/svo_sweep.h"
#include "bench_util.h"

#define THESIS_MS 33.8
#define WIDTH 1280
#define HEIGHT 720
#define YFOV (45.0f * 3.14159265f / 180.0f)
#define MAX_FRAMES 8

static void die(const char *what, const char *msg)
{
    fprintf(stderr, "bench_svo: %s: %s\n", what, msg);
    exit(1);
}

static void *xmalloc(size_t n)
{
    void *p = malloc(n ? n : 1);
    if (!p)
        die("malloc", "out of memory");
    return p;
}

static void *xrealloc(void *p, size_t n)
{
    p = realloc(p, n ? n : 1);
    if (!p)
        die("realloc", "out of memory");
    return p;
}

/* ---- process memory */

static double rss_now(void)
{
    long pages = 0, resident = 0;
    FILE *f = fopen("/proc/self/statm", "r");
    if (f) {
        if (fscanf(f, "%ld %ld", &pages, &resident) != 2)
            resident = 0;
        fclose(f);
    }
    return (double)resident * (double)sysconf(_SC_PAGESIZE);
}

/* Peak RSS (VmHWM) since the last peak_reset; the reset (Linux clear_refs
 * "5") lets part d measure its own peak after parts b-c. */
static bool peak_reset(void)
{
    FILE *f = fopen("/proc/self/clear_refs", "w");
    if (!f)
        return false;
    bool ok = fputs("5", f) >= 0;
    ok = fclose(f) == 0 && ok;
    return ok;
}

static double peak_rss(void)
{
    char line[256];
    double kib = 0;
    FILE *f = fopen("/proc/self/status", "r");
    if (!f)
        return (double)mr_peak_rss_bytes();
    while (fgets(line, sizeof line, f))
        if (sscanf(line, "VmHWM: %lf kB", &kib) == 1)
            break;
    fclose(f);
    return kib > 0 ? kib * 1024.0 : (double)mr_peak_rss_bytes();
}

static double mem_available(void)
{
    char line[256];
    double kib = 0;
    FILE *f = fopen("/proc/meminfo", "r");
    if (!f)
        return 8.0 * (1 << 30);
    while (fgets(line, sizeof line, f))
        if (sscanf(line, "MemAvailable: %lf kB", &kib) == 1)
            break;
    fclose(f);
    return kib * 1024.0;
}

static const double GIB = 1024.0 * 1024.0 * 1024.0;

/* ---- skinning matrices of one posed instance (deform.h's mr_svo_skin) */

static void skin_init(mr_svo_skin *s, const mr_asset *a)
{
    mr_error err = {0};
    if (mr_svo_skin_init(s, a, &err) < 0)
        die("skin", err.msg);
}

static mr_pose_desc clip_desc(double offset)
{
    return (mr_pose_desc){.has_clip = true, .clip_index = 0, .speed = 1.0, .offset = offset,
                          .loop = true};
}

/* ---- camera: OpenGL-style view-projection (row-major, column vectors) */

static mr_mat4 view_proj(mr_vec3 eye, mr_vec3 target, float zn, float zf)
{
    mr_vec3 f = mr_v3_normalize_or(mr_v3_sub(target, eye), mr_v3(0, 0, -1));
    mr_vec3 s = mr_v3_normalize_or(mr_v3_cross(f, mr_v3(0, 1, 0)), mr_v3(1, 0, 0));
    mr_vec3 u = mr_v3_cross(s, f);
    mr_mat4 v = {{s.x, s.y, s.z, -mr_v3_dot(s, eye), u.x, u.y, u.z, -mr_v3_dot(u, eye), -f.x,
                  -f.y, -f.z, mr_v3_dot(f, eye), 0, 0, 0, 1}};
    const float t = 1.0f / tanf(0.5f * YFOV), aspect = (float)WIDTH / HEIGHT;
    mr_mat4 p = {{t / aspect, 0, 0, 0, 0, t, 0, 0, 0, 0, (zf + zn) / (zn - zf),
                  2 * zf * zn / (zn - zf), 0, 0, -1, 0}};
    return mr_mat4_mul(&p, &v);
}

static mr_svo_view make_view(mr_vec3 eye, mr_vec3 target, float zn, float zf)
{
    return (mr_svo_view){.enabled = true, .view_proj = view_proj(eye, target, zn, zf),
                         .width = WIDTH, .height = HEIGHT, .delta = 1.0f, .cull = true};
}

/* ---- a. the sweep */

static void part_a(bool quick)
{
    const unsigned depth = quick ? 6 : 7;
    const mr_svo_voxelize_mode mode = quick ? MR_SVO_VOXELIZE_SURFACE : MR_SVO_VOXELIZE_SOLID;
    mr_asset *asset = NULL;
    mr_svo *svo = NULL;
    mr_svo_extremes ex = {0};
    sw_bounds shape;
    mr_error err = {0};
    if (sw_bcn_octree(depth, mode, 0, &asset, &svo, &err) < 0 ||
        mr_svo_extremes_build(svo, &ex, &err) < 0 || sw_octree_bounds(svo, &shape, &err) < 0)
        die("sweep shape", err.msg);
    printf("\n## SVO deformation (paper 004)\n\n### a. Resampling sweep (thesis 3.4, Figs. 20-28)\n\n"
           "BCN character, %s voxels at depth %u: %u voxels (the thesis' human: 33,720). Orthographic "
           "view along z, pixel = 1/4 source voxel. error = |coverage XOR direct| / |direct|; diff = "
           "(|coverage| - |direct|) / |direct| (the thesis' subtraction); cells per voxel emitted "
           "before compaction (Figs. 27-28); out = voxels of the rebuilt octree. Shear: the top moves "
           "by amount shape heights; twist: amount radians over the height.\n\n",
           mode == MR_SVO_VOXELIZE_SOLID ? "solid" : "surface", depth, svo->leaf_count);
    printf("| deformation | amount | direct px | resize error | resize diff | emit error | emit "
           "diff | emit missing px | resize cells/voxel | emit cells/voxel | resize out | emit out "
           "|\n|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    const sw_kind kinds[2] = {SW_SHEAR, SW_TWIST};
    const double scales[] = {0.37, 0.5, 1.0, 1.3, 2.0, 3.7};
    for (int k = 0; k < 3; k++) {
        const int count = k < 2 ? 7 : (int)(sizeof scales / sizeof *scales);
        for (int i = 0; i < count; i++) {
            const sw_kind kind = k < 2 ? kinds[k] : SW_SCALE;
            const double amount = k < 2 ? 0.2 * (double)(1 << i) : scales[i];
            sw_field f = sw_field_make(kind, amount, &shape);
            sw_params p = {.threads = 0};
            sw_result r;
            if (sw_measure(svo, &ex, &f, &p, &r, &err) < 0)
                die("sweep", err.msg);
            printf("| %s | %.2f | %llu | %.4f | %+.4f | %.4f | %+.4f | %llu | %.2f | %.2f | %u | %u "
                   "|\n",
                   sw_kind_name(kind), amount, (unsigned long long)r.direct_px, r.error[SW_RESIZE],
                   r.diff[SW_RESIZE], r.error[SW_EMIT], r.diff[SW_EMIT],
                   (unsigned long long)r.missing[SW_EMIT],
                   (double)r.cells[SW_RESIZE] / (double)r.voxels,
                   (double)r.cells[SW_EMIT] / (double)r.voxels, r.leaves[SW_RESIZE],
                   r.leaves[SW_EMIT]);
            fflush(stdout);
        }
    }
    mr_svo_extremes_free(&ex);
    mr_svo_voxelize_free(svo);
    mr_asset_free(asset);
}

/* ---- b. per-frame cost per depth */

/* The cells deform.h's formulas give for sel in the cube of out (its origin,
 * size and depth): the bench rebuilds them to time sort + compact + build
 * apart from the cell generation. Returns the count (keys, payload grown). */
static size_t regen_cells(const mr_svo_selection *sel, mr_svo_method method, const mr_svo *out,
                          mr_svo_key **keys, uint32_t **payload, size_t *cap)
{
    const unsigned depth = out->depth;
    const double S = out->size, o[3] = {out->origin.x, out->origin.y, out->origin.z};
    size_t n = 0;
    for (size_t i = 0; i < sel->count; i++) {
        const float *b = sel->box + 6 * i;
        double mx = 0, mn = INFINITY;
        for (int a = 0; a < 3; a++) {
            mx = fmax(mx, (double)b[3 + a] - b[a]);
            mn = fmin(mn, (double)b[3 + a] - b[a]);
        }
        int64_t lo[3], hi[3];
        unsigned level;
        if (method == MR_SVO_RESIZE) {
            unsigned h = 0;
            while (h + 1 < depth && S / (double)(1ull << (h + 1)) >= mx)
                h++;
            level = h + 1;
            const double r = (double)(1ull << level) / S;
            for (int a = 0; a < 3; a++) {
                lo[a] = (int64_t)floor(r * (0.5 * ((double)b[a] + b[3 + a]) - o[a]) - 0.5);
                lo[a] = lo[a] < 0 ? 0 : lo[a];
                lo[a] = lo[a] > (int64_t)(1ull << level) - 2 ? (int64_t)(1ull << level) - 2 : lo[a];
                hi[a] = lo[a] + 1;
            }
        } else {
            unsigned h = 0;
            while (h < depth && S / (double)(1ull << (h + 1)) >= mn)
                h++;
            for (;;) {
                const double r = (double)(1ull << h) / S;
                uint64_t total = 1;
                for (int a = 0; a < 3; a++) {
                    lo[a] = (int64_t)floor(r * ((double)b[a] - o[a]));
                    hi[a] = (int64_t)ceil(r * ((double)b[3 + a] - o[a])) - 1;
                    lo[a] = lo[a] < 0 ? 0 : lo[a];
                    hi[a] = hi[a] > (int64_t)(1ull << h) - 1 ? (int64_t)(1ull << h) - 1 : hi[a];
                    hi[a] = hi[a] < lo[a] ? lo[a] : hi[a];
                    total *= (uint64_t)(hi[a] - lo[a] + 1);
                }
                if (total <= MR_SVO_EMIT_MAX_CELLS || h == 0)
                    break;
                h--;
            }
            level = h;
        }
        const uint64_t total =
            (uint64_t)(hi[0] - lo[0] + 1) * (uint64_t)(hi[1] - lo[1] + 1) * (uint64_t)(hi[2] - lo[2] + 1);
        if (n + total > *cap) {
            *cap = (n + total) * 2;
            *keys = xrealloc(*keys, *cap * sizeof **keys);
            *payload = xrealloc(*payload, *cap * sizeof **payload);
        }
        const unsigned sh = depth - level;
        for (int64_t z = lo[2]; z <= hi[2]; z++)
            for (int64_t y = lo[1]; y <= hi[1]; y++)
                for (int64_t x = lo[0]; x <= hi[0]; x++) {
                    (*keys)[n] = (mr_svo_key){mr_morton_encode((uint32_t)x << sh, (uint32_t)y << sh,
                                                               (uint32_t)z << sh),
                                              level};
                    (*payload)[n++] = (uint32_t)i;
                }
    }
    return n;
}

typedef struct rebuild_scratch {
    mr_svo_key *keys;
    uint32_t *payload, *kept;
    mr_svo_leaf *leaves;
    size_t cap;
} rebuild_scratch;

/* Times sort + compact + build of the regenerated cells; -1 when their count
 * is more than 0.1 % off what mr_svo_resample reported (deform.c settles
 * cell boundaries with exact plane tests; plain floor / ceil here can differ
 * by a cell on a rare box, which does not change the timing). */
static double time_rebuild(const mr_svo_selection *sel, mr_svo_method method, const mr_svo *out,
                           uint64_t cells, unsigned threads, rebuild_scratch *s)
{
    size_t cap0 = s->cap;
    size_t n = regen_cells(sel, method, out, &s->keys, &s->payload, &s->cap);
    if (s->cap != cap0) {
        s->kept = xrealloc(s->kept, s->cap * sizeof *s->kept);
        s->leaves = xrealloc(s->leaves, s->cap * sizeof *s->leaves);
    }
    if (fabs((double)n - (double)cells) > 1e-3 * (double)cells)
        return -1;
    mr_error err = {0};
    mr_svo built = {0};
    size_t m = 0;
    double t0 = mr_now();
    if (mr_svo_radix_sort_payload(s->keys, s->payload, n, NULL, NULL, threads, &err) < 0 ||
        mr_svo_compact(s->keys, n, out->depth, s->kept, &m, &err) < 0)
        die("rebuild", err.msg);
    for (size_t i = 0; i < m; i++)
        s->leaves[i] = sel->leaf[s->payload[s->kept[i]]];
    if (mr_svo_build(s->keys, s->leaves, m, out->depth, out->origin, out->size, out->palette,
                     out->palette_count, threads, &built, &err) < 0)
        die("rebuild", err.msg);
    double t = mr_now() - t0;
    mr_svo_free(&built);
    return t;
}

typedef struct depth_row {
    unsigned depth, threads;
    uint32_t voxels;
    double select_ms, mvox_s;     /* every leaf */
    double ms[2], mcells_s[2], rebuild_ms[2];
    double cells[2], out_voxels[2];
    const char *skipped[2]; /* why a resample was not run, or NULL */
    double cam_selected, cam_visited, cam_ms, cam_resize_ms;
} depth_row;

typedef struct memory_row {
    unsigned depth;
    uint32_t voxels;
    double svo_bytes, svo_layout_bytes; /* per voxel: with leaf keys, nodes + leaves + palette */
    double rebuilt_bytes, rebuilt_voxels;
    double triangles, embree_bytes, embree_peak, buffer_bytes, build_s;
    bool embree;
} memory_row;

/* Exposed faces of the leaves of svo (a face is exposed unless a leaf at
 * its own level or coarser covers the cell behind it) as triangles with
 * shared vertices. */
typedef struct tri_mesh {
    float *v;
    uint32_t *idx;
    size_t vcount, tcount;
} tri_mesh;

static size_t find_code(const mr_svo_key *k, size_t n, uint64_t code) /* last key with code <= */
{
    size_t lo = 0, hi = n;
    while (lo < hi) {
        size_t mid = lo + (hi - lo) / 2;
        if (k[mid].code <= code)
            lo = mid + 1;
        else
            hi = mid;
    }
    return lo; /* 0: none; else lo - 1 */
}

static void exposed_faces(const mr_svo *svo, unsigned threads, tri_mesh *out, bool count_only)
{
    mr_error err = {0};
    mr_svo_key *keys = NULL;
    if (sw_octree_keys(svo, &keys, &err) < 0)
        die("keys", err.msg);
    const size_t n = svo->leaf_count;
    const unsigned D = svo->depth;
    const int64_t grid = (int64_t)1 << D;
    size_t faces = 0, cap = 0;
    uint64_t *corner = NULL;
    for (int pass = 0; pass < (count_only ? 1 : 2); pass++) {
        if (pass == 1) {
            cap = faces;
            corner = xmalloc(4 * cap * sizeof *corner);
            faces = 0;
        }
        for (size_t i = 0; i < n; i++) {
            uint32_t c[3];
            mr_morton_decode(keys[i].code, &c[0], &c[1], &c[2]);
            const int64_t w = (int64_t)1 << (D - keys[i].level);
            for (int f = 0; f < 6; f++) {
                const int a = f >> 1, sgn = f & 1 ? 1 : -1;
                int64_t nb[3] = {c[0], c[1], c[2]};
                nb[a] += sgn * w;
                bool exposed = nb[a] < 0 || nb[a] >= grid;
                if (!exposed) {
                    uint64_t code = mr_morton_encode((uint32_t)nb[0], (uint32_t)nb[1], (uint32_t)nb[2]);
                    size_t j = find_code(keys, n, code);
                    exposed = true;
                    if (j > 0) {
                        const mr_svo_key *k = &keys[j - 1];
                        const uint64_t span = 1ull << (3 * (D - k->level));
                        exposed = !(k->level <= keys[i].level && code < k->code + span);
                    }
                }
                if (!exposed)
                    continue;
                if (pass == 1) {
                    /* the face's plane and its 4 corners, counter-clockwise seen from outside */
                    const int b = (a + 1) % 3, d = (a + 2) % 3;
                    int64_t p[3] = {c[0], c[1], c[2]};
                    p[a] += sgn > 0 ? w : 0;
                    int64_t q[4][3];
                    for (int k = 0; k < 4; k++) {
                        memcpy(q[k], p, sizeof p);
                        const int u = sgn > 0 ? (k == 1 || k == 2) : (k == 2 || k == 3);
                        const int v = sgn > 0 ? (k == 2 || k == 3) : (k == 1 || k == 2);
                        q[k][b] += u * w;
                        q[k][d] += v * w;
                        corner[4 * faces + (size_t)k] =
                            mr_morton_encode((uint32_t)q[k][0], (uint32_t)q[k][1], (uint32_t)q[k][2]);
                    }
                }
                faces++;
            }
        }
    }
    free(keys);
    memset(out, 0, sizeof *out);
    out->tcount = 2 * faces;
    if (count_only)
        return;
    /* unique corners: sort their codes */
    mr_svo_key *vk = xmalloc(4 * faces * sizeof *vk);
    for (size_t i = 0; i < 4 * faces; i++)
        vk[i] = (mr_svo_key){corner[i], 0};
    if (mr_svo_radix_sort(vk, 4 * faces, NULL, threads, &err) < 0)
        die("sort", err.msg);
    size_t nv = 0;
    for (size_t i = 0; i < 4 * faces; i++)
        if (nv == 0 || vk[nv - 1].code != vk[i].code)
            vk[nv++] = vk[i];
    const double cell = (double)svo->size / (double)grid;
    out->vcount = nv;
    out->v = xmalloc((3 * nv + 1) * sizeof *out->v); /* Embree reads 16 bytes at the last vertex */
    for (size_t i = 0; i < nv; i++) {
        uint32_t c[3];
        mr_morton_decode(vk[i].code, &c[0], &c[1], &c[2]);
        out->v[3 * i] = (float)(svo->origin.x + c[0] * cell);
        out->v[3 * i + 1] = (float)(svo->origin.y + c[1] * cell);
        out->v[3 * i + 2] = (float)(svo->origin.z + c[2] * cell);
    }
    out->idx = xmalloc(3 * out->tcount * sizeof *out->idx);
    for (size_t f = 0; f < faces; f++) {
        uint32_t id[4];
        for (int k = 0; k < 4; k++)
            id[k] = (uint32_t)(find_code(vk, nv, corner[4 * f + (size_t)k]) - 1);
        const uint32_t tri[6] = {id[0], id[1], id[2], id[0], id[2], id[3]};
        memcpy(out->idx + 6 * f, tri, sizeof tri);
    }
    free(vk);
    free(corner);
}

typedef struct embree_mem {
    atomic_llong cur, peak;
} embree_mem;

static bool on_embree_memory(void *user, ssize_t bytes, bool post)
{
    embree_mem *m = user;
    (void)post;
    long long now = atomic_fetch_add(&m->cur, (long long)bytes) + (long long)bytes;
    long long peak = atomic_load(&m->peak);
    while (now > peak && !atomic_compare_exchange_weak(&m->peak, &peak, now)) {
    }
    return true;
}

static void embree_measure(const tri_mesh *t, memory_row *row)
{
    embree_mem mem;
    atomic_init(&mem.cur, 0);
    atomic_init(&mem.peak, 0);
    RTCDevice dev = rtcNewDevice("threads=2");
    if (!dev)
        die("embree", "rtcNewDevice failed");
    rtcSetDeviceMemoryMonitorFunction(dev, on_embree_memory, &mem);
    RTCScene scene = rtcNewScene(dev);
    rtcSetSceneFlags(scene, RTC_SCENE_FLAG_ROBUST);
    rtcSetSceneBuildQuality(scene, RTC_BUILD_QUALITY_MEDIUM);
    RTCGeometry g = rtcNewGeometry(dev, RTC_GEOMETRY_TYPE_TRIANGLE);
    rtcSetGeometryBuildQuality(g, RTC_BUILD_QUALITY_MEDIUM);
    rtcSetSharedGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, t->v, 0,
                               3 * sizeof(float), t->vcount);
    rtcSetSharedGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, t->idx, 0,
                               3 * sizeof(uint32_t), t->tcount);
    rtcCommitGeometry(g);
    rtcAttachGeometry(scene, g);
    rtcReleaseGeometry(g);
    double t0 = mr_now();
    rtcCommitScene(scene);
    row->build_s = mr_now() - t0;
    if (rtcGetDeviceError(dev) != RTC_ERROR_NONE)
        die("embree", "scene build failed");
    row->embree_bytes = (double)atomic_load(&mem.cur);
    row->embree_peak = (double)atomic_load(&mem.peak);
    row->buffer_bytes = (double)(3 * t->vcount * sizeof(float) + 3 * t->tcount * sizeof(uint32_t));
    row->triangles = (double)t->tcount;
    row->embree = true;
    rtcReleaseScene(scene);
    rtcReleaseDevice(dev);
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
    const double budget = fmin(6.0 * GIB, 0.5 * mem_available());
    mr_asset *asset = NULL;
    mr_error err = {0};
    if (mr_asset_load(SW_BCN_MODEL, &asset, &err) < 0)
        die(SW_BCN_MODEL, err.msg);
    if (asset->clip_count < 1)
        die(SW_BCN_MODEL, "no clip");
    const double duration = asset->clips[0].duration;
    printf("\n### b. Per-frame cost on the BCN character (%zu triangles, clip of %.2f s)\n\n",
           asset->triangle_count, duration);
    printf("| depth | voxels | nodes | voxelise s (%u threads) | extremes ms | shared bytes/voxel "
           "|\n|---|---|---|---|---|---|\n",
           mr_cpu_count());
    mr_pose *pose = NULL;
    if (mr_pose_new(asset, &pose, &err) < 0)
        die("pose", err.msg);
    mr_svo_skin sk;
    skin_init(&sk, asset);
    rebuild_scratch rs = {0};
    for (int di = 0; di < ndepth; di++) {
        const unsigned depth = depths[di];
        mr_svo *svo = NULL;
        mr_svo_extremes ex = {0};
        mr_svo_voxelize_params vp = {.depth = depth, .mode = MR_SVO_VOXELIZE_SURFACE};
        double t0 = mr_now();
        if (mr_svo_voxelize(asset, &vp, &svo, &err) < 0)
            die("voxelise", err.msg);
        const double vox_s = mr_now() - t0;
        t0 = mr_now();
        if (mr_svo_extremes_build(svo, &ex, &err) < 0)
            die("extremes", err.msg);
        const double ex_ms = (mr_now() - t0) * 1e3;
        memory_row *mrow = &mem[di];
        memset(mrow, 0, sizeof *mrow);
        mrow->depth = depth;
        mrow->voxels = svo->leaf_count;
        mrow->svo_bytes = (double)mr_svo_memory(svo) / svo->leaf_count;
        mrow->svo_layout_bytes =
            (double)(mr_svo_memory(svo) - (svo->leaf_keys ? svo->leaf_count * sizeof(mr_svo_key) : 0)) /
            svo->leaf_count;
        printf("| %u | %u | %u | %.2f | %.1f | %.2f |\n", depth, svo->leaf_count, svo->node_count,
               vox_s, ex_ms, mrow->svo_bytes);
        fflush(stdout);

        sw_bounds shape;
        if (sw_octree_bounds(svo, &shape, &err) < 0)
            die("bounds", err.msg);
        const double H = shape.hi[1] - shape.lo[1];
        const mr_vec3 target = mr_v3((float)(0.5 * (shape.lo[0] + shape.hi[0])),
                                     (float)(0.5 * (shape.lo[1] + shape.hi[1])),
                                     (float)(0.5 * (shape.lo[2] + shape.hi[2])));
        const mr_vec3 eye = mr_v3_add(target, mr_v3(0, 0, (float)(3 * H)));
        const mr_svo_view cam = make_view(eye, target, (float)(0.05 * H), (float)(10 * H));
        /* big frames cost seconds: fewer of them (the bench stays within ~5 minutes) */
        const int frames = svo->leaf_count > 4000000 ? 1 : svo->leaf_count > 400000 ? 3 : frames_full;
        const unsigned out_depth = depth + 2 > MR_SVO_MAX_DEPTH ? MR_SVO_MAX_DEPTH : depth + 2;
        const bool fits[2] = {8.0 * svo->leaf_count * 48.0 < budget,
                              emit_ratio * svo->leaf_count * 48.0 < budget};
        for (int ti = 0; ti < 2; ti++) {
            const unsigned threads = ti == 0 ? 2 : 1;
            /* depth 12 resamples for tens of seconds: on 2 threads only */
            const bool big = svo->leaf_count > 4000000 && threads == 1;
            const bool run[2] = {fits[0] && !big, fits[1] && !big};
            depth_row *row = &rows[nrows++];
            memset(row, 0, sizeof *row);
            row->depth = depth;
            row->threads = threads;
            row->voxels = svo->leaf_count;
            double sel_t[MAX_FRAMES], mvox[MAX_FRAMES], ms[2][MAX_FRAMES], mc[2][MAX_FRAMES],
                rb[2][MAX_FRAMES], cells[2][MAX_FRAMES], outv[2][MAX_FRAMES], cs[MAX_FRAMES],
                cv[MAX_FRAMES], ct[MAX_FRAMES], cr[MAX_FRAMES];
            int nrb[2] = {0, 0}, rb_skipped[2] = {0, 0};
            mr_svo_selection sel = {0};
            for (int f = 0; f < frames; f++) {
                mr_pose_desc desc = clip_desc(0);
                if (mr_pose_eval(pose, asset, &desc, (f + 0.5) * duration / frames, &err) < 0)
                    die("pose", err.msg);
                const mr_mat4 id = mr_mat4_identity();
                mr_svo_skin_pose(&sk, asset, pose, &id);
                mr_svo_deformer d = sk.d;
                t0 = mr_now();
                if (mr_svo_select(svo, &ex, &d, NULL, depth, threads, &sel, &err) < 0)
                    die("select", err.msg);
                sel_t[f] = (mr_now() - t0) * 1e3;
                mvox[f] = (double)sel.visited / (sel_t[f] * 1e-3) * 1e-6;
                for (int m = 0; m < 2; m++) {
                    if (!run[m])
                        continue;
                    mr_svo out = {0};
                    uint64_t nc = 0;
                    t0 = mr_now();
                    if (mr_svo_resample(&sel, m == 0 ? MR_SVO_RESIZE : MR_SVO_EMIT, out_depth,
                                        svo->palette, svo->palette_count, threads, &out, &nc,
                                        &err) < 0)
                        die("resample", err.msg);
                    ms[m][f] = (mr_now() - t0) * 1e3;
                    mc[m][f] = (double)nc / (ms[m][f] * 1e-3) * 1e-6;
                    cells[m][f] = (double)nc;
                    outv[m][f] = out.leaf_count;
                    if (f == 0 && ti == 0 && m == 0) {
                        mrow->rebuilt_bytes = (double)mr_svo_memory(&out) / out.leaf_count;
                        mrow->rebuilt_voxels = out.leaf_count;
                    }
                    /* the rebuild split costs a second copy of the cells: 2 frames */
                    if (f < 2 && (double)nc * 96.0 < budget) {
                        double t = time_rebuild(&sel, m == 0 ? MR_SVO_RESIZE : MR_SVO_EMIT, &out,
                                                nc, threads, &rs);
                        if (t >= 0)
                            rb[m][nrb[m]++] = t * 1e3;
                    } else if (f < 2) {
                        rb_skipped[m] = 1;
                    }
                    mr_svo_free(&out);
                    if (m == 1 && ti == 0 && f == 0)
                        emit_ratio = fmax(emit_ratio * 0.5, (double)nc / sel.count * 1.2);
                }
                /* camera: screen-space selection at delta 1 */
                t0 = mr_now();
                if (mr_svo_select(svo, &ex, &d, &cam, depth, threads, &sel, &err) < 0)
                    die("select (camera)", err.msg);
                ct[f] = (mr_now() - t0) * 1e3;
                cs[f] = (double)sel.count;
                cv[f] = (double)sel.visited;
                mr_svo out = {0};
                t0 = mr_now();
                if (mr_svo_resample(&sel, MR_SVO_RESIZE, out_depth, svo->palette,
                                    svo->palette_count, threads, &out, NULL, &err) < 0)
                    die("resample (camera)", err.msg);
                cr[f] = (mr_now() - t0) * 1e3;
                mr_svo_free(&out);
            }
            mr_svo_selection_free(&sel);
            row->select_ms = median(sel_t, frames);
            row->mvox_s = median(mvox, frames);
            for (int m = 0; m < 2; m++) {
                row->skipped[m] = !fits[m] ? "skipped (memory)" : big ? "2 threads only (time)" : NULL;
                if (!run[m])
                    continue;
                row->ms[m] = median(ms[m], frames);
                row->mcells_s[m] = median(mc[m], frames);
                row->cells[m] = median(cells[m], frames);
                row->out_voxels[m] = median(outv[m], frames);
                row->rebuild_ms[m] = nrb[m] ? median(rb[m], nrb[m]) : rb_skipped[m] ? -2 : -1;
            }
            row->cam_selected = median(cs, frames);
            row->cam_visited = median(cv, frames);
            row->cam_ms = median(ct, frames);
            row->cam_resize_ms = median(cr, frames);
        }
        /* c. Embree triangles of the same voxels (depth 12: counted only) */
        tri_mesh tm;
        const bool embree = depth <= 10;
        exposed_faces(svo, 2, &tm, !embree);
        mrow->triangles = (double)tm.tcount;
        if (embree)
            embree_measure(&tm, mrow);
        free(tm.v);
        free(tm.idx);
        mr_svo_extremes_free(&ex);
        mr_svo_voxelize_free(svo);
    }
    free(rs.keys);
    free(rs.payload);
    free(rs.kept);
    free(rs.leaves);
    mr_svo_skin_free(&sk);
    mr_pose_free(pose);
    mr_asset_free(asset);

    printf("\nEvery leaf, no view (median over the clip's frames; rebuilt octree depth = source + "
           "2). select: selection + deformation, Mvox/s = voxels deformed (visited) per second. "
           "Resample columns: total ms, Mcells/s, rebuild = radix sort + compaction + octree build "
           "of the same cells timed apart (the rest of the total is cell generation; not timed "
           "where a second copy of the cells would not fit the memory budget of %.1f GiB), cells "
           "and output voxels.\n\n",
           budget / GIB);
    printf("| depth | threads | voxels | select ms | Mvox/s | resize ms | resize Mcells/s | resize "
           "rebuild ms | resize cells | resize out | emit ms | emit Mcells/s | emit rebuild ms | "
           "emit cells | emit out |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    for (int i = 0; i < nrows; i++) {
        const depth_row *r = &rows[i];
        printf("| %u | %u | %u | %.1f | %.1f ", r->depth, r->threads, r->voxels, r->select_ms,
               r->mvox_s);
        for (int m = 0; m < 2; m++) {
            if (r->skipped[m]) {
                printf("| %s | | | | ", r->skipped[m]);
                continue;
            }
            char rb[32];
            if (r->rebuild_ms[m] >= 0)
                snprintf(rb, sizeof rb, "%.1f", r->rebuild_ms[m]);
            else
                snprintf(rb, sizeof rb, "%s", r->rebuild_ms[m] < -1.5 ? "(memory)" : "n/a");
            printf("| %.1f | %.1f | %s | %.0f | %.0f ", r->ms[m], r->mcells_s[m], rb, r->cells[m],
                   r->out_voxels[m]);
        }
        printf("|\n");
    }
    printf("\nCamera %dx%d, 45 deg vertical, 3 character heights in front, screen-space selection "
           "at delta 1 with frustum culling:\n\n| depth | threads | selected | visited | select ms "
           "| resize ms |\n|---|---|---|---|---|---|\n",
           WIDTH, HEIGHT);
    for (int i = 0; i < nrows; i++)
        printf("| %u | %u | %.0f | %.0f | %.2f | %.2f |\n", rows[i].depth, rows[i].threads,
               rows[i].cam_selected, rows[i].cam_visited, rows[i].cam_ms, rows[i].cam_resize_ms);

    printf("\n### c. Memory per voxel\n\nshared = mr_svo_memory / voxels (with leaf keys; "
           "layout = nodes + leaves + palette only); rebuilt = resize output of the first frame, "
           "per its own voxel. Embree: exposed faces of the shared octree's voxels as shared-vertex "
           "triangles, TRIANGLE geometry, MEDIUM quality, ROBUST scene; bytes = Embree's own "
           "(memory monitor, after the build; peak during it in brackets) + vertex and index "
           "buffers.\n\n");
    printf("| depth | voxels | shared B/voxel | layout B/voxel | rebuilt B/voxel | triangles | "
           "tris/voxel | Embree B/voxel (peak) | Embree / layout | Embree build s |\n"
           "|---|---|---|---|---|---|---|---|---|---|\n");
    double per_tri = 0;
    for (int i = 0; i < ndepth; i++) {
        const memory_row *m = &mem[i];
        printf("| %u | %u | %.2f | %.2f | %.2f | %.0f | %.2f ", m->depth, m->voxels, m->svo_bytes,
               m->svo_layout_bytes, m->rebuilt_bytes, m->triangles, m->triangles / m->voxels);
        if (m->embree) {
            const double b = (m->embree_bytes + m->buffer_bytes) / m->voxels;
            per_tri = (m->embree_bytes + m->buffer_bytes) / m->triangles;
            printf("| %.1f (%.1f) | %.1f | %.2f |\n", b,
                   (m->embree_peak + m->buffer_bytes) / m->voxels, b / m->svo_layout_bytes,
                   m->build_s);
        } else {
            const double b = per_tri * m->triangles / m->voxels;
            printf("| ~%.1f (not built: %.0f B/triangle of the depth above) | ~%.1f | |\n", b,
                   per_tri, b / m->svo_layout_bytes);
        }
    }
}

/* ---- d. instances */

typedef struct inst_worker {
    mr_pose *pose;
    mr_svo_skin sk;
    mr_svo_selection sel;
    float *box;
    mr_svo_leaf *leaf;
    uint8_t *level;
    size_t count, cap;
} inst_worker;

typedef struct inst_rec {
    uint32_t worker;
    size_t at, count;
} inst_rec;

typedef struct inst_frame {
    const mr_asset *asset;
    const mr_svo *svo;
    const mr_svo_extremes *ex;
    const mr_svo_view *view;
    const mr_mat4 *xf;
    const double *offset;
    double time;
    unsigned inner_threads;
    inst_worker *w;
    inst_rec *rec;
} inst_frame;

static void inst_select(void *ctx, size_t begin, size_t end, unsigned worker)
{
    inst_frame *f = ctx;
    inst_worker *w = &f->w[worker];
    mr_error err = {0};
    for (size_t i = begin; i < end; i++) {
        mr_pose_desc desc = clip_desc(f->offset[i]);
        if (mr_pose_eval(w->pose, f->asset, &desc, f->time, &err) < 0)
            die("pose", err.msg);
        mr_svo_skin_pose(&w->sk, f->asset, w->pose, &f->xf[i]);
        mr_svo_deformer d = w->sk.d;
        if (mr_svo_select(f->svo, f->ex, &d, f->view, f->svo->depth, f->inner_threads, &w->sel,
                          &err) < 0)
            die("select", err.msg);
        const size_t n = w->sel.count;
        if (w->count + n > w->cap) {
            w->cap = (w->count + n) * 2;
            w->box = xrealloc(w->box, w->cap * 6 * sizeof *w->box);
            w->leaf = xrealloc(w->leaf, w->cap * sizeof *w->leaf);
            w->level = xrealloc(w->level, w->cap);
        }
        memcpy(w->box + 6 * w->count, w->sel.box, n * 6 * sizeof *w->box);
        memcpy(w->leaf + w->count, w->sel.leaf, n * sizeof *w->leaf);
        memcpy(w->level + w->count, w->sel.level, n);
        f->rec[i] = (inst_rec){worker, w->count, n};
        w->count += n;
    }
}

typedef struct inst_result {
    double select_ms, resample_ms, total_ms;
    double selected, cells, out_voxels;
    double peak;
    unsigned out_depth;
} inst_result;

static void part_d(double deadline)
{
    const unsigned threads = 2;
    mr_asset *asset = NULL;
    mr_svo *svo = NULL;
    mr_svo_extremes ex = {0};
    sw_bounds shape;
    mr_error err = {0};
    if (sw_bcn_octree(8, MR_SVO_VOXELIZE_SURFACE, 0, &asset, &svo, &err) < 0 ||
        mr_svo_extremes_build(svo, &ex, &err) < 0 || sw_octree_bounds(svo, &shape, &err) < 0)
        die("instances", err.msg);
    const double H = shape.hi[1] - shape.lo[1], spacing = 2.0;
    const double voxel = (double)svo->size / (double)(1u << svo->depth);
    const double avail = mem_available();
    const double budget = fmin(8.0 * GIB, 0.6 * avail);
    const size_t n_max = 1u << 20;
    printf("\n### d. Instances (thesis: 10^6 instances of 6 models, 33.8 ms per frame, GTX 260)\n\n"
           "BCN at depth 8 (%u voxels) per instance, each with its own clip offset (poses by "
           "mr_pose_eval) and a turn about y, on a square grid %.1f units apart, the camera "
           "(%dx%d, 45 deg) 30 deg above the grid framing all of it; screen-space selection at "
           "delta 1 with frustum culling (instances in parallel, %u threads), then one resize of "
           "all selected voxels into a world octree. Memory budget %.1f GiB. The renderer's own "
           "per-instance cost (Embree instances of the shared octree) is measured separately "
           "(bench_render).\n\n",
           svo->leaf_count, spacing, WIDTH, HEIGHT, threads, budget / GIB);
    printf("| N | selected | voxels/instance | select ms | resample ms | total ms | cells | world "
           "depth | out voxels | peak RSS MiB | bytes/instance | marginal bytes/instance |\n"
           "|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    inst_worker w[MR_MAX_THREADS];
    memset(w, 0, sizeof w);
    for (unsigned i = 0; i < threads; i++) {
        if (mr_pose_new(asset, &w[i].pose, &err) < 0)
            die("pose", err.msg);
        skin_init(&w[i].sk, asset);
    }
    mr_svo_selection all = {0};
    const bool reset = peak_reset();
    const double base_rss = rss_now();
    size_t fit = 0, last_n = 0;
    double first_ms = 0;
    double last_bytes = 0, last_marginal = 0, last_peak = base_rss;
    const char *stop = "N = 2^20";
    for (size_t n = 1; n <= n_max; n *= 2) {
        const size_t side = (size_t)ceil(sqrt((double)n));
        mr_mat4 *xf = xmalloc(n * sizeof *xf);
        double *offset = xmalloc(n * sizeof *offset);
        inst_rec *rec = xmalloc(n * sizeof *rec);
        for (size_t i = 0; i < n; i++) {
            const double gx = ((double)(i % side) - 0.5 * (double)(side - 1)) * spacing;
            const double gz = ((double)(i / side) - 0.5 * (double)(side - 1)) * spacing;
            uint64_t h = (uint64_t)i * 0x9e3779b97f4a7c15ull;
            h ^= h >> 29;
            const float ang = (float)((double)(h % 6283) * 1e-3);
            mr_mat4 r = mr_mat4_from_trs(mr_v3((float)gx, (float)-shape.lo[1], (float)gz),
                                         mr_quat_from_axis_angle(mr_v3(0, 1, 0), ang),
                                         mr_v3(1, 1, 1));
            xf[i] = r;
            offset[i] = (double)((h >> 16) % 1000) * 1e-3 * asset->clips[0].duration;
        }
        /* frame the grid: radius of the ground square plus a character */
        const double radius = 0.5 * sqrt(2.0) * (double)side * spacing + H;
        const double dist = fmax(3 * H, radius / sin(0.5 * YFOV));
        const mr_vec3 target = mr_v3(0, (float)(0.5 * H), 0);
        const mr_vec3 eye = mr_v3_add(target, mr_v3(0, (float)(dist * 0.5), (float)(dist * 0.866)));
        const mr_svo_view view = make_view(eye, target, (float)(0.01 * dist), (float)(4 * dist));
        const double extent = (double)side * spacing + 2 * H;
        unsigned out_depth = (unsigned)ceil(log2(extent / voxel)) + 1;
        out_depth = out_depth > MR_SVO_MAX_DEPTH ? MR_SVO_MAX_DEPTH : out_depth;
        /* large N: one frame each, so the series reaches far within its time */
        const int repeats = n <= 16 ? 3 : 1;
        double sel_ms[3], res_ms[3], tot_ms[3], selected = 0, cells = 0, outv = 0;
        for (int rep = 0; rep < repeats; rep++) {
            inst_frame f = {.asset = asset, .svo = svo, .ex = &ex, .view = &view, .xf = xf,
                            .offset = offset, .time = rep / 30.0, .w = w, .rec = rec};
            for (unsigned i = 0; i < threads; i++)
                w[i].count = 0;
            double t0 = mr_now();
            if (n < 4 * threads) { /* too few instances to share: parallel inside each */
                f.inner_threads = threads;
                inst_select(&f, 0, n, 0);
            } else {
                f.inner_threads = 1;
                mr_parallel_for(threads, n, 16, inst_select, &f);
            }
            size_t total = 0;
            for (size_t i = 0; i < n; i++)
                total += rec[i].count;
            if (total > all.capacity) {
                all.capacity = total + total / 4;
                all.box = xrealloc(all.box, all.capacity * 6 * sizeof *all.box);
                all.leaf = xrealloc(all.leaf, all.capacity * sizeof *all.leaf);
                all.level = xrealloc(all.level, all.capacity);
            }
            size_t at = 0;
            for (size_t i = 0; i < n; i++) {
                const inst_rec *r = &rec[i];
                const inst_worker *wk = &w[r->worker];
                memcpy(all.box + 6 * at, wk->box + 6 * r->at, r->count * 6 * sizeof *all.box);
                memcpy(all.leaf + at, wk->leaf + r->at, r->count * sizeof *all.leaf);
                memcpy(all.level + at, wk->level + r->at, r->count);
                at += r->count;
            }
            all.count = total;
            double t1 = mr_now();
            mr_svo out = {0};
            uint64_t nc = 0;
            if (mr_svo_resample(&all, MR_SVO_RESIZE, out_depth, svo->palette, svo->palette_count,
                                threads, &out, &nc, &err) < 0)
                die("resample", err.msg);
            double t2 = mr_now();
            sel_ms[rep] = (t1 - t0) * 1e3;
            res_ms[rep] = (t2 - t1) * 1e3;
            tot_ms[rep] = (t2 - t0) * 1e3;
            selected = (double)total;
            cells = (double)nc;
            outv = out.leaf_count;
            mr_svo_free(&out);
        }
        inst_result r = {.select_ms = median(sel_ms, repeats),
                         .resample_ms = median(res_ms, repeats),
                         .total_ms = median(tot_ms, repeats),
                         .selected = selected,
                         .cells = cells,
                         .out_voxels = outv,
                         .peak = peak_rss(),
                         .out_depth = out_depth};
        /* peak RSS grows with the frame's transient buffers (selection, cells, octree) and
         * the per-instance state; the marginal cost of the last doubling is what scales */
        const double bytes = (r.peak - base_rss) / (double)n;
        const double marginal = n > 1 ? (r.peak - last_peak) / (double)(n - last_n) : bytes;
        printf("| %zu | %.0f | %.1f | %.2f | %.2f | %.2f | %.0f | %u | %.0f | %.0f | %.0f | %.0f "
               "|\n",
               n, r.selected, r.selected / (double)n, r.select_ms, r.resample_ms, r.total_ms,
               r.cells, r.out_depth, r.out_voxels, r.peak / (1024.0 * 1024.0), bytes, marginal);
        fflush(stdout);
        if (r.total_ms <= THESIS_MS)
            fit = n;
        if (n == 1)
            first_ms = r.total_ms;
        last_n = n;
        last_bytes = bytes;
        last_marginal = marginal;
        last_peak = r.peak;
        free(xf);
        free(offset);
        free(rec);
        /* the next doubling would need about twice this frame's memory and time */
        if (base_rss + 2.0 * (r.peak - base_rss) > budget && n * 2 <= n_max) {
            stop = "memory budget";
            break;
        }
        const int next_repeats = 2 * n <= 16 ? 3 : 1;
        if (mr_now() + 2.2 * r.total_ms * 1e-3 * next_repeats > deadline && n * 2 <= n_max) {
            stop = "the bench's time budget";
            break;
        }
    }
    /* Where an instance's time goes: pose + skin matrices, and the selection
     * of one far-away instance (a few voxels), one thread, averaged. */
    {
        const int reps = 200;
        mr_pose_desc desc = clip_desc(0);
        const mr_mat4 id = mr_mat4_identity();
        double t0 = mr_now();
        for (int i = 0; i < reps; i++) {
            desc.offset = i * 1e-3;
            if (mr_pose_eval(w[0].pose, asset, &desc, 0.5, &err) < 0)
                die("pose", err.msg);
            mr_svo_skin_pose(&w[0].sk, asset, w[0].pose, &id);
        }
        const double pose_us = (mr_now() - t0) / reps * 1e6;
        const mr_vec3 target = mr_v3(0, (float)(0.5 * H), 0);
        const mr_svo_view far = make_view(mr_v3(0, (float)(0.5 * H), (float)(2000 * H)), target,
                                          (float)H, (float)(4000 * H));
        mr_svo_deformer d = w[0].sk.d;
        t0 = mr_now();
        for (int i = 0; i < reps; i++)
            if (mr_svo_select(svo, &ex, &d, &far, svo->depth, 1, &w[0].sel, &err) < 0)
                die("select", err.msg);
        const double sel_us = (mr_now() - t0) / reps * 1e6;
        sw_field ident = sw_field_make(SW_SCALE, 1.0, &shape);
        mr_svo_deformer fd = {.field = sw_field_matrix, .field_ctx = &ident};
        t0 = mr_now();
        for (int i = 0; i < reps; i++)
            if (mr_svo_select(svo, &ex, &fd, &far, svo->depth, 1, &w[0].sel, &err) < 0)
                die("select", err.msg);
        const double field_us = (mr_now() - t0) / reps * 1e6;
        printf("\nPer instance, one thread: pose (mr_pose_eval) + skin matrices %.1f us; selection "
               "of a far instance (%zu voxels) %.1f us skinned (matrices blended for the voxels "
               "it reaches, of a palette of %u entries), %.1f us with a field deformer.\n",
               pose_us, w[0].sel.count, sel_us, svo->palette_count, field_us);
    }
    /* 24 GiB: from the last frame's peak on at the marginal cost (the average if the
     * marginal one is not positive: RSS measurements are coarse) */
    const double per = last_marginal > 0 ? last_marginal : last_bytes;
    const double n24 = per > 0 ? (double)last_n + (24.0 * GIB - last_peak) / per : 0.0;
    char fits[64];
    if (fit)
        snprintf(fits, sizeof fits, "%zu", fit);
    else
        snprintf(fits, sizeof fits, "none (N = 1 takes %.1f ms)", first_ms);
    printf("\nLargest N within %.1f ms per frame: %s. Stopped at N = %zu (%s). At N = %zu: "
           "%.0f bytes of peak RSS growth per instance (average), %.0f per added instance "
           "(marginal, last doubling); 24 GiB would run out near N = %.3g (extrapolated "
           "linearly at the marginal cost).\n",
           THESIS_MS, fits, last_n, stop, last_n, last_bytes, last_marginal, n24);
    if (!reset)
        printf("(The peak RSS could not be reset: figures include the earlier parts' peak.)\n");
    for (unsigned i = 0; i < threads; i++) {
        mr_pose_free(w[i].pose);
        mr_svo_skin_free(&w[i].sk);
        mr_svo_selection_free(&w[i].sel);
        free(w[i].box);
        free(w[i].leaf);
        free(w[i].level);
    }
    free(all.box);
    free(all.leaf);
    free(all.level);
    mr_svo_extremes_free(&ex);
    mr_svo_voxelize_free(svo);
    mr_asset_free(asset);
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
    double t0 = mr_now();
    if (strchr(only, 'a'))
        part_a(quick);
    if (strchr(only, 'b') || strchr(only, 'c'))
        part_bc(quick);
    /* part d doubles N while the next frame fits in its share of the ~5 minutes */
    if (strchr(only, 'd'))
        part_d(mr_now() + (quick ? 45.0 : 110.0));
    printf("\n(bench_svo: %.0f s)\n", mr_now() - t0);
    return 0;
}
