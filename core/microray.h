/*
 * microray.h - the public API of libmicroray, the core renderer.
 *
 * This is the one core header that server/ (the daemon and the one-shot
 * command) and the benchmarks include: everything they may use from
 * core is declared here, and nothing here names an Embree, assimp or OpenEXR
 * type. The module headers beside the code (util/, math/, asset/, anim/,
 * kinds/, render/) include this file and add what only core itself (and the
 * tests, which may look inside) uses; each thing is declared once, here or
 * there. scripts/check-layout.sh fails a server/ file that includes any other
 * core header.
 *
 * What a client does: parse a job into the plain structs of the "Jobs"
 * section (no JSON in core: server/job_json.c does that, reading each kind's
 * block from its parameter table), import its assets (mr_asset_load and
 * mr_refine_asset), make a renderer on a device and render frame by frame
 * into a film, then write the film as EXR and the mr_frame_stats through the
 * field table.
 *
 * Sections, in order: errors; utilities (clock, hex, copies, SHA-256, files,
 * cores); math value types; film, comparison, EXR; device; assets; kinds and
 * parameter tables; jobs; frame statistics; renderer.
 *
 * Conventions (see ../shared/ARCHITECTURE.md):
 *  - public names are mr_<noun>_<verb>(); mr_x_new() / mr_x_free() pairs;
 *    handles (mr_device, mr_asset, mr_kind, mr_renderer) are opaque, their
 *    accessors are functions; plain data (jobs, films, stats, tables) are
 *    structs with public fields;
 *  - functions that can fail return int: MR_OK (0) or a negative mr_err, and
 *    write a human-readable message into the caller's mr_error; predicates
 *    return bool; there is no global error state;
 *  - free functions accept NULL.
 */
#ifndef MICRORAY_H
#define MICRORAY_H

#include <stdatomic.h>
#include <stdbool.h>
#include <stddef.h>
#include <math.h>
#include <stdint.h>

#define MR_VERSION_STRING "0.1.0"

/* ==== Errors ============================================================== */

/* Error codes. Negative so "if (rc < 0)" reads naturally. */
typedef enum mr_err {
    MR_OK = 0,
    MR_ERR_NOMEM = -1,     /* allocation failed */
    MR_ERR_INVALID = -2,   /* bad argument or bad input data */
    MR_ERR_IO = -3,        /* file could not be read or written */
    MR_ERR_FORMAT = -4,    /* file read but its content is broken or unsupported */
    MR_ERR_EMBREE = -5,    /* Embree reported an error */
    MR_ERR_LIMIT = -6,     /* a documented size cap was exceeded */
    MR_ERR_CANCELLED = -7, /* the caller asked to stop */
    MR_ERR_NOT_FOUND = -8, /* a named thing (clip, joint, node, job, asset) does not exist */
    MR_ERR_CONFLICT = -9,  /* the request contradicts stored state (e.g. idempotency key reuse) */
    MR_ERR_NO_SPACE = -10, /* a write failed for want of disk space (ENOSPC, EDQUOT, SQLITE_FULL) */
    MR_ERR_CRASHED = -11   /* the process doing the work died (a crash, a kill, a memory limit) */
} mr_err;

/* Where a failing call leaves its message. Callers own it (often on the stack). */
typedef struct mr_error {
    int code;       /* the mr_err returned */
    char msg[512];  /* NUL-terminated, never empty after a failure */
} mr_error;

/* Records code and a printf-style message in err (which may be NULL); returns code. */
int mr_error_set(mr_error *err, int code, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 3, 4)))
#endif
    ;

/* Puts a printf-style prefix in front of the message already in err (for
 * adding where a failure happened, e.g. a JSON pointer); keeps the code and
 * returns it. */
int mr_error_prefix(mr_error *err, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 2, 3)))
#endif
    ;

/* Static name of an error code, e.g. "MR_ERR_FORMAT". */
const char *mr_err_name(int code);

/* ==== Utilities =========================================================== */

/* ---- clock (util/clock.c) ----
 * The one clock every duration in microray is measured with: frame stats,
 * asset import and cache savings, request log lines, event stream
 * keepalives, benchmarks and the tests' timings. It is CLOCK_MONOTONIC,
 * which never jumps when the wall clock is set, so the difference of two
 * readings is always an elapsed time. (Timestamps people read, such as a
 * job's "created", are wall-clock time and not from here.) */

/* Monotonic clock, seconds (nanosecond resolution). */
double mr_now(void);
/* "1.5 GiB", "320.0 KiB", "12 bytes" (binary units, one decimal). */
#define MR_BYTES_TEXT 24
void mr_format_bytes(size_t bytes, char *out, size_t size);
/* t (unix seconds) as RFC 3339 in UTC with milliseconds,
 * "2025-01-31T09:05:03.250Z"; false (out untouched) for times before 1970,
 * after 9999 or a buffer too small. */
bool mr_format_rfc3339(double t, char *out, size_t size);
/* The same clock in whole milliseconds, for integer deadlines. */
int64_t mr_now_ms(void);

/* ---- hex (util/hex.c) ----
 * Bytes as lowercase hexadecimal, and the check for it: SHA-256 digests
 * become asset ids, idempotency body hashes and the file names of the
 * derived-data caches; random bytes become job ids. Ids arrive back in URLs
 * and job documents, and only exact lowercase hex is ever turned into a
 * path, so the spelling is checked by one function too. */

/* Writes 2 * n lowercase hex digits of bytes[0, n) and a NUL into out
 * (2 * n + 1 bytes). */
void mr_hex_encode(const void *bytes, size_t n, char *out);

/* Whether s is exactly `digits` characters of 0-9a-f (false for NULL, for
 * uppercase, and for shorter or longer strings). */
bool mr_hex_is_lower(const char *s, size_t digits);

/* ---- copies (util/dup.c) ----
 * malloc'ed copies of strings and byte ranges: names and arrays copied
 * between assets, meshes and rigs, and text columns read out of sqlite.
 * Plain C11 has no strdup, and copies that must also work on a range that
 * is not NUL-terminated were written again in every module. Every result
 * is the caller's to free. */

/* A copy of the string s; NULL for a NULL s or when out of memory. */
char *mr_strdup(const char *s);

/* A copy of bytes [src, src + n); NULL for a NULL src, for n == 0 (there
 * is nothing to own) or when out of memory. */
void *mr_memdup(const void *src, size_t n);

/* The n bytes at src followed by a NUL, as a string; the bytes are copied
 * as they are (a NUL among them is copied too). src may be NULL when n is
 * 0, which gives "". NULL only when out of memory. */
char *mr_memdup_str(const void *src, size_t n);

/* ---- SHA-256 (util/sha256.c) ----
 * FIPS 180-4, for content-addressed assets, idempotency body hashes and
 * the keys of the derived-data disk caches (util/sha256.h adds the
 * little-endian number feed those keys are hashed with). Written from the
 * standard; no dependency. */

typedef struct mr_sha256 {
    uint32_t h[8];
    uint64_t length;     /* bytes hashed so far */
    uint8_t block[64];
    size_t used;         /* bytes in block */
} mr_sha256;

void mr_sha256_init(mr_sha256 *s);
void mr_sha256_update(mr_sha256 *s, const void *data, size_t size);
void mr_sha256_final(mr_sha256 *s, uint8_t digest[32]);
/* One-shot: lowercase hex digest of data into hex (65 bytes with the NUL). */
void mr_sha256_hex(const void *data, size_t size, char hex[65]);

/* ---- files (util/file_io.c) ----
 * The whole-file reads, crash-safe writes, mkdir -p and removal of
 * microray's file formats, disk caches (baked DMMs, .mrdmm, .mrsvo) and
 * the daemon's files, in one place so every file gets the same guarantees:
 *  - a read never blocks on a FIFO planted under the name, refuses
 *    anything but a regular file, and refuses a file above the format's
 *    cap before allocating for it;
 *  - a write never leaves a half-written file under the final name, even
 *    after a crash, and two writers of the same name never collide.
 * The server writes through these too (frames, uploads, stats.json, port
 * files); server/files.h keeps only its NUL-terminated job-file read.
 * `what` starts every error message ("svo file", "dmm cache", ...). */

/* Directory part of path, malloc'ed: "." without a slash, "/" for "/x".
 * NULL when out of memory. */
char *mr_fs_dir_of(const char *path);

/* mkdir -p dir with mode 0755; existing directories are fine. A directory
 * it creates is durable when it returns (its parent is fsynced), so a file
 * renamed into it later survives a crash too. MR_ERR_INVALID for an empty
 * name; MR_ERR_IO when a component cannot be made or dir is not a directory
 * in the end. */
int mr_fs_make_dirs(const char *dir, const char *what, mr_error *err);

/* The one atomic write of microray (core formats, caches, frames, uploads,
 * stats.json, port files): bytes go to a unique <path>.tmpXXXXXX in the
 * target's directory (mode 0644; two writers of one target never share a
 * temporary), which appears under the final name only by commit: fsync of
 * the file, rename, fsync of the directory so the rename survives a crash.
 * Nothing half-written is ever visible under the final name, and the
 * temporary never outlives a failed or aborted write. For writers that
 * stream (EXR encoding, uploads whose name is their hash):
 *     mr_fs_atomic a;
 *     begin(&a, path) -> write(&a, ...) or write(2) to a.fd ... ->
 *     commit(&a, NULL or another name in the same directory) | abort(&a)
 * Every error names `what` and the file, and the failing step. */
typedef struct mr_fs_atomic {
    int fd;     /* the temporary, open for writing; -1 once ended */
    char *tmp;  /* its name */
    char *path; /* the target given to begin */
    char *dir;  /* the directory of both */
} mr_fs_atomic;

/* Creates the temporary next to path. On failure *a needs no abort. */
int mr_fs_atomic_begin(mr_fs_atomic *a, const char *path, const char *what, mr_error *err);
/* Appends size bytes to the temporary (retrying short writes). */
int mr_fs_atomic_write(mr_fs_atomic *a, const void *buf, size_t size, const char *what,
                       mr_error *err);
/* fsync, close, rename onto path (NULL: begin's path; otherwise a name in
 * the same directory), fsync of the directory. Ends the write either way:
 * on failure the temporary is removed and the target untouched. */
int mr_fs_atomic_commit(mr_fs_atomic *a, const char *path, const char *what, mr_error *err);
/* Ends an unfinished write: closes and removes the temporary. Safe on an
 * ended or zeroed-after-failed-begin *a. */
