/*
 * springmass_kind.c - the spring-mass kind's descriptor, parameter table
 * and ops (springmass_kind.h): the asset's meshes at rest, placed by the
 * object's transform, are filled with a node grid (grid.h), simulated
 * (sim.h) and followed by the mapped detailed mesh (map.h), one Embree
 * triangle geometry.
 */
#include "kinds/springmass/springmass_kind.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "kinds/springmass/map.h"
#include "kinds/springmass/sim.h"
#include "util/clock.h"
#include "util/derived.h"

/* The simulation state's format and the builders' revision: in every
 * checkpoint id, so a checkpoint of another layout or grid is never used. */
#define SM_STATE_VERSION 2u
#define SM_REVISION 1u

/* Levels of detail ("tolerance_px"), finest first: the mappings an object
 * with a tolerance picks from each frame. Trilinear is the ground truth
 * (the references); the triangle mappings cost a fifth to a tenth of it
 * (bench_springmass). one_to_one is left out: it costs more than
 * triangle_basis and strays farther. */
static const int LOD_MAPPINGS[] = {MR_SPRINGMASS_TRILINEAR, MR_SPRINGMASS_TRIANGLE_CURVATURE,
                                   MR_SPRINGMASS_TRIANGLE_BASIS};
#define LOD_LEVELS 3
/* Every LOD_STRIDE-th vertex is also mapped trilinearly each frame: the
 * sample a cheaper mapping is measured against. */
#define LOD_STRIDE 16

/* Bytes per grid cell the simulation holds (18 float arrays and the
 * grid's two byte arrays), for the memory budget. */
#define SM_BYTES_PER_CELL (18u * 4u + 2u)

struct mr_geom {
    const mr_springmass_params *p;
    const char *asset_path;
    unsigned threads;
    uint32_t vertex_count, triangle_count;
    float *rest_pos, *rest_nrm; /* world space, rest */
    float *rest_tan;            /* world space, rest, 0 for meshes without; NULL: no mesh has them */
    float *positions;           /* 3 per vertex + 1 padding (Embree) */
    float *normals;
    float *tangents;            /* this frame's (with rest_tan) */
    uint32_t *indices;
    sm_sim *sim;
    /* maps[0]: the object's mapping; with a tolerance, maps[k] maps by
     * LOD_MAPPINGS[k] and maps[level] placed this frame's mesh */
    sm_map *maps[LOD_LEVELS];
    uint32_t map_count, level;
    double tolerance_px, predicted_px;
    float *sample_pos, *sample_nrm; /* trilinear at every LOD_STRIDE-th vertex */
    RTCGeometry rtc;
    uint8_t id[32];             /* checkpoint id */
    /* the last update's figures */
    double simulate_s, map_s;
    uint64_t steps;
};

static void springmass_free(mr_geom *g)
{
    if (!g)
        return;
    if (g->rtc)
        rtcReleaseGeometry(g->rtc);
    for (uint32_t k = 0; k < g->map_count; k++)
        sm_map_free(g->maps[k]);
    free(g->sample_pos);
    free(g->sample_nrm);
    sm_sim_free(g->sim);
    free(g->rest_pos);
    free(g->rest_nrm);
    free(g->rest_tan);
    free(g->positions);
    free(g->normals);
    free(g->tangents);
    free(g->indices);
    free(g);
}

/* The asset's meshes at rest, placed by the transform, merged. */
static int rest_mesh(mr_geom *g, const mr_asset *asset, const mr_mat4 *transform, mr_error *err)
{
    uint64_t nv = 0, nt = 0;
    for (size_t i = 0; i < asset->mesh_count; i++) {
        nv += asset->meshes[i].vertex_count;
        nt += asset->meshes[i].triangle_count;
    }
    if (nt == 0)
        return mr_error_set(err, MR_ERR_FORMAT, "%s: no triangles to simulate", asset->path);
    if (nv > MR_MAX_ASSET_VERTICES || nt > MR_MAX_ASSET_TRIANGLES)
        return mr_error_set(err, MR_ERR_LIMIT, "%s: %llu vertices / %llu triangles exceed the caps",
                            asset->path, (unsigned long long)nv, (unsigned long long)nt);
    g->vertex_count = (uint32_t)nv;
    g->triangle_count = (uint32_t)nt;
    g->rest_pos = malloc(nv * 3 * sizeof(float) + 4);
    g->rest_nrm = malloc(nv * 3 * sizeof(float) + 4);
    g->positions = calloc(nv * 3 + 1, sizeof(float));
    g->normals = calloc(nv * 3 + 1, sizeof(float));
    g->indices = malloc(nt * 3 * sizeof(uint32_t));
    if (!g->rest_pos || !g->rest_nrm || !g->positions || !g->normals || !g->indices)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for %llu vertices", asset->path,
                            (unsigned long long)nv);
    for (size_t i = 0; i < asset->mesh_count && !g->rest_tan; i++)
        if (asset->meshes[i].tangents &&
            (!(g->rest_tan = calloc(nv * 3 + 1, sizeof(float))) || !(g->tangents = calloc(nv * 3 + 1, sizeof(float)))))
            return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for %llu tangents", asset->path,
                                (unsigned long long)nv);
    mr_pose *pose = NULL;
    int rc = mr_pose_new(asset, &pose, err);
    if (rc < 0)
        return rc;
    if ((rc = mr_pose_eval(pose, asset, NULL, 0, err)) < 0) {
        mr_pose_free(pose);
        return rc;
    }
    uint32_t v0 = 0, t0 = 0;
    for (size_t i = 0; i < asset->mesh_count; i++) {
        const mr_mesh *m = &asset->meshes[i];
        mr_skin_mesh_tangents(asset, i, pose, transform, g->rest_pos + (size_t)v0 * 3, g->rest_nrm + (size_t)v0 * 3,
                              g->rest_tan ? g->rest_tan + (size_t)v0 * 3 : NULL, g->threads);
        for (uint64_t k = 0; k < (uint64_t)m->triangle_count * 3; k++)
            g->indices[(uint64_t)t0 * 3 + k] = m->indices[k] + v0;
        v0 += m->vertex_count;
        t0 += m->triangle_count;
    }
    mr_pose_free(pose);
    for (size_t k = 0; k < nv * 3; k++)
        if (!(fabsf(g->rest_pos[k]) <= MR_MAX_COORDINATE))
            return mr_error_set(err, MR_ERR_INVALID, "transform: vertex %zu lands at a coordinate of %g",
                                k / 3, (double)g->rest_pos[k]);
    return MR_OK;
}

