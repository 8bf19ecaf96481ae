/*
 * svo_kind.c - the `svo` geometry kind (issue 5, paper 004): an asset
 * voxelised once into a sparse voxel octree shared by every instance of the
 * object, each instance with its own transform and pose.
 *
 * Methods (job "method", deform.h):
 *  - rigid: the shared octree sits in its own Embree scene as a user
 *    geometry (svo_trace.h casts the rays); every instance is an Embree
 *    instance of that scene (the thesis' instance model: shared octree,
 *    unshared matrices). One Embree geometry id per instance (kind.h
 *    geometry_ids), so hits name the instance.
 *  - direct: each frame every instance is selected and deformed (deform.h);
 *    the deformed voxel boxes of all instances are one user geometry, one
 *    primitive per box, over which Embree builds its BVH.
 *  - resize / emit: each instance's selection is resampled into its own
 *    world-space octree, rebuilt every frame; one user geometry whose
 *    primitives are the instances' octrees, each as its subtrees (or whole
 *    when small: octree_prim), traced by svo_trace.h. The id pass names
 *    the instance (svo_id_primitive).
 * Rays hitting an octree report the leaf and its level in u and v (u: the
 * leaf's high 16 bits and the level above them, v: its low 16 bits; small
 * exact floats) so normal() can find the voxel's normal and surface_step
 * its size.
 * Instance poses are evaluated here (self_posed), one instance after the
 * other per worker, so memory does not grow with instances x joints.
 * With "skeleton" the asset has no usable skin: a skeleton is extracted
 * from the voxels (chapter 5, skeleton.h) and the kind poses the rigged
 * copy, whose bones "bone<k>" the instance poses may name.
 * The exact reference (tessellate) is the asset's triangles skinned with
 * each instance's pose: what the voxels approximate.
 */
#include <float.h>
#include <math.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "kinds/svo/deform.h"
#include "kinds/svo/skeleton.h"
#include "kinds/svo/svo_kind.h"
#include "kinds/svo/svo_file.h"
#include "kinds/svo/svo_trace.h"
#include "kinds/svo/voxelize.h"
#include "kinds/user_rays.h"
#include "util/parallel.h"

/* An Embree primitive of an octree object: an octree (rigid: the shared
 * one; resize, emit: instance `instance`'s), whole (PRIM_WHOLE) or below
 * the subtree of interior node `node` at `level`, cell xyz. A piece's box
 * is its occupied cells some levels down (fit_boxes), kept as their range
 * within its cell in cells of that level, 4 bits an end (fit: first |
 * end << 4 per axis); prim_box makes the floats from it when Embree or a
 * ray asks. 16 bytes a piece: the rigid dancer's 3,425 pieces at depth 10
 * take 0.06 bytes a voxel of its octree's 7.9; with float boxes and the
 * subtree's full coordinates (52 bytes) they took 0.20. */
typedef struct octree_prim {
    uint32_t node;
    uint32_t instance;
    uint8_t level;
    uint8_t xyz[3];
    uint8_t fit[3];
    uint8_t flags;
} octree_prim;
_Static_assert(sizeof(octree_prim) == 16, "a piece is 16 bytes");

enum {
    PRIM_WHOLE = 1, /* the octree from its root, boxed by its leaves (mr_svo_bounds) */
    PRIM_EMPTY = 2, /* no leaf: no box */
};

/* Scratch of one worker: a pose and the matrices of one instance. */
typedef struct worker_scratch {
    mr_pose *pose;
    mr_svo_skin skin;
    mr_svo_workspace *ws;         /* selection / resampling scratch, kept across frames */
    mr_svo_selection sel;         /* resize, emit: the instance being resampled (direct keeps
                                   * each instance's selection in mr_geom.sel) */
    int rc;                       /* first failure of this worker ... */
    size_t failed_instance;       /* ... and the instance it came from */
    mr_error err;
    /* where this frame's time went, over the instances this worker did */
    double pose_s, select_s, emit_s, rebuild_s;
    uint64_t cells;               /* emitted before compaction */
    uint64_t visited, selected;   /* voxels deformed / selected */
    double worst_px;              /* with a tolerance: the worst selected voxel (predict) */
    uint32_t deepest;             /* ... and the deepest level selected */
} worker_scratch;

struct mr_geom {
    const mr_asset *asset;        /* posing asset: the source, or the rigged copy */
    mr_asset *rigged;             /* owned rigged copy (skeleton), or NULL */
    const mr_object_desc *desc;
    const mr_svo_params *p;      /* desc->params */
    mr_svo_method method;
    mr_svo *svo;                  /* shared octree, bind space */
    mr_svo_extremes extremes;
    unsigned out_depth;           /* depth of the per-frame world octrees */
    size_t instance_count;
    mr_mat4 *world;               /* per instance: object transform * instance transform */
    mr_mat4 *world_normal;        /* per instance: its normal matrix */
    bool *invertible;             /* per instance (rigid instances need an inverse) */
    mr_svo_lod *lod;              /* rigid with "tolerance_px": per instance, the cast's level
                                   * of detail for the frame's camera (rigid_lod); else NULL */
    unsigned workers;
    worker_scratch *scratch;
    /* per frame */
    mr_svo_selection *sel;        /* direct: per instance (resize and emit select into the
                                   * worker's scratch and keep only the octree) */
    mr_svo *octree;               /* per instance (resize, emit) */
    octree_prim *prims;           /* rigid (made once), resize, emit (each frame): what
                                   * Embree traces, prim_count of them */
    uint32_t prim_count;
    size_t prim_capacity;
    size_t box_count, box_capacity;
    float *box;                   /* direct: all instances' boxes */
    mr_svo_leaf *box_leaf;
    uint64_t visited, cells;      /* voxels deformed / output voxels, last frame */
    uint64_t selected, emitted;   /* voxels selected / cells emitted, last frame */
    double pose_s, select_s, emit_s, rebuild_s; /* last frame, summed over instances */
    size_t octree_bytes;          /* the per-instance octrees, last frame */
    /* creation (reported with the renderer's first frame: SVO_STATS) */
    double build_s, skeleton_s;
    uint32_t bones;
    double thinness_pct;
    size_t last_frame;            /* the frame of the last update (tessellate poses it) */
    double last_time;
    /* Embree */
    RTCScene shared_scene;        /* rigid: the octree as a user geometry */
    RTCGeometry user;             /* direct / resize / emit: the object's user geometry */
    RTCGeometry *instances;       /* rigid: one instance geometry per instance */
    unsigned first_id;
    size_t budget;                /* bytes the object may hold (kind.h memory_budget), 0: any */
    /* "tolerance_px" (0: off; the selecting methods' delta, rigid's cast
     * level of detail), the last frame's predicted error and deepest
     * level selected (predict; rigid: the tolerance and the depth) */
    double tolerance_px, predicted_px;
    uint32_t deepest;
};

/* The "method" names, in mr_svo_method order. */
static const char *const METHODS[] = {"rigid", "direct", "resize", "emit"};

/* ---- the posing side ------------------------------------------------ */

static const mr_pose_desc *object_pose(const mr_object_desc *d, size_t frame)
{
    if (d->pose_count == 0)
        return NULL;
    return d->pose_count == 1 ? &d->poses[0] : &d->poses[frame < d->pose_count ? frame : 0];
}

static const mr_pose_desc *instance_pose(const mr_geom *g, size_t k, size_t frame)
{
    const mr_svo_params *s = g->p;
    if (s->instance_count > 0 && s->instances[k].has_pose)
        return &s->instances[k].pose;
    return object_pose(g->desc, frame);
}

#define SQRT3 1.7320508075688772

/* The largest scale matrix m applies (its longest column). */
static double largest_scale(const mr_mat4 *m)
{
    double scale = 0;
    for (int c = 0; c < 3; c++) {
        const float *e = m->m;
        double len = sqrt((double)e[c] * e[c] + (double)e[4 + c] * e[4 + c] + (double)e[8 + c] * e[8 + c]);
        scale = len > scale ? len : scale;
    }
    return scale;
}

/* Perspective projection of the frame's camera, far plane at infinity
 * (only the near plane culls), for the screen-space selection. With a
 * tolerance, voxels are refined until they project smaller than
 * tolerance / sqrt(3) (predict says why). */
static mr_svo_view frame_view(const mr_geom *g, const mr_geom_frame *f)
{
    mr_svo_view v = {.enabled = false};
    if (!f || f->width <= 0 || f->height <= 0)
        return v;
    mr_mat4 cam = mr_mat4_from_trs(f->camera.position, f->camera.rotation, mr_v3(1, 1, 1));
    mr_mat4 view;
    if (!mr_mat4_inverse(&cam, &view))
        return v;
    float fy = 1.0f / tanf(0.5f * f->camera.yfov);
    float fx = fy * (float)f->height / (float)f->width;
    const float near = 1e-4f;
    mr_mat4 proj = {{fx, 0, 0, 0, 0, fy, 0, 0, 0, 0, -1, -2 * near, 0, 0, -1, 0}};
    v.enabled = true;
    v.view_proj = mr_mat4_mul(&proj, &view);
    v.width = f->width;
    v.height = f->height;
    /* (held to the smallest normal float: a tolerance of 1e-45 pixels is
     * every leaf, not a delta of 0) */
    v.delta = g->tolerance_px > 0 ? fmaxf((float)(g->tolerance_px / SQRT3), FLT_MIN) : g->p->delta;
    v.cull = g->p->cull;
    return v;
}

typedef struct frame_ctx {
    mr_geom *g;
    const mr_geom_frame *frame;
    mr_svo_view view;
    unsigned inner_threads;
    _Atomic size_t held;          /* bytes the instances deformed so far hold */
    atomic_bool over_budget;      /* the failure is the object's, not one instance's */
} frame_ctx;

static size_t selection_bytes(const mr_svo_selection *sel)
{
    return sel->capacity * (6 * sizeof(float) + sizeof(mr_svo_leaf) + 1);
}

/* What instance k's per-frame data holds: its selection (direct) or its
 * octree (resize, emit). */
static size_t instance_bytes(const mr_geom *g, size_t k)
{
    return g->octree ? mr_svo_memory(&g->octree[k]) : selection_bytes(&g->sel[k]);
}

static int over_budget(frame_ctx *c, size_t held, mr_error *err)
{
    char have[MR_BYTES_TEXT], cap[MR_BYTES_TEXT];
    mr_format_bytes(held, have, sizeof have);
    mr_format_bytes(c->g->budget, cap, sizeof cap);
    atomic_store(&c->over_budget, true);
    return mr_error_set(err, MR_ERR_LIMIT,
                        "svo/instances: %zu instances hold more than the job's memory budget of "
                        "%s this frame (%s before all were deformed; fewer instances, a smaller "
                        "depth, or method rigid)", c->g->instance_count, cap, have);
}

