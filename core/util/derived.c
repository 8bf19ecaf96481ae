/*
 * derived.c - the derived-data cache (derived.h): keys, paths, the file
 * envelope and the hit/miss/replace policy, once for every kind.
 */
#include "util/derived.h"

#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "util/file_io.h"
#include "util/hex.h"
#include "util/le.h"

/* ---- the key */

void mr_derived_key_begin(mr_derived_key_builder *kb, const char *tag, uint32_t version,
                          uint32_t revision)
{
    mr_sha256_feed_init(&kb->feed);
    mr_sha256_feed_bytes(&kb->feed, tag, strlen(tag) + 1);
    mr_sha256_feed_u32(&kb->feed, version);
    mr_sha256_feed_u32(&kb->feed, revision);
}

bool mr_derived_mesh_skinned(const mr_mesh *m)
{
    return m->joint_count > 0 && m->joints && m->weights;
}

unsigned mr_derived_mesh_parts(const mr_mesh *m, unsigned parts)
{
    unsigned have = (m->positions ? MR_DERIVED_POSITIONS : 0u) |
                    (m->normals ? MR_DERIVED_NORMALS : 0u) |
                    (m->indices ? MR_DERIVED_INDICES : 0u) |
                    (mr_derived_mesh_skinned(m) ? MR_DERIVED_SKIN : 0u);
    return have & parts;
}

void mr_derived_key_mesh_counts(mr_derived_key_builder *kb, const mr_mesh *m)
{
    mr_sha256_feed_u32(&kb->feed, m->vertex_count);
    mr_sha256_feed_u32(&kb->feed, m->triangle_count);
    mr_sha256_feed_u32(&kb->feed, m->joint_count);
}

void mr_derived_key_mesh_arrays(mr_derived_key_builder *kb, const mr_mesh *m, unsigned parts)
{
    const unsigned have = mr_derived_mesh_parts(m, parts);
    const size_t nv = m->vertex_count;
    if (have & MR_DERIVED_POSITIONS)
        mr_sha256_feed_f32s(&kb->feed, m->positions, nv * 3);
    if (have & MR_DERIVED_NORMALS)
        mr_sha256_feed_f32s(&kb->feed, m->normals, nv * 3);
    if (have & MR_DERIVED_INDICES)
        mr_sha256_feed_u32s(&kb->feed, m->indices, (size_t)m->triangle_count * 3);
    if (have & MR_DERIVED_SKIN) {
        mr_sha256_feed_u16s(&kb->feed, m->joints, nv * MR_MAX_INFLUENCES);
        mr_sha256_feed_f32s(&kb->feed, m->weights, nv * MR_MAX_INFLUENCES);
    }
}

void mr_derived_key_nodes(mr_derived_key_builder *kb, const mr_asset *asset)
{
    mr_sha256_feed_u64(&kb->feed, asset->node_count);
    for (size_t i = 0; i < asset->node_count; i++) {
        mr_sha256_feed_u32(&kb->feed, (uint32_t)asset->nodes[i].parent);
        mr_sha256_feed_f32s(&kb->feed, asset->nodes[i].local.m, 16);
    }
}

void mr_derived_key_end(mr_derived_key_builder *kb, uint8_t key[MR_DERIVED_KEY_BYTES])
{
    mr_sha256_feed_final(&kb->feed, key);
}

/* ---- the path */

int mr_derived_path(const char *dir, const uint8_t key[MR_DERIVED_KEY_BYTES], const char *ext,
                    char **path, mr_error *err)
{
    if (path)
        *path = NULL;
    if (!dir || !dir[0] || !key || !ext || !ext[0] || !path)
        return mr_error_set(err, MR_ERR_INVALID, "derived-data cache: no directory, key or "
                            "extension");
    size_t n = strlen(dir) + 1 + 2 * MR_DERIVED_KEY_BYTES + 1 + strlen(ext) + 1;
    char *p = malloc(n);
    if (!p)
        return mr_error_set(err, MR_ERR_NOMEM, "derived-data cache: out of memory");
    size_t at = (size_t)snprintf(p, n, "%s/", dir);
    mr_hex_encode(key, MR_DERIVED_KEY_BYTES, p + at);
    at += 2 * MR_DERIVED_KEY_BYTES;
    snprintf(p + at, n - at, ".%s", ext);
    *path = p;
    return MR_OK;
}