static const mr_param_table SPRINGMASS_TABLE;

static void state_id(mr_geom *g)
{
    mr_derived_key_builder kb;
    mr_derived_key_begin(&kb, "microray springmass state", SM_STATE_VERSION, SM_REVISION);
    mr_derived_key_u32(&kb, g->vertex_count);
    mr_derived_key_u32(&kb, g->triangle_count);
    mr_derived_key_f32s(&kb, g->rest_pos, (size_t)g->vertex_count * 3);
    mr_derived_key_bytes(&kb, g->indices, (size_t)g->triangle_count * 3 * sizeof(uint32_t));
    mr_derived_key_params(&kb, &SPRINGMASS_TABLE, g->p);
    mr_derived_key_end(&kb, g->id);
}

static int springmass_create(const mr_asset *asset, const mr_object_desc *desc, const mr_kind_context *ctx,
                             mr_geom **out, mr_error *err)
{
    *out = NULL;
    if (desc->pose_count)
        return mr_error_set(err, MR_ERR_INVALID,
                            "pose: a springmass object is moved by its simulation and takes no pose");
    mr_geom *g = calloc(1, sizeof *g);
    if (!g)
        return mr_error_set(err, MR_ERR_NOMEM, "springmass: out of memory");
    g->p = desc->params;
    g->asset_path = asset->path;
    g->threads = ctx ? ctx->threads : 0;
    const mr_springmass_params *p = g->p;
    const char *grid_field = p->spacing > 0 ? "springmass/spacing" : "springmass/nodes";
    int rc = rest_mesh(g, asset, &desc->transform, err);
    if (rc < 0)
        goto fail;
    double *dpos = malloc((size_t)g->vertex_count * 3 * sizeof *dpos);
    if (!dpos) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "springmass: out of memory");
        goto fail;
    }
    for (size_t k = 0; k < (size_t)g->vertex_count * 3; k++)
        dpos[k] = g->rest_pos[k];
    size_t max_cells = ctx && ctx->memory_budget ? ctx->memory_budget / SM_BYTES_PER_CELL : 0;
    sm_grid grid;
    rc = sm_grid_build(dpos, g->vertex_count, g->indices, g->triangle_count, p->spacing, p->nodes,
                       max_cells, g->threads, &grid, err);
    free(dpos);
    if (rc < 0) {
        mr_error_prefix(err, "%s: %s: ", grid_field, asset->path);
        goto fail;
    }
    if ((rc = sm_sim_new(&grid, p, g->threads, &g->sim, err)) < 0) {
        mr_error_prefix(err, "springmass: ");
        goto fail;
    }
    g->tolerance_px = desc->tolerance_px > 0 ? desc->tolerance_px : 0;
    g->map_count = g->tolerance_px > 0 ? LOD_LEVELS : 1;
    for (uint32_t k = 0; k < g->map_count; k++)
        if ((rc = sm_map_new(g->sim, g->map_count > 1 ? LOD_MAPPINGS[k] : p->mapping, g->rest_pos,
                             g->rest_nrm, g->rest_tan, g->vertex_count, g->threads, &g->maps[k],
                             err)) < 0) {
            mr_error_prefix(err, "springmass: ");
            goto fail;
        }
    if (g->map_count > 1 &&
        (!(g->sample_pos = calloc((size_t)g->vertex_count * 3, sizeof(float))) ||
         !(g->sample_nrm = calloc((size_t)g->vertex_count * 3, sizeof(float))))) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "springmass: out of memory");
        goto fail;
    }
    sm_map_apply(g->maps[0], g->sim, g->positions, g->normals, g->tangents, g->threads);
    state_id(g);
    *out = g;
    return MR_OK;
fail:
    springmass_free(g);
    return rc;
}

