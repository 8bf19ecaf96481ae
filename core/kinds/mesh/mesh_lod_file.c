/* mesh_lod_file.c - a mesh's levels of detail in the derived-data cache
 * (mesh_lod_file.h). */
#include "kinds/mesh/mesh_lod_file.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "kinds/lod.h"
#include "util/crc32.h"
#include "util/derived.h"
#include "util/le.h"

#define HEAD 96u
#define AT_VERTICES 16u
#define AT_TRIANGLES 20u
#define AT_LEVELS 24u
#define AT_DISTINCT 28u
#define AT_PAYLOAD_BYTES 32u
#define AT_PAYLOAD_CRC 40u
#define AT_KEY 48u
#define LEVEL_BYTES 16u

static const mr_derived_format LOD_FORMAT = {
    .name = "mesh lod file",
    .ext = "mrlod",
    .magic = {'M', 'R', 'M', 'L', 'O', 'D', '\r', '\n'},
    .version = MR_MESH_LOD_FILE_VERSION,
    .header_bytes = HEAD,
    .key_at = AT_KEY,
    /* 16 levels of at most MR_MAX_ASSET_TRIANGLES, halving: < 2x level 0's 12 B a triangle */
    .max_bytes = (uint64_t)HEAD + 16u * LEVEL_BYTES + 24ull * MR_MAX_ASSET_TRIANGLES +
                 4ull * MR_MAX_ASSET_VERTICES,
};

/* What is asked for and, once parsed or built, the chain. */
typedef struct request {
    mr_mesh_lod *lod;
    const float *pos, *normals;
    uint32_t nv, nt;
    const uint32_t *idx;
    const float *const *posed;
    uint32_t pose_count;
    unsigned threads;
    const char *who;
} request;

static void lod_key(const request *q, uint8_t key[MR_DERIVED_KEY_BYTES])
{
    mr_derived_key_builder kb;
    mr_derived_key_begin(&kb, "microray mesh lod", MR_MESH_LOD_FILE_VERSION, 1);
    mr_derived_key_u32(&kb, q->nv);
    mr_derived_key_u32(&kb, q->nt);
    mr_derived_key_f32s(&kb, q->pos, (size_t)q->nv * 3);
    mr_derived_key_f32s(&kb, q->normals, (size_t)q->nv * 3);
    for (size_t i = 0; i < (size_t)q->nt * 3; i++)
        mr_derived_key_u32(&kb, q->idx[i]);
    mr_derived_key_u32(&kb, q->pose_count);
    for (uint32_t j = 0; j < q->pose_count; j++)
        mr_derived_key_f32s(&kb, q->posed[j], (size_t)q->nv * 3);
    mr_derived_key_end(&kb, key);
}

static int parse(void *ctx, const uint8_t *buf, size_t size, mr_error *err)
{
    request *q = ctx;
    const mr_derived_format *f = &LOD_FORMAT;
    const uint32_t nv = mr_le_get_u32(buf + AT_VERTICES), nt = mr_le_get_u32(buf + AT_TRIANGLES);
    const uint32_t levels = mr_le_get_u32(buf + AT_LEVELS), distinct = mr_le_get_u32(buf + AT_DISTINCT);
    if (nv != q->nv || nt != q->nt)
        return mr_derived_bad(f, err, "%u vertices, %u triangles at byte offset %u (want %u, %u)", nv, nt,
                              AT_VERTICES, q->nv, q->nt);
    if (levels < 1 || levels > MR_MESH_LOD_MAX)
        return mr_derived_bad(f, err, "%u levels at byte offset %u (1..%u)", levels, AT_LEVELS,
                              MR_MESH_LOD_MAX);
    if (distinct < 1 || distinct > nv)
        return mr_derived_bad(f, err, "%u distinct vertices at byte offset %u (1..%u)", distinct, AT_DISTINCT,
                              nv);
    if (mr_le_get_u64(buf + AT_PAYLOAD_BYTES) != size - HEAD)
        return mr_derived_bad(f, err, "payload of %llu bytes at byte offset %u, the file holds %zu",
                              (unsigned long long)mr_le_get_u64(buf + AT_PAYLOAD_BYTES), AT_PAYLOAD_BYTES,
                              size - HEAD);
    if (!mr_crc32_matches(mr_le_get_u32(buf + AT_PAYLOAD_CRC), buf + HEAD, size - HEAD))
        return mr_derived_bad(f, err, "payload checksum mismatch (bytes %u..%zu)", HEAD, size - 1);
    mr_mesh_lod lod = {.level_count = levels, .indices = {(uint32_t *)q->idx}, .distinct_count = distinct};
    uint64_t need = (uint64_t)LEVEL_BYTES * levels + 4ull * distinct;
    for (uint32_t k = 0; k < levels; k++) {
        const uint8_t *l = buf + HEAD + (size_t)k * LEVEL_BYTES;
        const size_t at = HEAD + (size_t)k * LEVEL_BYTES;
        lod.triangles[k] = mr_le_get_u32(l);
        lod.error[k] = mr_le_get_f64(l + 8);
        if (k == 0 ? lod.triangles[0] != nt || lod.error[0] != 0.0
                   : lod.triangles[k] < 1 || lod.triangles[k] >= lod.triangles[k - 1])
            return mr_derived_bad(f, err, "level %u of %u triangles at byte offset %zu does not fit the mesh",
                                  k, lod.triangles[k], at);
        if (!isfinite(lod.error[k]) || lod.error[k] < 0.0)
            return mr_derived_bad(f, err, "level %u error %g at byte offset %zu", k, lod.error[k], at + 8);
        if (k > 0)
            need += 12ull * lod.triangles[k];
    }
    if (need != size - HEAD)
        return mr_derived_bad(f, err, "the levels need %llu payload bytes, the file holds %zu",
                              (unsigned long long)need, size - HEAD);
    const uint8_t *p = buf + HEAD + (size_t)LEVEL_BYTES * levels;
    for (size_t i = 0; i < (size_t)(need - LEVEL_BYTES * levels) / 4; i++)
        if (mr_le_get_u32(p + 4 * i) >= nv)
            return mr_derived_bad(f, err, "vertex %u at byte offset %zu (the mesh has %u)",
                                  mr_le_get_u32(p + 4 * i), (size_t)(p - buf) + 4 * i, nv);
    lod.distinct = malloc((size_t)distinct * sizeof(uint32_t));
    bool ok = lod.distinct != NULL;
    for (uint32_t k = 1; k < levels && ok; k++)
        ok = (lod.indices[k] = malloc((size_t)lod.triangles[k] * 3 * sizeof(uint32_t))) != NULL;
    if (!ok) {
        mr_mesh_lod_free(&lod);
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", f->name);
    }
    for (uint32_t k = 1; k < levels; k++)
        for (size_t i = 0; i < (size_t)lod.triangles[k] * 3; i++, p += 4)
            lod.indices[k][i] = mr_le_get_u32(p);
    for (uint32_t i = 0; i < distinct; i++, p += 4)
        lod.distinct[i] = mr_le_get_u32(p);
    *q->lod = lod;
    return MR_OK;
}

