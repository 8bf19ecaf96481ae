/*
 * micromesh.c - micro-mesh topology and displaced micro-vertex evaluation
 * (micromesh.h). The edge rule and the numerics are explained in the header;
 * the point of this file is that one code path computes every micro-vertex
 * of a base edge, from that edge's data only.
 */
#include "geom/micromesh.h"

#include <string.h>

typedef struct dvec3 { double x, y, z; } dvec3;

uint32_t mr_umesh_segments(unsigned level)
{
    return level > MR_UMESH_MAX_LEVEL ? 0u : 1u << level;
}

uint32_t mr_umesh_vertex_count(unsigned level)
{
    uint32_t n = mr_umesh_segments(level);
    return n ? (n + 1) * (n + 2) / 2 : 0u;
}

uint32_t mr_umesh_triangle_count(unsigned level)
{
    uint32_t n = mr_umesh_segments(level);
    return n * n;
}

/* Index of the first vertex of row b: rows 0..b-1 hold n+1, n, ..., n-b+2. */
static uint32_t row_start(uint32_t n, uint32_t b)
{
    return b * (n + 1) - b * (b - 1) / 2;
}

uint32_t mr_umesh_vertex_index(unsigned level, uint32_t a, uint32_t b)
{
    uint32_t n = mr_umesh_segments(level);
    if (!n || a > n || b > n || a + b > n)
        return UINT32_MAX;
    return row_start(n, b) + a;
}

bool mr_umesh_vertex_coords(unsigned level, uint32_t index, uint32_t *a, uint32_t *b)
{
    uint32_t n = mr_umesh_segments(level);
    if (!n || index >= mr_umesh_vertex_count(level))
        return false;
    uint32_t row = 0;
    /* at most 33 rows: a linear walk is simpler than inverting the quadratic */
    while (row < n && row_start(n, row + 1) <= index)
        row++;
    *a = index - row_start(n, row);
    *b = row;
    return true;
}

bool mr_umesh_vertex_bary(unsigned level, uint32_t index, float *u, float *v)
{
    uint32_t a, b;
    if (!mr_umesh_vertex_coords(level, index, &a, &b))
        return false;
    float n = (float)mr_umesh_segments(level);
    *u = (float)a / n;
    *v = (float)b / n;
    return true;
}

int mr_umesh_vertex_edge(unsigned level, uint32_t a, uint32_t b, uint32_t *k)
{
    uint32_t n = mr_umesh_segments(level);
    uint32_t kk = 0;
    int e = -1;
    if (a == 0 && b == 0) {
        e = 3, kk = 0;
    } else if (a == n && b == 0) {
        e = 3, kk = 1;
    } else if (a == 0 && b == n) {
        e = 3, kk = 2;
    } else if (b == 0) {
        e = 0, kk = a;
    } else if (a + b == n) {
        e = 1, kk = b;
    } else if (a == 0) {
        e = 2, kk = n - b;
    }
    if (k)
        *k = kk;
    return e;
}

bool mr_umesh_triangle(unsigned level, uint32_t tri, uint32_t idx[3])
{
    uint32_t n = mr_umesh_segments(level);
    if (tri >= n * n)
        return false;
    /* row b holds 2(n-b)-1 triangles; rows 0..b-1 hold b(2n-b) */
    uint32_t b = 0;
    while (b < n && (b + 1) * (2 * n - b - 1) <= tri)
        b++;
    uint32_t r = tri - b * (2 * n - b);
    uint32_t a = r / 2;
    if (r % 2 == 0) {
        idx[0] = mr_umesh_vertex_index(level, a, b);
        idx[1] = mr_umesh_vertex_index(level, a + 1, b);
        idx[2] = mr_umesh_vertex_index(level, a, b + 1);
    } else {
        idx[0] = mr_umesh_vertex_index(level, a + 1, b);
        idx[1] = mr_umesh_vertex_index(level, a + 1, b + 1);
        idx[2] = mr_umesh_vertex_index(level, a, b + 1);
    }
    return true;
}

