/*
 * asset.c - model import through assimp's C API into the plain arrays of
 * asset.h, plus in-memory meshes for tests and generated fixtures.
 *
 * Why copy everything: the renderer, the scene cache and the skinning code
 * must not depend on assimp's object model or on its lifetime, and every
 * index that later code trusts (face indices, joint indices, node parents) is
 * validated here once, so a broken file fails with MR_ERR_FORMAT instead of
 * crashing a worker.
 *
 * assimp details this file relies on (assimp 5.2.5, Debian 12):
 *  - aiGetErrorString() is global state inside assimp; we copy it into the
 *    caller's mr_error right after the failing aiImportFile call.
 *  - aiQuaternion is laid out (w, x, y, z); mr_quat is (x, y, z, w). Fields
 *    are copied by name, never by memory order.
 *  - aiAnimation times are in ticks; mTicksPerSecond == 0 means "not given in
 *    the file". We then use 25 ticks/s, the rate assimp's own importers (SMD,
 *    MD5, ...) write when a format has none.
 *  - aiCamera::mHorizontalFOV is documented as HALF the horizontal angle, but
 *    the 5.2.5 importers disagree: FBX, COLLADA and ASE store the full
 *    horizontal angle, the Blender importer stores the half angle, and the
 *    glTF 1/2 importers store yfov * aspectRatio (measured: yfov 0.7 with
 *    aspectRatio 2 imports as 1.4). camera_yfov() inverts each of these.
 *    The glTF importers also copy the node's translation into mPosition,
 *    which import_cameras undoes.
 */
#include "asset/asset.h"

#include <assimp/cfileio.h>
#include <assimp/cimport.h>
#include <assimp/postprocess.h>
#include <assimp/scene.h>
#include <ctype.h>
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>
#include <sys/stat.h>
#include <unistd.h>

#include "asset/image.h"
#include "util/dup.h"
#include "util/file_io.h"

/* ---- the files assimp may open ------------------------------------------
 * A model may name other files: glTF buffers and images, an OBJ's .mtl,
 * textures. assimp opens whatever it is told, so a file uploaded with a
 * buffer "uri": "../../../../etc/passwd" (or "../microray.sqlite") would
 * read outside the asset roots and leak bytes through error messages. The
 * import therefore goes through this file system: the model itself and files
 * inside the model's own folder (its bundle, after resolving "..", symlinks
 * and absolute names) open; anything else, and anything but a regular file
 * (a FIFO would block), is refused as missing, and the first refused name is
 * kept for the error message. Only reading is offered. */
typedef struct confined_fs {
    char model[PATH_MAX]; /* realpath of the model file */
    char dir[PATH_MAX];   /* its folder, with a trailing '/' */
    char refused[256];    /* the first name refused, as assimp asked for it */
} confined_fs;

static size_t cfs_read(struct aiFile *f, char *buf, size_t size, size_t count)
{
    return size && count ? fread(buf, size, count, (FILE *)f->UserData) : 0;
}

static size_t cfs_write(struct aiFile *f, const char *buf, size_t size, size_t count)
{
    (void)f, (void)buf, (void)size, (void)count;
    return 0;
}

static size_t cfs_tell(struct aiFile *f)
{
    long at = ftell((FILE *)f->UserData);
    return at < 0 ? 0 : (size_t)at;
}

static size_t cfs_size(struct aiFile *f)
{
    struct stat st;
    return fstat(fileno((FILE *)f->UserData), &st) == 0 ? (size_t)st.st_size : 0;
}

static enum aiReturn cfs_seek(struct aiFile *f, size_t offset, enum aiOrigin origin)
{
    int whence = origin == aiOrigin_SET ? SEEK_SET : origin == aiOrigin_CUR ? SEEK_CUR : SEEK_END;
    if (offset > (size_t)LONG_MAX)
        return aiReturn_FAILURE;
    return fseek((FILE *)f->UserData, (long)offset, whence) == 0 ? aiReturn_SUCCESS
                                                                : aiReturn_FAILURE;
}

static void cfs_flush(struct aiFile *f) { (void)f; }

static struct aiFile *cfs_open(struct aiFileIO *io, const char *name, const char *mode)
{
    confined_fs *fs = (confined_fs *)io->UserData;
    char real[PATH_MAX];
    if (!name || !mode || strchr(mode, 'w') || strchr(mode, 'a') || strchr(mode, '+'))
        return NULL;
    if (!realpath(name, real))
        return NULL; /* missing: assimp says so itself */
    if (strcmp(real, fs->model) != 0 && strncmp(real, fs->dir, strlen(fs->dir)) != 0) {
        if (!fs->refused[0])
            snprintf(fs->refused, sizeof fs->refused, "%s", name);
        return NULL;
    }
    int fd = open(real, O_RDONLY | O_NONBLOCK | O_CLOEXEC);
    struct stat st;
    if (fd < 0)
        return NULL;
    if (fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
        close(fd);
        if (!fs->refused[0])
            snprintf(fs->refused, sizeof fs->refused, "%s", name);
        return NULL;
    }
    FILE *fp = fdopen(fd, "rb");
    struct aiFile *f = fp ? calloc(1, sizeof *f) : NULL;
    if (!f) {
        if (fp)
            fclose(fp);
        else
            close(fd);
        return NULL;
    }
    *f = (struct aiFile){.ReadProc = cfs_read, .WriteProc = cfs_write, .TellProc = cfs_tell,
                         .FileSizeProc = cfs_size, .SeekProc = cfs_seek, .FlushProc = cfs_flush,
                         .UserData = (aiUserData)fp};
    return f;
}

static void cfs_close(struct aiFileIO *io, struct aiFile *f)
{
    (void)io;
    if (!f)
        return;
    fclose((FILE *)f->UserData);
    free(f);
}

/* Sets fs up for the model at path; false when it cannot be resolved. */
static bool cfs_init(confined_fs *fs, const char *path)
{
    memset(fs, 0, sizeof *fs);
    if (!realpath(path, fs->model))
        return false;
    const char *slash = strrchr(fs->model, '/');
    size_t n = slash ? (size_t)(slash - fs->model) + 1 : 0;
    if (n == 0 || n >= sizeof fs->dir)
        return false;
    memcpy(fs->dir, fs->model, n);
    fs->dir[n] = '\0';
    return true;
}

/* Import runs in two phases. aiImportFile does the parsing with only
 * aiProcess_ValidateDataStructure (a failure there comes back the safe way,
 * NULL plus aiGetErrorString). We then refuse non-finite positions, and only
 * then aiApplyPostProcessing runs the steps below. The order matters:
 * aiProcess_JoinIdenticalVertices silently merges a NaN vertex into another
 * one (measured: a triangle (0,0,0) (1,NaN,0) (0,1,0) comes out with 2
 * vertices), so after it a broken file can no longer be told apart.
 * These steps do not fail on a scene that passed validation, which matters
 * because assimp 5.2.5 mishandles a failing step in aiApplyPostProcessing
 * (it releases a scene the failing step already deleted).
 *
 * Steps deliberately left out:
 *  - aiProcess_LimitBoneWeights keeps 4 influences; we keep MR_MAX_INFLUENCES.
 *  - aiProcess_GenSmoothNormals: we compute area-weighted normals ourselves
 *    only where the file has none (or a zero / non-finite one), independent
 *    of assimp's smoothing-angle heuristics.
 *  - aiProcess_FindInvalidData: it silently DELETES a mesh that has a NaN or
 *    infinite position (measured: an OBJ with one good and one NaN object
 *    imports as the good object alone), losing data without an error. We
 *    refuse such files naming mesh and vertex instead. Its other duties are
 *    covered here: unusable normals are recomputed per vertex, non-finite
 *    UVs become 0, and redundant animation keys are harmless to the sampler.
 */
#define MR_ASSIMP_IMPORT_FLAGS aiProcess_ValidateDataStructure
#define MR_ASSIMP_POST_FLAGS                                                                  \
    (aiProcess_Triangulate | aiProcess_JoinIdenticalVertices | aiProcess_SortByPType)

#define MR_DEFAULT_TICKS_PER_SECOND 25.0

/* ------------------------------------------------------------------------ */
/* small helpers                                                              */

/* aiString carries an explicit length (< MAXLEN) and is NUL-terminated;
 * trust neither blindly. */
static char *dup_aistring(const struct aiString *s)
{
    size_t n = s->length;
    if (n >= MAXLEN)
        n = MAXLEN - 1;
    return mr_memdup_str(s->data, strnlen(s->data, n));
}

static mr_mat4 mat_from_ai(const struct aiMatrix4x4 *a)
{
    /* Same row-major element order on both sides (see mr_math.h). */
    mr_mat4 m = {{(float)a->a1, (float)a->a2, (float)a->a3, (float)a->a4,
                  (float)a->b1, (float)a->b2, (float)a->b3, (float)a->b4,
                  (float)a->c1, (float)a->c2, (float)a->c3, (float)a->c4,
                  (float)a->d1, (float)a->d2, (float)a->d3, (float)a->d4}};
    return m;
}

static bool vec_finite(mr_vec3 v) { return isfinite(v.x) && isfinite(v.y) && isfinite(v.z); }

/* Label for messages: the mesh's name, or its index when it has none. */
static const char *mesh_label(const char *name, size_t index, char buf[32])
{
    if (name && name[0])
        return name;
    snprintf(buf, 32, "#%zu", index);
    return buf;
}

/* ------------------------------------------------------------------------ */
/* skin influences                                                            */

typedef struct infl {
    uint32_t joint;
    uint32_t order; /* position in the input: the tie-breaker that keeps this deterministic */
    double w;
} infl;

static int infl_by_joint(const void *pa, const void *pb)
{
    const infl *a = pa, *b = pb;
    if (a->joint != b->joint)
        return a->joint < b->joint ? -1 : 1;
    return a->order < b->order ? -1 : (a->order > b->order);
}

static int infl_by_weight(const void *pa, const void *pb)
{
    const infl *a = pa, *b = pb;
    if (a->w != b->w)
        return a->w > b->w ? -1 : 1;
    return a->order < b->order ? -1 : (a->order > b->order);
}

