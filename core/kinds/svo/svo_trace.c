/*
 * svo_trace.c - stack-based ray casting of a sparse voxel octree (see
 * svo_trace.h for the rules: integer plane positions, closed boxes,
 * mirrored child order, explicit handling of zero direction components).
 *
 * One stack frame per level holds an interior node, its integer
 * coordinates, its t interval (already clipped to [tmin, tmax]), the t of
 * its three midplanes, and the mask of children the ray still has to visit
 * (in mirrored order, computed once when the node is entered). The walk takes the lowest pending child of the top frame: a
 * leaf ends the walk (it is the nearest, see the header), an interior child
 * gets a new frame. A frame with nothing pending is popped.
 *
 * Entering a node prefetches its children's fields. A single ray then
 * waits for them one level after another; mr_svo_intersect_rays keeps
 * each ray's walk in a walker of its own and steps the rays in turn, one
 * entered node each, so the fetches of one overlap the others' work.
 * Each ray's sequence of steps is the single walk's, so its hit is too.
 */
#include "kinds/svo/svo_trace.h"
#include "util/morton.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* Every plane is placed on the finest possible grid, 2^21 cells per axis,
 * whatever the octree's depth: a node at level l spans 2^(21 - l) cells. */
#define GRID_BITS MR_SVO_MAX_DEPTH
#define GRID_CELLS (1u << GRID_BITS)

#define DMAX(a, b) ((a) > (b) ? (a) : (b))
#define DMIN(a, b) ((a) < (b) ? (a) : (b))

/* Per-ray constants. A plane at finest-grid position k on axis a lies at
 * signed distance s = d0[a] + k * cell from the ray origin (k * cell is
 * exact: 22 bits of k times the 24 bits of size), at t = s * inv[a]. */
typedef struct svo_ray {
    double d0[3];
    double cell;
    double inv[3];  /* 1 / dir; unused on parallel axes */
    unsigned mirror; /* bit a: dir[a] < 0 */
    unsigned par;    /* bit a: dir[a] == 0 (the ray never crosses a plane of a) */
    bool tie;        /* the ray lies in a midplane it is parallel to (see frame_enter) */
    bool lod;        /* a level of detail (mr_svo_lod): lz0 + t lzd bounds a hit cell's edge */
    double lz0, lzd;
    unsigned cut_from; /* no node above this level is small enough (walk_start) */
    bool clip;       /* cut nodes are clipped to the box [clip_lo, clip_hi) (mr_svo_lod) */
    uint32_t clip_lo[3], clip_hi[3]; /* finest-grid positions */
    double tmin, tmax;
} svo_ray;

typedef struct svo_frame {
    /* Per axis and half h (mirrored: 0 near, 1 far), the t where the
     * half's slab starts (en) and ends (ex) within the node: the far half
     * starts and the near half ends at the midplane's t, the others are
     * -inf and +inf, and on parallel axes both halves span all t. A child's
     * interval is then [max(t0, en), min(t1, ex)] over its three halves,
     * without a branch on which halves those are. */
    double en[3][2], ex[3][2];
    double t0, t1;    /* the node's interval, clipped */
    uint32_t node;
    uint32_t xyz[3];  /* integer coordinates at the frame's level */
    unsigned pending; /* mirrored child indices still to visit */
    int axis;         /* axis of the plane t0 lies on, -1 for tmin */
} svo_frame;

/* Children of mirrored index i with bit a equal to h, for a parallel axis
 * that rules one half out. */
static const uint8_t half_children[3][2] = {{0x55, 0xaa}, {0x33, 0xcc}, {0x0f, 0xf0}};

/* The lowest axis in a nonzero 3-bit mask of axes. */
static const int8_t FIRST_AXIS[8] = {-1, 0, 1, 0, 2, 0, 1, 0};

static inline double plane_s(const svo_ray *r, int a, uint32_t k)
{
    return r->d0[a] + (double)k * r->cell;
}

/* The edge of a cell of the given level (exact: a power of 2 times the
 * cube's size). */
static inline double cell_edge(const svo_ray *r, unsigned level)
{
    return (double)(GRID_CELLS >> level) * r->cell;
}