/* The predicted error of a selection ("tolerance_px"), gathered into the
 * worker's scratch over its instances: the most
 * pixels the diagonal of any selected voxel's deformed box spans
 * (mr_camera_px_per_unit at the box). The detailed surface passes through
 * every voxel it was voxelised into and the voxel's faces lie within its
 * diagonal of it, so a voxel strays from the surface by at most that; the
 * selection stops refining a voxel once its box projects below
 * tolerance / sqrt(3) pixels on both axes, so coarse voxels keep within
 * the tolerance, and leaves (which cannot be refined) show what the
 * octree's depth allows: up close the prediction passes the tolerance,
 * which then needs a deeper octree ("depth"). Deformation moves voxels
 * off the skinned detailed mesh besides; the reference passes measure
 * that. */
static void predict(const mr_svo_selection *sel, const mr_geom_frame *frame, worker_scratch *s)
{
    for (size_t i = 0; i < sel->count; i++) {
        s->deepest = sel->level[i] > s->deepest ? sel->level[i] : s->deepest;
        const float *b = sel->box + i * 6;
        mr_vec3 lo = mr_v3(b[0], b[1], b[2]), hi = mr_v3(b[3], b[4], b[5]);
        double px = mr_camera_px_per_unit(&frame->camera, frame->width, frame->height, lo, hi);
        if (!isfinite(px))
            continue; /* reaches the camera's plane: refined to its leaves, not projected */
        s->worst_px = fmax(s->worst_px, px * mr_v3_len(mr_v3_sub(hi, lo)));
    }
}

static int deform_instance(frame_ctx *c, size_t k, worker_scratch *s, mr_error *err)
{
    mr_geom *g = c->g;
    size_t frame = c->frame ? c->frame->index : 0;
    double t = c->frame ? c->frame->time : 0;
    double t0 = mr_now();
    int rc = mr_pose_eval(s->pose, g->asset, instance_pose(g, k, frame), t, err);
    if (rc < 0)
        return rc;
    mr_svo_skin_pose(&s->skin, g->asset, s->pose, &g->world[k]);
    double t1 = mr_now();
    mr_svo_selection *sel = g->method == MR_SVO_DIRECT ? &g->sel[k] : &s->sel;
    rc = mr_svo_select_ws(g->svo, &g->extremes, &s->skin.d, &c->view, g->svo->depth, c->inner_threads, s->ws,
                          sel, err);
    s->pose_s += t1 - t0;
    s->select_s += mr_now() - t1;
    if (rc == MR_OK) {
        s->visited += sel->visited;
        s->selected += sel->count;
        if (g->tolerance_px > 0 && c->frame)
            predict(sel, c->frame, s);
    }
    if (rc == MR_OK && g->method != MR_SVO_DIRECT) {
        uint64_t cells = 0;
        double emit_s, rebuild_s;
        rc = mr_svo_resample_ws(sel, g->method, g->out_depth, g->svo->palette,
                                g->svo->palette_count, c->inner_threads, s->ws, &g->octree[k], &cells,
                                err);
        mr_svo_workspace_resample_times(s->ws, &emit_s, &rebuild_s);
        s->emit_s += emit_s;
        s->rebuild_s += rebuild_s;
        s->cells += cells;
    }
    if (rc < 0)
        return rc;
    /* The creation estimate can be beaten by a frame that selects more:
     * the running total stops the frame within one instance per worker of
     * the budget instead of letting it grow to whatever the parameters
     * ask (issue 12: 100,000 emit instances grew past 23 GB). */
    size_t held = atomic_fetch_add(&c->held, instance_bytes(g, k)) + instance_bytes(g, k);
    if (g->budget && held > g->budget)
        return over_budget(c, held, err);
    return MR_OK;
}

static void deform_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    frame_ctx *c = ctx;
    worker_scratch *s = &c->g->scratch[worker];
    for (size_t k = begin; k < end; k++) {
        if (s->rc < 0 || atomic_load(&c->over_budget)) /* the others stop too */
            return;
        mr_error e = {0};
        int rc = deform_instance(c, k, s, &e);
        if (rc < 0) {
            s->rc = rc;
            s->failed_instance = k;
            s->err = e;
        }
    }
}

/* Every kind keeps what it hands Embree within MR_MAX_COORDINATE (kind.h):
 * beyond ~1.8e18 Embree silently drops primitives, so a pose that scales
 * voxels that far fails the frame instead. */
static int check_extent(float biggest, size_t instance, mr_error *err)
{
    if (biggest <= MR_MAX_COORDINATE)
        return MR_OK;
    return mr_error_set(err, MR_ERR_INVALID,
                        "svo: instance %zu's posed voxels reach %g, beyond %g", instance,
                        (double)biggest, MR_MAX_COORDINATE);
}

static float octree_extent(const mr_svo *o)
{
    float lo[3], hi[3], m = 0;
    if (!mr_svo_bounds(o, lo, hi))
        return 0;
    for (int a = 0; a < 3; a++)
        m = fmaxf(m, fmaxf(fabsf(lo[a]), fabsf(hi[a])));
    return m;
}

static int gather_boxes(mr_geom *g, mr_error *err)
{
    size_t total = 0;
    for (size_t k = 0; k < g->instance_count; k++)
        total += g->sel[k].count;
    if (total > UINT32_MAX - 1)
        return mr_error_set(err, MR_ERR_LIMIT, "svo: %zu deformed voxels in one frame, more than Embree takes", total);
    if (total > g->box_capacity) {
        float *b = realloc(g->box, total * 6 * sizeof *b);
        if (b)
            g->box = b;
        mr_svo_leaf *l = realloc(g->box_leaf, total * sizeof *l);
        if (l)
            g->box_leaf = l;
        if (!b || !l)
            return mr_error_set(err, MR_ERR_NOMEM, "svo: out of memory for %zu deformed voxels", total);
        g->box_capacity = total;
    }
    size_t at = 0;
    for (size_t k = 0; k < g->instance_count; k++) {
        const mr_svo_selection *s = &g->sel[k];
        if (s->count == 0)
            continue;
        /* (the selection refused non-finite boxes; fmaxf is a library
         * call per coordinate here, 3 % of a direct frame) */
        float biggest = 0;
        for (size_t i = 0; i < s->count * 6; i++) {
            const float x = fabsf(s->box[i]);
            biggest = x > biggest ? x : biggest;
        }
        int rc = check_extent(biggest, k, err);
        if (rc < 0)
            return rc;
        memcpy(g->box + at * 6, s->box, s->count * 6 * sizeof *g->box);
        memcpy(g->box_leaf + at, s->leaf, s->count * sizeof *g->box_leaf);
        at += s->count;
    }
    g->box_count = total;
    return MR_OK;
}

/* The octrees' primitives for Embree: their subtrees at level
 * SUBTREE_LEVEL (mr_svo_subtrees). Embree's tree over their boxes then does
 * the octree's top levels, where rays mostly cross empty space. The rigid
 * dancer at 640x360 (bench_svo_render), trace time over the triangles' at
 * depths 8 / 10 / 12, when pieces were boxed by their cells: one walk from the
 * root 2.3 / 3.2 / 4.8; subtrees at level 3: 1.9 / 2.8 / 4.5, 4: 1.8 / 2.8 /
 * 4.4, 5: 1.7 / 2.6 / 4.2, 6: 1.7 / 2.7 / 4.2, with Embree's tree over them
 * at 0.1, 0.5, 2.2 and 6.6 bytes per voxel at depth 8. */
#define SUBTREE_LEVEL 5u
/* The rigid octree's pieces (made once), since their boxes are fitted to
 * their occupied cells (RIGID_BOX_LEVELS): a level deeper, in 4.2 times as
 * many pieces (the dancer: 3,425 at level 6, 815 at 5), rays walk a level
 * less in each piece they enter. The dancer at 640x360, trace ms at level 6
 * over level 5, alternated: 0.93-0.94 at depth 8, 0.88-0.93 at depth 10,
 * 0.85-0.93 at depth 12 with "tolerance_px" 1, the frames bit for bit the
 * same; level 7 over 6 read 0.96-0.98 at depth 8 and 0.94-1.01 at 10, level
 * 8 1.08 at 10. Embree's tree over the pieces grows from 0.1 to 0.3 bytes
 * a voxel at depth 10. */
#define RIGID_SUBTREE_LEVEL 6u
/* A piece's cell coordinates and its box's range are small integers. */
_Static_assert(SUBTREE_LEVEL <= 8 && RIGID_SUBTREE_LEVEL <= 8, "a piece's cell fits in 8 bits an axis");
/* Leaves a resize / emit octree's subtrees hold at least on average: an
 * octree whose subtrees at SUBTREE_LEVEL hold fewer is cut nearer the
 * root, or traced whole: Embree builds its tree over the pieces every
 * frame, and small pieces cost more to build than they save in tracing
 * (bench_svo d, 256 instances of ~5,000 voxels at level 5 always: 137 ms
 * to build against 0.3 whole; 2.6 ms with this rule). The dancer at
 * 640x360 (bench_svo_render, depths 8 / 10, resize) traces in 3.3 / 3.8 ms
 * at 16 leaves a subtree, 3.6 / 3.9 at 256, 4.0 / 4.0 at 1024 and 4.8 /
 * 5.1 whole. */
#define LEAVES_PER_SUBTREE 256u
/* How far below an octree's piece its box is fitted to the occupied cells
 * (mr_svo_subtree_cells): a piece's cube around a sheet of surface is
 * mostly air, and every ray through that air called the piece. The rigid
 * dancer at 640x360, trace ms at depths 8 / 10 / 12 (three runs each, side
 * by side): the cube 1.94-1.96 / 2.98-3.10 / 5.18-6.04, 3 levels 1.58-1.70
 * / 2.22-2.77 / 4.83-5.31, every level 1.50-1.76 / 2.38-2.63 / 4.70-5.25.
 * Rigid pieces get their boxes once, when the object is made. Resize and
 * emit pieces get theirs every frame, on the job's threads (fit_boxes),
 * and two levels down: the dancer resized at depth 10 (about 1,000
 * pieces, two threads) traced in 2.06-2.14 ms with cubes, 1.79-1.87 two
 * levels down and 1.70-1.77 three, but three levels took 0.43-0.50 ms to
 * fit and two take 0.19-0.23. */
#define RIGID_BOX_LEVELS 3u
#define FRAME_BOX_LEVELS 2u
_Static_assert(RIGID_BOX_LEVELS <= 3 && FRAME_BOX_LEVELS <= 3, "a piece's box ends fit in 4 bits");

static void prim_fit(const mr_geom *g, octree_prim *p);

/* Appends instance k's octree (rigid: the shared one) to the primitives as
 * its n subtrees st, or whole when n is 0; frees st. Their boxes are made
 * afterwards, by fit_boxes. */