/* How far g->positions strays from the trilinear sample at the sampled
 * vertices, and *px: the projection at the nearest depth of the box of
 * positions (all of them, or the sampled ones) grown by that distance. */
static double sample_distance(const mr_geom *g, const mr_geom_frame *frame, bool all, double *px)
{
    double worst = 0;
    for (size_t v = 0; v < g->vertex_count; v += LOD_STRIDE) {
        const float *a = g->positions + v * 3, *b = g->sample_pos + v * 3;
        double dx = (double)a[0] - b[0], dy = (double)a[1] - b[1], dz = (double)a[2] - b[2];
        worst = fmax(worst, sqrt(dx * dx + dy * dy + dz * dz));
    }
    mr_vec3 lo = mr_v3(INFINITY, INFINITY, INFINITY), hi = mr_v3(-INFINITY, -INFINITY, -INFINITY);
    for (size_t v = 0; v < g->vertex_count; v += all ? 1 : LOD_STRIDE) {
        mr_vec3 p = mr_v3(g->positions[v * 3], g->positions[v * 3 + 1], g->positions[v * 3 + 2]);
        lo = mr_v3_min(lo, p);
        hi = mr_v3_max(hi, p);
    }
    float pad = (float)worst;
    *px = mr_camera_px_per_unit(&frame->camera, frame->width, frame->height,
                                mr_v3_sub(lo, mr_v3(pad, pad, pad)), mr_v3_add(hi, mr_v3(pad, pad, pad)));
    return worst;
}

/* "tolerance_px": the cheapest mapping whose distance to the trilinear one
 * (the ground truth), projected at this frame's mesh's nearest depth (its
 * bounds grown by the distance), stays below the tolerance; trilinear when
 * none does. How far a mapping strays depends on how the grid deforms, so
 * it is measured each frame, at every LOD_STRIDE-th vertex mapped both
 * ways: the largest distance there is the prediction (a sample, not a
 * bound: the reference passes measure the rest). A candidate that passes
 * on the sample is mapped in full and checked again at the whole mesh's
 * nearest depth. A frame costs the samples (an eighth of a trilinear
 * mapping) and one full mapping. */
static void pick_mapping(mr_geom *g, const mr_geom_frame *frame, unsigned threads)
{
    sm_map_apply_every(g->maps[0], g->sim, LOD_STRIDE, g->sample_pos, g->sample_nrm, threads);
    for (uint32_t k = g->map_count - 1; k >= 1; k--) {
        double px, d;
        /* the candidate's sample, into the mesh's own arrays (mapped in
         * full below, whatever wins) */
        sm_map_apply_every(g->maps[k], g->sim, LOD_STRIDE, g->positions, g->normals, threads);
        d = sample_distance(g, frame, false, &px);
        if (!(isfinite(px) && d * px <= g->tolerance_px))
            continue;
        sm_map_apply(g->maps[k], g->sim, g->positions, g->normals, g->tangents, threads);
        d = sample_distance(g, frame, true, &px);
        if (isfinite(px) && d * px <= g->tolerance_px) {
            g->level = k;
            g->predicted_px = d * px;
            return;
        }
    }
    sm_map_apply(g->maps[0], g->sim, g->positions, g->normals, g->tangents, threads);
    g->level = 0;
    g->predicted_px = 0;
}

static int springmass_update(mr_geom *g, const mr_geom_frame *frame, const mr_pose *pose,
                             const mr_mat4 *transform, unsigned threads, mr_error *err)
{
    (void)pose;
    (void)transform; /* the simulation runs in world space: the transform placed the grid */
    uint64_t target = (uint64_t)(frame ? frame->index : 0) * g->p->steps_per_frame;
    uint64_t now = sm_sim_steps(g->sim);
    if (target < now)
        return mr_error_set(err, MR_ERR_INVALID,
                            "springmass: frame %zu asked for after step %llu (rewind first)",
                            frame ? frame->index : 0, (unsigned long long)now);
    double t0 = mr_now();
    int rc = sm_sim_advance(g->sim, target - now, threads, err);
    double t1 = mr_now();
    g->simulate_s = t1 - t0;
    g->steps = target - now;
    if (rc < 0)
        return mr_error_prefix(err, "springmass: ");
    if (g->map_count > 1 && frame)
        pick_mapping(g, frame, threads);
    else
        sm_map_apply(g->maps[0], g->sim, g->positions, g->normals, g->tangents, threads);
    g->map_s = mr_now() - t1;
    return MR_OK;
}

static int springmass_rewind(mr_geom *g, mr_error *err)
{
    (void)err;
    sm_sim_reset(g->sim, g->threads);
    return MR_OK;
}

static int springmass_attach(mr_geom *g, RTCDevice device, RTCScene scene, unsigned geom_id,
                             enum RTCBuildQuality quality, mr_error *err)
{
    return mr_geom_attach_triangles(device, scene, geom_id, quality, g->positions, g->vertex_count,
                                    g->indices, g->triangle_count, &g->rtc, err);
}

static bool springmass_commit(mr_geom *g)
{
    mr_geom_commit_vertices(g->rtc);
    return true;
}

