/*
 * dmm_file.c - the baked-DMM file and the disk cache of bakes (dmm_file.h,
 * docs/dmm-format.md "Baked DMM file").
 *
 * One parser serves both directions: the reader runs it keeping what it
 * parses, the writer runs it over the bytes it just produced and keeps
 * nothing, so a writer can never store a file its reader refuses (a cache
 * entry that never loads would make every job bake again, silently).
 * Values are assembled byte by byte, so the host's byte order and the
 * buffer's alignment never matter.
 *
 * The cache's mechanics (envelope checks, key stream, path, hit/miss/
 * replace, atomic store) are util/derived.h's; what is here is the DMM's
 * own: the layout, the key's inputs, the fit check and the builder.
 */
#include "kinds/dmm/dmm_file.h"

#include <math.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "util/crc32.h"
#include "util/derived.h"
#include "util/le.h"

/* this file's format (the envelope's constants; below) */
#define FORMAT (&mr_dmm_file_format)

/* File header fields (byte offsets) after the envelope's magic, version
 * and header size (util/derived.h); the key and the CRC are the envelope's
 * too. */
enum { H_MESHES = 16, H_LEVEL = 20, H_BITS = 24, H_KEY = 32, H_CRC = 64 };
_Static_assert(H_CRC + 4 == MR_DMM_FILE_HEADER_BYTES, "header layout");

const mr_derived_format mr_dmm_file_format = {
    .name = "dmm bake file", .ext = "dmm", .magic = {'M', 'R', 'D', 'M', 'B', 0, '\r', '\n'},
    .version = MR_DMM_FILE_VERSION, .header_bytes = MR_DMM_FILE_HEADER_BYTES, .key_at = H_KEY,
    .max_bytes = MR_DMM_FILE_MAX_BYTES};

static const uint8_t mesh_tag[4] = {'M', 'E', 'S', 'H'};

#define FLAG_BAKED 1u
#define FLAG_SKINNED 2u
/* Mesh section header fields (offsets from the section start). */
enum { M_INDEX = 4, M_FLAGS = 8, M_SRC_VERTICES = 12, M_SRC_JOINTS = 16, M_VERTICES = 20,
       M_TRIANGLES = 24, M_RESERVED0 = 28, M_FALLBACKS = 32, M_SAMPLES = 40, M_RMS = 48,
       M_MAX = 56, M_SIMPLIFY = 64, M_RESERVED1 = 68, M_ARRAY_BYTES = 72, M_DMM_BYTES = 80,
       M_RESERVED2 = 88, M_CRC = 92 };

/* Per base vertex: position, direction (3 f32 each), source (u32); skinned
 * adds MR_MAX_INFLUENCES u16 joints and f32 weights. Per base triangle: 3
 * u32 indices. */
#define VERTEX_BYTES 28u
#define SKIN_BYTES (MR_MAX_INFLUENCES * 6u)
#define TRIANGLE_BYTES 12u

/* ---- parser (reader, and the writer's read-back check) */

/* keep: build the mr_dmm_file (a read) or only check (the writer's) */
typedef mr_derived_reader parser;

/* MR_ERR_FORMAT "dmm bake file: ..." */
#define bad(p, ...) mr_derived_bad((p)->format, (p)->err, __VA_ARGS__)

static bool finite_nonneg(double v) { return isfinite(v) && v >= 0; }

static int parse_header(parser *p, mr_dmm_file *f)
{
    const uint8_t *b = p->buf;
    int rc = mr_derived_header_check(p);
    if (rc < 0)
        return rc;
    uint32_t meshes = mr_le_get_u32(b + H_MESHES);
    uint64_t room = (p->size - MR_DMM_FILE_HEADER_BYTES) / MR_DMM_FILE_MESH_HEADER_BYTES;
    if (meshes == 0 || meshes > room)
        return bad(p, "mesh count %u at byte offset %d (1..%llu: each mesh takes at least %u of "
                   "the %zu bytes)", meshes, H_MESHES, (unsigned long long)room,
                   MR_DMM_FILE_MESH_HEADER_BYTES, p->size);
    uint32_t level = mr_le_get_u32(b + H_LEVEL);
    if (level > MR_UMESH_MAX_LEVEL)
        return bad(p, "level %u at byte offset %d (max %u)", level, H_LEVEL, MR_UMESH_MAX_LEVEL);
    memset(f->bits, 0, sizeof f->bits);
    for (unsigned i = 0; i < 8; i++) {
        uint8_t v = b[H_BITS + i];
        bool ok = i == 0       ? v >= 1 && v <= MR_DMM_MAX_BITS
                  : i <= level ? v >= 2 && v <= MR_DMM_MAX_BITS
                               : v == 0;
        if (!ok)
            return bad(p, "bad bit width %u at byte offset %u", v, H_BITS + i);
        if (i <= MR_UMESH_MAX_LEVEL)
            f->bits[i] = v;
    }
    f->level = level;
    f->mesh_count = meshes;
    memcpy(f->key, b + H_KEY, MR_DERIVED_KEY_BYTES);
    return MR_OK;
}

/* Running totals over the meshes, for the asset-wide caps. */
typedef struct totals { uint64_t vertices, triangles; } totals;

