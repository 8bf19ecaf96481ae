/*
 * dmm_lod.c - the distance of a dmm level to its detailed mesh (dmm_lod.h).
 */
#include "kinds/dmm/dmm_lod.h"
#include "kinds/dmm/dmm_encode.h"
#include "kinds/dmm/micromesh.h"

#include <math.h>
#include <meshoptimizer.h>
#include <stdlib.h>
#include <string.h>

#include "util/le.h"

int mr_dmm_lod_truth_init(mr_dmm_lod_truth *t, const float *pos, uint32_t nv, const uint32_t *idx,
                          uint32_t nt, const char *who, mr_error *err)
{
    memset(t, 0, sizeof *t);
    t->pos = pos;
    t->nv = nv;
    uint32_t *remap = malloc((size_t)(nv ? nv : 1) * sizeof *remap);
    t->distinct = malloc((size_t)(nv ? nv : 1) * sizeof *t->distinct);
    if (!remap || !t->distinct) {
        free(remap);
        free(t->distinct);
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory measuring levels of detail", who);
    }
    /* vertices by bitwise position (a vertex split for its normals or uvs
     * is one sample) */
    meshopt_generateVertexRemap(remap, NULL, nv, pos, nv, 3 * sizeof(float));
    for (uint32_t v = 0; v < nv; v++)
        if (remap[v] == t->distinct_count) /* remap numbers positions in order of first use */
            t->distinct[t->distinct_count++] = v;
    free(remap);
    int rc = mr_closest_mesh_init(&t->closest, NULL, pos, nv, idx, nt, who, err);
    if (rc < 0) {
        free(t->distinct);
        memset(t, 0, sizeof *t);
    }
    return rc;
}

void mr_dmm_lod_truth_free(mr_dmm_lod_truth *t)
{
    if (t->distinct)
        mr_closest_mesh_free(&t->closest);
    free(t->distinct);
    memset(t, 0, sizeof *t);
}

typedef struct distance_ctx {
    const mr_dmm_lod_truth *truth;
    const mr_closest_mesh *level;
    const float *pos;           /* the level's */
    const uint32_t *idx;
    const uint32_t *used;       /* the level's vertices some triangle uses */
    uint32_t stride;            /* every stride-th sample of each kind */
    uint32_t distinct_n, used_n, tri_n; /* how many of each are sampled */
    double *dist;               /* per sample, in item order */
    uint32_t *prim;             /* per distinct sample: the level's triangle nearest it */
} distance_ctx;

static void point_of(const float *pos, uint32_t v, double p[3])
{
    p[0] = pos[3 * (size_t)v], p[1] = pos[3 * (size_t)v + 1], p[2] = pos[3 * (size_t)v + 2];
}

/* Items: the truth's distinct positions against the level, then the
 * level's used vertices and then its triangles' centroids against the
 * truth. */
static void distance_range(void *vctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    distance_ctx *c = vctx;
    const mr_dmm_lod_truth *t = c->truth;
    for (size_t i = begin; i < end; i++) {
        double p[3];
        if (i < c->distinct_n) {
            point_of(t->pos, t->distinct[i * c->stride], p);
            c->dist[i] = mr_closest_mesh_nearest(c->level, p, NULL, &c->prim[i]);
            continue;
        }
        size_t j = i - c->distinct_n;
        if (j < c->used_n) {
            point_of(c->pos, c->used[j * c->stride], p);
        } else {
            const uint32_t *tri = c->idx + 3 * (j - c->used_n) * c->stride;
            double a[3], b[3], d[3];
            point_of(c->pos, tri[0], a);
            point_of(c->pos, tri[1], b);
            point_of(c->pos, tri[2], d);
            for (int k = 0; k < 3; k++)
                p[k] = (a[k] + b[k] + d[k]) / 3.0;
        }
        c->dist[i] = mr_closest_mesh_distance(&t->closest, p, NULL);
    }
}

