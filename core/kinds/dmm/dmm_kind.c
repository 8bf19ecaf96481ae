/*
 * dmm_kind.c - the displaced micro-mesh (DMM) kind (paper 000, issue 4).
 *
 * create   bakes every mesh of the asset (dmm_bake.h: meshoptimizer base mesh
 *          whose vertices keep their bone weights, Embree-measured
 *          displacements), encodes them (dmm_encode.h) and keeps the DECODED
 *          grid values and the min/max pyramid down to the traversal's leaf
 *          sublevel: what is rendered is exactly what a DMM file stores;
 *          with a cache folder (mr_kind_context), bakes are kept on disk (dmm_file.h) keyed
 *          by the mesh data and bake parameters, and a hit skips bake and
 *          encode (the decoded data is the same, bit for bit);
 * update   computes each base vertex's accumulated skinning matrix M_a
 *          (mr_skin_matrices; static meshes get their node's matrix), then
 *           - mode base: skins base vertices and directions with it
 *             (v' = M v, n' = M n, eq. 4: directions are neither
 *             inverse-transposed nor renormalised, so the prism bounds hold
 *             and displacements scale with the bone);
 *           - mode interpolated: keeps the rest pose; M is interpolated per
 *             micro-vertex (eq. 6-8);
 *          and then either the box of every base triangle (dmm_trace.h: prism
 *          or 12 Bezier control points), for the Embree user geometry to
 *          refit over: cost proportional to base triangles; or, in mode
 *          tessellated, every micro-vertex with the same mr_dmm_vertex;
 * attach   tessellation-free modes: one Embree USER geometry, one primitive
 *          per base triangle, whose callbacks run dmm_trace.h's traversal;
 *          tessellated, intersector embree: one TRIANGLE geometry over the
 *          micro-triangles (base triangle after base triangle, each its
 *          surviving micro-triangles in micromesh.h row order:
 *          mr_umesh_triangles); tessellated, intersector watertight (the
 *          exact reference, issue 17): the tessellation-free modes' user
 *          geometry and boxes (update checks they hold every micro-vertex),
 *          whose callbacks test the base triangle's micro-triangles one by
 *          one (mr_dmm_intersect_micro). In every user geometry hits at the
 *          same t go to the smaller base triangle, then micro-triangle, so
 *          the reference's frames equal the traversal's bit for bit;
 * normal   the hit micro-triangle's geometric normal, or (normals "matrix")
 *          the rest-pose micro-triangle normal moved by the cofactor of the
 *          interpolated matrix at the hit.
 *
 * Base triangles have their own levels (bake parameter "adaptive"): every
 * per-triangle array (decoded values, pyramid, micro-vertices and
 * micro-triangles) is packed, with a prefix offset per base triangle.
 *
 * With "tolerance_px" every base triangle traces, each frame, the coarsest
 * of its levels (its baked one down to 0) whose bound, projected by the
 * frame's camera, stays below the tolerance (see "levels of detail"
 * below): one Embree geometry whose base triangles change level.
 *
 * Everything per base triangle is computed from that triangle's own data in
 * a fixed order, so results are bit-identical for any thread count, and
 * micromesh.h's edge rule makes shared-edge micro-vertices bit-identical on
 * both sides: the surface is watertight in every mode.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "kinds/dmm/dmm_bake.h"
#include "kinds/dmm/dmm_encode.h"
#include "kinds/dmm/dmm_file.h"
#include "kinds/dmm/dmm_trace.h"
#include "kinds/dmm/dmm_kind.h"
#include "kinds/dmm/dmm_lod.h"
#include "kinds/dmm/micromesh.h"
#include "kinds/lod.h"
#include "kinds/user_rays.h"
#include "util/parallel.h"

#define UPDATE_GRAIN 64
/* Per base triangle and frame: box lo, hi, and the traversal's pad. */
#define BOX_FLOATS 9

/* One subdivision level of a dmm object: everything an object without
 * levels of detail is (struct mr_geom holds one, or one per level). */
typedef struct dmm_level dmm_level;
struct dmm_level {
    const mr_asset *asset;
    mr_dmm_params desc;
    mr_umesh_topology topo;       /* surviving micro-triangles per level and decimation mask:
                                     a hit maps back to its lattice in O(1) */
    uint8_t *tri_info;            /* per base triangle: level and decimation (dmm_encode.h) */
    /* per base triangle + 1, prefix sums: first decoded value (= first
     * micro-vertex), first pyramid entry, first surviving micro-triangle */
    uint32_t *value_first, *pyramid_first, *micro_first;
    mr_dmm_bake **bakes;          /* per asset mesh; NULL for a mesh without triangles */
    mr_dmm_encoded **encoded;     /* per asset mesh, as bakes */
    uint32_t *mesh_first_base;    /* per asset mesh: first base vertex in the merged arrays */
    uint32_t base_vertex_count, base_triangle_count;
    uint32_t *base_indices;       /* 3 per base triangle, merged vertex numbering */
    uint32_t *tri_mesh;           /* per base triangle: its asset mesh */
    float *rest_pos, *rest_dir;   /* rest-pose base vertices, 3 each */
    uint16_t *values;             /* decoded grid values, from value_first[t] */
    uint16_t *minv, *maxv;        /* pyramid prefixes (mr_dmm_trace_pyramid_size), from
                                     pyramid_first[t] */
    mr_affine *mats, *last_mats;  /* per base vertex: accumulated matrix this / last frame */
    float *posed_pos, *posed_dir; /* mode base: skinned base vertices, 3 each */
    bool evaluated;
    uint64_t stamp;               /* this evaluation's (mr_dmm_patch.stamp), 0: none */
    float *boxes;                 /* tessellation-free: BOX_FLOATS per base triangle */
    float *root_children;         /* interpolated, tessellation-free: per base triangle of
                                     level >= 2, MR_DMM_ROOT_CHILDREN_FLOATS, made by each
                                     evaluation (update_range) */
    uint32_t vertex_count, triangle_count; /* tessellated: micro-vertices / micro-triangles */
    float *positions;             /* 3 per micro-vertex + 1 float padding (Embree 16-byte loads) */
    uint32_t *indices;            /* 3 per micro-triangle */
    size_t encoded_bytes;         /* bytes of the encoded records (what a file stores) */
    double bake_quality[3];       /* the bake's own report, DMM_STATS order */
    double bake_s;                /* create's bake and encoding, or their load from the cache */
    /* normals "smooth": per base triangle its coarse sublevel and, from
     * coarse_first[t], the ids of its coarse lattice vertices (shared with
     * its neighbours on shared edges and corners) into smooth_normals
     * (rest pose, unit, 3 floats per id) */
    uint8_t *coarse_level;
    uint32_t *coarse_first, *coarse_id;
    float *smooth_normals;
    uint32_t smooth_count;        /* coarse vertices (smooth_normals holds 3 floats each) */
    bool relaid;                  /* levels of detail laid the arrays out again since the last
                                     commit (Embree's triangle buffers change size) */
    bool boxes_given;             /* levels of detail fill boxes (their baked levels' boxes,
                                     which hold every coarser surface) before evaluating */
    RTCGeometry rtc;
};

/* Mode tessellated: every micro-vertex evaluated per frame. */
static bool tessellated(const dmm_level *g) { return g->desc.mode == MR_DMM_TESSELLATED; }
/* ... and its micro-triangles given to Embree as triangles (prim: the
 * micro-triangle); otherwise, tessellation-free or the watertight
 * reference, a user geometry of base triangles over their boxes (prim: the
 * base triangle, (u, v) in its domain). */
static bool embree_triangles(const dmm_level *g)
{
    return tessellated(g) && g->desc.intersector == MR_DMM_INTERSECT_EMBREE;
}
/* Mode tessellated, intersector watertight: the exact reference. */
static bool watertight_reference(const dmm_level *g)
{
    return tessellated(g) && g->desc.intersector == MR_DMM_INTERSECT_WATERTIGHT;
}

static void level_free(dmm_level *g)
{
    if (!g)
        return;
    if (g->rtc)
        rtcReleaseGeometry(g->rtc);
    for (size_t i = 0; i < g->asset->mesh_count; i++) {
        if (g->bakes)
            mr_dmm_bake_free(g->bakes[i]);
        if (g->encoded)
            mr_dmm_encoded_free(g->encoded[i]);
    }
    free(g->bakes);
    free(g->encoded);
    mr_umesh_topology_free(&g->topo);
    free(g->tri_info);
    free(g->value_first);
    free(g->pyramid_first);
    free(g->micro_first);
    free(g->mesh_first_base);
    free(g->base_indices);
    free(g->tri_mesh);
    free(g->rest_pos);
    free(g->rest_dir);
    free(g->values);
    free(g->minv);
    free(g->maxv);
    free(g->mats);
    free(g->last_mats);
    free(g->posed_pos);
    free(g->posed_dir);
    free(g->boxes);
    free(g->root_children);
    free(g->positions);
    free(g->indices);
    free(g->coarse_level);
    free(g->coarse_first);
    free(g->coarse_id);
    free(g->smooth_normals);
    free(g);
}

/* Decodes mesh i's values and pyramid prefixes into the packed arrays from
 * base triangle t0 on: freshly baked or from the disk cache, what is
 * rendered is the encoding. */
static int quantise(dmm_level *g, size_t i, uint32_t t0, mr_error *err)
{
    const mr_dmm_bake *b = g->bakes[i];
    int rc = MR_OK;
    const mr_dmm_encoded *enc = g->encoded[i];
    uint32_t full = mr_dmm_pyramid_size(b->level);
    uint16_t *minv = malloc(full * sizeof *minv), *maxv = malloc(full * sizeof *maxv);
    if (!minv || !maxv)
        rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory decoding a dmm");
    for (uint32_t t = 0; t < b->base_triangle_count && rc >= 0; t++) {
        uint32_t at = t0 + t;
        unsigned level = mr_dmm_info_level(g->tri_info[at]);
        uint16_t *values = g->values + g->value_first[at];
        if ((rc = mr_dmm_decode_values(enc, t, values, err)) < 0 ||
            (rc = mr_dmm_pyramid_build(level, values, minv, maxv, err)) < 0)
            break;
        uint32_t keep = g->pyramid_first[at + 1] - g->pyramid_first[at];
        memcpy(g->minv + g->pyramid_first[at], minv, keep * sizeof *minv);
        memcpy(g->maxv + g->pyramid_first[at], maxv, keep * sizeof *maxv);
        g->tri_mesh[at] = (uint32_t)i;
    }
    free(minv);
    free(maxv);
    g->encoded_bytes += (size_t)enc->triangle_count + enc->records_bytes;
    return rc;
}

/* Surviving micro-triangles of base triangle t (local vertex indices). */
static const uint32_t *local_tris(const dmm_level *g, uint32_t t, uint32_t *count)
{
    unsigned l = mr_dmm_info_level(g->tri_info[t]), m = mr_dmm_info_decimate(g->tri_info[t]);
    *count = g->topo.count[l][m];
    return g->topo.tris[l][m];
}

/* The micro-triangle indices of every base triangle, each over its own
 * block of micro-vertices from value_first[t], into out. */
static void fill_micro_indices(const dmm_level *g, uint32_t *out)
{
    for (uint32_t t = 0; t < g->base_triangle_count; t++) {
        uint32_t count;
        const uint32_t *local = local_tris(g, t, &count);
        uint32_t *o = out + (size_t)g->micro_first[t] * 3;
        for (uint32_t k = 0; k < count * 3; k++)
            o[k] = local[k] + g->value_first[t];
    }
}

static int check_desc(const mr_dmm_params *d, mr_error *err)
{
    if (d->level > MR_UMESH_MAX_LEVEL)
        return mr_error_set(err, MR_ERR_INVALID, "dmm level %u is outside 0..%u", d->level,
                            MR_UMESH_MAX_LEVEL);
    if (d->base_triangles == 0 && !(d->base_ratio > 0 && d->base_ratio <= 1))
        return mr_error_set(err, MR_ERR_INVALID, "dmm base_ratio %g is outside (0, 1]",
                            (double)d->base_ratio);
    if ((d->mode == MR_DMM_BASE && d->deform != MR_DMM_DEFORM_BASE) ||
        (d->mode == MR_DMM_INTERPOLATED && d->deform != MR_DMM_DEFORM_INTERPOLATED) ||
        d->mode > MR_DMM_INTERPOLATED || d->deform > MR_DMM_DEFORM_INTERPOLATED ||
        d->normals > MR_DMM_NORMALS_SMOOTH)
        return mr_error_set(err, MR_ERR_INVALID, "dmm mode %d cannot use deformation %d",
                            (int)d->mode, (int)d->deform);
    return MR_OK;
}

/* Per-triangle levels into the packed layout: tri_info and the prefix
 * offsets, within the asset caps. */
static int lay_out(dmm_level *g, mr_error *err)
{
    size_t nt = g->base_triangle_count;
    g->tri_info = malloc(nt);
    g->value_first = malloc((nt + 1) * sizeof(uint32_t));
    g->pyramid_first = malloc((nt + 1) * sizeof(uint32_t));
    g->micro_first = malloc((nt + 1) * sizeof(uint32_t));
    if (!g->tri_info || !g->value_first || !g->pyramid_first || !g->micro_first)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory for a dmm object");
    size_t t = 0;
    for (size_t i = 0; i < g->asset->mesh_count; i++)
        if (g->bakes[i]) {
            memcpy(g->tri_info + t, g->bakes[i]->tri_info, g->bakes[i]->base_triangle_count);
            t += g->bakes[i]->base_triangle_count;
        }
    uint64_t values = 0, pyramid = 0, micro = 0;
    for (t = 0; t < nt; t++) {
        g->value_first[t] = (uint32_t)values;
        g->pyramid_first[t] = (uint32_t)pyramid;
        g->micro_first[t] = (uint32_t)micro;
        unsigned level = mr_dmm_info_level(g->tri_info[t]);
        uint32_t count;
        local_tris(g, (uint32_t)t, &count);
        values += mr_umesh_vertex_count(level);
        pyramid += mr_dmm_trace_pyramid_size(level);
        micro += count;
        if (values > MR_MAX_ASSET_VERTICES || micro > MR_MAX_ASSET_TRIANGLES)
            return mr_error_set(err, MR_ERR_LIMIT,
                                "%s: %zu base triangles at level %u exceed the caps (%u "
                                "micro-triangles / vertices)",
                                g->asset->path, nt, g->desc.level, MR_MAX_ASSET_TRIANGLES);
    }
    g->value_first[nt] = (uint32_t)values;
    g->pyramid_first[nt] = (uint32_t)pyramid;
    g->micro_first[nt] = (uint32_t)micro;
    return MR_OK;
}