/* Checks the fixed mesh header at off; fills m (counts) and the section's
 * byte sizes. */
static int parse_mesh_header(parser *p, const mr_dmm_file *f, uint32_t i, size_t off, totals *tot,
                             uint32_t *flags, uint32_t *nv, uint32_t *nt, uint64_t *array_bytes,
                             uint64_t *dmm_bytes, mr_dmm_file_mesh *m, mr_dmm_bake *report)
{
    const uint8_t *h = p->buf + off;
    if (p->size - off < MR_DMM_FILE_MESH_HEADER_BYTES)
        return bad(p, "mesh %u: truncated at byte offset %zu (its header at %zu needs %u bytes)",
                   i, p->size, off, MR_DMM_FILE_MESH_HEADER_BYTES);
    for (size_t k = 0; k < sizeof mesh_tag; k++)
        if (h[k] != mesh_tag[k])
            return bad(p, "mesh %u: bad section tag at byte offset %zu", i, off + k);
    if (!mr_crc32_matches(mr_le_get_u32(h + M_CRC), h, M_CRC))
        return bad(p, "mesh %u: header checksum mismatch at byte offset %zu (bytes %zu..%zu "
                   "corrupted)", i, off + M_CRC, off, off + M_CRC - 1);
#define FIELD(o) (off + (size_t)(o))
    if (mr_le_get_u32(h + M_INDEX) != i)
        return bad(p, "mesh index %u at byte offset %zu (want %u)", mr_le_get_u32(h + M_INDEX),
                   FIELD(M_INDEX), i);
    *flags = mr_le_get_u32(h + M_FLAGS);
    bool baked = *flags & FLAG_BAKED, skinned = *flags & FLAG_SKINNED;
    if ((*flags & ~(FLAG_BAKED | FLAG_SKINNED)) || (skinned && !baked))
        return bad(p, "mesh %u: bad flags 0x%x at byte offset %zu", i, *flags, FIELD(M_FLAGS));
    const int reserved[3] = {M_RESERVED0, M_RESERVED1, M_RESERVED2};
    for (int k = 0; k < 3; k++)
        if (mr_le_get_u32(h + reserved[k]) != 0)
            return bad(p, "mesh %u: reserved field at byte offset %zu is not 0", i,
                       FIELD(reserved[k]));
    m->source_vertex_count = mr_le_get_u32(h + M_SRC_VERTICES);
    m->source_joint_count = mr_le_get_u32(h + M_SRC_JOINTS);
    if (m->source_vertex_count > MR_MAX_ASSET_VERTICES)
        return bad(p, "mesh %u: source vertex count %u at byte offset %zu (max %u)", i,
                   m->source_vertex_count, FIELD(M_SRC_VERTICES), MR_MAX_ASSET_VERTICES);
    if (m->source_joint_count > MR_MAX_ASSET_JOINTS)
        return bad(p, "mesh %u: source joint count %u at byte offset %zu (max %u)", i,
                   m->source_joint_count, FIELD(M_SRC_JOINTS), MR_MAX_ASSET_JOINTS);
    *nv = mr_le_get_u32(h + M_VERTICES);
    *nt = mr_le_get_u32(h + M_TRIANGLES);
    report->fallback_count = mr_le_get_u64(h + M_FALLBACKS);
    report->sample_count = mr_le_get_u64(h + M_SAMPLES);
    report->rms_distance = mr_le_get_f64(h + M_RMS);
    report->max_distance = mr_le_get_f64(h + M_MAX);
    report->simplify_error = mr_le_get_f32(h + M_SIMPLIFY);
    *array_bytes = mr_le_get_u64(h + M_ARRAY_BYTES);
    *dmm_bytes = mr_le_get_u64(h + M_DMM_BYTES);
    if (!baked) {
        /* a mesh without triangles: nothing but its source counts */
        const int zero[] = {M_VERTICES, M_TRIANGLES, M_FALLBACKS, M_FALLBACKS + 4, M_SAMPLES,
                            M_SAMPLES + 4, M_RMS, M_RMS + 4, M_MAX, M_MAX + 4, M_SIMPLIFY,
                            M_ARRAY_BYTES, M_ARRAY_BYTES + 4, M_DMM_BYTES, M_DMM_BYTES + 4};
        for (size_t k = 0; k < sizeof zero / sizeof zero[0]; k++)
            if (mr_le_get_u32(h + zero[k]) != 0)
                return bad(p, "mesh %u has no DMM but byte offset %zu is not 0", i,
                           FIELD(zero[k]));
        return MR_OK;
    }
    uint64_t mv = mr_umesh_vertex_count(f->level), mt = mr_umesh_triangle_count(f->level);
    if (*nv < 3 || *nv > m->source_vertex_count)
        return bad(p, "mesh %u: base vertex count %u at byte offset %zu (3..%u, the source "
                   "vertex count)", i, *nv, FIELD(M_VERTICES), m->source_vertex_count);
    tot->vertices += *nv;
    if (tot->vertices > MR_MAX_ASSET_VERTICES)
        return bad(p, "mesh %u: base vertex count %u at byte offset %zu brings the asset to "
                   "%llu (max %u)", i, *nv, FIELD(M_VERTICES),
                   (unsigned long long)tot->vertices, MR_MAX_ASSET_VERTICES);
    if (*nt < 1 || *nt > MR_DMM_MAX_TRIANGLES)
        return bad(p, "mesh %u: base triangle count %u at byte offset %zu (1..%u)", i, *nt,
                   FIELD(M_TRIANGLES), MR_DMM_MAX_TRIANGLES);
    tot->triangles += *nt;
    if (tot->triangles * mt > MR_MAX_ASSET_TRIANGLES ||
        tot->triangles * mv > MR_MAX_ASSET_VERTICES)
        return bad(p, "mesh %u: base triangle count %u at byte offset %zu brings the asset to "
                   "%llu at level %u, beyond %u micro-triangles / vertices", i, *nt,
                   FIELD(M_TRIANGLES), (unsigned long long)tot->triangles, f->level,
                   MR_MAX_ASSET_TRIANGLES);
    if (skinned && m->source_joint_count == 0)
        return bad(p, "mesh %u: skinned (flags at byte offset %zu) but its source has no joints "
                   "(byte offset %zu)", i, FIELD(M_FLAGS), FIELD(M_SRC_JOINTS));
    if (report->fallback_count > *nt * mv)
        return bad(p, "mesh %u: fallback count %llu at byte offset %zu exceeds the %llu "
                   "micro-vertices", i, (unsigned long long)report->fallback_count,
                   FIELD(M_FALLBACKS), (unsigned long long)(*nt * mv));
    /* triangles below the file's level take fewer samples */
    if (report->sample_count < *nt * 4 || report->sample_count > *nt * (mv + mt))
        return bad(p, "mesh %u: sample count %llu at byte offset %zu (%llu..%llu)", i,
                   (unsigned long long)report->sample_count, FIELD(M_SAMPLES),
                   (unsigned long long)(*nt * 4), (unsigned long long)(*nt * (mv + mt)));
    if (!finite_nonneg(report->rms_distance))
        return bad(p, "mesh %u: rms distance at byte offset %zu is not finite and >= 0", i,
                   FIELD(M_RMS));
    if (!finite_nonneg(report->max_distance))
        return bad(p, "mesh %u: max distance at byte offset %zu is not finite and >= 0", i,
                   FIELD(M_MAX));
    if (!finite_nonneg(report->simplify_error))
        return bad(p, "mesh %u: simplify error at byte offset %zu is not finite and >= 0", i,
                   FIELD(M_SIMPLIFY));
    uint64_t want_arrays = (uint64_t)*nv * (VERTEX_BYTES + (skinned ? SKIN_BYTES : 0)) +
                           (uint64_t)*nt * TRIANGLE_BYTES;
    if (*array_bytes != want_arrays)
        return bad(p, "mesh %u: array size %llu at byte offset %zu (counts give %llu)", i,
                   (unsigned long long)*array_bytes, FIELD(M_ARRAY_BYTES),
                   (unsigned long long)want_arrays);
    /* per-triangle levels: the block checks its exact size itself; here
     * the bounds of level 0 and the file's level */
    uint64_t min_dmm = MR_DMM_HEADER_BYTES + (uint64_t)*nt * (1 + mr_dmm_record_bytes(0, f->bits)) + 4;
    uint64_t want_dmm = MR_DMM_HEADER_BYTES +
                        (uint64_t)*nt * (1 + mr_dmm_record_bytes(f->level, f->bits)) + 4;
    if (*dmm_bytes < min_dmm || *dmm_bytes > want_dmm)
        return bad(p, "mesh %u: displacement block size %llu at byte offset %zu (counts give "
                   "%llu..%llu)", i, (unsigned long long)*dmm_bytes, FIELD(M_DMM_BYTES),
                   (unsigned long long)min_dmm, (unsigned long long)want_dmm);
    want_dmm = *dmm_bytes;
    /* every size is capped above, so the sum cannot overflow */
    uint64_t need = MR_DMM_FILE_MESH_HEADER_BYTES + want_arrays + 4 + want_dmm;
    if ((uint64_t)(p->size - off) < need)
        return bad(p, "mesh %u: truncated at byte offset %zu (its section at %zu needs %llu "
                   "bytes)", i, p->size, off, (unsigned long long)need);
#undef FIELD
    return MR_OK;
}

