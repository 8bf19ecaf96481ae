/* kind.c - a kind's public accessors (microray.h) and helpers shared by
 * geometry kinds (kind.h): triangle soups and Embree triangle geometries.
 * The registry is registry.c. */
#include "kinds/kind.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

const char *mr_kind_name(const mr_kind *kind) { return kind ? kind->name : NULL; }
const char *mr_kind_summary(const mr_kind *kind) { return kind ? kind->summary : NULL; }
const mr_param_table *mr_kind_params(const mr_kind *kind) { return kind ? kind->params : NULL; }
bool mr_kind_keeps_derived(const mr_kind *kind) { return kind && kind->has_derived; }
bool mr_kind_takes_pose(const mr_kind *kind) { return !kind || !kind->takes_no_pose; }

bool mr_object_derives(const mr_object_desc *desc)
{
    const mr_kind *k = desc ? desc->kind : NULL;
    return k && k->has_derived && (!k->derives || k->derives(desc));
}

size_t mr_kind_stat_count(const mr_kind *kind) { return kind ? kind->stat_count : 0; }

const mr_kind_stat *mr_kind_stat_at(const mr_kind *kind, size_t i)
{
    return kind && i < kind->stat_count ? &kind->stats[i] : NULL;
}

/* An object's memory floor (kind.h). */
static size_t object_floor(const mr_object_desc *o)
{
    return o->kind && o->kind->memory_floor ? o->kind->memory_floor(o->params) : 0;
}

size_t mr_job_memory_floor(const mr_job *job)
{
    size_t total = 0;
    for (size_t i = 0; i < job->object_count; i++) {
        size_t floor = object_floor(&job->objects[i]);
        total = floor > SIZE_MAX - total ? SIZE_MAX : total + floor;
    }
    return total;
}

int mr_job_check_memory(const mr_job *job, size_t budget, char pointer[512], mr_error *err)
{
    pointer[0] = '\0';
    if (!budget)
        return MR_OK;
    size_t total = mr_job_memory_floor(job), largest = 0, worst = 0;
    if (total <= budget)
        return MR_OK;
    for (size_t i = 0; i < job->object_count; i++) {
        size_t floor = object_floor(&job->objects[i]);
        if (floor > largest) {
            largest = floor;
            worst = i;
        }
    }
    const mr_kind *k = job->objects[worst].kind;
    snprintf(pointer, 512, "/objects/%zu/%s/%s", worst, k->name, k->memory_field);
    char need[MR_BYTES_TEXT], most[MR_BYTES_TEXT], cap[MR_BYTES_TEXT];
    mr_format_bytes(total, need, sizeof need);
    mr_format_bytes(largest, most, sizeof most);
    mr_format_bytes(budget, cap, sizeof cap);
    return mr_error_set(err, MR_ERR_LIMIT, "the job's objects need at least %s of geometry (%s "
                        "for this one's %s), over the job memory budget of %s", need, most,
                        k->memory_field, cap);
}

/* ---- the objects of a reference pass ---- */

int mr_reference_objects_add(mr_reference_objects *out, const mr_object_desc *desc, mr_error *err)
{
    if (out->count == out->cap) {
        size_t cap = out->cap ? 2 * out->cap : 8;
        mr_object_desc *grown = realloc(out->objects, cap * sizeof *grown);
        if (!grown)
            return mr_error_set(err, MR_ERR_NOMEM, "out of memory for a reference pass's objects");
        out->objects = grown;
        out->cap = cap;
    }
    out->objects[out->count++] = *desc;
    return MR_OK;
}

void *mr_reference_alloc(mr_reference_objects *out, size_t bytes, mr_error *err)
{
    if (out->block_count == out->block_cap) {
        size_t cap = out->block_cap ? 2 * out->block_cap : 8;
        void **grown = realloc(out->blocks, cap * sizeof *grown);
        if (!grown) {
            mr_error_set(err, MR_ERR_NOMEM, "out of memory for a reference pass's objects");
            return NULL;
        }
        out->blocks = grown;
        out->block_cap = cap;
    }
    void *p = calloc(1, bytes ? bytes : 1);
    if (!p) {
        mr_error_set(err, MR_ERR_NOMEM, "out of memory for a reference pass's objects");
        return NULL;
    }
    return out->blocks[out->block_count++] = p;
}