static mr_vec3 springmass_normal(const mr_geom *g, unsigned prim, float u, float v, mr_vec3 ng)
{
    const uint32_t *tri = g->indices + (size_t)prim * 3;
    const float *n0 = g->normals + (size_t)tri[0] * 3, *n1 = g->normals + (size_t)tri[1] * 3,
                *n2 = g->normals + (size_t)tri[2] * 3;
    float w = 1.0f - u - v;
    return mr_v3(w * n0[0] + u * n1[0] + v * n2[0], w * n0[1] + u * n1[1] + v * n2[1],
                 w * n0[2] + u * n1[2] + v * n2[2]);
}

/* The mapped tangents (map.h) interpolated like the normals. */
static bool springmass_tangent(const mr_geom *g, unsigned prim, float u, float v, mr_vec3 *out)
{
    if (!g->tangents)
        return false;
    const uint32_t *tri = g->indices + (size_t)prim * 3;
    const float *t0 = g->tangents + (size_t)tri[0] * 3, *t1 = g->tangents + (size_t)tri[1] * 3,
                *t2 = g->tangents + (size_t)tri[2] * 3;
    float w = 1.0f - u - v;
    *out = mr_v3(w * t0[0] + u * t1[0] + v * t2[0], w * t0[1] + u * t1[1] + v * t2[1],
                 w * t0[2] + u * t1[2] + v * t2[2]);
    return out->x != 0.0f || out->y != 0.0f || out->z != 0.0f; /* 0: a mesh without */
}

static int springmass_tessellate(const mr_geom *g, mr_trimesh *out, mr_error *err)
{
    return mr_trimesh_copy(g->positions, g->vertex_count, g->indices, g->triangle_count, out, err);
}

static size_t maps_bytes(const mr_geom *g)
{
    size_t b = g->sample_pos ? (size_t)g->vertex_count * 6 * sizeof(float) : 0;
    for (uint32_t k = 0; k < g->map_count; k++)
        b += sm_map_bytes(g->maps[k]);
    return b;
}

static size_t springmass_memory(const mr_geom *g)
{
    return ((size_t)g->vertex_count * (g->rest_tan ? 18 : 12) + 2) * sizeof(float) +
           (size_t)g->triangle_count * 3 * sizeof(uint32_t) + sm_sim_grid(g->sim)->cells * SM_BYTES_PER_CELL +
           maps_bytes(g);
}

static uint64_t springmass_primitives(const mr_geom *g) { return g->triangle_count; }

static const mr_kind_stat SPRINGMASS_STATS[] = {
    {"simulate_s", "s", "Seconds the simulation steps of this frame took", MR_STAT_SUM},
    {"map_s", "s", "Seconds mapping the detailed mesh to the nodes took", MR_STAT_SUM},
    {"sim_steps", "count", "Steps of dt simulated for this frame", MR_STAT_SUM},
    {"sim_substeps", "count", "Substeps per step the stability bound asks for (1: dt is below it)",
     MR_STAT_MAX},
    {"sim_energy", "energy",
     "Kinetic plus spring plus gravity energy (gravity relative to rest) after the frame",
     MR_STAT_SUM},
    {"max_strain", "1", "Largest |length / rest length - 1| of a spring after the frame", MR_STAT_MAX},
    {"inverted_cells", "count", "Grid cells with a corner of non-positive volume (inverted)",
     MR_STAT_SUM},
    {"sim_nodes", "count", "Nodes of the simulation grid", MR_STAT_SUM},
};

/* Level: 0 trilinear, 1 triangle_basis_curvature, 2 triangle_basis. */
static bool springmass_lod(const mr_geom *g, uint32_t *level, double *error_px)
{
    *level = g->level;
    *error_px = g->predicted_px;
    return g->tolerance_px > 0;
}

static void springmass_frame_stats(const mr_geom *g, double *values)
{
    const sm_measure *m = sm_sim_measure(g->sim);
    values[0] = g->simulate_s;
    values[1] = g->map_s;
    values[2] = (double)g->steps;
    values[3] = sm_sim_substeps(g->sim);
    values[4] = m->kinetic + m->spring + m->gravity;
    values[5] = m->max_strain;
    values[6] = m->inverted_cells;
    values[7] = (double)sm_sim_grid(g->sim)->nodes;
}

/* ---- checkpoints */

static uint32_t springmass_checkpoint_every(const mr_geom *g) { return g->p->checkpoint_every; }

static void springmass_checkpoint_id(const mr_geom *g, uint8_t id[32]) { memcpy(id, g->id, 32); }

static int springmass_checkpoint_save(const mr_geom *g, uint64_t frames, uint8_t **buf, size_t *size,
                                      mr_error *err)
{
    (void)frames;
    size_t n = sm_sim_state_bytes(g->sim);
    if (!(*buf = malloc(n)))
        return mr_error_set(err, MR_ERR_NOMEM, "springmass: out of memory for a checkpoint");
    sm_sim_state_save(g->sim, *buf);
    *size = n;
    return MR_OK;
}