/* Allocates everything after the bake counts are known. */
static int allocate(dmm_level *g, mr_error *err)
{
    size_t nv = g->base_vertex_count, nt = g->base_triangle_count;
    size_t values = g->value_first[nt], pyramid = g->pyramid_first[nt];
    g->base_indices = malloc(nt * 3 * sizeof(uint32_t));
    g->tri_mesh = malloc(nt * sizeof(uint32_t));
    g->rest_pos = malloc(nv * 3 * sizeof(float));
    g->rest_dir = malloc(nv * 3 * sizeof(float));
    g->values = malloc(values * sizeof(uint16_t));
    g->minv = malloc(pyramid * sizeof(uint16_t));
    g->maxv = malloc(pyramid * sizeof(uint16_t));
    g->mats = calloc(nv, sizeof(mr_affine));
    g->last_mats = calloc(nv, sizeof(mr_affine));
    bool ok = g->base_indices && g->tri_mesh && g->rest_pos && g->rest_dir && g->values &&
              g->minv && g->maxv && g->mats && g->last_mats;
    if (g->desc.deform == MR_DMM_DEFORM_BASE) {
        g->posed_pos = calloc(nv * 3, sizeof(float));
        g->posed_dir = calloc(nv * 3, sizeof(float));
        ok = ok && g->posed_pos && g->posed_dir;
    }
    if (tessellated(g)) {
        g->vertex_count = (uint32_t)values;
        g->triangle_count = g->micro_first[nt];
        g->positions = calloc((size_t)g->vertex_count * 3 + 1, sizeof(float));
        g->indices = malloc((size_t)g->triangle_count * 3 * sizeof(uint32_t));
        ok = ok && g->positions && g->indices;
    }
    if (!embree_triangles(g)) {
        g->boxes = calloc(nt * BOX_FLOATS, sizeof(float));
        ok = ok && g->boxes;
    }
    if (!tessellated(g) && g->desc.deform == MR_DMM_DEFORM_INTERPOLATED) {
        g->root_children = calloc(nt * MR_DMM_ROOT_CHILDREN_FLOATS, sizeof(float));
        ok = ok && g->root_children;
    }
    return ok ? MR_OK : mr_error_set(err, MR_ERR_NOMEM, "out of memory for a dmm object");
}

/* The bake's report (dmm_bake.h step 6) over the asset's meshes, in the
 * units of DMM_STATS: distances as fractions of the rest-pose
 * bounding-box diagonal of the asset's meshes (the space the bake works
 * in), unmatched micro-vertices as % of all. */
static void bake_quality(dmm_level *g)
{
    double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    double sum2 = 0, worst = 0, samples = 0, unmatched = 0, vertices = 0;
    for (size_t i = 0; i < g->asset->mesh_count; i++) {
        const mr_mesh *m = &g->asset->meshes[i];
        for (size_t v = 0; v < (size_t)m->vertex_count * 3; v++) {
            lo[v % 3] = fmin(lo[v % 3], m->positions[v]);
            hi[v % 3] = fmax(hi[v % 3], m->positions[v]);
        }
        const mr_dmm_bake *b = g->bakes[i];
        if (!b)
            continue;
        sum2 += b->rms_distance * b->rms_distance * (double)b->sample_count;
        samples += (double)b->sample_count;
        worst = fmax(worst, b->max_distance);
        unmatched += (double)b->fallback_count;
        for (uint32_t t = 0; t < b->base_triangle_count; t++)
            vertices += mr_umesh_vertex_count(mr_dmm_info_level(b->tri_info[t]));
    }
    double d2 = 0;
    for (int k = 0; k < 3; k++)
        d2 += (hi[k] - lo[k]) * (hi[k] - lo[k]);
    double diag = sqrt(d2) > 0 ? sqrt(d2) : 1.0;
    g->bake_quality[0] = samples > 0 ? sqrt(sum2 / samples) / diag : 0;
    g->bake_quality[1] = worst / diag;
    g->bake_quality[2] = vertices > 0 ? 100.0 * unmatched / vertices : 0;
}

/* ---- normals "smooth" ----
 * A DMM stores no normals: shaded by its micro-triangles' own, it shows
 * their facets, and the finer the level the more exactly it shows the
 * detailed mesh's facets rather than the smooth surface the detailed
 * mesh's own interpolated normals describe (bench_dmm: against those, flat
 * normals are best at the level matching the detail's density and worse
 * above it). Smooth normals are made at the detail's scale instead: on
 * each base triangle a coarse lattice at the sublevel whose triangles
 * match the detailed mesh's mean triangle area (per mesh, at most the
 * triangle's level), each coarse vertex gets the area-weighted normal of
 * the micro-surface in its coarse one-ring (every surviving micro-triangle's
 * cross product added to the corners of the coarse sub-triangle holding
 * it), in the rest pose, once at create; coarse vertices on shared base
 * edges and corners are one vertex for all the triangles around them, so
 * the normals are continuous across base edges. A hit interpolates its
 * coarse sub-triangle's three normals barycentrically and moves the result
 * by the cofactor of the interpolated matrix at the hit (as "matrix"). The
 * finer the level, the closer the coarse normals are to the detailed
 * surface's own area-weighted normals at that scale. */

typedef struct coarse_key {
    uint32_t kind, x, y, z; /* 0: base vertex x; 1: edge (x < y) at q = z/32 from x;
                               2: interior (a, b) = (y, z) of triangle x */
    uint32_t slot;          /* into coarse_id */
} coarse_key;

static int coarse_key_cmp(const void *pa, const void *pb)
{
    const coarse_key *a = pa, *b = pb;
    if (a->kind != b->kind)
        return a->kind < b->kind ? -1 : 1;
    if (a->x != b->x)
        return a->x < b->x ? -1 : 1;
    if (a->y != b->y)
        return a->y < b->y ? -1 : 1;
    if (a->z != b->z)
        return a->z < b->z ? -1 : 1;
    return 0;
}

/* The key of coarse lattice vertex (a, b) at sublevel s of base triangle t. */
static coarse_key coarse_key_of(const dmm_level *g, uint32_t t, unsigned s, uint32_t a, uint32_t b)
{
    const uint32_t *idx = g->base_indices + (size_t)t * 3;
    uint32_t k;
    int e = mr_umesh_vertex_edge(s, a, b, &k);
    if (e == 3)
        return (coarse_key){0, idx[k], 0, 0, 0};
    if (e >= 0) {
        uint32_t u = idx[e], w = idx[(e + 1) % 3], q = k << (MR_UMESH_MAX_LEVEL - s);
        uint32_t full = 1u << MR_UMESH_MAX_LEVEL;
        return u < w ? (coarse_key){1, u, w, q, 0} : (coarse_key){1, w, u, full - q, 0};
    }
    return (coarse_key){2, t, a, b, 0};
}

/* Barycentric weights of base-domain (u, v) in the sublevel-s lattice
 * triangle (a[k], b[k]). */
static void lattice_weights(unsigned s, float u, float v, const uint32_t a[3], const uint32_t b[3],
                            float w[3])
{
    float n = (float)mr_umesh_segments(s);
    float x = u * n - (float)a[0], y = v * n - (float)b[0];
    float d1x = (float)a[1] - (float)a[0], d1y = (float)b[1] - (float)b[0];
    float d2x = (float)a[2] - (float)a[0], d2y = (float)b[2] - (float)b[0];
    float det = d1x * d2y - d1y * d2x;
    w[1] = (x * d2y - y * d2x) / det;
    w[2] = (d1x * y - d1y * x) / det;
    w[0] = 1.0f - w[1] - w[2];
}

static mr_dmm_patch patch_of(const dmm_level *g, uint32_t t);

/* The base triangle t as a rest-pose patch. */
static mr_dmm_patch rest_patch(const dmm_level *g, uint32_t t)
{
    mr_dmm_patch p = patch_of(g, t);
    const uint32_t *idx = g->base_indices + (size_t)t * 3;
    for (int k = 0; k < 3; k++) {
        p.tri.pos[k] = mr_v3(g->rest_pos[idx[k] * 3], g->rest_pos[idx[k] * 3 + 1],
                             g->rest_pos[idx[k] * 3 + 2]);
        p.tri.dir[k] = mr_v3(g->rest_dir[idx[k] * 3], g->rest_dir[idx[k] * 3 + 1],
                             g->rest_dir[idx[k] * 3 + 2]);
        p.mats[k] = NULL;
    }
    p.stamp = 0; /* not this evaluation's data: no kept micro-vertices or boxes */
    p.root_children = NULL;
    return p;
}

static double tri_area(const float *pos, const uint32_t *ix)
{
    mr_vec3 p0 = mr_v3(pos[ix[0] * 3], pos[ix[0] * 3 + 1], pos[ix[0] * 3 + 2]);
    mr_vec3 p1 = mr_v3(pos[ix[1] * 3], pos[ix[1] * 3 + 1], pos[ix[1] * 3 + 2]);
    mr_vec3 p2 = mr_v3(pos[ix[2] * 3], pos[ix[2] * 3 + 1], pos[ix[2] * 3 + 2]);
    return 0.5 * (double)mr_v3_len(mr_v3_cross(mr_v3_sub(p1, p0), mr_v3_sub(p2, p0)));
}

static int smooth_normals_build(dmm_level *g, mr_error *err)
{
    size_t nt = g->base_triangle_count, meshes = g->asset->mesh_count;
    int rc = MR_OK;
    double *base_area = calloc(meshes, sizeof(double)), *acc = NULL;
    uint32_t *base_count = calloc(meshes, sizeof(uint32_t));
    unsigned *mesh_level = calloc(meshes, sizeof(unsigned));
    coarse_key *keys = NULL;
    mr_vec3 *pts = malloc(mr_umesh_vertex_count(MR_UMESH_MAX_LEVEL) * sizeof(mr_vec3));
    g->coarse_level = malloc(nt);
    g->coarse_first = malloc((nt + 1) * sizeof(uint32_t));
    if (!base_area || !base_count || !mesh_level || !pts || !g->coarse_level || !g->coarse_first)
        goto nomem;
    /* the coarse sublevel: micro-triangles of the detail's mean area */
    for (size_t t = 0; t < nt; t++) {
        base_area[g->tri_mesh[t]] += tri_area(g->rest_pos, g->base_indices + t * 3);
        base_count[g->tri_mesh[t]]++;
    }
    for (size_t i = 0; i < meshes; i++) {
        const mr_mesh *m = &g->asset->meshes[i];
        double detail = 0;
        for (size_t k = 0; k < m->triangle_count; k++)
            detail += tri_area(m->positions, m->indices + 3 * k);
        double ratio = base_count[i] && detail > 0
                           ? (base_area[i] / base_count[i]) / (detail / m->triangle_count)
                           : 1.0;
        double l = ratio > 1 ? nearbyint(0.5 * log2(ratio)) : 0;
        mesh_level[i] = (unsigned)fmin(fmax(l, 0), MR_UMESH_MAX_LEVEL);
    }
    uint64_t total = 0;
    for (size_t t = 0; t < nt; t++) {
        unsigned level = mr_dmm_info_level(g->tri_info[t]);
        unsigned want = mesh_level[g->tri_mesh[t]];
        g->coarse_level[t] = (uint8_t)(want < level ? want : level);
        g->coarse_first[t] = (uint32_t)total;
        total += mr_umesh_vertex_count(g->coarse_level[t]);
    }
    g->coarse_first[nt] = (uint32_t)total;
    keys = malloc(total * sizeof *keys);
    g->coarse_id = malloc(total * sizeof(uint32_t));
    if (!keys || !g->coarse_id)
        goto nomem;
    for (size_t t = 0; t < nt; t++) {
        unsigned s = g->coarse_level[t];
        for (uint32_t i = 0; i < mr_umesh_vertex_count(s); i++) {
            uint32_t a, b;
            mr_umesh_vertex_coords(s, i, &a, &b);
            coarse_key *k = &keys[g->coarse_first[t] + i];
            *k = coarse_key_of(g, (uint32_t)t, s, a, b);
            k->slot = g->coarse_first[t] + i;
        }
    }
    qsort(keys, total, sizeof *keys, coarse_key_cmp);
    uint32_t ids = 0;
    for (size_t i = 0; i < total; i++) {
        if (i > 0 && coarse_key_cmp(&keys[i - 1], &keys[i]) != 0)
            ids++;
        g->coarse_id[keys[i].slot] = ids;
    }
    ids = total ? ids + 1 : 0;
    g->smooth_count = ids;
    acc = calloc((size_t)ids * 3, sizeof(double));
    g->smooth_normals = malloc((size_t)ids * 3 * sizeof(float));
    if (!acc || !g->smooth_normals)
        goto nomem;
    /* every surviving micro-triangle's cross product to the corners of the
     * coarse sub-triangle holding it (rest pose, decoded displacements) */
    for (size_t t = 0; t < nt; t++) {
        mr_dmm_patch p = rest_patch(g, (uint32_t)t);
        unsigned level = p.level, s = g->coarse_level[t];
        uint32_t n = mr_umesh_segments(level), count;
        for (uint32_t b = 0; b <= n; b++)
            for (uint32_t a = 0; a + b <= n; a++)
                pts[mr_umesh_vertex_index(level, a, b)] = mr_dmm_vertex(&p, a, b);
        const uint32_t *tris = local_tris(g, (uint32_t)t, &count);
        for (uint32_t k = 0; k < count; k++) {
            const uint32_t *ix = tris + 3 * k;
            mr_vec3 c = mr_v3_cross(mr_v3_sub(pts[ix[1]], pts[ix[0]]), mr_v3_sub(pts[ix[2]], pts[ix[0]]));
            uint32_t sa = 0, sb = 0, ca[3], cb[3];
            for (int j = 0; j < 3; j++) {
                uint32_t a, b;
                mr_umesh_vertex_coords(level, ix[j], &a, &b);
                sa += a, sb += b;
            }
            mr_dmm_locate(s, 0, (float)sa / (3.0f * (float)n), (float)sb / (3.0f * (float)n), ca, cb);
            for (int j = 0; j < 3; j++) {
                double *dst = acc + 3 * (size_t)g->coarse_id[g->coarse_first[t] +
                                                            mr_umesh_vertex_index(s, ca[j], cb[j])];
                dst[0] += c.x, dst[1] += c.y, dst[2] += c.z;
            }
        }
    }
    for (size_t i = 0; i < ids; i++) {
        double *a = acc + 3 * i, len = sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
        for (int k = 0; k < 3; k++)
            g->smooth_normals[3 * i + k] = len > 0 ? (float)(a[k] / len) : 0.0f;
    }
    goto done;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for smooth dmm normals", g->asset->path);
done:
    free(base_area);
    free(base_count);
    free(mesh_level);
    free(keys);
    free(acc);
    free(pts);
    return rc;
}