int mr_influences_normalize(const uint32_t *joints, const float *weights, size_t count,
                            uint16_t out_joints[MR_MAX_INFLUENCES],
                            float out_weights[MR_MAX_INFLUENCES])
{
    for (int k = 0; k < MR_MAX_INFLUENCES; k++) {
        out_joints[k] = 0;
        out_weights[k] = 0.0f;
    }
    if (count == 0 || !joints || !weights)
        return 0;
    /* Small counts (the normal case) stay on the stack. */
    infl local[64];
    infl *v = local;
    if (count > 64) {
        if (count > SIZE_MAX / sizeof(infl))
            return MR_ERR_NOMEM;
        v = malloc(count * sizeof(infl));
        if (!v)
            return MR_ERR_NOMEM;
    }
    size_t n = 0;
    for (size_t i = 0; i < count; i++) {
        float w = weights[i];
        if (!(w > 0.0f) || !isfinite(w) || joints[i] > MR_MAX_ASSET_JOINTS)
            continue;
        v[n++] = (infl){joints[i], (uint32_t)(i > UINT32_MAX ? UINT32_MAX : i), w};
    }
    /* Sum influences that name the same joint (a file may list a bone twice). */
    qsort(v, n, sizeof *v, infl_by_joint);
    size_t m = 0;
    for (size_t i = 0; i < n; i++) {
        if (m > 0 && v[m - 1].joint == v[i].joint)
            v[m - 1].w += v[i].w;
        else
            v[m++] = v[i];
    }
    qsort(v, m, sizeof *v, infl_by_weight);
    size_t keep = m < MR_MAX_INFLUENCES ? m : MR_MAX_INFLUENCES;
    double sum = 0.0;
    for (size_t k = 0; k < keep; k++)
        sum += v[k].w;
    int kept = 0;
    if (sum > 0.0 && isfinite(sum)) {
        for (size_t k = 0; k < keep; k++) {
            out_joints[k] = (uint16_t)v[k].joint;
            out_weights[k] = (float)(v[k].w / sum);
        }
        kept = (int)keep;
    }
    if (v != local)
        free(v);
    return kept;
}

/* ------------------------------------------------------------------------ */
/* freeing and memory                                                         */

void mr_mesh_release(mr_mesh *m)
{
    if (!m)
        return;
    free(m->name);
    free(m->positions);
    free(m->normals);
    free(m->uvs);
    free(m->tangents);
    free(m->indices);
    free(m->joint_nodes);
    free(m->inverse_bind);
    free(m->joints);
    free(m->weights);
    memset(m, 0, sizeof *m);
}

static void clip_free(mr_clip *c)
{
    free(c->name);
    for (size_t i = 0; i < c->channel_count; i++) {
        free(c->channels[i].positions);
        free(c->channels[i].rotations);
        free(c->channels[i].scales);
    }
    free(c->channels);
}

static int copy_clip(const mr_clip *src, mr_clip *dst)
{
    dst->duration = src->duration;
    if (src->name && !(dst->name = strdup(src->name)))
        return MR_ERR_NOMEM;
    if (src->channel_count == 0)
        return MR_OK;
    dst->channels = calloc(src->channel_count, sizeof *dst->channels);
    if (!dst->channels)
        return MR_ERR_NOMEM;
    dst->channel_count = src->channel_count;
    for (size_t i = 0; i < src->channel_count; i++) {
        const mr_channel *a = &src->channels[i];
        mr_channel *b = &dst->channels[i];
        b->node = a->node;
        b->position_count = a->position_count;
        b->rotation_count = a->rotation_count;
        b->scale_count = a->scale_count;
        b->positions = mr_memdup(a->positions, a->position_count * sizeof *a->positions);
        b->rotations = mr_memdup(a->rotations, a->rotation_count * sizeof *a->rotations);
        b->scales = mr_memdup(a->scales, a->scale_count * sizeof *a->scales);
        if ((a->position_count && !b->positions) || (a->rotation_count && !b->rotations) ||
            (a->scale_count && !b->scales))
            return MR_ERR_NOMEM;
    }
    return MR_OK;
}

int mr_asset_copy_shell(const mr_asset *in, size_t extra_nodes, mr_asset **out)
{
    mr_asset *a = calloc(1, sizeof *a);
    *out = a;
    if (!a)
        return MR_ERR_NOMEM;
    /* Counts are set as soon as an array exists (zeroed), so mr_asset_free
     * can release a partial copy. */
    if (in->path && !(a->path = strdup(in->path)))
        return MR_ERR_NOMEM;
    if (in->node_count + extra_nodes > 0 &&
        !(a->nodes = calloc(in->node_count + extra_nodes, sizeof *a->nodes)))
        return MR_ERR_NOMEM;
    for (size_t i = 0; i < in->node_count; i++) {
        a->nodes[i] = in->nodes[i];
        a->nodes[i].name = NULL;
        a->node_count = i + 1;
        /* mr_node.name is never NULL. */
        if (!(a->nodes[i].name = strdup(in->nodes[i].name ? in->nodes[i].name : "")))
            return MR_ERR_NOMEM;
    }
    if (in->clip_count) {
        if (!(a->clips = calloc(in->clip_count, sizeof *a->clips)))
            return MR_ERR_NOMEM;
        a->clip_count = in->clip_count;
        for (size_t i = 0; i < in->clip_count; i++)
            if (copy_clip(&in->clips[i], &a->clips[i]) < 0)
                return MR_ERR_NOMEM;
    }
    if (in->camera_count) {
        if (!(a->cameras = calloc(in->camera_count, sizeof *a->cameras)))
            return MR_ERR_NOMEM;
        a->camera_count = in->camera_count;
        for (size_t i = 0; i < in->camera_count; i++) {
            a->cameras[i] = in->cameras[i];
            a->cameras[i].name = NULL;
            if (in->cameras[i].name && !(a->cameras[i].name = strdup(in->cameras[i].name)))
                return MR_ERR_NOMEM;
        }
    }
    if (in->mesh_count) {
        if (!(a->meshes = calloc(in->mesh_count, sizeof *a->meshes)))
            return MR_ERR_NOMEM;
        a->mesh_count = in->mesh_count;
    }
    a->triangle_count = in->triangle_count;
    return MR_OK;
}

void mr_asset_free(mr_asset *asset)
{
    if (!asset)
        return;
    free(asset->path);
    for (size_t i = 0; i < asset->node_count; i++)
        free(asset->nodes[i].name);
    free(asset->nodes);
    for (size_t i = 0; i < asset->mesh_count; i++)
        mr_mesh_release(&asset->meshes[i]);
    free(asset->meshes);
    for (size_t i = 0; i < asset->clip_count; i++)
        clip_free(&asset->clips[i]);
    free(asset->clips);
    for (size_t i = 0; i < asset->camera_count; i++)
        free(asset->cameras[i].name);
    free(asset->cameras);
    mr_image_free(asset->image);
    free(asset);
}

bool mr_asset_is_image(const mr_asset *asset) { return asset && asset->image; }

bool mr_asset_image_size(const mr_asset *asset, uint32_t *width, uint32_t *height)
{
    if (!asset || !asset->image)
        return false;
    *width = asset->image->width;
    *height = asset->image->height;
    return true;
}

size_t mr_asset_triangle_count(const mr_asset *asset)
{
    return asset ? asset->triangle_count : 0;
}

size_t mr_asset_clip_count(const mr_asset *asset)
{
    return asset ? asset->clip_count : 0;
}

double mr_asset_clip_duration(const mr_asset *asset, size_t clip)
{
    return asset && clip < asset->clip_count ? asset->clips[clip].duration : 0.0;
}

size_t mr_asset_memory(const mr_asset *asset)
{
    if (!asset)
        return 0;
    size_t b = sizeof *asset;
    if (asset->path)
        b += strlen(asset->path) + 1;
    b += asset->node_count * sizeof(mr_node);
    for (size_t i = 0; i < asset->node_count; i++)
        b += strlen(asset->nodes[i].name) + 1;
    b += asset->mesh_count * sizeof(mr_mesh);
    for (size_t i = 0; i < asset->mesh_count; i++) {
        const mr_mesh *m = &asset->meshes[i];
        size_t nv = m->vertex_count;
        if (m->name)
            b += strlen(m->name) + 1;
        b += nv * 3 * sizeof(float) * 2; /* positions, normals */
        if (m->uvs)
            b += nv * 2 * sizeof(float);
        if (m->tangents)
            b += nv * 4 * sizeof(float);
        b += (size_t)m->triangle_count * 3 * sizeof(uint32_t);
        b += m->joint_count * (sizeof(int) + sizeof(mr_mat4));
        if (m->joints)
            b += nv * MR_MAX_INFLUENCES * (sizeof(uint16_t) + sizeof(float));
    }
    b += asset->clip_count * sizeof(mr_clip);
    for (size_t i = 0; i < asset->clip_count; i++) {
        const mr_clip *c = &asset->clips[i];
        if (c->name)
            b += strlen(c->name) + 1;
        b += c->channel_count * sizeof(mr_channel);
        for (size_t k = 0; k < c->channel_count; k++) {
            const mr_channel *ch = &c->channels[k];
            b += (ch->position_count + ch->scale_count) * sizeof(mr_vec3_key);
            b += ch->rotation_count * sizeof(mr_quat_key);
        }
    }
    b += asset->camera_count * sizeof(mr_camera_info);
    for (size_t i = 0; i < asset->camera_count; i++)
        if (asset->cameras[i].name)
            b += strlen(asset->cameras[i].name) + 1;
    return b + mr_image_bytes(asset->image);
}

/* ------------------------------------------------------------------------ */
/* lookups                                                                    */

int mr_asset_find_node(const mr_asset *asset, const char *name)
{
    if (!asset || !name)
        return -1;
    for (size_t i = 0; i < asset->node_count; i++)
        if (strcmp(asset->nodes[i].name, name) == 0)
            return (int)i;
    return -1;
}

int mr_asset_find_clip(const mr_asset *asset, const char *name)
{
    if (!asset || !name)
        return -1;
    for (size_t i = 0; i < asset->clip_count; i++)
        if (asset->clips[i].name && strcmp(asset->clips[i].name, name) == 0)
            return (int)i;
    return -1;
}