/* Checks (and with p->keep, copies into b) the arrays of a baked mesh at off. */
static int parse_arrays(parser *p, uint32_t i, size_t off, uint32_t flags, uint32_t nv,
                        uint32_t nt, const mr_dmm_file_mesh *m, mr_dmm_bake *b)
{
    const uint8_t *a = p->buf + off;
    bool skinned = flags & FLAG_SKINNED;
    size_t n = (size_t)nv * (VERTEX_BYTES + (skinned ? SKIN_BYTES : 0)) + (size_t)nt * TRIANGLE_BYTES;
    if (!mr_crc32_matches(mr_le_get_u32(a + n), a, n))
        return bad(p, "mesh %u: array checksum mismatch at byte offset %zu (bytes %zu..%zu "
                   "corrupted)", i, off + n, off, off + n - 1);
    size_t pos_at = 0, dir_at = pos_at + (size_t)nv * 12, idx_at = dir_at + (size_t)nv * 12;
    size_t src_at = idx_at + (size_t)nt * 12, joint_at = src_at + (size_t)nv * 4;
    size_t weight_at = joint_at + (size_t)nv * MR_MAX_INFLUENCES * 2;
    for (size_t k = 0; k < (size_t)nv * 3; k++) {
        float x = mr_le_get_f32(a + pos_at + k * 4), d = mr_le_get_f32(a + dir_at + k * 4);
        if (!isfinite(x))
            return bad(p, "mesh %u: base position %zu at byte offset %zu is not finite", i, k / 3,
                       off + pos_at + k * 4);
        if (!isfinite(d))
            return bad(p, "mesh %u: base direction %zu at byte offset %zu is not finite", i,
                       k / 3, off + dir_at + k * 4);
        if (p->keep)
            b->base_positions[k] = x, b->base_directions[k] = d;
    }
    for (size_t k = 0; k < (size_t)nt * 3; k++) {
        uint32_t v = mr_le_get_u32(a + idx_at + k * 4);
        if (v >= nv)
            return bad(p, "mesh %u: base index %u at byte offset %zu is not below the %u base "
                       "vertices", i, v, off + idx_at + k * 4, nv);
        if (p->keep)
            b->base_indices[k] = v;
    }
    for (size_t k = 0; k < nv; k++) {
        uint32_t s = mr_le_get_u32(a + src_at + k * 4);
        if (s >= m->source_vertex_count)
            return bad(p, "mesh %u: source vertex %u at byte offset %zu is not below the %u "
                       "source vertices", i, s, off + src_at + k * 4, m->source_vertex_count);
        if (p->keep)
            b->base_source[k] = s;
    }
    if (!skinned)
        return MR_OK;
    for (size_t k = 0; k < (size_t)nv * MR_MAX_INFLUENCES; k++) {
        uint16_t j = mr_le_get_u16(a + joint_at + k * 2);
        float w = mr_le_get_f32(a + weight_at + k * 4);
        if (!isfinite(w))
            return bad(p, "mesh %u: weight at byte offset %zu is not finite", i,
                       off + weight_at + k * 4);
        /* the skinning skips zero weights, so only used joints must exist */
        if (w != 0.0f && j >= m->source_joint_count)
            return bad(p, "mesh %u: joint %u at byte offset %zu is not below the %u source "
                       "joints", i, j, off + joint_at + k * 2, m->source_joint_count);
        if (p->keep)
            b->joints[k] = j, b->weights[k] = w;
    }
    return MR_OK;
}