int mr_dmm_lod_distance(const mr_dmm_lod_truth *t, const float *pos, uint32_t nv,
                        const uint32_t *idx, uint32_t nt, const uint32_t *owner, uint32_t stride,
                        unsigned threads, const char *who, double *out, mr_error *err)
{
    stride = stride ? stride : 1;
    const uint32_t distinct_n = (t->distinct_count + stride - 1) / stride;
    uint32_t *vsample = calloc(nv ? nv : 1, sizeof *vsample); /* vertex -> used sample */
    uint32_t *used = malloc((size_t)(nv ? nv : 1) * sizeof *used);
    uint32_t *prim = malloc(((size_t)distinct_n + 1) * sizeof *prim);
    if (!vsample || !used || !prim) {
        free(vsample);
        free(used);
        free(prim);
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory measuring levels of detail", who);
    }
    for (size_t e = 0; e < (size_t)nt * 3; e++)
        vsample[idx[e]] = 1;
    uint32_t used_count = 0;
    for (uint32_t v = 0; v < nv; v++)
        if (vsample[v]) {
            vsample[v] = used_count % stride ? UINT32_MAX : used_count / stride;
            used[used_count++] = v;
        }
    const uint32_t used_n = (used_count + stride - 1) / stride, tri_n = (nt + stride - 1) / stride;
    const size_t items = (size_t)distinct_n + used_n + tri_n;
    double *dist = malloc((items + 1) * sizeof *dist);
    mr_closest_mesh level;
    int rc = dist ? mr_closest_mesh_init(&level, t->closest.device, pos, nv, idx, nt, who, err)
                  : mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory measuring levels of detail", who);
    if (rc == MR_OK) {
        distance_ctx c = {.truth = t, .level = &level, .pos = pos, .idx = idx, .used = used,
                          .stride = stride, .distinct_n = distinct_n, .used_n = used_n,
                          .tri_n = tri_n, .dist = dist, .prim = prim};
        mr_parallel_for(threads, items, 256, distance_range, &c);
        mr_closest_mesh_free(&level);
        /* each sample to its owner, in a fixed order: the detail's points
         * to the owner of the triangle nearest them, the level's vertices
         * to the owners of every triangle using them, its centroids to
         * their triangle's */
        for (uint32_t i = 0; i < distinct_n; i++) {
            uint32_t o = owner && prim[i] < nt ? owner[prim[i]] : 0;
            out[o] = fmax(out[o], dist[i]);
        }
        const double *vdist = dist + distinct_n, *cdist = vdist + used_n;
        for (uint32_t k = 0; k < nt; k++) {
            uint32_t o = owner ? owner[k] : 0;
            for (int j = 0; j < 3; j++)
                if (vsample[idx[3 * (size_t)k + j]] != UINT32_MAX)
                    out[o] = fmax(out[o], vdist[vsample[idx[3 * (size_t)k + j]]]);
            if (k % stride == 0)
                out[o] = fmax(out[o], cdist[k / stride]);
        }
    }
    free(dist);
    free(vsample);
    free(used);
    free(prim);
    return rc;
}

/* ---- the bounds in the derived-data cache ---- */

#define LOD_HEAD 64u
#define AT_TRIANGLES 16u
#define AT_LEVELS 20u
#define AT_KEY 24u
#define AT_PAYLOAD_CRC 56u
#define PER_TRIANGLE (1u + 2u * MR_DMM_LOD_LEVELS) /* f64 */

static const mr_derived_format TABLE_FORMAT = {
    .name = "dmm lod bounds file",
    .ext = "mrdle",
    .magic = {'M', 'R', 'D', 'L', 'E', '\0', '\r', '\n'},
    .version = MR_DMM_LOD_FILE_VERSION,
    .header_bytes = LOD_HEAD,
    .key_at = AT_KEY,
    .max_bytes = LOD_HEAD + 8ull * PER_TRIANGLE * (1ull << 24),
};

typedef struct table_request {
    mr_dmm_lod_table *table;
    int (*measure)(void *ctx, mr_error *err);
    void *ctx;
} table_request;

/* One triangle's figures in file order, from the table or into it. */
static double *table_slot(const mr_dmm_lod_table *t, uint32_t tri, uint32_t k)
{
    if (k == 0)
        return &t->fine[tri];
    if (k <= MR_DMM_LOD_LEVELS)
        return &t->error[(size_t)tri * MR_DMM_LOD_LEVELS + k - 1];
    return &t->whole[(size_t)tri * MR_DMM_LOD_LEVELS + k - 1 - MR_DMM_LOD_LEVELS];
}

