/*
 * asset_blob.c - mr_asset to bytes and back (mr_asset_blob_write/read,
 * microray.h).
 *
 * Layout: a header (magic, the sizes of the structs whose bytes are copied
 * as they are), then the asset's fields in struct order. A string is its
 * length (uint64, UINT64_MAX for NULL) and its bytes; an array is its
 * element count (uint64) and count * element bytes. Scalars are copied as
 * they are: the blob never leaves the build that wrote it.
 */
#include "asset/asset.h"
#include "asset/image.h"

#include <stdbool.h>
#include <stdlib.h>
#include <string.h>

#define BLOB_MAGIC 0x424f4c42736d726dull /* "mrsmBLOB" */
/* The field list's revision, in the header: 2 added the meshes' tangents. */
#define BLOB_VERSION 2u
#define NO_STRING UINT64_MAX

typedef struct writer {
    uint8_t *data;
    size_t size, cap;
    bool failed;
} writer;

static void put(writer *w, const void *p, size_t n)
{
    if (w->failed || n == 0)
        return;
    if (n > w->cap - w->size) {
        size_t cap = w->cap ? w->cap : 4096;
        while (cap - w->size < n) {
            if (cap > SIZE_MAX / 2) {
                w->failed = true;
                return;
            }
            cap *= 2;
        }
        uint8_t *d = realloc(w->data, cap);
        if (!d) {
            w->failed = true;
            return;
        }
        w->data = d;
        w->cap = cap;
    }
    memcpy(w->data + w->size, p, n);
    w->size += n;
}

static void put_u64(writer *w, uint64_t v) { put(w, &v, sizeof v); }

static void put_string(writer *w, const char *s)
{
    if (!s) {
        put_u64(w, NO_STRING);
        return;
    }
    size_t n = strlen(s);
    put_u64(w, n);
    put(w, s, n);
}

/* An array that may be NULL (count 0 then): NULL and empty read back as
 * NULL, which is what the asset's owners expect of an absent array. */
static void put_array(writer *w, const void *p, size_t count, size_t elem)
{
    if (!p)
        count = 0;
    put_u64(w, count);
    put(w, p, count * elem);
}

/* Keys one by one, padding zeroed: the same asset always gives the same
 * bytes. */
static void put_vec3_keys(writer *w, const mr_vec3_key *k, size_t count)
{
    if (!k)
        count = 0;
    put_u64(w, count);
    for (size_t i = 0; i < count; i++) {
        mr_vec3_key clean;
        memset(&clean, 0, sizeof clean);
        clean.time = k[i].time;
        clean.value = k[i].value;
        put(w, &clean, sizeof clean);
    }
}

/* The struct sizes the layout depends on: a blob from another build (or a
 * torn one) is refused at the header, and so is one of another field list
 * (BLOB_VERSION). */
static void header(uint64_t h[8])
{
    h[0] = BLOB_MAGIC;
    h[1] = sizeof(mr_asset);
    h[2] = sizeof(mr_node);
    h[3] = sizeof(mr_mesh);
    h[4] = sizeof(mr_clip);
    h[5] = sizeof(mr_channel);
    h[6] = sizeof(mr_camera_info);
    h[7] = sizeof(mr_mat4) | (uint64_t)sizeof(mr_vec3_key) << 16 | (uint64_t)sizeof(mr_quat_key) << 32 |
           (uint64_t)BLOB_VERSION << 48;
}