static int parse_block(parser *p, const mr_dmm_file *f, uint32_t i, size_t off, size_t n,
                       uint32_t nt, mr_dmm_encoded **out)
{
    mr_dmm_encoded *enc = NULL;
    int rc = mr_dmm_read(p->buf + off, n, &enc, p->err);
    if (rc < 0) {
        /* its own offsets are relative to the block */
        mr_error_prefix(p->err, "dmm bake file: mesh %u: displacement block at byte offset %zu: ",
                        i, off);
        return rc;
    }
    if (enc->level != f->level || memcmp(enc->bits, f->bits, sizeof f->bits) != 0)
        rc = bad(p, "mesh %u: displacement block level/widths at byte offset %zu differ from the "
                 "file header's", i, off + 16);
    else if (enc->triangle_count != nt)
        rc = bad(p, "mesh %u: displacement block triangle count %u at byte offset %zu (want %u)",
                 i, enc->triangle_count, off + 28, nt);
    if (rc < 0 || !p->keep)
        mr_dmm_encoded_free(enc);
    else
        *out = enc;
    return rc;
}

static mr_dmm_bake *bake_alloc(uint32_t flags, uint32_t nv, uint32_t nt)
{
    mr_dmm_bake *b = calloc(1, sizeof *b);
    if (!b)
        return NULL;
    b->base_positions = malloc((size_t)nv * 3 * sizeof(float));
    b->base_directions = malloc((size_t)nv * 3 * sizeof(float));
    b->base_indices = malloc((size_t)nt * 3 * sizeof(uint32_t));
    b->base_source = malloc((size_t)nv * sizeof(uint32_t));
    bool ok = b->base_positions && b->base_directions && b->base_indices && b->base_source;
    if (flags & FLAG_SKINNED) {
        b->joints = malloc((size_t)nv * MR_MAX_INFLUENCES * sizeof(uint16_t));
        b->weights = malloc((size_t)nv * MR_MAX_INFLUENCES * sizeof(float));
        ok = ok && b->joints && b->weights;
    }
    if (!ok) {
        mr_dmm_bake_free(b);
        return NULL;
    }
    return b;
}

