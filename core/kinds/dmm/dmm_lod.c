/*
 * dmm_lod.c - the distance of a dmm level to its detailed mesh (dmm_lod.h).
 */
#include "kinds/dmm/dmm_lod.h"

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
    uint32_t used_count, nt;
    uint32_t stride;            /* every stride-th sample of each kind */
    uint32_t distinct_n, used_n, tri_n; /* how many of each are sampled */
    double worst[MR_MAX_THREADS];
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
    distance_ctx *c = vctx;
    const mr_dmm_lod_truth *t = c->truth;
    double worst = c->worst[worker];
    for (size_t i = begin; i < end; i++) {
        double p[3];
        if (i < c->distinct_n) {
            point_of(t->pos, t->distinct[i * c->stride], p);
            worst = fmax(worst, mr_closest_mesh_distance(c->level, p, NULL));
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
        worst = fmax(worst, mr_closest_mesh_distance(&t->closest, p, NULL));
    }
    c->worst[worker] = worst;
}

int mr_dmm_lod_distance(const mr_dmm_lod_truth *t, const float *pos, uint32_t nv,
                        const uint32_t *idx, uint32_t nt, uint32_t stride, unsigned threads,
                        const char *who, double *out, mr_error *err)
{
    stride = stride ? stride : 1;
    *out = 0;
    uint8_t *mark = calloc(nv ? nv : 1, 1);
    uint32_t *used = malloc((size_t)(nv ? nv : 1) * sizeof *used);
    if (!mark || !used) {
        free(mark);
        free(used);
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory measuring levels of detail", who);
    }
    for (size_t e = 0; e < (size_t)nt * 3; e++)
        mark[idx[e]] = 1;
    uint32_t used_count = 0;
    for (uint32_t v = 0; v < nv; v++)
        if (mark[v])
            used[used_count++] = v;
    free(mark);
    mr_closest_mesh level;
    int rc = mr_closest_mesh_init(&level, t->closest.device, pos, nv, idx, nt, who, err);
    if (rc == MR_OK) {
        distance_ctx *c = calloc(1, sizeof *c);
        if (!c) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory measuring levels of detail", who);
        } else {
            *c = (distance_ctx){.truth = t, .level = &level, .pos = pos, .idx = idx, .used = used,
                                .used_count = used_count, .nt = nt, .stride = stride,
                                .distinct_n = (t->distinct_count + stride - 1) / stride,
                                .used_n = (used_count + stride - 1) / stride,
                                .tri_n = (nt + stride - 1) / stride};
            mr_parallel_for(threads, (size_t)c->distinct_n + c->used_n + c->tri_n, 256,
                            distance_range, c);
            for (unsigned w = 0; w < MR_MAX_THREADS; w++)
                *out = fmax(*out, c->worst[w]);
            free(c);
        }
        mr_closest_mesh_free(&level);
    }
    free(used);
    return rc;
}

/* ---- the errors in the derived-data cache ---- */

#define LOD_HEAD 104u /* errors end at 52 + 8 * 6 = 100, then the CRC */
#define AT_COUNT 16u
#define AT_KEY 20u
#define AT_ERRORS 52u

static const mr_derived_format ERRORS_FORMAT = {
    .name = "dmm lod errors file",
    .ext = "mrdle",
    .magic = {'M', 'R', 'D', 'L', 'E', '\0', '\r', '\n'},
    .version = MR_DMM_LOD_FILE_VERSION,
    .header_bytes = LOD_HEAD,
    .key_at = AT_KEY,
    .max_bytes = LOD_HEAD,
};

typedef struct errors_request {
    uint32_t count;
    double *errors;
    int (*measure)(void *ctx, double *errors, mr_error *err);
    void *ctx;
} errors_request;

static int errors_parse(void *vctx, const uint8_t *buf, size_t size, mr_error *err)
{
    errors_request *q = vctx;
    const mr_derived_format *f = &ERRORS_FORMAT;
    if (size != LOD_HEAD)
        return mr_derived_bad(f, err, "%zu bytes (the header's %u and nothing after it)", size, LOD_HEAD);
    const uint32_t count = mr_le_get_u32(buf + AT_COUNT);
    if (count != q->count)
        return mr_derived_bad(f, err, "%u levels at byte offset %u (want %u)", count, AT_COUNT, q->count);
    double e[MR_DMM_LOD_FILE_LEVELS];
    for (uint32_t k = 0; k < count; k++) {
        e[k] = mr_le_get_f64(buf + AT_ERRORS + 8 * k);
        if (!isfinite(e[k]) || e[k] < 0.0 || (k > 0 && e[k] < e[k - 1]))
            return mr_derived_bad(f, err, "level %u error %g at byte offset %u", k, e[k], AT_ERRORS + 8 * k);
    }
    memcpy(q->errors, e, count * sizeof *e);
    return MR_OK;
}

static int errors_serialise(void *vctx, const uint8_t key[MR_DERIVED_KEY_BYTES], uint8_t **out,
                            size_t *out_size, mr_error *err)
{
    errors_request *q = vctx;
    uint8_t *buf = NULL;
    mr_derived_reader *check = NULL;
    int rc = mr_derived_buffer(&ERRORS_FORMAT, LOD_HEAD, &buf, &check, err);
    if (rc < 0)
        return rc;
    mr_le_put_u32(buf + AT_COUNT, q->count);
    for (uint32_t k = 0; k < q->count; k++)
        mr_le_put_f64(buf + AT_ERRORS + 8 * k, q->errors[k]);
    mr_derived_header_seal(&ERRORS_FORMAT, &check->crc, key, buf);
    free(check);
    double back[MR_DMM_LOD_FILE_LEVELS];
    errors_request readback = *q;
    readback.errors = back;
    if ((rc = errors_parse(&readback, buf, LOD_HEAD, err)) < 0) {
        free(buf);
        return mr_derived_readback_failed(&ERRORS_FORMAT, rc, err);
    }
    *out = buf;
    *out_size = LOD_HEAD;
    return MR_OK;
}

static int errors_build(void *vctx, mr_error *err)
{
    errors_request *q = vctx;
    return q->measure(q->ctx, q->errors, err);
}

static const mr_derived_ops ERRORS_OPS = {errors_parse, errors_serialise, errors_build};

int mr_dmm_lod_errors_cached(const char *cache_dir, const uint8_t key[MR_DERIVED_KEY_BYTES], uint32_t count,
                             double *errors, int (*measure)(void *ctx, double *errors, mr_error *err),
                             void *ctx, bool *hit, mr_error *err)
{
    if (count < 1 || count > MR_DMM_LOD_FILE_LEVELS)
        return mr_error_set(err, MR_ERR_INVALID, "dmm lod errors: %u levels (1..%u)", count,
                            MR_DMM_LOD_FILE_LEVELS);
    errors_request q = {count, errors, measure, ctx};
    return mr_derived_get(cache_dir, key, &ERRORS_FORMAT, &ERRORS_OPS, &q, hit, err);
}
