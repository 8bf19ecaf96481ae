/*
 * svo_file.c - the `.mrsvo` file and the disk cache of voxelisations
 * (svo_file.h, docs/svo-format.md).
 *
 * One parser serves both directions: the reader keeps what it parses, the
 * writer runs it over the bytes it just produced and discards the result,
 * so a writer can never store a file its reader refuses (a cache entry that
 * never loads would make every job voxelise again, silently). Values are
 * assembled byte by byte, so the host's byte order and the buffer's
 * alignment never matter.
 *
 * The cache's mechanics (envelope checks, key stream, path, hit/miss/
 * replace, atomic store) are util/derived.h's; what is here is the
 * octree's own: the layout, the key's inputs, the fit check and the
 * builder.
 */
#include "kinds/svo/svo_file.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "util/crc32.h"
#include "util/derived.h"
#include "util/le.h"

/* this file's format (the envelope's constants; below) */
#define FORMAT (&mr_svo_file_format)

/* Header fields (byte offsets; docs/svo-format.md) after the envelope's
 * magic, version and header size (util/derived.h); the key and the CRC
 * are the envelope's too. */
enum { H_FLAGS = 16, H_DEPTH = 20, H_ORIGIN = 24, H_SIZE = 36, H_NODES = 40, H_LEAVES = 44,
       H_PALETTE = 48, H_RESERVED = 52, H_PAYLOAD = 56, H_KEY = 64, H_CRC = 96 };
_Static_assert(H_CRC + 4 == MR_SVO_FILE_HEADER_BYTES, "header layout");

const mr_derived_format mr_svo_file_format = {
    .name = "svo file", .ext = "mrsvo", .magic = {'M', 'R', 'S', 'V', 'O', 0, '\r', '\n'},
    .version = MR_SVO_FILE_VERSION, .header_bytes = MR_SVO_FILE_HEADER_BYTES, .key_at = H_KEY,
    .max_bytes = MR_SVO_FILE_MAX_BYTES};

/* Payload bytes per node (first_node, first_leaf: u32; child_mask,
 * leaf_mask: u8), per leaf (2 x u8 normal, u16 attr) and per palette entry
 * (3 x u8 albedo, u8 mesh, 4 x u16 joints, 4 x u8 weights). */
#define NODE_BYTES 10u
#define LEAF_BYTES 4u
#define ATTR_BYTES 16u

/* ======================================================================
 * Parser (the reader, and the writer's read-back check)
 * ====================================================================== */

/* keep is ignored: the read-back builds the octree too (and drops it) */
typedef mr_derived_reader parser;

/* Where the payload's arrays start, for counts n (nodes), l (leaves), pc
 * (palette entries). */
typedef struct layout {
    size_t first_node, first_leaf, child_mask, leaf_mask, leaves, palette, crc, end;
} layout;

static layout layout_of(uint32_t n, uint32_t l, uint32_t pc)
{
    layout o;
    o.first_node = MR_SVO_FILE_HEADER_BYTES;
    o.first_leaf = o.first_node + (size_t)n * 4;
    o.child_mask = o.first_leaf + (size_t)n * 4;
    o.leaf_mask = o.child_mask + n;
    o.leaves = o.leaf_mask + n;
    o.palette = o.leaves + (size_t)l * LEAF_BYTES;
    o.crc = o.palette + (size_t)pc * ATTR_BYTES;
    o.end = o.crc + 4;
    return o;
}

/* MR_ERR_FORMAT "svo file: ..." */
#define bad(p, ...) mr_derived_bad((p)->format, (p)->err, __VA_ARGS__)

/* Header checks, in the documented order: the envelope's (size, magic,
 * version, header_bytes, CRC), then the fields and the file size they
 * imply. */
