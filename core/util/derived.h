/*
 * derived.h - the one derived-data cache: what a geometry kind derives from
 * an asset at a cost (baked DMMs, voxelised assets; height-texture mipmaps
 * next) is kept on disk, so it is derived once per input, not once per
 * job, and survives restarts. Simulation checkpoints (render/checkpoint.h)
 * use its keys, envelope and atomic store too.
 *
 * A kind writes only its file format (serialise, parse) and its builder;
 * this module gives it the rest, the same way for every kind:
 *  - the key: SHA-256 over a domain tag naming the kind, the format
 *    version, the builder revision and everything the builder reads
 *    (mr_derived_key_*; numbers little-endian, floats as their bits, so a
 *    key is the same on every host). Whatever is not fed in must not change
 *    the result; whatever changes the result must be fed in or bump the
 *    revision;
 *  - the path: <dir>/<lowercase hex key>.<ext> (mr_derived_path);
 *  - the envelope every such file starts with (mr_derived_format): magic,
 *    version and header size, the key the file is stored under at a fixed
 *    offset of the header, and a CRC-32 of the header as its last 4 bytes.
 *    The kind's own header fields fill the bytes in between, its payload
 *    follows with checksums of its own;
 *  - the policy (mr_derived_get): a file that is missing, unreadable, not a
 *    regular file (a FIFO is refused without blocking), too large, broken,
 *    of another version, stored under another key or refused by the kind's
 *    parser (it does not fit the request) is a miss; a miss builds and
 *    replaces the file atomically (temporary file, fsync, rename, fsync of
 *    the directory: util/file_io.h), creating the directory and its parents
 *    (mode 0755). A cache that cannot be written costs the next job a
 *    rebuild, never this job its result: only the builder's errors reach
 *    the caller. Files are never evicted.
 *
 * Every refusal is MR_ERR_FORMAT with a message "<format name>: ... at byte
 * offset N" (the path in front when read from disk), as every microray file
 * reader does.
 */
#ifndef MR_DERIVED_H
#define MR_DERIVED_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "asset/asset.h"
#include "microray.h"
#include "util/crc32.h"
#include "util/sha256.h"

/* Bytes of a cache key (a SHA-256 digest). */
#define MR_DERIVED_KEY_BYTES 32u

/* ---- the key */

typedef struct mr_derived_key_builder {
    mr_sha256_feed feed;
} mr_derived_key_builder;

/* Starts a key: the bytes of tag with its NUL (e.g. "microray svo cache":
 * one tag per kind, so two kinds never share a key), then version and
 * revision as u32. version is the file format's (a reader refuses other
 * versions anyway; in the key, an old file is a plain miss); revision is
 * the builder's, bumped whenever it produces something else for the same
 * input, so old files stop matching instead of being used as fresh. */
void mr_derived_key_begin(mr_derived_key_builder *kb, const char *tag, uint32_t version,
                          uint32_t revision);
/* Values in the order fed, little-endian; floats as their bit patterns
 * (-0 and 0 differ, as in a file). */
static inline void mr_derived_key_u32(mr_derived_key_builder *kb, uint32_t v)
{
    mr_sha256_feed_u32(&kb->feed, v);
}
static inline void mr_derived_key_u64(mr_derived_key_builder *kb, uint64_t v)
{
    mr_sha256_feed_u64(&kb->feed, v);
}
static inline void mr_derived_key_f32s(mr_derived_key_builder *kb, const float *v, size_t n)
{
    mr_sha256_feed_f32s(&kb->feed, v, n);
}

/* Parts of a mesh a builder may read, as bits of a presence word. */
#define MR_DERIVED_POSITIONS 1u /* 3 f32 per vertex */
#define MR_DERIVED_NORMALS 2u   /* 3 f32 per vertex */
#define MR_DERIVED_INDICES 4u   /* 3 u32 per triangle */
#define MR_DERIVED_SKIN 8u      /* MR_MAX_INFLUENCES u16 joints, then as many f32 weights, per
                                   vertex; only when mr_derived_mesh_skinned */

/* The rule every builder reads joints and weights by: a joint count and
 * both arrays. */