static int prims_add(mr_geom *g, size_t k, mr_svo_subtree *st, uint32_t n, mr_error *err)
{
    const size_t need = (size_t)g->prim_count + (n ? n : 1);
    if (need >= UINT32_MAX) {
        free(st);
        return mr_error_set(err, MR_ERR_LIMIT, "svo: %zu octree pieces, more than Embree takes", need);
    }
    if (need > g->prim_capacity) {
        const size_t cap = need > 2 * g->prim_capacity ? need : 2 * g->prim_capacity;
        octree_prim *q = realloc(g->prims, cap * sizeof *q);
        if (!q) {
            free(st);
            return mr_error_set(err, MR_ERR_NOMEM, "svo: out of memory for %zu octree pieces", need);
        }
        g->prims = q;
        g->prim_capacity = cap;
    }
    if (n == 0)
        g->prims[g->prim_count++] = (octree_prim){.instance = (uint32_t)k, .flags = PRIM_WHOLE};
    for (uint32_t i = 0; i < n; i++)
        g->prims[g->prim_count++] = (octree_prim){.node = st[i].node,
                                                  .instance = (uint32_t)k,
                                                  .level = (uint8_t)st[i].level,
                                                  .xyz = {(uint8_t)st[i].xyz[0], (uint8_t)st[i].xyz[1],
                                                          (uint8_t)st[i].xyz[2]}};
    free(st);
    return MR_OK;
}

static void fit_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    mr_geom *g = ctx;
    for (size_t i = begin; i < end; i++)
        prim_fit(g, &g->prims[i]);
}

/* Every primitive's box (prim_box), on `threads` threads: each box is its
 * piece's alone, so they are the same for any thread count. */
static void fit_boxes(mr_geom *g, unsigned threads)
{
    mr_parallel_for(threads, g->prim_count, 64, fit_range, g);
}

/* The frame's primitives (resize, emit): each instance's octree as its
 * subtrees, or whole when it is small or has no interior node; empty
 * octrees give none; their boxes on `threads` threads. */
static int gather_prims(mr_geom *g, unsigned threads, mr_error *err)
{
    g->prim_count = 0;
    for (size_t k = 0; k < g->instance_count; k++) {
        const mr_svo *o = &g->octree[k];
        if (o->leaf_count == 0)
            continue;
        mr_svo_subtree *st = NULL;
        uint32_t n = 0, counts[SUBTREE_LEVEL + 1];
        /* the deepest level whose subtrees hold enough (fewer than two
         * subtrees' worth of leaves: whole, without looking) */
        unsigned level = 0;
        int rc;
        if (o->leaf_count >= 2 * LEAVES_PER_SUBTREE) {
            if ((rc = mr_svo_subtree_counts(o, SUBTREE_LEVEL, counts, err)) < 0)
                return rc;
            for (level = SUBTREE_LEVEL; level > 0; level--)
                if (counts[level] <= 1 || (uint64_t)counts[level] * LEAVES_PER_SUBTREE <= o->leaf_count)
                    break;
        }
        if ((level > 0 && (rc = mr_svo_subtrees(o, level, &st, &n, err)) < 0) ||
            (rc = prims_add(g, k, st, n, err)) < 0)
            return rc;
    }
    fit_boxes(g, threads);
    return MR_OK;
}

/* Scratch for `workers` workers (a pose, skin matrices and a workspace
 * each), grown as the job's thread count asks; kept across frames. */
static int ensure_workers(mr_geom *g, unsigned workers, mr_error *err)
{
    if (workers <= g->workers)
        return MR_OK;
    worker_scratch *grown = realloc(g->scratch, workers * sizeof *grown);
    if (!grown)
        return mr_error_set(err, MR_ERR_NOMEM, "svo: out of memory for %u workers", workers);
    memset(grown + g->workers, 0, (workers - g->workers) * sizeof *grown);
    g->scratch = grown;
    unsigned first = g->workers;
    g->workers = workers; /* zeroed entries are safe to free */
    for (unsigned w = first; w < workers; w++) {
        worker_scratch *s = &g->scratch[w];
        int rc;
        if ((rc = mr_pose_new(g->asset, &s->pose, err)) < 0 ||
            (rc = mr_svo_skin_init(&s->skin, g->asset, err)) < 0 ||
            (rc = mr_svo_workspace_new(&s->ws, err)) < 0)
            return rc;
    }
    return MR_OK;
}

/* Rigid with a tolerance: each instance's level of detail (mr_svo_lod)
 * for the frame's camera. A hit on a cell of edge e (bind space) rather
 * than on the leaves inside it moves by at most sqrt(3) e s in the world
 * (s the instance's largest scale), which spans at most sqrt(3) e s k / z
 * pixels (mr_camera_px_scale: k pixels per unit at depth 1, the frustum's
 * corners included; z the camera depth of the hit, to first order in e /
 * z). That is within the tolerance t when e <= t z / (sqrt(3) s k), and z
 * is affine in the bind-space point p: z = (W^T f) . p + (w - c) . f, W
 * and w the instance's linear part and translation, c and f the camera's
 * position and forward axis. Without a camera (or a degenerate scale) the
 * cast keeps every level: b = -inf turns the walk's test off. */
static void rigid_lod(mr_geom *g, const mr_geom_frame *frame)
{
    if (!g->lod)
        return;
    const mr_px_scale px = frame ? mr_camera_px_scale(&frame->camera, frame->width, frame->height)
                                 : (mr_px_scale){.none = true};
    const double f[3] = {px.forward.x, px.forward.y, px.forward.z};
    const double c[3] = {px.position.x, px.position.y, px.position.z};
    for (size_t k = 0; k < g->instance_count; k++) {
        mr_svo_lod *l = &g->lod[k];
        const double s = largest_scale(&g->world[k]);
        const double q = px.none ? 0.0 : g->tolerance_px / (SQRT3 * s * px.k);
        if (!(q > 0.0) || !isfinite(q)) {
            *l = (mr_svo_lod){.b = -INFINITY};
            continue;
        }
        const float *w = g->world[k].m;
        double b = 0.0;
        for (int a = 0; a < 3; a++) {
            l->a[a] = q * ((double)w[a] * f[0] + (double)w[4 + a] * f[1] + (double)w[8 + a] * f[2]);
            b += ((double)w[4 * a + 3] - c[a]) * f[a];
        }
        l->b = q * b;
    }
}

static int svo_update(mr_geom *g, const mr_geom_frame *frame, const mr_pose *pose,
                      const mr_mat4 *transform, unsigned threads, mr_error *err)
{
    (void)pose; /* self_posed: each instance has its own */
    if (frame && frame->view_only && g->method == MR_SVO_RIGID) {
        rigid_lod(g, frame); /* nothing but the camera moved: the instances are where they were */
        return MR_OK;
    }
    mr_mat4 object = transform ? *transform : mr_mat4_identity();
    for (size_t k = 0; k < g->instance_count; k++) {
        const mr_mat4 inst = g->p->instance_count ? g->p->instances[k].transform
                                                         : mr_mat4_identity();
        g->world[k] = mr_mat4_mul(&object, &inst);
        /* The cofactor flips normals of mirroring transforms (det < 0):
         * undo that, so normals keep pointing out of the surface. */
        g->world_normal[k] = mr_mat4_normal_matrix(&g->world[k]);
        const float *w = g->world[k].m;
        float det = w[0] * (w[5] * w[10] - w[6] * w[9]) - w[1] * (w[4] * w[10] - w[6] * w[8]) +
                    w[2] * (w[4] * w[9] - w[5] * w[8]);
        if (det < 0)
            for (int i = 0; i < 12; i++)
                g->world_normal[k].m[i] = -g->world_normal[k].m[i];
        mr_mat4 inv;
        g->invertible[k] = mr_mat4_inverse(&g->world[k], &inv);
        for (int i = 0; i < 12; i++)
            if (!(fabsf(g->world[k].m[i]) <= MR_MAX_COORDINATE))
                return mr_error_set(err, MR_ERR_INVALID,
                                    "svo: instance %zu's transform reaches beyond %g", k,
                                    MR_MAX_COORDINATE);
    }
    if (g->method == MR_SVO_RIGID) {
        float lo[3], hi[3];
        if (mr_svo_bounds(g->svo, lo, hi))
            for (size_t k = 0; k < g->instance_count; k++) {
                float biggest = 0;
                for (int c = 0; c < 8; c++) {
                    mr_vec3 p = mr_mat4_point(&g->world[k], mr_v3(c & 1 ? hi[0] : lo[0],
                                                                  c & 2 ? hi[1] : lo[1],
                                                                  c & 4 ? hi[2] : lo[2]));
                    biggest = fmaxf(biggest, fmaxf(fabsf(p.x), fmaxf(fabsf(p.y), fabsf(p.z))));
                }
                int rc = check_extent(biggest, k, err);
                if (rc < 0)
                    return rc;
            }
    }
    g->visited = g->cells = g->selected = g->emitted = 0;
    g->pose_s = g->select_s = g->emit_s = g->rebuild_s = 0;
    g->predicted_px = 0;
    g->deepest = 0;
    g->octree_bytes = 0;
    g->last_frame = frame ? frame->index : 0;
    g->last_time = frame ? frame->time : 0;
    if (g->method == MR_SVO_RIGID) {
        rigid_lod(g, frame);
        if (g->lod) {
            g->predicted_px = g->tolerance_px;
            g->deepest = g->svo->depth;
        }
        return MR_OK;
    }

    /* The job's thread count (the renderer's device), not the machine's
     * cores: a job asked to use T threads uses T, and holds scratch for no
     * more workers than it runs. */
    unsigned workers = threads ? threads : mr_cpu_count();
    if (workers > MR_MAX_THREADS)
        workers = MR_MAX_THREADS;
    /* Many instances: one instance per task, each single-threaded, one
     * scratch per worker; few: one after the other, each on all workers,
     * in scratch 0. Either way the results do not depend on the thread
     * count (deform.h). */
    bool per_instance = g->instance_count >= 2 * (size_t)workers && workers > 1;
    int rc = ensure_workers(g, per_instance ? workers : 1, err);
    if (rc < 0)
        return rc;
    frame_ctx c = {.g = g, .frame = frame, .view = frame_view(g, frame),
                   .held = mr_svo_memory(g->svo)};
    for (unsigned w = 0; w < g->workers; w++) {
        worker_scratch *s = &g->scratch[w];
        s->rc = 0;
        s->pose_s = s->select_s = s->emit_s = s->rebuild_s = 0;
        s->cells = s->visited = s->selected = 0;
        s->worst_px = 0;
        s->deepest = 0;
    }
    if (per_instance) {
        c.inner_threads = 1;
        mr_parallel_for(workers, g->instance_count, 1, deform_range, &c);
    } else {
        c.inner_threads = workers;
        deform_range(&c, 0, g->instance_count, 0);
    }
    worker_scratch *bad = NULL;
    for (unsigned w = 0; w < g->workers; w++)
        if (g->scratch[w].rc < 0 && (!bad || g->scratch[w].failed_instance < bad->failed_instance))
            bad = &g->scratch[w];
    if (bad) {
        *err = bad->err;
        if (g->p->instance_count && !atomic_load(&c.over_budget))
            mr_error_prefix(err, "svo/instances/%zu: ", bad->failed_instance);
        return bad->rc;
    }
    for (unsigned w = 0; w < g->workers; w++) {
        const worker_scratch *s = &g->scratch[w];
        g->pose_s += s->pose_s;
        g->select_s += s->select_s;
        g->emit_s += s->emit_s;
        g->rebuild_s += s->rebuild_s;
        g->emitted += s->cells;
        g->visited += s->visited;
        g->selected += s->selected;
        g->predicted_px = fmax(g->predicted_px, s->worst_px);
        g->deepest = s->deepest > g->deepest ? s->deepest : g->deepest;
    }
    for (size_t k = 0; k < g->instance_count && g->method != MR_SVO_DIRECT; k++) {
        g->cells += g->octree[k].leaf_count;
        g->octree_bytes += mr_svo_memory(&g->octree[k]);
        if ((rc = check_extent(octree_extent(&g->octree[k]), k, err)) < 0)
            return rc;
    }
    if (g->method == MR_SVO_DIRECT)
        return gather_boxes(g, err);
    return gather_prims(g, workers, err);
}