/* ---- the envelope */

int mr_derived_bad(const mr_derived_format *f, mr_error *err, const char *fmt, ...)
{
    char msg[sizeof err->msg];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(msg, sizeof msg, fmt, ap);
    va_end(ap);
    return mr_error_set(err, MR_ERR_FORMAT, "%s: %s", f->name, msg);
}

int mr_derived_parse(const mr_derived_format *f, const uint8_t *buf, size_t size,
                     int (*parse)(mr_derived_reader *r, void *out), void *out, mr_error *err)
{
    if (!buf && size)
        return mr_error_set(err, MR_ERR_INVALID, "%s read: bad arguments", f->name);
    mr_derived_reader r = {.format = f, .buf = buf, .size = size, .keep = true, .err = err};
    return parse(&r, out);
}

int mr_derived_header_check(mr_derived_reader *r)
{
    const mr_derived_format *f = r->format;
    const uint8_t *buf = r->buf;
    const uint32_t at_crc = f->header_bytes - 4;
    if (r->size < f->header_bytes)
        return mr_derived_bad(f, r->err, "truncated header at byte offset %zu (need %u bytes)",
                              r->size, f->header_bytes);
    for (size_t i = 0; i < sizeof f->magic; i++)
        if (buf[i] != f->magic[i])
            return mr_derived_bad(f, r->err, "bad magic at byte offset %zu (not a .%s file)", i,
                                  f->ext);
    uint32_t version = mr_le_get_u32(buf + MR_DERIVED_AT_VERSION);
    if (version != f->version)
        return mr_derived_bad(f, r->err, "unsupported version %u at byte offset %u (want %u)",
                              version, MR_DERIVED_AT_VERSION, f->version);
    uint32_t hb = mr_le_get_u32(buf + MR_DERIVED_AT_HEADER_BYTES);
    if (hb != f->header_bytes)
        return mr_derived_bad(f, r->err, "header_bytes %u at byte offset %u (want %u)", hb,
                              MR_DERIVED_AT_HEADER_BYTES, f->header_bytes);
    if (!mr_crc32_matches(mr_le_get_u32(buf + at_crc), buf, at_crc))
        return mr_derived_bad(f, r->err, "header checksum mismatch at byte offset %u (bytes "
                              "0..%u corrupted)", at_crc, at_crc - 1);
    return MR_OK;
}

int mr_derived_buffer(const mr_derived_format *f, uint64_t size, uint8_t **buf,
                      mr_derived_reader **check, mr_error *err)
{
    *buf = NULL;
    *check = NULL;
    /* the first write of any format under test finds a bad constant */
    if (f->key_at < MR_DERIVED_AT_FIELDS || f->header_bytes < 4 ||
        (uint64_t)f->key_at + MR_DERIVED_KEY_BYTES > f->header_bytes - 4u || size < f->header_bytes)
        return mr_error_set(err, MR_ERR_INVALID, "%s write: the header (%u bytes, key at byte "
                            "offset %u) does not hold its fields in %llu bytes", f->name,
                            f->header_bytes, f->key_at, (unsigned long long)size);
    if (size > f->max_bytes)
        return mr_error_set(err, MR_ERR_LIMIT, "%s write: %llu bytes exceed the %llu a reader "
                            "accepts", f->name, (unsigned long long)size,
                            (unsigned long long)f->max_bytes);
    uint8_t *b = calloc(1, size ? (size_t)size : 1);
    mr_derived_reader *r = malloc(sizeof *r);
    if (!b || !r) {
        free(b);
        free(r);
        return mr_error_set(err, MR_ERR_NOMEM, "%s write: out of memory for %llu bytes",
                            f->name, (unsigned long long)size);
    }
    *r = (mr_derived_reader){.format = f, .buf = b, .size = (size_t)size, .keep = false,
                             .err = err};
    *buf = b;
    *check = r;
    return MR_OK;
}