static int parse(parser *p, void *result)
{
    mr_dmm_file **out = result;
    mr_dmm_file *f = calloc(1, sizeof *f);
    if (!f)
        return mr_error_set(p->err, MR_ERR_NOMEM, "dmm bake file: out of memory");
    int rc = parse_header(p, f);
    if (rc < 0)
        goto fail;
    f->meshes = calloc(f->mesh_count, sizeof *f->meshes);
    if (!f->meshes) {
        rc = mr_error_set(p->err, MR_ERR_NOMEM, "dmm bake file: out of memory for %u meshes",
                          f->mesh_count);
        goto fail;
    }
    size_t off = MR_DMM_FILE_HEADER_BYTES;
    totals tot = {0, 0};
    for (uint32_t i = 0; i < f->mesh_count; i++) {
        mr_dmm_file_mesh *m = &f->meshes[i];
        uint32_t flags = 0, nv = 0, nt = 0;
        uint64_t array_bytes = 0, dmm_bytes = 0;
        mr_dmm_bake report = {0};
        rc = parse_mesh_header(p, f, i, off, &tot, &flags, &nv, &nt, &array_bytes, &dmm_bytes, m,
                               &report);
        if (rc < 0)
            goto fail;
        off += MR_DMM_FILE_MESH_HEADER_BYTES;
        if (!(flags & FLAG_BAKED))
            continue;
        if (p->keep) {
            if (!(m->bake = bake_alloc(flags, nv, nt))) {
                rc = mr_error_set(p->err, MR_ERR_NOMEM,
                                  "dmm bake file: out of memory for mesh %u (%u base vertices)",
                                  i, nv);
                goto fail;
            }
            mr_dmm_bake *b = m->bake;
            b->level = f->level;
            b->micro_vertex_count = mr_umesh_vertex_count(f->level);
            b->base_vertex_count = nv;
            b->base_triangle_count = nt;
            b->fallback_count = report.fallback_count;
            b->sample_count = report.sample_count;
            b->rms_distance = report.rms_distance;
            b->max_distance = report.max_distance;
            b->simplify_error = report.simplify_error;
        }
        if ((rc = parse_arrays(p, i, off, flags, nv, nt, m, m->bake)) < 0)
            goto fail;
        off += (size_t)array_bytes + 4;
        if ((rc = parse_block(p, f, i, off, (size_t)dmm_bytes, nt, &m->encoded)) < 0)
            goto fail;
        if (p->keep && !(m->bake->tri_info = malloc(nt))) {
            rc = mr_error_set(p->err, MR_ERR_NOMEM, "dmm bake file: out of memory for mesh %u", i);
            goto fail;
        }
        if (p->keep)
            memcpy(m->bake->tri_info, m->encoded->tri_info, nt);
        off += (size_t)dmm_bytes;
    }
    if (off != p->size) {
        rc = bad(p, "%zu unexpected trailing bytes at byte offset %zu", p->size - off, off);
        goto fail;
    }
    if (p->keep)
        *out = f;
    else
        mr_dmm_file_free(f);
    return MR_OK;
fail:
    mr_dmm_file_free(f);
    return rc;
}

void mr_dmm_file_free(mr_dmm_file *f)
{
    if (!f)
        return;
    if (f->meshes)
        for (uint32_t i = 0; i < f->mesh_count; i++) {
            mr_dmm_bake_free(f->meshes[i].bake);
            mr_dmm_encoded_free(f->meshes[i].encoded);
        }
    free(f->meshes);
    free(f);
}

int mr_dmm_file_read(const uint8_t *buf, size_t size, mr_dmm_file **out, mr_error *err)
{
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "dmm bake file read: bad arguments");
    *out = NULL;
    return mr_derived_parse(FORMAT, buf, size, parse, out, err);
}

/* ---- writer */

static int write_invalid(mr_error *err, const char *what)
{
    return mr_error_set(err, MR_ERR_INVALID, "dmm bake file write: %s", what);
}