int mr_asset_find_camera(const mr_asset *asset, const char *name)
{
    if (!asset || !name)
        return -1;
    for (size_t i = 0; i < asset->camera_count; i++)
        if (asset->cameras[i].name && strcmp(asset->cameras[i].name, name) == 0)
            return (int)i;
    return -1;
}

/* Name -> node lookups during import (bones, channels, cameras) go through
 * node indices sorted by (name, index), so a file with many bones and nodes
 * stays O(n log n) and duplicate names resolve to the first node, exactly as
 * mr_asset_find_node does. */
typedef struct name_index {
    const mr_node *nodes;
    int *order;
    size_t count;
} name_index;

/* qsort has no context argument in C11; sort (name, index) pairs instead. */
typedef struct name_ref {
    const char *name;
    int index;
} name_ref;

static int name_ref_cmp(const void *pa, const void *pb)
{
    const name_ref *a = pa, *b = pb;
    int c = strcmp(a->name, b->name);
    if (c)
        return c;
    return (a->index > b->index) - (a->index < b->index);
}

static int name_index_build(name_index *ix, const mr_node *nodes, size_t count)
{
    ix->nodes = nodes;
    ix->count = count;
    ix->order = NULL;
    if (count == 0)
        return MR_OK;
    name_ref *refs = malloc(count * sizeof *refs);
    ix->order = malloc(count * sizeof *ix->order);
    if (!refs || !ix->order) {
        free(refs);
        free(ix->order);
        ix->order = NULL;
        return MR_ERR_NOMEM;
    }
    for (size_t i = 0; i < count; i++)
        refs[i] = (name_ref){nodes[i].name, (int)i};
    qsort(refs, count, sizeof *refs, name_ref_cmp);
    for (size_t i = 0; i < count; i++)
        ix->order[i] = refs[i].index;
    free(refs);
    return MR_OK;
}

static int name_index_find(const name_index *ix, const char *name)
{
    size_t lo = 0, hi = ix->count;
    while (lo < hi) { /* lower bound: first entry whose name >= name */
        size_t mid = lo + (hi - lo) / 2;
        if (strcmp(ix->nodes[ix->order[mid]].name, name) < 0)
            lo = mid + 1;
        else
            hi = mid;
    }
    if (lo < ix->count && strcmp(ix->nodes[ix->order[lo]].name, name) == 0)
        return ix->order[lo];
    return -1;
}

/* ------------------------------------------------------------------------ */
/* normals                                                                    */

/* Area-weighted vertex normals: the unnormalised cross product of each
 * triangle is twice its area times its unit normal, so summing it weights
 * faces by area. Vertices on no (or only degenerate) triangles get +Z so the
 * array stays unit length everywhere. only_invalid != NULL: fill only the
 * vertices flagged there, keeping the file's normals elsewhere. */
static int compute_normals(mr_mesh *m, const unsigned char *only_invalid)
{
    size_t nv = m->vertex_count;
    double *acc = calloc(nv * 3, sizeof *acc);
    if (!acc)
        return MR_ERR_NOMEM;
    const float *p = m->positions;
    for (size_t t = 0; t < m->triangle_count; t++) {
        const uint32_t *tri = &m->indices[t * 3];
        const float *a = &p[tri[0] * 3], *b = &p[tri[1] * 3], *c = &p[tri[2] * 3];
        double e1[3] = {(double)b[0] - a[0], (double)b[1] - a[1], (double)b[2] - a[2]};
        double e2[3] = {(double)c[0] - a[0], (double)c[1] - a[1], (double)c[2] - a[2]};
        double n[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                       e1[0] * e2[1] - e1[1] * e2[0]};
        for (int k = 0; k < 3; k++)
            for (int j = 0; j < 3; j++)
                acc[(size_t)tri[k] * 3 + j] += n[j];
    }
    for (size_t i = 0; i < nv; i++) {
        if (only_invalid && !only_invalid[i])
            continue;
        double *n = &acc[i * 3];
        double len = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
        float *o = &m->normals[i * 3];
        if (len > 0.0 && isfinite(len)) {
            o[0] = (float)(n[0] / len);
            o[1] = (float)(n[1] / len);
            o[2] = (float)(n[2] / len);
        } else {
            o[0] = 0.0f;
            o[1] = 0.0f;
            o[2] = 1.0f;
        }
    }
    free(acc);
    return MR_OK;
}

/* Fills m->normals (already allocated) from src (3 floats per vertex, may be
 * NULL): normalised copies where usable, area-weighted normals elsewhere. */
static int finish_normals(mr_mesh *m, const float *src)
{
    if (!src)
        return compute_normals(m, NULL);
    size_t nv = m->vertex_count;
    unsigned char *bad = NULL;
    for (size_t i = 0; i < nv; i++) {
        mr_vec3 n = mr_v3(src[i * 3], src[i * 3 + 1], src[i * 3 + 2]);
        mr_vec3 u = mr_v3_normalize_or(n, mr_v3(0, 0, 0));
        if (u.x == 0.0f && u.y == 0.0f && u.z == 0.0f) {
            if (!bad) {
                bad = calloc(nv, 1);
                if (!bad)
                    return MR_ERR_NOMEM;
            }
            bad[i] = 1;
        }
        m->normals[i * 3] = u.x;
        m->normals[i * 3 + 1] = u.y;
        m->normals[i * 3 + 2] = u.z;
    }
    int rc = MR_OK;
    if (bad)
        rc = compute_normals(m, bad);
    free(bad);
    return rc;
}

/* ------------------------------------------------------------------------ */
/* tangents                                                                   */

int mr_mesh_tangents(mr_mesh *m)
{
    free(m->tangents);
    m->tangents = NULL;
    if (!m->uvs || !m->normals || !m->positions || m->vertex_count == 0)
        return MR_OK;
    size_t nv = m->vertex_count;
    double *acc = calloc(nv * 6, sizeof *acc); /* per vertex: tangent sum, bitangent sum */
    float *out = malloc(nv * 4 * sizeof *out);
    if (!acc || !out) {
        free(acc);
        free(out);
        return MR_ERR_NOMEM;
    }
    const float *p = m->positions, *uv = m->uvs;
    for (size_t t = 0; t < m->triangle_count; t++) {
        const uint32_t *tri = &m->indices[t * 3];
        double e1[3], e2[3];
        for (int a = 0; a < 3; a++) {
            e1[a] = (double)p[tri[1] * 3 + a] - p[tri[0] * 3 + a];
            e2[a] = (double)p[tri[2] * 3 + a] - p[tri[0] * 3 + a];
        }
        double du1 = (double)uv[tri[1] * 2] - uv[tri[0] * 2], dv1 = (double)uv[tri[1] * 2 + 1] - uv[tri[0] * 2 + 1];
        double du2 = (double)uv[tri[2] * 2] - uv[tri[0] * 2], dv2 = (double)uv[tri[2] * 2 + 1] - uv[tri[0] * 2 + 1];
        double det = du1 * dv2 - du2 * dv1;
        if (!(det != 0.0) || !isfinite(det))
            continue; /* collinear uvs: no direction of u here */
        double tg[3], bt[3], c[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                                     e1[0] * e2[1] - e1[1] * e2[0]};
        for (int a = 0; a < 3; a++) {
            tg[a] = (e1[a] * dv2 - e2[a] * dv1) / det; /* dp/du */
            bt[a] = (e2[a] * du1 - e1[a] * du2) / det; /* dp/dv */
        }
        double area = sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
        double lt = sqrt(tg[0] * tg[0] + tg[1] * tg[1] + tg[2] * tg[2]);
        double lb = sqrt(bt[0] * bt[0] + bt[1] * bt[1] + bt[2] * bt[2]);
        if (!(area > 0) || !(lt > 0) || !(lb > 0) || !isfinite(area * lt * lb))
            continue;
        for (int k = 0; k < 3; k++)
            for (int a = 0; a < 3; a++) {
                acc[(size_t)tri[k] * 6 + a] += area * tg[a] / lt;
                acc[(size_t)tri[k] * 6 + 3 + a] += area * bt[a] / lb;
            }
    }
    for (size_t i = 0; i < nv; i++) {
        const double *s = &acc[i * 6];
        /* the float normal made unit in double, so that the part of the
         * sum along it goes whole however long the sum is against the rest */
        double n[3] = {m->normals[i * 3], m->normals[i * 3 + 1], m->normals[i * 3 + 2]};
        double ln = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
        for (int a = 0; a < 3 && ln > 0; a++)
            n[a] /= ln;
        double along = n[0] * s[0] + n[1] * s[1] + n[2] * s[2];
        double t[3] = {s[0] - along * n[0], s[1] - along * n[1], s[2] - along * n[2]};
        double again = n[0] * t[0] + n[1] * t[1] + n[2] * t[2];
        for (int a = 0; a < 3; a++)
            t[a] -= again * n[a];
        double ls = sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2]);
        double lt = sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2]);
        float *o = &out[i * 4];
        if (ls > 0 && lt > (double)MR_TANGENT_PARALLEL * ls) {
            double c[3] = {n[1] * t[2] - n[2] * t[1], n[2] * t[0] - n[0] * t[2], n[0] * t[1] - n[1] * t[0]};
            for (int a = 0; a < 3; a++)
                o[a] = (float)(t[a] / lt);
            o[3] = c[0] * s[3] + c[1] * s[4] + c[2] * s[5] < 0 ? -1.0f : 1.0f;
        } else {
            mr_vec3 any = mr_v3_any_orthogonal(mr_v3((float)n[0], (float)n[1], (float)n[2]));
            o[0] = any.x;
            o[1] = any.y;
            o[2] = any.z;
            o[3] = 1.0f;
        }
    }
    free(acc);
    m->tangents = out;
    return MR_OK;
}

/* ------------------------------------------------------------------------ */
/* import: nodes                                                              */