static int level_create(const mr_asset *asset, const mr_object_desc *desc,
                        const mr_kind_context *ctx, dmm_level **out, mr_error *err)
{
    *out = NULL;
    if (!desc->params)
        return mr_error_set(err, MR_ERR_INVALID, "a dmm object needs its parameters");
    int rc = check_desc(desc->params, err);
    if (rc < 0)
        return rc;
    dmm_level *g = calloc(1, sizeof *g);
    if (!g)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory creating a dmm object");
    g->asset = asset;
    g->desc = *(const mr_dmm_params *)desc->params;
    unsigned level = g->desc.level;
    size_t meshes = asset->mesh_count ? asset->mesh_count : 1;
    g->bakes = calloc(meshes, sizeof *g->bakes);
    g->encoded = calloc(meshes, sizeof *g->encoded);
    g->mesh_first_base = calloc(meshes, sizeof(uint32_t));
    if (!g->bakes || !g->encoded || !g->mesh_first_base)
        goto nomem;

    mr_dmm_bake_params bp = mr_dmm_bake_params_default();
    bp.level = level;
    bp.adaptive = g->desc.levels == MR_DMM_LEVELS_ADAPTIVE;
    bp.target_triangles = g->desc.base_triangles;
    bp.target_ratio = g->desc.base_ratio;
    bp.threads = 0; /* the bake does not depend on it */
    /* bake and encode, or load both from the disk cache (dmm_file.h) */
    uint8_t bits[MR_UMESH_MAX_LEVEL + 1];
    mr_dmm_default_bits(bits);
    double bake_start = mr_now();
    if ((rc = mr_dmm_bake_cached(asset, &bp, bits, ctx ? ctx->cache_dir : NULL, g->bakes, g->encoded, NULL,
                                 err)) < 0)
        goto fail;
    g->bake_s = mr_now() - bake_start;
    uint64_t nv = 0, nt = 0;
    for (size_t i = 0; i < asset->mesh_count; i++) {
        if (!g->bakes[i])
            continue;
        g->mesh_first_base[i] = (uint32_t)nv;
        nv += g->bakes[i]->base_vertex_count;
        nt += g->bakes[i]->base_triangle_count;
        if (nv > MR_MAX_ASSET_VERTICES || nt > MR_DMM_MAX_TRIANGLES) {
            rc = mr_error_set(err, MR_ERR_LIMIT, "%s: %llu base triangles exceed the cap (%u)",
                              asset->path, (unsigned long long)nt, MR_DMM_MAX_TRIANGLES);
            goto fail;
        }
    }
    if (nt == 0) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: no triangles to render", asset->path);
        goto fail;
    }
    g->base_vertex_count = (uint32_t)nv;
    g->base_triangle_count = (uint32_t)nt;
    bake_quality(g);
    if ((rc = mr_umesh_topology_init(&g->topo, level, err)) < 0 || (rc = lay_out(g, err)) < 0 ||
        (rc = allocate(g, err)) < 0)
        goto fail;

    uint32_t t0 = 0;
    for (size_t i = 0; i < asset->mesh_count; i++) {
        const mr_dmm_bake *b = g->bakes[i];
        if (!b)
            continue;
        uint32_t v0 = g->mesh_first_base[i];
        for (uint64_t k = 0; k < (uint64_t)b->base_triangle_count * 3; k++)
            g->base_indices[(uint64_t)t0 * 3 + k] = b->base_indices[k] + v0;
        memcpy(g->rest_pos + (size_t)v0 * 3, b->base_positions,
               (size_t)b->base_vertex_count * 3 * sizeof(float));
        memcpy(g->rest_dir + (size_t)v0 * 3, b->base_directions,
               (size_t)b->base_vertex_count * 3 * sizeof(float));
        if ((rc = quantise(g, i, t0, err)) < 0)
            goto fail;
        t0 += b->base_triangle_count;
    }
    if (tessellated(g))
        fill_micro_indices(g, g->indices);
    if (g->desc.normals == MR_DMM_NORMALS_SMOOTH && (rc = smooth_normals_build(g, err)) < 0)
        goto fail;
    *out = g;
    return MR_OK;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for a dmm object", asset->path);
fail:
    level_free(g);
    return rc;
}

static mr_vec3 load3(const float *a, size_t i) { return mr_v3(a[i * 3], a[i * 3 + 1], a[i * 3 + 2]); }

/* Base triangle t as a traversal patch for this frame. */
static mr_dmm_patch patch_of(const dmm_level *g, uint32_t t)
{
    /* every field assigned, none zero-filled first: an initializer's fill
     * of the rest was a `rep stos`, a tenth of a callback's set-up */
    mr_dmm_patch p;
    p.level = mr_dmm_info_level(g->tri_info[t]);
    p.decimate = mr_dmm_info_decimate(g->tri_info[t]);
    p.enc = g->encoded[g->tri_mesh[t]];
    p.values = g->values + g->value_first[t];
    p.minv = g->minv + g->pyramid_first[t];
    p.maxv = g->maxv + g->pyramid_first[t];
    const uint32_t *idx = g->base_indices + (size_t)t * 3;
    bool interpolated = g->desc.deform == MR_DMM_DEFORM_INTERPOLATED;
    for (int k = 0; k < 3; k++) {
        if (interpolated) {
            p.tri.pos[k] = load3(g->rest_pos, idx[k]);
            p.tri.dir[k] = load3(g->rest_dir, idx[k]);
            p.mats[k] = &g->mats[idx[k]];
        } else {
            p.tri.pos[k] = load3(g->posed_pos, idx[k]);
            p.tri.dir[k] = load3(g->posed_dir, idx[k]);
            p.mats[k] = NULL;
        }
    }
    if (g->boxes && g->evaluated) {
        memcpy(p.pad, g->boxes + (size_t)t * BOX_FLOATS + 6, sizeof p.pad);
        p.stamp = g->stamp;
    } else {
        p.pad[0] = p.pad[1] = p.pad[2] = 0;
        p.stamp = 0;
    }
    p.root_children = g->root_children && g->evaluated && mr_dmm_trace_leaf_sublevel(p.level) > 0
                          ? g->root_children + (size_t)t * MR_DMM_ROOT_CHILDREN_FLOATS
                          : NULL;
    return p;
}

static bool finite_bounded(mr_vec3 v)
{
    return fabsf(v.x) <= MR_MAX_COORDINATE && fabsf(v.y) <= MR_MAX_COORDINATE &&
           fabsf(v.z) <= MR_MAX_COORDINATE;
}

/* Every micro-vertex of base triangle t (mr_dmm_vertex, the one evaluation
 * all modes share) into dst, 3 floats each in micromesh.h order (vertices a
 * decimated edge collapses are evaluated too; no surviving micro-triangle
 * uses them); false if one is not finite or beyond MR_MAX_COORDINATE. */
static bool eval_patch_vertices(const mr_dmm_patch *pp, float *dst)
{
    mr_dmm_patch p = *pp;
    uint32_t n = mr_umesh_segments(p.level);
    bool ok = true;
    for (uint32_t b = 0; b <= n; b++)
        for (uint32_t a = 0; a + b <= n; a++) {
            mr_vec3 v = mr_dmm_vertex(&p, a, b);
            ok = ok && finite_bounded(v);
            float *o = dst + (size_t)mr_umesh_vertex_index(p.level, a, b) * 3;
            o[0] = v.x, o[1] = v.y, o[2] = v.z;
        }
    return ok;
}

static bool eval_micro_vertices(const dmm_level *g, uint32_t t, float *dst)
{
    mr_dmm_patch p = patch_of(g, t);
    return eval_patch_vertices(&p, dst);
}

typedef struct update_ctx {
    dmm_level *g;
    uint32_t bad[MR_MAX_THREADS]; /* per worker: first failing base triangle + 1, or 0 */
    uint32_t outside[MR_MAX_THREADS]; /* the same for a micro-vertex outside its box */
} update_ctx;

/* The watertight reference tests micro-triangles only inside the boxes the
 * tessellation-free modes trace (their Embree BVHs are then the same): it
 * checks that those boxes hold every micro-vertex, so a box that cut one
 * off is an error, not a hole both renders share. */
static bool box_holds(const float *box, const float *v, uint32_t count)
{
    for (uint32_t i = 0; i < count; i++)
        for (int k = 0; k < 3; k++)
            if (!(v[3 * i + k] >= box[k] && v[3 * i + k] <= box[3 + k]))
                return false;
    return true;
}

static void note_bad(update_ctx *c, unsigned worker, size_t t)
{
    if (c->bad[worker] == 0)
        c->bad[worker] = (uint32_t)t + 1;
}

static void update_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    update_ctx *c = ctx;
    dmm_level *g = c->g;
    const bool own_boxes = g->boxes && !g->boxes_given;
    for (size_t t = begin; t < end; t++) {
        if (g->boxes_given && g->boxes) {
            const float *b = g->boxes + t * BOX_FLOATS;
            if (!finite_bounded(mr_v3(b[0], b[1], b[2])) || !finite_bounded(mr_v3(b[3], b[4], b[5])))
                note_bad(c, worker, t);
        }
        if (own_boxes || g->root_children) { /* (a tessellation needs no patch) */
            mr_dmm_patch p = patch_of(g, (uint32_t)t);
            if (own_boxes) {
                /* the pad once: the bounds use it, and it is cached for the rays */
                float *b = g->boxes + t * BOX_FLOATS;
                mr_dmm_patch_pad(&p, p.pad);
                memcpy(b + 6, p.pad, sizeof p.pad);
                mr_vec3 lo, hi;
                if (!mr_dmm_patch_bounds(&p, &lo, &hi) || !finite_bounded(lo) || !finite_bounded(hi))
                    note_bad(c, worker, t);
                b[0] = lo.x, b[1] = lo.y, b[2] = lo.z, b[3] = hi.x, b[4] = hi.y, b[5] = hi.z;
            }
            /* the root's children with every evaluation, given boxes or
             * not: levels of detail give the baked level's boxes, and the
             * children are this evaluation's level's */
            if (g->root_children)
                mr_dmm_patch_root_children(&p, g->root_children + t * MR_DMM_ROOT_CHILDREN_FLOATS);
        }
        if (!tessellated(g))
            continue;
        float *v = g->positions + (size_t)g->value_first[t] * 3;
        if (!eval_micro_vertices(g, (uint32_t)t, v))
            note_bad(c, worker, t);
        else if (watertight_reference(g) &&
                 !box_holds(g->boxes + t * BOX_FLOATS, v,
                            mr_umesh_vertex_count(mr_dmm_info_level(g->tri_info[t]))) &&
                 c->outside[worker] == 0)
            c->outside[worker] = (uint32_t)t + 1;
    }
}

/* Mode base: v' = M v, n' = M n (eq. 4), per base vertex. */
static void pose_base_vertices(dmm_level *g)
{
    for (size_t i = 0; i < g->base_vertex_count; i++) {
        const float *m = g->mats[i].m, *v = g->rest_pos + i * 3, *d = g->rest_dir + i * 3;
        for (int r = 0; r < 3; r++) {
            g->posed_pos[i * 3 + r] = m[r * 4] * v[0] + m[r * 4 + 1] * v[1] +
                                      m[r * 4 + 2] * v[2] + m[r * 4 + 3];
            g->posed_dir[i * 3 + r] = m[r * 4] * d[0] + m[r * 4 + 1] * d[1] + m[r * 4 + 2] * d[2];
        }
    }
}

/* The frame's accumulated matrix of every base vertex (a one-mesh view of
 * the asset whose vertices are the base vertices with their own weights,
 * which the bake kept) and, mode base, the skinned base vertices. *moved:
 * whether they differ from the last evaluated frame's (static objects, and
 * frames where nothing moved, keep their data). */