/* Sets up the ray; false when it cannot hit anything (non-finite input,
 * empty [tmin, tmax]). */
static bool ray_setup(const mr_svo *svo, mr_vec3 org, mr_vec3 dir, float tmin, float tmax, const mr_svo_lod *lod,
                      svo_ray *r)
{
    const float o[3] = {org.x, org.y, org.z};
    const float d[3] = {dir.x, dir.y, dir.z};
    const float c[3] = {svo->origin.x, svo->origin.y, svo->origin.z};
    if (!isfinite(tmin) || isnan(tmax) || !(tmax >= tmin))
        return false;
    if (!isfinite(svo->size) || !(svo->size > 0.0f))
        return false;
    r->mirror = 0;
    r->par = 0;
    r->tie = false;
    for (int a = 0; a < 3; a++) {
        if (!isfinite(o[a]) || !isfinite(d[a]) || !isfinite(c[a]))
            return false;
        r->d0[a] = (double)c[a] - (double)o[a];
        if (d[a] == 0.0f) {
            r->par |= 1u << a;
            r->inv[a] = 0.0;
        } else {
            /* In double, even 1 / (smallest denormal) is finite. */
            r->inv[a] = 1.0 / (double)d[a];
            if (d[a] < 0.0f)
                r->mirror |= 1u << a;
        }
    }
    r->cell = (double)svo->size * (1.0 / (double)GRID_CELLS); /* exact: a power of 2 */
    r->lod = lod != NULL;
    if (lod) {
        r->lz0 = lod->a[0] * (double)o[0] + lod->a[1] * (double)o[1] + lod->a[2] * (double)o[2] + lod->b;
        r->lzd = lod->a[0] * (double)d[0] + lod->a[1] * (double)d[1] + lod->a[2] * (double)d[2];
        /* (a node's hit reports leaf_count + node: a uint32_t) */
        r->lod = isfinite(r->lz0) && isfinite(r->lzd) &&
                 (uint64_t)svo->leaf_count + svo->node_count <= UINT32_MAX;
        r->clip = lod->clip;
        if (r->clip) {
            if (lod->clip_level > GRID_BITS)
                return false;
            const unsigned shift = GRID_BITS - lod->clip_level;
            for (int a = 0; a < 3; a++) {
                const uint64_t lo = (uint64_t)lod->clip_lo[a] << shift, hi = (uint64_t)lod->clip_hi[a] << shift;
                if (!(lo < hi && hi <= GRID_CELLS))
                    return false; /* an empty or malformed box holds no leaf */
                r->clip_lo[a] = (uint32_t)lo;
                r->clip_hi[a] = (uint32_t)hi;
            }
        }
    }
    r->tmin = (double)tmin;
    /* A t past FLT_MAX could not be reported as a float. */
    r->tmax = DMIN((double)tmax, (double)FLT_MAX);
    return r->tmin <= r->tmax;
}

/* The child mask in mirrored order: bit i is bit i ^ mirror of m. */
static inline unsigned mirror_mask(unsigned m, unsigned mirror)
{
    if (mirror & 1u)
        m = ((m & 0x55u) << 1) | ((m >> 1) & 0x55u);
    if (mirror & 2u)
        m = ((m & 0x33u) << 2) | ((m >> 2) & 0x33u);
    if (mirror & 4u)
        m = ((m & 0x0fu) << 4) | ((m >> 4) & 0x0fu);
    return m;
}

/* All children but `children` when cond fails, else all (branch-free). */
#define DROP(cond, children) (~(0u - (unsigned)!(cond)) | ~(unsigned)(children))

/* Computes f's midplanes and the children the ray touches. f->xyz, node,
 * t0, t1 are set; level is the node's level (< GRID_BITS).
 * Child (hx, hy, hz) (mirrored halves) has the interval [max(t0, mid of
 * each axis with h = 1), min(t1, mid of each axis with h = 0)], since a
 * node's near planes are <= t0 and its far planes >= t1. It is non-empty
 * exactly when each entry is <= each exit, i.e. per axis mid >= t0 (near
 * half) or mid <= t1 (far half), and per pair of axes a far half of a and
 * a near half of b need mid_a <= mid_b. Nine comparisons, no branches
 * (which children a ray touches is unpredictable). */