static int springmass_checkpoint_load(mr_geom *g, uint64_t frames, const uint8_t *buf, size_t size,
                                      mr_error *err)
{
    /* the state after `frames` frames has simulated up to frame frames - 1 */
    uint64_t want = frames ? (frames - 1) * g->p->steps_per_frame : 0;
    if (size >= 8) {
        uint64_t steps = 0;
        for (int i = 7; i >= 0; i--)
            steps = steps << 8 | buf[i];
        if (steps != want)
            return mr_error_set(err, MR_ERR_FORMAT, "springmass state after %llu steps, want %llu",
                                (unsigned long long)steps, (unsigned long long)want);
    }
    return sm_sim_state_load(g->sim, buf, size, g->threads, err);
}

/* ---- the "springmass" block */

static const char *const MAPPINGS[] = {"one_to_one", "triangle_basis", "triangle_basis_curvature",
                                       "trilinear"};
static const char *const FORCE_TYPES[] = {"point", "wind"};

enum { P_SPACING, P_NODES, P_STIFFNESS, P_SHEAR, P_DAMPING, P_MASS, P_GRAVITY, P_DT, P_STEPS };

static int after_shear(void *values, const bool *given, mr_param_error *err)
{
    (void)err;
    mr_springmass_params *p = values;
    if (!given[P_SHEAR])
        p->shear_stiffness = p->stiffness;
    return MR_OK;
}

static int after_dt(void *values, const bool *given, mr_param_error *err)
{
    const mr_springmass_params *p = values;
    double h_crit;
    if (sm_substeps(p, &h_crit) == 0)
        return mr_param_fail(err, MR_ERR_LIMIT,
                             given[P_DT] ? "dt" : given[P_STIFFNESS] ? "stiffness" : "mass",
                             "dt %g s needs more than %u substeps under the stability bound %.3g s "
                             "(sqrt(mass / (stiffness + 2 shear_stiffness)) = sqrt(%g / (%g + 2 x %g))): "
                             "lower dt or the stiffness, or raise the mass",
                             (double)p->dt, SM_MAX_SUBSTEPS, h_crit, (double)p->mass, (double)p->stiffness,
                             (double)p->shear_stiffness);
    return MR_OK;
}

static int after_steps(void *values, const bool *given, mr_param_error *err)
{
    (void)given;
    const mr_springmass_params *p = values;
    uint64_t per_frame = (uint64_t)p->steps_per_frame * sm_substeps(p, NULL);
    if (per_frame > 100000)
        return mr_param_fail(err, MR_ERR_LIMIT, "steps_per_frame",
                             "%u steps of %u substeps each make %llu per frame, more than 100000",
                             p->steps_per_frame, sm_substeps(p, NULL), (unsigned long long)per_frame);
    return MR_OK;
}

/* Path keys in increasing time. */
#define KEYS_INCREASING(type, keys, count, err)                                                    \
    do {                                                                                           \
        for (size_t k_ = 1; k_ < (count); k_++)                                                    \
            if (!((keys)[k_].t > (keys)[k_ - 1].t))                                                \
                return mr_param_fail(err, MR_ERR_INVALID, "path",                                  \
                                     "keys must have increasing t: key %zu has t = %g, key %zu "   \
                                     "t = %g",                                                     \
                                     k_, (double)(keys)[k_].t, k_ - 1, (double)(keys)[k_ - 1].t);  \
    } while (0)

static int after_key_t(void *values, const bool *given, mr_param_error *err)
{
    (void)values;
    if (!given[0])
        return mr_param_fail(err, MR_ERR_INVALID, "", "a path key needs \"t\"");
    return MR_OK;
}

static int after_probe_position(void *values, const bool *given, mr_param_error *err)
{
    (void)values;
    if (!given[1])
        return mr_param_fail(err, MR_ERR_INVALID, "", "a probe key needs \"position\"");
    return MR_OK;
}

static int after_pin_path(void *values, const bool *given, mr_param_error *err)
{
    (void)given;
    const mr_springmass_pin *pin = values;
    KEYS_INCREASING(mr_springmass_pin_key, pin->path, pin->path_count, err);
    return MR_OK;
}

static int after_pin_box(void *values, const bool *given, mr_param_error *err)
{
    (void)given;
    const mr_springmass_pin *pin = values;
    if (!(pin->box_min.x <= pin->box_max.x && pin->box_min.y <= pin->box_max.y &&
          pin->box_min.z <= pin->box_max.z))
        return mr_param_fail(err, MR_ERR_INVALID, "box_max", "expected box_max >= box_min on every axis");
    return MR_OK;
}

static int after_pin_points(void *values, const bool *given, mr_param_error *err)
{
    (void)err;
    mr_springmass_pin *pin = values;
    pin->points_only = given[2] && !given[0] && !given[1];
    return MR_OK;
}

static int after_pin_pivot(void *values, const bool *given, mr_param_error *err)
{
    (void)err;
    mr_springmass_pin *pin = values;
    pin->has_pivot = given[3];
    return MR_OK;
}

static const mr_param PIN_POINT_PARAMS[] = {
    {.field = "position", .type = MR_PARAM_VEC3, .offset = offsetof(mr_springmass_pin_point, position),
     .lo = -1e9, .hi = 1e9, .description = "Where: the node nearest to it at rest is pinned."},
};
static const mr_param_table PIN_POINT_TABLE = {
    .params = PIN_POINT_PARAMS, .count = 1, .size = sizeof(mr_springmass_pin_point), .expect = "a point object",
    .plural = "point objects", .schema_rules = "{\"required\": [\"position\"]}"};