/* Checks the file in buf and, with keep, copies it into the table. */
static int table_parse_into(const mr_dmm_lod_table *t, bool keep, const uint8_t *buf, size_t size,
                            mr_error *err)
{
    const mr_derived_format *f = &TABLE_FORMAT;
    const uint64_t want = LOD_HEAD + 8ull * PER_TRIANGLE * t->triangles;
    if (mr_le_get_u32(buf + AT_TRIANGLES) != t->triangles)
        return mr_derived_bad(f, err, "%u base triangles at byte offset %u (want %u)",
                              mr_le_get_u32(buf + AT_TRIANGLES), AT_TRIANGLES, t->triangles);
    if (mr_le_get_u32(buf + AT_LEVELS) != MR_DMM_LOD_LEVELS)
        return mr_derived_bad(f, err, "%u levels at byte offset %u (want %u)",
                              mr_le_get_u32(buf + AT_LEVELS), AT_LEVELS, MR_DMM_LOD_LEVELS);
    if (size != want)
        return mr_derived_bad(f, err, "%zu bytes (want %llu for %u base triangles)", size,
                              (unsigned long long)want, t->triangles);
    if (!mr_crc32_matches(mr_le_get_u32(buf + AT_PAYLOAD_CRC), buf + LOD_HEAD, size - LOD_HEAD))
        return mr_derived_bad(f, err, "payload CRC mismatch at byte offset %u", AT_PAYLOAD_CRC);
    for (uint32_t tri = 0; tri < t->triangles; tri++)
        for (uint32_t k = 0; k < PER_TRIANGLE; k++) {
            const size_t at = LOD_HEAD + 8 * ((size_t)tri * PER_TRIANGLE + k);
            double v = mr_le_get_f64(buf + at), finer = k >= 1 && k < MR_DMM_LOD_LEVELS
                                                            ? mr_le_get_f64(buf + at + 8)
                                                            : 0;
            if (!isfinite(v) || v < 0 || v < finer)
                return mr_derived_bad(f, err, "bound %g at byte offset %zu", v, at);
            if (keep)
                *table_slot(t, tri, k) = v;
        }
    return MR_OK;
}

static int table_parse(void *vctx, const uint8_t *buf, size_t size, mr_error *err)
{
    const table_request *q = vctx;
    /* checked whole before anything is kept: a bad file leaves the table
     * for the measurement */
    int rc = table_parse_into(q->table, false, buf, size, err);
    return rc < 0 ? rc : table_parse_into(q->table, true, buf, size, err);
}

static int table_serialise(void *vctx, const uint8_t key[MR_DERIVED_KEY_BYTES], uint8_t **out,
                           size_t *out_size, mr_error *err)
{
    const table_request *q = vctx;
    const mr_dmm_lod_table *t = q->table;
    const size_t size = LOD_HEAD + 8 * (size_t)PER_TRIANGLE * t->triangles;
    uint8_t *buf = NULL;
    mr_derived_reader *check = NULL;
    int rc = mr_derived_buffer(&TABLE_FORMAT, size, &buf, &check, err);
    if (rc < 0)
        return rc;
    mr_le_put_u32(buf + AT_TRIANGLES, t->triangles);
    mr_le_put_u32(buf + AT_LEVELS, MR_DMM_LOD_LEVELS);
    for (uint32_t tri = 0; tri < t->triangles; tri++)
        for (uint32_t k = 0; k < PER_TRIANGLE; k++)
            mr_le_put_f64(buf + LOD_HEAD + 8 * ((size_t)tri * PER_TRIANGLE + k), *table_slot(t, tri, k));
    mr_le_put_u32(buf + AT_PAYLOAD_CRC, mr_crc32(buf + LOD_HEAD, size - LOD_HEAD));
    mr_derived_header_seal(&TABLE_FORMAT, key, buf);
    free(check);
    if ((rc = table_parse_into(t, false, buf, size, err)) < 0) {
        free(buf);
        return mr_derived_readback_failed(&TABLE_FORMAT, rc, err);
    }
    *out = buf;
    *out_size = size;
    return MR_OK;
}

static int table_build(void *vctx, mr_error *err)
{
    const table_request *q = vctx;
    return q->measure(q->ctx, err);
}

static const mr_derived_ops TABLE_OPS = {table_parse, table_serialise, table_build};

int mr_dmm_lod_table_cached(const char *cache_dir, const uint8_t key[MR_DERIVED_KEY_BYTES],
                            mr_dmm_lod_table *table, int (*measure)(void *ctx, mr_error *err),
                            void *ctx, bool *hit, mr_error *err)
{
    if (table->triangles < 1 || table->triangles > MR_DMM_MAX_TRIANGLES)
        return mr_error_set(err, MR_ERR_INVALID, "dmm lod bounds: %u base triangles (1..%u)",
                            table->triangles, MR_DMM_MAX_TRIANGLES);
    table_request q = {table, measure, ctx};
    return mr_derived_get(cache_dir, key, &TABLE_FORMAT, &TABLE_OPS, &q, hit, err);
}

/* A point of the base domain in level-L lattice coordinates (a, b) with
 * the level-L surface there (affine over each level-L micro-triangle). */
typedef struct domain_pt {
    double a, b, x[3];
} domain_pt;

/* Sutherland-Hodgman: the part of polygon in (n points) where
 * ga a + gb b + g0 >= 0, into out (n + 1 points at most); its count. */