static int import_nodes(mr_asset *a, const struct aiScene *s, const struct aiNode ***ai_nodes_out,
                        mr_error *err)
{
    int rc = MR_OK;
    const struct aiNode **ai_nodes = NULL;
    typedef struct { const struct aiNode *n; int parent; } item;
    item *stack = NULL;
    size_t cap = 0, top = 0, ncap = 0;

    if (!s->mRootNode)
        return mr_error_set(err, MR_ERR_FORMAT, "%s: the scene has no root node", a->path);

    /* Iterative pre-order walk (parent before child), so a deep hierarchy
     * cannot overflow our stack; the cap also ends a cyclic (corrupt) tree. */
    cap = 64;
    stack = malloc(cap * sizeof *stack);
    if (!stack)
        goto nomem;
    stack[top++] = (item){s->mRootNode, -1};
    while (top > 0) {
        item it = stack[--top];
        if (a->node_count + top >= MR_MAX_ASSET_NODES) {
            rc = mr_error_set(err, MR_ERR_LIMIT, "%s: more than %u nodes", a->path,
                              MR_MAX_ASSET_NODES);
            goto cleanup;
        }
        if (a->node_count == ncap) {
            size_t nc = ncap ? ncap * 2 : 64;
            mr_node *nn = realloc(a->nodes, nc * sizeof *nn);
            if (!nn)
                goto nomem;
            a->nodes = nn;
            const struct aiNode **na = realloc(ai_nodes, nc * sizeof *na);
            if (!na)
                goto nomem;
            ai_nodes = na;
            ncap = nc;
        }
        size_t idx = a->node_count;
        mr_node *node = &a->nodes[idx];
        node->name = dup_aistring(&it.n->mName);
        if (!node->name)
            goto nomem;
        node->parent = it.parent;
        node->local = mat_from_ai(&it.n->mTransformation);
        ai_nodes[idx] = it.n;
        a->node_count++;
        if (!mr_mat4_is_finite(&node->local)) {
            rc = mr_error_set(err, MR_ERR_FORMAT, "%s: node '%s' has a non-finite transform",
                              a->path, node->name);
            goto cleanup;
        }
        if (it.n->mNumChildren > 0 && !it.n->mChildren) {
            rc = mr_error_set(err, MR_ERR_FORMAT, "%s: node '%s' has a NULL child list",
                              a->path, node->name);
            goto cleanup;
        }
        if (top + it.n->mNumChildren > cap) {
            size_t nc = cap;
            while (top + it.n->mNumChildren > nc)
                nc *= 2;
            item *ns = realloc(stack, nc * sizeof *ns);
            if (!ns)
                goto nomem;
            stack = ns;
            cap = nc;
        }
        /* Reverse push so the first child is visited first. */
        for (unsigned c = it.n->mNumChildren; c-- > 0;) {
            if (!it.n->mChildren[c]) {
                rc = mr_error_set(err, MR_ERR_FORMAT, "%s: node '%s' has a NULL child",
                                  a->path, node->name);
                goto cleanup;
            }
            stack[top++] = (item){it.n->mChildren[c], (int)idx};
        }
    }
    goto cleanup;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory reading nodes", a->path);
cleanup:
    free(stack);
    if (rc == MR_OK)
        *ai_nodes_out = ai_nodes;
    else
        free(ai_nodes);
    return rc;
}

/* ------------------------------------------------------------------------ */
/* import: meshes                                                             */

static int import_skin(mr_asset *a, mr_mesh *m, const struct aiMesh *am, const name_index *ix,
                       const char *label, mr_error *err)
{
    int rc = MR_OK;
    size_t *offset = NULL;
    uint32_t *vj = NULL;
    float *vw = NULL;
    size_t nv = m->vertex_count;

    if (am->mNumBones > MR_MAX_ASSET_JOINTS)
        return mr_error_set(err, MR_ERR_LIMIT, "%s: mesh '%s' has %u bones (at most %u)",
                            a->path, label, am->mNumBones, MR_MAX_ASSET_JOINTS);
    if (!am->mBones)
        return mr_error_set(err, MR_ERR_FORMAT, "%s: mesh '%s' has a NULL bone list", a->path,
                            label);
    uint32_t nj = am->mNumBones;
    m->joint_nodes = malloc(nj * sizeof *m->joint_nodes);
    m->inverse_bind = malloc(nj * sizeof *m->inverse_bind);
    m->joints = calloc(nv * MR_MAX_INFLUENCES, sizeof *m->joints);
    m->weights = calloc(nv * MR_MAX_INFLUENCES, sizeof *m->weights);
    offset = calloc(nv + 1, sizeof *offset);
    if (!m->joint_nodes || !m->inverse_bind || !m->joints || !m->weights || !offset)
        goto nomem;
    m->joint_count = nj;

    /* Gather the bone-major lists of assimp into vertex-major ones (CSR). */
    for (uint32_t j = 0; j < nj; j++) {
        const struct aiBone *b = am->mBones[j];
        if (!b || (b->mNumWeights > 0 && !b->mWeights)) {
            rc = mr_error_set(err, MR_ERR_FORMAT, "%s: mesh '%s' bone %u is incomplete",
                              a->path, label, j);
            goto cleanup;
        }
        char name[MAXLEN];
        size_t len = b->mName.length < MAXLEN ? b->mName.length : MAXLEN - 1;
        len = strnlen(b->mName.data, len);
        memcpy(name, b->mName.data, len);
        name[len] = '\0';
        int node = name_index_find(ix, name);
        if (node < 0) {
            rc = mr_error_set(err, MR_ERR_FORMAT,
                              "%s: bone '%s' of mesh '%s' names no node of the scene", a->path,
                              name, label);
            goto cleanup;
        }
        m->joint_nodes[j] = node;
        m->inverse_bind[j] = mat_from_ai(&b->mOffsetMatrix);
        if (!mr_mat4_is_finite(&m->inverse_bind[j])) {
            rc = mr_error_set(err, MR_ERR_FORMAT,
                              "%s: bone '%s' of mesh '%s' has a non-finite offset matrix",
                              a->path, name, label);
            goto cleanup;
        }
        for (unsigned k = 0; k < b->mNumWeights; k++) {
            unsigned v = b->mWeights[k].mVertexId;
            if (v >= nv) {
                rc = mr_error_set(err, MR_ERR_FORMAT,
                                  "%s: bone '%s' of mesh '%s' weights vertex %u of %zu",
                                  a->path, name, label, v, nv);
                goto cleanup;
            }
            offset[v + 1]++;
        }
    }
    for (size_t i = 0; i < nv; i++)
        offset[i + 1] += offset[i];
    size_t total = offset[nv];
    if (total > 0) {
        vj = malloc(total * sizeof *vj);
        vw = malloc(total * sizeof *vw);
        if (!vj || !vw)
            goto nomem;
        /* Fill in bone order so each vertex's list is in a fixed order. */
        for (uint32_t j = 0; j < nj; j++) {
            const struct aiBone *b = am->mBones[j];
            for (unsigned k = 0; k < b->mNumWeights; k++) {
                unsigned v = b->mWeights[k].mVertexId;
                size_t at = offset[v]++;
                vj[at] = j;
                vw[at] = (float)b->mWeights[k].mWeight;
            }
        }
        /* offset[v] now points at the end of v's list: shift back. */
        for (size_t i = nv; i > 0; i--)
            offset[i] = offset[i - 1];
        offset[0] = 0;
        for (size_t i = 0; i < nv; i++) {
            int kept = mr_influences_normalize(vj + offset[i], vw + offset[i],
                                               offset[i + 1] - offset[i],
                                               &m->joints[i * MR_MAX_INFLUENCES],
                                               &m->weights[i * MR_MAX_INFLUENCES]);
            if (kept < 0)
                goto nomem;
        }
    }
    goto cleanup;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory reading the skin of mesh '%s'",
                      a->path, label);
cleanup:
    free(offset);
    free(vj);
    free(vw);
    return rc;
}

static size_t mesh_triangles(const struct aiMesh *am)
{
    size_t t = 0;
    if (!am->mFaces)
        return 0;
    for (unsigned f = 0; f < am->mNumFaces; f++)
        if (am->mFaces[f].mNumIndices >= 3 && am->mFaces[f].mIndices)
            t += am->mFaces[f].mNumIndices - 2;
    return t;
}