/* ---- Embree callbacks ------------------------------------------------ */

static void set_bounds(struct RTCBounds *b, const float lo[3], const float hi[3])
{
    b->lower_x = lo[0];
    b->lower_y = lo[1];
    b->lower_z = lo[2];
    b->upper_x = hi[0];
    b->upper_y = hi[1];
    b->upper_z = hi[2];
}

/* The octree Embree primitive prim traces (octree_prim) and in *st the
 * subtree below which (made in *buf), or NULL when it traces the whole
 * octree. NULL: no such primitive. */
static const mr_svo *prim_octree(const mr_geom *g, unsigned prim, mr_svo_subtree *buf,
                                 const mr_svo_subtree **st)
{
    *st = NULL;
    if (prim >= g->prim_count)
        return NULL;
    const octree_prim *p = &g->prims[prim];
    if (!(p->flags & PRIM_WHOLE)) {
        *buf = (mr_svo_subtree){p->node, p->level, {p->xyz[0], p->xyz[1], p->xyz[2]}};
        *st = buf;
    }
    return g->method == MR_SVO_RIGID ? g->svo : &g->octree[p->instance];
}

/* How many levels below a piece of octree o at `level` its box is fitted
 * (RIGID_BOX_LEVELS or FRAME_BOX_LEVELS, not past the leaves). */
static unsigned fit_levels(const mr_geom *g, const mr_svo *o, unsigned level)
{
    const unsigned below = g->method == MR_SVO_RIGID ? RIGID_BOX_LEVELS : FRAME_BOX_LEVELS;
    return level + below < o->depth ? below : o->depth > level ? o->depth - level : 0;
}

/* p's box as prim_box reads it (fit), or PRIM_EMPTY in its flags when it
 * has none: a whole octree's is its leaves' box; a piece's, its occupied
 * cells fit_levels down (mr_svo_subtree_cells) within its cell. */
static void prim_fit(const mr_geom *g, octree_prim *p)
{
    const mr_svo_subtree *st;
    mr_svo_subtree buf;
    const mr_svo *o = prim_octree(g, (unsigned)(p - g->prims), &buf, &st);
    p->flags &= (uint8_t)~PRIM_EMPTY;
    float flo[3], fhi[3];
    uint32_t lo[3], hi[3];
    if (!st) {
        if (!mr_svo_bounds(o, flo, fhi))
            p->flags |= PRIM_EMPTY;
        return;
    }
    const unsigned b = fit_levels(g, o, st->level);
    if (!mr_svo_subtree_cells(o, st, b, lo, hi)) {
        p->flags |= PRIM_EMPTY;
        return;
    }
    /* in cells b levels below the piece's, from its first */
    const unsigned shift = o->depth - st->level - b;
    for (int a = 0; a < 3; a++) {
        const uint32_t first = st->xyz[a] << b;
        const uint32_t l = (lo[a] >> shift) - first, h = ((hi[a] - 1u) >> shift) + 1u - first;
        if (lo[a] >= hi[a] || l >= h || h > (1u << b)) { /* no leaf, or malformed */
            p->flags |= PRIM_EMPTY;
            return;
        }
        p->fit[a] = (uint8_t)(l | h << 4);
    }
}

/* An octree's or subtree's box, grown by 2^-24 of the octree's size on
 * every side (at least one float step). The walk hits closed leaf boxes,
 * so a ray lying in a face of the box (in the plane between two
 * subtrees, parallel to it) can hit leaves on it; Embree tests such a ray
 * against the box's slab with a huge finite reciprocal for the zero
 * direction (rcp_safe: the ray then crosses the slab in a t interval of
 * width/1e18 around where it starts), so an exact face held the ray for
 * one neighbour and not the other, whichever the rule below prefers.
 * Strictly inside both by this much, the ray enters each at any t below
 * 2^-24 * 1e18 sizes, and the order rule decides (test_svo_instances
 * check_pieces_whole_walk). False for an empty primitive. */
static bool prim_box(const mr_geom *g, unsigned prim, float lo[3], float hi[3])
{
    if (prim >= g->prim_count || (g->prims[prim].flags & PRIM_EMPTY))
        return false;
    const octree_prim *p = &g->prims[prim];
    const mr_svo *o = g->method == MR_SVO_RIGID ? g->svo : &g->octree[p->instance];
    if (p->flags & PRIM_WHOLE) {
        const double pad = (double)o->size * 0x1p-24;
        mr_svo_bounds(o, lo, hi);
        for (int a = 0; a < 3; a++) {
            lo[a] = mr_float_down((double)lo[a] - pad);
            hi[a] = mr_float_up((double)hi[a] + pad);
        }
        return true;
    }
    /* In cells of the fitted level, size * 2^-(level + b) (2^-n made from
     * its bit pattern, not divided): the corners are exact in double. Moved
     * out by step, at least twice the largest float step in the cube (far
     * bounds every coordinate, a float step is at most 2^-23 of it), they
     * round to nearest still at least far 2^-24 >= pad outside: no
     * mr_float_down on the path of every ray packet (stored float boxes
     * took 52 bytes a piece; this is as fast, 0.99-1.03 of their trace
     * time). */
    const unsigned b = fit_levels(g, o, p->level);
    const uint64_t scale_bits = (uint64_t)(1023u - p->level - b) << 52;
    double cell;
    memcpy(&cell, &scale_bits, sizeof cell);
    cell *= (double)o->size;
    const double c[3] = {o->origin.x, o->origin.y, o->origin.z};
    const double far = fmax(fmax(fabs(c[0]), fabs(c[1])), fabs(c[2])) + 2.0 * (double)o->size;
    const double step = far * 0x1p-23;
    for (int a = 0; a < 3; a++) {
        const uint32_t first = (uint32_t)p->xyz[a] << b;
        /* (past the float range: the largest float, as mr_float_down gives) */
        lo[a] = fmaxf((float)(c[a] + (double)(first + (p->fit[a] & 15u)) * cell - step), -FLT_MAX);
        hi[a] = fminf((float)(c[a] + (double)(first + (p->fit[a] >> 4)) * cell + step), FLT_MAX);
    }
    return true;
}

static void octree_bounds(const struct RTCBoundsFunctionArguments *args)
{
    const mr_geom *g = args->geometryUserPtr;
    float lo[3], hi[3];
    if (!prim_box(g, args->primID, lo, hi)) {
        /* Empty: an inverted box, which Embree leaves out of its BVH. */
        for (int a = 0; a < 3; a++)
            lo[a] = 1.0f, hi[a] = -1.0f;
    }
    set_bounds(args->bounds_o, lo, hi);
}

/* The lanes of an N-packet whose ray can meet primitive prim's box
 * (mr_rays_in_box): Embree hands a primitive the rays of a leaf of its
 * tree, which holds several. */
static uint32_t lanes_to_trace(const mr_geom *g, unsigned prim, void *ray, unsigned N,
                               const int *valid)
{
    float lo[3], hi[3];
    return prim_box(g, prim, lo, hi) ? mr_rays_in_box(ray, N, valid, lo, hi) : 0;
}

static void box_bounds(const struct RTCBoundsFunctionArguments *args)
{
    const mr_geom *g = args->geometryUserPtr;
    const float *b = g->box + (size_t)args->primID * 6;
    set_bounds(args->bounds_o, b, b + 3);
}

/* The instance a hit on primitive prim (as the renderer passes it: rigid,
 * the instance; resize and emit, the Embree primitive) belongs to, or
 * SIZE_MAX. */
static size_t hit_instance(const mr_geom *g, unsigned prim)
{
    if (g->method == MR_SVO_RIGID)
        return prim < g->instance_count ? prim : SIZE_MAX;
    return prim < g->prim_count ? g->prims[prim].instance : SIZE_MAX;
}

static const mr_svo *hit_octree(const mr_geom *g, size_t instance)
{
    return g->method == MR_SVO_RIGID ? g->svo : &g->octree[instance];
}

/* The leaf and level an octree hit reports in u and v (octree_intersect);
 * false for what no octree hit gives. */
static bool hit_leaf(float u, float v, uint32_t *leaf, unsigned *level)
{
    if (!(u >= 0 && u < 0x200000 && v >= 0 && v < 0x10000))
        return false;
    uint32_t hi = (uint32_t)u;
    *leaf = (hi & 0xffffu) << 16 | (uint32_t)v;
    *level = hi >> 16;
    return true;
}

/* The rays of a packet's lanes to trace, gathered for
 * mr_svo_intersect_rays: the octree walks of a packet's rays take turns,
 * so one ray's cache misses overlap the others' work. */
typedef struct packet_rays {
    unsigned n;
    unsigned lane[MR_RAY_CACHE_LANES];
    mr_vec3 org[MR_RAY_CACHE_LANES], dir[MR_RAY_CACHE_LANES];
    float tnear[MR_RAY_CACHE_LANES], tfar[MR_RAY_CACHE_LANES];
} packet_rays;

static void gather_rays(packet_rays *p, float *ray, unsigned N, uint32_t lanes)
{
    p->n = 0;
    for (unsigned i = 0; i < N && i < MR_RAY_CACHE_LANES; i++) {
        if (!(lanes >> i & 1u))
            continue;
        const unsigned k = p->n++;
        p->lane[k] = i;
        p->org[k] = mr_ray_v3(ray, N, MR_RAY_ORG, i);
        p->dir[k] = mr_ray_v3(ray, N, MR_RAY_DIR, i);
        p->tnear[k] = *mr_ray_f(ray, N, MR_RAY_TNEAR, i);
        p->tfar[k] = *mr_ray_f(ray, N, MR_RAY_TFAR, i);
    }
}

/* Which of a rigid object's instances Embree instance inst is, or
 * SIZE_MAX (another method, or no instance of this object). */
static size_t rigid_instance(const mr_geom *g, unsigned inst)
{
    if (g->method != MR_SVO_RIGID || inst == RTC_INVALID_GEOMETRY_ID || inst < g->first_id ||
        inst - g->first_id >= g->instance_count)
        return SIZE_MAX;
    return inst - g->first_id;
}

/* The level of detail piece prim of Embree instance inst is cast with
 * (rigid with a tolerance; else NULL): the instance's, its cut nodes
 * clipped to the piece's box (mr_svo_lod.clip). A cut node's cell reaches
 * out of that box where the piece's leaves fill only part of it (a sheet
 * of surface in a cube). Unclipped, a hit there was found only for the
 * rays Embree called the piece for, and for a ray grazing the box that
 * depended on the rays traced with it (examples/lod-svo.json: one pixel in
 * three of seven frames changed from 8 x 2 to 4 x 4 packets). Within the
 * box, Embree calls the piece for every ray that can hit it, in any order
 * (test_svo_instances check_lod_pieces_any_order). */