static int parse_header(parser *p, mr_svo *s, mr_svo_file_meta *meta)
{
    const uint8_t *b = p->buf;
    int rc = mr_derived_header_check(p);
    if (rc < 0)
        return rc;
    uint32_t flags = mr_le_get_u32(b + H_FLAGS);
    if ((flags & ~(uint32_t)(MR_SVO_FILE_VOXELIZED | MR_SVO_FILE_SOLID)) ||
        ((flags & MR_SVO_FILE_SOLID) && !(flags & MR_SVO_FILE_VOXELIZED)))
        return bad(p, "flags %#x at byte offset %d (known: 1 voxelized, 2 solid with 1)", flags,
                   H_FLAGS);
    uint32_t depth = mr_le_get_u32(b + H_DEPTH);
    if (depth < 1 || depth > MR_SVO_MAX_DEPTH)
        return bad(p, "depth %u at byte offset %d (want 1..%u)", depth, H_DEPTH,
                   MR_SVO_MAX_DEPTH);
    float o[3];
    for (int k = 0; k < 3; k++) {
        o[k] = mr_le_get_f32(b + H_ORIGIN + 4 * k);
        if (!isfinite(o[k]))
            return bad(p, "origin.%c at byte offset %d is not finite", "xyz"[k], H_ORIGIN + 4 * k);
    }
    float size = mr_le_get_f32(b + H_SIZE);
    if (!isfinite(size) || !(size > 0.0f))
        return bad(p, "cube size %g at byte offset %d (want finite and > 0)", (double)size,
                   H_SIZE);
    uint32_t n = mr_le_get_u32(b + H_NODES), l = mr_le_get_u32(b + H_LEAVES), pc = mr_le_get_u32(b + H_PALETTE);
    if (pc > MR_SVO_MAX_PALETTE)
        return bad(p, "palette_count %u at byte offset %d (max %u)", pc, H_PALETTE,
                   MR_SVO_MAX_PALETTE);
    if (n == 0 && l > 1)
        return bad(p, "leaf_count %u at byte offset %d without nodes (at most 1: the root)", l,
                   H_LEAVES);
    if (mr_le_get_u32(b + H_RESERVED) != 0)
        return bad(p, "reserved field at byte offset %d is not 0", H_RESERVED);
    uint64_t payload = mr_le_get_u64(b + H_PAYLOAD);
    uint64_t want = (uint64_t)n * NODE_BYTES + (uint64_t)l * LEAF_BYTES + (uint64_t)pc * ATTR_BYTES;
    if (payload != want)
        return bad(p, "payload_bytes %llu at byte offset %d (the counts give %llu)",
                   (unsigned long long)payload, H_PAYLOAD, (unsigned long long)want);
    uint64_t total = MR_SVO_FILE_HEADER_BYTES + payload + 4;
    if (total > MR_SVO_FILE_MAX_BYTES)
        return bad(p, "node/leaf/palette counts at byte offset %d..%d make a %llu-byte file "
                   "(limit %llu)", H_NODES, H_PALETTE + 3, (unsigned long long)total,
                   (unsigned long long)MR_SVO_FILE_MAX_BYTES);
    if (p->size < total)
        return bad(p, "truncated at byte offset %zu (the header's counts need %llu bytes)",
                   p->size, (unsigned long long)total);
    if (p->size > total)
        return bad(p, "%zu unexpected trailing bytes at byte offset %llu", p->size - (size_t)total,
                   (unsigned long long)total);
    s->depth = depth;
    s->origin = mr_v3(o[0], o[1], o[2]);
    s->size = size;
    s->node_count = n;
    s->leaf_count = l;
    s->palette_count = pc;
    if (meta) {
        meta->flags = flags;
        memcpy(meta->key, b + H_KEY, MR_DERIVED_KEY_BYTES);
    }
    return MR_OK;
}

/* The node arrays: decoded into s, checked against mr_svo_build's layout
 * (children consecutive, numbered breadth-first as prefix sums of the
 * children counts: then every node but the root and every leaf has exactly
 * one parent, which comes earlier, so the arrays form one tree) and the
 * depth (no interior node at the finest level). */