static int after_probe_path(void *values, const bool *given, mr_param_error *err)
{
    const mr_springmass_probe *pr = values;
    if (!given[1])
        return mr_param_fail(err, MR_ERR_INVALID, "", "a probe needs a path (one key or more)");
    KEYS_INCREASING(mr_springmass_probe_key, pr->path, pr->path_count, err);
    return MR_OK;
}

static int after_force_end(void *values, const bool *given, mr_param_error *err)
{
    (void)given;
    const mr_springmass_force *f = values;
    if (!(f->end > f->start))
        return mr_param_fail(err, MR_ERR_INVALID, "end", "expected end > start (%g), got %g",
                             (double)f->start, (double)f->end);
    return MR_OK;
}

#define COORD 1e9
#define BIG 1e12

static const mr_param PIN_KEY_PARAMS[] = {
    {.field = "t", .type = MR_PARAM_NUMBER, .offset = offsetof(mr_springmass_pin_key, t), .lo = -1e9,
     .hi = 1e9, .flags = MR_PARAM_NO_DEFAULT, .after = after_key_t,
     .description = "Simulation time of the key, seconds."},
    {.field = "translation", .type = MR_PARAM_VEC3, .offset = offsetof(mr_springmass_pin_key, translation),
     .lo = -COORD, .hi = COORD, .description = "Where the pinned nodes are moved."},
    {.field = "rotation", .type = MR_PARAM_QUAT, .offset = offsetof(mr_springmass_pin_key, rotation),
     .description = "How they are turned about the pivot, [x, y, z, w]."},
};
static const mr_param_table PIN_KEY_TABLE = {
    .params = PIN_KEY_PARAMS, .count = 3, .size = sizeof(mr_springmass_pin_key),
    .expect = "a pin key object", .plural = "pin keys", .schema_rules = "{\"required\": [\"t\"]}"};

static const mr_param PIN_PARAMS[] = {
    {.field = "box_min", .type = MR_PARAM_VEC3, .offset = offsetof(mr_springmass_pin, box_min), .lo = -COORD,
     .hi = COORD, .def3 = {-COORD, -COORD, -COORD},
     .description = "Low corner of the box whose nodes (rest positions, world space) are pinned."},
    {.field = "box_max", .type = MR_PARAM_VEC3, .offset = offsetof(mr_springmass_pin, box_max), .lo = -COORD,
     .hi = COORD, .def3 = {COORD, COORD, COORD}, .after = after_pin_box,
     .description = "High corner of that box (default: every node, unless points are given)."},
    {.field = "points", .type = MR_PARAM_ARRAY, .offset = offsetof(mr_springmass_pin, points),
     .count_offset = offsetof(mr_springmass_pin, point_count), .max_items = MR_SPRINGMASS_MAX_POINTS,
     .sub = &PIN_POINT_TABLE, .after = after_pin_points,
     .description = "A node set: the nodes nearest to these points at rest (with a box, both; "
                    "without one, only these)."},
    {.field = "pivot", .type = MR_PARAM_VEC3, .offset = offsetof(mr_springmass_pin, pivot), .lo = -COORD,
     .hi = COORD, .flags = MR_PARAM_NO_DEFAULT, .after = after_pin_pivot,
     .description = "Centre of the path's rotations (default: the pinned nodes' centroid)."},
    {.field = "path", .type = MR_PARAM_ARRAY, .offset = offsetof(mr_springmass_pin, path),
     .count_offset = offsetof(mr_springmass_pin, path_count), .max_items = MR_SPRINGMASS_MAX_KEYS,
     .sub = &PIN_KEY_TABLE, .after = after_pin_path,
     .description = "Keys moving the pinned nodes (default: they stay at rest)."},
};
static const mr_param_table PIN_TABLE = {
    .params = PIN_PARAMS, .count = 5, .size = sizeof(mr_springmass_pin), .expect = "a pin object",
    .plural = "pin objects"};

static const mr_param PROBE_KEY_PARAMS[] = {
    {.field = "t", .type = MR_PARAM_NUMBER, .offset = offsetof(mr_springmass_probe_key, t), .lo = -1e9,
     .hi = 1e9, .flags = MR_PARAM_NO_DEFAULT, .after = after_key_t,
     .description = "Simulation time of the key, seconds."},
    {.field = "position", .type = MR_PARAM_VEC3, .offset = offsetof(mr_springmass_probe_key, position),
     .lo = -COORD, .hi = COORD, .flags = MR_PARAM_NO_DEFAULT, .after = after_probe_position,
     .description = "The probe's centre, world space."},
};
static const mr_param_table PROBE_KEY_TABLE = {
    .params = PROBE_KEY_PARAMS, .count = 2, .size = sizeof(mr_springmass_probe_key),
    .expect = "a probe key object", .plural = "probe keys",
    .schema_rules = "{\"required\": [\"t\", \"position\"]}"};