bool mr_derived_mesh_skinned(const mr_mesh *m);
/* Which of parts m has (an array present; SKIN: mr_derived_mesh_skinned). */
unsigned mr_derived_mesh_parts(const mr_mesh *m, unsigned parts);
/* m's vertex, triangle and joint counts, u32 each. */
void mr_derived_key_mesh_counts(mr_derived_key_builder *kb, const mr_mesh *m);
/* Those of parts m has (mr_derived_mesh_parts), in the order positions,
 * normals, indices, joints, weights. Say what is present in the key too
 * (the counts, a presence word) when a part may be absent. */
void mr_derived_key_mesh_arrays(mr_derived_key_builder *kb, const mr_mesh *m, unsigned parts);
/* The node count (u64), then per node its parent (i32 as u32, -1 for a
 * root) and rest transform (16 f32, mr_mat4.m order). */
void mr_derived_key_nodes(mr_derived_key_builder *kb, const mr_asset *asset);
/* A kind's parameter block (values of table t): every field in table
 * order, INT/ENUM as u32, NUMBER as f32, BOOL as u32 0/1, VEC3 3 f32,
 * QUAT 4 f32, TRANSFORM 16 f32, FLAG_OBJECT its flag then its sub table,
 * ARRAY its count (u64) then each element; POSE fields are not fed (a
 * builder that reads poses feeds them itself). */
void mr_derived_key_params(mr_derived_key_builder *kb, const mr_param_table *t, const void *values);
/* Raw bytes (a digest of something else, a name). */
static inline void mr_derived_key_bytes(mr_derived_key_builder *kb, const void *data, size_t size)
{
    mr_sha256_feed_bytes(&kb->feed, data, size);
}
/* The key; kb is spent. */
void mr_derived_key_end(mr_derived_key_builder *kb, uint8_t key[MR_DERIVED_KEY_BYTES]);

/* ---- the path */

/* "<dir>/<64 lowercase hex digits>.<ext>", malloc'ed into *path (NULL on
 * failure). MR_ERR_INVALID without a directory, key or ext. */
int mr_derived_path(const char *dir, const uint8_t key[MR_DERIVED_KEY_BYTES], const char *ext,
                    char **path, mr_error *err);

/* ---- the envelope */

/* Header bytes the envelope itself uses at fixed places: magic 0..7,
 * version at 8, header_bytes at 12 (the format's fields start at 16), the
 * key at key_at, the header CRC-32 at header_bytes - 4. */
#define MR_DERIVED_AT_VERSION 8u
#define MR_DERIVED_AT_HEADER_BYTES 12u
#define MR_DERIVED_AT_FIELDS 16u

/* One file format, as a static constant of its kind. */
typedef struct mr_derived_format {
    const char *name;      /* starts its messages: "svo file" */
    const char *ext;       /* file name extension without the dot: "mrsvo" */
    uint8_t magic[8];
    uint32_t version;      /* the layout's; changes with any layout change */
    uint32_t header_bytes; /* the header CRC-32 is its last 4 bytes */
    uint32_t key_at;       /* offset of the key: MR_DERIVED_AT_FIELDS or later, and the key
                              ends at or before the CRC (mr_derived_buffer checks) */
    uint64_t max_bytes;    /* largest file read from disk or written */
} mr_derived_format;

/* A format parser's state. One parser serves both directions: a read
 * keeps what it parses, a writer runs it over the bytes it just produced
 * (keep false) so it can never store a file its reader refuses (a cache
 * entry that never loads would make every job rebuild, silently). */
typedef struct mr_derived_reader {
    const mr_derived_format *format;
    const uint8_t *buf;
    size_t size;
    bool keep;           /* build the result, or only check (a parser may build anyway) */
    mr_error *err;
} mr_derived_reader;

/* MR_ERR_FORMAT with "<f->name>: <message>" (a parser's one way to fail). */
int mr_derived_bad(const mr_derived_format *f, mr_error *err, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 3, 4)))
#endif
    ;

/* Runs parse(r, out) over size bytes at buf with a reader that keeps what
 * it parses. MR_ERR_INVALID when buf is NULL but size is not, else parse's
 * result. */
int mr_derived_parse(const mr_derived_format *f, const uint8_t *buf, size_t size,
                     int (*parse)(mr_derived_reader *r, void *out), void *out, mr_error *err);
/* Checks the header at r->buf in this order: size, magic, version,
 * header_bytes, header CRC (the message names the offset of each). The key
 * is not compared: any key reads; mr_derived_load compares it. */