uint32_t mr_umesh_vertex_remap(unsigned level, unsigned decimate_mask, uint32_t index)
{
    uint32_t a, b, k;
    if (!mr_umesh_vertex_coords(level, index, &a, &b))
        return UINT32_MAX;
    uint32_t n = mr_umesh_segments(level);
    int e = mr_umesh_vertex_edge(level, a, b, &k);
    if (e < 0 || e > 2 || !(decimate_mask & (1u << e)) || k % 2 == 0)
        return index;
    /* odd vertex: collapse onto step k-1 of the same edge (k-1 >= 0 is even,
     * so it is a corner or an even edge vertex, which is never moved) */
    uint32_t j = k - 1;
    switch (e) {
    case 0: return mr_umesh_vertex_index(level, j, 0);
    case 1: return mr_umesh_vertex_index(level, n - j, j);
    default: return mr_umesh_vertex_index(level, 0, n - j);
    }
}

uint32_t mr_umesh_triangles(unsigned level, unsigned decimate_mask, uint32_t *out)
{
    uint32_t count = mr_umesh_triangle_count(level), kept = 0;
    for (uint32_t t = 0; t < count; t++) {
        uint32_t idx[3];
        mr_umesh_triangle(level, t, idx);
        for (int i = 0; i < 3; i++)
            idx[i] = mr_umesh_vertex_remap(level, decimate_mask, idx[i]);
        if (idx[0] == idx[1] || idx[1] == idx[2] || idx[2] == idx[0])
            continue;
        memcpy(out + 3 * kept, idx, sizeof idx);
        kept++;
    }
    return kept;
}

static uint32_t fbits(float f)
{
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    return u;
}

/* Total order on an endpoint's (position, direction) bit patterns. It need
 * not mean anything geometrically: both triangles only have to agree. */
static int endpoint_cmp(mr_vec3 pa, mr_vec3 da, mr_vec3 pb, mr_vec3 db)
{
    const float ka[6] = {pa.x, pa.y, pa.z, da.x, da.y, da.z};
    const float kb[6] = {pb.x, pb.y, pb.z, db.x, db.y, db.z};
    for (int i = 0; i < 6; i++) {
        uint32_t x = fbits(ka[i]), y = fbits(kb[i]);
        if (x != y)
            return x < y ? -1 : 1;
    }
    return 0;
}

static dvec3 dv(mr_vec3 v) { return (dvec3){v.x, v.y, v.z}; }

static dvec3 lerp2(mr_vec3 p, double wp, mr_vec3 q, double wq)
{
    return (dvec3){wp * p.x + wq * q.x, wp * p.y + wq * q.y, wp * p.z + wq * q.z};
}

/* Undisplaced point and direction in double, by the edge rule. */
static void frame_d(const mr_umesh_tri *tri, unsigned level, uint32_t a, uint32_t b, dvec3 *p,
                    dvec3 *d)
{
    uint32_t k, n = mr_umesh_segments(level);
    int e = mr_umesh_vertex_edge(level, a, b, &k);
    if (e == 3) {
        *p = dv(tri->pos[k]);
        *d = dv(tri->dir[k]);
        return;
    }
    if (e >= 0) {
        int i0 = e, i1 = (e + 1) % 3;
        uint32_t k0 = n - k, k1 = k; /* weights (in units of 1/n) of i0 and i1 */
        if (endpoint_cmp(tri->pos[i0], tri->dir[i0], tri->pos[i1], tri->dir[i1]) > 0) {
            int ti = i0;
            i0 = i1, i1 = ti;
            uint32_t tk = k0;
            k0 = k1, k1 = tk;
        }
        double w0 = (double)k0 / n, w1 = (double)k1 / n;
        *p = lerp2(tri->pos[i0], w0, tri->pos[i1], w1);
        *d = lerp2(tri->dir[i0], w0, tri->dir[i1], w1);
        return;
    }
    double w0 = (double)(n - a - b) / n, w1 = (double)a / n, w2 = (double)b / n;
    const mr_vec3 *v = tri->pos, *m = tri->dir;
    *p = (dvec3){w0 * v[0].x + w1 * v[1].x + w2 * v[2].x, w0 * v[0].y + w1 * v[1].y + w2 * v[2].y,
                 w0 * v[0].z + w1 * v[1].z + w2 * v[2].z};
    *d = (dvec3){w0 * m[0].x + w1 * m[1].x + w2 * m[2].x, w0 * m[0].y + w1 * m[1].y + w2 * m[2].y,
                 w0 * m[0].z + w1 * m[1].z + w2 * m[2].z};
}