static const mr_svo_lod *piece_lod(const mr_geom *g, unsigned prim, unsigned inst, mr_svo_lod *buf)
{
    const size_t k = rigid_instance(g, inst);
    if (!g->lod || k == SIZE_MAX || prim >= g->prim_count)
        return NULL;
    *buf = g->lod[k];
    buf->clip = true;
    const octree_prim *p = &g->prims[prim];
    if (p->flags & PRIM_WHOLE) {
        buf->clip_level = g->svo->depth;
        mr_svo_bounds_cells(g->svo, buf->clip_lo, buf->clip_hi);
        return buf;
    }
    const unsigned b = fit_levels(g, g->svo, p->level);
    buf->clip_level = p->level + b;
    for (int a = 0; a < 3; a++) {
        const uint32_t first = (uint32_t)p->xyz[a] << b;
        buf->clip_lo[a] = first + (p->fit[a] & 15u);
        buf->clip_hi[a] = first + (p->fit[a] >> 4);
    }
    return buf;
}

static void octree_intersect(const struct RTCIntersectFunctionNArguments *args)
{
    const mr_geom *g = args->geometryUserPtr;
    const mr_svo_subtree *st;
    mr_svo_subtree buf;
    const mr_svo *o = prim_octree(g, args->primID, &buf, &st);
    if (!o)
        return;
    unsigned N = args->N;
    float *ray = (float *)args->rayhit;
    float *hit = ray + MR_RAY_FIELDS * N;
    unsigned inst = args->context->instID[0];
    const uint32_t lanes = lanes_to_trace(g, args->primID, ray, N, args->valid);
    packet_rays p;
    gather_rays(&p, ray, N, lanes);
    mr_svo_hit hits[MR_RAY_CACHE_LANES];
    mr_svo_lod lod;
    const uint32_t hit_mask = mr_svo_intersect_rays(o, st, p.n, p.org, p.dir, p.tnear, p.tfar,
                                                    piece_lod(g, args->primID, inst, &lod), hits);
    const size_t rk = rigid_instance(g, inst); /* its world normal matrix */
    for (unsigned k = 0; k < p.n; k++) {
        if (!(hit_mask >> k & 1u))
            continue;
        const unsigned i = p.lane[k];
        const mr_vec3 dir = p.dir[k];
        const mr_svo_hit h = hits[k];
        if (st) {
            /* a hit at the t another subtree of this instance's octree
             * holds: the one the whole walk meets first, whatever order
             * Embree visits them in */
            const mr_svo_subtree *held = NULL;
            mr_svo_subtree held_buf;
            if (h.t == p.tfar[k] && *mr_ray_u(hit, N, MR_HIT_GEOM, i) == args->geomID &&
                *mr_ray_u(hit, N, MR_HIT_INST, i) == inst &&
                prim_octree(g, *mr_ray_u(hit, N, MR_HIT_PRIM, i), &held_buf, &held) == o && held &&
                mr_svo_subtree_order(held, dir) < mr_svo_subtree_order(st, dir))
                continue;
        }
        mr_vec3 ng = h.axis >= 0 ? h.ng : mr_v3_scale(dir, -1.0f);
        if (rk != SIZE_MAX)
            ng = mr_mat4_dir(&g->world_normal[rk], ng); /* world space */
        /* the shading reads the leaf's normal (svo_normal): its line
         * comes in while Embree goes on with the packet (it was a cache
         * miss at every hit, a tenth of a rigid frame) */
        if (h.leaf < o->leaf_count)
            __builtin_prefetch(&o->leaves[h.leaf]);
        *mr_ray_f(ray, N, MR_RAY_TFAR, i) = h.t;
        /* u: the leaf's high bits and level, v: its low bits (< 2^21: exact) */
        mr_ray_write_hit(args, i, ng, (float)((h.leaf >> 16) | h.level << 16),
                         (float)(h.leaf & 0xffffu));
    }
}

static void octree_occluded(const struct RTCOccludedFunctionNArguments *args)
{
    const mr_geom *g = args->geometryUserPtr;
    const mr_svo_subtree *st;
    mr_svo_subtree buf;
    const mr_svo *o = prim_octree(g, args->primID, &buf, &st);
    if (!o)
        return;
    unsigned N = args->N;
    float *ray = (float *)args->ray;
    const uint32_t lanes = lanes_to_trace(g, args->primID, ray, N, args->valid);
    packet_rays p;
    gather_rays(&p, ray, N, lanes);
    mr_svo_lod lod;
    const uint32_t hit_mask = mr_svo_intersect_rays(
        o, st, p.n, p.org, p.dir, p.tnear, p.tfar, piece_lod(g, args->primID, args->context->instID[0], &lod), NULL);
    for (unsigned k = 0; k < p.n; k++)
        if (hit_mask >> k & 1u)
            *mr_ray_f(ray, N, MR_RAY_TFAR, p.lane[k]) = -INFINITY;
}

/* Closed slab test of one deformed box: entry t (clipped to tnear) and the
 * axis of the entry face, or false. */
static bool box_hit(const float *b, mr_vec3 org, mr_vec3 dir, float tnear, float tfar, float *t,
                    int *axis)
{
    const float o[3] = {org.x, org.y, org.z}, d[3] = {dir.x, dir.y, dir.z};
    float t0 = tnear, t1 = tfar;
    int ax = -1;
    for (int a = 0; a < 3; a++) {
        if (d[a] == 0) {
            if (o[a] < b[a] || o[a] > b[a + 3])
                return false;
            continue;
        }
        float inv = 1.0f / d[a];
        float n = (b[a] - o[a]) * inv, f = (b[a + 3] - o[a]) * inv;
        if (n > f) {
            float s = n;
            n = f;
            f = s;
        }
        if (n > t0) {
            t0 = n;
            ax = a;
        }
        if (f < t1)
            t1 = f;
        if (!(t0 <= t1))
            return false;
    }
    *t = t0;
    *axis = ax;
    return true;
}

static void boxes_intersect(const struct RTCIntersectFunctionNArguments *args)
{
    const mr_geom *g = args->geometryUserPtr;
    const float *b = g->box + (size_t)args->primID * 6;
    unsigned N = args->N;
    float *ray = (float *)args->rayhit;
    bool any = false;
    for (unsigned i = 0; i < N; i++) {
        if (!args->valid[i])
            continue;
        const mr_vec3 org = mr_ray_v3(ray, N, MR_RAY_ORG, i), dir = mr_ray_v3(ray, N, MR_RAY_DIR, i);
        float t;
        int axis;
        if (!box_hit(b, org, dir, *mr_ray_f(ray, N, MR_RAY_TNEAR, i),
                     *mr_ray_f(ray, N, MR_RAY_TFAR, i), &t, &axis))
            continue;
        float n[3] = {0, 0, 0};
        if (axis >= 0)
            n[axis] = (axis == 0 ? dir.x : axis == 1 ? dir.y : dir.z) > 0 ? -1.0f : 1.0f;
        else {
            n[0] = -dir.x;
            n[1] = -dir.y;
            n[2] = -dir.z;
        }
        *mr_ray_f(ray, N, MR_RAY_TFAR, i) = t;
        mr_ray_write_hit(args, i, mr_v3(n[0], n[1], n[2]), 0, 0);
        any = true;
    }
    if (any)
        __builtin_prefetch(&g->box_leaf[args->primID]); /* as octree_intersect does */
}

static void boxes_occluded(const struct RTCOccludedFunctionNArguments *args)
{
    const mr_geom *g = args->geometryUserPtr;
    const float *b = g->box + (size_t)args->primID * 6;
    unsigned N = args->N;
    float *ray = (float *)args->ray;
    for (unsigned i = 0; i < N; i++) {
        if (!args->valid[i])
            continue;
        const mr_vec3 org = mr_ray_v3(ray, N, MR_RAY_ORG, i), dir = mr_ray_v3(ray, N, MR_RAY_DIR, i);
        float t;
        int axis;
        if (box_hit(b, org, dir, *mr_ray_f(ray, N, MR_RAY_TNEAR, i),
                    *mr_ray_f(ray, N, MR_RAY_TFAR, i), &t, &axis))
            *mr_ray_f(ray, N, MR_RAY_TFAR, i) = -INFINITY;
    }
}

/* The object's user geometry: octrees (rigid, resize, emit) or boxes. */
static int attach_user(mr_geom *g, RTCDevice device, RTCScene scene, unsigned geom_id, unsigned count,
                       enum RTCBuildQuality quality, RTCGeometry *out, mr_error *err)
{
    const bool boxes = g->method == MR_SVO_DIRECT;
    return mr_geom_attach_user(device, scene, geom_id, quality, count, g, boxes ? box_bounds : octree_bounds,
                               boxes ? boxes_intersect : octree_intersect,
                               boxes ? boxes_occluded : octree_occluded, "svo", out, err);
}

static int svo_attach(mr_geom *g, RTCDevice device, RTCScene scene, unsigned geom_id,
                      enum RTCBuildQuality quality, mr_error *err)
{
    g->first_id = geom_id;
    if (g->method != MR_SVO_RIGID) {
        /* Primitive counts change every frame: always a fresh (LOW) build. */
        (void)quality;
        return attach_user(g, device, scene, geom_id, 0, RTC_BUILD_QUALITY_LOW, &g->user, err);
    }
    g->shared_scene = rtcNewScene(device);
    if (!g->shared_scene)
        return mr_error_set(err, MR_ERR_EMBREE, "svo: Embree could not create the octree scene");
    RTCGeometry oct;
    int rc = attach_user(g, device, g->shared_scene, RTC_INVALID_GEOMETRY_ID,
                         g->prim_count, RTC_BUILD_QUALITY_HIGH, &oct, err);
    if (rc < 0)
        return rc;
    rtcReleaseGeometry(oct); /* the scene holds it */
    /* The top scene's ROBUST does not reach into instanced scenes. */
    rtcSetSceneFlags(g->shared_scene, RTC_SCENE_FLAG_ROBUST);
    rtcCommitScene(g->shared_scene);
    g->instances = calloc(g->instance_count, sizeof *g->instances);
    if (!g->instances)
        return mr_error_set(err, MR_ERR_NOMEM, "svo: out of memory for %zu instances", g->instance_count);
    for (size_t k = 0; k < g->instance_count; k++) {
        RTCGeometry in = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_INSTANCE);
        if (!in)
            return mr_error_set(err, MR_ERR_EMBREE, "svo: Embree could not create instance %zu", k);
        rtcSetGeometryInstancedScene(in, g->shared_scene);
        rtcSetGeometryTimeStepCount(in, 1);
        rtcAttachGeometryByID(scene, in, geom_id + (unsigned)k);
        g->instances[k] = in;
    }
    return MR_OK;
}