static int parse_nodes(parser *p, const layout *o, mr_svo *s)
{
    const uint8_t *b = p->buf;
    const uint32_t n = s->node_count, l = s->leaf_count;
    if (n == 0)
        return MR_OK;
    uint8_t *level = malloc(n);
    if (!level)
        return mr_error_set(p->err, MR_ERR_NOMEM, "svo file: out of memory for %u nodes", n);
    int rc = MR_OK;
    uint64_t next_node = 1, next_leaf = 0; /* node 0, the root, is nobody's child */
    level[0] = 0;
    for (uint32_t i = 0; i < n; i++) {
        const size_t fn_at = o->first_node + (size_t)i * 4, fl_at = o->first_leaf + (size_t)i * 4;
        const size_t cm_at = o->child_mask + i, lm_at = o->leaf_mask + i;
        const unsigned cm = b[cm_at], lm = b[lm_at];
        const uint32_t fn = mr_le_get_u32(b + fn_at), fl = mr_le_get_u32(b + fl_at);
        if (i >= next_node) {
            rc = bad(p, "node %u is no node's child: node_count %u at byte offset %d exceeds the "
                     "%llu nodes of the tree", i, n, H_NODES, (unsigned long long)next_node);
            goto done;
        }
        if (cm == 0) {
            rc = bad(p, "node %u: child_mask 0 at byte offset %zu (a node has children)", i,
                     cm_at);
            goto done;
        }
        if (lm & ~cm) {
            rc = bad(p, "node %u: leaf_mask %#x at byte offset %zu has a leaf bit outside "
                     "child_mask %#x", i, lm, lm_at, cm);
            goto done;
        }
        if (fn != next_node) {
            rc = bad(p, "node %u: first_node %u at byte offset %zu (want %llu: nodes are "
                     "numbered breadth-first)", i, fn, fn_at, (unsigned long long)next_node);
            goto done;
        }
        if (fl != next_leaf) {
            rc = bad(p, "node %u: first_leaf %u at byte offset %zu (want %llu: leaves are "
                     "numbered breadth-first)", i, fl, fl_at, (unsigned long long)next_leaf);
            goto done;
        }
        const unsigned inner = mr_svo_popcount8(cm & ~lm), leafs = mr_svo_popcount8(lm);
        if (inner > 0 && level[i] + 1u >= s->depth) {
            rc = bad(p, "node %u at level %u: child_mask %#x at byte offset %zu / leaf_mask %#x "
                     "at byte offset %zu give it interior children at the finest level %u", i,
                     level[i], cm, cm_at, lm, lm_at, s->depth);
            goto done;
        }
        if (next_node + inner > n) {
            rc = bad(p, "node %u: interior children from first_node %u at byte offset %zu go "
                     "beyond node_count %u", i, fn, fn_at, n);
            goto done;
        }
        if (next_leaf + leafs > l) {
            rc = bad(p, "node %u: leaf children from first_leaf %u at byte offset %zu go beyond "
                     "leaf_count %u", i, fl, fl_at, l);
            goto done;
        }
        for (unsigned k = 0; k < inner; k++)
            level[next_node + k] = (uint8_t)(level[i] + 1u);
        next_node += inner;
        next_leaf += leafs;
        s->first_node[i] = fn;
        s->first_leaf[i] = fl;
        s->child_mask[i] = (uint8_t)cm;
        s->leaf_mask[i] = (uint8_t)lm;
    }
    /* every node was some node's child (checked above); now every leaf */
    if (next_leaf != l)
        rc = bad(p, "leaf_count %u at byte offset %d, but the nodes have %llu leaf children", l,
                 H_LEAVES, (unsigned long long)next_leaf);
done:
    free(level);
    return rc;
}

static int parse_leaves_palette(parser *p, const layout *o, mr_svo *s)
{
    const uint8_t *b = p->buf;
    for (uint32_t i = 0; i < s->leaf_count; i++) {
        const uint8_t *q = b + o->leaves + (size_t)i * LEAF_BYTES;
        uint16_t attr = mr_le_get_u16(q + 2);
        if (attr >= s->palette_count)
            return bad(p, "leaf %u: palette index %u at byte offset %zu (palette_count %u)", i,
                       attr, o->leaves + (size_t)i * LEAF_BYTES + 2, s->palette_count);
        s->leaves[i].normal[0] = q[0];
        s->leaves[i].normal[1] = q[1];
        s->leaves[i].attr = attr;
    }
    for (uint32_t i = 0; i < s->palette_count; i++) {
        const size_t at = o->palette + (size_t)i * ATTR_BYTES;
        const uint8_t *q = b + at;
        mr_svo_attr *a = &s->palette[i];
        memcpy(a->albedo, q, 3);
        a->mesh = q[3];
        unsigned sum = 0;
        for (unsigned k = 0; k < MR_SVO_INFLUENCES; k++) {
            a->joints[k] = mr_le_get_u16(q + 4 + 2 * k);
            a->weights[k] = q[12 + k];
            sum += q[12 + k];
        }
        if (sum != 0 && sum != 255)
            return bad(p, "palette entry %u: weights at byte offset %zu sum to %u (want 255, or "
                       "0 for rigid)", i, at + 12, sum);
    }
    return MR_OK;
}