static int check_args(unsigned level, uint32_t a, uint32_t b, mr_error *err)
{
    if (level > MR_UMESH_MAX_LEVEL)
        return mr_error_set(err, MR_ERR_INVALID, "micro-mesh level %u is above %u", level,
                            MR_UMESH_MAX_LEVEL);
    if (mr_umesh_vertex_index(level, a, b) == UINT32_MAX)
        return mr_error_set(err, MR_ERR_INVALID,
                            "micro-vertex (%u, %u) is outside the level-%u triangle", a, b, level);
    return MR_OK;
}

static mr_vec3 to_f(dvec3 v) { return mr_v3((float)v.x, (float)v.y, (float)v.z); }

static mr_vec3 displace(dvec3 p, dvec3 d, float disp)
{
    double s = disp;
    return mr_v3((float)(p.x + s * d.x), (float)(p.y + s * d.y), (float)(p.z + s * d.z));
}

int mr_umesh_frame(const mr_umesh_tri *tri, unsigned level, uint32_t a, uint32_t b,
                   mr_vec3 *point, mr_vec3 *dir, mr_error *err)
{
    int rc = check_args(level, a, b, err);
    if (rc < 0)
        return rc;
    dvec3 p, d;
    frame_d(tri, level, a, b, &p, &d);
    if (point)
        *point = to_f(p);
    if (dir)
        *dir = to_f(d);
    return MR_OK;
}

int mr_umesh_eval(const mr_umesh_tri *tri, unsigned level, uint32_t a, uint32_t b, float disp,
                  mr_vec3 *out, mr_error *err)
{
    int rc = check_args(level, a, b, err);
    if (rc < 0)
        return rc;
    dvec3 p, d;
    frame_d(tri, level, a, b, &p, &d);
    *out = displace(p, d, disp);
    return MR_OK;
}

static bool v3_finite(mr_vec3 v) { return isfinite(v.x) && isfinite(v.y) && isfinite(v.z); }

int mr_umesh_eval_all(const mr_umesh_tri *tri, unsigned level, unsigned decimate_mask,
                      const float *disp, mr_vec3 *out, mr_error *err)
{
    if (level > MR_UMESH_MAX_LEVEL)
        return mr_error_set(err, MR_ERR_INVALID, "micro-mesh level %u is above %u", level,
                            MR_UMESH_MAX_LEVEL);
    if (decimate_mask > 7u)
        return mr_error_set(err, MR_ERR_INVALID, "decimate mask 0x%x names edges above 2",
                            decimate_mask);
    for (int i = 0; i < 3; i++)
        if (!v3_finite(tri->pos[i]) || !v3_finite(tri->dir[i]))
            return mr_error_set(err, MR_ERR_INVALID,
                                "base corner %d has a non-finite position or direction", i);
    uint32_t count = mr_umesh_vertex_count(level);
    if (disp)
        for (uint32_t i = 0; i < count; i++)
            if (!isfinite(disp[i]))
                return mr_error_set(err, MR_ERR_INVALID,
                                    "displacement of micro-vertex %u is not finite", i);
    for (uint32_t i = 0; i < count; i++) {
        uint32_t r = mr_umesh_vertex_remap(level, decimate_mask, i), a, b;
        mr_umesh_vertex_coords(level, r, &a, &b);
        dvec3 p, d;
        frame_d(tri, level, a, b, &p, &d);
        out[i] = displace(p, d, disp ? disp[r] : 0.0f);
    }
    return MR_OK;
}