static inline __attribute__((always_inline)) void frame_enter(svo_ray *r, const mr_svo *svo, svo_frame *f,
                                                              unsigned level)
{
    /* The node's other fields are read when its children are popped: start
     * those cache misses together with the child mask's. */
    __builtin_prefetch(&svo->leaf_mask[f->node]);
    __builtin_prefetch(&svo->first_leaf[f->node]);
    __builtin_prefetch(&svo->first_node[f->node]);
    const uint32_t span = GRID_CELLS >> level;
    unsigned keep = 0xffu;
    double me[3], mx[3]; /* the far half's entry, the near half's exit */
    for (int a = 0; a < 3; a++) {
        const uint32_t kmid = f->xyz[a] * span + (span >> 1);
        if (r->par & (1u << a)) {
            /* Constant position along a: a half is in when its closed slab
             * holds it (on the midplane, both are). */
            const double s = plane_s(r, a, kmid);
            if (s < 0.0)
                keep &= half_children[a][1];
            else if (s > 0.0)
                keep &= half_children[a][0];
            else
                r->tie = true;
            me[a] = -INFINITY;
            mx[a] = INFINITY;
        } else {
            me[a] = mx[a] = plane_s(r, a, kmid) * r->inv[a];
        }
        f->en[a][0] = -INFINITY;
        f->en[a][1] = me[a];
        f->ex[a][0] = mx[a];
        f->ex[a][1] = INFINITY;
    }
    keep &= DROP(mx[0] >= f->t0, 0x55u) & DROP(me[0] <= f->t1, 0xaau);
    keep &= DROP(mx[1] >= f->t0, 0x33u) & DROP(me[1] <= f->t1, 0xccu);
    keep &= DROP(mx[2] >= f->t0, 0x0fu) & DROP(me[2] <= f->t1, 0xf0u);
    /* far half of the first axis, near half of the second */
    keep &= DROP(me[0] <= mx[1], 0x22u) & DROP(me[1] <= mx[0], 0x44u);
    keep &= DROP(me[0] <= mx[2], 0x0au) & DROP(me[2] <= mx[0], 0x50u);
    keep &= DROP(me[1] <= mx[2], 0x0cu) & DROP(me[2] <= mx[1], 0x30u);
    f->pending = keep & mirror_mask(svo->child_mask[f->node], r->mirror);
    /* The interior children's fields, side by side in each array: the
     * walk descends into one of them next, and at depth 10 and beyond the
     * child's mask was the walk's costliest load (a cache miss a level). */
    const uint32_t fn = svo->first_node[f->node];
    __builtin_prefetch(&svo->child_mask[fn]);
    __builtin_prefetch(&svo->leaf_mask[fn]);
    __builtin_prefetch(&svo->first_node[fn]);
    __builtin_prefetch(&svo->first_leaf[fn]);
}

static void fill_hit(const svo_ray *r, mr_svo_hit *hit, uint32_t leaf, unsigned level, const uint32_t xyz[3],
                     int axis, double t0)
{
    hit->t = (float)t0;
    hit->leaf = leaf;
    hit->level = level;
    hit->x = xyz[0];
    hit->y = xyz[1];
    hit->z = xyz[2];
    hit->axis = axis;
    float n[3] = {0.0f, 0.0f, 0.0f};
    if (axis >= 0)
        n[axis] = (r->mirror & (1u << axis)) ? 1.0f : -1.0f;
    hit->ng = mr_v3(n[0], n[1], n[2]);
}

/* A cut node's cell at level, xyz clipped to r's box: *t, *axis (the ray
 * enters the cell there, through that face, and leaves it by t1) become
 * where the ray enters the part of the cell within the box; false when it
 * misses that part. Plane t's as the walk makes them (plane_s * inv), so a
 * box face that is a cell face gives the walk's own t. */