static bool svo_commit(mr_geom *g)
{
    if (g->method == MR_SVO_RIGID) {
        for (size_t k = 0; k < g->instance_count; k++) {
            RTCGeometry in = g->instances[k];
            /* A singular transform has no inverse to move rays by: such an
             * instance has no volume and is left out (Embree would divide
             * by zero). */
            if (!g->invertible[k]) {
                rtcDisableGeometry(in);
                continue;
            }
            rtcEnableGeometry(in);
            float xfm[12]; /* RTC_FORMAT_FLOAT3X4_ROW_MAJOR */
            memcpy(xfm, g->world[k].m, sizeof xfm);
            rtcSetGeometryTransform(in, 0, RTC_FORMAT_FLOAT3X4_ROW_MAJOR, xfm);
            rtcCommitGeometry(in);
        }
        return true;
    }
    unsigned count = g->method == MR_SVO_DIRECT ? (unsigned)g->box_count : g->prim_count;
    rtcSetGeometryUserPrimitiveCount(g->user, count);
    rtcCommitGeometry(g->user);
    return true;
}

static mr_vec3 svo_normal(const mr_geom *g, unsigned prim, float u, float v, mr_vec3 ng)
{
    if (g->method == MR_SVO_DIRECT) {
        if (prim >= g->box_count)
            return mr_v3(0, 0, 0);
        return mr_svo_normal_decode(g->box_leaf[prim].normal);
    }
    uint32_t leaf;
    unsigned level;
    const size_t k = hit_instance(g, prim);
    if (k == SIZE_MAX || !hit_leaf(u, v, &leaf, &level))
        return mr_v3(0, 0, 0);
    const mr_svo *o = hit_octree(g, k);
    mr_vec3 n;
    if (leaf < o->leaf_count)
        n = mr_svo_normal_decode(o->leaves[leaf].normal);
    else if (g->lod && leaf - o->leaf_count < g->extremes.node_count)
        n = mr_svo_normal_decode(g->extremes.normal[leaf - o->leaf_count]); /* a node's (rigid_lod) */
    else
        return mr_v3(0, 0, 0);
    if (g->method == MR_SVO_RIGID)
        n = mr_mat4_dir(&g->world_normal[k], n);
    return n;
}

const mr_svo *mr_svo_kind_octree(const mr_geom *g, size_t k, uint32_t *pieces)
{
    *pieces = 0;
    if (!g || g->method == MR_SVO_DIRECT || k >= g->instance_count)
        return NULL;
    for (uint32_t i = 0; i < g->prim_count; i++) /* rigid: all are the shared octree's */
        *pieces += g->method == MR_SVO_RIGID || g->prims[i].instance == k;
    return g->method == MR_SVO_RIGID ? g->svo : &g->octree[k];
}

bool mr_svo_kind_cast(const mr_geom *g, size_t k, mr_vec3 org, mr_vec3 dir, mr_svo_hit *hit)
{
    if (!g || g->method != MR_SVO_RIGID || k >= g->instance_count)
        return false;
    bool found = false;
    const mr_svo_subtree *held = NULL;
    mr_svo_subtree held_buf;
    for (unsigned prim = 0; prim < g->prim_count; prim++) {
        const mr_svo_subtree *st;
        mr_svo_subtree buf;
        const mr_svo *o = prim_octree(g, prim, &buf, &st);
        mr_svo_lod buf_lod;
        const mr_svo_lod *lod = piece_lod(g, prim, g->first_id + (unsigned)k, &buf_lod);
        const float tmin = 0.0f, tmax = found ? hit->t : INFINITY;
        mr_svo_hit h;
        if (!(mr_svo_intersect_rays(o, st, 1, &org, &dir, &tmin, &tmax, lod, &h) & 1u))
            continue;
        /* a tie: the piece the whole walk meets first, as octree_intersect */
        if (found && h.t == hit->t && st && held && mr_svo_subtree_order(held, dir) < mr_svo_subtree_order(st, dir))
            continue;
        *hit = h;
        found = true;
        if (st) {
            held_buf = *st;
            held = &held_buf;
        }
    }
    return found;
}

/* The id pass names the instance hit (rigid: the renderer passes it as
 * prim already), or the voxel box (direct). */
static uint32_t svo_id_primitive(const mr_geom *g, unsigned prim)
{
    if (g->method == MR_SVO_RESIZE || g->method == MR_SVO_EMIT) {
        const size_t k = hit_instance(g, prim);
        return k == SIZE_MAX ? prim : (uint32_t)k;
    }
    return prim;
}

/* ---- reference, sizes, lifetime -------------------------------------- */

/* References (kind.h): no "tessellated" (the voxels are traced as they are,
 * boxes and octrees, with no triangle form in the renderer); "ground_truth"
 * is what svo_tessellate gives, drawn by the triangle kind: the asset's
 * triangles skinned with each instance's pose (rigid instances in the rest
 * pose) and placed by its transform after the object's, one object per
 * instance. An object with an extracted skeleton has none: its poses name
 * bones the asset lacks. */
static int svo_reference(const mr_object_desc *obj, mr_reference_type type,
                         mr_reference_objects *out, mr_error *err)
{
    const mr_svo_params *s = obj->params;
    if (type != MR_REFERENCE_GROUND_TRUTH || s->skeleton)
        return MR_OK;
    size_t n = s->instance_count ? s->instance_count : 1;
    for (size_t k = 0; k < n; k++) {
        mr_object_desc d = *obj;
        d.kind = mr_kind_triangles();
        d.params = NULL;
        if (s->instance_count) {
            d.transform = mr_mat4_mul(&obj->transform, &s->instances[k].transform);
            if (s->instances[k].has_pose) {
                d.pose_count = 1;
                d.poses = &s->instances[k].pose;
            }
        }
        if (s->method == MR_SVO_RIGID) {
            d.pose_count = 0;
            d.poses = NULL;
        }
        int rc = mr_reference_objects_add(out, &d, err);
        if (rc < 0)
            return rc;
    }
    return MR_OK;
}

static int svo_tessellate(const mr_geom *g, mr_trimesh *out, mr_error *err)
{
    *out = (mr_trimesh){0};
    const mr_asset *a = g->asset;
    uint64_t nv = 0, nt = 0;
    for (size_t m = 0; m < a->mesh_count; m++) {
        nv += a->meshes[m].vertex_count;
        nt += a->meshes[m].triangle_count;
    }
    nv *= g->instance_count;
    nt *= g->instance_count;
    if (nv > UINT32_MAX / 3 || nt > UINT32_MAX / 3)
        return mr_error_set(err, MR_ERR_LIMIT, "svo: the reference of %zu instances is too large",
                            g->instance_count);
    out->positions = malloc((size_t)nv * 3 * sizeof *out->positions + 4);
    out->indices = malloc((size_t)nt * 3 * sizeof *out->indices);
    mr_pose *pose = NULL;
    int rc = mr_pose_new(a, &pose, err);
    if (rc < 0 || !out->positions || !out->indices) {
        mr_pose_free(pose);
        mr_trimesh_free(out);
        return rc < 0 ? rc : mr_error_set(err, MR_ERR_NOMEM, "svo: out of memory for the reference");
    }
    uint32_t v0 = 0, t0 = 0;
    for (size_t k = 0; k < g->instance_count; k++) {
        /* Rigid instances stay in the rest pose; the others take the pose
         * of the last update. */
        const mr_pose_desc *pd = g->method == MR_SVO_RIGID ? NULL : instance_pose(g, k, g->last_frame);
        if ((rc = mr_pose_eval(pose, a, pd, g->last_time, err)) < 0)
            break;
        for (size_t m = 0; m < a->mesh_count; m++) {
            const mr_mesh *mesh = &a->meshes[m];
            mr_skin_mesh(a, m, pose, &g->world[k], out->positions + (size_t)v0 * 3, NULL, 1);
            for (size_t i = 0; i < (size_t)mesh->triangle_count * 3; i++)
                out->indices[(size_t)t0 * 3 + i] = v0 + mesh->indices[i];
            v0 += mesh->vertex_count;
            t0 += mesh->triangle_count;
        }
    }
    mr_pose_free(pose);
    if (rc < 0) {
        mr_trimesh_free(out);
        return rc;
    }
    out->vertex_count = v0;
    out->triangle_count = t0;
    return MR_OK;
}

/* The shared octree with the selection's side data (svo_shared_bytes). */
static size_t shared_memory(const mr_geom *g)
{
    return mr_svo_memory(g->svo) + (size_t)g->extremes.node_count * 6;
}

/* What the object's geometry holds: the shared part, the rigid octree's
 * subtrees, and per instance what tracing reads (rebuilt octrees) or
 * gathers from (direct: selections and the gathered boxes). */
static size_t svo_memory(const mr_geom *g)
{
    size_t bytes = shared_memory(g) + g->prim_capacity * sizeof *g->prims;
    bytes += g->box_capacity * (6 * sizeof(float) + sizeof(mr_svo_leaf));
    for (size_t k = 0; k < g->instance_count && (g->sel || g->octree); k++)
        bytes += instance_bytes(g, k);
    return bytes;
}

/* The workers' scratch, kept between frames so a frame allocates nothing:
 * selection and resampling arrays (reported as svo_scratch_bytes, not as
 * geometry: nothing traced reads them). */
static size_t scratch_memory(const mr_geom *g)
{
    size_t bytes = 0;
    for (unsigned w = 0; g->scratch && w < g->workers; w++)
        bytes += mr_svo_workspace_memory(g->scratch[w].ws) + selection_bytes(&g->scratch[w].sel);
    return bytes;
}

/* Voxels traced: the shared octree's leaves once per instance (rigid), the
 * deformed boxes (direct) or the rebuilt octrees' leaves. */
static uint64_t svo_primitives(const mr_geom *g)
{
    if (g->method == MR_SVO_RIGID)
        return (uint64_t)g->svo->leaf_count * g->instance_count;
    if (g->method == MR_SVO_DIRECT)
        return g->box_count;
    return g->cells;
}

/* Where an svo object's time goes (paper 004's pipeline, per frame), and
 * what its creation built. The phase seconds are summed over instances:
 * with many instances they run in parallel on the job's threads, so their
 * sum can pass the frame's pose_s (the wall time of all updates). */
enum { S_VOXELS, S_BUILD, S_SKELETON, S_BONES, S_THINNESS, S_POSE, S_SELECT, S_DEFORMED,
       S_SELECTED, S_EMIT, S_REBUILD, S_CELLS, S_OCTREE_BYTES, S_SHARED_BYTES, S_SCRATCH_BYTES,
       S_ERROR_PX, S_COUNT };