int mr_asset_blob_write(const mr_asset *a, uint8_t **out, size_t *size, mr_error *err)
{
    *out = NULL;
    *size = 0;
    writer w = {0};
    uint64_t h[8];
    header(h);
    put(&w, h, sizeof h);
    put_string(&w, a->path);
    put_u64(&w, a->triangle_count);
    put_u64(&w, a->node_count);
    for (size_t i = 0; i < a->node_count; i++) {
        const mr_node *n = &a->nodes[i];
        put_string(&w, n->name);
        put(&w, &n->parent, sizeof n->parent);
        put(&w, &n->local, sizeof n->local);
    }
    put_u64(&w, a->mesh_count);
    for (size_t i = 0; i < a->mesh_count; i++) {
        const mr_mesh *m = &a->meshes[i];
        size_t nv = m->vertex_count, nt = m->triangle_count;
        put_string(&w, m->name);
        put(&w, &m->node, sizeof m->node);
        put(&w, &m->vertex_count, sizeof m->vertex_count);
        put(&w, &m->triangle_count, sizeof m->triangle_count);
        put(&w, &m->joint_count, sizeof m->joint_count);
        put_array(&w, m->positions, nv * 3, sizeof(float));
        put_array(&w, m->normals, nv * 3, sizeof(float));
        put_array(&w, m->uvs, nv * 2, sizeof(float));
        put_array(&w, m->tangents, nv * 4, sizeof(float));
        put_array(&w, m->indices, nt * 3, sizeof(uint32_t));
        put_array(&w, m->joint_nodes, m->joint_count, sizeof(int));
        put_array(&w, m->inverse_bind, m->joint_count, sizeof(mr_mat4));
        put_array(&w, m->joints, nv * MR_MAX_INFLUENCES, sizeof(uint16_t));
        put_array(&w, m->weights, nv * MR_MAX_INFLUENCES, sizeof(float));
    }
    put_u64(&w, a->clip_count);
    for (size_t i = 0; i < a->clip_count; i++) {
        const mr_clip *c = &a->clips[i];
        put_string(&w, c->name);
        put(&w, &c->duration, sizeof c->duration);
        put_u64(&w, c->channel_count);
        for (size_t k = 0; k < c->channel_count; k++) {
            const mr_channel *ch = &c->channels[k];
            put(&w, &ch->node, sizeof ch->node);
            put_vec3_keys(&w, ch->positions, ch->position_count);
            put_array(&w, ch->rotations, ch->rotation_count, sizeof(mr_quat_key));
            put_vec3_keys(&w, ch->scales, ch->scale_count);
        }
    }
    put_u64(&w, a->camera_count);
    for (size_t i = 0; i < a->camera_count; i++) {
        const mr_camera_info *src = &a->cameras[i];
        mr_camera_info c;
        memset(&c, 0, sizeof c); /* padding zeroed; the name travels as a string */
        c.node = src->node;
        c.position = src->position;
        c.look_at = src->look_at;
        c.up = src->up;
        c.yfov = src->yfov;
        c.aspect = src->aspect;
        put_string(&w, src->name);
        put(&w, &c, sizeof c);
    }
    /* an image asset: its four header words, then its samples */
    const mr_image *img = a->image;
    put_u64(&w, img != NULL);
    if (img) {
        uint32_t hdr[4] = {img->width, img->height, img->file_channels,
                           (uint32_t)img->type | (uint32_t)img->format << 8};
        put(&w, hdr, sizeof hdr);
        put_array(&w, img->samples, (size_t)img->width * img->height, (size_t)img->type);
    }
    if (w.failed) {
        free(w.data);
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory packing the asset (%zu bytes so far)",
                            w.size);
    }
    *out = w.data;
    *size = w.size;
    return MR_OK;
}

/* ---- reading ---------------------------------------------------------------- */

typedef struct reader {
    const uint8_t *p;
    size_t left;
    bool bad;    /* short or inconsistent */
    bool nomem;
} reader;

static bool take(reader *r, void *dst, size_t n)
{
    if (r->bad || n > r->left) {
        r->bad = true;
        return false;
    }
    memcpy(dst, r->p, n);
    r->p += n;
    r->left -= n;
    return true;
}

static uint64_t take_u64(reader *r)
{
    uint64_t v = 0;
    take(r, &v, sizeof v);
    return v;
}