int mr_dmm_file_write(const mr_dmm_file *f, uint8_t **buf, size_t *size, mr_error *err)
{
    if (buf)
        *buf = NULL;
    if (!f || !buf || !size || f->mesh_count == 0 || !f->meshes || f->level > MR_UMESH_MAX_LEVEL)
        return write_invalid(err, "bad arguments");
    uint8_t bits[MR_UMESH_MAX_LEVEL + 1] = {0};
    memcpy(bits, f->bits, f->level + 1);
    if (mr_dmm_record_bytes(f->level, bits) == 0)
        return write_invalid(err, "bad bit widths");
    /* sizes first; the read-back check below catches counts beyond the caps */
    uint64_t total = MR_DMM_FILE_HEADER_BYTES;
    for (uint32_t i = 0; i < f->mesh_count; i++) {
        const mr_dmm_file_mesh *m = &f->meshes[i];
        total += MR_DMM_FILE_MESH_HEADER_BYTES;
        if (!m->bake && !m->encoded)
            continue;
        const mr_dmm_bake *b = m->bake;
        const mr_dmm_encoded *e = m->encoded;
        if (!b || !e || !e->records || !b->base_positions || !b->base_directions ||
            !b->base_indices || !b->base_source || !b->joints != !b->weights)
            return write_invalid(err, "a mesh lacks its bake or its encoding");
        if (e->triangle_count != b->base_triangle_count || e->level != f->level ||
            memcmp(e->bits, bits, f->level + 1) != 0 ||
            b->base_triangle_count > MR_DMM_MAX_TRIANGLES || !b->tri_info ||
            memcmp(b->tri_info, e->tri_info, b->base_triangle_count) != 0)
            return write_invalid(err, "a mesh's encoding does not match its bake or the level");
        total += (uint64_t)b->base_vertex_count * (VERTEX_BYTES + (b->joints ? SKIN_BYTES : 0)) +
                 (uint64_t)b->base_triangle_count * TRIANGLE_BYTES + 4 + MR_DMM_HEADER_BYTES +
                 (uint64_t)b->base_triangle_count + e->records_bytes + 4;
    }
    uint8_t *out = NULL;
    parser *p = NULL; /* over out: its CRC table, then the read-back */
    int rc = mr_derived_buffer(FORMAT, total, &out, &p, err);
    if (rc < 0)
        return rc;
    mr_le_put_u32(out + H_MESHES, f->mesh_count);
    mr_le_put_u32(out + H_LEVEL, f->level);
    memcpy(out + H_BITS, bits, f->level + 1);
    mr_derived_header_seal(FORMAT, f->key, out);
    size_t off = MR_DMM_FILE_HEADER_BYTES;
    for (uint32_t i = 0; i < f->mesh_count; i++) {
        const mr_dmm_file_mesh *m = &f->meshes[i];
        const mr_dmm_bake *b = m->bake;
        uint8_t *h = out + off;
        memcpy(h, mesh_tag, sizeof mesh_tag);
        mr_le_put_u32(h + M_INDEX, i);
        mr_le_put_u32(h + M_SRC_VERTICES, m->source_vertex_count);
        mr_le_put_u32(h + M_SRC_JOINTS, m->source_joint_count);
        off += MR_DMM_FILE_MESH_HEADER_BYTES;
        if (!b) {
            mr_le_put_u32(h + M_CRC, mr_crc32(h, M_CRC));
            continue;
        }
        uint32_t nv = b->base_vertex_count, nt = b->base_triangle_count;
        bool skinned = b->joints != NULL;
        size_t arrays = (size_t)nv * (VERTEX_BYTES + (skinned ? SKIN_BYTES : 0)) +
                        (size_t)nt * TRIANGLE_BYTES;
        uint8_t *block = NULL;
        size_t block_size = 0;
        if ((rc = mr_dmm_write(m->encoded, &block, &block_size, err)) < 0) {
            mr_error_prefix(err, "dmm bake file write: mesh %u: ", i);
            goto cleanup;
        }
        mr_le_put_u32(h + M_FLAGS, FLAG_BAKED | (skinned ? FLAG_SKINNED : 0));
        mr_le_put_u32(h + M_VERTICES, nv);
        mr_le_put_u32(h + M_TRIANGLES, nt);
        mr_le_put_u64(h + M_FALLBACKS, b->fallback_count);
        mr_le_put_u64(h + M_SAMPLES, b->sample_count);
        mr_le_put_f64(h + M_RMS, b->rms_distance);
        mr_le_put_f64(h + M_MAX, b->max_distance);
        mr_le_put_f32(h + M_SIMPLIFY, b->simplify_error);
        mr_le_put_u64(h + M_ARRAY_BYTES, arrays);
        mr_le_put_u64(h + M_DMM_BYTES, block_size);
        mr_le_put_u32(h + M_CRC, mr_crc32(h, M_CRC));
        uint8_t *a = out + off;
        for (size_t k = 0; k < (size_t)nv * 3; k++)
            mr_le_put_f32(a + k * 4, b->base_positions[k]);
        a += (size_t)nv * 12;
        for (size_t k = 0; k < (size_t)nv * 3; k++)
            mr_le_put_f32(a + k * 4, b->base_directions[k]);
        a += (size_t)nv * 12;
        for (size_t k = 0; k < (size_t)nt * 3; k++)
            mr_le_put_u32(a + k * 4, b->base_indices[k]);
        a += (size_t)nt * 12;
        for (size_t k = 0; k < nv; k++)
            mr_le_put_u32(a + k * 4, b->base_source[k]);
        a += (size_t)nv * 4;
        if (skinned) {
            for (size_t k = 0; k < (size_t)nv * MR_MAX_INFLUENCES; k++)
                mr_le_put_u16(a + k * 2, b->joints[k]);
            a += (size_t)nv * MR_MAX_INFLUENCES * 2;
            for (size_t k = 0; k < (size_t)nv * MR_MAX_INFLUENCES; k++)
                mr_le_put_f32(a + k * 4, b->weights[k]);
        }
        mr_le_put_u32(out + off + arrays, mr_crc32(out + off, arrays));
        off += arrays + 4;
        /* the size check above used the same record size mr_dmm_write does */
        memcpy(out + off, block, block_size);
        off += block_size;
        free(block);
    }
    if ((rc = parse(p, NULL)) < 0) {
        rc = mr_derived_readback_failed(FORMAT, rc, err);
        goto cleanup;
    }
    *buf = out;
    *size = (size_t)total;
    out = NULL;
cleanup:
    free(out);
    free(p);
    return rc;
}

int mr_dmm_file_write_path(const mr_dmm_file *f, const char *path, mr_error *err)
{
    uint8_t *buf = NULL;
    size_t size = 0;
    if (!path || !path[0])
        return mr_error_set(err, MR_ERR_INVALID, "dmm bake file write: no path");
    int rc = mr_dmm_file_write(f, &buf, &size, err);
    if (rc == MR_OK)
        rc = mr_derived_write(FORMAT, path, buf, size, err);
    free(buf);
    return rc;
}

static int read_parse(void *ctx, const uint8_t *buf, size_t size, mr_error *err)
{
    return mr_dmm_file_read(buf, size, ctx, err);
}

