/*
 * micromesh.c - micro-mesh topology and displaced micro-vertex evaluation
 * (micromesh.h). The edge rule and the numerics are explained in the header;
 * the point of this file is that one code path computes every micro-vertex
 * of a base edge, from that edge's data only.
 */
#include "kinds/dmm/micromesh.h"

#include <stdlib.h>
#include <string.h>
#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#elif defined(__SSE2__)
#include <emmintrin.h>
#endif

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
    return mr_umesh_vertex_index_at(level, a, b);
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

/* mr_umesh_vertex_edge for n segments (inlined into weights_of). */
static inline int vertex_edge(uint32_t n, uint32_t a, uint32_t b, uint32_t *k)
{
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

int mr_umesh_vertex_edge(unsigned level, uint32_t a, uint32_t b, uint32_t *k)
{
    return vertex_edge(mr_umesh_segments(level), a, b, k);
}

void mr_umesh_lattice_triangle(uint32_t a, uint32_t b, bool inverted, uint32_t ta[3],
                               uint32_t tb[3])
{
    if (!inverted) {
        ta[0] = a, tb[0] = b;
        ta[1] = a + 1, tb[1] = b;
        ta[2] = a, tb[2] = b + 1;
    } else {
        ta[0] = a + 1, tb[0] = b;
        ta[1] = a + 1, tb[1] = b + 1;
        ta[2] = a, tb[2] = b + 1;
    }
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
    uint32_t r = tri - b * (2 * n - b), ta[3], tb[3];
    mr_umesh_lattice_triangle(r / 2, b, r % 2 != 0, ta, tb);
    for (int k = 0; k < 3; k++)
        idx[k] = mr_umesh_vertex_index(level, ta[k], tb[k]);
    return true;
}

uint32_t mr_umesh_vertex_remap(unsigned level, unsigned decimate_mask, uint32_t index)
{
    uint32_t a, b;
    if (!mr_umesh_vertex_coords(level, index, &a, &b))
        return UINT32_MAX;
    mr_umesh_remap_coords(level, decimate_mask, &a, &b);
    return mr_umesh_vertex_index(level, a, b);
}

void mr_umesh_remap_coords(unsigned level, unsigned decimate_mask, uint32_t *a, uint32_t *b)
{
    /* on lattice coordinates, not vertex indices: the traversal remaps
     * every vertex of a decimated patch's leaves, and an index's
     * coordinates are a walk over the rows */
    const uint32_t n = mr_umesh_segments(level);
    uint32_t k;
    if (!n || *a + *b > n)
        return;
    const int e = vertex_edge(n, *a, *b, &k);
    if (e < 0 || e > 2 || !(decimate_mask & (1u << e)) || k % 2 == 0)
        return;
    /* odd vertex: collapse onto step k-1 of the same edge (k-1 >= 0 is even,
     * so it is a corner or an even edge vertex, which is never moved) */
    const uint32_t j = k - 1;
    switch (e) {
    case 0: *a = j, *b = 0; break;
    case 1: *a = n - j, *b = j; break;
    default: *a = 0, *b = n - j; break;
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

/* Total order on an endpoint's (position, direction) bit patterns, corner i
 * against corner j. It need not mean anything geometrically: both triangles
 * only have to agree. */
static int endpoint_cmp(const mr_umesh_tri *tri, int i, int j)
{
    const mr_vec3 *k[2][2] = {{&tri->pos[i], &tri->dir[i]}, {&tri->pos[j], &tri->dir[j]}};
    for (int h = 0; h < 2; h++) {
        const float a[3] = {k[0][h]->x, k[0][h]->y, k[0][h]->z};
        const float b[3] = {k[1][h]->x, k[1][h]->y, k[1][h]->z};
        for (int c = 0; c < 3; c++) {
            uint32_t x = fbits(a[c]), y = fbits(b[c]);
            if (x != y)
                return x < y ? -1 : 1;
        }
    }
    return 0;
}

/* The corners a micro-vertex depends on and their weights, in the order they
 * are summed: a corner alone; an edge's two endpoints in canonical order (the
 * edge rule above); the three corners for an interior vertex. Every
 * interpolated quantity (position, direction, skinning matrix) is summed in
 * this order, so shared-edge vertices are bit-identical on both sides. */
typedef struct corner_weights {
    int count;
    int corner[3];
    double w[3];
} corner_weights;

/* 1 / n for n = 2^level: a power of two, so k * INV_SEGMENTS[level] is k / n
 * exactly (a multiplication where a division cost three times as much). */
static const double INV_SEGMENTS[MR_UMESH_MAX_LEVEL + 1] = {1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125};

/* level <= MR_UMESH_MAX_LEVEL, (a, b) on its lattice. Inlined, as blend
 * below (called, their 40- and 24-byte results go through memory). */
static inline __attribute__((always_inline)) corner_weights
weights_of(const mr_umesh_tri *tri, unsigned level, uint32_t a, uint32_t b)
{
    const uint32_t n = 1u << level;
    const double inv = INV_SEGMENTS[level];
    uint32_t k;
    if (a > 0 && b > 0 && a + b < n) /* interior: most micro-vertices */
        return (corner_weights){3, {0, 1, 2},
                                {(double)(n - a - b) * inv, (double)a * inv, (double)b * inv}};
    int e = vertex_edge(n, a, b, &k);
    if (e == 3)
        return (corner_weights){1, {(int)k, 0, 0}, {1.0, 0, 0}};
    if (e >= 0) {
        int i0 = e, i1 = (e + 1) % 3;
        uint32_t k0 = n - k, k1 = k; /* weights (in units of 1/n) of i0 and i1 */
        if (endpoint_cmp(tri, i0, i1) > 0) {
            int ti = i0;
            i0 = i1, i1 = ti;
            uint32_t tk = k0;
            k0 = k1, k1 = tk;
        }
        return (corner_weights){2, {i0, i1, 0}, {(double)k0 * inv, (double)k1 * inv, 0}};
    }
    return (corner_weights){3, {0, 1, 2},
                            {(double)(n - a - b) * inv, (double)a * inv, (double)b * inv}};
}

/* sum w_i v_i in the order of cw, each term added to the sum before it;
 * one body per corner count rather than a loop over it. */
static inline __attribute__((always_inline)) dvec3 blend(const mr_vec3 *v,
                                                         const corner_weights *cw)
{
    const int *c = cw->corner;
    const double *w = cw->w;
    const mr_vec3 x = v[c[0]];
    if (cw->count == 3) {
        const mr_vec3 y = v[c[1]], z = v[c[2]];
        return (dvec3){w[0] * x.x + w[1] * y.x + w[2] * z.x, w[0] * x.y + w[1] * y.y + w[2] * z.y,
                       w[0] * x.z + w[1] * y.z + w[2] * z.z};
    }
    if (cw->count == 2) {
        const mr_vec3 y = v[c[1]];
        return (dvec3){w[0] * x.x + w[1] * y.x, w[0] * x.y + w[1] * y.y, w[0] * x.z + w[1] * y.z};
    }
    return (dvec3){w[0] * x.x, w[0] * x.y, w[0] * x.z};
}

/* Undisplaced point and direction in double, by the edge rule. */
static void frame_d(const mr_umesh_tri *tri, unsigned level, uint32_t a, uint32_t b, dvec3 *p,
                    dvec3 *d)
{
    corner_weights cw = weights_of(tri, level, a, b);
    *p = blend(tri->pos, &cw);
    *d = blend(tri->dir, &cw);
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

/* (float)x, (float)y, (float)z as a vector. x and y are rounded together
 * (cvtpd2ps, the rounding of each one's own conversion) and stored as one
 * 8-byte piece: stored as two floats, the struct was then read back as
 * one 8-byte load, which the store buffer cannot forward from two
 * 4-byte stores (perf put half of the micro-vertex's time on it). */
static inline mr_vec3 to_f3(double x, double y, double z)
{
#if defined(__SSE2__)
    const __m128 xy = _mm_cvtpd_ps(_mm_set_pd(y, x));
    mr_vec3 v;
    _mm_storel_pi((__m64 *)&v, xy);
    v.z = (float)z;
    return v;
#else
    return mr_v3((float)x, (float)y, (float)z);
#endif
}

static mr_vec3 to_f(dvec3 v) { return to_f3(v.x, v.y, v.z); }

static mr_vec3 displace(dvec3 p, dvec3 d, float disp)
{
    double s = disp;
    return to_f3(p.x + s * d.x, p.y + s * d.y, p.z + s * d.z);
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

mr_vec3 mr_umesh_eval_at(const mr_umesh_tri *tri, unsigned level, uint32_t a, uint32_t b,
                         float disp)
{
    corner_weights cw = weights_of(tri, level, a, b);
    return displace(blend(tri->pos, &cw), blend(tri->dir, &cw), disp);
}

#if defined(__x86_64__) && defined(__GNUC__)
/* mr_umesh_eval_many (mats NULL) and mr_umesh_eval_interpolated_many
 * (tri the rest pose) with AVX2: a vertex's x, y, z in one vector of four
 * doubles (the fourth lane unused), the corners converted once for all of
 * them. weights_of's three cases are one sum here: every vertex takes the
 * interior weights (n - a - b, a, b) / n, which are an edge vertex's
 * two weights and a corner's 1 where those apply and 0 for the corners it
 * does not depend on. An absent corner's term is -0.0, which adds nothing
 * to any double (x + -0.0 is x, -0.0 included), so (t0 + t1) + t2 is blend's
 * sum term for term: the interior sum in its order, an edge's two products
 * in either order (a sum of two is the same both ways round), a corner's
 * product alone. With matrices, the matrix is blended so column by column
 * (lane r of column j: element r * 4 + j), element by element the sums of
 * mr_umesh_eval_interpolated_at, and row r of the product, ((m[r][0] x +
 * m[r][1] y) + m[r][2] z) + m[r][3], comes out in lane r. */
__attribute__((target("avx2"))) static void eval_many_avx2(const mr_umesh_tri *tri,
                                                           const mr_affine *const *mats,
                                                           unsigned level, int count,
                                                           const uint32_t *a, const uint32_t *b,
                                                           const float *disp, mr_vec3 *out)
{
    const mr_vec3 *P = tri->pos, *D = tri->dir;
    const __m256d p0 = _mm256_cvtps_pd(_mm_setr_ps(P[0].x, P[0].y, P[0].z, 0.0f)),
                  p1 = _mm256_cvtps_pd(_mm_setr_ps(P[1].x, P[1].y, P[1].z, 0.0f)),
                  p2 = _mm256_cvtps_pd(_mm_setr_ps(P[2].x, P[2].y, P[2].z, 0.0f)),
                  d0 = _mm256_cvtps_pd(_mm_setr_ps(D[0].x, D[0].y, D[0].z, 0.0f)),
                  d1 = _mm256_cvtps_pd(_mm_setr_ps(D[1].x, D[1].y, D[1].z, 0.0f)),
                  d2 = _mm256_cvtps_pd(_mm_setr_ps(D[2].x, D[2].y, D[2].z, 0.0f));
    __m256d c[3][4]; /* c[i][j]: column j of corner i's matrix */
    for (int i = 0; i < 3 && mats; i++)
        for (int j = 0; j < 4; j++)
            c[i][j] = _mm256_cvtps_pd(
                _mm_setr_ps(mats[i]->m[j], mats[i]->m[4 + j], mats[i]->m[8 + j], 0.0f));
    const uint32_t n = 1u << level;
    const double inv = INV_SEGMENTS[level];
    const __m256d none = _mm256_set1_pd(-0.0), zero = _mm256_setzero_pd();
    for (int k = 0; k < count; k++) {
        const __m256d w0 = _mm256_set1_pd((double)(n - a[k] - b[k]) * inv),
                      w1 = _mm256_set1_pd((double)a[k] * inv),
                      w2 = _mm256_set1_pd((double)b[k] * inv);
        /* an absent corner's product is +-0: its sign bit set makes it -0 */
        const __m256d off0 = _mm256_and_pd(_mm256_cmp_pd(w0, zero, _CMP_EQ_OQ), none),
                      off1 = _mm256_and_pd(_mm256_cmp_pd(w1, zero, _CMP_EQ_OQ), none),
                      off2 = _mm256_and_pd(_mm256_cmp_pd(w2, zero, _CMP_EQ_OQ), none);
#define TERM(w, x, off) _mm256_or_pd(_mm256_mul_pd(w, x), off)
#define BLEND(x0, x1, x2)                                                                          \
    _mm256_add_pd(_mm256_add_pd(TERM(w0, x0, off0), TERM(w1, x1, off1)), TERM(w2, x2, off2))
        __m256d x = _mm256_add_pd(BLEND(p0, p1, p2),
                                  _mm256_mul_pd(_mm256_set1_pd((double)disp[k]), BLEND(d0, d1, d2)));
        if (mats) {
            const __m256d x0 = _mm256_permute4x64_pd(x, 0x00),
                          x1 = _mm256_permute4x64_pd(x, 0x55),
                          x2 = _mm256_permute4x64_pd(x, 0xAA);
            x = _mm256_add_pd(
                _mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(BLEND(c[0][0], c[1][0], c[2][0]), x0),
                                            _mm256_mul_pd(BLEND(c[0][1], c[1][1], c[2][1]), x1)),
                              _mm256_mul_pd(BLEND(c[0][2], c[1][2], c[2][2]), x2)),
                BLEND(c[0][3], c[1][3], c[2][3]));
        }
#undef BLEND
#undef TERM
        const __m128 f = _mm256_cvtpd_ps(x);
        _mm_storel_pi((__m64 *)&out[k], f);
        out[k].z = _mm_cvtss_f32(_mm_movehl_ps(f, f));
    }
}
#endif

void mr_umesh_eval_many(const mr_umesh_tri *tri, unsigned level, int count, const uint32_t *a,
                        const uint32_t *b, const float *disp, mr_vec3 *out)
{
#if defined(__x86_64__) && defined(__GNUC__)
    if (__builtin_cpu_supports("avx2")) {
        eval_many_avx2(tri, NULL, level, count, a, b, disp, out);
        return;
    }
#endif
    for (int k = 0; k < count; k++)
        out[k] = mr_umesh_eval_at(tri, level, a[k], b[k], disp[k]);
}

int mr_umesh_eval(const mr_umesh_tri *tri, unsigned level, uint32_t a, uint32_t b, float disp,
                  mr_vec3 *out, mr_error *err)
{
    int rc = check_args(level, a, b, err);
    if (rc < 0)
        return rc;
    *out = mr_umesh_eval_at(tri, level, a, b, disp);
    return MR_OK;
}

mr_vec3 mr_umesh_eval_interpolated_at(const mr_umesh_tri *rest, const mr_affine *const mats[3],
                                      unsigned level, uint32_t a, uint32_t b, float disp)
{
    corner_weights cw = weights_of(rest, level, a, b);
    dvec3 p = blend(rest->pos, &cw), d = blend(rest->dir, &cw);
    double s = disp, x[3] = {p.x + s * d.x, p.y + s * d.y, p.z + s * d.z};
    /* M(w): summed in cw's order, one body per corner count as in blend */
    const double *w = cw.w;
    const float *m0 = mats[cw.corner[0]]->m, *m1 = mats[cw.corner[1]]->m,
                *m2 = mats[cw.corner[2]]->m;
    double m[12];
    if (cw.count == 3)
        for (int e = 0; e < 12; e++)
            m[e] = w[0] * m0[e] + w[1] * m1[e] + w[2] * m2[e];
    else if (cw.count == 2)
        for (int e = 0; e < 12; e++)
            m[e] = w[0] * m0[e] + w[1] * m1[e];
    else
        for (int e = 0; e < 12; e++)
            m[e] = w[0] * m0[e];
    double r[3];
    for (int row = 0; row < 3; row++)
        r[row] = m[row * 4] * x[0] + m[row * 4 + 1] * x[1] + m[row * 4 + 2] * x[2] + m[row * 4 + 3];
    return mr_v3((float)r[0], (float)r[1], (float)r[2]);
}

void mr_umesh_eval_interpolated_many(const mr_umesh_tri *rest, const mr_affine *const mats[3],
                                     unsigned level, int count, const uint32_t *a,
                                     const uint32_t *b, const float *disp, mr_vec3 *out)
{
#if defined(__x86_64__) && defined(__GNUC__)
    if (__builtin_cpu_supports("avx2")) {
        eval_many_avx2(rest, mats, level, count, a, b, disp, out);
        return;
    }
#endif
    for (int k = 0; k < count; k++)
        out[k] = mr_umesh_eval_interpolated_at(rest, mats, level, a[k], b[k], disp[k]);
}

int mr_umesh_eval_interpolated(const mr_umesh_tri *rest, const mr_affine *const mats[3],
                               unsigned level, uint32_t a, uint32_t b, float disp, mr_vec3 *out,
                               mr_error *err)
{
    int rc = check_args(level, a, b, err);
    if (rc < 0)
        return rc;
    *out = mr_umesh_eval_interpolated_at(rest, mats, level, a, b, disp);
    return MR_OK;
}

static bool v3_finite(mr_vec3 v) { return isfinite(v.x) && isfinite(v.y) && isfinite(v.z); }

void mr_umesh_topology_free(mr_umesh_topology *t)
{
    for (unsigned l = 0; l <= MR_UMESH_MAX_LEVEL; l++)
        for (unsigned m = 0; m < 8; m++) {
            free(t->tris[l][m]);
            t->tris[l][m] = NULL;
            t->count[l][m] = 0;
        }
}

int mr_umesh_topology_init(mr_umesh_topology *t, unsigned max_level, mr_error *err)
{
    memset(t, 0, sizeof *t);
    if (max_level > MR_UMESH_MAX_LEVEL)
        return mr_error_set(err, MR_ERR_INVALID, "micro-mesh level %u is above %u", max_level,
                            MR_UMESH_MAX_LEVEL);
    for (unsigned l = 0; l <= max_level; l++)
        for (unsigned m = 0; m < (l ? 8u : 1u); m++) {
            t->tris[l][m] = malloc((size_t)mr_umesh_triangle_count(l) * 3 * sizeof(uint32_t));
            if (!t->tris[l][m]) {
                mr_umesh_topology_free(t);
                return mr_error_set(err, MR_ERR_NOMEM, "out of memory for micro-mesh topology");
            }
            t->count[l][m] = mr_umesh_triangles(l, m, t->tris[l][m]);
        }
    return MR_OK;
}

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
        uint32_t r = mr_umesh_vertex_remap(level, decimate_mask, i), a = 0, b = 0;
        mr_umesh_vertex_coords(level, r, &a, &b);
        out[i] = mr_umesh_eval_at(tri, level, a, b, disp ? disp[r] : 0.0f);
    }
    return MR_OK;
}

static int edge_cmp(const void *x, const void *y)
{
    const mr_umesh_edge *a = x, *b = y;
    if (a->lo != b->lo)
        return a->lo < b->lo ? -1 : 1;
    if (a->hi != b->hi)
        return a->hi < b->hi ? -1 : 1;
    return a->tri < b->tri ? -1 : a->tri > b->tri;
}

int mr_umesh_edges_init(mr_umesh_edges *out, const uint32_t *idx, uint32_t nt, mr_error *err)
{
    *out = (mr_umesh_edges){0};
    size_t n = (size_t)nt * 3;
    out->e = malloc((n + 1) * sizeof *out->e);
    out->group = malloc((n + 1) * sizeof *out->group);
    out->at = malloc((n + 1) * sizeof *out->at);
    out->order = malloc(((size_t)nt * 2 + 1) * sizeof *out->order);
    if (!out->e || !out->group || !out->at || !out->order) {
        mr_umesh_edges_free(out);
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory for a mesh's edges");
    }
    for (uint32_t t = 0; t < nt; t++)
        for (uint32_t k = 0; k < 3; k++) {
            uint32_t u = idx[3 * t + k], v = idx[3 * t + (k + 1) % 3];
            out->e[3 * (size_t)t + k] = (mr_umesh_edge){u < v ? u : v, u < v ? v : u, t, k};
        }
    out->count = n;
    out->triangles = nt;
    qsort(out->e, n, sizeof *out->e, edge_cmp);
    for (size_t i = 0; i < n; i++) {
        bool same = i > 0 && out->e[i].lo == out->e[i - 1].lo && out->e[i].hi == out->e[i - 1].hi;
        out->group[i] = same ? out->group[i - 1] : (uint32_t)i;
        out->at[3 * (size_t)out->e[i].tri + out->e[i].k] = (uint32_t)i;
    }
    return MR_OK;
}

void mr_umesh_edges_free(mr_umesh_edges *e)
{
    free(e->e);
    free(e->group);
    free(e->at);
    free(e->order);
    *e = (mr_umesh_edges){0};
}

size_t mr_umesh_edges_group_end(const mr_umesh_edges *e, size_t i)
{
    size_t j = i + 1;
    while (j < e->count && e->group[j] == e->group[i])
        j++;
    return j;
}

void mr_umesh_edges_shared(const mr_umesh_edges *e, uint8_t *shared)
{
    memset(shared, 0, e->triangles);
    for (size_t i = 0, j; i < e->count; i = j)
        if ((j = mr_umesh_edges_group_end(e, i)) - i > 1)
            for (size_t m = i; m < j; m++)
                shared[e->e[m].tri] |= (uint8_t)(1u << e->e[m].k);
}

void mr_umesh_balance(const mr_umesh_edges *e, uint8_t *level, uint8_t *decimate)
{
    const uint32_t nt = e->triangles;
    /* the triangles finest first (counting sort), then, level by level,
     * those raised to it while the level above was processed */
    uint32_t *order = e->order, *raised = e->order + nt, count[MR_UMESH_MAX_LEVEL + 2] = {0};
    for (uint32_t t = 0; t < nt; t++)
        count[MR_UMESH_MAX_LEVEL - level[t] + 1]++;
    for (unsigned l = 1; l <= MR_UMESH_MAX_LEVEL + 1; l++)
        count[l] += count[l - 1];
    uint32_t first[MR_UMESH_MAX_LEVEL + 2];
    memcpy(first, count, sizeof first);
    for (uint32_t t = 0; t < nt; t++)
        order[count[MR_UMESH_MAX_LEVEL - level[t]]++] = t;
    uint32_t pending = 0; /* raised[0 .. pending): at the level being processed */
    for (int l = MR_UMESH_MAX_LEVEL; l >= 1; l--) {
        uint32_t from = first[MR_UMESH_MAX_LEVEL - l], to = first[MR_UMESH_MAX_LEVEL - l + 1];
        uint32_t was_pending = pending, next = 0;
        for (uint32_t i = from; i < to + was_pending; i++) {
            uint32_t t = i < to ? order[i] : raised[i - to];
            if (level[t] != l)
                continue; /* raised above the level it was sorted at */
            for (uint32_t k = 0; k < 3; k++) {
                uint32_t g = e->group[e->at[3 * (size_t)t + k]];
                for (size_t m = g, end = mr_umesh_edges_group_end(e, g); m < end; m++) {
                    uint32_t u = e->e[m].tri;
                    if (level[u] + 1 < l) {
                        level[u] = (uint8_t)(l - 1);
                        /* processed at l - 1: after this level's pending
                         * ones are read (they sit below `next`) */
                        raised[was_pending + next++] = u;
                    }
                }
            }
        }
        memmove(raised, raised + was_pending, next * sizeof *raised);
        pending = next;
    }
    memset(decimate, 0, nt);
    for (size_t i = 0, j; i < e->count; i = j) {
        unsigned low = UINT32_MAX;
        j = mr_umesh_edges_group_end(e, i);
        for (size_t m = i; m < j; m++)
            low = level[e->e[m].tri] < low ? level[e->e[m].tri] : low;
        for (size_t m = i; m < j; m++)
            if (level[e->e[m].tri] > low)
                decimate[e->e[m].tri] |= (uint8_t)(1u << e->e[m].k);
    }
}