void mr_fs_atomic_abort(mr_fs_atomic *a);

/* begin + write + commit of one buffer. */
int mr_fs_write_atomic(const char *path, const void *buf, size_t size, const char *what,
                       mr_error *err);

/* Whether `name` in the directory dirfd is a temporary of these writes
 * ("<target>.tmpXXXXXX") that no live writer holds (its writer was killed:
 * each writer holds a lock on its temporary until the write ends); its
 * target in *target (size bytes) when so. */
bool mr_fs_atomic_abandoned(int dirfd, const char *name, char *target, size_t size);

/* Removes the files in dir, then dir itself; a missing dir is fine. A file
 * that appears while it is emptied (a writer racing the removal) keeps the
 * directory without an error: that writer owns cleaning up after itself.
 * MR_ERR_IO naming the first entry that could not be removed. */
int mr_fs_remove_dir(const char *dir, mr_error *err);

/* Reads the whole regular file path (at most max bytes) into a malloc'ed
 * buffer (*buf, *size; a 0-byte file gives a 1-byte allocation). A file
 * that shrinks while read comes back shorter: the caller's parser then
 * sees the truncated file it now is. MR_ERR_IO: cannot open or read, not a
 * regular file (FIFOs are refused without blocking); MR_ERR_FORMAT: larger
 * than max, refused before reading; MR_ERR_NOMEM. */
int mr_fs_read_capped(const char *path, uint64_t max, uint8_t **buf, size_t *size,
                      const char *what, mr_error *err);

/* ---- the heap between frames (util/heap.c) ---- */

/* For a process that renders frames (microrayd's render commands, the
 * benchmarks): memory freed at the end of a frame stays in the process for
 * the next frame instead of going back to the system and being faulted in
 * again page by page (with glibc; elsewhere these do nothing). Call
 * mr_heap_keep_freed once before rendering and mr_heap_release after a job:
 * it hands back what is free once that passes 256 MiB (less is kept for
 * the next job). Process-wide: a library host decides. */
void mr_heap_keep_freed(void);
void mr_heap_release(void);

/* ---- cores and the parallel loop (util/parallel.c) ---- */

/* Most workers one parallel loop starts (and the cap on configured threads). */
#define MR_MAX_THREADS 256

/* Number of online cores (at least 1), as the process first asked. */
unsigned mr_cpu_count(void);

/* The one way microray uses several cores: mr_parallel_for splits [0,
 * count) into chunks of `grain` items run by `threads` workers (the
 * calling thread is one of them; 0: all online cores), each taking the
 * chunks of its own contiguous share first and then any left in the
 * others' (so successive loops over the same items mostly run where they
 * ran before, on data in that core's cache), and
 * falls back to running everything on the caller when threads cannot be
 * started. fn gets a half-open range and the worker's index in [0,
 * threads). Work must be independent per item, so results do not depend
 * on the thread count or the order chunks are taken in (what keeps frames
 * bit-identical for any thread count). */
typedef void (*mr_range_fn)(void *ctx, size_t begin, size_t end, unsigned worker);
void mr_parallel_for(unsigned threads, size_t count, size_t grain, mr_range_fn fn, void *ctx);
/* The workers are a pool started on first use and kept (sleeping when
 * idle) for the process' life, one loop on it at a time:
 *  - a call while another thread's loop runs on the pool runs on threads
 *    started for that call (two renderers in one process each get theirs);
 *  - a call from inside fn of a loop that runs on several threads runs
 *    serially on the calling thread (worker 0): the outer loop already
 *    has the threads, and waiting for the pool from its own task would
 *    deadlock;
 *  - the child of a fork starts a pool of its own if it calls.
 * mr_parallel_shutdown joins the pool's workers (waiting for a running
 * loop to end; a no-op from inside fn); a later call starts them again.
 * mr_parallel_use_pool(false) makes every call start and join threads of
 * its own, the way before the pool (benchmarks compare the two). */
void mr_parallel_shutdown(void);
void mr_parallel_use_pool(bool on);

/* Peak resident set size of the process, bytes (render/renderer.c). */
uint64_t mr_peak_rss_bytes(void);

/* ==== Math value types (math/math.c; the rest is math/mr_math.h) ==========
 * Conventions, used everywhere in microray:
 *  - mr_mat4 is stored row-major (m[row*4 + col]) and applied to column
 *    vectors: p' = M p. Translation lives in m[3], m[7], m[11]. This is the
 *    layout of assimp's aiMatrix4x4 (a1..a4 is the first row), so imported
 *    matrices copy over element by element.
 *  - Quaternions are (x, y, z, w) with w the scalar part, unit length when
 *    they represent rotations; rotation of v is q v q*.
 *  - Composition reads right to left: mr_mat4_mul(A, B) applies B first.
 * Only what a job parser needs to build a job is here. */

typedef struct mr_vec3 { float x, y, z; } mr_vec3;
typedef struct mr_quat { float x, y, z, w; } mr_quat;
typedef struct mr_mat4 { float m[16]; } mr_mat4;

static inline mr_vec3 mr_v3(float x, float y, float z) { return (mr_vec3){x, y, z}; }

mr_mat4 mr_mat4_identity(void);
/* General 4x4 inverse by cofactors. Returns false (and leaves *out as identity)
 * when numerically singular: |det| <= 1e-12 * (largest |entry|)^4, or for
 * affine matrices (last row 0 0 0 1) |det| <= 1e-12 * (largest |entry| of the
 * 3x3 linear part)^3, so translation never makes a matrix "singular". */
bool mr_mat4_inverse(const mr_mat4 *a, mr_mat4 *out);
mr_vec3 mr_mat4_point(const mr_mat4 *a, mr_vec3 p);  /* w = 1, no divide */
/* T * R * S: scale first, then rotate, then translate (glTF/assimp order). */
mr_mat4 mr_mat4_from_trs(mr_vec3 t, mr_quat r, mr_vec3 s);
bool mr_mat4_is_finite(const mr_mat4 *a);

mr_quat mr_quat_identity(void);

/* Normalises the n doubles of d in place, scaling by the largest component
 * before squaring so tiny but non-zero inputs (1e-200) normalise instead of
 * underflowing to a zero length. Returns false for the zero vector. */
bool mr_normalize_d(double *d, size_t n);

/* ==== Film (render/film.c) ================================================
 * The frame buffer a render writes into: one plane per AOV channel, and
 * only the planes of the passes asked for (a job's output.aovs): the
 * integrator computes nothing for a pass the film lacks and the EXR writer
 * writes exactly the film's passes.
 *
 * Planes are row-major, row 0 at the top of the image (EXR's increasing-y
 * order). Colour is linear and premultiplied by alpha.
 *
 * The data AOVs (z, n*, p*, t*, object_id, prim_id) describe the pixel-centre
 * ray (sample 0), so two renders of the same camera compare pixel by pixel
 * whatever their sample counts; colour, alpha and the Cryptomatte coverage
 * average all samples.
 *  - z: depth of the hit in camera space: its distance from the camera's
 *    image plane along the viewing direction (the z of the camera space of
 *    OpenEXR's worldToCamera, positive in front; not the distance along the
 *    ray), the convention of OpenEXR's deep images, RenderMan, Nuke's deep
 *    nodes and Blender's Z pass. MR_DEPTH_MISS where the ray missed:
 *    farther than anything, never 0 (which reads as nearest).
 *  - nx, ny, nz: world-space shading normal, unit length, facing the camera;
 *    0 where it missed.
 *  - px, py, pz: world-space position of the hit; 0 where it missed.
 *  - tx, ty, tz: world-space shading tangent at the hit, along increasing u
 *    of the asset's texture coordinates, unit length and orthogonal to the
 *    n pass's normal (the tangent space of normal mapping: paper 001,
 *    3.3.4); 0 where it missed and where the object has none (a kind
 *    without the tangent op, a mesh without texture coordinates).
 *  - object_id: 1-based index of the job object hit, 0 = miss.
 *  - prim_id: the primitive within that object (per kind: README, "EXR
 *    frames").
 *  - crypto[layer][2k], crypto[layer][2k + 1]: Cryptomatte rank k of the
 *    layer (MR_CRYPTO_OBJECT: object names, MR_CRYPTO_ASSET: asset names):
 *    the name's hash as a float (mr_cryptomatte_float) and its coverage,
 *    the fraction of the pixel's samples that hit it; ranks by falling
 *    coverage, unused ranks 0, 0. Misses rank nothing. */

/* Caps shared by the job parser and the film allocator (documented in README). */
#define MR_MAX_RESOLUTION 8192                 /* per side, pixels */
#define MR_MAX_PIXELS (4096u * 4096u)          /* width * height */

/* Depth of a pixel whose ray missed: farther than any depth a valid job can
 * produce (coordinates are capped at 1e9) and finite, so a compositor's
 * filters and arithmetic never meet an Inf; 1e11 is also the value Blender
 * fills an empty Z pass with. */
#define MR_DEPTH_MISS 1e11f

/* The passes (output.aovs), as bits. */
typedef enum mr_aov {
    MR_AOV_RGBA = 1u << 0,        /* R G B A: colour and alpha */
    MR_AOV_Z = 1u << 1,           /* Z: camera-space depth */
    MR_AOV_N = 1u << 2,           /* N.X N.Y N.Z: world-space normal */
    MR_AOV_P = 1u << 3,           /* P.X P.Y P.Z: world-space position */
    MR_AOV_ID = 1u << 4,          /* id.object id.primitive */
    MR_AOV_CRYPTOMATTE = 1u << 5, /* CryptoObject00.R ..., CryptoAsset00.R ... */
    MR_AOV_T = 1u << 6            /* T.X T.Y T.Z: world-space shading tangent */
} mr_aov;
#define MR_AOV_COUNT 7
#define MR_AOV_ALL 0x7fu
/* What a job gets without output.aovs, and what mr_film_new allocates. */
#define MR_AOV_DEFAULT (MR_AOV_RGBA | MR_AOV_Z | MR_AOV_N | MR_AOV_ID)

/* "rgba", "z", "n", "p", "id", "cryptomatte", "t" (the job's names); NULL for
 * anything but a single bit. */
const char *mr_aov_name(mr_aov aov);
/* The bit of a job name as above; false for anything else. */
bool mr_aov_parse(const char *name, mr_aov *out);