static int level_pose(dmm_level *g, const mr_pose *pose, const mr_mat4 *transform, unsigned threads,
                      bool *moved, mr_error *err)
{
    for (size_t i = 0; i < g->asset->mesh_count; i++) {
        const mr_dmm_bake *b = g->bakes[i];
        if (!b)
            continue;
        mr_mesh m = g->asset->meshes[i];
        m.vertex_count = b->base_vertex_count;
        m.triangle_count = b->base_triangle_count;
        m.positions = b->base_positions;
        m.normals = b->base_directions;
        m.uvs = NULL;
        m.tangents = NULL; /* the asset's vertices', not the base's */
        m.indices = b->base_indices;
        m.joints = b->joints;
        m.weights = b->weights;
        if (!b->joints || !b->weights) {
            m.joint_count = 0;
            m.joint_nodes = NULL;
            m.inverse_bind = NULL;
            m.joints = NULL;
            m.weights = NULL;
        }
        mr_asset view = *g->asset;
        view.mesh_count = 1;
        view.meshes = &m;
        mr_skin_matrices(&view, 0, pose, transform, g->mats + g->mesh_first_base[i], threads);
    }
    size_t nb = (size_t)g->base_vertex_count * sizeof(mr_affine);
    *moved = !(g->evaluated && memcmp(g->mats, g->last_mats, nb) == 0);
    if (!*moved)
        return MR_OK;
    g->evaluated = false;
    for (size_t k = 0; k < (size_t)g->base_vertex_count * 12; k++)
        if (!isfinite(g->mats[k / 12].m[k % 12]))
            return mr_error_set(err, MR_ERR_INVALID,
                                "%s: the skinning matrix of base vertex %zu is not finite: check "
                                "the object's transform and pose",
                                g->asset->path, k / 12);
    if (g->posed_pos)
        pose_base_vertices(g);
    return MR_OK;
}

/* Every base triangle's box (and, tessellated, micro-vertices) for the
 * posed base vertices. */
static int level_evaluate(dmm_level *g, unsigned threads, mr_error *err)
{
    update_ctx *c = calloc(1, sizeof *c);
    if (!c)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory updating a dmm object");
    c->g = g;
    mr_parallel_for(threads, g->base_triangle_count, UPDATE_GRAIN, update_range, c);
    uint32_t bad = 0, outside = 0;
    for (unsigned w = 0; w < MR_MAX_THREADS; w++) {
        if (c->bad[w] && (bad == 0 || c->bad[w] < bad))
            bad = c->bad[w];
        if (c->outside[w] && (outside == 0 || c->outside[w] < outside))
            outside = c->outside[w];
    }
    free(c);
    if (bad)
        return mr_error_set(err, MR_ERR_INVALID,
                            "%s: base triangle %u is not finite or beyond %g after posing: check "
                            "the object's transform and pose",
                            g->asset->path, bad - 1, MR_MAX_COORDINATE);
    if (outside)
        return mr_error_set(err, MR_ERR_INVALID,
                            "%s: base triangle %u has a micro-vertex outside the box the "
                            "tessellation-free traversal bounds it by (a bug in its bounds)",
                            g->asset->path, outside - 1);
    memcpy(g->last_mats, g->mats, (size_t)g->base_vertex_count * sizeof(mr_affine));
    g->evaluated = true;
    /* levels of detail lay the values out anew between evaluations: no
     * micro-vertex kept across calls there */
    g->stamp = g->boxes_given ? 0 : mr_dmm_stamp();
    return MR_OK;
}

static int level_update(dmm_level *g, const mr_pose *pose, const mr_mat4 *transform, unsigned threads,
                        mr_error *err)
{
    bool moved;
    int rc = level_pose(g, pose, transform, threads, &moved, err);
    return rc < 0 || !moved ? rc : level_evaluate(g, threads, err);
}

/* Embree user-geometry callbacks (tessellation-free modes and the
 * watertight reference: one primitive per base triangle, its box). */

static void bounds_cb(const struct RTCBoundsFunctionArguments *args)
{
    const dmm_level *g = args->geometryUserPtr;
    const float *b = g->boxes + (size_t)args->primID * BOX_FLOATS;
    struct RTCBounds *o = args->bounds_o;
    o->lower_x = b[0], o->lower_y = b[1], o->lower_z = b[2];
    o->upper_x = b[3], o->upper_y = b[4], o->upper_z = b[5];
}

/* Ray i of an N-packet set up for the traversal (user_rays.h). */
MR_RAY_SETUP_CACHE_REF(ray_setup_kept, mr_dmm_ray, mr_dmm_ray_setup)

/* The lanes of an N-packet a callback for base triangle t traces: the
 * valid ones whose ray can meet t's box (mr_rays_in_box: three in four of
 * the rays Embree hands the dancer's base triangles at level 2 miss it,
 * and their set-up and first slab tests were a fifth of the trace), or
 * every valid one for the watertight reference, which stays the plain
 * test of every micro-triangle. */
static uint32_t lanes_to_trace(const dmm_level *g, void *ray, unsigned N, const int *valid,
                               uint32_t t)
{
    if (watertight_reference(g))
        return mr_valid_lanes(N, valid);
    const float *box = g->boxes + (size_t)t * BOX_FLOATS;
    return mr_rays_in_box(ray, N, valid, box, box + 3);
}

/* Traces ray i of an N-packet against base triangle t (patch p): the
 * traversal, or the watertight reference's test of every micro-triangle;
 * tfar shrinks on a hit. take_tmax: see mr_dmm_intersect. */
static bool trace_one(const dmm_level *g, uint32_t t, const mr_dmm_patch *p, void *ray, unsigned N,
                      unsigned i, bool take_tmax, bool any_hit, mr_dmm_hit *h)
{
    const mr_dmm_ray *r = ray_setup_kept(ray, N, i);
    if (!r)
        return false;
    float *tfar = mr_ray_f(ray, N, MR_RAY_TFAR, i);
    float tnear = *mr_ray_f(ray, N, MR_RAY_TNEAR, i);
    if (watertight_reference(g)) {
        uint32_t count;
        const uint32_t *tris = local_tris(g, t, &count);
        return mr_dmm_intersect_micro(p, g->positions + (size_t)g->value_first[t] * 3, tris, count,
                                      r, tnear, tfar, take_tmax, any_hit, h);
    }
    return mr_dmm_intersect(p, r, tnear, tfar, take_tmax, any_hit, h, NULL);
}

/* Up to MR_DMM_PACKET_MAX of a packet's rays through one patch together
 * (mr_dmm_intersect_packet). Their set-ups are the thread's kept ones
 * (ray_setup_kept: each lane's stays put through the callback), read in
 * place rather than copied, 112 bytes a ray and base triangle. */
typedef struct ray_batch {
    int n;
    unsigned lane[MR_DMM_PACKET_MAX];
    const mr_dmm_ray *r[MR_DMM_PACKET_MAX];
    float tmin[MR_DMM_PACKET_MAX], *tmax[MR_DMM_PACKET_MAX];
    bool take_tmax[MR_DMM_PACKET_MAX];
} ray_batch;

static void trace_batch(const struct RTCIntersectFunctionNArguments *args,
                        const mr_dmm_patch *p, ray_batch *b)
{
    mr_dmm_hit hits[MR_DMM_PACKET_MAX];
    uint32_t hm = mr_dmm_intersect_packet(p, b->n, b->r, b->tmin, b->tmax, b->take_tmax, false,
                                          hits, NULL);
    for (int k = 0; k < b->n; k++)
        if (hm >> k & 1u)
            mr_ray_write_hit(args, b->lane[k], hits[k].ng, hits[k].u, hits[k].v);
    b->n = 0;
}

static void intersect_cb(const struct RTCIntersectFunctionNArguments *args)
{
    const dmm_level *g = args->geometryUserPtr;
    unsigned N = args->N;
    void *ray = args->rayhit, *hit = (float *)args->rayhit + MR_RAY_FIELDS * N;
    const uint32_t lanes = lanes_to_trace(g, ray, N, args->valid, args->primID);
    if (!lanes)
        return;
    mr_dmm_patch p = patch_of(g, args->primID);
    ray_batch b;
    b.n = 0;
    for (unsigned i = 0; i < N; i++) {
        mr_dmm_hit h;
        if (!(lanes >> i & 1u))
            continue;
        /* A hit at exactly the ray's tfar beats the one held there when
         * that is none, or one of this object's base triangles with a
         * larger index: every mode orders equal-t hits by (base triangle,
         * micro-triangle), whatever order Embree visits them in. */
        unsigned held = *mr_ray_u(hit, N, MR_HIT_GEOM, i);
        bool take_tmax = held == RTC_INVALID_GEOMETRY_ID ||
                         (held == args->geomID &&
                          *mr_ray_u(hit, N, MR_HIT_INST, i) == args->context->instID[0] &&
                          args->primID < *mr_ray_u(hit, N, MR_HIT_PRIM, i));
        if (watertight_reference(g)) {
            if (trace_one(g, args->primID, &p, ray, N, i, take_tmax, false, &h))
                mr_ray_write_hit(args, i, h.ng, h.u, h.v);
            continue;
        }
        /* the traversal: the packet's rays together */
        if (!(b.r[b.n] = ray_setup_kept(ray, N, i)))
            continue;
        b.lane[b.n] = i;
        b.tmin[b.n] = *mr_ray_f(ray, N, MR_RAY_TNEAR, i);
        b.tmax[b.n] = mr_ray_f(ray, N, MR_RAY_TFAR, i);
        b.take_tmax[b.n] = take_tmax;
        if (++b.n == MR_DMM_PACKET_MAX)
            trace_batch(args, &p, &b);
    }
    if (b.n)
        trace_batch(args, &p, &b);
}

static void occluded_cb(const struct RTCOccludedFunctionNArguments *args)
{
    const dmm_level *g = args->geometryUserPtr;
    unsigned N = args->N;
    const uint32_t lanes = lanes_to_trace(g, args->ray, N, args->valid, args->primID);
    if (!lanes)
        return;
    mr_dmm_patch p = patch_of(g, args->primID);
    if (watertight_reference(g) || N == 1) {
        for (unsigned i = 0; i < N; i++)
            if ((lanes >> i & 1u) &&
                trace_one(g, args->primID, &p, args->ray, N, i, true, true, NULL))
                *mr_ray_f(args->ray, N, MR_RAY_TFAR, i) = -INFINITY;
        return;
    }
    /* a packet of shadow rays through the patch together, each stopping at
     * its first hit */
    ray_batch b;
    b.n = 0;
    for (unsigned i = 0; i <= N; i++) {
        if (i < N && (lanes >> i & 1u) && (b.r[b.n] = ray_setup_kept(args->ray, N, i))) {
            b.lane[b.n] = i;
            b.tmin[b.n] = *mr_ray_f(args->ray, N, MR_RAY_TNEAR, i);
            b.tmax[b.n] = mr_ray_f(args->ray, N, MR_RAY_TFAR, i);
            b.take_tmax[b.n] = true;
            b.n++;
        }
        if (b.n == MR_DMM_PACKET_MAX || (i == N && b.n)) {
            uint32_t hm = mr_dmm_intersect_packet(&p, b.n, b.r, b.tmin, b.tmax, b.take_tmax, true,
                                                  NULL, NULL);
            for (int k = 0; k < b.n; k++)
                if (hm >> k & 1u)
                    *b.tmax[k] = -INFINITY;
            b.n = 0;
        }
    }
}

static int level_attach(dmm_level *g, RTCDevice device, RTCScene scene, unsigned geom_id,
                        enum RTCBuildQuality quality, mr_error *err)
{
    if (embree_triangles(g))
        return mr_geom_attach_triangles(device, scene, geom_id, quality, g->positions,
                                        g->vertex_count, g->indices, g->triangle_count, &g->rtc,
                                        err);
    return mr_geom_attach_user(device, scene, geom_id, quality, g->base_triangle_count, g, bounds_cb,
                               intersect_cb, occluded_cb, "dmm", &g->rtc, err);
}

static void level_commit(dmm_level *g)
{
    if (embree_triangles(g) && g->relaid) {
        rtcSetSharedGeometryBuffer(g->rtc, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                   g->positions, 0, 3 * sizeof(float), g->vertex_count);
        rtcSetSharedGeometryBuffer(g->rtc, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, g->indices,
                                   0, 3 * sizeof(uint32_t), g->triangle_count);
        rtcCommitGeometry(g->rtc);
    } else if (embree_triangles(g))
        mr_geom_commit_vertices(g->rtc);
    else
        rtcCommitGeometry(g->rtc);
    g->relaid = false;
}

/* Base triangle and base-domain (u, v) of a hit. */
static uint32_t hit_domain(const dmm_level *g, unsigned prim, float *u, float *v)
{
    if (!embree_triangles(g))
        return prim;
    if (prim >= g->micro_first[g->base_triangle_count])
        return UINT32_MAX;
    /* the base triangle whose micro-triangle range holds prim */
    uint32_t lo = 0, hi = g->base_triangle_count;
    while (hi - lo > 1) {
        uint32_t mid = lo + (hi - lo) / 2;
        if (g->micro_first[mid] <= prim)
            lo = mid;
        else
            hi = mid;
    }
    uint32_t t = lo, count, a[3], b[3];
    unsigned level = mr_dmm_info_level(g->tri_info[t]);
    const uint32_t *idx = local_tris(g, t, &count) + 3 * (size_t)(prim - g->micro_first[t]);
    for (int k = 0; k < 3; k++)
        mr_umesh_vertex_coords(level, idx[k], &a[k], &b[k]);
    float w0 = 1.0f - *u - *v, n = (float)mr_umesh_segments(level);
    float bu = (w0 * (float)a[0] + *u * (float)a[1] + *v * (float)a[2]) / n;
    float bv = (w0 * (float)b[0] + *u * (float)b[1] + *v * (float)b[2]) / n;
    *u = bu, *v = bv;
    return t;
}

/* The cofactor of the barycentric blend of base triangle t's corner
 * matrices at base-domain (u, v): what moves a rest-pose normal there. */