static const mr_param PROBE_PARAMS[] = {
    {.field = "radius", .type = MR_PARAM_NUMBER, .offset = offsetof(mr_springmass_probe, radius), .lo = 0,
     .hi = COORD, .flags = MR_PARAM_LO_OPEN, .def = 0.1, .description = "Radius of the spherical probe."},
    {.field = "path", .type = MR_PARAM_ARRAY, .offset = offsetof(mr_springmass_probe, path),
     .count_offset = offsetof(mr_springmass_probe, path_count), .max_items = MR_SPRINGMASS_MAX_KEYS,
     .sub = &PROBE_KEY_TABLE, .after = after_probe_path,
     .description = "Keys of the probe's centre (linear between them)."},
};
static const mr_param_table PROBE_TABLE = {
    .params = PROBE_PARAMS, .count = 2, .size = sizeof(mr_springmass_probe), .expect = "a probe object",
    .plural = "probe objects", .schema_rules = "{\"required\": [\"path\"]}"};

static const mr_param FORCE_PARAMS[] = {
    {.field = "type", .type = MR_PARAM_ENUM, .offset = offsetof(mr_springmass_force, type),
     MR_PARAM_CHOICES(FORCE_TYPES), .def = MR_SPRINGMASS_FORCE_POINT,
     .description = "point: on the node nearest to position; wind: on every surface node."},
    {.field = "position", .type = MR_PARAM_VEC3, .offset = offsetof(mr_springmass_force, position),
     .lo = -COORD, .hi = COORD, .description = "Where a point force acts (its nearest node at rest)."},
    {.field = "force", .type = MR_PARAM_VEC3, .offset = offsetof(mr_springmass_force, force), .lo = -BIG,
     .hi = BIG, .description = "The force (wind: on each surface node)."},
    {.field = "start", .type = MR_PARAM_NUMBER, .offset = offsetof(mr_springmass_force, start), .lo = -1e9,
     .hi = 1e9, .def = 0, .description = "Simulation time the force starts, seconds."},
    {.field = "end", .type = MR_PARAM_NUMBER, .offset = offsetof(mr_springmass_force, end), .lo = -1e9,
     .hi = 1e9, .def = 1e9, .after = after_force_end,
     .description = "Simulation time it stops (exclusive), seconds."},
};
static const mr_param_table FORCE_TABLE = {
    .params = FORCE_PARAMS, .count = 5, .size = sizeof(mr_springmass_force), .expect = "a force object",
    .plural = "force objects"};

static const mr_param SPRINGMASS_PARAMS[] = {
    [P_SPACING] = {.field = "spacing", .type = MR_PARAM_NUMBER, .offset = offsetof(mr_springmass_params, spacing),
                   .lo = 0, .hi = COORD, .flags = MR_PARAM_LO_OPEN | MR_PARAM_NO_DEFAULT, .conflicts = "nodes",
                   .description = "Distance between neighbouring nodes, world units (instead of nodes)."},
    [P_NODES] = {.field = "nodes", .type = MR_PARAM_INT, .offset = offsetof(mr_springmass_params, nodes),
                 /* the spacing found lands within 5 % of the count: up to
                  * 20/21 of the cap, so the grid it makes stays within it */
                 .lo = 1, .hi = SM_GRID_MAX_NODES / 21 * 20, .def = 4096,
                 .description = "About how many nodes fill the mesh (the spacing is found for it, within 5 %)."},
    [P_STIFFNESS] = {.field = "stiffness", .type = MR_PARAM_NUMBER,
                     .offset = offsetof(mr_springmass_params, stiffness), .lo = 0, .hi = BIG, .def = 1000,
                     .description = "k of the 6 axis springs of a node (force per unit of stretch)."},
    [P_SHEAR] = {.field = "shear_stiffness", .type = MR_PARAM_NUMBER,
                 .offset = offsetof(mr_springmass_params, shear_stiffness), .lo = 0, .hi = BIG, .flags = MR_PARAM_NO_DEFAULT,
                 .after = after_shear, .description = "k of the 12 diagonal springs (default: stiffness)."},
    [P_DAMPING] = {.field = "damping", .type = MR_PARAM_NUMBER, .offset = offsetof(mr_springmass_params, damping),
                   .lo = 0, .hi = BIG, .def = 0.1,
                   .description = "Viscous damping c: each node feels -c v (implicit: no stability cost)."},
    [P_MASS] = {.field = "mass", .type = MR_PARAM_NUMBER, .offset = offsetof(mr_springmass_params, mass),
                .lo = 0, .hi = BIG, .flags = MR_PARAM_LO_OPEN, .def = 0.01, .description = "Mass of each node."},
    [P_GRAVITY] = {.field = "gravity", .type = MR_PARAM_VEC3, .offset = offsetof(mr_springmass_params, gravity),
                   .lo = -1e6, .hi = 1e6, .def3 = {0, -9.81, 0},
                   .description = "Acceleration of gravity, world units per second squared."},
    [P_DT] = {.field = "dt", .type = MR_PARAM_NUMBER, .offset = offsetof(mr_springmass_params, dt), .lo = 0,
              .hi = 1, .flags = MR_PARAM_LO_OPEN, .def = 1.0 / 360, .after = after_dt,
              .description = "Seconds per step; above 0.9 of the stability bound sqrt(mass / (stiffness + "
                             "2 shear_stiffness)) each step is split into substeps."},
    [P_STEPS] = {.field = "steps_per_frame", .type = MR_PARAM_INT,
                 .offset = offsetof(mr_springmass_params, steps_per_frame), .lo = 1, .hi = 100000, .def = 15,
                 .after = after_steps,
                 .description = "Steps between frames: frame k shows the simulation at k steps_per_frame dt."},
    {.field = "mapping", .type = MR_PARAM_ENUM, .offset = offsetof(mr_springmass_params, mapping),
     MR_PARAM_CHOICES(MAPPINGS), .def = MR_SPRINGMASS_TRIANGLE_CURVATURE,
     .description = "How the detailed mesh follows the nodes: one_to_one (3.2), triangle_basis (3.3.1), "
                    "triangle_basis_curvature (3.3.2) or trilinear (the cell's trilinear displacement, the "
                    "reference). With \"tolerance_px\" each frame picks the cheapest of triangle_basis, "
                    "triangle_basis_curvature and trilinear that stays within it instead."},
    {.field = "checkpoint_every", .type = MR_PARAM_INT,
     .offset = offsetof(mr_springmass_params, checkpoint_every), .lo = 0, .hi = 100000, .def = 8,
     .description = "Frames between checkpoints of the simulation state (0: none)."},
    {.field = "pins", .type = MR_PARAM_ARRAY, .offset = offsetof(mr_springmass_params, pins),
     .count_offset = offsetof(mr_springmass_params, pin_count), .max_items = MR_SPRINGMASS_MAX_PINS,
     .sub = &PIN_TABLE, .description = "Nodes held in place or moved along a path (the first pin holding a node wins)."},
    {.field = "probes", .type = MR_PARAM_ARRAY, .offset = offsetof(mr_springmass_params, probes),
     .count_offset = offsetof(mr_springmass_params, probe_count), .max_items = MR_SPRINGMASS_MAX_PROBES,
     .sub = &PROBE_TABLE, .description = "Spheres pressing nodes out of their way along a path."},
    {.field = "forces", .type = MR_PARAM_ARRAY, .offset = offsetof(mr_springmass_params, forces),
     .count_offset = offsetof(mr_springmass_params, force_count), .max_items = MR_SPRINGMASS_MAX_FORCES,
     .sub = &FORCE_TABLE, .description = "Point forces and wind over time."},
};

