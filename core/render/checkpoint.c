/* checkpoint.c - a sequential kind's state snapshots on disk (checkpoint.h). */
#include "render/checkpoint.h"

#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "util/crc32.h"
#include "util/derived.h"
#include "util/le.h"

#define HEAD 140u
#define AT_FRAMES 16u
#define AT_PAYLOAD_BYTES 24u
#define AT_PAYLOAD_CRC 32u
#define AT_KIND 36u
#define KIND_BYTES 32u
#define AT_ID 68u
#define AT_KEY 100u

static const mr_derived_format CHECKPOINT_FORMAT = {
    .name = "checkpoint file",
    .ext = "mrckpt",
    .magic = {'M', 'R', 'C', 'K', 'P', 'T', '\r', '\n'},
    .version = MR_CHECKPOINT_VERSION,
    .header_bytes = HEAD,
    .key_at = AT_KEY,
    .max_bytes = 1ull << 32,
};

typedef struct request {
    const mr_kind *kind;
    mr_geom *geom;
    const mr_geom *cgeom;
    uint64_t frames;
    uint8_t id[32];
} request;

bool mr_checkpoint_kept(const mr_kind *k, const mr_geom *g, const char *dir)
{
    return dir && dir[0] && k->frame_order == MR_FRAMES_SEQUENTIAL && k->checkpoint_every &&
           k->checkpoint_every(g) > 0;
}

static void checkpoint_key(const request *q, uint8_t key[MR_DERIVED_KEY_BYTES])
{
    mr_derived_key_builder kb;
    mr_derived_key_begin(&kb, "microray checkpoint", MR_CHECKPOINT_VERSION, 1);
    mr_derived_key_bytes(&kb, q->kind->name, strlen(q->kind->name) + 1);
    mr_derived_key_bytes(&kb, q->id, sizeof q->id);
    mr_derived_key_u64(&kb, q->frames);
    mr_derived_key_end(&kb, key);
}

static int parse(void *ctx, const uint8_t *buf, size_t size, mr_error *err)
{
    request *q = ctx;
    const mr_derived_format *f = &CHECKPOINT_FORMAT;
    uint64_t frames = mr_le_get_u64(buf + AT_FRAMES), payload = mr_le_get_u64(buf + AT_PAYLOAD_BYTES);
    if (frames != q->frames)
        return mr_derived_bad(f, err, "frames %llu at byte offset %u (want %llu)",
                              (unsigned long long)frames, AT_FRAMES, (unsigned long long)q->frames);
    char name[KIND_BYTES + 1] = {0};
    memcpy(name, buf + AT_KIND, KIND_BYTES);
    if (strcmp(name, q->kind->name) != 0)
        return mr_derived_bad(f, err, "kind \"%s\" at byte offset %u (want \"%s\")", name, AT_KIND,
                              q->kind->name);
    if (memcmp(buf + AT_ID, q->id, sizeof q->id) != 0)
        return mr_derived_bad(f, err, "another state id at byte offset %u", AT_ID);
    if (payload != size - HEAD)
        return mr_derived_bad(f, err, "payload of %llu bytes at byte offset %u, the file holds %zu",
                              (unsigned long long)payload, AT_PAYLOAD_BYTES, size - HEAD);
    if (!mr_crc32_matches(mr_le_get_u32(buf + AT_PAYLOAD_CRC), buf + HEAD, size - HEAD))
        return mr_derived_bad(f, err, "payload checksum mismatch (bytes %u..%zu)", HEAD, size - 1);
    int rc = q->kind->checkpoint_load(q->geom, q->frames, buf + HEAD, size - HEAD, err);
    if (rc < 0)
        mr_error_prefix(err, "%s: ", f->name);
    return rc;
}

static int serialise(void *ctx, const uint8_t key[MR_DERIVED_KEY_BYTES], uint8_t **out, size_t *out_size,
                     mr_error *err)
{
    request *q = ctx;
    uint8_t *state = NULL;
    size_t state_size = 0;
    int rc = q->kind->checkpoint_save(q->cgeom, q->frames, &state, &state_size, err);
    if (rc < 0)
        return rc;
    uint8_t *buf = NULL;
    mr_derived_reader *check = NULL;
    if ((rc = mr_derived_buffer(&CHECKPOINT_FORMAT, (uint64_t)HEAD + state_size, &buf, &check, err)) < 0) {
        free(state);
        return rc;
    }
    mr_le_put_u64(buf + AT_FRAMES, q->frames);
    mr_le_put_u64(buf + AT_PAYLOAD_BYTES, state_size);
    memcpy(buf + HEAD, state, state_size);
    mr_le_put_u32(buf + AT_PAYLOAD_CRC, mr_crc32(buf + HEAD, state_size));
    memcpy(buf + AT_KIND, q->kind->name, strlen(q->kind->name));
    memcpy(buf + AT_ID, q->id, sizeof q->id);
    mr_derived_header_seal(&CHECKPOINT_FORMAT, key, buf);
    free(state);
    free(check);
    *out = buf;
    *out_size = HEAD + state_size;
    return MR_OK;
}

static const mr_derived_ops CHECKPOINT_OPS = {parse, serialise, NULL};

static int prepare(const char *dir, const mr_kind *k, const mr_geom *g, uint64_t frames, request *q,
                   uint8_t key[MR_DERIVED_KEY_BYTES], char **path, mr_error *err)
{
    if (!mr_checkpoint_kept(k, g, dir) || strlen(k->name) > KIND_BYTES)
        return mr_error_set(err, MR_ERR_INVALID, "kind \"%s\" keeps no checkpoints here", k->name);
    memset(q, 0, sizeof *q);
    q->kind = k;
    q->cgeom = g;
    q->frames = frames;
    k->checkpoint_id(g, q->id);
    checkpoint_key(q, key);
    return mr_derived_path(dir, key, CHECKPOINT_FORMAT.ext, path, err);
}

int mr_checkpoint_path(const char *dir, const mr_kind *k, const mr_geom *g, uint64_t frames,
                       char **path, mr_error *err)
{
    request q;
    uint8_t key[MR_DERIVED_KEY_BYTES];
    return prepare(dir, k, g, frames, &q, key, path, err);
}

int mr_checkpoint_store(const char *dir, const mr_kind *k, const mr_geom *g, uint64_t frames,
                        mr_error *err)
{
    request q;
    uint8_t key[MR_DERIVED_KEY_BYTES];
    char *path = NULL;
    struct stat sb;
    int rc = prepare(dir, k, g, frames, &q, key, &path, err);
    /* the same key holds the same state: a file already there (an earlier
     * run of the job, a replay passing it) is kept; a bad one was removed
     * when it was refused */
    if (rc == MR_OK && stat(path, &sb) != 0)
        rc = mr_derived_store(path, key, &CHECKPOINT_FORMAT, &CHECKPOINT_OPS, &q, err);
    free(path);
    return rc;
}

int mr_checkpoint_load(const char *dir, const mr_kind *k, mr_geom *g, uint64_t frames, mr_error *err)
{
    request q;
    uint8_t key[MR_DERIVED_KEY_BYTES];
    char *path = NULL;
    int rc = prepare(dir, k, g, frames, &q, key, &path, err);
    q.geom = g;
    if (rc == MR_OK) {
        rc = mr_derived_load(path, key, &CHECKPOINT_FORMAT, &CHECKPOINT_OPS, &q, err);
        /* a refused file goes, so the replay that passes its frame writes it anew */
        if (rc == MR_ERR_FORMAT)
            unlink(path);
    }
    free(path);
    return rc;
}