static mr_mat4 normal_matrix_at(const dmm_level *g, uint32_t t, float u, float v)
{
    const uint32_t *idx = g->base_indices + (size_t)t * 3;
    float w[3] = {1.0f - u - v, u, v};
    mr_mat4 m = mr_mat4_identity();
    for (int e = 0; e < 12; e++)
        m.m[e] = w[0] * g->mats[idx[0]].m[e] + w[1] * g->mats[idx[1]].m[e] +
                 w[2] * g->mats[idx[2]].m[e];
    return mr_mat4_normal_matrix(&m);
}

/* The sublevel smooth normals are interpolated at on base triangle t when
 * it traces level `level`: its coarse sublevel, or the level itself where
 * a level of detail traces it coarser (the normals then vary no finer than
 * the surface does). */
static unsigned smooth_sublevel(const dmm_level *g, uint32_t t, unsigned level)
{
    return g->coarse_level[t] < level ? g->coarse_level[t] : level;
}

/* Normals "smooth" at base-domain (u, v) of base triangle t, rest pose:
 * the sub-triangle of sublevel s (smooth_sublevel) holding it (lattice
 * (a[k], b[k])), the normals n[k] of its corners, and their interpolation
 * *out. */
static void smooth_rest_normal(const dmm_level *g, uint32_t t, unsigned s, float u, float v,
                               uint32_t a[3], uint32_t b[3], mr_vec3 n[3], mr_vec3 *out)
{
    unsigned coarse = g->coarse_level[t], up = coarse - s;
    float w[3];
    mr_dmm_locate(s, 0, u, v, a, b);
    lattice_weights(s, u, v, a, b, w);
    *out = mr_v3(0, 0, 0);
    for (int k = 0; k < 3; k++) {
        const float *x = g->smooth_normals +
                         3 * (size_t)g->coarse_id[g->coarse_first[t] +
                                                  mr_umesh_vertex_index(coarse, a[k] << up, b[k] << up)];
        n[k] = mr_v3(x[0], x[1], x[2]);
        *out = mr_v3_add(*out, mr_v3_scale(n[k], w[k]));
    }
}

static mr_vec3 level_normal(const dmm_level *g, unsigned prim, float u, float v)
{
    uint32_t t = hit_domain(g, prim, &u, &v);
    if (t >= g->base_triangle_count)
        return mr_v3(0, 0, 1);
    mr_dmm_patch p = patch_of(g, t);
    uint32_t a[3], b[3];
    if (g->desc.normals == MR_DMM_NORMALS_SMOOTH) {
        mr_vec3 n[3], rest;
        smooth_rest_normal(g, t, smooth_sublevel(g, t, p.level), u, v, a, b, n, &rest);
        mr_mat4 cof = normal_matrix_at(g, t, u, v);
        return mr_mat4_dir(&cof, rest);
    }
    mr_dmm_locate(p.level, p.decimate, u, v, a, b);
    if (g->desc.normals == MR_DMM_NORMALS_GEOMETRIC) {
        mr_vec3 x[3];
        for (int k = 0; k < 3; k++)
            x[k] = mr_dmm_vertex(&p, a[k], b[k]);
        return mr_v3_cross(mr_v3_sub(x[1], x[0]), mr_v3_sub(x[2], x[0]));
    }
    /* Interpolated-matrix normal: the rest micro-triangle's normal through
     * the cofactor of M(u, v). */
    mr_dmm_patch rest = rest_patch(g, t);
    mr_vec3 x[3];
    for (int k = 0; k < 3; k++)
        x[k] = mr_dmm_vertex(&rest, a[k], b[k]);
    mr_vec3 n = mr_v3_cross(mr_v3_sub(x[1], x[0]), mr_v3_sub(x[2], x[0]));
    mr_mat4 cof = normal_matrix_at(g, t, u, v);
    return mr_mat4_dir(&cof, n);
}

/* Normals "smooth": the hit lifted onto the surface they describe, as the
 * mesh kind does for its vertex normals (kind.h shading_point; Hanika
 * 2021), with the coarse sub-triangle's posed corners and their normals:
 * the micro-surface's own bumps keep shadowing each other, the facets of
 * the coarse lattice do not. */
static bool level_shading_point(const dmm_level *g, unsigned prim, float u, float v, mr_vec3 p,
                                mr_vec3 *out)
{
    if (g->desc.normals != MR_DMM_NORMALS_SMOOTH)
        return false;
    uint32_t t = hit_domain(g, prim, &u, &v);
    if (t >= g->base_triangle_count)
        return false;
    mr_dmm_patch patch = patch_of(g, t);
    uint32_t a[3], b[3];
    mr_vec3 n[3], rest;
    unsigned s = smooth_sublevel(g, t, patch.level), shift = patch.level - s;
    smooth_rest_normal(g, t, s, u, v, a, b, n, &rest);
    float w[3];
    lattice_weights(s, u, v, a, b, w);
    mr_mat4 cof = normal_matrix_at(g, t, u, v);
    *out = p;
    for (int k = 0; k < 3; k++) {
        mr_vec3 x = mr_dmm_vertex(&patch, a[k] << shift, b[k] << shift);
        mr_vec3 nk = mr_v3_normalize_or(mr_mat4_dir(&cof, n[k]), mr_v3(0, 0, 0));
        float depth = mr_v3_dot(mr_v3_sub(p, x), nk);
        if (depth < 0)
            *out = mr_v3_add(*out, mr_v3_scale(nk, -depth * w[k]));
    }
    return true;
}

/* The micro-triangles, posed (this frame's) or in the rest pose. */
static int micro_triangles(const dmm_level *g, bool rest, mr_trimesh *out, mr_error *err)
{
    if (tessellated(g) && !rest)
        return mr_trimesh_copy(g->positions, g->vertex_count, g->indices, g->triangle_count, out,
                               err);
    /* The exact reference of a tessellation-free object: its micro-triangles
     * from the same mr_dmm_vertex, one vertex set per base triangle. */
    memset(out, 0, sizeof *out);
    uint64_t nv = g->value_first[g->base_triangle_count];
    uint64_t nt = g->micro_first[g->base_triangle_count];
    out->positions = calloc(nv * 3 + 1, sizeof(float)); /* a coarser level leaves gaps */
    out->indices = malloc(nt * 3 * sizeof(uint32_t));
    if (!out->positions || !out->indices) {
        mr_trimesh_free(out);
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory tessellating a dmm object");
    }
    fill_micro_indices(g, out->indices);
    /* update() already refused frames with non-finite micro-vertices (the
     * rest pose is the bake's, finite) */
    for (uint32_t t = 0; t < g->base_triangle_count; t++) {
        mr_dmm_patch p = rest ? rest_patch(g, t) : patch_of(g, t);
        eval_patch_vertices(&p, out->positions + (size_t)g->value_first[t] * 3);
    }
    out->vertex_count = (uint32_t)nv;
    out->triangle_count = (uint32_t)nt;
    return MR_OK;
}

static int level_tessellate(const dmm_level *g, mr_trimesh *out, mr_error *err)
{
    return micro_triangles(g, false, out, err);
}

static size_t level_memory(const dmm_level *g)
{
    size_t nv = g->base_vertex_count, nt = g->base_triangle_count;
    size_t bytes = sizeof *g + g->asset->mesh_count * (2 * sizeof(void *) + sizeof(uint32_t));
    for (size_t i = 0; i < g->asset->mesh_count; i++)
        if (g->bakes[i])
            bytes += mr_dmm_bake_memory(g->bakes[i]);
    bytes += g->encoded_bytes;
    bytes += nt * 4 * sizeof(uint32_t);                                 /* indices, tri_mesh */
    bytes += nt * (1 + 3 * sizeof(uint32_t));                           /* tri_info, offsets */
    bytes += nv * 6 * sizeof(float) + nv * 2 * sizeof(mr_affine);      /* rest, mats */
    bytes += ((size_t)g->value_first[nt] + 2 * (size_t)g->pyramid_first[nt]) * sizeof(uint16_t);
    if (g->posed_pos)
        bytes += nv * 6 * sizeof(float);
    if (g->boxes)
        bytes += nt * BOX_FLOATS * sizeof(float);
    if (g->root_children)
        bytes += nt * MR_DMM_ROOT_CHILDREN_FLOATS * sizeof(float);
    if (g->positions)
        bytes += ((size_t)g->vertex_count * 3 + 1) * sizeof(float) +
                 (size_t)g->triangle_count * 3 * sizeof(uint32_t);
    if (g->coarse_first)
        bytes += nt * (1 + sizeof(uint32_t)) + sizeof(uint32_t) +
                 (size_t)g->coarse_first[nt] * sizeof(uint32_t) +
                 (size_t)g->smooth_count * 3 * sizeof(float);
    return bytes;
}

static uint64_t level_primitives(const dmm_level *g)
{
    return g->micro_first[g->base_triangle_count];
}

/* The bake's own quality (dmm_bake.h steps 5 and 6), the same every frame:
 * what a user reads to judge a level or base ratio before looking at
 * frames; its size; and (first frame) what making it took. */
enum { S_RMS, S_MAX, S_UNMATCHED, S_BASE, S_STORED, S_BAKE_S, S_LEVEL, S_LEVEL_MEAN, S_ERROR_PX,
       S_LOD_BYTES, S_LOD_BUILD_S, S_COUNT };
static const mr_kind_stat DMM_STATS[S_COUNT] = {
    {"dmm_bake_rms_distance", "diagonal",
     "RMS distance of the baked surface (its micro-vertices and micro-triangle centroids, rest "
     "pose) to the detailed mesh, as a fraction of the asset's rest-pose bounding-box diagonal",
     MR_STAT_MAX},
    {"dmm_bake_max_distance", "diagonal",
     "largest such distance, as a fraction of the same diagonal", MR_STAT_MAX},
    {"dmm_bake_unmatched_pct", "%",
     "micro-vertices whose displacement search found no detailed surface facing its way within "
     "its reach (their height came from the nearest detailed point), as % of all",
     MR_STAT_MAX},
    {"dmm_base_triangles", "count", "base triangles of the baked meshes", MR_STAT_SUM},
    {"dmm_stored_bytes", "bytes",
     "the encoded displacements as a file stores them: a level byte per base triangle and the "
     "records", MR_STAT_SUM},
    {"dmm_bake_s", "s",
     "baking and encoding at creation, or loading them from the derived-data cache",
     MR_STAT_ONCE},
    {"dmm_lod_level", "level",
     "the finest subdivision level traced (\"tolerance_px\": each base triangle at the coarsest "
     "within the tolerance, neighbours at most one apart; without one, the object's \"level\")",
     MR_STAT_MAX},
    {"dmm_lod_level_mean", "level",
     "the mean level over the base triangles (\"tolerance_px\"; without one, the object's "
     "\"level\")",
     MR_STAT_MAX},
    {"dmm_lod_error_px", "px",
     "the predicted error: the largest over the base triangles of its level's bound on its "
     "distance to the detailed mesh, projected at its nearest depth by this frame's camera (0 "
     "without a tolerance)",
     MR_STAT_MAX},
    {"dmm_lod_bytes", "bytes",
     "what the levels of detail hold: the baked layout while a frame traces another, the "
     "bounds, the edges (\"tolerance_px\"; 0 without)",
     MR_STAT_SUM},
    {"dmm_lod_build_s", "s",
     "measuring the bounds at creation (\"tolerance_px\")",
     MR_STAT_ONCE},
};

static void level_frame_stats(const dmm_level *g, double *values)
{
    memcpy(values, g->bake_quality, sizeof g->bake_quality);
    values[S_BASE] = g->base_triangle_count;
    values[S_STORED] = (double)g->encoded_bytes;
    values[S_BAKE_S] = g->bake_s;
}

/* ---- levels of detail ("tolerance_px", issue 16), per base triangle ----
 * An object with a tolerance is its one bake. Each frame every base
 * triangle t traces the coarsest level l <= its baked level L_t whose
 * bound, projected by the frame's camera at t's nearest depth and
 * stretched by the object's transform (kinds/lod.h), stays below the
 * tolerance; then the coarse side of every shared edge joining levels more
 * than one apart is raised and the finer side of every edge between levels
 * decimated (mr_umesh_balance), as in an adaptive bake, so the surface
 * stays watertight. A level-l surface is the encoding's own prefix
 * (dmm_lod.h): a triangle whose level changes gets its values subsampled
 * from the baked ones and its pyramid rebuilt, in the level's own arrays at
 * its baked offsets, and everything else (traversal, tessellation,
 * references) reads them as it reads a bake's.
 *
 * t's bound at level l is error[t][l] + fine[t]:
 *  - fine[t]: t's share of the baked surface's two-sided distance to the
 *    detailed mesh (dmm_lod.h: its own samples against the detail, and the
 *    detail's points whose nearest baked point is on t), measured at rest
 *    and in the poses of the object's clip (where a base triangle spans a
 *    joint, the interpolated matrices and the detail's own skinning part);
 *  - error[t][l]: how far t's level-l surface, under any decimation its
 *    shared edges allow, strays from its baked lattice at equal domain
 *    coordinates (mr_dmm_lod_coarsening, exact: not sampled), plus how far
 *    the baked surface's own decimation strays from that lattice, at rest
 *    and in the same poses; the largest over levels l..L_t, so raising a
 *    level never raises its bound. error_whole[t][l] is the same for
 *    level l alone without decimation: what a frame predicts for t when no
 *    edge of its is decimated.
 * By the triangle inequality a point of t's level-l surface is within the
 * sum of the detailed mesh, and a point of the detailed mesh within
 * fine[t'] of the baked surface of the triangle t' its nearest baked point
 * is on, and so within t''s sum of the traced one. t's nearest depth: its
 * box at its baked level (which holds every coarser surface: their
 * micro-vertices are its own) grown by its coarsest bound. A triangle that
 * no level fits with its edges decimated raises its neighbours to its level
 * (as far as theirs reach), so none of its edges is. The pick reads only
 * the frame, so a resumed job traces the uninterrupted run's levels. The
 * bounds are kept in the derived-data cache (dmm_lod.h). */