static bool clip_cut(const svo_ray *r, unsigned level, const uint32_t xyz[3], double *t, int *axis, double t1)
{
    const uint32_t span = GRID_CELLS >> level;
    for (int a = 0; a < 3; a++) {
        const uint32_t k0 = xyz[a] * span, k1 = k0 + span;
        const uint32_t lo = k0 > r->clip_lo[a] ? k0 : r->clip_lo[a], hi = k1 < r->clip_hi[a] ? k1 : r->clip_hi[a];
        if (lo >= hi)
            return false;
        if (lo == k0 && hi == k1)
            continue; /* the cell's own faces on this axis */
        if (r->par & (1u << a)) {
            if (plane_s(r, a, lo) > 0.0 || plane_s(r, a, hi) < 0.0)
                return false;
            continue;
        }
        const double ta = plane_s(r, a, lo) * r->inv[a], tb = plane_s(r, a, hi) * r->inv[a];
        const double near = DMIN(ta, tb), far = DMAX(ta, tb);
        if (near > *t) {
            *t = near;
            *axis = a;
        }
        t1 = DMIN(t1, far);
    }
    return *t <= t1;
}

/* One ray's walk, a step at a time (svo_walk runs one to its end;
 * mr_svo_intersect_rays runs several, taking turns). */
typedef struct svo_walker {
    svo_ray r;
    mr_svo_hit *hit; /* NULL: any hit ends the walk */
    int base;        /* the start node's level */
    int top;         /* == the top frame's level */
    bool found;      /* tie case: a hit so far, at t best */
    double best;
    svo_frame stack[MR_SVO_MAX_DEPTH + 1];
} svo_walker;

typedef enum { WALK_MISS, WALK_HIT, WALK_ON } walk_state;

/* Starts w's walk from interior node `start` at level `base` and cell
 * bxyz (the root: 0, 0, {0, 0, 0}); hit may be NULL. WALK_ON when it
 * entered the start node, else the walk's answer. */
static inline __attribute__((always_inline)) walk_state
walk_start(const mr_svo *svo, uint32_t start, unsigned base, const uint32_t bxyz[3], mr_vec3 org, mr_vec3 dir,
           float tmin, float tmax, const mr_svo_lod *lod, mr_svo_hit *hit, svo_walker *w)
{
    svo_ray *r = &w->r;
    if (!svo || (svo->node_count == 0 && svo->leaf_count == 0))
        return WALK_MISS;
    if (!ray_setup(svo, org, dir, tmin, tmax, lod, r))
        return WALK_MISS;
    const uint32_t bspan = GRID_CELLS >> base;

    /* The start node's cube. The entry face is the axis whose near plane is
     * the latest, if that is not before tmin (else the ray starts inside). */
    double t0 = r->tmin, t1 = r->tmax;
    int axis = -1;
    for (int a = 0; a < 3; a++) {
        const uint32_t k0 = bxyz[a] * bspan, k1 = k0 + bspan;
        if (r->par & (1u << a)) {
            if (plane_s(r, a, k0) > 0.0 || plane_s(r, a, k1) < 0.0)
                return WALK_MISS;
            continue;
        }
        const double ta = plane_s(r, a, k0) * r->inv[a];
        const double tb = plane_s(r, a, k1) * r->inv[a];
        const double near = DMIN(ta, tb), far = DMAX(ta, tb);
        if (near > t0 || (near == t0 && axis < 0)) {
            t0 = near;
            axis = a;
        }
        t1 = DMIN(t1, far);
    }
    if (!(t0 <= t1))
        return WALK_MISS;
    /* The level of detail's bound is largest at an end of [t0, t1] (its
     * rounded a + t b is monotonic in t), and every cell entered is
     * entered within it: nodes above the first level whose edge fits that
     * largest bound need no test (the same answers, fewer tests; nodes
     * sit above the octree's depth). */
    r->cut_from = GRID_BITS + 1u;
    if (r->lod) {
        const double most = DMAX(r->lz0 + t0 * r->lzd, r->lz0 + t1 * r->lzd);
        for (unsigned l = base + 1u; l < svo->depth && l <= GRID_BITS; l++)
            if (cell_edge(r, l) <= most) {
                r->cut_from = l;
                break;
            }
    }
    if (svo->node_count == 0) {
        /* The root is a leaf. */
        if (hit) {
            const uint32_t zero[3] = {0, 0, 0};
            fill_hit(r, hit, 0, 0, zero, axis, t0);
        }
        return WALK_HIT;
    }
    /* A walk from a subtree's node (a piece) tests that node as the whole
     * walk tests it when it comes to it, at the t where the ray enters its
     * cell: the same cut whatever level the pieces are cut at. The root is
     * never cut (nor by the whole walk). */
    if (r->lod && base > 0 && cell_edge(r, base) <= r->lz0 + t0 * r->lzd) {
        if (r->clip && !clip_cut(r, base, bxyz, &t0, &axis, t1))
            return WALK_MISS;
        if (hit)
            fill_hit(r, hit, svo->leaf_count + start, base, bxyz, axis, t0);
        return WALK_HIT;
    }

    w->hit = hit;
    w->base = (int)base;
    w->top = (int)base;
    w->found = false;
    w->best = r->tmax;
    svo_frame *f = &w->stack[base];
    f->node = start;
    f->xyz[0] = bxyz[0], f->xyz[1] = bxyz[1], f->xyz[2] = bxyz[2];
    f->t0 = t0;
    f->t1 = t1;
    f->axis = axis;
    frame_enter(r, svo, f, base);
    return WALK_ON;
}