static int import_mesh(mr_asset *a, mr_mesh *m, const struct aiMesh *am, int node,
                       const name_index *ix, mr_error *err)
{
    char lbuf[32];
    int rc;
    m->name = dup_aistring(&am->mName);
    if (!m->name)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", a->path);
    const char *label = mesh_label(m->name, a->mesh_count, lbuf);
    m->node = node;
    size_t nv = am->mNumVertices;
    size_t nt = mesh_triangles(am);
    if (nv == 0 || !am->mVertices)
        return mr_error_set(err, MR_ERR_FORMAT, "%s: mesh '%s' has triangles but no vertices",
                            a->path, label);
    m->vertex_count = (uint32_t)nv;
    m->triangle_count = (uint32_t)nt;
    m->positions = malloc(nv * 3 * sizeof(float));
    m->normals = malloc(nv * 3 * sizeof(float));
    m->indices = malloc(nt * 3 * sizeof(uint32_t));
    if (!m->positions || !m->normals || !m->indices)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory reading mesh '%s'", a->path,
                            label);
    for (size_t i = 0; i < nv; i++) {
        mr_vec3 p = mr_v3((float)am->mVertices[i].x, (float)am->mVertices[i].y,
                          (float)am->mVertices[i].z);
        if (!vec_finite(p)) /* check_positions caught this already; kept for safety */
            return mr_error_set(err, MR_ERR_FORMAT,
                                "%s: mesh '%s' vertex %zu has a non-finite position", a->path,
                                label, i);
        m->positions[i * 3] = p.x;
        m->positions[i * 3 + 1] = p.y;
        m->positions[i * 3 + 2] = p.z;
    }
    /* Triangles only: points and lines are dropped. Polygons should not
     * survive aiProcess_Triangulate; if one does, it is fanned. */
    size_t t = 0;
    for (unsigned f = 0; f < am->mNumFaces; f++) {
        const struct aiFace *face = &am->mFaces[f];
        if (face->mNumIndices < 3 || !face->mIndices)
            continue;
        for (unsigned k = 0; k < face->mNumIndices; k++)
            if (face->mIndices[k] >= nv)
                return mr_error_set(err, MR_ERR_FORMAT,
                                    "%s: mesh '%s' face %u uses vertex %u of %zu", a->path,
                                    label, f, face->mIndices[k], nv);
        for (unsigned k = 1; k + 1 < face->mNumIndices; k++, t++) {
            m->indices[t * 3] = face->mIndices[0];
            m->indices[t * 3 + 1] = face->mIndices[k];
            m->indices[t * 3 + 2] = face->mIndices[k + 1];
        }
    }
    float *src_normals = NULL;
    if (am->mNormals) {
        src_normals = malloc(nv * 3 * sizeof(float));
        if (!src_normals)
            return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", a->path);
        for (size_t i = 0; i < nv; i++) {
            src_normals[i * 3] = (float)am->mNormals[i].x;
            src_normals[i * 3 + 1] = (float)am->mNormals[i].y;
            src_normals[i * 3 + 2] = (float)am->mNormals[i].z;
        }
    }
    rc = finish_normals(m, src_normals);
    free(src_normals);
    if (rc < 0)
        return mr_error_set(err, rc, "%s: out of memory computing normals", a->path);
    if (am->mTextureCoords[0]) {
        m->uvs = malloc(nv * 2 * sizeof(float));
        if (!m->uvs)
            return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", a->path);
        for (size_t i = 0; i < nv; i++) {
            float u = (float)am->mTextureCoords[0][i].x, v = (float)am->mTextureCoords[0][i].y;
            m->uvs[i * 2] = isfinite(u) ? u : 0.0f;
            m->uvs[i * 2 + 1] = isfinite(v) ? v : 0.0f;
        }
        if (mr_mesh_tangents(m) < 0)
            return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory computing tangents", a->path);
    }
    if (am->mNumBones > 0)
        return import_skin(a, m, am, ix, label, err);
    return MR_OK;
}

static int import_meshes(mr_asset *a, const struct aiScene *s, const struct aiNode **ai_nodes,
                         const name_index *ix, mr_error *err)
{
    size_t refs = 0;
    for (size_t i = 0; i < a->node_count; i++) {
        const struct aiNode *n = ai_nodes[i];
        if (n->mNumMeshes > 0 && !n->mMeshes)
            return mr_error_set(err, MR_ERR_FORMAT, "%s: node '%s' has a NULL mesh list",
                                a->path, a->nodes[i].name);
        refs += n->mNumMeshes;
    }
    if (refs == 0)
        return mr_error_set(err, MR_ERR_FORMAT, "%s: the file holds no triangles", a->path);
    a->meshes = calloc(refs, sizeof *a->meshes);
    if (!a->meshes)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", a->path);
    size_t total_v = 0, total_t = 0;
    /* One mr_mesh per (node, mesh) reference: an instanced mesh is copied
     * so each entry carries its own node. */
    for (size_t i = 0; i < a->node_count; i++) {
        const struct aiNode *n = ai_nodes[i];
        for (unsigned k = 0; k < n->mNumMeshes; k++) {
            unsigned mi = n->mMeshes[k];
            if (mi >= s->mNumMeshes || !s->mMeshes || !s->mMeshes[mi])
                return mr_error_set(err, MR_ERR_FORMAT,
                                    "%s: node '%s' references mesh %u of %u", a->path,
                                    a->nodes[i].name, mi, s->mNumMeshes);
            const struct aiMesh *am = s->mMeshes[mi];
            size_t nt = mesh_triangles(am);
            if (nt == 0)
                continue; /* a point or line mesh (aiProcess_SortByPType split it off) */
            total_v += am->mNumVertices;
            total_t += nt;
            if (total_v > MR_MAX_ASSET_VERTICES)
                return mr_error_set(err, MR_ERR_LIMIT, "%s: more than %u vertices", a->path,
                                    MR_MAX_ASSET_VERTICES);
            if (total_t > MR_MAX_ASSET_TRIANGLES)
                return mr_error_set(err, MR_ERR_LIMIT, "%s: more than %u triangles", a->path,
                                    MR_MAX_ASSET_TRIANGLES);
            mr_mesh *m = &a->meshes[a->mesh_count];
            int rc = import_mesh(a, m, am, (int)i, ix, err);
            a->mesh_count++; /* counted even on failure so mr_asset_free releases it */
            if (rc < 0)
                return rc;
        }
    }
    a->triangle_count = total_t;
    if (total_t == 0)
        return mr_error_set(err, MR_ERR_FORMAT, "%s: the file holds no triangles", a->path);
    return MR_OK;
}

/* ------------------------------------------------------------------------ */
/* import: animation                                                          */

typedef struct key_ref {
    double t;
    uint32_t i;
} key_ref;

static int key_ref_cmp(const void *pa, const void *pb)
{
    const key_ref *a = pa, *b = pb;
    if (a->t != b->t)
        return a->t < b->t ? -1 : 1;
    return (a->i > b->i) - (a->i < b->i);
}

/* Order of the usable keys: finite ones (valid[i] != 0), sorted by time,
 * the first in file order kept where times repeat, so times come out
 * strictly increasing. Returns the count (in *n) and an index list. */
static int key_order(const double *times, const unsigned char *valid, size_t count,
                     uint32_t **order, size_t *n)
{
    *order = NULL;
    *n = 0;
    if (count == 0)
        return MR_OK;
    key_ref *r = malloc(count * sizeof *r);
    uint32_t *o = malloc(count * sizeof *o);
    if (!r || !o) {
        free(r);
        free(o);
        return MR_ERR_NOMEM;
    }
    size_t m = 0;
    for (size_t i = 0; i < count; i++)
        if (valid[i])
            r[m++] = (key_ref){times[i], (uint32_t)i};
    qsort(r, m, sizeof *r, key_ref_cmp);
    size_t k = 0;
    for (size_t i = 0; i < m; i++)
        if (k == 0 || r[i].t > times[o[k - 1]])
            o[k++] = r[i].i;
    free(r);
    *order = o;
    *n = k;
    return MR_OK;
}

static int import_vec_keys(const struct aiVectorKey *keys, unsigned count, double tps,
                           mr_vec3_key **out, size_t *out_count)
{
    *out = NULL;
    *out_count = 0;
    if (count == 0 || !keys)
        return MR_OK;
    int rc = MR_ERR_NOMEM;
    double *t = malloc(count * sizeof *t);
    unsigned char *ok = malloc(count);
    uint32_t *order = NULL;
    size_t n = 0;
    if (!t || !ok)
        goto cleanup;
    for (unsigned i = 0; i < count; i++) {
        t[i] = keys[i].mTime / tps;
        mr_vec3 v = mr_v3((float)keys[i].mValue.x, (float)keys[i].mValue.y,
                          (float)keys[i].mValue.z);
        ok[i] = isfinite(t[i]) && vec_finite(v);
    }
    if (key_order(t, ok, count, &order, &n) < 0)
        goto cleanup;
    if (n > 0) {
        *out = malloc(n * sizeof **out);
        if (!*out)
            goto cleanup;
        for (size_t k = 0; k < n; k++) {
            const struct aiVectorKey *src = &keys[order[k]];
            (*out)[k].time = t[order[k]];
            (*out)[k].value = mr_v3((float)src->mValue.x, (float)src->mValue.y,
                                    (float)src->mValue.z);
        }
        *out_count = n;
    }
    rc = MR_OK;
cleanup:
    free(t);
    free(ok);
    free(order);
    return rc;
}

static int import_quat_keys(const struct aiQuatKey *keys, unsigned count, double tps,
                            mr_quat_key **out, size_t *out_count)
{
    *out = NULL;
    *out_count = 0;
    if (count == 0 || !keys)
        return MR_OK;
    int rc = MR_ERR_NOMEM;
    double *t = malloc(count * sizeof *t);
    unsigned char *ok = malloc(count);
    uint32_t *order = NULL;
    size_t n = 0;
    if (!t || !ok)
        goto cleanup;
    for (unsigned i = 0; i < count; i++) {
        const struct aiQuaternion *q = &keys[i].mValue;
        t[i] = keys[i].mTime / tps;
        double len2 = (double)q->w * q->w + (double)q->x * q->x + (double)q->y * q->y +
                      (double)q->z * q->z;
        /* A zero or non-finite quaternion is no rotation at all: drop the key. */
        ok[i] = isfinite(t[i]) && isfinite(len2) && len2 > 0.0;
    }
    if (key_order(t, ok, count, &order, &n) < 0)
        goto cleanup;
    if (n > 0) {
        *out = malloc(n * sizeof **out);
        if (!*out)
            goto cleanup;
        for (size_t k = 0; k < n; k++) {
            const struct aiQuaternion *q = &keys[order[k]].mValue;
            (*out)[k].time = t[order[k]];
            /* by name: aiQuaternion is (w, x, y, z) in memory, mr_quat (x, y, z, w) */
            (*out)[k].value = mr_quat_normalize(
                (mr_quat){(float)q->x, (float)q->y, (float)q->z, (float)q->w});
        }
        *out_count = n;
    }
    rc = MR_OK;
cleanup:
    free(t);
    free(ok);
    free(order);
    return rc;
}