static char *take_string(reader *r)
{
    uint64_t n = take_u64(r);
    if (r->bad || n == NO_STRING)
        return NULL;
    if (n > r->left) {
        r->bad = true;
        return NULL;
    }
    char *s = malloc((size_t)n + 1);
    if (!s) {
        r->nomem = r->bad = true;
        return NULL;
    }
    take(r, s, (size_t)n);
    s[n] = '\0';
    return s;
}

/* An array of count elements; expect (when not SIZE_MAX) is the count the
 * asset's own fields imply (0 stays NULL). */
static void *take_array(reader *r, size_t elem, size_t expect, size_t *count)
{
    uint64_t n = take_u64(r);
    if (count)
        *count = (size_t)n;
    if (r->bad || n == 0)
        return NULL;
    if ((expect != SIZE_MAX && n != expect) || n > r->left / elem) {
        r->bad = true;
        return NULL;
    }
    void *a = malloc((size_t)n * elem);
    if (!a) {
        r->nomem = r->bad = true;
        return NULL;
    }
    take(r, a, (size_t)n * elem);
    return a;
}

/* A count of structs that will be allocated: each takes at least min_bytes
 * of blob, so a count beyond what is left is refused before calloc. */
static size_t take_count(reader *r, size_t min_bytes)
{
    uint64_t n = take_u64(r);
    if (!r->bad && n > r->left / min_bytes)
        r->bad = true;
    return r->bad ? 0 : (size_t)n;
}

static void *take_structs(reader *r, size_t n, size_t elem)
{
    if (r->bad || n == 0)
        return NULL;
    void *a = calloc(n, elem);
    if (!a)
        r->nomem = r->bad = true;
    return a;
}