static int clip_half(const domain_pt *in, int n, double ga, double gb, double g0, domain_pt *out)
{
    int m = 0;
    for (int i = 0; i < n; i++) {
        const domain_pt *p = &in[i], *q = &in[(i + 1) % n];
        double dp = ga * p->a + gb * p->b + g0, dq = ga * q->a + gb * q->b + g0;
        if (dp >= 0)
            out[m++] = *p;
        if ((dp >= 0) != (dq >= 0)) {
            double s = dp / (dp - dq);
            domain_pt *r = &out[m++];
            r->a = p->a + s * (q->a - p->a);
            r->b = p->b + s * (q->b - p->b);
            for (int k = 0; k < 3; k++)
                r->x[k] = p->x[k] + s * (q->x[k] - p->x[k]);
        }
    }
    return m;
}

static domain_pt lattice_pt(unsigned fine, const float *pos, int64_t a, int64_t b)
{
    const float *x = pos + 3 * (size_t)mr_umesh_vertex_index(fine, (uint32_t)a, (uint32_t)b);
    return (domain_pt){(double)a, (double)b, {x[0], x[1], x[2]}};
}

double mr_dmm_lod_coarsening(unsigned fine, const float *pos, unsigned level, const uint32_t *tris,
                             uint32_t count)
{
    const int64_t n = mr_umesh_segments(fine);
    const int64_t s = (int64_t)1 << (fine - level);
    double worst = 0;
    for (uint32_t k = 0; k < count; k++) {
        int64_t A[3], B[3];
        domain_pt X[3];
        for (int j = 0; j < 3; j++) {
            uint32_t a, b;
            mr_umesh_vertex_coords(level, tris[3 * k + j], &a, &b);
            A[j] = a * s, B[j] = b * s;
            X[j] = lattice_pt(fine, pos, A[j], B[j]);
        }
        const int64_t d1a = A[1] - A[0], d1b = B[1] - B[0], d2a = A[2] - A[0], d2b = B[2] - B[0];
        const double det = (double)(d1a * d2b - d1b * d2a);
        if (det == 0)
            continue; /* collapsed: decimation drops it */
        /* T's barycentric coordinates 1 and 2 as affine functions of (a, b):
         * w1 = g1a a + g1b b + g10, w2 likewise, w0 = 1 - w1 - w2 */
        const double g1a = (double)d2b / det, g1b = (double)-d2a / det;
        const double g2a = (double)-d1b / det, g2b = (double)d1a / det;
        const double g10 = -(double)A[0] * g1a - (double)B[0] * g1b;
        const double g20 = -(double)A[0] * g2a - (double)B[0] * g2b;
        int64_t alo = A[0], ahi = A[0], blo = B[0], bhi = B[0];
        for (int j = 1; j < 3; j++) {
            alo = A[j] < alo ? A[j] : alo, ahi = A[j] > ahi ? A[j] : ahi;
            blo = B[j] < blo ? B[j] : blo, bhi = B[j] > bhi ? B[j] : bhi;
        }
        /* every level-L micro-triangle in T's box: upright (a, b) (a+1, b)
         * (a, b+1) and inverted (a+1, b) (a+1, b+1) (a, b+1), clipped to
         * T; the difference is affine on each piece, largest at a corner */
        for (int64_t b = blo; b < bhi; b++)
            for (int64_t a = alo; a < ahi && a + b < n; a++)
                for (int inv = 0; inv < 2 && !(inv && a + b + 2 > n); inv++) {
                    domain_pt p[8], q[8];
                    p[0] = lattice_pt(fine, pos, a + inv, b);
                    p[1] = inv ? lattice_pt(fine, pos, a + 1, b + 1) : lattice_pt(fine, pos, a + 1, b);
                    p[2] = lattice_pt(fine, pos, a, b + 1);
                    int m = clip_half(p, 3, g1a, g1b, g10, q);
                    m = clip_half(q, m, g2a, g2b, g20, p);
                    m = clip_half(p, m, -g1a - g2a, -g1b - g2b, 1.0 - g10 - g20, q);
                    for (int i = 0; i < m; i++) {
                        double w1 = g1a * q[i].a + g1b * q[i].b + g10;
                        double w2 = g2a * q[i].a + g2b * q[i].b + g20, w0 = 1.0 - w1 - w2, d2 = 0;
                        for (int e = 0; e < 3; e++) {
                            double d = q[i].x[e] - (w0 * X[0].x[e] + w1 * X[1].x[e] + w2 * X[2].x[e]);
                            d2 += d * d;
                        }
                        worst = fmax(worst, d2);
                    }
                }
    }
    return sqrt(worst);
}