static int import_clips(mr_asset *a, const struct aiScene *s, const name_index *ix,
                        mr_error *err)
{
    if (s->mNumAnimations == 0 || !s->mAnimations)
        return MR_OK;
    a->clips = calloc(s->mNumAnimations, sizeof *a->clips);
    if (!a->clips)
        goto nomem;
    for (unsigned i = 0; i < s->mNumAnimations; i++) {
        const struct aiAnimation *an = s->mAnimations[i];
        if (!an)
            continue;
        mr_clip *c = &a->clips[a->clip_count++];
        c->name = dup_aistring(&an->mName);
        if (!c->name)
            goto nomem;
        double tps = an->mTicksPerSecond;
        if (!(tps > 0.0) || !isfinite(tps))
            tps = MR_DEFAULT_TICKS_PER_SECOND;
        double duration = an->mDuration / tps;
        if (!(duration >= 0.0) || !isfinite(duration))
            duration = 0.0;
        if (an->mNumChannels > 0 && an->mChannels) {
            c->channels = calloc(an->mNumChannels, sizeof *c->channels);
            if (!c->channels)
                goto nomem;
        }
        for (unsigned k = 0; c->channels && k < an->mNumChannels; k++) {
            const struct aiNodeAnim *na = an->mChannels[k];
            if (!na)
                continue;
            char name[MAXLEN];
            size_t len = na->mNodeName.length < MAXLEN ? na->mNodeName.length : MAXLEN - 1;
            len = strnlen(na->mNodeName.data, len);
            memcpy(name, na->mNodeName.data, len);
            name[len] = '\0';
            int node = name_index_find(ix, name);
            if (node < 0)
                continue; /* animates something we did not import: harmless */
            mr_channel *ch = &c->channels[c->channel_count++];
            ch->node = node;
            if (import_vec_keys(na->mPositionKeys, na->mNumPositionKeys, tps, &ch->positions,
                                &ch->position_count) < 0 ||
                import_quat_keys(na->mRotationKeys, na->mNumRotationKeys, tps, &ch->rotations,
                                 &ch->rotation_count) < 0 ||
                import_vec_keys(na->mScalingKeys, na->mNumScalingKeys, tps, &ch->scales,
                                &ch->scale_count) < 0)
                goto nomem;
            /* Never let the declared duration cut keys off the loop. */
            if (ch->position_count && ch->positions[ch->position_count - 1].time > duration)
                duration = ch->positions[ch->position_count - 1].time;
            if (ch->rotation_count && ch->rotations[ch->rotation_count - 1].time > duration)
                duration = ch->rotations[ch->rotation_count - 1].time;
            if (ch->scale_count && ch->scales[ch->scale_count - 1].time > duration)
                duration = ch->scales[ch->scale_count - 1].time;
        }
        c->duration = duration;
    }
    return MR_OK;
nomem:
    return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory reading animations", a->path);
}

/* ------------------------------------------------------------------------ */
/* import: cameras                                                            */

static bool has_ext(const char *path, const char *ext)
{
    const char *dot = strrchr(path, '.');
    return dot && strcasecmp(dot + 1, ext) == 0;
}

/* Vertical field of view from assimp's mHorizontalFOV, whose meaning depends
 * on the importer (see the head of this file). Returns 0 for orthographic
 * cameras (assimp stores 0 there) and for unusable values. */
static float camera_yfov(const char *path, float hfov, float aspect)
{
    if (!(hfov > 0.0f) || !isfinite(hfov))
        return 0.0f;
    double a = (aspect > 0.0f && isfinite(aspect)) ? aspect : 1.0;
    double y;
    if (has_ext(path, "gltf") || has_ext(path, "glb"))
        y = hfov / a; /* undoes yfov * aspectRatio */
    else if (has_ext(path, "blend"))
        y = 2.0 * atan(tan((double)hfov) / a); /* hfov is the half angle */
    else
        y = 2.0 * atan(tan(0.5 * hfov) / a); /* hfov is the full angle */
    if (!(y > 0.0) || !(y < M_PI))
        return 0.0f;
    return (float)y;
}

static int import_cameras(mr_asset *a, const struct aiScene *s, const name_index *ix,
                          mr_error *err)
{
    if (s->mNumCameras == 0 || !s->mCameras)
        return MR_OK;
    a->cameras = calloc(s->mNumCameras, sizeof *a->cameras);
    if (!a->cameras)
        goto nomem;
    for (unsigned i = 0; i < s->mNumCameras; i++) {
        const struct aiCamera *ac = s->mCameras[i];
        if (!ac)
            continue;
        mr_camera_info *c = &a->cameras[a->camera_count++];
        c->name = dup_aistring(&ac->mName);
        if (!c->name)
            goto nomem;
        c->node = name_index_find(ix, c->name);
        c->position = mr_v3((float)ac->mPosition.x, (float)ac->mPosition.y,
                            (float)ac->mPosition.z);
        c->look_at = mr_v3((float)ac->mLookAt.x, (float)ac->mLookAt.y, (float)ac->mLookAt.z);
        c->up = mr_v3((float)ac->mUp.x, (float)ac->mUp.y, (float)ac->mUp.z);
        /* assimp 5.2.5's glTF importers copy the camera node's translation
         * into mPosition (measured: a camera node at (0.5,0.5,3) gives
         * mPosition (0.5,0.5,3)), so placing it by the node again would count
         * it twice. A glTF camera sits at its node's origin. */
        if (!vec_finite(c->position) || has_ext(a->path, "gltf") || has_ext(a->path, "glb"))
            c->position = mr_v3(0, 0, 0);
        /* aiCamera's defaults when a file gives garbage */
        c->look_at = mr_v3_normalize_or(c->look_at, mr_v3(0, 0, 1));
        c->up = mr_v3_normalize_or(c->up, mr_v3(0, 1, 0));
        c->aspect = (ac->mAspect > 0.0f && isfinite(ac->mAspect)) ? (float)ac->mAspect : 0.0f;
        c->yfov = camera_yfov(a->path, (float)ac->mHorizontalFOV, c->aspect);
    }
    return MR_OK;
nomem:
    return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory reading cameras", a->path);
}

/* ------------------------------------------------------------------------ */
/* entry points                                                               */

/* ------------------------------------------------------------------------ */
/* declared-count plausibility (before assimp allocates)                     */

/* assimp's OFF and PLY loaders size their arrays from the counts a file
 * declares before reading any data. invalid/OutOfMemory.off (309 bytes,
 * declaring 353535235358 vertices) made assimp 5.2.5 touch 15.8 GB in 25 s
 * and a 300-byte ASCII PLY declaring 1.5e9 vertices 17.6 GB in 4 minutes,
 * enough to take a daemon down. So for these two formats (recognised by
 * content, as assimp also does) the declared counts are checked first: a
 * file must have at least one byte per declared PLY element and five bytes
 * per OFF vertex ("0 0 0") plus two per face, or it cannot hold what it
 * declares (MR_ERR_FORMAT); plausible counts above the caps are refused with
 * MR_ERR_LIMIT. Other formats rely on assimp's own checks. */
#define MR_SNIFF_BYTES 65536

static unsigned long long sat_add(unsigned long long a, unsigned long long b)
{
    return a > ULLONG_MAX - b ? ULLONG_MAX : a + b;
}

static unsigned long long sat_mul(unsigned long long a, unsigned long long b)
{
    return (b != 0 && a > ULLONG_MAX / b) ? ULLONG_MAX : a * b;
}

/* Next whitespace-separated token of an OFF file, skipping # comments. */
static const char *off_token(const char **cur, const char *end, size_t *len)
{
    const char *c = *cur;
    for (;;) {
        while (c < end && (*c == ' ' || *c == '\t' || *c == '\r' || *c == '\n'))
            c++;
        if (c < end && *c == '#') {
            while (c < end && *c != '\n')
                c++;
            continue;
        }
        break;
    }
    const char *start = c;
    while (c < end && !(*c == ' ' || *c == '\t' || *c == '\r' || *c == '\n' || *c == '#'))
        c++;
    *cur = c;
    *len = (size_t)(c - start);
    return *len ? start : NULL;
}

/* Parses a decimal count; saturates at ULLONG_MAX. false if not a number. */
static bool parse_count(const char *t, size_t len, unsigned long long *out)
{
    unsigned long long v = 0;
    if (len == 0)
        return false;
    for (size_t i = 0; i < len; i++) {
        if (t[i] < '0' || t[i] > '9')
            return false;
        v = sat_add(sat_mul(v, 10), (unsigned long long)(t[i] - '0'));
    }
    *out = v;
    return true;
}

static int check_counts(const char *path, unsigned long long vertices,
                        unsigned long long faces, unsigned long long min_bytes,
                        long long size, mr_error *err)
{
    if (min_bytes > (unsigned long long)size)
        return mr_error_set(err, MR_ERR_FORMAT,
                            "%s: declares %llu vertices and %llu faces, more than its %lld "
                            "bytes can hold",
                            path, vertices, faces, size);
    if (vertices > MR_MAX_ASSET_VERTICES || faces > MR_MAX_ASSET_TRIANGLES)
        return mr_error_set(err, MR_ERR_LIMIT,
                            "%s: declares %llu vertices and %llu faces (caps %u and %u)", path,
                            vertices, faces, MR_MAX_ASSET_VERTICES, MR_MAX_ASSET_TRIANGLES);
    return MR_OK;
}

static int precheck_off(const char *path, const char *buf, size_t n, long long size,
                        mr_error *err)
{
    const char *cur = buf, *end = buf + n;
    size_t len;
    const char *t = off_token(&cur, end, &len);
    /* OFF, COFF, NOFF, STOFF, 4OFF, ...; nOFF has an extra dimension field
     * and binary OFF stores counts differently: leave those to assimp. */
    if (!t || len < 3 || len > 8 || memcmp(t + len - 3, "OFF", 3) != 0 || t[0] == 'n')
        return MR_OK;
    unsigned long long c[2];
    for (int i = 0; i < 2; i++) {
        t = off_token(&cur, end, &len);
        if (!t || !parse_count(t, len, &c[i]))
            return MR_OK; /* not the layout we know: assimp decides */
    }
    return check_counts(path, c[0], c[1], sat_add(sat_mul(c[0], 5), sat_mul(c[1], 2)), size,
                        err);
}