#define LOD_LEVELS MR_DMM_LOD_LEVELS
_Static_assert(LOD_LEVELS == MR_UMESH_MAX_LEVEL + 1, "a bound per level");

typedef struct tri_lod {
    /* the baked levels and data (the level's own arrays hold the frame's,
     * at the same offsets: value_first, pyramid_first) */
    uint8_t *info;
    uint16_t *values, *minv, *maxv;
    mr_umesh_edges edges;
    uint8_t *shared;           /* per base triangle: the edges it shares (micromesh.h) */
    double *error;             /* LOD_LEVELS per base triangle: error[t][l], l <= its baked level */
    double *error_whole;       /* the same for level l with no edge decimated, alone (not the
                                  largest over finer levels): what a frame predicts for it */
    double *fine;              /* per base triangle: fine[t] (above) */
    float *box;                /* 6 per base triangle: its posed box at its baked level */
    double *px;                /* per base triangle: pixels per unit at its nearest depth */
    uint8_t *level, *decimate; /* per base triangle: this frame's */
    uint16_t *pyr_min, *pyr_max; /* a whole pyramid of the largest level: scratch */
    bool boxed;                /* box holds the level's current pose */
    unsigned level_max;        /* this frame's finest level and mean level */
    double level_mean;
} tri_lod;

struct mr_geom {
    const mr_asset *asset;
    dmm_level *lv;
    tri_lod *lod;              /* NULL without a tolerance (or at level 0) */
    double tolerance_px;
    double predicted_px;       /* this frame's largest projected bound */
    bool changed;              /* what Embree holds changed since the last commit */
    double lod_build_s;        /* measuring the bounds */
};

static size_t lod_bytes(const tri_lod *d, uint32_t nt, uint32_t values, uint32_t pyramid)
{
    if (!d)
        return 0;
    return sizeof *d + (size_t)nt * (4 + (2 * LOD_LEVELS + 1) * sizeof(double) +
                                     6 * sizeof(float) + sizeof(double)) +
           ((size_t)values + 2 * (size_t)pyramid) * sizeof(uint16_t) +
           d->edges.count * sizeof(mr_umesh_edge) +
           2 * (size_t)mr_dmm_pyramid_size(MR_UMESH_MAX_LEVEL) * sizeof(uint16_t);
}

static void lod_free(tri_lod *d)
{
    if (!d)
        return;
    free(d->info);
    free(d->values);
    free(d->minv);
    free(d->maxv);
    mr_umesh_edges_free(&d->edges);
    free(d->shared);
    free(d->error);
    free(d->error_whole);
    free(d->fine);
    free(d->box);
    free(d->px);
    free(d->level);
    free(d->decimate);
    free(d->pyr_min);
    free(d->pyr_max);
    free(d);
}

static void dmm_free(mr_geom *g)
{
    if (!g)
        return;
    level_free(g->lv);
    lod_free(g->lod);
    free(g);
}

/* Base triangle t at its baked level (rest: in the rest pose). */
static mr_dmm_patch fine_patch(const dmm_level *g, const tri_lod *d, uint32_t t, bool rest)
{
    mr_dmm_patch p = rest ? rest_patch(g, t) : patch_of(g, t);
    p.level = mr_dmm_info_level(d->info[t]);
    p.decimate = mr_dmm_info_decimate(d->info[t]);
    p.values = d->values + g->value_first[t];
    p.minv = d->minv + g->pyramid_first[t];
    p.maxv = d->maxv + g->pyramid_first[t];
    p.pad[0] = p.pad[1] = p.pad[2] = 0;
    p.stamp = 0; /* values laid out anew per level: no kept micro-vertices */
    p.root_children = NULL; /* (another level's pyramid: not those boxes) */
    return p;
}

/* A copy of the level's baked levels and data, its edges, and room for the
 * rest. */
static int lod_new(const dmm_level *g, tri_lod **out, mr_error *err)
{
    size_t nt = g->base_triangle_count, values = g->value_first[nt], pyramid = g->pyramid_first[nt];
    size_t full = mr_dmm_pyramid_size(MR_UMESH_MAX_LEVEL);
    tri_lod *d = calloc(1, sizeof *d);
    *out = d;
    if (!d)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for levels of detail", g->asset->path);
    d->info = malloc(nt);
    d->values = malloc(values * sizeof(uint16_t) + 1);
    d->minv = malloc(pyramid * sizeof(uint16_t) + 1);
    d->maxv = malloc(pyramid * sizeof(uint16_t) + 1);
    d->shared = malloc(nt);
    d->error = calloc(nt * LOD_LEVELS, sizeof(double));
    d->error_whole = calloc(nt * LOD_LEVELS, sizeof(double));
    d->fine = calloc(nt, sizeof(double));
    d->box = calloc(nt * 6, sizeof(float));
    d->px = calloc(nt, sizeof(double));
    d->level = malloc(nt);
    d->decimate = malloc(nt);
    d->pyr_min = malloc(full * sizeof(uint16_t));
    d->pyr_max = malloc(full * sizeof(uint16_t));
    if (!d->info || !d->values || !d->minv || !d->maxv || !d->shared || !d->error ||
        !d->error_whole || !d->fine || !d->box || !d->px || !d->level || !d->decimate ||
        !d->pyr_min || !d->pyr_max)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for levels of detail", g->asset->path);
    memcpy(d->info, g->tri_info, nt);
    memcpy(d->values, g->values, values * sizeof(uint16_t));
    memcpy(d->minv, g->minv, pyramid * sizeof(uint16_t));
    memcpy(d->maxv, g->maxv, pyramid * sizeof(uint16_t));
    int rc = mr_umesh_edges_init(&d->edges, g->base_indices, (uint32_t)nt, err);
    if (rc < 0)
        return rc;
    mr_umesh_edges_shared(&d->edges, d->shared);
    return MR_OK;
}

/* The detailed mesh in the rest pose: the asset's meshes merged. */
static int rest_detail(const mr_asset *a, float **pos, uint32_t **idx, uint32_t *nv, uint32_t *nt,
                       mr_error *err)
{
    uint64_t v = 0, t = 0;
    for (size_t i = 0; i < a->mesh_count; i++) {
        v += a->meshes[i].vertex_count;
        t += a->meshes[i].triangle_count;
    }
    *pos = malloc((v ? v : 1) * 3 * sizeof(float));
    *idx = malloc((t ? t : 1) * 3 * sizeof(uint32_t));
    if (!*pos || !*idx)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory measuring levels of detail",
                            a->path);
    uint32_t v0 = 0, t0 = 0;
    for (size_t i = 0; i < a->mesh_count; i++) {
        const mr_mesh *m = &a->meshes[i];
        memcpy(*pos + (size_t)v0 * 3, m->positions, (size_t)m->vertex_count * 3 * sizeof(float));
        for (size_t k = 0; k < (size_t)m->triangle_count * 3; k++)
            (*idx)[(size_t)t0 * 3 + k] = m->indices[k] + v0;
        v0 += m->vertex_count;
        t0 += m->triangle_count;
    }
    *nv = v0;
    *nt = t0;
    return MR_OK;
}

/* The baked surface's distance to the detail as posed, per base triangle
 * (dmm_lod.h's owners): the rest pose (pose NULL: the bake's own
 * positions, all samples) or a pose of the clip (both skinned without the
 * object's transform, every MR_LOD_POSE_STRIDE-th sample); error[t] raised
 * to what it finds. detail: the merged detailed mesh (positions as posed). */
static int measure_pose(mr_geom *g, const mr_pose *pose, const float *detail, uint32_t nv,
                        const uint32_t *idx, uint32_t nt, unsigned threads, double *error,
                        mr_error *err)
{
    const mr_asset *a = g->asset;
    const dmm_level *lv = g->lv;
    mr_dmm_lod_truth truth;
    int rc = mr_dmm_lod_truth_init(&truth, detail, nv, idx, nt, a->path, err);
    mr_trimesh m = {0};
    uint32_t *owner = NULL;
    if (rc == MR_OK && pose)
        rc = level_update(g->lv, pose, NULL, threads, err);
    if (rc == MR_OK && (rc = micro_triangles(g->lv, pose == NULL, &m, err)) == MR_OK &&
        !(owner = malloc(((size_t)m.triangle_count + 1) * sizeof *owner)))
        rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory measuring levels of detail", a->path);
    if (rc == MR_OK) {
        for (uint32_t t = 0; t < lv->base_triangle_count; t++)
            for (uint32_t k = lv->micro_first[t]; k < lv->micro_first[t + 1]; k++)
                owner[k] = t;
        rc = mr_dmm_lod_distance(&truth, m.positions, m.vertex_count, m.indices, m.triangle_count,
                                 owner, pose ? MR_LOD_POSE_STRIDE : 1, threads, a->path, error, err);
    }
    free(owner);
    mr_trimesh_free(&m);
    if (truth.distinct)
        mr_dmm_lod_truth_free(&truth);
    return rc;
}

/* What measuring reads, for measure_fine and measure_coarsening. */
typedef struct measure_ctx {
    mr_geom *g;
    const float *pos;      /* the merged detailed mesh at rest */
    const uint32_t *idx;
    uint32_t nv, nt;
    mr_pose *poses[MR_LOD_POSES];
    uint32_t pose_count;
    unsigned threads;
} measure_ctx;

/* Each base triangle's fine bound (above) into error: in the rest pose and
 * in the poses of m. */
static int measure_fine(measure_ctx *m, double *error, mr_error *err)
{
    mr_geom *g = m->g;
    const mr_asset *a = g->asset;
    memset(error, 0, g->lv->base_triangle_count * sizeof *error);
    int rc = measure_pose(g, NULL, m->pos, m->nv, m->idx, m->nt, m->threads, error, err);
    float *posed = NULL;
    if (rc == MR_OK && m->pose_count && !(posed = malloc(((size_t)m->nv * 3 + 1) * sizeof(float))))
        rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory posing levels", a->path);
    for (uint32_t j = 0; j < m->pose_count && rc == MR_OK; j++) {
        size_t at = 0;
        for (size_t i = 0; i < a->mesh_count; i++) {
            mr_skin_mesh(a, i, m->poses[j], NULL, posed + at, NULL, m->threads);
            at += (size_t)a->meshes[i].vertex_count * 3;
        }
        rc = measure_pose(g, m->poses[j], posed, m->nv, m->idx, m->nt, m->threads, error, err);
    }
    free(posed);
    return rc;
}

typedef struct coarsen_ctx {
    const mr_geom *g;
    bool rest;
} coarsen_ctx;

/* error[t][l] raised to what base triangles [begin, end) show as posed. */
static void coarsen_range(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    const coarsen_ctx *c = vctx;
    const dmm_level *lv = c->g->lv;
    tri_lod *d = c->g->lod;
    float pos[3 * 561]; /* mr_umesh_vertex_count(MR_UMESH_MAX_LEVEL) */
    _Static_assert(MR_UMESH_MAX_LEVEL == 5, "pos holds a level-5 lattice");
    for (size_t t = begin; t < end; t++) {
        mr_dmm_patch p = fine_patch(lv, d, (uint32_t)t, c->rest);
        eval_patch_vertices(&p, pos);
        unsigned top = p.level, own = p.decimate;
        const mr_umesh_topology *tp = &lv->topo;
        /* the baked surface against its lattice (0 unless decimated) */
        double baked = mr_dmm_lod_coarsening(top, pos, top, tp->tris[top][own], tp->count[top][own]);
        double *e = d->error + t * LOD_LEVELS, *whole = d->error_whole + t * LOD_LEVELS;
        for (unsigned l = 0; l <= top; l++)
            for (unsigned m = 0; m < (l ? 8u : 1u); m++)
                if (!(m & ~d->shared[t])) {
                    double x = baked + mr_dmm_lod_coarsening(top, pos, l, tp->tris[l][m], tp->count[l][m]);
                    e[l] = fmax(e[l], x);
                    if (m == 0)
                        whole[l] = fmax(whole[l], x);
                }
    }
}

/* error[t][l] (above): in the rest pose and in the poses of m, then the
 * largest over levels l and finer. */
static int measure_coarsening(mr_geom *g, measure_ctx *m, mr_error *err)
{
    tri_lod *d = g->lod;
    coarsen_ctx c = {g, true};
    mr_parallel_for(m->threads, g->lv->base_triangle_count, UPDATE_GRAIN, coarsen_range, &c);
    c.rest = false;
    for (uint32_t j = 0; j < m->pose_count; j++) {
        bool moved;
        int rc = level_pose(g->lv, m->poses[j], NULL, m->threads, &moved, err);
        if (rc < 0)
            return rc;
        mr_parallel_for(m->threads, g->lv->base_triangle_count, UPDATE_GRAIN, coarsen_range, &c);
    }
    for (size_t t = 0; t < g->lv->base_triangle_count; t++) {
        double *e = d->error + t * LOD_LEVELS;
        for (unsigned l = mr_dmm_info_level(d->info[t]); l-- > 0;)
            e[l] = fmax(e[l], e[l + 1]);
    }
    return MR_OK;
}

/* The key of the bounds (dmm_lod.h): everything the bake and the
 * measurement read. The asset (nodes; each mesh's node, counts, positions,
 * normals, triangles and skin), the object's parameters (the bake follows
 * from them) and each measured pose's node transforms (the detailed and the
 * base mesh are skinned by them, whatever in the job chose them). */