/* Cryptomatte layers and ranks (issue 13; the published Cryptomatte
 * specification 1.1). Ranks per layer are even (each EXR layer
 * <name>00, <name>01, ... holds two) and at most the specification's
 * suggested 6. */
enum { MR_CRYPTO_OBJECT = 0, MR_CRYPTO_ASSET = 1, MR_CRYPTO_LAYERS = 2 };
#define MR_CRYPTO_MAX_RANKS 6

typedef struct mr_film {
    int width, height;
    unsigned aovs;                  /* mr_aov bits: the planes below that exist */
    float *r, *g, *b, *a;           /* MR_AOV_RGBA */
    float *z;                       /* MR_AOV_Z */
    float *nx, *ny, *nz;            /* MR_AOV_N */
    float *px, *py, *pz;            /* MR_AOV_P */
    float *tx, *ty, *tz;            /* MR_AOV_T */
    uint32_t *object_id, *prim_id;  /* MR_AOV_ID */
    int crypto_ranks;               /* MR_AOV_CRYPTOMATTE: ranks per layer, else 0 */
    float *crypto[MR_CRYPTO_LAYERS][2 * MR_CRYPTO_MAX_RANKS]; /* [0, 2 * crypto_ranks) exist */
    /* The camera the film was rendered with (mr_renderer_render sets it):
     * what the EXR header's worldToCamera, worldToNDC and screen window
     * describe. Its local frame looks down -Z with +Y up. */
    bool has_camera;
    mr_mat4 camera_to_world;        /* rigid */
    float yfov;                     /* vertical field of view, radians */
    /* What the renderer knows of the planes' contents (integrator.c): the
     * blocks of pixels that hold exactly what a miss leaves there, written
     * by an earlier frame, or what mr_film_clear left. A frame writes such
     * a block again only where it hits something (or, a cleared block,
     * only the planes a miss changes), so an animation's background is
     * written once. NULL: nothing known. */
    struct mr_film_misses *misses;
    /* Whether the planes hold what mr_film_clear left and nothing since
     * (mr_film_new's films too): a first frame then leaves out a miss's
     * planes that hold its values already. The renderer and the EXR reader
     * (mr_exr_read_file) reset it. Code that writes the planes itself
     * and then renders into the film frees misses (setting it NULL) and
     * sets this false after its writes, or calls mr_film_clear (which
     * resets the planes too) before rendering. */
    bool cleared;
} mr_film;

/* Allocates a film of the passes in aovs (mr_aov bits, at least one) with
 * crypto_ranks ranks per Cryptomatte layer (rounded up to even, 2..
 * MR_CRYPTO_MAX_RANKS; ignored without MR_AOV_CRYPTOMATTE), cleared to
 * "all miss" (mr_film_clear). Fails with MR_ERR_LIMIT beyond the caps
 * above, MR_ERR_INVALID for no or unknown passes. */
int mr_film_new_aovs(int width, int height, unsigned aovs, int crypto_ranks, mr_film **out,
                     mr_error *err);
/* The same with MR_AOV_DEFAULT. */
int mr_film_new(int width, int height, mr_film **out, mr_error *err);
/* Bytes the planes of such a film take (0 for a size that is none). */
size_t mr_film_bytes(int width, int height, unsigned aovs, int crypto_ranks);
void mr_film_free(mr_film *film);
/* Resets every plane to "miss": z to MR_DEPTH_MISS, everything else 0,
 * and forgets what the renderer knew of them (misses). */
void mr_film_clear(mr_film *film);

/* ---- comparison (render/compare.c) ----
 * Error metrics between a frame and a reference frame of the same camera
 * (../shared/ARCHITECTURE.md, "Error metrics"). Every geometry kind reports
 * its accuracy with these figures.
 *
 * A pixel is "hit" when its object_id is non-zero.
 *  - coverage_pct: pixels hit in exactly one frame, as % of pixels hit in either
 *    (0 when neither frame hits anything);
 *  - depth_rmse, depth_max: RMSE and max of |Za - Zb| over pixels hit in both,
 *    divided by scene_diagonal;
 *  - normal_mean_deg, normal_max_deg: angle between the normals over pixels
 *    hit in both (acos clamped to [-1, 1]);
 *  - holes: pixels the reference b hits, together with all 8 neighbours (so
 *    not on its silhouette), that a misses: gaps inside the reference's
 *    silhouette, as opposed to a silhouette that is a little off;
 *  - strays: the converse, pixels a hits that the reference b misses,
 *    together with all 8 neighbours (so more than one pixel from b's
 *    silhouette): geometry floating beside the reference's outline, as
 *    opposed to an outline a little off. As for holes, a pixel on the
 *    frame border is never counted;
 *  - psnr_rgb: 10 log10(1 / MSE) over R, G, B of all pixels, colours clamped to
 *    [0, 1] first; reported as 999 when the images are identical (MSE = 0),
 *    which keeps JSON free of infinities;
 *  - surface_px: how far apart the two surfaces are on screen, in pixels:
 *    for every pixel p one film hits, the least over the other film's hits
 *    q within MR_SURFACE_WINDOW pixels of the screen distance (|p - q| less
 *    half a pixel for q != p: the other's edge lies between the centres) plus
 *    their depth difference beyond the depths the two pixels span (half the
 *    largest depth step to a neighbour: a surface at a grazing angle steps
 *    far in depth from pixel to pixel), in pixels at p's depth (as a
 *    tolerance projects a distance); the largest over both films. Equal
 *    films give 0; a surface moved by d pixels on screen gives about d (to
 *    within half a pixel), at silhouettes too; one moved by e along the view gives e in pixels at its
 *    depth. Near depth edges it reads up to a pixel low (the span there
 *    covers both sides). A pixel with no hit of the other within the window
 *    counts MR_SURFACE_WINDOW + 1. Films without a camera (or depth): 0.
 *    This is the figure a level-of-detail tolerance ("tolerance_px") is
 *    held to. */

#define MR_PSNR_IDENTICAL 999.0
#define MR_SURFACE_WINDOW 8

typedef struct mr_compare_result {
    size_t pixels;            /* width * height */
    size_t hit_either, hit_both, hit_one;
    size_t holes, strays;
    double coverage_pct;
    double depth_rmse, depth_max;  /* relative to scene_diagonal */
    double normal_mean_deg, normal_max_deg;
    double psnr_rgb;
    double surface_px;
} mr_compare_result;

/* A way to look at a film's surface between its pixel centres: the depth
 * (as the z pass: camera-space, along the view) its scene shows at film
 * position (px, py) in pixels ((0, 0) the top-left corner, pixel x covering
 * [x, x + 1)), or 0 or less where it shows nothing. */
typedef struct mr_surface_probe {
    double (*depth_at)(void *ctx, double px, double py);
    void *ctx;
} mr_surface_probe;

/* Fails with MR_ERR_INVALID when sizes differ or scene_diagonal is not a
 * positive finite number. */
int mr_film_compare(const mr_film *a, const mr_film *b, double scene_diagonal,
                    mr_compare_result *out, mr_error *err);

/* mr_film_compare with probes of the films' scenes (either NULL: none) for
 * surface_px: a pixel of one film whose nearest match among the other's
 * pixel centres is more than a quarter pixel away is looked for again
 * between them, on a grid of quarter pixels. Thin parts (a limb a
 * fraction of a pixel wide, far away) cover pixel centres here and there,
 * so the nearest centre they cover can lie pixels away from a surface
 * that moved by less than one. The renderer's reference passes probe both
 * scenes; mr_film_compare (two EXR files, no scene) passes none. */
int mr_film_compare_probed(const mr_film *a, const mr_film *b, double scene_diagonal,
                           const mr_surface_probe *probe_a, const mr_surface_probe *probe_b,
                           mr_compare_result *out, mr_error *err);

/* Isolated dark pixels of one frame (speckles: shadow acne, pinholes,
 * floating dark pixels; issue 13). An interior pixel is one whose 8
 * neighbours all hit one object (whatever the pixel itself hits); it is a
 * speckle when its luminance (Rec. 709 weights of the linear colour) is
 * below 0.6 times the median of theirs (the mean of the 4th and 5th of the
 * eight; a NaN colour reads as black). speckle_pct = 100 speckles /
 * interior (0 without interior pixels). Frame borders are never interior. */
typedef struct mr_speckle_result {
    size_t interior, speckles;
    double speckle_pct;
} mr_speckle_result;
#define MR_SPECKLE_RATIO 0.6
void mr_film_speckles(const mr_film *f, mr_speckle_result *out);

/* ---- EXR (render/exr.c, through the OpenEXR 3 C API) ----
 * A frame is one scanline part with the channels of the film's passes (EXR
 * stores them sorted by name; we always match channels by name, never by
 * position):
 *   R G B A            HALF   linear, premultiplied colour (rgba)
 *   Z                  FLOAT  camera-space depth, MR_DEPTH_MISS = miss (z)
 *   N.X N.Y N.Z        FLOAT  world-space normal (n; HALF with half_normals)
 *   P.X P.Y P.Z        FLOAT  world-space position (p)
 *   T.X T.Y T.Z        FLOAT  world-space unit shading tangent, 0 = none (t)
 *   id.object          UINT   1-based object index, 0 = miss (id)
 *   id.primitive       UINT   primitive index within the object (id)
 *   CryptoObject00.R .. CryptoObjectNN.A, CryptoAsset00.R .. CryptoAssetNN.A
 *                      FLOAT  Cryptomatte (id, coverage) rank pairs of object
 *                             and asset names (cryptomatte)
 * and header attributes (string unless noted):
 *   microray.version, microray.job, microray.frame (int), microray.time
 *   (double, seconds on the job's timeline), microray.renderSeconds (double),
 *   microray.sceneDiagonal (float: bounding-box diagonal of the scene, the
 *   unit depth errors are expressed in);
 *   the standard ones a compositor reads: worldToCamera and worldToNDC
 *   (m44f, OpenEXR's row-vector convention: p' = p M; camera space is
 *   OpenEXR's, +x right, +y up, +z the viewing direction, so the z of a
 *   point in front is its depth Z; NDC (0, 0) is the display window's top
 *   left and (1, 1) its bottom right, reached after the divide by w),
 *   screenWindowWidth (float, the image's width on the z = 1 plane of
 *   camera space) and screenWindowCenter (v2f, 0 0) when the film has a
 *   camera; pixelAspectRatio (float, 1); chromaticities (linear Rec. 709
 *   primaries and D65 white, as rendered); framesPerSecond (rational),
 *   owner, comments, capDate ("YYYY:MM:DD hh:mm:ss", local time) and
 *   utcOffset (float, seconds: UTC = local time + utcOffset) from the
 *   meta; and per Cryptomatte layer cryptomatte/<key>/name, hash
 *   ("MurmurHash3_32"), conversion ("uint32_to_float32") and manifest
 *   (JSON: name -> 8 hex digits of the float's bits), key being the first 7
 *   hex digits of the layer name's hash. */