/* Goes on with w's walk until it enters a node (WALK_ON: the node's
 * children are being fetched, a good time to step another ray) or ends. */
static inline __attribute__((always_inline)) walk_state walk_step(const mr_svo *svo, svo_walker *w)
{
    svo_ray *r = &w->r;
    for (;;) {
        svo_frame *f = &w->stack[w->top];
        if (f->pending == 0) {
            if (w->top == w->base)
                return w->found ? WALK_HIT : WALK_MISS;
            w->top--;
            continue;
        }
        const unsigned i = (unsigned)__builtin_ctz(f->pending);
        f->pending &= f->pending - 1u;
        const unsigned c = i ^ r->mirror;
        /* The child's interval, and the axis of its entry face: the first
         * axis whose half starts at c0 when that is past t0, or when t0 is
         * tmin (axis -1) and some half starts there too; else the node's. */
        const double e0 = f->en[0][i & 1u], e1 = f->en[1][(i >> 1) & 1u], e2 = f->en[2][i >> 2];
        const double c0 = DMAX(DMAX(f->t0, e0), DMAX(e1, e2));
        const double c1 = DMIN(DMIN(DMIN(f->t1, w->best), f->ex[0][i & 1u]),
                               DMIN(f->ex[1][(i >> 1) & 1u], f->ex[2][i >> 2]));
        const unsigned starts = (unsigned)(e0 == c0) | (unsigned)(e1 == c0) << 1 | (unsigned)(e2 == c0) << 2;
        const int caxis = starts && (c0 > f->t0 || f->axis < 0) ? FIRST_AXIS[starts] : f->axis;
        if (!(c0 <= c1))
            continue; /* only after a hit in the tie case */
        const unsigned cbit = 1u << c;
        const unsigned lmask = svo->leaf_mask[f->node];
        const unsigned clevel = (unsigned)w->top + 1u;
        const uint32_t cxyz[3] = {f->xyz[0] * 2u + (c & 1u), f->xyz[1] * 2u + ((c >> 1) & 1u),
                                  f->xyz[2] * 2u + (c >> 2)};
        uint32_t leaf; /* what the walk hits: a leaf, or a node that stands for its leaves */
        double t = c0;  /* ... where, and the axis of that face */
        int axis = caxis;
        if (lmask & cbit) {
            leaf = svo->first_leaf[f->node] + mr_svo_popcount8(lmask & (cbit - 1u));
            if (leaf >= svo->leaf_count)
                continue; /* malformed octree: skip rather than read out of bounds */
        } else {
            /* Interior children never sit at the finest level. */
            const unsigned nmask = svo->child_mask[f->node] & ~lmask;
            const uint32_t node = svo->first_node[f->node] + mr_svo_popcount8(nmask & (cbit - 1u));
            if (clevel >= GRID_BITS || node >= svo->node_count)
                continue;
            if (clevel < r->cut_from || cell_edge(r, clevel) > r->lz0 + c0 * r->lzd) {
                svo_frame *g = &w->stack[++w->top];
                g->node = node;
                g->xyz[0] = cxyz[0];
                g->xyz[1] = cxyz[1];
                g->xyz[2] = cxyz[2];
                g->t0 = c0;
                g->t1 = c1;
                g->axis = caxis;
                frame_enter(r, svo, g, clevel);
                return WALK_ON;
            }
            /* small enough for the level of detail: hit as a leaf */
            leaf = svo->leaf_count + node;
            if (r->clip && !clip_cut(r, clevel, cxyz, &t, &axis, c1))
                continue;
        }
        if (!w->hit)
            return WALK_HIT;
        /* The first leaf met is the nearest unless the ray lies in a
         * midplane it is parallel to: then the two halves along that
         * axis share one t interval and the walk finishes the other
         * half, keeping the nearest (ties: the first). */
        if (!r->tie || t <= r->tmin) {
            fill_hit(r, w->hit, leaf, clevel, cxyz, axis, t);
            return WALK_HIT;
        }
        if (!w->found || t < w->best) {
            fill_hit(r, w->hit, leaf, clevel, cxyz, axis, t);
            w->found = true;
            w->best = t;
        }
    }
}

