/*
 * springmass_fixture.h - meshes and set-ups for the spring-mass kind's
 * tests (core/kinds/springmass/): an indexed UV sphere (optionally with
 * holes), boxes (a slab thinner than a node spacing), and the kind's
 * default parameters. Meshes may carry tangents (3.3.4): the sphere its
 * analytic ones, others a fixed direction fitted to each normal.
 */
#ifndef SPRINGMASS_FIXTURE_H
#define SPRINGMASS_FIXTURE_H

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "kinds/params.h"
#include "math/mr_math.h"
#include "kinds/springmass/grid.h"
#include "kinds/springmass/map.h"
#include "kinds/springmass/sim.h"
#include "kinds/springmass/springmass_kind.h"

typedef struct sm_mesh {
    uint32_t vertex_count, triangle_count;
    double *pos;     /* 3 per vertex */
    float *fpos;     /* the same as floats */
    float *nrm;      /* 3 per vertex, unit */
    float *tan;      /* 3 per vertex, unit and orthogonal to nrm; NULL: none */
    uint32_t *tri;   /* 3 per triangle */
} sm_mesh;

static inline void sm_mesh_free(sm_mesh *m)
{
    free(m->pos);
    free(m->fpos);
    free(m->nrm);
    free(m->tan);
    free(m->tri);
    memset(m, 0, sizeof *m);
}

static inline void sm_mesh_alloc(sm_mesh *m, uint32_t nv, uint32_t nt)
{
    m->vertex_count = nv;
    m->triangle_count = nt;
    m->pos = calloc((size_t)nv * 3, sizeof *m->pos);
    m->fpos = calloc((size_t)nv * 3 + 1, sizeof *m->fpos);
    m->nrm = calloc((size_t)nv * 3 + 1, sizeof *m->nrm);
    m->tri = calloc((size_t)nt * 3, sizeof *m->tri);
    m->tan = NULL; /* a mesh without tangents unless one is given */
}

static inline void sm_mesh_sync(sm_mesh *m)
{
    for (size_t k = 0; k < (size_t)m->vertex_count * 3; k++)
        m->fpos[k] = (float)m->pos[k];
}

/* A closed, outward-oriented UV sphere of `rings` x `segments` around c. */
static inline void sm_mesh_sphere(sm_mesh *m, double cx, double cy, double cz, double r, uint32_t rings,
                           uint32_t segments)
{
    uint32_t nv = 2 + (rings - 1) * segments, nt = 2 * segments * (rings - 1);
    sm_mesh_alloc(m, nv, nt);
    double unit[3];
    for (uint32_t v = 0; v < nv; v++) {
        if (v == 0) {
            unit[0] = 0, unit[1] = 1, unit[2] = 0;
        } else if (v == nv - 1) {
            unit[0] = 0, unit[1] = -1, unit[2] = 0;
        } else {
            uint32_t ring = (v - 1) / segments + 1, seg = (v - 1) % segments;
            double th = M_PI * ring / rings, ph = 2 * M_PI * seg / segments;
            unit[0] = sin(th) * cos(ph);
            unit[1] = cos(th);
            unit[2] = sin(th) * sin(ph);
        }
        m->pos[v * 3] = cx + r * unit[0];
        m->pos[v * 3 + 1] = cy + r * unit[1];
        m->pos[v * 3 + 2] = cz + r * unit[2];
        for (int a = 0; a < 3; a++)
            m->nrm[v * 3 + a] = (float)unit[a];
    }
    /* tangents along the segments' direction (increasing longitude; x at
     * the poles) */
    m->tan = calloc((size_t)nv * 3 + 1, sizeof *m->tan);
    for (uint32_t v = 0; v < nv; v++) {
        double ph = v == 0 || v == nv - 1 ? 0 : 2 * M_PI * ((v - 1) % segments) / segments;
        m->tan[v * 3] = (float)-sin(ph);
        m->tan[v * 3 + 2] = (float)cos(ph);
        if (v == 0 || v == nv - 1)
            m->tan[v * 3] = 1, m->tan[v * 3 + 2] = 0;
    }
    uint32_t t = 0;
#define RV(ring, seg) (1 + ((ring) - 1) * segments + (seg) % segments)
    for (uint32_t s = 0; s < segments; s++) { /* caps, outward (counter-clockwise seen from outside) */
        uint32_t a = RV(1, s), b = RV(1, s + 1);
        m->tri[t * 3] = 0, m->tri[t * 3 + 1] = b, m->tri[t * 3 + 2] = a, t++;
        a = RV(rings - 1, s), b = RV(rings - 1, s + 1);
        m->tri[t * 3] = nv - 1, m->tri[t * 3 + 1] = a, m->tri[t * 3 + 2] = b, t++;
    }
    for (uint32_t ring = 1; ring + 1 < rings; ring++)
        for (uint32_t s = 0; s < segments; s++) {
            uint32_t a = RV(ring, s), b = RV(ring, s + 1), c = RV(ring + 1, s), d = RV(ring + 1, s + 1);
            m->tri[t * 3] = a, m->tri[t * 3 + 1] = b, m->tri[t * 3 + 2] = d, t++;
            m->tri[t * 3] = a, m->tri[t * 3 + 1] = d, m->tri[t * 3 + 2] = c, t++;
        }
#undef RV
    m->triangle_count = t;
    sm_mesh_sync(m);
}