static void bounds_key(const mr_geom *g, const mr_dmm_params *p, const measure_ctx *m,
                       uint8_t key[MR_DERIVED_KEY_BYTES])
{
    const mr_asset *a = g->asset;
    mr_derived_key_builder kb;
    mr_derived_key_begin(&kb, "microray dmm lod bounds", MR_DMM_LOD_FILE_VERSION, 1);
    mr_derived_key_nodes(&kb, a);
    mr_derived_key_u64(&kb, a->mesh_count);
    const unsigned parts = MR_DERIVED_POSITIONS | MR_DERIVED_NORMALS | MR_DERIVED_INDICES | MR_DERIVED_SKIN;
    for (size_t i = 0; i < a->mesh_count; i++) {
        const mr_mesh *mesh = &a->meshes[i];
        mr_derived_key_u32(&kb, (uint32_t)mesh->node);
        mr_derived_key_mesh_counts(&kb, mesh);
        mr_derived_key_u32(&kb, mr_derived_mesh_parts(mesh, parts));
        mr_derived_key_mesh_arrays(&kb, mesh, parts);
    }
    mr_derived_key_u32(&kb, p->level);
    mr_derived_key_f32s(&kb, &p->base_ratio, 1);
    mr_derived_key_u32(&kb, p->base_triangles);
    mr_derived_key_u32(&kb, (uint32_t)p->mode);
    mr_derived_key_u32(&kb, (uint32_t)p->deform);
    mr_derived_key_u32(&kb, (uint32_t)p->normals);
    mr_derived_key_u32(&kb, (uint32_t)p->levels);
    mr_derived_key_u32(&kb, (uint32_t)p->intersector);
    mr_derived_key_u32(&kb, m->pose_count);
    for (uint32_t j = 0; j < m->pose_count; j++)
        for (size_t n = 0; n < m->poses[j]->node_count; n++)
            mr_derived_key_f32s(&kb, m->poses[j]->global[n].m, 16);
    mr_derived_key_end(&kb, key);
}

/* Both bounds of every base triangle (above), measured: for the
 * derived-data cache (dmm_lod.h). */
static int measure_all(void *vctx, mr_error *err)
{
    measure_ctx *m = vctx;
    int rc = measure_fine(m, m->g->lod->fine, err);
    return rc < 0 ? rc : measure_coarsening(m->g, m, err);
}

/* The bounds (above), in the poses (mr_lod_pose_times) of the object's
 * first pose description when it plays a clip or moves joints, measured
 * (measure_all) or read from the derived-data cache. */
static int measure_levels(mr_geom *g, const mr_object_desc *desc, const mr_kind_context *ctx, mr_error *err)
{
    const mr_asset *a = g->asset;
    float *pos = NULL;
    uint32_t *idx = NULL;
    measure_ctx m = {.g = g, .threads = ctx ? ctx->threads : 0};
    int rc = rest_detail(a, &pos, &idx, &m.nv, &m.nt, err);
    m.pos = pos;
    m.idx = idx;
    const mr_pose_desc *d = desc->pose_count > 0 ? &desc->poses[0] : NULL;
    double times[MR_LOD_POSES];
    const uint32_t n = mr_lod_pose_times(a, d, times);
    for (uint32_t j = 0; j < n && rc == MR_OK; j++)
        if ((rc = mr_pose_new(a, &m.poses[j], err)) == MR_OK) {
            m.pose_count++;
            rc = mr_pose_eval(m.poses[j], a, d, times[j], err);
        }
    if (rc == MR_OK) {
        uint8_t key[MR_DERIVED_KEY_BYTES];
        bounds_key(g, desc->params, &m, key);
        tri_lod *t = g->lod;
        mr_dmm_lod_table table = {g->lv->base_triangle_count, t->fine, t->error, t->error_whole};
        rc = mr_dmm_lod_table_cached(ctx ? ctx->cache_dir : NULL, key, &table, measure_all, &m, NULL,
                                     err);
    }
    g->lv->evaluated = false; /* posed for measuring: the first frame poses it again */
    for (uint32_t j = 0; j < m.pose_count; j++)
        mr_pose_free(m.poses[j]);
    free(pos);
    free(idx);
    return rc;
}

static int dmm_create(const mr_asset *asset, const mr_object_desc *desc,
                      const mr_kind_context *ctx, mr_geom **out, mr_error *err)
{
    *out = NULL;
    if (!desc->params)
        return mr_error_set(err, MR_ERR_INVALID, "a dmm object needs its parameters");
    const mr_dmm_params *p = desc->params;
    int rc = check_desc(p, err);
    if (rc < 0)
        return rc;
    mr_geom *g = calloc(1, sizeof *g);
    if (!g)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory creating a dmm object");
    g->asset = asset;
    g->tolerance_px = desc->tolerance_px > 0 ? desc->tolerance_px : 0;
    g->changed = true;
    if ((rc = level_create(asset, desc, ctx, &g->lv, err)) < 0) {
        dmm_free(g);
        return rc;
    }
    if (g->tolerance_px > 0 && p->level > 0) {
        double t = mr_now();
        if ((rc = lod_new(g->lv, &g->lod, err)) < 0 || (rc = measure_levels(g, desc, ctx, err)) < 0) {
            dmm_free(g);
            return rc;
        }
        g->lv->boxes_given = true;
        g->lod_build_s = mr_now() - t;
    }
    *out = g;
    return MR_OK;
}

/* Each base triangle's box at its baked level, as posed: what places it
 * for the pick, and (user geometries) what Embree and the traversal bound
 * it by at any level (a coarser level's micro-vertices are among its own,
 * bit for bit, and its pad bounds their coordinates too). A box that is
 * not finite is refused by level_evaluate's check of it. */
static void lod_box_range(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    const mr_geom *g = vctx;
    for (size_t t = begin; t < end; t++) {
        mr_dmm_patch p = fine_patch(g->lv, g->lod, (uint32_t)t, false);
        mr_vec3 lo = {0, 0, 0}, hi = {0, 0, 0};
        mr_dmm_patch_pad(&p, p.pad);
        if (!mr_dmm_patch_bounds(&p, &lo, &hi))
            lo = hi = mr_v3(NAN, NAN, NAN);
        float *b = g->lod->box + t * 6;
        b[0] = lo.x, b[1] = lo.y, b[2] = lo.z, b[3] = hi.x, b[4] = hi.y, b[5] = hi.z;
        if (g->lv->boxes) { /* the level's too, with the pad (the traversal's cache) */
            float *to = g->lv->boxes + t * BOX_FLOATS;
            memcpy(to, b, 6 * sizeof *b);
            memcpy(to + 6, p.pad, sizeof p.pad);
        }
    }
}

/* This frame's level of every base triangle (above; without a camera, the
 * baked ones), balanced, and the predicted error. */
static void lod_pick(mr_geom *g, const mr_geom_frame *frame, double stretch)
{
    tri_lod *d = g->lod;
    size_t nt = g->lv->base_triangle_count;
    mr_px_scale scale = {.none = true};
    if (frame)
        scale = mr_camera_px_scale(&frame->camera, frame->width, frame->height);
    for (size_t t = 0; t < nt; t++) {
        unsigned top = mr_dmm_info_level(d->info[t]), l = 0;
        const double *e = d->error + t * LOD_LEVELS;
        d->px[t] = 0;
        if (frame) {
            const float *b = d->box + t * 6;
            float grow = (float)((e[0] + d->fine[t]) * stretch);
            mr_vec3 lo = mr_v3(b[0] - grow, b[1] - grow, b[2] - grow);
            mr_vec3 hi = mr_v3(b[3] + grow, b[4] + grow, b[5] + grow);
            d->px[t] = mr_px_scale_box(&scale, lo, hi) * stretch;
        }
        while (l < top && !(frame && (e[l] + d->fine[t]) * d->px[t] <= g->tolerance_px))
            l++;
        d->level[t] = (uint8_t)l;
        /* until the balance sets the masks: whether no level fits t with
         * its edges decimated, so none of them may be */
        d->decimate[t] = !(frame && (e[l] + d->fine[t]) * d->px[t] <= g->tolerance_px);
    }
    /* such a triangle's neighbours rise to its level, where theirs reach */
    const mr_umesh_edge *ed = d->edges.e;
    for (size_t i = 0, j; i < d->edges.count; i = j) {
        unsigned want = 0;
        j = mr_umesh_edges_group_end(&d->edges, i);
        for (size_t m = i; m < j; m++)
            if (d->decimate[ed[m].tri] && d->level[ed[m].tri] > want)
                want = d->level[ed[m].tri];
        for (size_t m = i; m < j; m++) {
            unsigned cap = mr_dmm_info_level(d->info[ed[m].tri]);
            unsigned to = want < cap ? want : cap;
            if (d->level[ed[m].tri] < to)
                d->level[ed[m].tri] = (uint8_t)to;
        }
    }
    mr_umesh_balance(&d->edges, d->level, d->decimate);
    g->predicted_px = 0;
    d->level_max = 0;
    double sum = 0;
    for (size_t t = 0; t < nt; t++) {
        const double *bound = d->decimate[t] ? d->error : d->error_whole;
        double e = bound[t * LOD_LEVELS + d->level[t]] + d->fine[t];
        double px = e > 0 ? (isfinite(d->px[t]) ? e * d->px[t] : MR_LOD_UNBOUNDED_PX) : 0;
        g->predicted_px = fmax(g->predicted_px, px);
        d->level_max = d->level[t] > d->level_max ? d->level[t] : d->level_max;
        sum += d->level[t];
    }
    d->level_mean = nt ? sum / (double)nt : 0;
}

/* The level's arrays for this frame's levels: each base triangle whose
 * level changed gets its values (subsampled from the baked ones) and its
 * pyramid (rebuilt: a level's pyramid bounds its own values) at its baked
 * offsets, which have room for any coarser level; the micro-triangles'
 * offsets and indices follow. Whether anything changed. */
static bool lod_lay_out(dmm_level *g, tri_lod *d)
{
    size_t nt = g->base_triangle_count;
    bool changed = false;
    for (size_t t = 0; t < nt; t++) {
        uint8_t info = mr_dmm_tri_info(d->level[t], d->decimate[t]);
        if (g->tri_info[t] == info)
            continue;
        changed = true;
        unsigned was = mr_dmm_info_level(g->tri_info[t]);
        g->tri_info[t] = info;
        if (was == d->level[t])
            continue; /* only its decimation changed */
        unsigned l = d->level[t], top = mr_dmm_info_level(d->info[t]), up = top - l;
        uint16_t *dst = g->values + g->value_first[t];
        const uint16_t *src = d->values + g->value_first[t];
        uint32_t n = mr_umesh_segments(l), keep = mr_dmm_trace_pyramid_size(l);
        for (uint32_t b = 0; b <= n; b++)
            for (uint32_t a = 0; a + b <= n; a++)
                dst[mr_umesh_vertex_index(l, a, b)] = src[mr_umesh_vertex_index(top, a << up, b << up)];
        const uint16_t *lo = d->minv + g->pyramid_first[t], *hi = d->maxv + g->pyramid_first[t];
        if (up) { /* the baked data decoded and bounded fine: only the level can fail */
            mr_dmm_pyramid_build(l, dst, d->pyr_min, d->pyr_max, NULL);
            lo = d->pyr_min, hi = d->pyr_max;
        }
        memcpy(g->minv + g->pyramid_first[t], lo, keep * sizeof *lo);
        memcpy(g->maxv + g->pyramid_first[t], hi, keep * sizeof *hi);
    }
    if (!changed)
        return false;
    uint32_t micro = 0;
    for (size_t t = 0; t < nt; t++) {
        uint32_t count;
        g->micro_first[t] = micro;
        local_tris(g, (uint32_t)t, &count);
        micro += count;
    }
    g->micro_first[nt] = micro;
    if (tessellated(g)) {
        fill_micro_indices(g, g->indices);
        g->triangle_count = micro;
    }
    g->evaluated = false;
    g->relaid = true;
    return true;
}

/* Without levels: the level posed. With levels: posed (its boxes at the
 * baked levels again if it moved), the levels picked and laid out, and
 * evaluated when either changed. */
static int dmm_update(mr_geom *g, const mr_geom_frame *frame, const mr_pose *pose,
                      const mr_mat4 *transform, unsigned threads, mr_error *err)
{
    if (!g->lod)
        return level_update(g->lv, pose, transform, threads, err);
    bool moved = false; /* a frame where only the camera moved keeps the pose */
    int rc = frame && frame->view_only && g->lv->evaluated
                 ? MR_OK
                 : level_pose(g->lv, pose, transform, threads, &moved, err);
    if (rc < 0)
        return rc;
    if (moved || !g->lod->boxed) {
        mr_parallel_for(threads, g->lv->base_triangle_count, UPDATE_GRAIN, lod_box_range, g);
        g->lod->boxed = true;
    }
    lod_pick(g, frame, transform ? mr_lod_stretch(transform) : 1.0);
    bool relaid = lod_lay_out(g->lv, g->lod);
    if (!moved && !relaid && g->lv->evaluated)
        return MR_OK;
    /* Embree needs the frame only when the boxes moved or, intersector
     * "embree", the micro-triangles changed: a user geometry's boxes are
     * the baked levels' whatever the levels, and its callbacks read the
     * levels laid out */
    g->changed = g->changed || moved || (relaid && embree_triangles(g->lv));
    return level_evaluate(g->lv, threads, err);
}

/* One geometry, whose base triangles show any of LOD_LEVELS levels with
 * levels of detail: built as mr_lod_build_quality says for several (the
 * micro-triangles of intersector "embree" change with the levels, which a
 * refit cannot follow, and a resumed job must trace the uninterrupted
 * run's trees). */
static int dmm_attach(mr_geom *g, RTCDevice device, RTCScene scene, unsigned geom_id,
                      enum RTCBuildQuality quality, mr_error *err)
{
    return level_attach(g->lv, device, scene, geom_id,
                        mr_lod_build_quality(g->lod ? LOD_LEVELS : 1, quality), err);
}

/* Always without levels of detail (as before them); with, only a frame
 * that changed what Embree holds (dmm_update). */