void mr_reference_objects_clear(mr_reference_objects *out)
{
    for (size_t i = 0; i < out->block_count; i++)
        free(out->blocks[i]);
    free(out->blocks);
    free(out->objects);
    *out = (mr_reference_objects){0};
}

int mr_trimesh_copy(const float *positions, uint32_t vertex_count, const uint32_t *indices,
                    uint32_t triangle_count, mr_trimesh *out, mr_error *err)
{
    *out = (mr_trimesh){0};
    out->positions = malloc((size_t)vertex_count * 3 * sizeof(float));
    out->indices = malloc((size_t)triangle_count * 3 * sizeof(uint32_t));
    if (!out->positions || !out->indices) {
        mr_trimesh_free(out);
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory copying %u triangles", triangle_count);
    }
    memcpy(out->positions, positions, (size_t)vertex_count * 3 * sizeof(float));
    memcpy(out->indices, indices, (size_t)triangle_count * 3 * sizeof(uint32_t));
    out->vertex_count = vertex_count;
    out->triangle_count = triangle_count;
    return MR_OK;
}

int mr_geom_attach_triangles(RTCDevice device, RTCScene scene, unsigned geom_id,
                             enum RTCBuildQuality quality, float *positions, uint32_t vertex_count,
                             uint32_t *indices, uint32_t triangle_count, RTCGeometry *out,
                             mr_error *err)
{
    RTCGeometry g = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
    *out = g;
    if (!g)
        return mr_error_set(err, MR_ERR_EMBREE, "Embree could not create a triangle geometry");
    rtcSetGeometryBuildQuality(g, quality);
    rtcSetSharedGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, positions, 0,
                               3 * sizeof(float), vertex_count);
    rtcSetSharedGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, indices, 0,
                               3 * sizeof(uint32_t), triangle_count);
    rtcCommitGeometry(g);
    rtcAttachGeometryByID(scene, g, geom_id);
    return MR_OK;
}

int mr_geom_attach_user(RTCDevice device, RTCScene scene, unsigned geom_id,
                        enum RTCBuildQuality quality, unsigned count, void *user,
                        RTCBoundsFunction bounds, RTCIntersectFunctionN intersect,
                        RTCOccludedFunctionN occluded, const char *what, RTCGeometry *out,
                        mr_error *err)
{
    *out = NULL;
    RTCGeometry geom = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_USER);
    if (!geom)
        return mr_error_set(err, MR_ERR_EMBREE, "Embree could not create the %s user geometry (%d)", what,
                            (int)rtcGetDeviceError(device));
    rtcSetGeometryUserPrimitiveCount(geom, count);
    rtcSetGeometryUserData(geom, user);
    rtcSetGeometryBoundsFunction(geom, bounds, NULL);
    rtcSetGeometryIntersectFunction(geom, intersect);
    rtcSetGeometryOccludedFunction(geom, occluded);
    rtcSetGeometryBuildQuality(geom, quality == RTC_BUILD_QUALITY_REFIT ? RTC_BUILD_QUALITY_LOW : quality);
    rtcCommitGeometry(geom);
    if (geom_id == RTC_INVALID_GEOMETRY_ID)
        rtcAttachGeometry(scene, geom);
    else
        rtcAttachGeometryByID(scene, geom, geom_id);
    if (rtcGetDeviceError(device) != RTC_ERROR_NONE) {
        rtcReleaseGeometry(geom);
        return mr_error_set(err, MR_ERR_EMBREE, "Embree refused the %s user geometry", what);
    }
    *out = geom;
    return MR_OK;
}

void mr_geom_commit_vertices(RTCGeometry geom)
{
    rtcUpdateGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0);
    rtcCommitGeometry(geom);
}

void mr_trimesh_free(mr_trimesh *m)
{
    if (!m)
        return;
    free(m->positions);
    free(m->indices);
    *m = (mr_trimesh){0};
}
