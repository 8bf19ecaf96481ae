/*
 * closest_mesh.c - distances from points to a triangle mesh (closest_mesh.h).
 */
#include "math/closest_mesh.h"

#include <math.h>
#include <string.h>

typedef struct d3 { double x, y, z; } d3;
static d3 d3_sub(d3 a, d3 b) { return (d3){a.x - b.x, a.y - b.y, a.z - b.z}; }
static double d3_dot(d3 a, d3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
static d3 d3_mad(d3 a, d3 b, double s) { return (d3){a.x + b.x * s, a.y + b.y * s, a.z + b.z * s}; }

/* Squared distance from p to triangle (a, b, c) and its closest point, by
 * the Voronoi regions of the vertices, edges and face. */
static double point_triangle_dist2(d3 p, d3 a, d3 b, d3 c, d3 *closest)
{
    d3 ab = d3_sub(b, a), ac = d3_sub(c, a), ap = d3_sub(p, a), q;
    double d1 = d3_dot(ab, ap), d2 = d3_dot(ac, ap);
    if (d1 <= 0 && d2 <= 0) {
        q = a;
        goto done;
    }
    d3 bp = d3_sub(p, b);
    double d3v = d3_dot(ab, bp), d4 = d3_dot(ac, bp);
    if (d3v >= 0 && d4 <= d3v) {
        q = b;
        goto done;
    }
    double vc = d1 * d4 - d3v * d2;
    if (vc <= 0 && d1 >= 0 && d3v <= 0) {
        q = d3_mad(a, ab, d1 / (d1 - d3v));
        goto done;
    }
    d3 cp = d3_sub(p, c);
    double d5 = d3_dot(ab, cp), d6 = d3_dot(ac, cp);
    if (d6 >= 0 && d5 <= d6) {
        q = c;
        goto done;
    }
    double vb = d5 * d2 - d1 * d6;
    if (vb <= 0 && d2 >= 0 && d6 <= 0) {
        q = d3_mad(a, ac, d2 / (d2 - d6));
        goto done;
    }
    double va = d3v * d6 - d5 * d4;
    if (va <= 0 && (d4 - d3v) >= 0 && (d5 - d6) >= 0) {
        q = d3_mad(b, d3_sub(c, b), (d4 - d3v) / ((d4 - d3v) + (d5 - d6)));
        goto done;
    }
    {
        double denom = va + vb + vc;
        if (!(denom > 0)) { /* degenerate triangle: its vertices are close enough */
            double da = d3_dot(ap, ap), db = d3_dot(bp, bp), dc = d3_dot(cp, cp);
            *closest = da <= db && da <= dc ? a : db <= dc ? b : c;
            return fmin(da, fmin(db, dc));
        }
        q = d3_mad(d3_mad(a, ab, vb / denom), ac, vc / denom);
    }
done : {
    *closest = q;
    d3 e = d3_sub(p, q);
    return d3_dot(e, e);
}
}

typedef struct query_ctx {
    const float *pos;
    const uint32_t *idx;
    double best2;
    d3 best;
    uint32_t prim;
} query_ctx;

static d3 vtx(const float *pos, uint32_t i) { return (d3){pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]}; }

static bool query_cb(struct RTCPointQueryFunctionArguments *args)
{
    query_ctx *c = args->userPtr;
    const uint32_t *t = c->idx + 3 * (size_t)args->primID;
    d3 p = {args->query->x, args->query->y, args->query->z};
    d3 q;
    double dd = point_triangle_dist2(p, vtx(c->pos, t[0]), vtx(c->pos, t[1]), vtx(c->pos, t[2]), &q);
    if (dd < c->best2) {
        c->best2 = dd;
        c->best = q;
        c->prim = args->primID;
        /* float radius rounded up so the true closest is never culled */
        args->query->radius = nextafterf((float)sqrt(dd), INFINITY);
        return true;
    }
    return false;
}

int mr_closest_mesh_init(mr_closest_mesh *m, RTCDevice device, const float *pos, uint32_t nv,
                         const uint32_t *idx, uint32_t nt, const char *who, mr_error *err)
{
    memset(m, 0, sizeof *m);
    m->pos = pos;
    m->idx = idx;
    m->own_device = !device;
    m->device = device ? device : rtcNewDevice(NULL);
    if (!m->device)
        return mr_error_set(err, MR_ERR_EMBREE, "%s: rtcNewDevice failed", who);
    m->scene = rtcNewScene(m->device);
    rtcSetSceneFlags(m->scene, RTC_SCENE_FLAG_ROBUST);
    RTCGeometry geom = rtcNewGeometry(m->device, RTC_GEOMETRY_TYPE_TRIANGLE);
    float *vb = rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                        3 * sizeof(float), nv);
    unsigned *ib = rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                           3 * sizeof(unsigned), nt);
    if (vb && ib) {
        memcpy(vb, pos, (size_t)nv * 3 * sizeof(float));
        memcpy(ib, idx, (size_t)nt * 3 * sizeof(unsigned));
        rtcCommitGeometry(geom);
        rtcAttachGeometry(m->scene, geom);
    }
    rtcReleaseGeometry(geom);
    rtcCommitScene(m->scene);
    enum RTCError e = rtcGetDeviceError(m->device);
    if (e != RTC_ERROR_NONE || !vb || !ib) {
        mr_closest_mesh_free(m);
        return mr_error_set(err, e == RTC_ERROR_OUT_OF_MEMORY ? MR_ERR_NOMEM : MR_ERR_EMBREE,
                            "%s: building the Embree scene failed (error %d)", who, (int)e);
    }
    return MR_OK;
}

double mr_closest_mesh_nearest(const mr_closest_mesh *m, const double p[3], double at[3],
                               uint32_t *prim)
{
    struct RTCPointQuery q;
    q.x = (float)p[0], q.y = (float)p[1], q.z = (float)p[2], q.time = 0, q.radius = INFINITY;
    struct RTCPointQueryContext qc;
    rtcInitPointQueryContext(&qc);
    query_ctx c = {m->pos, m->idx, INFINITY, {0, 0, 0}, UINT32_MAX};
    rtcPointQuery(m->scene, &q, &qc, query_cb, &c);
    if (at)
        at[0] = c.best.x, at[1] = c.best.y, at[2] = c.best.z;
    if (prim)
        *prim = c.prim;
    return sqrt(c.best2);
}

double mr_closest_mesh_distance(const mr_closest_mesh *m, const double p[3], double at[3])
{
    return mr_closest_mesh_nearest(m, p, at, NULL);
}

void mr_closest_mesh_free(mr_closest_mesh *m)
{
    if (m->scene)
        rtcReleaseScene(m->scene);
    if (m->device && m->own_device)
        rtcReleaseDevice(m->device);
    memset(m, 0, sizeof *m);
}