typedef enum mr_compression {
    MR_COMPRESSION_NONE = 0,
    MR_COMPRESSION_ZIP,   /* 16 scanlines per chunk */
    MR_COMPRESSION_ZIPS,  /* 1 scanline per chunk */
    MR_COMPRESSION_PIZ
} mr_compression;

#define MR_ZIP_LEVEL_DEFAULT 4
/* ZIP/ZIPS levels below this deflate with microray's own encoder (one
 * setting: the levels below give the same bytes), fast on rendered frames;
 * this level and above with libdeflate's general match finder at that
 * level, several times slower (README, "EXR encode"). */
#define MR_ZIP_LEVEL_LIBDEFLATE 6

typedef struct mr_exr_options {
    mr_compression compression;
    int zip_level; /* 1..9, used by ZIP/ZIPS; 0 means MR_ZIP_LEVEL_DEFAULT */
    /* Threads that encode (pack + compress) chunks; 0 = all online cores,
     * values above 256 act as 256. The written bytes are the same for every
     * value, so this is purely a speed setting. */
    unsigned threads;
    /* N.X N.Y N.Z as HALF (11 significant bits: directions to about 0.03
     * degrees) instead of FLOAT: 6 bytes a pixel less to store and encode. */
    bool half_normals;
} mr_exr_options;

struct mr_job;
struct mr_frame_stats;

typedef struct mr_exr_meta {
    char job[128];          /* job name or id, may be empty */
    int frame;              /* frame index within the job */
    double time;            /* frame time on the job's timeline, seconds */
    double render_seconds;  /* wall time spent rendering this frame */
    float scene_diagonal;   /* > 0 */
    double fps;             /* framesPerSecond (as the nearest rational); 0: not written */
    int64_t capture_time;   /* Unix seconds: capDate and utcOffset; 0: not written */
    char owner[64];         /* owner; "": not written */
    /* The job the frame belongs to: the comments and the Cryptomatte
     * manifests (its objects' and assets' names). May be NULL; borrowed. */
    const struct mr_job *source;
} mr_exr_meta;

/* The meta of frame st->frame of job as the renderers write it: the stats'
 * time, render seconds and scene diagonal, the job's name and fps, the
 * job itself (comments, manifests), the current time as capture time and
 * the user the process runs as as owner. */
void mr_exr_meta_for_frame(mr_exr_meta *meta, const struct mr_job *job,
                           const struct mr_frame_stats *st);

/* Name of a compression as used in jobs ("none", "zip", "zips", "piz"). */
const char *mr_compression_name(mr_compression c);
/* Parses a name as above; returns false for anything else. */
bool mr_compression_parse(const char *name, mr_compression *out);

/* opt may be NULL (same as a zeroed struct: no compression, default level,
 * all cores, float normals);
 * meta may be NULL (only microray.version and the film's own attributes
 * are written). The channels are the film's passes. NaN/Inf pixels are
 * written as finite values (colour and half normals as above; Z, N and P:
 * NaN -> 0, +-Inf -> +-FLT_MAX). */

/* Writes film to path atomically (mr_fs_atomic: a unique temporary next to
 * path, fsynced and renamed over it on success, then the directory synced),
 * so nobody sees a partial frame, a failed write leaves an existing file at
 * path untouched and a crash loses no finished frame. */
int mr_exr_write_file(const char *path, const mr_film *film, const mr_exr_options *opt,
                      const mr_exr_meta *meta, mr_error *err);
/* Writes film into a malloc'ed buffer (*data, *size); caller frees *data. */
int mr_exr_write_memory(uint8_t **data, size_t *size, const mr_film *film,
                        const mr_exr_options *opt, const mr_exr_meta *meta, mr_error *err);
/* Reads a microray EXR (any compression the library decodes) into a new film
 * holding MR_AOV_DEFAULT's passes and any other pass the file has channels
 * of; planes the file lacks stay "miss" (mr_film_clear); the camera is not
 * read back. meta may be NULL (fps, capture time, owner and source are left
 * 0). Fails with MR_ERR_FORMAT for files that are not scanline EXR images. */
int mr_exr_read_file(const char *path, mr_film **out, mr_exr_meta *meta, mr_error *err);

/* ---- PNG previews and contact sheets (render/preview.c, Debian's libpng) ----
 * 8-bit sRGB pictures of a film's beauty pass (R, G, B, A only: no other
 * AOV is read, so they work whatever passes a frame has) for people to look
 * at; the EXR stays the frame.
 *
 * The operator, per pixel, from the film's linear premultiplied R, G, B, A
 * (the colour of a frame is linear and premultiplied; PNG alpha is straight):
 *   a = clamp(A, 0, 1)                         (NaN reads as 0)
 *   c = C / a   when 0 < a < 1                 (un-premultiplied)
 *       C       when a = 1;   0 when a = 0     (nothing there: black)
 *   colour code = round(255 * srgb(clamp(c, 0, 1)))
 *   alpha code  = round(255 * a)
 *   srgb(v) = 12.92 v                   for v <= 0.0031308
 *             1.055 v^(1/2.4) - 0.055   above (IEC 61966-2-1)
 * i.e. no exposure change and no highlight roll-off: values above 1 clip to
 * white, as in a compositor's plain sRGB view. The codes are exact up to
 * float rounding (the encoder compares c against the 255 code boundaries
 * srgb^-1((k - 0.5) / 255), computed in double and rounded to float, so a
 * value within a float ulp of a boundary may land on either side). PNGs
 * carry an sRGB chunk (perceptual intent).
 *
 * Contact sheets: thumbnails no larger than MR_THUMB_MAX_SIDE on either side
 * (the frame scaled by min(160 / width, 160 / height, 1), each side rounded
 * and at least 1), each thumbnail pixel the mean of the premultiplied
 * linear pixels of its source box [floor(x W / w), floor((x+1) W / w)) x
 * (the same in y), composited over a checkerboard of 8-pixel squares (sRGB
 * codes 153 and 102, the light one at the thumbnail's top left) in linear
 * light, so transparency shows, then encoded by srgb() as above (opaque).
 * Frames not finished are a flat grey cell (code 56) crossed by its two
 * diagonals (code 128). Cells are laid out in ceil(sqrt(n)) columns, row by
 * row, MR_SHEET_GUTTER pixels apart and from the edges, on code 16; at most
 * MR_SHEET_MAX_FRAMES frames (8 x 8) appear: a longer job shows frames
 * i (N - 1) / 63 (integer division, i = 0..63), so the first and last. */

#define MR_THUMB_MAX_SIDE 160
#define MR_SHEET_MAX_FRAMES 64
#define MR_SHEET_GUTTER 4

/* An 8-bit picture: channels 3 (RGB) or 4 (RGBA, straight alpha), row-major,
 * row 0 at the top, width * channels bytes per row. */
typedef struct mr_image8 {
    int width, height, channels;
    uint8_t *px;
} mr_image8;

/* Frees px and zeroes the struct; NULL is fine. */
void mr_image8_free(mr_image8 *img);

/* The full-size RGBA preview of film by the operator above. MR_ERR_INVALID
 * when the film has no R, G, B or A plane; MR_ERR_NOMEM. */
int mr_preview_from_film(const mr_film *film, mr_image8 *out, mr_error *err);

/* The contact-sheet thumbnail of film (RGB, opaque; see above). */
int mr_preview_thumbnail(const mr_film *film, mr_image8 *out, mr_error *err);

/* Thumbnail size of a width x height frame (both >= 1). */
void mr_preview_thumb_size(int width, int height, int *thumb_w, int *thumb_h);

/* Which frames of a job of frame_count frames a contact sheet shows:
 * writes at most MR_SHEET_MAX_FRAMES indices, ascending; returns how many. */
size_t mr_contact_sheet_frames(size_t frame_count, size_t index[MR_SHEET_MAX_FRAMES]);

/* Where cell i of a sheet of `count` cells of thumb_w x thumb_h lies. */
typedef struct mr_sheet_layout {
    int columns, rows, width, height; /* the sheet, pixels */
    int cell_w, cell_h;
} mr_sheet_layout;
void mr_contact_sheet_layout(size_t count, int thumb_w, int thumb_h, mr_sheet_layout *out);
void mr_contact_sheet_cell(const mr_sheet_layout *l, size_t i, int *x, int *y);

/* A sheet of `count` cells (1..MR_SHEET_MAX_FRAMES) of thumb_w x thumb_h,
 * every cell drawn as "not finished": RGB, background code 16. */
int mr_contact_sheet_new(size_t count, int thumb_w, int thumb_h, mr_image8 *sheet,
                         mr_error *err);
/* Copies thumb (RGB, the sheet's thumbnail size) into cell i. */
int mr_contact_sheet_put(mr_image8 *sheet, size_t i, const mr_image8 *thumb, mr_error *err);

/* PNG (8-bit, RGB or RGBA by img->channels, sRGB chunk) in a malloc'ed
 * buffer (*data, *size; caller frees). The UP filter and zlib's run-length
 * strategy: about 4x faster than libpng's defaults for files about 12 %
 * larger (measured in render/preview.c). */
int mr_png_encode(const mr_image8 *img, uint8_t **data, size_t *size, mr_error *err);
/* Decodes an 8-bit RGB or RGBA PNG without colour conversion (what
 * mr_png_encode writes; other kinds are converted to RGBA by libpng).
 * MR_ERR_FORMAT naming `what` for a damaged or truncated file. */
int mr_png_decode(const uint8_t *data, size_t size, const char *what, mr_image8 *out,
                  mr_error *err);
/* mr_preview_from_film + mr_png_encode + the atomic write of path
 * (mr_fs_write_atomic). */
int mr_png_write_film(const char *path, const mr_film *film, mr_error *err);

/* ==== Device (render/device.c; its Embree side is render/device.h) ========
 * The process-wide render device. One device is shared by every job of a
 * process (Embree devices are heavy: each owns a task scheduler). It carries
 * the worker thread count used for tracing and skinning, a memory monitor
 * that counts the bytes Embree itself allocates (its acceleration
 * structures), and the last Embree error message. */