/* Parses the whole buffer into a new octree (*out) and meta. */
static int parse(parser *p, mr_svo **out, mr_svo_file_meta *meta)
{
    *out = NULL;
    mr_svo *s = calloc(1, sizeof *s);
    if (!s)
        return mr_error_set(p->err, MR_ERR_NOMEM, "svo file: out of memory");
    int rc = parse_header(p, s, meta);
    if (rc < 0)
        goto fail;
    const layout o = layout_of(s->node_count, s->leaf_count, s->palette_count);
    if (!mr_crc32_matches(mr_le_get_u32(p->buf + o.crc), p->buf + o.first_node, o.crc - o.first_node)) {
        rc = bad(p, "payload checksum mismatch at byte offset %zu (bytes %zu..%zu corrupted)",
                 o.crc, o.first_node, o.crc - 1);
        goto fail;
    }
    /* sizes are backed by the bytes present, so garbage cannot make these
     * allocations larger than the file */
    const uint32_t n = s->node_count;
    if (n) {
        s->first_node = malloc((size_t)n * sizeof *s->first_node);
        s->first_leaf = malloc((size_t)n * sizeof *s->first_leaf);
        s->child_mask = malloc(n);
        s->leaf_mask = malloc(n);
    }
    s->leaves = malloc((s->leaf_count ? s->leaf_count : 1) * sizeof *s->leaves);
    s->palette = malloc((s->palette_count ? s->palette_count : 1) * sizeof *s->palette);
    if ((n && (!s->first_node || !s->first_leaf || !s->child_mask || !s->leaf_mask)) ||
        !s->leaves || !s->palette) {
        rc = mr_error_set(p->err, MR_ERR_NOMEM, "svo file: out of memory for %u nodes, %u leaves",
                          n, s->leaf_count);
        goto fail;
    }
    if ((rc = parse_nodes(p, &o, s)) < 0 || (rc = parse_leaves_palette(p, &o, s)) < 0)
        goto fail;
    /* The checks above make the arrays a tree; svo.h's own walk must agree
     * (it is what consumers rely on). */
    if ((rc = mr_svo_collect_keys(s, NULL, NULL, p->err)) < 0) {
        mr_error_prefix(p->err, "svo file: node arrays at byte offset %zu: ", o.first_node);
        rc = MR_ERR_FORMAT;
        if (p->err)
            p->err->code = rc;
        goto fail;
    }
    *out = s;
    return MR_OK;
fail:
    mr_svo_free(s);
    free(s);
    return rc;
}

/* Where a read puts what it parses. */
typedef struct read_target {
    mr_svo **out;
    mr_svo_file_meta *meta; /* may be NULL */
} read_target;

static int parse_into(parser *p, void *target)
{
    const read_target *t = target;
    mr_svo_file_meta m;
    int rc = parse(p, t->out, &m);
    if (rc == MR_OK && t->meta)
        *t->meta = m;
    return rc;
}

int mr_svo_file_read_meta(const uint8_t *buf, size_t size, mr_svo **out, mr_svo_file_meta *meta,
                          mr_error *err)
{
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "svo file read: bad arguments");
    *out = NULL;
    return mr_derived_parse(FORMAT, buf, size, parse_into, &(read_target){out, meta}, err);
}

int mr_svo_file_read(const uint8_t *buf, size_t size, mr_svo **out, mr_error *err)
{
    return mr_svo_file_read_meta(buf, size, out, NULL, err);
}

/* A whole file into an octree (mr_derived_load's parse). */
static int read_parse(void *ctx, const uint8_t *buf, size_t size, mr_error *err)
{
    const read_target *t = ctx;
    return mr_svo_file_read_meta(buf, size, t->out, t->meta, err);
}

int mr_svo_file_read_path(const char *path, mr_svo **out, mr_error *err)
{
    static const mr_derived_ops read_ops = {.parse = read_parse};
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "svo file read: bad arguments");
    *out = NULL;
    return mr_derived_load(path, NULL, FORMAT, &read_ops, &(read_target){out, NULL}, err);
}

/* ======================================================================
 * Writer
 * ====================================================================== */