static const mr_param_table SPRINGMASS_TABLE = {
    .params = SPRINGMASS_PARAMS,
    .count = sizeof SPRINGMASS_PARAMS / sizeof SPRINGMASS_PARAMS[0],
    .size = sizeof(mr_springmass_params),
    .expect = "an object of springmass parameters",
};

/* References (kind.h): "tessellated" is the object itself (its Embree form
 * is the mapped mesh's own triangles); "ground_truth" is the same
 * simulation followed by the trilinear mapping (each vertex displaced with
 * its grid cell), which the paper's mappings approximate. An object mapped
 * trilinearly has none beyond itself, unless a tolerance lets it pick
 * other mappings. */
static int springmass_reference(const mr_object_desc *obj, mr_reference_type type,
                                mr_reference_objects *out, mr_error *err)
{
    const mr_springmass_params *src = obj->params;
    if (type == MR_REFERENCE_TESSELLATED)
        return mr_reference_objects_add(out, obj, err);
    if (src->mapping == MR_SPRINGMASS_TRILINEAR && !(obj->tolerance_px > 0))
        return MR_OK;
    mr_springmass_params *p = mr_reference_alloc(out, sizeof *p, err);
    if (!p)
        return MR_ERR_NOMEM;
    *p = *src;
    p->mapping = MR_SPRINGMASS_TRILINEAR;
    mr_object_desc d = *obj;
    d.params = p;
    return mr_reference_objects_add(out, &d, err);
}

const mr_kind mr_kind_springmass = {
    .name = "springmass",
    .summary = "Parameters of a spring-mass object (kind \"springmass\", paper 001): a grid of nodes "
               "filling the asset is simulated and the detailed mesh follows it through a mapping.",
    .params = &SPRINGMASS_TABLE,
    .frame_order = MR_FRAMES_SEQUENTIAL,
    .has_derived = true,
    .stats = SPRINGMASS_STATS,
    .stat_count = sizeof SPRINGMASS_STATS / sizeof SPRINGMASS_STATS[0],
    .self_posed = true,
    .takes_no_pose = true,
    .create = springmass_create,
    .update = springmass_update,
    .attach = springmass_attach,
    .commit = springmass_commit,
    .normal = springmass_normal,
    .tangent = springmass_tangent,
    .tessellate = springmass_tessellate,
    .memory = springmass_memory,
    .primitives = springmass_primitives,
    .has_lod = true,
    .lod = springmass_lod,
    .frame_stats = springmass_frame_stats,
    .rewind = springmass_rewind,
    .checkpoint_every = springmass_checkpoint_every,
    .checkpoint_id = springmass_checkpoint_id,
    .checkpoint_save = springmass_checkpoint_save,
    .checkpoint_load = springmass_checkpoint_load,
    .reference = springmass_reference,
    .free = springmass_free,
};