typedef struct mr_device mr_device;

/* threads == 0: all online cores. */
int mr_device_new(unsigned threads, mr_device **out, mr_error *err);
void mr_device_free(mr_device *dev);
unsigned mr_device_threads(const mr_device *dev);

/* ==== Assets (asset/asset.c, asset/refine.c; the arrays are asset/asset.h) ==
 * Imported models: meshes, node hierarchy, skins, animation clips, cameras,
 * imported once with assimp (glTF 2.0, FBX, COLLADA, X, SMD, OBJ, PLY and
 * whatever else assimp reads) into plain arrays so nothing after the import
 * depends on assimp. */

typedef struct mr_asset mr_asset;

/* Import caps: larger files are refused with MR_ERR_LIMIT rather than
 * exhausting memory in the daemon. */
#define MR_MAX_ASSET_FILE_BYTES (2ull * 1024u * 1024u * 1024u)
#define MR_MAX_ASSET_TRIANGLES (16u * 1024u * 1024u)
#define MR_MAX_ASSET_VERTICES (16u * 1024u * 1024u)
#define MR_MAX_ASSET_NODES (1u << 20)
/* Joint indices are stored as uint16_t. */
#define MR_MAX_ASSET_JOINTS 65535u

/* Imports a model file. Broken, empty or unsupported files fail with
 * MR_ERR_FORMAT (or MR_ERR_IO when unreadable) and a message naming the
 * file; they never crash. A file without any triangles is an error, and so
 * is a non-finite vertex position (named by mesh and vertex) or a bone that
 * names no node. Files above the caps fail with MR_ERR_LIMIT. Only meshes
 * placed by a node are imported, one mesh per (node, mesh) reference;
 * points and lines are dropped. Camera yfov is converted from whatever the
 * format's importer stored in assimp's mHorizontalFOV (see asset.c). */
int mr_asset_load(const char *path, mr_asset **out, mr_error *err);
void mr_asset_free(mr_asset *asset);

/* Builds an asset from one in-memory triangle mesh (copied), with a single
 * root node. For clients with meshes of their own (tests, generated fixtures,
 * references a benchmark makes). normals may be NULL. */
int mr_asset_from_mesh(const char *name, const float *positions, const float *normals,
                       uint32_t vertex_count, const uint32_t *indices,
                       uint32_t triangle_count, mr_asset **out, mr_error *err);

/* The same triangles shaded by their facets: an asset of one mesh whose
 * triangles have corners of their own (3 per triangle) that carry the
 * triangle's unit normal ((0, 0, 1) for a degenerate one). The reference
 * for how a surface is oriented, as opposed to its interpolated vertex
 * normals: what a kind that shades micro-triangles by their own normals
 * (dmm) converges to. Errors as mr_asset_from_mesh (3 * triangle_count
 * corners count against the vertex cap). */
int mr_asset_faceted(const char *name, const float *positions, uint32_t vertex_count,
                     const uint32_t *indices, uint32_t triangle_count, mr_asset **out,
                     mr_error *err);

/* Images are assets too (height textures and tiling exemplars of the
 * displacement kinds): a file that starts with a PNG, JPEG or OpenEXR
 * signature is decoded by mr_asset_load into one channel of samples
 * instead of being handed to assimp (asset/image.h: 8 and 16 bit PNG,
 * JPEG, scanline EXR with a Y channel, R G B, or a single channel; colour
 * becomes Rec. 709 luminance). Such an asset has no meshes. Images larger
 * than these caps are refused before their pixels are allocated. */
#define MR_MAX_IMAGE_SIDE 16384u
#define MR_MAX_IMAGE_PIXELS (8192u * 8192u)
/* Whether the asset is an image; its size in pixels when it is. */
bool mr_asset_is_image(const mr_asset *asset);
bool mr_asset_image_size(const mr_asset *asset, uint32_t *width, uint32_t *height);

/* Triangles over all meshes. */
size_t mr_asset_triangle_count(const mr_asset *asset);
/* Animation clips (a job's pose names them by index or name), and the
 * length of clip i in seconds (0 for a clip it does not have): what a
 * client spreads its frame times over. */
size_t mr_asset_clip_count(const mr_asset *asset);
double mr_asset_clip_duration(const mr_asset *asset, size_t clip);
/* Bytes held by the asset's arrays. */
size_t mr_asset_memory(const mr_asset *asset);
/* Address space the import's own thread reserves for its stack (asset.c:
 * deep hierarchies recurse in assimp); memory only as deep as a file goes. */
#define MR_ASSET_IMPORT_STACK_BYTES ((size_t)1 << 30)

/* An imported asset as one flat byte string and back, for handing an
 * import from the process that did it to the one that renders (the daemon
 * imports in a child process). The blob is for the same build on the same
 * machine (native byte order and struct layout, checked by its header),
 * never stored; reading checks every length against the bytes left, so a
 * short or damaged blob is refused (MR_ERR_FORMAT), never overread. */
int mr_asset_blob_write(const mr_asset *asset, uint8_t **out, size_t *size, mr_error *err);
int mr_asset_blob_read(const uint8_t *data, size_t size, mr_asset **out, mr_error *err);

/* ---- refinement (asset/refine.h says how) ----
 * Detailed skinned meshes made from low-poly rigs: Loop subdivision plus a
 * procedural displacement, with skin weights carried along; bit-identical
 * for any thread count. */

/* Most Loop rounds one call does (each multiplies triangles by 4). */
#define MR_REFINE_MAX_ROUNDS 8
/* Most noise octaves. */
#define MR_REFINE_MAX_OCTAVES 16

typedef struct mr_refine_params {
    unsigned rounds;   /* Loop subdivision rounds, 0..MR_REFINE_MAX_ROUNDS */
    float amplitude;   /* largest displacement, mesh units; 0: no detail */
    float frequency;   /* lattice cells per mesh unit of the first octave (> 0 when amplitude != 0) */
    unsigned octaves;  /* 0 or 1: one band; k: k bands, each 2x the frequency and 1/2 the weight */
    uint32_t seed;     /* picks the noise pattern */
    unsigned threads;  /* 0: all cores */
} mr_refine_params;

/* A deep copy of in (path, nodes, clips, cameras) with every mesh replaced
 * by its refinement; mr_asset_free releases it. Fails with MR_ERR_INVALID
 * for bad params or a broken mesh and MR_ERR_LIMIT when a mesh would exceed
 * MR_MAX_ASSET_TRIANGLES / MR_MAX_ASSET_VERTICES. */
int mr_refine_asset(const mr_asset *in, const mr_refine_params *params, mr_asset **out,
                    mr_error *err);

/* ==== Kinds and parameter tables (kinds/registry.c, kinds/params.c) =======
 * A geometry kind (triangle mesh, displaced micro-mesh, voxels, ...) is an
 * opaque descriptor from the registry (its ops are kinds/kind.h). What a
 * client sees of it: its name (the job's "kind" string and its block's key),
 * a one-line summary, the parameter table of its job block and its own
 * per-frame statistics fields.
 *
 * A parameter table describes a kind's job block ("<kind>": {...}) once, as
 * data: field name, type, range or enum values, default, one-line
 * description, and where the value lives in the kind's own C struct.
 * Everything else is derived from that table:
 *   - the server reads and validates the block generically (server/
 *     job_json.c), with a JSON pointer and an "expected X, got Y" message
 *     for every bad value;
 *   - the job schema's kind blocks are generated from it (microrayd schema,
 *     `make schema`), so the schema cannot drift from the parser;
 *   - defaults are filled in and owned memory released generically
 *     (mr_params_defaults, mr_params_clear), so core/job.c knows no kind.
 * Rules a table cannot express (two fields that exclude each other, a
 * limit that depends on another field) are per-field `after` hooks, run
 * right after the field was read (or found absent), in table order, so the
 * first error in the document is the one reported.
 *
 * Storage by type: INT -> uint32_t (tables give lo >= 0), NUMBER -> float
 * (lo/hi within the float range), BOOL -> bool, ENUM -> int (index into
 * choices), TRANSFORM -> mr_mat4 (the job's transform grammar, identity by
 * default), POSE -> mr_pose_desc plus a bool at present_offset,
 * FLAG_OBJECT -> bool at offset, given as true/false or as an object of the
 * sub table's fields (stored in the same struct; the bool then becomes
 * true), ARRAY -> a pointer at offset to count elements of sub->size bytes,
 * the count a size_t at count_offset, 1..max_items of them, ASSET -> a
 * uint32_t: 0 when absent, else 1 + the index in mr_job.assets of the asset
 * the job names (a key of its "assets"; a kind reads that asset through
 * mr_kind_context.assets), NUMBERS -> float[max_items], given as an array of
 * exactly max_items numbers in lo..hi (def fills every element), VEC3 ->
 * mr_vec3 (three numbers, each in lo..hi; default def3), QUAT -> mr_quat
 * ([x, y, z, w], any non-zero length, normalised; identity by default). */

typedef enum mr_param_type {
    MR_PARAM_INT = 0,
    MR_PARAM_NUMBER,
    MR_PARAM_BOOL,
    MR_PARAM_ENUM,
    MR_PARAM_FLAG_OBJECT,
    MR_PARAM_ARRAY,
    MR_PARAM_TRANSFORM,
    MR_PARAM_POSE,
    MR_PARAM_ASSET,
    MR_PARAM_NUMBERS,
    MR_PARAM_VEC3,
    MR_PARAM_QUAT
} mr_param_type;

/* mr_param.flags: open ends of a number's range; NO_DEFAULT: the value
 * when absent depends on other fields (an after hook sets it), so the
 * schema states no default. */
enum { MR_PARAM_LO_OPEN = 1u, MR_PARAM_HI_OPEN = 2u, MR_PARAM_NO_DEFAULT = 4u };

/* At most this many fields in one table (the reader tracks them in a
 * 32-bit set). */
#define MR_PARAM_MAX_FIELDS 32u

/* What an `after` hook reports: the field the pointer should end at
 * (relative to the block; "" for the block itself), code and message. */
typedef struct mr_param_error {
    int code;
    char field[64];
    char message[256];
} mr_param_error;

typedef struct mr_param_table mr_param_table;

/* An ENUM's names in a table entry: .choices and .choice_count of a static
 * array of strings, e.g. {.type = MR_PARAM_ENUM, MR_PARAM_CHOICES(MODES)}. */