int mr_svo_file_write_meta(const mr_svo *svo, const mr_svo_file_meta *meta, uint8_t **buf,
                           size_t *size, mr_error *err)
{
    if (buf)
        *buf = NULL;
    if (!svo || !buf || !size)
        return mr_error_set(err, MR_ERR_INVALID, "svo file write: bad arguments");
    const uint32_t n = svo->node_count, l = svo->leaf_count, pc = svo->palette_count;
    if ((n && (!svo->first_node || !svo->first_leaf || !svo->child_mask || !svo->leaf_mask)) ||
        (l && !svo->leaves) || (pc && !svo->palette))
        return mr_error_set(err, MR_ERR_INVALID, "svo file write: octree arrays missing");
    if (pc > MR_SVO_MAX_PALETTE)
        return mr_error_set(err, MR_ERR_INVALID, "svo file write: %u palette entries (max %u)",
                            pc, MR_SVO_MAX_PALETTE);
    uint64_t total = MR_SVO_FILE_HEADER_BYTES + (uint64_t)n * NODE_BYTES +
                     (uint64_t)l * LEAF_BYTES + (uint64_t)pc * ATTR_BYTES + 4;
    mr_svo *back = NULL;
    uint8_t *b = NULL;
    parser *p = NULL; /* over b: its CRC table, then the read-back */
    int rc = mr_derived_buffer(FORMAT, total, &b, &p, err);
    if (rc < 0)
        return rc;
    mr_le_put_u32(b + H_FLAGS, meta ? meta->flags : 0);
    mr_le_put_u32(b + H_DEPTH, svo->depth);
    mr_le_put_f32(b + H_ORIGIN, svo->origin.x);
    mr_le_put_f32(b + H_ORIGIN + 4, svo->origin.y);
    mr_le_put_f32(b + H_ORIGIN + 8, svo->origin.z);
    mr_le_put_f32(b + H_SIZE, svo->size);
    mr_le_put_u32(b + H_NODES, n);
    mr_le_put_u32(b + H_LEAVES, l);
    mr_le_put_u32(b + H_PALETTE, pc);
    mr_le_put_u64(b + H_PAYLOAD, total - MR_SVO_FILE_HEADER_BYTES - 4);
    mr_derived_header_seal(FORMAT, meta ? meta->key : NULL, b);
    const layout o = layout_of(n, l, pc);
    for (uint32_t i = 0; i < n; i++) {
        mr_le_put_u32(b + o.first_node + (size_t)i * 4, svo->first_node[i]);
        mr_le_put_u32(b + o.first_leaf + (size_t)i * 4, svo->first_leaf[i]);
    }
    if (n) {
        memcpy(b + o.child_mask, svo->child_mask, n);
        memcpy(b + o.leaf_mask, svo->leaf_mask, n);
    }
    for (uint32_t i = 0; i < l; i++) {
        uint8_t *q = b + o.leaves + (size_t)i * LEAF_BYTES;
        q[0] = svo->leaves[i].normal[0];
        q[1] = svo->leaves[i].normal[1];
        mr_le_put_u16(q + 2, svo->leaves[i].attr);
    }
    for (uint32_t i = 0; i < pc; i++) {
        uint8_t *q = b + o.palette + (size_t)i * ATTR_BYTES;
        const mr_svo_attr *a = &svo->palette[i];
        memcpy(q, a->albedo, 3);
        q[3] = a->mesh;
        for (unsigned k = 0; k < MR_SVO_INFLUENCES; k++) {
            mr_le_put_u16(q + 4 + 2 * k, a->joints[k]);
            q[12 + k] = a->weights[k];
        }
    }
    mr_le_put_u32(b + o.crc, mr_crc32(b + o.first_node, o.crc - o.first_node));
    mr_svo_file_meta m;
    if ((rc = parse(p, &back, &m)) < 0) {
        rc = mr_derived_readback_failed(FORMAT, rc, err);
        goto done;
    }
    *buf = b;
    *size = (size_t)total;
    b = NULL;
done:
    if (back) {
        mr_svo_free(back);
        free(back);
    }
    free(b);
    free(p);
    return rc;
}

int mr_svo_file_write(const mr_svo *svo, uint8_t **buf, size_t *size, mr_error *err)
{
    return mr_svo_file_write_meta(svo, NULL, buf, size, err);
}

int mr_svo_file_write_path(const mr_svo *svo, const char *path, mr_error *err)
{
    if (!path || !path[0])
        return mr_error_set(err, MR_ERR_INVALID, "svo file write: no path");
    uint8_t *buf = NULL;
    size_t size = 0;
    int rc = mr_svo_file_write(svo, &buf, &size, err);
    if (rc == MR_OK)
        rc = mr_derived_write(FORMAT, path, buf, size, err);
    free(buf);
    return rc;
}