void mr_derived_header_seal(const mr_derived_format *f, const uint8_t *key, uint8_t *buf)
{
    memcpy(buf, f->magic, sizeof f->magic);
    mr_le_put_u32(buf + MR_DERIVED_AT_VERSION, f->version);
    mr_le_put_u32(buf + MR_DERIVED_AT_HEADER_BYTES, f->header_bytes);
    if (key)
        memcpy(buf + f->key_at, key, MR_DERIVED_KEY_BYTES);
    else
        memset(buf + f->key_at, 0, MR_DERIVED_KEY_BYTES);
    const uint32_t at_crc = f->header_bytes - 4;
    mr_le_put_u32(buf + at_crc, mr_crc32(buf, at_crc));
}

int mr_derived_readback_failed(const mr_derived_format *f, int rc, mr_error *err)
{
    mr_error_prefix(err, "%s write: would not read back: ", f->name);
    if (rc == MR_ERR_FORMAT) {
        rc = MR_ERR_INVALID;
        if (err)
            err->code = rc;
    }
    return rc;
}

/* ---- the cache */

/* mr_derived_load's parser: the envelope and the key, then the kind's. */
typedef struct load_request {
    const uint8_t *key;        /* NULL: any */
    const mr_derived_ops *ops; /* NULL: the envelope only */
    void *ctx;
} load_request;

static int parse_stored(mr_derived_reader *r, void *out)
{
    const load_request *q = out;
    const mr_derived_format *f = r->format;
    /* the envelope first: a foreign file is refused before it is parsed */
    int rc = mr_derived_header_check(r);
    if (rc < 0)
        return rc;
    if (q->key && memcmp(r->buf + f->key_at, q->key, MR_DERIVED_KEY_BYTES) != 0)
        return mr_derived_bad(f, r->err, "stored under another key (byte offset %u)", f->key_at);
    return q->ops ? q->ops->parse(q->ctx, r->buf, r->size, r->err) : MR_OK;
}

int mr_derived_load(const char *path, const uint8_t key[MR_DERIVED_KEY_BYTES],
                    const mr_derived_format *f, const mr_derived_ops *ops, void *ctx,
                    mr_error *err)
{
    if (!path || !path[0] || !f || !ops || !ops->parse)
        return mr_error_set(err, MR_ERR_INVALID, "derived-data cache load: bad arguments");
    uint8_t *buf = NULL;
    size_t size = 0;
    int rc = mr_fs_read_capped(path, f->max_bytes, &buf, &size, f->name, err);
    if (rc < 0)
        return rc;
    load_request q = {.key = key, .ops = ops, .ctx = ctx};
    if ((rc = mr_derived_parse(f, buf, size, parse_stored, &q, err)) < 0)
        mr_error_prefix(err, "%s: ", path);
    free(buf);
    return rc;
}

int mr_derived_write(const mr_derived_format *f, const char *path, const uint8_t *buf,
                     size_t size, mr_error *err)
{
    char what[128];
    snprintf(what, sizeof what, "%s write", f->name);
    return mr_fs_write_atomic(path, buf, size, what, err);
}

int mr_derived_store(const char *path, const uint8_t key[MR_DERIVED_KEY_BYTES],
                     const mr_derived_format *f, const mr_derived_ops *ops, void *ctx,
                     mr_error *err)
{
    if (!path || !path[0] || !key || !f || !ops || !ops->serialise)
        return mr_error_set(err, MR_ERR_INVALID, "derived-data cache store: bad arguments");
    uint8_t *buf = NULL;
    size_t size = 0;
    char *dir = NULL;
    int rc = ops->serialise(ctx, key, &buf, &size, err);
    if (rc < 0)
        goto done;
    /* what could never hit must not be stored: every later job would
     * rebuild and rewrite it, silently */
    load_request q = {.key = key}; /* the envelope only */
    if (mr_derived_parse(f, buf, size, parse_stored, &q, err) < 0) {
        rc = mr_error_set(err, MR_ERR_INVALID, "%s store: the file made would not be found "
                          "under its key", f->name);
        goto done;
    }
    if (!(dir = mr_fs_dir_of(path))) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", f->name);
        goto done;
    }
    if ((rc = mr_fs_make_dirs(dir, f->name, err)) == MR_OK)
        rc = mr_derived_write(f, path, buf, size, err);