/* The walk shared by the single-ray queries. */
static inline bool svo_walk(const mr_svo *svo, uint32_t start, unsigned base, const uint32_t bxyz[3],
                            mr_vec3 org, mr_vec3 dir, float tmin, float tmax, mr_svo_hit *hit)
{
    svo_walker w;
    walk_state st = walk_start(svo, start, base, bxyz, org, dir, tmin, tmax, NULL, hit, &w);
    while (st == WALK_ON)
        st = walk_step(svo, &w);
    return st == WALK_HIT;
}

static const uint32_t ROOT_XYZ[3] = {0, 0, 0};

bool mr_svo_intersect(const mr_svo *svo, mr_vec3 org, mr_vec3 dir, float tmin, float tmax, mr_svo_hit *hit)
{
    return svo_walk(svo, 0, 0, ROOT_XYZ, org, dir, tmin, tmax, hit);
}

bool mr_svo_occluded(const mr_svo *svo, mr_vec3 org, mr_vec3 dir, float tmin, float tmax)
{
    return svo_walk(svo, 0, 0, ROOT_XYZ, org, dir, tmin, tmax, NULL);
}

/* The walk of mr_svo_subtrees (the subtrees at `level` into s) and of
 * mr_svo_subtree_counts (counts != NULL: how many there are at every
 * level up to `level`, nothing collected). */
typedef struct {
    const mr_svo *svo;
    unsigned level;
    mr_svo_subtree *s;
    uint32_t count, cap;
    uint32_t *counts;
} subtree_list;

static int collect_subtrees(subtree_list *l, uint32_t node, unsigned level, const uint32_t xyz[3],
                            mr_error *err)
{
    const mr_svo *o = l->svo;
    /* a node with leaf children, or above the finest level, is a subtree at
     * every level from its own */
    const bool stops = level + 1 >= o->depth || o->leaf_mask[node];
    if (l->counts) {
        for (unsigned k = level; k <= (stops ? l->level : level); k++)
            l->counts[k]++;
        if (stops || level == l->level)
            return MR_OK;
    } else if (stops || level == l->level) {
        if (l->count == l->cap) {
            const uint32_t grown = l->cap ? 2 * l->cap : 256;
            mr_svo_subtree *s = realloc(l->s, (size_t)grown * sizeof *s);
            if (!s)
                return mr_error_set(err, MR_ERR_NOMEM, "svo subtrees: out of memory for %u", grown);
            l->s = s;
            l->cap = grown;
        }
        l->s[l->count++] = (mr_svo_subtree){node, level, {xyz[0], xyz[1], xyz[2]}};
        return MR_OK;
    }
    uint32_t child = o->first_node[node];
    for (unsigned ch = 0; ch < 8; ch++) {
        if (!(o->child_mask[node] >> ch & 1u))
            continue;
        if (child >= o->node_count)
            return mr_error_set(err, MR_ERR_FORMAT, "svo subtrees: node %u's children out of range", node);
        const uint32_t c[3] = {2 * xyz[0] + (ch & 1u), 2 * xyz[1] + (ch >> 1 & 1u), 2 * xyz[2] + (ch >> 2)};
        int rc = collect_subtrees(l, child++, level + 1, c, err);
        if (rc < 0)
            return rc;
    }
    return MR_OK;
}