int mr_dmm_file_read_path(const char *path, mr_dmm_file **out, mr_error *err)
{
    static const mr_derived_ops read_ops = {.parse = read_parse};
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "dmm bake file read: bad arguments");
    *out = NULL;
    return mr_derived_load(path, NULL, FORMAT, &read_ops, out, err);
}

/* ---- the cache (util/derived.h: key, path, load-or-bake, store) */

void mr_dmm_cache_key(const mr_asset *asset, const mr_dmm_bake_params *params,
                      const uint8_t bits[MR_UMESH_MAX_LEVEL + 1],
                      uint8_t key[MR_DERIVED_KEY_BYTES])
{
    mr_derived_key_builder kb;
    mr_derived_key_begin(&kb, "microray baked dmm cache", MR_DMM_FILE_VERSION,
                         MR_DMM_BAKER_REVISION);
    mr_derived_key_u32(&kb, (uint32_t)asset->mesh_count);
    for (size_t i = 0; i < asset->mesh_count; i++) {
        const mr_mesh *m = &asset->meshes[i];
        mr_derived_key_mesh_counts(&kb, m);
        mr_derived_key_u32(&kb, mr_derived_mesh_skinned(m)); /* the bake's rule */
        mr_derived_key_mesh_arrays(&kb, m, MR_DERIVED_POSITIONS | MR_DERIVED_INDICES |
                                               MR_DERIVED_SKIN);
    }
    mr_derived_key_u32(&kb, params->level);
    mr_derived_key_u32(&kb, params->adaptive);
    mr_derived_key_u32(&kb, params->target_triangles);
    mr_derived_key_f32s(&kb, &params->target_ratio, 1);
    mr_derived_key_f32s(&kb, &params->max_error, 1);
    mr_derived_key_f32s(&kb, &params->max_displacement, 1);
    for (unsigned l = 0; l <= MR_UMESH_MAX_LEVEL; l++)
        mr_derived_key_u32(&kb, bits[l]);
    mr_derived_key_end(&kb, key);
}

/* What the cache's callbacks see (their ctx): one bake of an asset. */
typedef struct bake_request {
    const mr_asset *asset;
    const mr_dmm_bake_params *params; /* the bake's: mr_dmm_bake_cached only */
    unsigned level;
    const uint8_t *bits;              /* MR_UMESH_MAX_LEVEL + 1 */
    mr_dmm_bake **bakes;              /* parse and build fill these (asset->mesh_count each) */
    mr_dmm_encoded **encoded;
    mr_dmm_bake *const *store_bakes;  /* serialise writes these */
    mr_dmm_encoded *const *store_encoded;
} bake_request;

/* Whether file f (stored under the right key) is the bake of r's asset at
 * r's level and widths; err says why not. */
static int matches(const mr_dmm_file *f, const bake_request *r, mr_error *err)
{
    const mr_asset *asset = r->asset;
    if (f->level != r->level || memcmp(f->bits, r->bits, r->level + 1) != 0)
        return mr_error_set(err, MR_ERR_FORMAT, "level or bit widths differ (byte offset %d)",
                            H_LEVEL);
    if (f->mesh_count != asset->mesh_count)
        return mr_error_set(err, MR_ERR_FORMAT, "%u meshes, the asset has %zu", f->mesh_count,
                            asset->mesh_count);
    for (uint32_t i = 0; i < f->mesh_count; i++) {
        const mr_mesh *am = &asset->meshes[i];
        const mr_dmm_file_mesh *m = &f->meshes[i];
        const mr_dmm_bake *b = m->bake;
        if ((b != NULL) != (am->triangle_count > 0) ||
            m->source_vertex_count != am->vertex_count ||
            m->source_joint_count != am->joint_count ||
            (b && (b->joints != NULL) != mr_derived_mesh_skinned(am)))
            return mr_error_set(err, MR_ERR_FORMAT, "mesh %u does not match the asset's", i);
        for (uint32_t v = 0; b && v < b->base_vertex_count; v++)
            if (memcmp(b->base_positions + (size_t)v * 3,
                       am->positions + (size_t)b->base_source[v] * 3, 3 * sizeof(float)) != 0)
                return mr_error_set(err, MR_ERR_FORMAT,
                                    "mesh %u: base vertex %u is not the asset's vertex %u", i, v,
                                    b->base_source[v]);
    }
    return MR_OK;
}

static int cache_parse(void *ctx, const uint8_t *buf, size_t size, mr_error *err)
{
    bake_request *r = ctx;
    mr_dmm_file *f = NULL;
    int rc = mr_dmm_file_read(buf, size, &f, err);
    if (rc == MR_OK && (rc = matches(f, r, err)) == MR_OK)
        for (size_t i = 0; i < r->asset->mesh_count; i++) {
            r->bakes[i] = f->meshes[i].bake;
            r->encoded[i] = f->meshes[i].encoded;
            f->meshes[i].bake = NULL;
            f->meshes[i].encoded = NULL;
        }
    mr_dmm_file_free(f);
    return rc;
}