#define MR_PARAM_CHOICES(names) .choices = (names), .choice_count = sizeof(names) / sizeof((names)[0])

typedef struct mr_param {
    const char *field;
    mr_param_type type;
    size_t offset;             /* of the value in the table's struct */
    double lo, hi;             /* INT, NUMBER: range */
    unsigned flags;            /* MR_PARAM_LO_OPEN | MR_PARAM_HI_OPEN */
    const char *const *choices; /* ENUM: names in the order of the stored int */
    size_t choice_count;
    double def;                /* default: the number, 0/1, or the enum index */
    double def3[3];            /* VEC3: default */
    const char *expect;        /* "expected ..." text instead of the generated one, or NULL */
    const char *description;   /* one line, for the schema and docs */
    const char *conflicts;     /* a later field of this table that may not be given with this one */
    const mr_param_table *sub; /* FLAG_OBJECT: its object's fields; ARRAY: an element's */
    size_t present_offset;     /* POSE: bool set when the pose is given */
    size_t count_offset;       /* ARRAY: size_t element count */
    size_t max_items;          /* ARRAY: most elements; NUMBERS: the count (at most 16) */
    /* Runs after the field was read or found absent (given[i]: field i of
     * the table was in the job). Returns MR_OK or fills err and returns its
     * code. May adjust other values (a default that depends on this one). */
    int (*after)(void *values, const bool *given, mr_param_error *err);
} mr_param;

struct mr_param_table {
    const mr_param *params;
    size_t count;
    size_t size;         /* bytes of the struct the values live in */
    const char *expect;  /* what the block is: "an object of <kind> parameters" */
    const char *plural;  /* ARRAY elements, for "an array of 1..N <plural>" */
    /* The after hooks' rules as JSON Schema keywords (the members of a JSON
     * object, e.g. "if"/"then"), merged into the generated block; NULL if
     * none. Text only: core parses no JSON. */
    const char *schema_rules;
};

/* Writes every default of t into values (sub tables included). */
void mr_params_defaults(const mr_param_table *t, void *values);
/* Releases what values own (arrays and the poses inside them), leaving
 * them empty; values itself is the caller's. Accepts partially read
 * values (NULL arrays, counts set as soon as arrays exist). */
void mr_params_clear(const mr_param_table *t, void *values);
/* A table's field by name, or NULL. */
const mr_param *mr_param_find(const mr_param_table *t, const char *field);
/* Index of `field` in t, or -1. */
int mr_param_index(const mr_param_table *t, const char *field);

/* Fills err (returns code): a helper for after hooks. */
int mr_param_fail(mr_param_error *err, int code, const char *field, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 4, 5)))
#endif
    ;

/* A geometry kind: its descriptor, from the registry. */
typedef struct mr_kind mr_kind;

/* How a kind's stats field adds up over a job's objects of the kind: the
 * sum (counts, seconds, bytes) or the largest (errors, ratios); ONCE is a
 * figure of the objects' creation (a derived-data build's seconds), summed
 * and reported with the renderer's first frame only, 0 on later ones (like
 * load_s), so a sum over frames stays true. */
typedef enum mr_stat_combine { MR_STAT_SUM = 0, MR_STAT_MAX, MR_STAT_ONCE } mr_stat_combine;

/* One of a kind's own per-frame statistics fields (reported as a frame's
 * extras, see mr_frame_extra). */
typedef struct mr_kind_stat {
    const char *name;        /* stats.json key, unique among all fields */
    const char *unit;        /* "s", "count", "bytes", ... */
    const char *description; /* one line */
    mr_stat_combine combine; /* over the job's objects and frames (default: sum) */
} mr_kind_stat;

/* The registry: the built-in kinds, in a fixed order, then any added by
 * mr_kind_register (kinds/kind.h). */
size_t mr_kind_count(void);
const mr_kind *mr_kind_at(size_t i);
/* The kind named name, or NULL. */
const mr_kind *mr_kind_find(const char *name);

/* The job's "kind" string and its block's key. */
const char *mr_kind_name(const mr_kind *kind);
/* One line, for the schema and docs. */
const char *mr_kind_summary(const mr_kind *kind);
/* The fields of the kind's job block; NULL: the kind takes none. */
const mr_param_table *mr_kind_params(const mr_kind *kind);
/* The kind's own per-frame statistics fields: stat_count of them, i < count. */
/* Whether the kind keeps derived data (bakes, voxelisations) in
 * <cache root>/<its name>/. */
bool mr_kind_keeps_derived(const mr_kind *kind);
/* Whether an object of the kind may have a "pose" (a simulated kind moves
 * by itself and takes none). */
bool mr_kind_takes_pose(const mr_kind *kind);
size_t mr_kind_stat_count(const mr_kind *kind);
const mr_kind_stat *mr_kind_stat_at(const mr_kind *kind, size_t i);

/* ==== Jobs (job.c) ========================================================
 * A render job as plain C structs: what to load, how to pose it, where the
 * camera goes, which frames to render and how to write them.
 *
 * The server parses and validates job JSON (server/job_json.c) into this
 * form; core never sees JSON. Every string and array here is owned by the
 * job and released by mr_job_free(). Caps below are enforced by the parser
 * and documented in the README. */

#define MR_MAX_ASSETS 256
#define MR_MAX_OBJECTS 1024
#define MR_MAX_LIGHTS 64
#define MR_MAX_FRAMES 100000
#define MR_MAX_SPP 1024
#define MR_MAX_JOINT_OVERRIDES 1024
#define MR_MAX_JOB_TRIANGLES (32u * 1024u * 1024u) /* over all objects (each holds its own copy) */
#define MR_MAX_NAME 256         /* bytes in any name or id */
#define MR_MAX_PATH 4096        /* bytes in an asset path */
#define MR_MAX_TOLERANCE_PX 1000.0 /* "tolerance_px": pixels */

/* ---- poses (anim/pose.c; evaluation is anim/pose.h) ----
 * A pose is the global transform of every node of an asset at one instant:
 * clip keys sampled at a time (positions and scales linearly, rotations by
 * slerp; clamped to the first/last key outside their range), then explicit
 * joint overrides replace the local transform of the named nodes, then
 * globals are composed parent to child. */

/* One explicit joint transform: replaces the named node's local transform. */
typedef struct mr_joint_override {
    char *joint;   /* node name */
    mr_mat4 local; /* from TRS or a 4x4 given in the job */
} mr_joint_override;

/* How to pose an object at one frame. */
typedef struct mr_pose_desc {
    bool has_clip;
    char *clip_name;  /* NULL: use clip_index */
    int clip_index;
    bool has_time;    /* explicit clip time in seconds ... */
    double time;
    double speed;     /* ... else clip time = offset + speed * frame time */
    double offset;
    bool loop;        /* wrap clip time into [0, duration) (default), else clamp */
    size_t joint_count;
    mr_joint_override *joints;
} mr_pose_desc;

/* Frees the strings and joint overrides a pose description owns (a job's
 * parser allocates them) and zeroes it. */
void mr_pose_desc_clear(mr_pose_desc *p);

/* ---- camera paths, cameras and their rays (render/camera.c) ----
 * A camera looks down its local -Z with +Y up (glTF's convention); its
 * orientation is a unit quaternion mapping camera space to world space.
 * A path is a list of keyframes sorted by time; between keys, position is
 * interpolated linearly or with uniform Catmull-Rom (end keys duplicated as
 * their own neighbours), orientation by slerp, field of view linearly.
 * Before the first key and after the last the path holds still.
 * A key gives its orientation either as a rotation or as a target point
 * (looked at with the path's up vector); targets are turned into rotations
 * at the key, so both kinds interpolate the same way. */

#define MR_MAX_CAMERA_KEYS 10000
/* Vertical field of view when a job or a camera node does not give one. */
#define MR_DEFAULT_YFOV_DEG 45.0

typedef enum mr_interp { MR_INTERP_LINEAR = 0, MR_INTERP_CATMULL_ROM } mr_interp;

typedef struct mr_camera_key {
    double t;          /* seconds, strictly increasing along the path */
    mr_vec3 position;
    bool has_target;   /* orientation from target (else from rotation) */
    mr_vec3 target;
    mr_quat rotation;
    float yfov;        /* vertical field of view, radians, in (0, pi) */
} mr_camera_key;

typedef struct mr_camera_path {
    mr_interp interp;
    mr_vec3 up;        /* for target keys; default +Y */
    size_t key_count;  /* >= 1 */
    mr_camera_key *keys;
} mr_camera_path;

/* The camera at one instant. */
typedef struct mr_camera {
    mr_vec3 position;
    mr_quat rotation;  /* camera space to world space */
    float yfov;        /* vertical field of view, radians */
} mr_camera;

/* Camera of the path at time t. */
mr_camera mr_camera_path_eval(const mr_camera_path *path, double t);

/* A camera set up for one film size: the rays the renderer shoots (its
 * pixel-centre rays are (x + 0.5, y + 0.5)), for clients that trace the
 * same rays themselves (a baseline, a picker). Ray directions are a corner
 * plus multiples of per-pixel steps, so a ray costs a few multiply-adds and
 * one normalisation (no trigonometry per ray). */
typedef struct mr_camera_rays {
    mr_vec3 origin;
    mr_vec3 corner;  /* direction through film point (0, 0), unnormalised */
    mr_vec3 step_x;  /* change per pixel to the right */
    mr_vec3 step_y;  /* change per pixel downwards */
} mr_camera_rays;

mr_camera_rays mr_camera_rays_setup(const mr_camera *cam, int width, int height);

/* Unit direction of the ray through film point (px, py) in pixels, (0,0)
 * being the top-left corner of the image and (width, height) the
 * bottom-right one. Inline: the renderer calls it once per ray. */
static inline mr_vec3 mr_camera_rays_dir(const mr_camera_rays *r, float px, float py)
{
    float x = r->corner.x + px * r->step_x.x + py * r->step_y.x;
    float y = r->corner.y + px * r->step_x.y + py * r->step_y.y;
    float z = r->corner.z + px * r->step_x.z + py * r->step_y.z;
    float s = 1.0f / sqrtf(x * x + y * y + z * z);
    return mr_v3(x * s, y * s, z * s);
}

/* ---- the job ---- */

/* An asset's "refine" (issue 4: detailed skinned meshes made from low-poly
 * rigs by mr_refine_asset). The job allows less than refinement does:
 * each round multiplies triangles by 4, and 4 rounds already turn a
 * 5000-triangle character into 1.3 million. */