static bool dmm_commit(mr_geom *g)
{
    if (g->lod && !g->changed)
        return false;
    level_commit(g->lv);
    g->changed = false;
    return true;
}

static uint32_t dmm_geometry_ids(const mr_geom *g) { return 1; }

static mr_vec3 dmm_normal(const mr_geom *g, unsigned prim, float u, float v, mr_vec3 ng)
{
    return level_normal(g->lv, prim, u, v);
}

static bool dmm_shading_point(const mr_geom *g, unsigned prim, float u, float v, mr_vec3 p,
                              mr_vec3 *out)
{
    return level_shading_point(g->lv, prim, u, v, p, out);
}

static int dmm_tessellate(const mr_geom *g, mr_trimesh *out, mr_error *err)
{
    return level_tessellate(g->lv, out, err);
}

static size_t dmm_bytes_lod(const mr_geom *g)
{
    const dmm_level *l = g->lv;
    size_t nt = l->base_triangle_count;
    return g->lod ? lod_bytes(g->lod, (uint32_t)nt, l->value_first[nt], l->pyramid_first[nt]) : 0;
}

static size_t dmm_memory(const mr_geom *g) { return sizeof *g + level_memory(g->lv) + dmm_bytes_lod(g); }

static uint64_t dmm_primitives(const mr_geom *g) { return level_primitives(g->lv); }

static void dmm_frame_stats(const mr_geom *g, double *values)
{
    level_frame_stats(g->lv, values);
    values[S_LEVEL] = g->lod ? g->lod->level_max : g->lv->desc.level;
    values[S_LEVEL_MEAN] = g->lod ? g->lod->level_mean : g->lv->desc.level;
    values[S_ERROR_PX] = g->predicted_px;
    values[S_LOD_BYTES] = (double)dmm_bytes_lod(g);
    values[S_LOD_BUILD_S] = g->lod_build_s;
}

/* The finest level traced; an object at level 0 has no other to pick. */
static bool dmm_lod(const mr_geom *g, uint32_t *level, double *error_px)
{
    *level = g->lod ? g->lod->level_max : g->lv->desc.level;
    *error_px = g->predicted_px;
    return g->lod != NULL;
}

bool mr_dmm_lod_bounds(const mr_geom *g, mr_dmm_lod_table *out)
{
    if (!g->lod)
        return false;
    *out = (mr_dmm_lod_table){g->lv->base_triangle_count, g->lod->fine, g->lod->error,
                              g->lod->error_whole};
    return true;
}

const uint8_t *mr_dmm_frame_tri_info(const mr_geom *g) { return g->lv->tri_info; }

int mr_dmm_rest_triangles(const mr_geom *g, mr_trimesh *out, mr_error *err)
{
    return micro_triangles(g->lv, true, out, err);
}

/* The "dmm" block. "deformation" chooses what mode "tessellated" expands
 * and must agree with the other modes; base_ratio and base_triangles are
 * alternatives. */
static const char *const MODES[] = {"tessellated", "base", "interpolated"};
static const char *const DEFORMS[] = {"base", "interpolated"};
static const char *const NORMALS[] = {"geometric", "matrix", "smooth"};
static const char *const LEVELS[] = {"uniform", "adaptive"};
static const char *const INTERSECTORS[] = {"embree", "watertight"};

enum { P_LEVEL, P_RATIO, P_TRIANGLES, P_MODE, P_DEFORM, P_NORMALS, P_LEVELS, P_INTERSECTOR };

static mr_dmm_deform deform_of_mode(mr_dmm_mode m)
{
    return m == MR_DMM_INTERPOLATED ? MR_DMM_DEFORM_INTERPOLATED : MR_DMM_DEFORM_BASE;
}

static int after_mode(void *values, const bool *given, mr_param_error *err)
{
    mr_dmm_params *d = values;
    d->deform = deform_of_mode(d->mode);
    return MR_OK;
}

static int after_deform(void *values, const bool *given, mr_param_error *err)
{
    mr_dmm_params *d = values;
    mr_dmm_deform implied = deform_of_mode(d->mode);
    if (given[P_DEFORM] && d->mode != MR_DMM_TESSELLATED && d->deform != implied)
        return mr_param_fail(err, MR_ERR_INVALID, "deformation",
                             "mode \"%s\" deforms by \"%s\"; \"deformation\" only chooses what "
                             "mode \"tessellated\" expands",
                             MODES[d->mode], DEFORMS[implied]);
    return MR_OK;
}

static int after_intersector(void *values, const bool *given, mr_param_error *err)
{
    const mr_dmm_params *d = values;
    if (given[P_INTERSECTOR] && d->mode != MR_DMM_TESSELLATED)
        return mr_param_fail(err, MR_ERR_INVALID, "intersector",
                             "mode \"%s\" traces its own micro-triangles; \"intersector\" only "
                             "chooses how mode \"tessellated\" intersects them",
                             MODES[d->mode]);
    return MR_OK;
}

static const mr_param DMM_PARAMS[] = {
    [P_LEVEL] = {.field = "level", .type = MR_PARAM_INT, .offset = offsetof(mr_dmm_params, level),
                 .lo = 0, .hi = MR_UMESH_MAX_LEVEL, .def = MR_DMM_DEFAULT_LEVEL,
                 .description = "Subdivision level: 4^level micro-triangles per base triangle."},
    [P_RATIO] = {.field = "base_ratio", .type = MR_PARAM_NUMBER,
                 .offset = offsetof(mr_dmm_params, base_ratio), .lo = 0, .hi = 1,
                 .flags = MR_PARAM_LO_OPEN, .def = MR_DMM_DEFAULT_BASE_RATIO,
                 .conflicts = "base_triangles",
                 .description = "Base triangles as a fraction of the detailed (welded) triangles, per mesh."},
    [P_TRIANGLES] = {.field = "base_triangles", .type = MR_PARAM_INT,
                     .offset = offsetof(mr_dmm_params, base_triangles), .lo = 1,
                     .hi = MR_MAX_ASSET_TRIANGLES, .def = 0,
                     .description = "Target base triangle count per mesh, instead of base_ratio (at "
                                    "least the mesh's welded triangles keeps every one)."},
    [P_MODE] = {.field = "mode", .type = MR_PARAM_ENUM, .offset = offsetof(mr_dmm_params, mode),
                MR_PARAM_CHOICES(MODES), .def = MR_DMM_TESSELLATED, .after = after_mode,
                .description = "How the micro-geometry is traced. \"tessellated\": the micro-triangles of the "
                               "chosen deformation expanded into Embree triangles (the exact reference and "
                               "pre-tessellation baseline). \"base\": deformation base, traced without "
                               "tessellation through prism bounds (Algorithms 2 and 4) in an Embree user "
                               "geometry with one primitive per base triangle. \"interpolated\": deformation "
                               "interpolated, traced without tessellation, bounded by the 12 control points of "
                               "the min/max quadratic Bezier patches (eq. 9-13, Algorithms 1 and 3), in the "
                               "same kind of user geometry. All three intersect the same micro-triangles for "
                               "the same deformation."},
    [P_DEFORM] = {.field = "deformation", .type = MR_PARAM_ENUM,
                  .offset = offsetof(mr_dmm_params, deform), MR_PARAM_CHOICES(DEFORMS),
                  .def = MR_DMM_DEFORM_BASE, .after = after_deform,
                  .description = "What mode \"tessellated\" expands. Mode \"base\" implies \"base\" and mode "
                                 "\"interpolated\" implies \"interpolated\" (then the default); a contradicting "
                                 "value is refused."},
    [P_NORMALS] = {.field = "normals", .type = MR_PARAM_ENUM,
                   .offset = offsetof(mr_dmm_params, normals), MR_PARAM_CHOICES(NORMALS),
                   .def = MR_DMM_NORMALS_SMOOTH,
                   .description = "Shading normal, in any mode. \"smooth\": normals at the detailed mesh's scale "
                                  "(the area-weighted normal of the micro-surface around each vertex of a "
                                  "coarse lattice whose triangles match the detailed mesh's, continuous across "
                                  "base edges), interpolated and moved by the cofactor of the interpolated "
                                  "matrix at the hit; shadow rays start on the smooth surface they describe. "
                                  "\"geometric\": the hit micro-triangle's own normal (flat, shows the facets). "
                                  "\"matrix\": the rest-pose micro-triangle normal moved by the cofactor of the "
                                  "interpolated matrix at the hit (the paper's Fig. 1c)."},
    [P_LEVELS] = {.field = "levels", .type = MR_PARAM_ENUM,
                  .offset = offsetof(mr_dmm_params, levels), MR_PARAM_CHOICES(LEVELS),
                  .def = MR_DMM_LEVELS_UNIFORM,
                  .description = "\"uniform\": every base triangle at level. \"adaptive\": each base triangle at "
                                 "the level (0..level) whose micro-triangles are closest in area to the detailed "
                                 "mesh's mean triangle; neighbours at most one level apart, the finer side's "
                                 "shared edge decimated (watertight)."},
    [P_INTERSECTOR] = {.field = "intersector", .type = MR_PARAM_ENUM,
                       .offset = offsetof(mr_dmm_params, intersector),
                       MR_PARAM_CHOICES(INTERSECTORS), .def = MR_DMM_INTERSECT_EMBREE,
                       .after = after_intersector,
                       .description = "Mode \"tessellated\" only: what intersects its micro-triangles. \"embree\": "
                                      "Embree's own triangle intersector over Embree triangles (the pre-tessellated "
                                      "baseline; its float arithmetic decides rays within rounding of a silhouette "
                                      "micro-edge, and its depths, slightly differently from the tessellation-free "
                                      "modes). \"watertight\": the tessellation-free modes' own watertight test, "
                                      "every micro-triangle of each base triangle whose box (theirs) the ray enters "
                                      "(the exact reference: frames bit-identical to modes \"base\" and "
                                      "\"interpolated\", and the reference pass's \"tessellated\"; slower)."},
};

static const mr_param_table DMM_TABLE = {
    .params = DMM_PARAMS,
    .count = sizeof DMM_PARAMS / sizeof DMM_PARAMS[0],
    .size = sizeof(mr_dmm_params),
    .expect = "an object of dmm bake parameters",
    .schema_rules =
        "{\"allOf\": ["
        "{\"if\": {\"required\": [\"mode\"], \"properties\": {\"mode\": {\"const\": \"base\"}}},"
        " \"then\": {\"properties\": {\"deformation\": {\"const\": \"base\"}}}},"
        "{\"if\": {\"required\": [\"mode\"], \"properties\": {\"mode\": {\"const\": "
        "\"interpolated\"}}},"
        " \"then\": {\"properties\": {\"deformation\": {\"const\": \"interpolated\"}}}},"
        "{\"if\": {\"required\": [\"intersector\"]},"
        " \"then\": {\"properties\": {\"mode\": {\"const\": \"tessellated\"}}}}]}",
};

/* References (kind.h): "tessellated" is the same micro-triangles (mode
 * "tessellated", expanding the deformation the object's mode implies)
 * intersected by the tessellation-free modes' own test (intersector
 * "watertight"): exact, so the tessellation-free modes must match it bit
 * for bit; with "tolerance_px" (which the tessellated pass keeps) at the
 * level the object picked: the reference measures the same errors on the
 * same micro-triangles and places the object by the same boxes, so it
 * picks the same level each frame;
 * "ground_truth" is the detailed mesh the micro-mesh was baked from (the
 * object's asset) skinned directly as plain triangles, which the bake, the
 * subdivision level and the deformation approximate. */
static int dmm_reference(const mr_object_desc *obj, mr_reference_type type,
                         mr_reference_objects *out, mr_error *err)
{
    mr_object_desc d = *obj;
    if (type == MR_REFERENCE_GROUND_TRUTH) {
        d.kind = mr_kind_triangles();
        d.params = NULL;
        return mr_reference_objects_add(out, &d, err);
    }
    mr_dmm_params *p = mr_reference_alloc(out, sizeof *p, err);
    if (!p)
        return MR_ERR_NOMEM;
    *p = *(const mr_dmm_params *)obj->params;
    p->mode = MR_DMM_TESSELLATED; /* p->deform is the mode's already (after_mode) */
    /* the exact reference: the same test, bit-identical frames */
    p->intersector = MR_DMM_INTERSECT_WATERTIGHT;
    d.params = p;
    return mr_reference_objects_add(out, &d, err);
}

const mr_kind mr_kind_dmm = {
    .name = "dmm",
    .summary = "Parameters of a displaced micro-mesh object (kind \"dmm\", paper 000). Every "
               "mesh of the asset is simplified to a base mesh whose vertices keep their bone "
               "weights, and displaced at every micro-vertex of the given subdivision level. "
               "Each frame every base vertex gets its accumulated skinning matrix M. "
               "Deformation \"base\": base vertices and directions skinned with it (v' = M v, "
               "n' = M n, eq. 4; not renormalised), micro-vertex = interpolated point + d * "
               "interpolated direction (eq. 5). Deformation \"interpolated\" (the paper's "
               "method): M interpolated barycentrically per micro-vertex and applied to the "
               "rest-pose displaced micro-vertex (eq. 6-8).",
    .params = &DMM_TABLE,
    .has_derived = true,
    .has_lod = true,
    .lod = dmm_lod,
    .create = dmm_create,
    .update = dmm_update,
    .attach = dmm_attach,
    .commit = dmm_commit,
    .normal = dmm_normal,
    .shading_point = dmm_shading_point,
    .tessellate = dmm_tessellate,
    .memory = dmm_memory,
    .primitives = dmm_primitives,
    .geometry_ids = dmm_geometry_ids,
    .stats = DMM_STATS,
    .stat_count = S_COUNT,
    .frame_stats = dmm_frame_stats,
    .reference = dmm_reference,
    .free = dmm_free,
};