static int cache_serialise(void *ctx, const uint8_t key[MR_DERIVED_KEY_BYTES], uint8_t **buf,
                           size_t *size, mr_error *err)
{
    const bake_request *r = ctx;
    const mr_asset *asset = r->asset;
    if (!asset || asset->mesh_count == 0 || asset->mesh_count > UINT32_MAX)
        return mr_error_set(err, MR_ERR_INVALID, "dmm cache store: bad arguments");
    mr_dmm_file f = {.level = r->level, .mesh_count = (uint32_t)asset->mesh_count};
    memcpy(f.bits, r->bits, sizeof f.bits);
    memcpy(f.key, key, MR_DERIVED_KEY_BYTES);
    if (!(f.meshes = calloc(asset->mesh_count, sizeof *f.meshes)))
        return mr_error_set(err, MR_ERR_NOMEM, "dmm cache store: out of memory");
    for (size_t i = 0; i < asset->mesh_count; i++)
        f.meshes[i] = (mr_dmm_file_mesh){.source_vertex_count = asset->meshes[i].vertex_count,
                                         .source_joint_count = asset->meshes[i].joint_count,
                                         .bake = r->store_bakes[i],
                                         .encoded = r->store_encoded[i]};
    int rc = mr_dmm_file_write(&f, buf, size, err);
    free(f.meshes);
    return rc;
}

/* Bakes and encodes every mesh with triangles; on failure nothing is kept. */
static int cache_build(void *ctx, mr_error *err)
{
    bake_request *r = ctx;
    const mr_asset *asset = r->asset;
    int rc = MR_OK;
    for (size_t i = 0; i < asset->mesh_count && rc == MR_OK; i++) {
        if (asset->meshes[i].triangle_count == 0)
            continue;
        if ((rc = mr_dmm_bake_run(&asset->meshes[i], r->params, &r->bakes[i], err)) == MR_OK) {
            mr_dmm_bake *b = r->bakes[i];
            rc = mr_dmm_encode(b->level, r->bits, b->base_triangle_count, b->tri_info,
                               b->displacements, &r->encoded[i], NULL, err);
            /* the encoding is what renders (and what a hit has): the float
             * displacements (up to 561 per base triangle) are done with */
            free(b->displacements);
            b->displacements = NULL;
        }
        if (rc < 0)
            mr_error_prefix(err, "%s: mesh %zu: ", asset->path, i);
    }
    for (size_t i = 0; i < asset->mesh_count && rc < 0; i++) {
        mr_dmm_bake_free(r->bakes[i]);
        mr_dmm_encoded_free(r->encoded[i]);
        r->bakes[i] = NULL;
        r->encoded[i] = NULL;
    }
    return rc;
}

static const mr_derived_ops bake_ops = {
    .parse = cache_parse, .serialise = cache_serialise, .build = cache_build};

static void clear(const mr_asset *asset, mr_dmm_bake **bakes, mr_dmm_encoded **encoded)
{
    for (size_t i = 0; i < asset->mesh_count; i++)
        bakes[i] = NULL, encoded[i] = NULL;
}

int mr_dmm_cache_load(const char *path, const uint8_t key[MR_DERIVED_KEY_BYTES],
                      const mr_asset *asset, unsigned level,
                      const uint8_t bits[MR_UMESH_MAX_LEVEL + 1], mr_dmm_bake **bakes,
                      mr_dmm_encoded **encoded, mr_error *err)
{
    clear(asset, bakes, encoded);
    bake_request r = {.asset = asset, .level = level, .bits = bits, .bakes = bakes,
                      .encoded = encoded};
    return mr_derived_load(path, key, FORMAT, &bake_ops, &r, err);
}

int mr_dmm_cache_store(const char *path, const uint8_t key[MR_DERIVED_KEY_BYTES],
                       const mr_asset *asset, unsigned level,
                       const uint8_t bits[MR_UMESH_MAX_LEVEL + 1], mr_dmm_bake *const *bakes,
                       mr_dmm_encoded *const *encoded, mr_error *err)
{
    bake_request r = {.asset = asset, .level = level, .bits = bits, .store_bakes = bakes,
                      .store_encoded = encoded};
    return mr_derived_store(path, key, FORMAT, &bake_ops, &r, err);
}

int mr_dmm_bake_cached(const mr_asset *asset, const mr_dmm_bake_params *params,
                       const uint8_t bits[MR_UMESH_MAX_LEVEL + 1], const char *cache_dir,
                       mr_dmm_bake **bakes, mr_dmm_encoded **encoded, bool *from_cache,
                       mr_error *err)
{
    if (from_cache)
        *from_cache = false;
    if (!asset || !params || !bits || !bakes || !encoded)
        return mr_error_set(err, MR_ERR_INVALID, "dmm bake: bad arguments");
    clear(asset, bakes, encoded);
    uint8_t key[MR_DERIVED_KEY_BYTES];
    const bool cached = cache_dir && cache_dir[0];
    if (cached)
        mr_dmm_cache_key(asset, params, bits, key);
    bake_request r = {.asset = asset, .params = params, .level = params->level, .bits = bits,
                      .bakes = bakes, .encoded = encoded, .store_bakes = bakes,
                      .store_encoded = encoded};
    return mr_derived_get(cached ? cache_dir : NULL, cached ? key : NULL, FORMAT, &bake_ops, &r,
                          from_cache, err);
}