/* ======================================================================
 * The cache (util/derived.h: key, path, load-or-voxelise, store)
 * ====================================================================== */

void mr_svo_cache_key(const mr_asset *asset, const mr_svo_voxelize_params *params,
                      uint8_t key[MR_DERIVED_KEY_BYTES])
{
    memset(key, 0, MR_DERIVED_KEY_BYTES);
    if (!asset || !params)
        return;
    /* what voxelize.c reads: rigid meshes are placed by their nodes */
    const unsigned parts = MR_DERIVED_POSITIONS | MR_DERIVED_NORMALS | MR_DERIVED_INDICES |
                           MR_DERIVED_SKIN;
    mr_derived_key_builder kb;
    mr_derived_key_begin(&kb, "microray svo cache", MR_SVO_FILE_VERSION,
                         MR_SVO_VOXELIZER_REVISION);
    mr_derived_key_nodes(&kb, asset);
    mr_derived_key_u64(&kb, asset->mesh_count);
    for (size_t i = 0; i < asset->mesh_count; i++) {
        const mr_mesh *m = &asset->meshes[i];
        mr_derived_key_u32(&kb, (uint32_t)m->node);
        mr_derived_key_mesh_counts(&kb, m);
        mr_derived_key_u32(&kb, mr_derived_mesh_parts(m, parts)); /* the presence word */
        mr_derived_key_mesh_arrays(&kb, m, parts);
    }
    mr_derived_key_u32(&kb, params->depth);
    mr_derived_key_u32(&kb, (uint32_t)params->mode);
    mr_derived_key_u32(&kb, params->albedo ? 1u : 0u);
    if (params->albedo)
        mr_derived_key_f32s(&kb, params->albedo, asset->mesh_count * 3);
    mr_derived_key_end(&kb, key);
}

static uint32_t mode_flags(mr_svo_voxelize_mode mode)
{
    return MR_SVO_FILE_VOXELIZED | (mode == MR_SVO_VOXELIZE_SOLID ? MR_SVO_FILE_SOLID : 0u);
}

/* What the cache's callbacks see (their ctx): one voxelisation. */
typedef struct voxel_request {
    const mr_asset *asset;                /* NULL: any octree stored under the key fits */
    const mr_svo_voxelize_params *params; /* with asset */
    uint32_t flags;                       /* the header's, for serialise */
    mr_svo *svo;                          /* parse and build leave the result here */
    const mr_svo *store;                  /* serialise writes this */
} voxel_request;

/* Whether a loaded octree answers r's request. */
static bool fits(const mr_svo *s, const mr_svo_file_meta *meta, const voxel_request *r)
{
    const mr_asset *a = r->asset;
    if (!a)
        return true;
    if (s->depth != r->params->depth || meta->flags != mode_flags(r->params->mode))
        return false;
    for (uint32_t i = 0; i < s->palette_count; i++) {
        const mr_svo_attr *e = &s->palette[i];
        if (e->mesh >= a->mesh_count)
            return false;
        for (unsigned k = 0; k < MR_SVO_INFLUENCES; k++)
            if (e->weights[k] && e->joints[k] >= a->meshes[e->mesh].joint_count)
                return false;
    }
    return true;
}

static int cache_parse(void *ctx, const uint8_t *buf, size_t size, mr_error *err)
{
    voxel_request *r = ctx;
    mr_svo *s = NULL;
    mr_svo_file_meta meta;
    int rc = mr_svo_file_read_meta(buf, size, &s, &meta, err);
    if (rc < 0)
        return rc;
    if (!fits(s, &meta, r)) {
        mr_svo_voxelize_free(s);
        return mr_error_set(err, MR_ERR_FORMAT, "depth, mode or palette (header flags at byte "
                            "offset %d) do not fit the request", H_FLAGS);
    }
    r->svo = s;
    return MR_OK;
}

static int cache_serialise(void *ctx, const uint8_t key[MR_DERIVED_KEY_BYTES], uint8_t **buf,
                           size_t *size, mr_error *err)
{
    const voxel_request *r = ctx;
    mr_svo_file_meta meta = {.flags = r->flags};
    memcpy(meta.key, key, MR_DERIVED_KEY_BYTES);
    return mr_svo_file_write_meta(r->store, &meta, buf, size, err);
}