done:
    free(dir);
    free(buf);
    return rc;
}

int mr_derived_get(const char *dir, const uint8_t key[MR_DERIVED_KEY_BYTES],
                   const mr_derived_format *f, const mr_derived_ops *ops, void *ctx, bool *hit,
                   mr_error *err)
{
    if (hit)
        *hit = false;
    if (!f || !ops || !ops->build)
        return mr_error_set(err, MR_ERR_INVALID, "derived-data cache: bad arguments");
    char *path = NULL;
    mr_error quiet = {0}; /* a miss or a failed store is not the caller's error */
    if (dir && dir[0] && key && mr_derived_path(dir, key, f->ext, &path, &quiet) == MR_OK &&
        mr_derived_load(path, key, f, ops, ctx, &quiet) == MR_OK) {
        if (hit)
            *hit = true;
        free(path);
        return MR_OK;
    }
    int rc = ops->build(ctx, err);
    /* a cache that cannot be written costs the next job a rebuild, never
     * this one its result */
    if (rc == MR_OK && path)
        (void)mr_derived_store(path, key, f, ops, ctx, &quiet);
    free(path);
    return rc;
}

void mr_derived_key_params(mr_derived_key_builder *kb, const mr_param_table *t, const void *values)
{
    for (size_t i = 0; i < t->count; i++) {
        const mr_param *p = &t->params[i];
        const char *at = (const char *)values + p->offset;
        switch (p->type) {
        case MR_PARAM_INT: mr_derived_key_u32(kb, *(const uint32_t *)at); break;
        case MR_PARAM_ENUM: mr_derived_key_u32(kb, (uint32_t) * (const int *)at); break;
        case MR_PARAM_NUMBER: mr_derived_key_f32s(kb, (const float *)at, 1); break;
        case MR_PARAM_BOOL: mr_derived_key_u32(kb, *(const bool *)at ? 1u : 0u); break;
        case MR_PARAM_VEC3: {
            const mr_vec3 *v = (const mr_vec3 *)at;
            float f[3] = {v->x, v->y, v->z};
            mr_derived_key_f32s(kb, f, 3);
            break;
        }
        case MR_PARAM_QUAT: {
            const mr_quat *q = (const mr_quat *)at;
            float f[4] = {q->x, q->y, q->z, q->w};
            mr_derived_key_f32s(kb, f, 4);
            break;
        }
        case MR_PARAM_TRANSFORM: mr_derived_key_f32s(kb, ((const mr_mat4 *)at)->m, 16); break;
        case MR_PARAM_FLAG_OBJECT:
            mr_derived_key_u32(kb, *(const bool *)at ? 1u : 0u);
            mr_derived_key_params(kb, p->sub, values);
            break;
        case MR_PARAM_ARRAY: {
            const char *items = *(const char *const *)at;
            size_t n = *(const size_t *)((const char *)values + p->count_offset);
            mr_derived_key_u64(kb, n);
            for (size_t k = 0; k < n; k++)
                mr_derived_key_params(kb, p->sub, items + k * p->sub->size);
            break;
        }
        case MR_PARAM_NUMBERS: mr_derived_key_f32s(kb, (const float *)at, p->max_items); break;
        /* a pose animates, it does not derive; an asset parameter names
         * another asset by its place in the job, not by its content: a
         * kind that derives from one feeds that asset's content itself */
        case MR_PARAM_POSE:
        case MR_PARAM_ASSET: break;
        }
    }
}