static int serialise(void *ctx, const uint8_t key[MR_DERIVED_KEY_BYTES], uint8_t **out, size_t *out_size,
                     mr_error *err)
{
    const request *q = ctx;
    const mr_mesh_lod *lod = q->lod;
    uint64_t payload = (uint64_t)LEVEL_BYTES * lod->level_count + 4ull * lod->distinct_count;
    for (uint32_t k = 1; k < lod->level_count; k++)
        payload += 12ull * lod->triangles[k];
    uint8_t *buf = NULL;
    mr_derived_reader *check = NULL;
    int rc = mr_derived_buffer(&LOD_FORMAT, HEAD + payload, &buf, &check, err);
    if (rc < 0)
        return rc;
    mr_le_put_u32(buf + AT_VERTICES, q->nv);
    mr_le_put_u32(buf + AT_TRIANGLES, q->nt);
    mr_le_put_u32(buf + AT_LEVELS, lod->level_count);
    mr_le_put_u32(buf + AT_DISTINCT, lod->distinct_count);
    mr_le_put_u64(buf + AT_PAYLOAD_BYTES, payload);
    uint8_t *p = buf + HEAD;
    for (uint32_t k = 0; k < lod->level_count; k++, p += LEVEL_BYTES) {
        mr_le_put_u32(p, lod->triangles[k]);
        mr_le_put_f64(p + 8, lod->error[k]);
    }
    for (uint32_t k = 1; k < lod->level_count; k++)
        for (size_t i = 0; i < (size_t)lod->triangles[k] * 3; i++, p += 4)
            mr_le_put_u32(p, lod->indices[k][i]);
    for (uint32_t i = 0; i < lod->distinct_count; i++, p += 4)
        mr_le_put_u32(p, lod->distinct[i]);
    mr_le_put_u32(buf + AT_PAYLOAD_CRC, mr_crc32(buf + HEAD, (size_t)payload));
    mr_derived_header_seal(&LOD_FORMAT, key, buf);
    /* read back with the parser, into a scratch chain (never a file the
     * reader refuses) */
    mr_mesh_lod scratch;
    request back = *q;
    back.lod = &scratch;
    if ((rc = parse(&back, buf, (size_t)(HEAD + payload), err)) < 0) {
        free(buf);
        free(check);
        return mr_derived_readback_failed(&LOD_FORMAT, rc, err);
    }
    mr_mesh_lod_free(&scratch);
    free(check);
    *out = buf;
    *out_size = (size_t)(HEAD + payload);
    return MR_OK;
}

static int build(void *ctx, mr_error *err)
{
    request *q = ctx;
    int rc = mr_mesh_lod_build(q->lod, q->pos, q->normals, q->nv, q->idx, q->nt, q->threads, q->who, err);
    for (uint32_t j = 0; j < q->pose_count && rc == MR_OK; j++)
        rc = mr_mesh_lod_measure(q->lod, q->posed[j], q->nv, MR_LOD_POSE_STRIDE, q->threads, q->who, err);
    if (rc < 0)
        mr_mesh_lod_free(q->lod);
    return rc;
}

static const mr_derived_ops LOD_OPS = {parse, serialise, build};

int mr_mesh_lod_cached(const char *cache_dir, mr_mesh_lod *lod, const float *pos, const float *normals,
                       uint32_t nv, const uint32_t *idx, uint32_t nt, const float *const *posed,
                       uint32_t pose_count, unsigned threads, const char *who, bool *hit, mr_error *err)
{
    request q = {lod, pos, normals, nv, nt, idx, posed, pose_count, threads, who};
    uint8_t key[MR_DERIVED_KEY_BYTES];
    if (cache_dir && cache_dir[0])
        lod_key(&q, key);
    else
        memset(key, 0, sizeof key);
    return mr_derived_get(cache_dir, key, &LOD_FORMAT, &LOD_OPS, &q, hit, err);
}