static const mr_kind_stat SVO_STATS[S_COUNT] = {
    [S_VOXELS] = {"svo_voxels", "count", "leaves of the shared octree (bind space)", MR_STAT_SUM},
    [S_BUILD] = {"svo_build_s", "s",
                 "building the shared octree at creation: voxelisation or its load from the "
                 "derived-data cache, and the selection's side data", MR_STAT_ONCE},
    [S_SKELETON] = {"svo_skeleton_s", "s",
                    "skeleton extraction and skinning to it at creation, with \"skeleton\"",
                    MR_STAT_ONCE},
    [S_BONES] = {"svo_bones", "count", "bones of the extracted skeleton (0 without one)",
                 MR_STAT_SUM},
    [S_THINNESS] = {"svo_thinness_pct", "%",
                    "thinness error of the extracted skeleton (thesis eq. 5.7.1)", MR_STAT_MAX},
    [S_POSE] = {"svo_pose_s", "s", "instance poses and their skin matrices, summed over instances",
                MR_STAT_SUM},
    [S_SELECT] = {"svo_select_s", "s",
                  "screen-space selection and deformation of voxels, summed over instances",
                  MR_STAT_SUM},
    [S_DEFORMED] = {"svo_deformed", "count", "voxels deformed while selecting (selected or not)",
                    MR_STAT_SUM},
    [S_SELECTED] = {"svo_selected", "count", "voxels selected: the deformed boxes", MR_STAT_SUM},
    [S_EMIT] = {"svo_emit_s", "s",
                "resampling (resize, emit): cells emitted for the deformed boxes, summed over "
                "instances", MR_STAT_SUM},
    [S_REBUILD] = {"svo_rebuild_s", "s",
                   "resampling (resize, emit): radix sort, compaction and build of the "
                   "per-instance world octrees, summed over instances", MR_STAT_SUM},
    [S_CELLS] = {"svo_cells", "count", "cells emitted before compaction (resize, emit)",
                 MR_STAT_SUM},
    [S_OCTREE_BYTES] = {"svo_octree_bytes", "bytes",
                        "the per-instance world octrees rebuilt this frame (resize, emit)",
                        MR_STAT_SUM},
    [S_SHARED_BYTES] = {"svo_shared_bytes", "bytes",
                        "the shared bind-space octree with the selection's side data: held once "
                        "per object, whatever its instances (in bytes.geometry)", MR_STAT_SUM},
    [S_SCRATCH_BYTES] = {"svo_scratch_bytes", "bytes",
                         "the workers' selection and resampling arrays, kept between frames "
                         "(not in bytes.geometry: nothing traced reads them)", MR_STAT_SUM},
    [S_ERROR_PX] = {"svo_lod_error_px", "px",
                    "with \"tolerance_px\": the selection's predicted error, the most pixels a "
                    "selected voxel's diagonal spans (methods direct, resize, emit); the tolerance "
                    "the cast keeps (rigid); 0 without", MR_STAT_MAX},
};

static void svo_frame_stats(const mr_geom *g, double *v)
{
    v[S_VOXELS] = g->svo->leaf_count;
    v[S_BUILD] = g->build_s;
    v[S_SKELETON] = g->skeleton_s;
    v[S_BONES] = g->bones;
    v[S_THINNESS] = g->thinness_pct;
    v[S_POSE] = g->pose_s;
    v[S_SELECT] = g->select_s;
    v[S_DEFORMED] = (double)g->visited;
    v[S_SELECTED] = (double)g->selected;
    v[S_EMIT] = g->emit_s;
    v[S_REBUILD] = g->rebuild_s;
    v[S_CELLS] = (double)g->emitted;
    v[S_OCTREE_BYTES] = (double)g->octree_bytes;
    v[S_SHARED_BYTES] = (double)shared_memory(g);
    v[S_SCRATCH_BYTES] = (double)scratch_memory(g);
    v[S_ERROR_PX] = g->predicted_px;
}

/* Level: the deepest octree level the frame's selection reached (a
 * selection mixes levels: it is where the octree's depth is felt). */
static bool svo_lod(const mr_geom *g, uint32_t *level, double *error_px)
{
    *level = g->deepest;
    *error_px = g->predicted_px;
    return g->tolerance_px > 0;
}

static uint32_t svo_geometry_ids(const mr_geom *g)
{
    return g->method == MR_SVO_RIGID ? (uint32_t)g->instance_count : 1u;
}

/* The edge, in world units, of the voxel hit (kind.h surface_step): a
 * deformed box's largest side (direct); else the hit leaf's edge in its
 * octree, times the instance's largest scale for the shared bind-space
 * octree (rigid). Selected for the screen, voxels of a distant instance are
 * coarser than the finest level, and resampled cells come in every size a
 * deformed box asks for; one figure for the object (the finest voxel) left
 * the shadow rays of coarse voxels starting inside the staircase. */
static float svo_surface_step(const mr_geom *g, unsigned prim, float u, float v)
{
    if (g->method == MR_SVO_DIRECT) {
        if (prim >= g->box_count)
            return 0.0f;
        const float *b = g->box + (size_t)prim * 6;
        return fmaxf(b[3] - b[0], fmaxf(b[4] - b[1], b[5] - b[2]));
    }
    uint32_t leaf;
    unsigned level;
    const size_t k = hit_instance(g, prim);
    if (k == SIZE_MAX || !hit_leaf(u, v, &leaf, &level))
        return 0.0f;
    const mr_svo *o = hit_octree(g, k);
    double edge = ldexp((double)o->size, -(int)level);
    if (g->method == MR_SVO_RIGID)
        edge *= largest_scale(&g->world[k]);
    return (float)edge;
}

static void svo_free(mr_geom *g)
{
    if (!g)
        return;
    if (g->instances)
        for (size_t k = 0; k < g->instance_count; k++)
            if (g->instances[k])
                rtcReleaseGeometry(g->instances[k]);
    free(g->instances);
    if (g->user)
        rtcReleaseGeometry(g->user);
    if (g->shared_scene)
        rtcReleaseScene(g->shared_scene);
    if (g->sel)
        for (size_t k = 0; k < g->instance_count; k++)
            mr_svo_selection_free(&g->sel[k]);
    free(g->sel);
    if (g->octree)
        for (size_t k = 0; k < g->instance_count; k++)
            mr_svo_free(&g->octree[k]);
    free(g->octree);
    if (g->scratch)
        for (unsigned w = 0; w < g->workers; w++) {
            mr_pose_free(g->scratch[w].pose);
            mr_svo_skin_free(&g->scratch[w].skin);
            mr_svo_workspace_free(g->scratch[w].ws);
            mr_svo_selection_free(&g->scratch[w].sel);
        }
    free(g->scratch);
    free(g->box);
    free(g->box_leaf);
    free(g->prims);
    free(g->world);
    free(g->world_normal);
    free(g->invertible);
    free(g->lod);
    mr_svo_extremes_free(&g->extremes);
    mr_svo_voxelize_free(g->svo);
    if (g->rigged)
        mr_asset_free(g->rigged);
    free(g);
}

/* Every pose the object's instances use must name clips and joints of the
 * posing asset (the rigged copy's bones, with a skeleton). */
static int check_poses(const mr_geom *g, mr_error *err)
{
    const mr_object_desc *d = g->desc;
    for (size_t k = 0; k < d->pose_count; k++) {
        int rc = mr_pose_desc_check(g->asset, &d->poses[k], err);
        if (rc < 0)
            return d->pose_count == 1 ? mr_error_prefix(err, "pose: ")
                                      : mr_error_prefix(err, "pose/%zu: ", k);
    }
    for (size_t k = 0; k < g->p->instance_count; k++) {
        if (!g->p->instances[k].has_pose)
            continue;
        int rc = mr_pose_desc_check(g->asset, &g->p->instances[k].pose, err);
        if (rc < 0)
            return mr_error_prefix(err, "svo/instances/%zu/pose: ", k);
    }
    return MR_OK;
}

/* Chapter 5: bones contracted out of the voxels, and the asset and octree
 * skinned to them (skeleton.h); from here on the kind poses the copy. */
static int rig_skeleton(mr_geom *g, mr_error *err)
{
    mr_svo_skeleton_params sp = {.omega = g->p->omega};
    mr_svo_skeleton sk = {0};
    mr_svo *rigged_svo = NULL;
    double t0 = mr_now();
    int rc = mr_svo_skeletonize(g->svo, &sp, &sk, err);
    if (rc >= 0)
        rc = mr_svo_skeleton_rig(g->asset, g->svo, &sk, &sp, &g->rigged, &rigged_svo, err);
    g->skeleton_s = mr_now() - t0;
    g->bones = sk.bone_count;
    g->thinness_pct = sk.thinness_error_percent;
    mr_svo_skeleton_free(&sk);
    if (rc < 0)
        return mr_error_prefix(err, "svo/skeleton: ");
    mr_svo_voxelize_free(g->svo);
    g->svo = rigged_svo;
    g->asset = g->rigged;
    return MR_OK;
}

/* Memory the instances surely need (kind.h memory_floor): what every
 * instance holds whatever the asset and the view (its matrices, its
 * Embree instance or selection). What a non-rigid instance holds on top
 * depends on the view far more than on the parameters: one emit instance
 * of BCN_Epileptic at depth 8 held 0.26 MB filling a 64x64 frame and 20 MB
 * close up at 640x360, 0.4x to 32x the shared octree. So no
 * parameter-only figure is honest for it: the running total in
 * deform_instance enforces the budget as the frame is built instead. */
static size_t instance_floor(mr_svo_method method)
{
    return 3 * sizeof(mr_mat4) + sizeof(bool) +
           (method == MR_SVO_RIGID ? 512 /* an Embree instance */
                                   : sizeof(mr_svo_selection) + sizeof(mr_svo));
}

static size_t svo_memory_floor(const void *params)
{
    const mr_svo_params *p = params;
    size_t n = p->instance_count ? p->instance_count : 1;
    return n * instance_floor(p->method);
}

/* Checked before any per-instance allocation: the floor plus the shared
 * octree, now that it is built. */
static int check_estimate(const mr_geom *g, mr_error *err)
{
    if (!g->budget)
        return MR_OK;
    size_t shared = mr_svo_memory(g->svo);
    size_t each = instance_floor(g->method);
    size_t n = g->instance_count;
    size_t need = each > (SIZE_MAX - shared) / n ? SIZE_MAX : shared + n * each;
    if (need <= g->budget)
        return MR_OK;
    char total[MR_BYTES_TEXT], per[MR_BYTES_TEXT], cap[MR_BYTES_TEXT];
    mr_format_bytes(need, total, sizeof total);
    mr_format_bytes(each, per, sizeof per);
    mr_format_bytes(g->budget, cap, sizeof cap);
    return mr_error_set(err, MR_ERR_LIMIT,
                        "svo/instances: %zu instances of this %llu-voxel octree (depth %u, method "
                        "%s) need at least %s (%s each), over the job's memory budget of %s "
                        "(fewer instances, a smaller depth, or method rigid)",
                        n, (unsigned long long)g->svo->leaf_count, g->p->depth,
                        METHODS[g->method], total, per, cap);
}