int mr_derived_header_check(mr_derived_reader *r);

/* A writer's start: a zeroed buffer of size bytes (*buf) and a reader over
 * it that only checks (*check, keep false), with which the writer reads
 * its bytes back through the format's parser. The caller frees both. MR_ERR_LIMIT above f->max_bytes (no reader
 * would take it), MR_ERR_INVALID for a format constant whose key does not
 * fit its header or a size below the header, MR_ERR_NOMEM. */
int mr_derived_buffer(const mr_derived_format *f, uint64_t size, uint8_t **buf,
                      mr_derived_reader **check, mr_error *err);
/* Writes magic, version, header_bytes, key (NULL: all zero) and, last, the
 * header CRC into buf (at least header_bytes): call it after the format's
 * own header fields are in place. */
void mr_derived_header_seal(const mr_derived_format *f, const uint8_t *key, uint8_t *buf);
/* What a writer returns when its bytes fail its read-back (rc from the
 * parser): the message gets "<name> write: would not read back: " in front
 * and MR_ERR_FORMAT becomes MR_ERR_INVALID (the data, not a file, is bad). */
int mr_derived_readback_failed(const mr_derived_format *f, int rc, mr_error *err);

/* ---- the cache */

/* The kind's side, each with the kind's request and result in ctx. */
typedef struct mr_derived_ops {
    /* Parses and fully validates a whole file whose envelope (size, magic,
     * version, header_bytes, header CRC, key) has been checked, keeps the
     * result in ctx, and checks that it answers ctx's request (e.g. fits
     * the asset). Anything but MR_OK is a miss, and then ctx must be as
     * before: nothing half-kept. */
    int (*parse)(void *ctx, const uint8_t *buf, size_t size, mr_error *err);
    /* The file of ctx's result, with key in its header, into a malloc'ed
     * buffer (*buf owned by the caller). Never run on a failed build. */
    int (*serialise)(void *ctx, const uint8_t key[MR_DERIVED_KEY_BYTES], uint8_t **buf,
                     size_t *size, mr_error *err);
    /* Derives the result into ctx from scratch; its errors are the
     * caller's. */
    int (*build)(void *ctx, mr_error *err);
} mr_derived_ops;

/* Reads the file at path and, when its envelope checks out and it is
 * stored under key, runs ops->parse over it (key NULL: any key; what a
 * format's own "read a file" is). MR_ERR_IO: no such file, or it cannot be
 * read, or is not a regular file (never blocks on a FIFO); MR_ERR_FORMAT:
 * larger than f->max_bytes (refused before reading), a defect, another key;
 * else parse's error. Messages start with the path. */
int mr_derived_load(const char *path, const uint8_t key[MR_DERIVED_KEY_BYTES],
                    const mr_derived_format *f, const mr_derived_ops *ops, void *ctx,
                    mr_error *err);
/* Writes size bytes to path atomically (util/file_io.h: temporary file in
 * the same directory, fsync, rename over path, fsync of the directory; mode
 * 0644). The directory must exist. MR_ERR_IO names the failing step. */
int mr_derived_write(const mr_derived_format *f, const char *path, const uint8_t *buf,
                     size_t size, mr_error *err);
/* Stores ctx's result at path under key: ops->serialise, the envelope
 * checked again (MR_ERR_INVALID if what serialise made would never be found
 * under key), path's directory made with its parents (mode 0755), then
 * mr_derived_write. MR_ERR_IO when the directory cannot be made or the file
 * written. */
int mr_derived_store(const char *path, const uint8_t key[MR_DERIVED_KEY_BYTES],
                     const mr_derived_format *f, const mr_derived_ops *ops, void *ctx,
                     mr_error *err);
/* The result for key through the cache in dir: a hit (mr_derived_load of
 * mr_derived_path(dir, key, f->ext) succeeds) leaves it in ctx by
 * ops->parse; a miss runs ops->build and, if it succeeds, mr_derived_store.
 * dir NULL or "": no cache, build only. *hit (may be NULL) says which. Only
 * build's errors are returned: a miss and a failed store are silent. */
int mr_derived_get(const char *dir, const uint8_t key[MR_DERIVED_KEY_BYTES],
                   const mr_derived_format *f, const mr_derived_ops *ops, void *ctx, bool *hit,
                   mr_error *err);

#endif /* MR_DERIVED_H */