int mr_asset_blob_read(const uint8_t *data, size_t size, mr_asset **out, mr_error *err)
{
    *out = NULL;
    reader r = {.p = data, .left = size};
    uint64_t h[8], want[8];
    header(want);
    if (!take(&r, h, sizeof h) || memcmp(h, want, sizeof h) != 0)
        return mr_error_set(err, MR_ERR_FORMAT, "not an asset blob of this build");
    mr_asset *a = calloc(1, sizeof *a);
    if (!a)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    a->path = take_string(&r);
    a->triangle_count = (size_t)take_u64(&r);
    /* Counts are set only once their arrays exist, so mr_asset_free of a
     * half-read asset frees exactly what was allocated. */
    size_t n = take_count(&r, 8 + sizeof(int) + sizeof(mr_mat4));
    a->nodes = take_structs(&r, n, sizeof *a->nodes);
    for (size_t i = 0; i < n && !r.bad; i++, a->node_count++) {
        mr_node *nd = &a->nodes[i];
        nd->name = take_string(&r);
        if (!nd->name && !r.bad)
            nd->name = calloc(1, 1); /* never NULL (asset.h) */
        take(&r, &nd->parent, sizeof nd->parent);
        take(&r, &nd->local, sizeof nd->local);
    }
    n = take_count(&r, 8 + 8 * 8);
    a->meshes = take_structs(&r, n, sizeof *a->meshes);
    for (size_t i = 0; i < n && !r.bad; i++, a->mesh_count++) {
        mr_mesh *m = &a->meshes[i];
        m->name = take_string(&r);
        take(&r, &m->node, sizeof m->node);
        take(&r, &m->vertex_count, sizeof m->vertex_count);
        take(&r, &m->triangle_count, sizeof m->triangle_count);
        take(&r, &m->joint_count, sizeof m->joint_count);
        size_t nv = m->vertex_count, nt = m->triangle_count, any = SIZE_MAX;
        size_t uv_count = 0, tangent_count = 0, joint_slots = 0, weight_slots = 0;
        m->positions = take_array(&r, sizeof(float), nv * 3, NULL);
        m->normals = take_array(&r, sizeof(float), nv * 3, NULL);
        m->uvs = take_array(&r, sizeof(float), any, &uv_count);
        m->tangents = take_array(&r, sizeof(float), any, &tangent_count);
        m->indices = take_array(&r, sizeof(uint32_t), nt * 3, NULL);
        m->joint_nodes = take_array(&r, sizeof(int), m->joint_count, NULL);
        m->inverse_bind = take_array(&r, sizeof(mr_mat4), m->joint_count, NULL);
        m->joints = take_array(&r, sizeof(uint16_t), any, &joint_slots);
        m->weights = take_array(&r, sizeof(float), any, &weight_slots);
        if ((uv_count && uv_count != nv * 2) || (tangent_count && (tangent_count != nv * 4 || !uv_count)) ||
            (joint_slots && joint_slots != nv * MR_MAX_INFLUENCES) || joint_slots != weight_slots)
            r.bad = true;
    }
    n = take_count(&r, 8 + sizeof(double) + 8);
    a->clips = take_structs(&r, n, sizeof *a->clips);
    for (size_t i = 0; i < n && !r.bad; i++, a->clip_count++) {
        mr_clip *c = &a->clips[i];
        c->name = take_string(&r);
        take(&r, &c->duration, sizeof c->duration);
        size_t nc = take_count(&r, sizeof(int) + 3 * 8);
        c->channels = take_structs(&r, nc, sizeof *c->channels);
        for (size_t k = 0; k < nc && !r.bad; k++, c->channel_count++) {
            mr_channel *ch = &c->channels[k];
            take(&r, &ch->node, sizeof ch->node);
            ch->positions = take_array(&r, sizeof(mr_vec3_key), SIZE_MAX, &ch->position_count);
            ch->rotations = take_array(&r, sizeof(mr_quat_key), SIZE_MAX, &ch->rotation_count);
            ch->scales = take_array(&r, sizeof(mr_vec3_key), SIZE_MAX, &ch->scale_count);
        }
    }
    n = take_count(&r, 8 + sizeof(mr_camera_info));
    a->cameras = take_structs(&r, n, sizeof *a->cameras);
    for (size_t i = 0; i < n && !r.bad; i++, a->camera_count++) {
        char *name = take_string(&r);
        take(&r, &a->cameras[i], sizeof a->cameras[i]);
        a->cameras[i].name = name;
    }
    uint64_t has_image = take_u64(&r);
    if (has_image > 1)
        r.bad = true;
    if (has_image == 1 && !r.bad) {
        uint32_t hdr[4];
        take(&r, hdr, sizeof hdr);
        mr_sample_type type = (mr_sample_type)(hdr[3] & 0xff);
        mr_image_format format = (mr_image_format)(hdr[3] >> 8);
        uint64_t px = (uint64_t)hdr[0] * hdr[1];
        if (r.bad || (type != MR_SAMPLE_U8 && type != MR_SAMPLE_U16 && type != MR_SAMPLE_F32) ||
            format > MR_IMAGE_EXR || hdr[0] == 0 || hdr[1] == 0 || hdr[0] > MR_MAX_IMAGE_SIDE ||
            hdr[1] > MR_MAX_IMAGE_SIDE || px > MR_MAX_IMAGE_PIXELS) {
            r.bad = true;
        } else if (!(a->image = calloc(1, sizeof *a->image))) {
            r.nomem = r.bad = true;
        } else {
            a->image->width = hdr[0];
            a->image->height = hdr[1];
            a->image->file_channels = hdr[2];
            a->image->type = type;
            a->image->format = format;
            a->image->samples = take_array(&r, (size_t)type, (size_t)px, NULL);
            if (!a->image->samples)
                r.bad = true;
        }
    }
    if (!r.bad && r.left != 0)
        r.bad = true;
    if (r.bad) {
        mr_asset_free(a);
        if (r.nomem)
            return mr_error_set(err, MR_ERR_NOMEM, "out of memory unpacking an asset of %zu bytes",
                                size);
        return mr_error_set(err, MR_ERR_FORMAT, "damaged asset blob (%zu bytes)", size);
    }
    *out = a;
    return MR_OK;
}