int mr_svo_subtrees(const mr_svo *svo, unsigned level, mr_svo_subtree **out, uint32_t *count, mr_error *err)
{
    *out = NULL;
    *count = 0;
    if (!svo || svo->node_count == 0)
        return MR_OK;
    subtree_list l = {.svo = svo, .level = level};
    int rc = collect_subtrees(&l, 0, 0, ROOT_XYZ, err);
    if (rc < 0) {
        free(l.s);
        return rc;
    }
    *out = l.s;
    *count = l.count;
    return MR_OK;
}

int mr_svo_subtree_counts(const mr_svo *svo, unsigned max_level, uint32_t *counts, mr_error *err)
{
    memset(counts, 0, (max_level + 1) * sizeof *counts);
    if (!svo || svo->node_count == 0)
        return MR_OK;
    subtree_list l = {.svo = svo, .level = max_level, .counts = counts};
    return collect_subtrees(&l, 0, 0, ROOT_XYZ, err);
}

bool mr_svo_subtree_cells(const mr_svo *svo, const mr_svo_subtree *s, unsigned below, uint32_t lo[3],
                          uint32_t hi[3])
{
    if (!svo || svo->depth > MR_SVO_MAX_DEPTH || s->level > svo->depth || (s->xyz[0] | s->xyz[1] | s->xyz[2]) >> s->level)
        return false;
    const unsigned shift = svo->depth - s->level;
    for (int a = 0; a < 3; a++) {
        lo[a] = s->xyz[a] << shift;
        hi[a] = (s->xyz[a] + 1u) << shift;
    }
    if (below) {
        uint32_t olo[3] = {UINT32_MAX, UINT32_MAX, UINT32_MAX}, ohi[3] = {0, 0, 0};
        mr_error err; /* a malformed octree keeps the cell */
        if (mr_svo_grow_occupied(svo, s->node, s->level, s->xyz,
                                 s->level + below < svo->depth ? s->level + below : svo->depth, olo, ohi, &err) == MR_OK) {
            memcpy(lo, olo, sizeof olo);
            memcpy(hi, ohi, sizeof ohi);
        }
    }
    return true;
}

/* A subtree's node must be interior and below the finest level. */
static bool subtree_ok(const mr_svo *svo, const mr_svo_subtree *s)
{
    return s->node < svo->node_count && s->level < svo->depth;
}

uint32_t mr_svo_intersect_rays(const mr_svo *svo, const mr_svo_subtree *s, unsigned n, const mr_vec3 *org,
                               const mr_vec3 *dir, const float *tmin, const float *tmax, const mr_svo_lod *lod,
                               mr_svo_hit *hit)
{
    if (!svo || (s && !subtree_ok(svo, s)))
        return 0;
    n = n < 32 ? n : 32;
    const uint32_t start = s ? s->node : 0;
    const unsigned base = s ? s->level : 0;
    const uint32_t *bxyz = s ? s->xyz : ROOT_XYZ;
    svo_walker w[MR_SVO_RAYS];
    uint32_t hits = 0;
    for (unsigned first = 0; first < n; first += MR_SVO_RAYS) {
        const unsigned count = n - first < MR_SVO_RAYS ? n - first : MR_SVO_RAYS;
        uint32_t on = 0;
        for (unsigned k = 0; k < count; k++) {
            const unsigned i = first + k;
            const walk_state st = walk_start(svo, start, base, bxyz, org[i], dir[i], tmin[i], tmax[i], lod,
                                             hit ? &hit[i] : NULL, &w[k]);
            on |= (uint32_t)(st == WALK_ON) << k;
            hits |= (uint32_t)(st == WALK_HIT) << i;
        }
        /* Round robin: a walk that entered a node has its children on the
         * way from memory while the others take their steps. */
        while (on) {
            for (uint32_t left = on; left; left &= left - 1u) {
                const unsigned k = (unsigned)__builtin_ctz(left);
                const walk_state st = walk_step(svo, &w[k]);
                if (st != WALK_ON) {
                    on &= ~(1u << k);
                    hits |= (uint32_t)(st == WALK_HIT) << (first + k);
                }
            }
        }
    }
    return hits;
}