static int cache_build(void *ctx, mr_error *err)
{
    voxel_request *r = ctx;
    int rc = mr_svo_voxelize(r->asset, r->params, &r->svo, err);
    r->store = r->svo;
    return rc;
}

static const mr_derived_ops voxel_ops = {
    .parse = cache_parse, .serialise = cache_serialise, .build = cache_build};

int mr_svo_cache_load(const char *path, const uint8_t key[MR_DERIVED_KEY_BYTES], mr_svo **out,
                      mr_error *err)
{
    if (out)
        *out = NULL;
    if (!path || !key || !out)
        return mr_error_set(err, MR_ERR_INVALID, "svo cache load: bad arguments");
    voxel_request r = {0};
    int rc = mr_derived_load(path, key, FORMAT, &voxel_ops, &r, err);
    *out = r.svo;
    return rc;
}

int mr_svo_cache_store(const char *path, const uint8_t key[MR_DERIVED_KEY_BYTES],
                       const mr_svo *svo, mr_error *err)
{
    if (!path || !path[0] || !key || !svo)
        return mr_error_set(err, MR_ERR_INVALID, "svo cache store: bad arguments");
    voxel_request r = {.flags = 0, .store = svo};
    return mr_derived_store(path, key, FORMAT, &voxel_ops, &r, err);
}

/* Parameters mr_svo_voxelize accepts (its first checks): others go
 * straight to it for its error, never to the cache. */
static bool params_valid(const mr_asset *a, const mr_svo_voxelize_params *p)
{
    if (!a || !p || p->depth < 1 || p->depth > MR_SVO_MAX_DEPTH ||
        (p->mode != MR_SVO_VOXELIZE_SURFACE && p->mode != MR_SVO_VOXELIZE_SOLID) ||
        (p->mode == MR_SVO_VOXELIZE_SOLID && p->depth > MR_SVO_SOLID_MAX_DEPTH) ||
        a->mesh_count > MR_SVO_VOXELIZE_MAX_MESHES || (a->mesh_count && !a->meshes))
        return false;
    for (size_t i = 0; p->albedo && i < a->mesh_count * 3; i++)
        if (!isfinite(p->albedo[i]))
            return false;
    return true;
}

/* leaf_keys of a loaded octree, indexed like its leaves. */
static int restore_leaf_keys(mr_svo *s, mr_error *err)
{
    const size_t n = s->leaf_count ? s->leaf_count : 1;
    mr_svo_key *walk = malloc(n * sizeof *walk), *keys = malloc(n * sizeof *keys);
    uint32_t *index = malloc(n * sizeof *index);
    int rc = MR_OK;
    if (!walk || !keys || !index) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "svo cache: out of memory for %u leaf keys",
                          s->leaf_count);
    } else if ((rc = mr_svo_collect_keys(s, walk, index, err)) == MR_OK) {
        for (uint32_t i = 0; i < s->leaf_count; i++)
            keys[index[i]] = walk[i];
        free(s->leaf_keys);
        s->leaf_keys = keys;
        keys = NULL;
    }
    free(walk);
    free(keys);
    free(index);
    return rc;
}

int mr_svo_voxelize_cached(const mr_asset *asset, const mr_svo_voxelize_params *params,
                           const char *cache_dir, mr_svo **out, bool *from_cache, mr_error *err)
{
    if (from_cache)
        *from_cache = false;
    if (out)
        *out = NULL;
    if (!out || !cache_dir || !cache_dir[0] || !params_valid(asset, params))
        return mr_svo_voxelize(asset, params, out, err);
    uint8_t key[MR_DERIVED_KEY_BYTES];
    mr_svo_cache_key(asset, params, key);
    voxel_request r = {.asset = asset, .params = params, .flags = mode_flags(params->mode)};
    bool hit = false;
    int rc = mr_derived_get(cache_dir, key, FORMAT, &voxel_ops, &r, &hit, err);
    /* with keep_leaf_keys a hit has the keys a fresh voxelisation keeps */
    if (rc == MR_OK && hit && params->keep_leaf_keys && (rc = restore_leaf_keys(r.svo, err)) < 0) {
        mr_svo_voxelize_free(r.svo);
        return rc;
    }
    if (from_cache)
        *from_cache = hit;
    *out = r.svo;
    return rc;
}