#define MR_ASSET_REFINE_MAX_ROUNDS 4u
#define MR_ASSET_REFINE_MAX_OCTAVES 8u
#define MR_ASSET_REFINE_DEFAULT_ROUNDS 2u
#define MR_ASSET_REFINE_DEFAULT_FREQUENCY 8.0f
#define MR_ASSET_REFINE_DEFAULT_OCTAVES 3u
#define MR_ASSET_REFINE_DEFAULT_SEED 1u

typedef struct mr_asset_desc {
    char *name;   /* key in the job's "assets" object */
    char *path;   /* server-side path, resolved by the server before rendering;
                     for an "id" asset the server fills in the stored file */
    char *id;     /* SHA-256 (64 hex) of an asset uploaded to the daemon, or NULL */
    bool refine;  /* "refine" given: the import is refined (mr_refine_asset) once */
    mr_refine_params refine_params; /* when refine; threads 0 (the worker sets its own) */
} mr_asset_desc;

typedef struct mr_object_desc {
    char *name;
    size_t asset;            /* index into mr_job.assets */
    const mr_kind *kind;     /* never NULL in a parsed job */
    void *params;            /* the kind's parameter struct (its table's size), owned;
                                NULL for a kind without parameters */
    mr_mat4 transform;       /* object to world, applied after posing */
    mr_vec3 color;           /* Lambert albedo, linear */
    size_t pose_count;       /* 0 = rest pose; 1 = same for every frame; else one per frame */
    mr_pose_desc *poses;
    bool reference;          /* reference passes draw it as its references (its own
                                "reference", else the job's; mr_reference_type) */
    double tolerance_px;     /* level of detail: the coarsest representation whose projected
                                error stays below this many pixels, chosen per frame (its own
                                "tolerance_px", else the job's); 0: off, the finest */
} mr_object_desc;

/* Whether the object derives data of its kind's (mr_kind_keeps_derived):
 * a mesh only with "tolerance_px" (its levels of detail). */
bool mr_object_derives(const mr_object_desc *desc);

typedef struct mr_light_desc {
    mr_vec3 direction;       /* unit; the direction light travels (sun rays) */
    mr_vec3 color;           /* linear, already multiplied by intensity */
} mr_light_desc;

typedef enum mr_camera_source { MR_CAMERA_SOURCE_PATH = 0, MR_CAMERA_SOURCE_NODE } mr_camera_source;

typedef struct mr_camera_desc {
    mr_camera_source source;
    mr_camera_path path;     /* SOURCE_PATH */
    size_t node_asset;       /* SOURCE_NODE: asset holding the camera ... */
    char *node_name;         /* ... and its camera (or node) name */
} mr_camera_desc;

typedef struct mr_output_desc {
    int width, height;       /* 1..MR_MAX_RESOLUTION, width*height <= MR_MAX_PIXELS */
    int spp;                 /* samples per pixel, 1..MR_MAX_SPP */
    bool shadows;            /* trace shadow rays to directional lights */
    uint32_t seed;           /* jitter seed */
    unsigned aovs;           /* the passes traced, kept and written: mr_aov bits (MR_AOV_DEFAULT) */
    mr_exr_options exr;
} mr_output_desc;

/* Cryptomatte ranks per layer a job's frames keep: its samples per pixel
 * (the most names a pixel can see) rounded up to even, at most
 * MR_CRYPTO_MAX_RANKS; 0 without the cryptomatte pass. */
int mr_output_crypto_ranks(const mr_output_desc *out);

#define MR_MAX_PRIORITY 1000     /* priorities run from -1000 to 1000 */
#define MR_MAX_RETRIES 10        /* per frame */

typedef struct mr_job {
    char *name;
    int priority;            /* queue order in the daemon: higher first (default 0) */
    int max_retries;         /* failed attempts allowed per frame (default 2) */
    char *notify;            /* the daemon POSTs the final state here (http(s) URL); NULL: none */
    size_t asset_count, object_count, light_count;
    mr_asset_desc *assets;
    mr_object_desc *objects;
    mr_light_desc *lights;
    mr_vec3 ambient;         /* linear radiance added to every hit */
    mr_vec3 background;      /* colour of missed samples, linear, not premultiplied */
    float background_alpha;  /* alpha of missed samples */
    mr_camera_desc camera;
    double fps;              /* frames per second of the timeline (> 0) */
    size_t frame_count;      /* 1..MR_MAX_FRAMES */
    double *frame_times;     /* seconds, one per frame */
    mr_output_desc output;
    bool reference;          /* "reference": the objects' default (mr_object_desc.reference) */
    double tolerance_px;     /* "tolerance_px": the objects' default (mr_object_desc.tolerance_px) */
} mr_job;

/* Whether any object of the job asks for reference passes. They compare
 * colour, depth, normals and ids, so such a job's output.aovs holds
 * MR_AOV_REFERENCE (the parser refuses it otherwise). */
bool mr_job_has_reference(const mr_job *job);
#define MR_AOV_REFERENCE (MR_AOV_RGBA | MR_AOV_Z | MR_AOV_N | MR_AOV_ID)

/* Refuses (MR_ERR_LIMIT) a job whose objects surely need more than budget
 * bytes of geometry, from their parameters alone (each kind's memory
 * floor: svo instances, say), before anything is imported or allocated;
 * pointer receives the field of the object with the largest floor
 * ("/objects/3/svo/instances"). budget 0: no limit. */
int mr_job_check_memory(const mr_job *job, size_t budget, char pointer[512], mr_error *err);
/* The bytes of geometry the job's objects surely need, from their
 * parameters alone (the sum of each kind's memory floor; SIZE_MAX when it
 * overflows): what mr_job_check_memory holds against the budget. */
size_t mr_job_memory_floor(const mr_job *job);

/* Frees everything the job owns, then the job. NULL is fine. */
void mr_job_free(mr_job *job);

/* A film for the job's frames: its size, its passes (output.aovs) and
 * Cryptomatte ranks (mr_output_crypto_ranks). */
int mr_job_film_new(const mr_job *job, mr_film **out, mr_error *err);

/* ==== Frame statistics (render/frame_stats.c) =============================
 * What a frame's statistics are: the struct the renderer, the worker and the
 * encoding caller fill (mr_frame_stats), and the one table of its fields
 * (mr_frame_stat_fields) that everything else is driven by: the stats writer
 * (stats.json, the stored per-frame object, the HTTP frame and job stats and
 * the "frame" event: server/stats_json.c), its reader (the HTTP job stats
 * rebuild totals from stored frames) and the API's schema of a frame's stats
 * (schemas/openapi.yaml, generated from the table by `make openapi`). A new
 * field is a struct member plus a table row.
 *
 * A geometry kind's own per-frame fields (an extra "simulate" phase, its
 * counters) are not table rows: the renderer appends them to the frame as
 * extras (mr_frame_stats_add_extra), and the writer emits them after the
 * table's fields as "name": value, in the order they were added.
 *
 * No JSON here (core/ has none): the table says names, types, units and
 * where each value lives; the writer decides how a type is spelled. */

typedef enum mr_bvh_update {
    MR_BVH_NONE = 0, /* nothing moved: the previous frame's tree was reused */
    MR_BVH_BUILD,    /* built from scratch */
    MR_BVH_REFIT     /* same tree, bounds refitted to the moved vertices */
} mr_bvh_update;

/* "none", "build" or "refit" (stats.json's "bvh"). */
const char *mr_bvh_update_name(mr_bvh_update u);

/* Most extras one frame carries: every registered kind's stats fields
 * (mr_kind_stat; a job may hold all kinds) plus MR_FRAME_EXTRAS_CALLER of
 * the caller's own (the one-shot renderer's png_s). Registering a kind
 * whose fields would pass that fails. */
#define MR_FRAME_EXTRAS_MAX 64
#define MR_FRAME_EXTRAS_CALLER 4

/* One per-frame field beyond the table's, e.g. {"simulate_s", "s", 0.02}. */
typedef struct mr_frame_extra {
    const char *name;  /* stats.json key; borrowed: a kind's static table */
    const char *unit;  /* "s", "count", "bytes", ...; borrowed */
    double value;
} mr_frame_extra;

/* ---- reference passes ----
 * A job (or one of its objects) with "reference": true renders every frame
 * a second time through each object's reference, per reference type, and
 * compares the frame with it (mr_film_compare): the figures land in the
 * frame's stats as its error entries (mr_frame_error), one per reference
 * the job's objects have. Which references an object has is its kind's to
 * say (kinds/kind.h, `reference`). */
typedef enum mr_reference_type {
    MR_REFERENCE_TESSELLATED = 0, /* each object as its exact tessellation: the same surface as
                                     plain triangles (a triangle mesh is its own) */
    MR_REFERENCE_GROUND_TRUTH     /* what the object's kind approximates, where it has one (the
                                     detailed mesh a DMM was baked from, skinned directly) */
} mr_reference_type;
#define MR_REFERENCE_TYPES 2

/* "tessellated" or "ground_truth" (the stats' "reference"). */
const char *mr_reference_name(mr_reference_type t);

/* The reference passes the job's frames get: bit (1u << type) for each
 * type some object that asks for references has (0: none asks, or none
 * has any). From the parameters alone: nothing is imported. */
int mr_job_reference_passes(const mr_job *job, unsigned *passes, mr_error *err);

/* A frame against one reference frame of the same camera (mr_film_compare
 * of the frame, a, against the reference, b, depths relative to the
 * reference's scene diagonal). Every member has a row in
 * mr_frame_error_fields. */
typedef struct mr_frame_error {
    mr_reference_type reference;
    double coverage_error_pct; /* mr_compare_result.coverage_pct */
    uint64_t holes;
    double depth_rmse, depth_max;
    double normal_mean_deg;
    double psnr_rgb_db;        /* MR_PSNR_IDENTICAL for identical colour */
    double speckle_pct;        /* the reference frame's own (beside the frame's speckle_pct) */
    double surface_px;         /* mr_compare_result.surface_px */
} mr_frame_error;

/* The level of detail one object traced ("tolerance_px"): the level of
 * its kind (what a level is, the kind says: README, Level of detail) and
 * the error the level is predicted to make, in pixels at this frame's
 * camera. */