static int svo_create(const mr_asset *asset, const mr_object_desc *desc,
                      const mr_kind_context *ctx, mr_geom **out, mr_error *err)
{
    *out = NULL;
    if (!desc->params)
        return mr_error_set(err, MR_ERR_INVALID, "an svo object needs its parameters");
    const mr_svo_params *p = desc->params;
    mr_geom *g = calloc(1, sizeof *g);
    if (!g)
        return mr_error_set(err, MR_ERR_NOMEM, "svo: out of memory");
    g->asset = asset;
    g->desc = desc;
    g->p = p;
    g->method = p->method;
    g->instance_count = p->instance_count ? p->instance_count : 1;
    g->tolerance_px = desc->tolerance_px > 0 ? desc->tolerance_px : 0;
    int rc;
    float *albedo = malloc((asset->mesh_count ? asset->mesh_count : 1) * 3 * sizeof *albedo);
    if (!albedo) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "svo: out of memory");
        goto fail;
    }
    for (size_t m = 0; m < asset->mesh_count; m++) {
        albedo[m * 3] = fminf(desc->color.x, 1.0f);
        albedo[m * 3 + 1] = fminf(desc->color.y, 1.0f);
        albedo[m * 3 + 2] = fminf(desc->color.z, 1.0f);
    }
    mr_svo_voxelize_params vp = {.depth = p->depth, .mode = p->voxelize,
                                 .albedo = albedo, .threads = 0};
    double t0 = mr_now();
    rc = mr_svo_voxelize_cached(asset, &vp, ctx ? ctx->cache_dir : NULL, &g->svo, NULL, err);
    g->build_s = mr_now() - t0;
    free(albedo);
    if (rc < 0)
        goto fail;
    if (p->skeleton && (rc = rig_skeleton(g, err)) < 0)
        goto fail;
    /* the leaves' box is what Embree bounds a rigid instance by (an octree
     * read from the cache comes without it): the cube around a standing
     * character is mostly air, and every ray into that air entered the
     * octree */
    if (!g->svo->has_occupied && (rc = mr_svo_fit_occupied(g->svo, err)) < 0)
        goto fail;
    if (g->method == MR_SVO_RIGID) { /* its pieces for good */
        mr_svo_subtree *st;
        uint32_t n;
        if ((rc = mr_svo_subtrees(g->svo, RIGID_SUBTREE_LEVEL, &st, &n, err)) < 0 ||
            (rc = prims_add(g, 0, st, n, err)) < 0)
            goto fail;
        fit_boxes(g, 1);
    }
    g->out_depth = p->depth + 2 < MR_SVO_MAX_DEPTH ? p->depth + 2 : MR_SVO_MAX_DEPTH;
    if ((rc = check_poses(g, err)) < 0)
        goto fail;
    if (g->method == MR_SVO_RIGID) {
        /* Rigid instances pose nothing, but the asset must be one the
         * other methods could skin (a rigid mesh's rest node invertible). */
        mr_svo_skin probe;
        rc = mr_svo_skin_init(&probe, g->asset, err);
        mr_svo_skin_free(&probe);
        if (rc < 0)
            goto fail;
    }
    g->budget = ctx ? ctx->memory_budget : 0;
    if ((rc = check_estimate(g, err)) < 0)
        goto fail;
    size_t n = g->instance_count;
    g->world = calloc(n, sizeof *g->world);
    g->world_normal = calloc(n, sizeof *g->world_normal);
    g->invertible = calloc(n, sizeof *g->invertible);
    if (!g->world || !g->world_normal || !g->invertible) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "svo: out of memory for %zu instances", n);
        goto fail;
    }
    if (g->method == MR_SVO_RIGID && g->tolerance_px > 0) {
        /* the cast's level of detail: its nodes' normals (the mean of
         * their leaves', as a selected node's) */
        double t1 = mr_now();
        if (!(g->lod = calloc(n, sizeof *g->lod))) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "svo: out of memory for %zu instances", n);
            goto fail;
        }
        if ((rc = mr_svo_extremes_build(g->svo, &g->extremes, err)) < 0)
            goto fail;
        g->build_s += mr_now() - t1;
    }
    if (g->method != MR_SVO_RIGID) {
        if (g->method == MR_SVO_DIRECT)
            g->sel = calloc(n, sizeof *g->sel);
        else
            g->octree = calloc(n, sizeof *g->octree);
        if (!g->sel && !g->octree) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "svo: out of memory for %zu instances", n);
            goto fail;
        }
        /* one worker now, so an asset the methods cannot skin fails here;
         * update adds the workers the job's thread count asks for */
        double t1 = mr_now();
        if ((rc = mr_svo_extremes_build(g->svo, &g->extremes, err)) < 0 ||
            (rc = ensure_workers(g, 1, err)) < 0)
            goto fail;
        g->build_s += mr_now() - t1;
    }
    *out = g;
    return MR_OK;
fail:
    svo_free(g);
    return rc;
}

static bool svo_animated(const void *params)
{
    /* Deformed voxels are selected for the screen and rebuilt every frame
     * (paper 004's pipeline), whatever moves. */
    return ((const mr_svo_params *)params)->method != MR_SVO_RIGID;
}

/* The "svo" block. */
static const char *const VOXELIZE[] = {"surface", "solid"};

enum { P_DEPTH, P_VOXELIZE, P_METHOD, P_DELTA, P_CULL, P_SKELETON, P_INSTANCES };

static int after_voxelize(void *values, const bool *given, mr_param_error *err)
{
    const mr_svo_params *d = values;
    if (d->voxelize == MR_SVO_VOXELIZE_SOLID && d->depth > MR_SVO_SOLID_MAX_DEPTH)
        return mr_param_fail(err, MR_ERR_LIMIT, given[P_DEPTH] ? "depth" : "voxelize",
                             "solid voxelisation goes to depth %u at most, asked for %u",
                             MR_SVO_SOLID_MAX_DEPTH, d->depth);
    return MR_OK;
}

static const mr_param SKELETON_PARAMS[] = {
    {.field = "omega", .type = MR_PARAM_NUMBER, .offset = offsetof(mr_svo_params, omega), .lo = 0x1p-20,
     .hi = 0.5, .flags = MR_PARAM_NO_DEFAULT, .def = 0,
     .expect = "a fraction of the voxel cube in [2^-20, 0.5]",
     .description = "feature size of the contraction, a fraction of the voxel cube (default "
                    "2^-min(depth,5))"},
};

static const mr_param_table SKELETON_TABLE = {
    .params = SKELETON_PARAMS,
    .count = 1,
    .size = sizeof(mr_svo_params),
    .expect = "true, false or an object of skeleton parameters",
};

static const mr_param INSTANCE_PARAMS[] = {
    {.field = "transform", .type = MR_PARAM_TRANSFORM, .offset = offsetof(mr_svo_instance, transform),
     .description = "instance to object space (then the object's transform)"},
    {.field = "pose", .type = MR_PARAM_POSE, .offset = offsetof(mr_svo_instance, pose),
     .present_offset = offsetof(mr_svo_instance, has_pose),
     .description = "this instance's pose (else the object's)"},
};

static const mr_param_table INSTANCE_TABLE = {
    .params = INSTANCE_PARAMS,
    .count = 2,
    .size = sizeof(mr_svo_instance),
    .expect = "an instance object",
    .plural = "instance objects",
};

static const mr_param SVO_PARAMS[] = {
    [P_DEPTH] = {.field = "depth", .type = MR_PARAM_INT, .offset = offsetof(mr_svo_params, depth),
                 .lo = 1, .hi = MR_SVO_JOB_MAX_DEPTH, .def = MR_SVO_DEFAULT_DEPTH,
                 .description = "2^depth voxels per axis around the asset."},
    [P_VOXELIZE] = {.field = "voxelize", .type = MR_PARAM_ENUM,
                    .offset = offsetof(mr_svo_params, voxelize), MR_PARAM_CHOICES(VOXELIZE),
                    .def = MR_SVO_VOXELIZE_SURFACE, .after = after_voxelize,
                    .description = "Surface cells only, or also the inside (depth <= 10)."},
    [P_METHOD] = {.field = "method", .type = MR_PARAM_ENUM, .offset = offsetof(mr_svo_params, method),
                  MR_PARAM_CHOICES(METHODS), .def = MR_SVO_RIGID,
                  .description = "rigid: transform only, Embree instances of the shared octree. direct: deformed "
                                 "voxel boxes (two matrices per voxel, thesis Fig. 16). resize / emit: resampled "
                                 "into a per-instance world-space octree every frame (2x2x2 cells from the "
                                 "largest side / cells filling the box from the smallest side)."},
    [P_DELTA] = {.field = "delta", .type = MR_PARAM_NUMBER, .offset = offsetof(mr_svo_params, delta),
                 .lo = 0, .hi = 1e6, .flags = MR_PARAM_LO_OPEN, .def = MR_SVO_DEFAULT_DELTA,
                 .expect = "a number of pixels in (0, 1e6]",
                 .description = "Screen-space refinement threshold in pixels: voxels projecting smaller are not "
                                "refined. With \"tolerance_px\" t (methods direct, resize, emit), t / sqrt(3) "
                                "instead; method rigid casts to the level of detail t gives (nodes spanning "
                                "at most t / sqrt(3) pixels hit as leaves)."},
    [P_CULL] = {.field = "cull", .type = MR_PARAM_BOOL, .offset = offsetof(mr_svo_params, cull),
                .def = 1,
                .description = "Drop voxels outside the view frustum (they then cast no shadows into the view "
                               "either; false keeps them, refined by their projected size like the rest)."},
    [P_SKELETON] = {.field = "skeleton", .type = MR_PARAM_FLAG_OBJECT,
                    .offset = offsetof(mr_svo_params, skeleton), .def = 0, .sub = &SKELETON_TABLE,
                    .description = "Extract a skeleton from the voxels (thesis chapter 5) and skin to it; bones "
                                   "are named bone0, bone1, ..."},
    [P_INSTANCES] = {.field = "instances", .type = MR_PARAM_ARRAY,
                     .offset = offsetof(mr_svo_params, instances),
                     .count_offset = offsetof(mr_svo_params, instance_count),
                     .max_items = MR_SVO_MAX_INSTANCES, .sub = &INSTANCE_TABLE,
                     .description = "instances of the shared octree (default: one at the "
                                    "object's transform)"},
};

static const mr_param_table SVO_TABLE = {
    .params = SVO_PARAMS,
    .count = sizeof SVO_PARAMS / sizeof SVO_PARAMS[0],
    .size = sizeof(mr_svo_params),
    .expect = "an object of svo parameters",
    .schema_rules = "{\"if\": {\"required\": [\"voxelize\"], \"properties\": {\"voxelize\": "
                    "{\"const\": \"solid\"}}}, \"then\": {\"properties\": {\"depth\": "
                    "{\"type\": \"integer\", \"maximum\": 10}}}}",
};

const mr_kind mr_kind_svo = {
    .name = "svo",
    .summary = "Parameters of a sparse voxel octree object (kind \"svo\", paper 004): the "
               "asset voxelised once, shared by every instance; each instance has its own "
               "transform and pose.",
    .params = &SVO_TABLE,
    .has_derived = true,
    .animated = svo_animated,
    .has_lod = true,
    .lod = svo_lod,
    .memory_floor = svo_memory_floor,
    .memory_field = "instances",
    .self_posed = true,
    .create = svo_create,
    .update = svo_update,
    .attach = svo_attach,
    .commit = svo_commit,
    .normal = svo_normal,
    .id_primitive = svo_id_primitive,
    .tessellate = svo_tessellate,
    .memory = svo_memory,
    .primitives = svo_primitives,
    .geometry_ids = svo_geometry_ids,
    .stats = SVO_STATS,
    .stat_count = S_COUNT,
    .frame_stats = svo_frame_stats,
    .surface_step = svo_surface_step,
    .reference = svo_reference,
    .free = svo_free,
};