static int precheck_ply(const char *path, const char *buf, size_t n, long long size,
                        mr_error *err)
{
    unsigned long long vertices = 0, faces = 0, elements = 0;
    const char *c = buf, *end = buf + n;
    while (c < end) {
        const char *eol = memchr(c, '\n', (size_t)(end - c));
        const char *line_end = eol ? eol : end;
        size_t len = (size_t)(line_end - c);
        if (len >= 10 && memcmp(c, "end_header", 10) == 0)
            break;
        if (len > 8 && memcmp(c, "element ", 8) == 0) {
            const char *name = c + 8, *sp = memchr(name, ' ', (size_t)(line_end - name));
            if (sp) {
                const char *num = sp + 1, *ne = num;
                while (ne < line_end && *ne >= '0' && *ne <= '9')
                    ne++;
                unsigned long long count;
                if (parse_count(num, (size_t)(ne - num), &count)) {
                    elements = sat_add(elements, count);
                    if ((size_t)(sp - name) == 6 && memcmp(name, "vertex", 6) == 0)
                        vertices = sat_add(vertices, count);
                    if ((size_t)(sp - name) == 4 && memcmp(name, "face", 4) == 0)
                        faces = sat_add(faces, count);
                }
            }
        }
        if (!eol)
            break;
        c = eol + 1;
    }
    return check_counts(path, vertices, faces, elements, size, err);
}

/* A text DirectX file ("xof 0303txt ..."): every "Mesh [name] {" starts
 * with its vertex count, and assimp reserves that many vertices before
 * reading one (an 83-byte file declaring 2e9 vertices grew past 12 GB).
 * A vertex takes at least 6 bytes ("0;0;0;"), so a count the file cannot
 * hold is refused here, as are counts above the caps. Binary and compressed
 * X files are left to assimp. Only the sniffed head is searched. */
static int precheck_x(const char *path, const char *buf, size_t n, long long size,
                      mr_error *err)
{
    if (n < 16 || memcmp(buf, "xof ", 4) != 0 || memcmp(buf + 8, "txt ", 4) != 0)
        return MR_OK;
    unsigned long long vertices = 0;
    for (size_t i = 16; i + 4 < n; i++) {
        bool word_start = !(isalnum((unsigned char)buf[i - 1]) || buf[i - 1] == '_');
        if (!word_start || memcmp(buf + i, "Mesh", 4) != 0 ||
            isalnum((unsigned char)buf[i + 4]) || buf[i + 4] == '_')
            continue;
        size_t k = i + 4;
        while (k < n && buf[k] != '{' && buf[k] != ';' && buf[k] != '}')
            k++; /* the optional name */
        if (k >= n || buf[k] != '{')
            continue;
        k++;
        while (k < n && isspace((unsigned char)buf[k]))
            k++;
        size_t d = k;
        while (d < n && buf[d] >= '0' && buf[d] <= '9')
            d++;
        unsigned long long count;
        if (d > k && parse_count(buf + k, d - k, &count))
            vertices = sat_add(vertices, count);
        i = d;
    }
    return check_counts(path, vertices, 0, sat_mul(vertices, 6), size, err);
}

/* assimp 5.2's SMD reader loops for ever (at full CPU, until the import's
 * deadline) on a bone name of the "nodes" section whose opening quote is
 * never closed: ParseNodeInfo stops at the end of the file and returns
 * where it started, and ParseNodesSection calls it again
 * (`version 1\nnodes\n0 "bone -1\n`, found by tests/fuzz/fuzz_asset). Such a
 * name leaves the file with an odd number of quotes, and the format has no
 * other use for them, so an odd count is refused. The whole file is read:
 * the quote that opens the name may come anywhere. */
static int precheck_smd(const char *path, mr_error *err)
{
    FILE *f = fopen(path, "rb");
    if (!f)
        return mr_error_set(err, MR_ERR_IO, "%s: %s", path, strerror(errno));
    char buf[65536];
    unsigned long long quotes = 0;
    size_t n;
    while ((n = fread(buf, 1, sizeof buf, f)) > 0)
        for (const char *p = buf; (p = memchr(p, '"', (size_t)(buf + n - p))); p++)
            quotes++;
    bool failed = ferror(f) != 0;
    fclose(f);
    if (failed)
        return mr_error_set(err, MR_ERR_IO, "%s: read error", path);
    if (quotes % 2)
        return mr_error_set(err, MR_ERR_FORMAT,
                            "%s: an SMD file with an unterminated quoted name (%llu quotes)",
                            path, quotes);
    return MR_OK;
}

static int precheck_counts(const char *path, long long size, mr_error *err)
{
    if (has_ext(path, "smd") || has_ext(path, "vta")) {
        int rc = precheck_smd(path, err);
        if (rc < 0)
            return rc;
    }
    char *buf = malloc(MR_SNIFF_BYTES);
    if (!buf)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", path);
    int rc = MR_OK;
    FILE *f = fopen(path, "rb");
    if (!f) {
        rc = mr_error_set(err, MR_ERR_IO, "%s: %s", path, strerror(errno));
        goto cleanup;
    }
    size_t n = fread(buf, 1, MR_SNIFF_BYTES, f);
    fclose(f);
    if (n >= 4 && memcmp(buf, "ply", 3) == 0 && (buf[3] == '\n' || buf[3] == '\r'))
        rc = precheck_ply(path, buf, n, size, err);
    else if (n >= 4 && memcmp(buf, "xof ", 4) == 0)
        rc = precheck_x(path, buf, n, size, err);
    else
        rc = precheck_off(path, buf, n, size, err);
cleanup:
    free(buf);
    return rc;
}

/* Raw (pre-post-processing) check, so the vertex number is the file's. */
static int check_positions(const struct aiScene *s, const char *path, mr_error *err)
{
    for (unsigned k = 0; s->mMeshes && k < s->mNumMeshes; k++) {
        const struct aiMesh *am = s->mMeshes[k];
        if (!am || !am->mVertices)
            continue; /* reported later, if a node uses it */
        for (unsigned i = 0; i < am->mNumVertices; i++) {
            const struct aiVector3D *v = &am->mVertices[i];
            if (isfinite(v->x) && isfinite(v->y) && isfinite(v->z))
                continue;
            char lbuf[32], *name = dup_aistring(&am->mName);
            int rc = mr_error_set(err, MR_ERR_FORMAT,
                                  "%s: mesh '%s' vertex %u has a non-finite position", path,
                                  mesh_label(name, k, lbuf), i);
            free(name);
            return rc;
        }
    }
    return MR_OK;
}

/* Raw faces, before post-processing: every face has indices, all within
 * the mesh, and each mesh's primitive types are set again from its faces.
 * assimp's scene preprocessor counts a face without indices (a binary PLY
 * face whose count byte is 0) as a polygon, and its triangulation then
 * finds nothing to split and dies of an assertion (abort(), found by
 * tests/fuzz/fuzz_asset); its post-processing steps also index vertices
 * with whatever a face holds. */
static int check_faces(const struct aiScene *s, const char *path, mr_error *err)
{
    for (unsigned k = 0; s->mMeshes && k < s->mNumMeshes; k++) {
        struct aiMesh *am = s->mMeshes[k];
        if (!am || !am->mFaces)
            continue;
        unsigned types = 0;
        for (unsigned f = 0; f < am->mNumFaces; f++) {
            const struct aiFace *face = &am->mFaces[f];
            const char *why = NULL;
            if (face->mNumIndices == 0 || !face->mIndices)
                why = "has no vertices";
            for (unsigned i = 0; !why && i < face->mNumIndices; i++)
                if (face->mIndices[i] >= am->mNumVertices)
                    why = "uses a vertex the mesh does not have";
            if (why) {
                char lbuf[32], *name = dup_aistring(&am->mName);
                int rc = mr_error_set(err, MR_ERR_FORMAT, "%s: mesh '%s' face %u %s", path,
                                      mesh_label(name, k, lbuf), f, why);
                free(name);
                return rc;
            }
            types |= face->mNumIndices == 1   ? aiPrimitiveType_POINT
                     : face->mNumIndices == 2 ? aiPrimitiveType_LINE
                     : face->mNumIndices == 3 ? aiPrimitiveType_TRIANGLE
                                              : aiPrimitiveType_POLYGON;
        }
        am->mPrimitiveTypes = types;
    }
    return MR_OK;
}

/* Whether the file starts with an image signature (asset/image.h): 1 yes,
 * 0 no, or an error. */
static int sniff_image(const char *path, mr_error *err)
{
    int fd = open(path, O_RDONLY | O_CLOEXEC | O_NONBLOCK);
    if (fd < 0)
        return mr_error_set(err, MR_ERR_IO, "%s: %s", path, strerror(errno));
    uint8_t head[8];
    ssize_t n = read(fd, head, sizeof head);
    close(fd);
    if (n < 0)
        return mr_error_set(err, MR_ERR_IO, "%s: %s", path, strerror(errno));
    return mr_image_sniff(head, (size_t)n) != MR_IMAGE_NONE;
}

/* An image asset: the whole file, decoded (asset/image.h). */
static int load_image(const char *path, mr_asset **out, mr_error *err)
{
    uint8_t *data = NULL;
    size_t size = 0;
    mr_image *img = NULL;
    int rc = mr_fs_read_capped(path, MR_MAX_ASSET_FILE_BYTES, &data, &size, "image", err);
    if (rc == MR_OK)
        rc = mr_image_decode(data, size, path, &img, err);
    free(data);
    if (rc < 0)
        return rc;
    return mr_asset_from_image(path, img, out, err);
}

/* The import itself, on whatever thread calls it (mr_asset_load gives it
 * a deep stack). */