bool mr_svo_intersect_subtree(const mr_svo *svo, const mr_svo_subtree *s, mr_vec3 org, mr_vec3 dir, float tmin,
                              float tmax, mr_svo_hit *hit)
{
    return svo && subtree_ok(svo, s) && svo_walk(svo, s->node, s->level, s->xyz, org, dir, tmin, tmax, hit);
}

bool mr_svo_occluded_subtree(const mr_svo *svo, const mr_svo_subtree *s, mr_vec3 org, mr_vec3 dir, float tmin,
                             float tmax)
{
    return svo && subtree_ok(svo, s) && svo_walk(svo, s->node, s->level, s->xyz, org, dir, tmin, tmax, NULL);
}

uint64_t mr_svo_subtree_order(const mr_svo_subtree *s, mr_vec3 dir)
{
    const float d[3] = {dir.x, dir.y, dir.z};
    uint32_t c[3];
    for (int a = 0; a < 3; a++) {
        /* mirrored along the axes the ray runs down: the walk's child order */
        const uint32_t cells = s->level ? (1u << s->level) - 1u : 0u;
        c[a] = d[a] < 0.0f ? cells - s->xyz[a] : s->xyz[a];
    }
    /* cells of coarser subtrees sort as their first finest-level cell */
    const unsigned up = MR_SVO_MAX_DEPTH - s->level;
    return mr_morton_encode(c[0] << up, c[1] << up, c[2] << up);
}

bool mr_svo_bounds_cells(const mr_svo *svo, uint32_t lo_cell[3], uint32_t hi_cell[3])
{
    for (int a = 0; a < 3; a++)
        lo_cell[a] = hi_cell[a] = 0;
    if (!svo || (svo->node_count == 0 && svo->leaf_count == 0))
        return false;
    /* The leaves' box, or else the halves of the root that hold anything,
     * per axis. */
    const uint32_t cells = 1u << svo->depth, half = cells / 2;
    for (int a = 0; a < 3; a++)
        hi_cell[a] = cells;
    if (svo->has_occupied) {
        memcpy(lo_cell, svo->occupied_lo, sizeof svo->occupied_lo);
        memcpy(hi_cell, svo->occupied_hi, sizeof svo->occupied_hi);
    } else if (svo->node_count > 0 && svo->child_mask[0] != 0) { /* 0: malformed, keep the cube */
        const unsigned m = svo->child_mask[0];
        for (unsigned a = 0; a < 3; a++) {
            const unsigned high = half_children[a][1]; /* the children on the high side of a */
            lo_cell[a] = (m & ~high & 0xffu) ? 0 : half;
            hi_cell[a] = (m & high) ? cells : half;
        }
    }
    return true;
}

bool mr_svo_bounds(const mr_svo *svo, float lo[3], float hi[3])
{
    uint32_t lo_cell[3], hi_cell[3];
    if (!mr_svo_bounds_cells(svo, lo_cell, hi_cell)) {
        const mr_vec3 c = svo ? svo->origin : mr_v3(0.0f, 0.0f, 0.0f);
        lo[0] = hi[0] = c.x, lo[1] = hi[1] = c.y, lo[2] = hi[2] = c.z;
        return false;
    }
    const float c[3] = {svo->origin.x, svo->origin.y, svo->origin.z};
    const double cell = ldexp((double)svo->size, -(int)svo->depth); /* cells * cell: exact */
    for (unsigned a = 0; a < 3; a++) {
        lo[a] = mr_float_down((double)c[a] + lo_cell[a] * cell);
        hi[a] = mr_float_up((double)c[a] + hi_cell[a] * cell);
    }
    return true;
}