typedef struct mr_object_lod {
    uint32_t object;  /* index in the job's objects */
    uint32_t level;
    double error_px;
} mr_object_lod;
/* Objects a frame lists (the first ones with a tolerance, in job order);
 * the kinds' own stats fields combine all of them. */
#define MR_FRAME_LOD_MAX 16

/* Per-frame statistics. Every member but the extras, the error entries and
 * the levels of detail has a row in mr_frame_stat_fields (test_stats_json
 * checks they agree). */
typedef struct mr_frame_stats {
    int frame;
    double time;              /* frame time on the job's timeline, s */
    double load_s;            /* asset import charged to this frame (the first) */
    uint32_t assets_cached;   /* first frame: assets a scene cache already held */
    uint32_t assets_loaded;   /* first frame: assets imported for this job */
    double load_saved_s;      /* first frame: import seconds the cache saved */
    double derive_s;          /* first frame: the renderer's set-up (derived data built or read) */
    double pose_s;            /* pose evaluation and skinning */
    double bvh_s;             /* Embree build or refit */
    mr_bvh_update bvh;        /* what happened to the BVH this frame */
    double trace_s;           /* primary + shadow rays and shading */
    double encode_s;          /* EXR encoding and writing (filled by the caller) */
    double total_s;           /* everything for this frame, encode included */
    double reference_s;       /* the reference passes (never part of total_s); 0: none ran */
    uint64_t rays;            /* primary + shadow rays traced */
    double mrays_per_s;       /* rays / trace_s / 1e6 */
    uint64_t triangles;       /* primitives in the scene */
    uint64_t geometry_bytes;  /* microray's vertex/index/normal arrays */
    uint64_t bvh_bytes;       /* Embree's own allocations (memory monitor) */
    uint64_t peak_rss_bytes;  /* process peak resident set so far */
    float scene_diagonal;     /* bounding-box diagonal of the frame's scene */
    double speckle_pct;       /* isolated dark pixels, % of interior pixels (mr_film_speckles) */
    uint32_t replay_frames;   /* frames of sequential kinds re-simulated untraced before this one */
    uint32_t replay_checkpoint; /* the checkpoint (frames it holds) that replay started from, 0: none */
    uint32_t extra_count;     /* extras[0, extra_count) are set */
    mr_frame_extra extras[MR_FRAME_EXTRAS_MAX];
    uint32_t error_count;     /* errors[0, error_count) are set: one per reference pass */
    mr_frame_error errors[MR_REFERENCE_TYPES];
    uint32_t lod_count;       /* lod[0, lod_count) are set: objects with a tolerance */
    mr_object_lod lod[MR_FRAME_LOD_MAX];
} mr_frame_stats;

/* Appends an extra field to the frame. name must be a non-empty run of
 * [a-z0-9_], and neither a field or group name of the table nor an extra
 * already added (MR_ERR_INVALID); at most MR_FRAME_EXTRAS_MAX extras
 * (MR_ERR_LIMIT). name and unit are borrowed: they must outlive st. */
int mr_frame_stats_add_extra(mr_frame_stats *st, const char *name, const char *unit, double value,
                             mr_error *err);

/* ---- the field table ---- */

/* How a field's value is stored in mr_frame_stats (and so how it is read
 * and written). The last two are derived, not stored (offset 0): the
 * writer makes them from other fields and readers skip them. */
typedef enum mr_stat_type {
    MR_STAT_INT,          /* int */
    MR_STAT_U32,          /* uint32_t */
    MR_STAT_U64,          /* uint64_t */
    MR_STAT_F32,          /* float */
    MR_STAT_F64,          /* double */
    MR_STAT_BVH,          /* mr_bvh_update, written as mr_bvh_update_name() */
    MR_STAT_FRAME_FILE,   /* the frame's EXR file name, from the frame index */
    MR_STAT_CACHE_RESULT, /* "hit", "partial" or "miss", from assets_cached/assets_loaded */
    MR_STAT_REFERENCE     /* mr_reference_type, written as mr_reference_name() */
} mr_stat_type;

/* mr_stat_field.flags. OPTIONAL: written only when non-zero (a frame's
 * seconds.reference, only where a reference pass ran; a job's totals and
 * medians hold it when any frame does). LOWER_WORSE: an error figure whose
 * worst value is its lowest (PSNR); the others' worst is their highest. */
#define MR_STAT_OPTIONAL 1u
#define MR_STAT_LOWER_WORSE 2u

/* A JSON object some fields are nested in ("seconds": {...}). */
typedef struct mr_stat_group {
    const char *name;
    const char *description;
    /* Written only for frames where one of the group's integer fields is
     * non-zero (the scene cache reports only on the frame that asked it). */
    bool optional;
} mr_stat_group;

typedef struct mr_stat_field {
    const mr_stat_group *group; /* NULL: a member of the frame object itself */
    const char *name;           /* JSON key within its group */
    mr_stat_type type;
    size_t offset;              /* offsetof(mr_frame_stats, ...) of the value */
    const char *unit;           /* "s", "bytes", "count", ... or "" */
    const char *description;    /* one sentence, for the API schema */
    unsigned flags;             /* MR_STAT_OPTIONAL, MR_STAT_LOWER_WORSE */
} mr_stat_field;

/* The fields in the order they are written; a group's fields are
 * consecutive. */
extern const mr_stat_field mr_frame_stat_fields[];
extern const size_t mr_frame_stat_field_count;

/* The fields of an error entry (mr_frame_error; offsets into it, no
 * groups), in the order they are written: "reference" first. A frame's
 * entries are written as its "error" array; a job's medians and worst
 * frames of each figure per reference as its "error" object. */
extern const mr_stat_field mr_frame_error_fields[];
extern const size_t mr_frame_error_field_count;

/* The groups "seconds" (the per-stage timings that job totals and medians
 * sum up), "bytes", "cache" and "replay". */
extern const mr_stat_group mr_stat_group_seconds, mr_stat_group_bytes, mr_stat_group_cache,
    mr_stat_group_replay;

/* The value of a stored numeric field (INT, U32, U64, F32, F64, BVH) as a
 * double; 0 for derived types. */
double mr_frame_stat_number(const mr_frame_stats *st, const mr_stat_field *f);
/* Sets a stored numeric field from a double, converted as the type needs
 * (integers truncate; negative, NaN and out-of-range counts become 0);
 * derived types are left alone. */
void mr_frame_stat_set_number(mr_frame_stats *st, const mr_stat_field *f, double v);

/* The same for a field of mr_frame_error_fields and an error entry
 * (MR_STAT_REFERENCE reads as the type's number). */
double mr_frame_error_number(const mr_frame_error *e, const mr_stat_field *f);
void mr_frame_error_set_number(mr_frame_error *e, const mr_stat_field *f, double v);

/* "hit" (every asset came from the cache), "partial" or "miss" for the
 * frame's cache counters. */
const char *mr_frame_cache_result(const mr_frame_stats *st);

/* ==== Renderer (render/renderer.c) ========================================
 * Renders the frames of one job. A renderer owns the job's objects (one
 * geometry kind instance each) and one Embree scene. Per frame it evaluates
 * the camera path and each object's pose, deforms what moved, refits
 * (animated scenes) or builds (first frame, static scenes, or force_rebuild)
 * the BVH, and traces the frame into a film.
 *
 * Animated scenes use the refit recipe of REFERENCE.md (scene DYNAMIC + LOW,
 * geometry REFIT): the first frame builds, later frames refit the same tree.
 * Static scenes build once with MEDIUM quality and never touch Embree again. */

typedef struct mr_renderer mr_renderer;

typedef struct mr_renderer_options {
    /* Rebuild the BVH every frame (same fast LOW-quality builder) instead of
     * refitting it: the baseline refit is measured against in benchmarks. */
    bool force_rebuild;
    /* When set to true (from any thread) a render in progress stops within
     * one tile and mr_renderer_render fails with MR_ERR_CANCELLED. May be NULL. */
    const atomic_bool *cancel;
    /* Root of the derived-data cache (bakes, voxelisations, ...): each kind
     * that keeps derived data reads and writes <cache_dir>/<kind name>/
     * (kinds/kind.h). NULL: nothing is kept on disk. Borrowed. */
    const char *cache_dir;
    /* Bytes the job's geometry may hold (0: no limit). Kinds whose memory
     * grows with their parameters (svo instances) estimate it before they
     * allocate and fail with MR_ERR_LIMIT, naming the field, beyond it. */
    size_t memory_budget;
    /* Trace a primary ray for every pixel, also where the film shows none
     * of the scene's bounding box (by default such pixels are misses
     * without a ray): the same work as a plain ray loop, for benchmarks that
     * compare ray rates. The frames are the same either way. */
    bool trace_every_pixel;
} mr_renderer_options;

/* The budget a daemon or the one-shot renderer gives a job when none is
 * set: half of the machine's memory. */
size_t mr_job_memory_default(void);

/* assets[i] is the import of job->assets[i]; the renderer borrows them (they
 * must outlive it). Fails naming the object for unknown clips/cameras. */
int mr_renderer_new(mr_device *dev, const mr_job *job, mr_asset *const *assets,
                    const mr_renderer_options *opt, mr_renderer **out, mr_error *err);
void mr_renderer_free(mr_renderer *r);

/* Renders frame `index` (0 <= index < job->frame_count) into film, which must
 * be job->output.width x height. */
int mr_renderer_render(mr_renderer *r, size_t index, mr_film *film, mr_frame_stats *stats,
                       mr_error *err);

/* A plain triangle soup in world space. */
typedef struct mr_trimesh {
    uint32_t vertex_count, triangle_count;
    float *positions;   /* 3 per vertex */
    uint32_t *indices;  /* 3 per triangle */
} mr_trimesh;

/* Frees the arrays and zeroes *m; NULL is fine. */
void mr_trimesh_free(mr_trimesh *m);

/* The exact triangle reference of job object `object` (an index into
 * job->objects) as the last mr_renderer_render posed it, in world space:
 * what the object's kind stands for (a mesh: its own triangles; dmm: its
 * micro-triangles; svo: the asset's triangles skinned with each instance's
 * pose). For accuracy comparisons and baselines, such as a bare Embree
 * loop over the same triangles. *out is the caller's (mr_trimesh_free).
 * MR_ERR_INVALID for an object out of range; MR_ERR_LIMIT, MR_ERR_NOMEM. */
int mr_renderer_tessellate(const mr_renderer *r, size_t object, mr_trimesh *out, mr_error *err);

#endif /* MICRORAY_H */