static int load_here(const char *path, mr_asset **out, mr_error *err)
{
    int rc = MR_OK;
    const struct aiScene *scene = NULL;
    const struct aiNode **ai_nodes = NULL;
    name_index ix = {0};
    mr_asset *a = NULL;

    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "mr_asset_load: out is NULL");
    *out = NULL;
    if (!path || !path[0])
        return mr_error_set(err, MR_ERR_INVALID, "mr_asset_load: no path given");

    /* Tell "cannot read" apart from "read but broken" before assimp folds
     * both into "No suitable reader found". */
    struct stat st;
    if (stat(path, &st) != 0)
        return mr_error_set(err, MR_ERR_IO, "%s: %s", path, strerror(errno));
    if (S_ISDIR(st.st_mode))
        return mr_error_set(err, MR_ERR_IO, "%s: is a directory, not a model file", path);
    if (!S_ISREG(st.st_mode))
        return mr_error_set(err, MR_ERR_IO, "%s: not a regular file", path);
    if ((unsigned long long)st.st_size > MR_MAX_ASSET_FILE_BYTES)
        return mr_error_set(err, MR_ERR_LIMIT, "%s: %lld bytes, more than the %llu a model file may have",
                            path, (long long)st.st_size, (unsigned long long)MR_MAX_ASSET_FILE_BYTES);
    if (st.st_size == 0) {
        /* still tell an unreadable empty file apart */
        FILE *f = fopen(path, "rb");
        if (!f)
            return mr_error_set(err, MR_ERR_IO, "%s: %s", path, strerror(errno));
        fclose(f);
        return mr_error_set(err, MR_ERR_FORMAT, "%s: the file is empty", path);
    }
    int image = sniff_image(path, err);
    if (image < 0)
        return image;
    if (image)
        return load_image(path, out, err);
    if ((rc = precheck_counts(path, (long long)st.st_size, err)) < 0)
        return rc;

    confined_fs fs;
    if (!cfs_init(&fs, path))
        return mr_error_set(err, MR_ERR_IO, "%s: %s", path, strerror(errno));
    struct aiFileIO io = {.OpenProc = cfs_open, .CloseProc = cfs_close, .UserData = (aiUserData)&fs};
    scene = aiImportFileEx(path, MR_ASSIMP_IMPORT_FLAGS, &io);
    if (!scene) {
        const char *why = aiGetErrorString();
        if (fs.refused[0])
            return mr_error_set(err, MR_ERR_INVALID,
                                "%s: it refers to \"%s\", outside the model's own folder (the "
                                "files a model names must sit beside it or below)",
                                path, fs.refused);
        return mr_error_set(err, MR_ERR_FORMAT, "%s: assimp could not import it: %s", path,
                            why && why[0] ? why : "(no reason given)");
    }
    if ((rc = check_positions(scene, path, err)) < 0 || (rc = check_faces(scene, path, err)) < 0)
        goto cleanup;
    if (!(scene = aiApplyPostProcessing(scene, MR_ASSIMP_POST_FLAGS))) {
        /* assimp has released the scene itself */
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: assimp post-processing failed", path);
        goto cleanup;
    }

    a = calloc(1, sizeof *a);
    if (!a || !(a->path = mr_strdup(path))) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", path);
        goto cleanup;
    }
    if ((rc = import_nodes(a, scene, &ai_nodes, err)) < 0)
        goto cleanup;
    if (name_index_build(&ix, a->nodes, a->node_count) < 0) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", path);
        goto cleanup;
    }
    if ((rc = import_meshes(a, scene, ai_nodes, &ix, err)) < 0)
        goto cleanup;
    if ((rc = import_clips(a, scene, &ix, err)) < 0)
        goto cleanup;
    if ((rc = import_cameras(a, scene, &ix, err)) < 0)
        goto cleanup;
    *out = a;
    a = NULL;
cleanup:
    aiReleaseImport(scene);
    free(ai_nodes);
    free(ix.order);
    mr_asset_free(a);
    return rc;
}

int mr_asset_from_mesh(const char *name, const float *positions, const float *normals,
                       uint32_t vertex_count, const uint32_t *indices,
                       uint32_t triangle_count, mr_asset **out, mr_error *err)
{
    int rc = MR_OK;
    mr_asset *a = NULL;
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "mr_asset_from_mesh: out is NULL");
    *out = NULL;
    if (!name)
        name = "";
    if (!positions || !indices || vertex_count == 0 || triangle_count == 0)
        return mr_error_set(err, MR_ERR_INVALID, "mesh '%s': no vertices or no triangles",
                            name);
    if (vertex_count > MR_MAX_ASSET_VERTICES || triangle_count > MR_MAX_ASSET_TRIANGLES)
        return mr_error_set(err, MR_ERR_LIMIT,
                            "mesh '%s': %u vertices / %u triangles exceed the caps (%u / %u)",
                            name, vertex_count, triangle_count, MR_MAX_ASSET_VERTICES,
                            MR_MAX_ASSET_TRIANGLES);
    for (size_t i = 0; i < (size_t)vertex_count * 3; i++)
        if (!isfinite(positions[i]))
            return mr_error_set(err, MR_ERR_INVALID,
                                "mesh '%s': vertex %zu has a non-finite position", name, i / 3);
    for (size_t i = 0; i < (size_t)triangle_count * 3; i++)
        if (indices[i] >= vertex_count)
            return mr_error_set(err, MR_ERR_INVALID,
                                "mesh '%s': triangle %zu uses vertex %u of %u", name, i / 3,
                                indices[i], vertex_count);

    size_t nv = vertex_count, nt = triangle_count;
    a = calloc(1, sizeof *a);
    if (!a)
        goto nomem;
    a->path = malloc(strlen(name) + sizeof "memory:");
    if (!a->path)
        goto nomem;
    sprintf(a->path, "memory:%s", name);
    a->nodes = calloc(1, sizeof *a->nodes);
    if (!a->nodes)
        goto nomem;
    a->node_count = 1;
    a->nodes[0].parent = -1;
    a->nodes[0].local = mr_mat4_identity();
    if (!(a->nodes[0].name = mr_strdup(name)))
        goto nomem;
    a->meshes = calloc(1, sizeof *a->meshes);
    if (!a->meshes)
        goto nomem;
    a->mesh_count = 1;
    mr_mesh *m = &a->meshes[0];
    m->node = 0;
    m->vertex_count = vertex_count;
    m->triangle_count = triangle_count;
    m->name = mr_strdup(name);
    m->positions = malloc(nv * 3 * sizeof(float));
    m->normals = malloc(nv * 3 * sizeof(float));
    m->indices = malloc(nt * 3 * sizeof(uint32_t));
    if (!m->name || !m->positions || !m->normals || !m->indices)
        goto nomem;
    memcpy(m->positions, positions, nv * 3 * sizeof(float));
    memcpy(m->indices, indices, nt * 3 * sizeof(uint32_t));
    if (finish_normals(m, normals) < 0)
        goto nomem;
    a->triangle_count = nt;
    *out = a;
    return MR_OK;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "mesh '%s': out of memory", name);
    mr_asset_free(a);
    return rc;
}

int mr_asset_faceted(const char *name, const float *positions, uint32_t vertex_count,
                     const uint32_t *indices, uint32_t triangle_count, mr_asset **out,
                     mr_error *err)
{
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "mr_asset_faceted: out is NULL");
    *out = NULL;
    if (!positions || !indices || vertex_count == 0 || triangle_count == 0)
        return mr_error_set(err, MR_ERR_INVALID, "mesh '%s': no vertices or no triangles",
                            name ? name : "");
    if ((uint64_t)triangle_count * 3 > MR_MAX_ASSET_VERTICES)
        return mr_error_set(err, MR_ERR_LIMIT, "mesh '%s': %u triangles need %llu corners (cap %u)",
                            name ? name : "", triangle_count,
                            (unsigned long long)triangle_count * 3, MR_MAX_ASSET_VERTICES);
    size_t nt = triangle_count;
    float *pos = malloc(nt * 9 * sizeof(float)), *nrm = malloc(nt * 9 * sizeof(float));
    uint32_t *idx = malloc(nt * 3 * sizeof(uint32_t));
    int rc = MR_OK;
    if (!pos || !nrm || !idx) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "mesh '%s': out of memory", name ? name : "");
        goto done;
    }
    for (size_t t = 0; t < nt; t++) {
        const float *v[3];
        for (int k = 0; k < 3; k++) {
            if (indices[3 * t + k] >= vertex_count) {
                rc = mr_error_set(err, MR_ERR_INVALID, "mesh '%s': triangle %zu uses vertex %u of %u",
                                  name ? name : "", t, indices[3 * t + k], vertex_count);
                goto done;
            }
            v[k] = positions + 3 * (size_t)indices[3 * t + k];
        }
        mr_vec3 n = mr_v3_normalize_or(
            mr_v3_cross(mr_v3(v[1][0] - v[0][0], v[1][1] - v[0][1], v[1][2] - v[0][2]),
                        mr_v3(v[2][0] - v[0][0], v[2][1] - v[0][1], v[2][2] - v[0][2])),
            mr_v3(0, 0, 1));
        for (int k = 0; k < 3; k++) {
            memcpy(pos + 9 * t + 3 * k, v[k], 3 * sizeof(float));
            nrm[9 * t + 3 * k] = n.x, nrm[9 * t + 3 * k + 1] = n.y, nrm[9 * t + 3 * k + 2] = n.z;
            idx[3 * t + k] = (uint32_t)(3 * t + (size_t)k);
        }
    }
    rc = mr_asset_from_mesh(name, pos, nrm, (uint32_t)(3 * nt), idx, triangle_count, out, err);
done:
    free(pos);
    free(nrm);
    free(idx);
    return rc;
}

/* ---- the import's stack ----------------------------------------------------
 * assimp walks node hierarchies recursively while it parses, post-processes
 * and releases a scene: a 679 KB glTF whose 30,000 nodes are nested one in
 * the other overflowed the 8 MiB stack of a daemon thread (about 35,000
 * frames; a crash, and again after every restart). So the whole import runs
 * on a thread of its own with a stack sized for the deepest hierarchy the
 * node cap allows (MR_MAX_ASSET_NODES, ~1 M, at about 1 KiB a level): the
 * stack is address space, taken from memory only as deep as a file goes. */
typedef struct load_call {
    const char *path;
    mr_asset **out;
    mr_error *err;
    int rc;
} load_call;

static void *load_thread(void *arg)
{
    load_call *c = arg;
    c->rc = load_here(c->path, c->out, c->err);
    return NULL;
}

int mr_asset_load(const char *path, mr_asset **out, mr_error *err)
{
    load_call call = {path, out, err, MR_OK};
    pthread_attr_t attr;
    pthread_t t;
    bool started = false;
    if (pthread_attr_init(&attr) == 0) {
        started = pthread_attr_setstacksize(&attr, MR_ASSET_IMPORT_STACK_BYTES) == 0 &&
                  pthread_create(&t, &attr, load_thread, &call) == 0;
        pthread_attr_destroy(&attr);
    }
    if (!started) /* no room for the stack: import here, as before */
        return load_here(path, out, err);
    pthread_join(t, NULL);
    return call.rc;
}