/* Removes every k-th triangle from `first` on, `count` of them: holes. */
static inline void sm_mesh_punch(sm_mesh *m, uint32_t first, uint32_t k, uint32_t count)
{
    uint32_t out = 0;
    for (uint32_t t = 0; t < m->triangle_count; t++) {
        bool gone = t >= first && (t - first) % k == 0 && (t - first) / k < count;
        if (!gone) {
            memmove(m->tri + (size_t)out * 3, m->tri + (size_t)t * 3, 3 * sizeof *m->tri);
            out++;
        }
    }
    m->triangle_count = out;
}

/* An axis-aligned box lo..hi, 12 outward triangles, 24 vertices (face
 * normals). */
static inline void sm_mesh_box(sm_mesh *m, const double lo[3], const double hi[3])
{
    sm_mesh_alloc(m, 24, 12);
    static const int faces[6][4][3] = {
        {{1, 0, 0}, {1, 1, 0}, {1, 1, 1}, {1, 0, 1}}, {{0, 0, 0}, {0, 0, 1}, {0, 1, 1}, {0, 1, 0}},
        {{0, 1, 0}, {0, 1, 1}, {1, 1, 1}, {1, 1, 0}}, {{0, 0, 0}, {1, 0, 0}, {1, 0, 1}, {0, 0, 1}},
        {{0, 0, 1}, {1, 0, 1}, {1, 1, 1}, {0, 1, 1}}, {{0, 0, 0}, {0, 1, 0}, {1, 1, 0}, {1, 0, 0}}};
    static const float normals[6][3] = {{1, 0, 0}, {-1, 0, 0}, {0, 1, 0}, {0, -1, 0}, {0, 0, 1}, {0, 0, -1}};
    for (int f = 0; f < 6; f++) {
        for (int q = 0; q < 4; q++)
            for (int a = 0; a < 3; a++) {
                m->pos[(f * 4 + q) * 3 + a] = faces[f][q][a] ? hi[a] : lo[a];
                m->nrm[(f * 4 + q) * 3 + a] = normals[f][a];
            }
        uint32_t b = (uint32_t)f * 4;
        uint32_t t[6] = {b, b + 1, b + 2, b, b + 2, b + 3};
        memcpy(m->tri + f * 6, t, sizeof t);
    }
    sm_mesh_sync(m);
}

/* Tangents for a mesh that has none: dir fitted to each vertex normal
 * (mr_v3_tangent_to, its fixed choice where dir lies along the normal). */
static inline void sm_mesh_fit_tangents(sm_mesh *m, mr_vec3 dir)
{
    free(m->tan);
    m->tan = calloc((size_t)m->vertex_count * 3 + 1, sizeof *m->tan);
    for (uint32_t v = 0; v < m->vertex_count; v++) {
        mr_vec3 t = mr_v3_tangent_to(dir, mr_v3(m->nrm[v * 3], m->nrm[v * 3 + 1], m->nrm[v * 3 + 2]), true);
        m->tan[v * 3] = t.x;
        m->tan[v * 3 + 1] = t.y;
        m->tan[v * 3 + 2] = t.z;
    }
}

/* The kind's defaults (its parameter table), as a job without a block gets. */
static inline mr_springmass_params sm_default_params(void)
{
    mr_springmass_params p;
    mr_params_defaults(mr_kind_params(&mr_kind_springmass), &p);
    p.shear_stiffness = p.stiffness; /* the after hook's default */
    return p;
}

/* Largest |a - b| over n floats. */
static inline double sm_max_diff(const float *a, const float *b, size_t n)
{
    double d = 0;
    for (size_t i = 0; i < n; i++)
        d = fmax(d, fabs((double)a[i] - b[i]));
    return d;
}

#endif
