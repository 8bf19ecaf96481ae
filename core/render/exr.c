/*
 * exr.c - OpenEXR frames through the OpenEXR 3.1 C API (exr.h).
 *
 * Why the code looks the way it does:
 *  - All I/O goes through our own read/write callbacks (pread/pwrite on a
 *    descriptor, or a growable memory buffer), so the file and the memory
 *    writer produce the same bytes from the same code path. The library
 *    writes the chunk offset table at exr_finish, after the chunks, so the
 *    memory writer accepts writes at any offset.
 *  - The library stores channels sorted by name, and the encode/decode
 *    pipelines list them in that order: channels are always matched by name
 *    (openexr issue 1900: matching by insertion order silently scrambles
 *    planes).
 *  - A frame's channels are those of the film's passes (film_channels:
 *    one table of names, file types and planes for the writer, the reader
 *    and the header's layout check).
 *  - Colour is converted to half here (mr_float_to_half), not by the
 *    library, so rounding, clamping and NaN/Inf handling are ours and tested.
 *    Our own packer writes the film straight into the packed chunk layout
 *    (one pass, no staging copy).
 *  - Encoding (pack + compress) is most of a frame's time, so chunks are
 *    encoded on all cores (mr_parallel_for). NONE, ZIP and ZIPS chunks are
 *    ours from end to end: packed, for ZIP reordered and predicted as the
 *    codec defines and deflated by our own encoder (util/deflate.h: matches
 *    where rendered rows repeat; several times faster than a general
 *    deflate at a smaller size) or, at zip levels from
 *    MR_ZIP_LEVEL_LIBDEFLATE up, by libdeflate, then handed to the library
 *    as finished chunks. PIZ goes through the library's pipeline, one
 *    exr_encode_pipeline_t per worker (pipelines are per thread by design
 *    and only read the context once the header is written). Writing stays
 *    on the calling thread in chunk order: exr_write_scanline_chunk moves
 *    the file offset and fills the chunk table, and the library refuses
 *    out-of-order chunks for INCREASING_Y files. A chunk's bytes depend
 *    only on its pixels, so the output is identical for any thread count.
 *  - Library messages arrive through an error callback. In 3.1.5 calling
 *    exr_get_user_data() from that callback deadlocks (the failing call
 *    still holds the context lock; measured), so the callback reaches the
 *    message buffer of the current call through a thread-local pointer that
 *    is set on entry to each public function (and by each encoding worker,
 *    to a sink of its own) and restored on exit. The library delivers
 *    errors on the thread that caused them.
 */
#include "render/exr.h"

#include <openexr.h>

#include <errno.h>
#include <fcntl.h>
#include <float.h>
#include <limits.h>
#include <math.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <pwd.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "util/deflate.h"
#include "util/file_io.h"
#include "util/murmur3.h"
#include "util/parallel.h"

#include <libdeflate.h>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

/* ------------------------------------------------------------------ */
/* half <-> float                                                      */

uint16_t mr_float_to_half(float f)
{
    uint32_t x, sign, a, h, rem;

    if (f != f)
        return 0; /* NaN */
    /* Clamping first also turns +-Inf into the largest finite half, and
     * means no rounding below can carry into the Inf exponent. */
    if (f > 65504.0f)
        f = 65504.0f;
    else if (f < -65504.0f)
        f = -65504.0f;

    memcpy(&x, &f, sizeof x);
    sign = (x >> 16) & 0x8000u;
    a = x & 0x7fffffffu;

    if (a >= 0x38800000u) {
        /* Normal half (|f| >= 2^-14): rebias the exponent from 127 to 15 and
         * drop 13 mantissa bits; a carry out of the mantissa correctly bumps
         * the exponent. */
        h = (a - 0x38000000u) >> 13;
        rem = a & 0x1fffu;
        if (rem > 0x1000u || (rem == 0x1000u && (h & 1u)))
            h++;
        return (uint16_t)(sign | h);
    }
    if (a <= 0x33000000u) {
        /* |f| <= 2^-25, at most half of the smallest subnormal 2^-24: the tie
         * at exactly 2^-25 goes to the even neighbour, zero. */
        return (uint16_t)sign;
    }
    {
        /* Subnormal half: value = m * 2^(e - 150), the half unit is 2^-24. */
        uint32_t e = a >> 23;                       /* 102 .. 112 */
        uint32_t m = (a & 0x7fffffu) | 0x800000u;   /* implicit bit */
        uint32_t shift = 126u - e;                  /* 14 .. 24 */
        uint32_t halfway = 1u << (shift - 1u);
        h = m >> shift;
        rem = m & ((1u << shift) - 1u);
        if (rem > halfway || (rem == halfway && (h & 1u)))
            h++; /* may reach 0x400, the smallest normal: still correct */
        return (uint16_t)(sign | h);
    }
}

float mr_half_to_float(uint16_t h)
{
    uint32_t sign = (uint32_t)(h & 0x8000u) << 16;
    uint32_t e = (h >> 10) & 0x1fu;
    uint32_t m = h & 0x3ffu;
    uint32_t x;
    float f;

    if (e == 0) {
        /* Zero or subnormal: m * 2^-24 is exact in float. */
        f = ldexpf((float)m, -24);
        return sign ? -f : f;
    }
    if (e == 31)
        x = sign | 0x7f800000u | (m << 13); /* Inf / NaN */
    else
        x = sign | ((e + 112u) << 23) | (m << 13);
    memcpy(&f, &x, sizeof f);
    return f;
}

/* Z and N are stored as float; keep them finite as well. */
static float sanitize_float(float v)
{
    if (v != v)
        return 0.0f;
    if (v > FLT_MAX)
        return FLT_MAX;
    if (v < -FLT_MAX)
        return -FLT_MAX;
    return v;
}

/* ------------------------------------------------------------------ */
/* compression names                                                   */

const char *mr_compression_name(mr_compression c)
{
    switch (c) {
    case MR_COMPRESSION_NONE: return "none";
    case MR_COMPRESSION_ZIP: return "zip";
    case MR_COMPRESSION_ZIPS: return "zips";
    case MR_COMPRESSION_PIZ: return "piz";
    }
    return "unknown";
}

bool mr_compression_parse(const char *name, mr_compression *out)
{
    static const mr_compression all[] = {MR_COMPRESSION_NONE, MR_COMPRESSION_ZIP,
                                          MR_COMPRESSION_ZIPS, MR_COMPRESSION_PIZ};
    size_t i;

    if (!name)
        return false;
    for (i = 0; i < sizeof all / sizeof all[0]; i++) {
        if (strcmp(name, mr_compression_name(all[i])) == 0) {
            if (out)
                *out = all[i];
            return true;
        }
    }
    return false;
}

/* ------------------------------------------------------------------ */
/* channel table                                                       */

/* Most channels a frame has: R G B A Z N.* P.* T.* id.* and two
 * Cryptomatte layers of MR_CRYPTO_MAX_RANKS ranks, two channels a rank. */
enum { CH_MAX = 16 + MR_CRYPTO_LAYERS * 2 * MR_CRYPTO_MAX_RANKS };

/* One channel of a frame and the film plane behind it (4-byte samples:
 * float, or uint32 for the ids). */
typedef struct chan_def {
    char name[32];
    exr_pixel_type_t type; /* type in the file */
    mr_aov aov;            /* the pass it belongs to */
    int rank;              /* Cryptomatte: the rank it holds (id or coverage); else -1 */
    void *plane;
} chan_def;

static const char *const k_crypto_layer[MR_CRYPTO_LAYERS] = {"CryptoObject", "CryptoAsset"};

static void add_chan(chan_def *ch, int *n, const char *name, exr_pixel_type_t type, mr_aov aov,
                     int rank, void *plane)
{
    chan_def *c = &ch[(*n)++];
    snprintf(c->name, sizeof c->name, "%s", name);
    c->type = type;
    c->aov = aov;
    c->rank = rank;
    c->plane = plane;
}

/* The channels of the film's passes, in our order (the file's is by
 * name), each with its plane (NULL in a hand-made film that lacks it). */
static int film_channels(const mr_film *f, bool half_normals, chan_def ch[CH_MAX])
{
    int n = 0;
    if (f->aovs & MR_AOV_RGBA) {
        add_chan(ch, &n, "R", EXR_PIXEL_HALF, MR_AOV_RGBA, -1, f->r);
        add_chan(ch, &n, "G", EXR_PIXEL_HALF, MR_AOV_RGBA, -1, f->g);
        add_chan(ch, &n, "B", EXR_PIXEL_HALF, MR_AOV_RGBA, -1, f->b);
        add_chan(ch, &n, "A", EXR_PIXEL_HALF, MR_AOV_RGBA, -1, f->a);
    }
    if (f->aovs & MR_AOV_Z)
        add_chan(ch, &n, "Z", EXR_PIXEL_FLOAT, MR_AOV_Z, -1, f->z);
    if (f->aovs & MR_AOV_N) {
        exr_pixel_type_t t = half_normals ? EXR_PIXEL_HALF : EXR_PIXEL_FLOAT;
        add_chan(ch, &n, "N.X", t, MR_AOV_N, -1, f->nx);
        add_chan(ch, &n, "N.Y", t, MR_AOV_N, -1, f->ny);
        add_chan(ch, &n, "N.Z", t, MR_AOV_N, -1, f->nz);
    }
    if (f->aovs & MR_AOV_P) {
        add_chan(ch, &n, "P.X", EXR_PIXEL_FLOAT, MR_AOV_P, -1, f->px);
        add_chan(ch, &n, "P.Y", EXR_PIXEL_FLOAT, MR_AOV_P, -1, f->py);
        add_chan(ch, &n, "P.Z", EXR_PIXEL_FLOAT, MR_AOV_P, -1, f->pz);
    }
    if (f->aovs & MR_AOV_T) {
        add_chan(ch, &n, "T.X", EXR_PIXEL_FLOAT, MR_AOV_T, -1, f->tx);
        add_chan(ch, &n, "T.Y", EXR_PIXEL_FLOAT, MR_AOV_T, -1, f->ty);
        add_chan(ch, &n, "T.Z", EXR_PIXEL_FLOAT, MR_AOV_T, -1, f->tz);
    }
    if (f->aovs & MR_AOV_ID) {
        add_chan(ch, &n, "id.object", EXR_PIXEL_UINT, MR_AOV_ID, -1, f->object_id);
        add_chan(ch, &n, "id.primitive", EXR_PIXEL_UINT, MR_AOV_ID, -1, f->prim_id);
    }
    if (f->aovs & MR_AOV_CRYPTOMATTE) {
        /* <layer>NN.R/G: id and coverage of rank 2 NN, .B/.A: of rank 2 NN + 1 */
        int ranks = f->crypto_ranks > MR_CRYPTO_MAX_RANKS ? MR_CRYPTO_MAX_RANKS : f->crypto_ranks;
        for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
            for (int k = 0; k < 2 * ranks; k++) {
                char name[32];
                snprintf(name, sizeof name, "%s%02d.%c", k_crypto_layer[l], k / 4, "RGBA"[k % 4]);
                add_chan(ch, &n, name, EXR_PIXEL_FLOAT, MR_AOV_CRYPTOMATTE, k / 2,
                         f->crypto[l][k]);
            }
    }
    return n;
}

static int chan_find(const chan_def *ch, int n, const char *name)
{
    if (!name)
        return -1;
    for (int i = 0; i < n; i++)
        if (strcmp(name, ch[i].name) == 0)
            return i;
    return -1;
}

/* ------------------------------------------------------------------ */
/* I/O state and library callbacks                                     */

typedef struct exr_io {
    const char *name;   /* path or "<memory>", for messages */
    int fd;             /* -1 for memory output */
    uint8_t *data;      /* memory output */
    size_t size, cap;
    int64_t file_size;  /* read: size of the input file */
    bool oom;           /* memory output could not grow */
    char msg[384];      /* last message from the library */
} exr_io;

/* See the file comment: the error sink of the call running on this thread. */
static _Thread_local exr_io *t_sink;

static void on_exr_error(exr_const_context_t ctxt, exr_result_t code, const char *msg)
{
    (void)ctxt;
    (void)code;
    if (t_sink && msg)
        snprintf(t_sink->msg, sizeof t_sink->msg, "%s", msg);
}

static int64_t io_write_mem(exr_const_context_t ctxt, void *user, const void *buf,
                            uint64_t sz, uint64_t offset,
                            exr_stream_error_func_ptr_t error_cb)
{
    exr_io *io = user;
    size_t end;

    if (sz > (uint64_t)INT64_MAX || offset > (uint64_t)SIZE_MAX - sz) {
        error_cb(ctxt, EXR_ERR_WRITE_IO, "write of %llu bytes at %llu is out of range",
                 (unsigned long long)sz, (unsigned long long)offset);
        return -1;
    }
    end = (size_t)(offset + sz);
    if (end > io->cap) {
        size_t ncap = io->cap ? io->cap : 65536;
        uint8_t *nd;
        while (ncap < end)
            ncap = ncap > SIZE_MAX / 2 ? end : ncap * 2;
        nd = realloc(io->data, ncap);
        if (!nd) {
            io->oom = true;
            error_cb(ctxt, EXR_ERR_OUT_OF_MEMORY, "cannot grow output buffer to %zu bytes",
                     ncap);
            return -1;
        }
        io->data = nd;
        io->cap = ncap;
    }
    if ((size_t)offset > io->size)
        memset(io->data + io->size, 0, (size_t)offset - io->size);
    if (sz)
        memcpy(io->data + offset, buf, (size_t)sz);
    if (end > io->size)
        io->size = end;
    return (int64_t)sz;
}

static int64_t io_write_fd(exr_const_context_t ctxt, void *user, const void *buf,
                           uint64_t sz, uint64_t offset,
                           exr_stream_error_func_ptr_t error_cb)
{
    exr_io *io = user;
    const uint8_t *p = buf;
    uint64_t done = 0;

    if (sz > (uint64_t)INT64_MAX || offset > (uint64_t)INT64_MAX - sz) {
        error_cb(ctxt, EXR_ERR_WRITE_IO, "write of %llu bytes at %llu is out of range",
                 (unsigned long long)sz, (unsigned long long)offset);
        return -1;
    }
    while (done < sz) {
        size_t chunk = (sz - done) > (uint64_t)(SSIZE_MAX / 2) ? (size_t)(SSIZE_MAX / 2)
                                                               : (size_t)(sz - done);
        ssize_t n = pwrite(io->fd, p + done, chunk, (off_t)(offset + done));
        if (n < 0) {
            if (errno == EINTR)
                continue;
            error_cb(ctxt, EXR_ERR_WRITE_IO, "%s: write at offset %llu failed: %s",
                     io->name, (unsigned long long)(offset + done), strerror(errno));
            return -1;
        }
        if (n == 0) {
            error_cb(ctxt, EXR_ERR_WRITE_IO, "%s: write at offset %llu made no progress",
                     io->name, (unsigned long long)(offset + done));
            return -1;
        }
        done += (uint64_t)n;
    }
    return (int64_t)sz;
}

static int64_t io_read_fd(exr_const_context_t ctxt, void *user, void *buf, uint64_t sz,
                          uint64_t offset, exr_stream_error_func_ptr_t error_cb)
{
    exr_io *io = user;
    uint8_t *p = buf;
    uint64_t done = 0;

    if (sz > (uint64_t)INT64_MAX || offset > (uint64_t)INT64_MAX - sz) {
        error_cb(ctxt, EXR_ERR_READ_IO, "read of %llu bytes at %llu is out of range",
                 (unsigned long long)sz, (unsigned long long)offset);
        return -1;
    }
    while (done < sz) {
        size_t chunk = (sz - done) > (uint64_t)(SSIZE_MAX / 2) ? (size_t)(SSIZE_MAX / 2)
                                                               : (size_t)(sz - done);
        ssize_t n = pread(io->fd, p + done, chunk, (off_t)(offset + done));
        if (n < 0) {
            if (errno == EINTR)
                continue;
            error_cb(ctxt, EXR_ERR_READ_IO, "%s: read at offset %llu failed: %s",
                     io->name, (unsigned long long)(offset + done), strerror(errno));
            return -1;
        }
        if (n == 0)
            break; /* end of file: a short read, the library decides */
        done += (uint64_t)n;
    }
    return (int64_t)done;
}

static int64_t io_size_fd(exr_const_context_t ctxt, void *user)
{
    (void)ctxt;
    return ((exr_io *)user)->file_size;
}

/* Turns a library failure into an mr_error naming the file and the step. */
static int exr_fail(mr_error *err, const exr_io *io, bool writing, const char *step,
                    exr_result_t rv)
{
    int code;

    if (rv == EXR_ERR_OUT_OF_MEMORY || io->oom)
        code = MR_ERR_NOMEM;
    else if (writing)
        code = (rv == EXR_ERR_WRITE_IO || rv == EXR_ERR_FILE_ACCESS) ? MR_ERR_IO
                                                                     : MR_ERR_FORMAT;
    else
        code = MR_ERR_FORMAT; /* we opened the file ourselves: the content is bad */
    return mr_error_set(err, code, "%s: EXR %s failed in %s: %s%s%s%s", io->name,
                        writing ? "write" : "read", step, exr_get_error_code_as_string(rv),
                        io->msg[0] ? " (" : "", io->msg, io->msg[0] ? ")" : "");
}

/* ------------------------------------------------------------------ */
/* writing                                                             */

static int check_film(const mr_film *film, mr_error *err)
{
    chan_def ch[CH_MAX];
    int i, n;

    if (!film)
        return mr_error_set(err, MR_ERR_INVALID, "EXR write: film is NULL");
    if (film->width <= 0 || film->height <= 0 || film->width > MR_MAX_RESOLUTION ||
        film->height > MR_MAX_RESOLUTION ||
        (size_t)film->width * (size_t)film->height > (size_t)MR_MAX_PIXELS)
        return mr_error_set(err, MR_ERR_INVALID, "EXR write: bad film size %dx%d",
                            film->width, film->height);
    if (film->aovs == 0 || (film->aovs & ~MR_AOV_ALL))
        return mr_error_set(err, MR_ERR_INVALID, "EXR write: film passes 0x%x are not a "
                            "non-empty set of mr_aov bits", film->aovs);
    if ((film->aovs & MR_AOV_CRYPTOMATTE) &&
        (film->crypto_ranks < 2 || film->crypto_ranks > MR_CRYPTO_MAX_RANKS ||
         film->crypto_ranks % 2))
        return mr_error_set(err, MR_ERR_INVALID, "EXR write: %d Cryptomatte ranks, expected "
                            "an even number in 2..%d", film->crypto_ranks, MR_CRYPTO_MAX_RANKS);
    n = film_channels(film, false, ch);
    for (i = 0; i < n; i++)
        if (!ch[i].plane)
            return mr_error_set(err, MR_ERR_INVALID, "EXR write: film plane %s is NULL",
                                ch[i].name);
    return MR_OK;
}

static int check_options(const mr_exr_options *opt, exr_compression_t *ctype, int *level,
                         mr_error *err)
{
    mr_exr_options o = {0};

    if (opt)
        o = *opt;
    switch (o.compression) {
    case MR_COMPRESSION_NONE: *ctype = EXR_COMPRESSION_NONE; break;
    case MR_COMPRESSION_ZIP: *ctype = EXR_COMPRESSION_ZIP; break;
    case MR_COMPRESSION_ZIPS: *ctype = EXR_COMPRESSION_ZIPS; break;
    case MR_COMPRESSION_PIZ: *ctype = EXR_COMPRESSION_PIZ; break;
    default:
        return mr_error_set(err, MR_ERR_INVALID, "EXR write: unknown compression %d",
                            (int)o.compression);
    }
    if (o.zip_level < 0 || o.zip_level > 9)
        return mr_error_set(err, MR_ERR_INVALID,
                            "EXR write: zip_level %d is outside 1..9 (0 = default %d)",
                            o.zip_level, MR_ZIP_LEVEL_DEFAULT);
    *level = o.zip_level ? o.zip_level : MR_ZIP_LEVEL_DEFAULT;
    return MR_OK;
}

static int check_meta(const mr_exr_meta *meta, mr_error *err)
{
    if (!meta)
        return MR_OK;
    if (!memchr(meta->job, '\0', sizeof meta->job))
        return mr_error_set(err, MR_ERR_INVALID, "EXR write: meta.job is not terminated");
    if (!isfinite(meta->time))
        return mr_error_set(err, MR_ERR_INVALID, "EXR write: meta.time is not finite");
    if (!isfinite(meta->render_seconds))
        return mr_error_set(err, MR_ERR_INVALID,
                            "EXR write: meta.render_seconds is not finite");
    if (!isfinite(meta->scene_diagonal))
        return mr_error_set(err, MR_ERR_INVALID,
                            "EXR write: meta.scene_diagonal is not finite");
    if (!(meta->fps >= 0 && meta->fps <= 1e6))
        return mr_error_set(err, MR_ERR_INVALID, "EXR write: meta.fps is not in 0..1e6");
    if (!memchr(meta->owner, '\0', sizeof meta->owner))
        return mr_error_set(err, MR_ERR_INVALID, "EXR write: meta.owner is not terminated");
    return MR_OK;
}

/* ------------------------------------------------------------------ */
/* parallel chunk encoding                                             */

/* Caps the worker array; mr_parallel_for never uses more threads than
 * there are chunks in a batch anyway. */
#define ENC_MAX_THREADS 256u
/* Raw (packed) bytes encoded per batch: bounds the memory holding encoded
 * chunks that wait for their turn to be written (at most their raw size
 * each; compressed chunks hold only their compressed bytes). 16 MiB takes
 * a 960x540 frame of the default passes in one batch: one start of the
 * workers, and no core idle while the other writes. */
#define ENC_BATCH_BYTES ((size_t)16 << 20)

/* One channel of the file, in the file's (name) order. */
typedef struct enc_chan {
    const chan_def *def;    /* name, type in the file, film plane */
} enc_chan;

/* The channels as the library stored them (read back after the header is
 * written, so the order is the library's, not our guess of it). */
typedef struct enc_layout {
    int count;
    enc_chan ch[CH_MAX];
    size_t pixel_bytes;     /* one pixel over all channels, as packed */
} enc_layout;

/* One chunk of the current batch. cinfo is filled on the calling thread,
 * the rest by the worker that encodes the chunk. */
typedef struct enc_slot {
    exr_chunk_info_t cinfo;
    uint8_t *data;      /* encoded bytes, reused from batch to batch */
    size_t size, cap;
    bool done;
    exr_result_t rv;
    const char *step;
    char msg[384];      /* library message of a failure, from the worker */
} enc_slot;

/* Per worker index, reused for every chunk that worker takes: for PIZ the
 * library's pipeline (pipelines are not thread-safe, the context is), for
 * ZIP/ZIPS our own compressor (util/deflate.h, or libdeflate at levels
 * from MR_ZIP_LEVEL_LIBDEFLATE up) and its two chunk-sized buffers. */
typedef struct enc_worker {
    exr_encode_pipeline_t pipe;
    bool ready, routines;
    const struct enc_batch *batch;
    mr_deflate *fast;
    struct libdeflate_compressor *deflate;
    uint8_t *predicted;     /* the chunk, packed and predicted */
    uint8_t *row_buf;       /* one channel's row, packed (4 * width bytes) */
    size_t predicted_cap;
    int last_y, last_h;     /* the rows of the last chunk compressed (last_h 0: none) ... */
    uint8_t *last_out;      /* ... and what they compressed to */
    size_t last_size, last_cap;
} enc_worker;

typedef struct enc_batch {
    exr_const_context_t ctxt;
    int part;
    const mr_film *film;
    enc_layout layout;
    exr_compression_t ctype;
    int level;          /* ZIP/ZIPS: the deflate level */
    size_t row;         /* ZIP/ZIPS: half a packed scanline (width * pixel_bytes / 2) */
    enc_slot *slots;
    enc_worker *workers;
    atomic_bool failed; /* set by the first failing chunk: skip the rest */
} enc_batch;

static void put_le16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}

static void put_le32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
}

static void half_row(const float *src, uint8_t *dst, size_t n)
{
    size_t x;
    for (x = 0; x < n; x++)
        put_le16(dst + 2 * x, mr_float_to_half(src[x]));
}

/* Finite samples skip sanitize_float and are copied as bits: compilers may
 * turn its compares into min/max instructions, which flush denormals when a
 * thread runs with denormals-are-zero (seen in a test build). */
static void float_row(const float *src, uint8_t *dst, size_t n)
{
    size_t x;
    for (x = 0; x < n; x++) {
        float v = src[x];
        uint32_t bits;
        if (!(v >= -FLT_MAX && v <= FLT_MAX))
            v = sanitize_float(v);
        memcpy(&bits, &v, sizeof bits);
        put_le32(dst + 4 * x, bits);
    }
}

static void uint_row(const uint32_t *src, uint8_t *dst, size_t n)
{
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
    memcpy(dst, src, n * sizeof *src); /* already the file's byte order */
#else
    size_t x;
    for (x = 0; x < n; x++)
        put_le32(dst + 4 * x, src[x]);
#endif
}

#if defined(__GNUC__) && defined(__x86_64__)
#include <cpuid.h>
#include <immintrin.h>
#define MR_EXR_F16C 1
/* Half conversion was about half of an uncompressed write and a tenth of a
 * ZIP or PIZ one (perf, 1080p). The hardware converter, after the same NaN
 * and range clamps, rounds to nearest even exactly like mr_float_to_half,
 * subnormals included: checked for all 2^32 float bit patterns, with
 * MXCSR flush-to-zero and denormals-are-zero both off and on. x86-64 is
 * little-endian, so the stored halves are in file order. */
__attribute__((target("avx,f16c"))) static void half_row_f16c(const float *src,
                                                               uint8_t *dst, size_t n)
{
    const __m256 lo = _mm256_set1_ps(-65504.0f), hi = _mm256_set1_ps(65504.0f);
    size_t x = 0;

    for (; x + 8 <= n; x += 8) {
        __m256 v = _mm256_loadu_ps(src + x);
        v = _mm256_and_ps(v, _mm256_cmp_ps(v, v, _CMP_ORD_Q)); /* NaN -> +0 */
        v = _mm256_min_ps(_mm256_max_ps(v, lo), hi);
        _mm_storeu_si128((__m128i *)(void *)(dst + 2 * x),
                         _mm256_cvtps_ph(v, _MM_FROUND_TO_NEAREST_INT));
    }
    half_row(src + x, dst + 2 * x, n - x);
}

/* float_row with AVX. Finite samples must pass bit for bit even when a
 * caller runs with denormals-are-zero (Embree advises it for render
 * threads), so no arithmetic touches them: blocks whose exponent bits show
 * no Inf/NaN are copied, the rare others take the scalar path. The masked
 * exponent is never a denormal, so the compare is immune to DAZ too. */
__attribute__((target("avx"))) static void float_row_avx(const float *src, uint8_t *dst,
                                                         size_t n)
{
    const __m256 expo = _mm256_castsi256_ps(_mm256_set1_epi32(0x7f800000));
    size_t x = 0;

    for (; x + 8 <= n; x += 8) {
        __m256 v = _mm256_loadu_ps(src + x);
        __m256 e = _mm256_and_ps(v, expo);
        if (_mm256_movemask_ps(_mm256_cmp_ps(e, expo, _CMP_EQ_OQ)))
            float_row(src + x, dst + 4 * x, 8);
        else
            _mm256_storeu_ps((float *)(void *)(dst + 4 * x), v);
    }
    float_row(src + x, dst + 4 * x, n - x);
}

static bool have_f16c(void)
{
#ifdef __clang__
    /* clang 14's __builtin_cpu_supports has no "f16c" (the fuzz build
     * compiles with clang): CPUID leaf 1 says it. */
    unsigned a, b, c, d;
    return __builtin_cpu_supports("avx") && __get_cpuid(1, &a, &b, &c, &d) && (c & bit_F16C);
#else
    return __builtin_cpu_supports("avx") && __builtin_cpu_supports("f16c");
#endif
}
#else
static bool have_f16c(void)
{
    return false;
}
#endif

/* One channel's samples of one scanline (film pixels [base, base +
 * width)) as the file stores them: little-endian, half rounding ours.
 * Returns the bytes written (2 or 4 per sample). */
static size_t pack_channel_row(const chan_def *def, size_t base, size_t width, bool f16c,
                               uint8_t *dst)
{
    const void *plane = def->plane;
    (void)f16c; /* unused where there are no vector paths */
    switch (def->type) {
    case EXR_PIXEL_HALF:
#ifdef MR_EXR_F16C
        if (f16c)
            half_row_f16c((const float *)plane + base, dst, width);
        else
#endif
            half_row((const float *)plane + base, dst, width);
        return 2 * width;
    case EXR_PIXEL_FLOAT:
#ifdef MR_EXR_F16C
        if (f16c)
            float_row_avx((const float *)plane + base, dst, width);
        else
#endif
            float_row((const float *)plane + base, dst, width);
        return 4 * width;
    default: /* UINT: ids go out untouched */
        uint_row((const uint32_t *)plane + base, dst, width);
        return 4 * width;
    }
}

/* Packs rows [y0, y0 + h) of the film in the layout of an uncompressed
 * scanline chunk (per scanline, every channel in file order, little-endian
 * samples), converting straight from the film: no staging copy, and the
 * half rounding stays ours. Returns the bytes written (h * width *
 * pixel_bytes). */
static size_t pack_rows(const mr_film *film, const enc_layout *L, int y0, int h, uint8_t *dst)
{
    size_t width = (size_t)film->width;
    uint8_t *start = dst;
    bool f16c = have_f16c(); /* F16C implies AVX */
    int row, c;

    for (row = 0; row < h; row++) {
        size_t base = (size_t)(y0 + row) * width;
        for (c = 0; c < L->count; c++)
            dst += pack_channel_row(L->ch[c].def, base, width, f16c, dst);
    }
    return (size_t)(dst - start);
}

/* The ZIP codec's byte order and predictor (mr_exr_zip_predict) over a
 * stream that arrives in pieces: the even-indexed bytes go to the first
 * half, the odd-indexed ones to the second, each stored as its difference
 * to the byte before it in that order plus 128 (mod 256). The byte before
 * the first even one counts as 128, so that one is stored as it is; the
 * byte before the first odd one is the last even one, known only at the
 * end: zip_finish corrects it (its start value 128 keeps the odd byte
 * itself until then). Every piece but the last must have an even length
 * (each channel's row has), so a piece starts with an even-indexed byte. */
typedef struct zip_stream {
    uint8_t *even, *odd;      /* where the next byte of each half goes */
    uint8_t *odd_start;
    uint8_t last_even, last_odd;
} zip_stream;

static void zip_start(zip_stream *z, uint8_t *out, size_t n)
{
    z->even = out;
    z->odd = z->odd_start = out + (n + 1) / 2;
    z->last_even = z->last_odd = 128;
}

#ifdef MR_EXR_F16C
/* zip_piece's vector loop 64 bytes at a time (AVX2): packus works within
 * 128-bit lanes, so the packed evens (odds) are put in order by a 64-bit
 * permute; each byte's predecessor comes from alignr over the vector and
 * the one before it. Returns the bytes done (a multiple of 64). */
__attribute__((target("avx2"))) static size_t zip_piece_avx2(const uint8_t *in, size_t m,
                                                             uint8_t *even, uint8_t *odd,
                                                             uint8_t *le, uint8_t *lo)
{
    const __m256i lo_mask = _mm256_set1_epi16(0x00ff), bias = _mm256_set1_epi8((char)0x80);
    __m256i prev_e = _mm256_set1_epi8((char)*le), prev_o = _mm256_set1_epi8((char)*lo);
    size_t k = 0;

    for (; k + 64 <= m; k += 64) {
        __m256i a = _mm256_loadu_si256((const __m256i *)(const void *)(in + k));
        __m256i b = _mm256_loadu_si256((const __m256i *)(const void *)(in + k + 32));
        __m256i ev = _mm256_permute4x64_epi64(
            _mm256_packus_epi16(_mm256_and_si256(a, lo_mask), _mm256_and_si256(b, lo_mask)),
            0xd8);
        __m256i od = _mm256_permute4x64_epi64(
            _mm256_packus_epi16(_mm256_srli_epi16(a, 8), _mm256_srli_epi16(b, 8)), 0xd8);
        /* [last lane of prev | first lane of this]: the bytes before each lane */
        __m256i pe = _mm256_alignr_epi8(ev, _mm256_permute2x128_si256(prev_e, ev, 0x21), 15);
        __m256i po = _mm256_alignr_epi8(od, _mm256_permute2x128_si256(prev_o, od, 0x21), 15);
        _mm256_storeu_si256((__m256i *)(void *)(even + k / 2),
                            _mm256_add_epi8(_mm256_sub_epi8(ev, pe), bias));
        _mm256_storeu_si256((__m256i *)(void *)(odd + k / 2),
                            _mm256_add_epi8(_mm256_sub_epi8(od, po), bias));
        prev_e = ev;
        prev_o = od;
    }
    if (k) {
        *le = in[k - 2];
        *lo = in[k - 1];
    }
    return k;
}
#endif

/* The vector loop splits 32 input bytes into 16 even and 16 odd ones and
 * subtracts from each lane its predecessor: the lane before it, or for
 * lane 0 the last lane of the block before. */
static void zip_piece(zip_stream *z, const uint8_t *in, size_t m)
{
    uint8_t *even = z->even, *odd = z->odd, le = z->last_even, lo = z->last_odd;
    size_t k = 0;
#ifdef MR_EXR_F16C
    if (m >= 64 && __builtin_cpu_supports("avx2")) {
        k = zip_piece_avx2(in, m, even, odd, &le, &lo);
        even += k / 2;
        odd += k / 2;
    }
#endif
#if defined(__SSE2__)
    if (m - k >= 32) {
        const __m128i lo_mask = _mm_set1_epi16(0x00ff), bias = _mm_set1_epi8((char)0x80);
        __m128i prev_e = _mm_slli_si128(_mm_cvtsi32_si128(le), 15);
        __m128i prev_o = _mm_slli_si128(_mm_cvtsi32_si128(lo), 15);
        for (; k + 32 <= m; k += 32) {
            __m128i a = _mm_loadu_si128((const __m128i *)(const void *)(in + k));
            __m128i b = _mm_loadu_si128((const __m128i *)(const void *)(in + k + 16));
            __m128i ev = _mm_packus_epi16(_mm_and_si128(a, lo_mask), _mm_and_si128(b, lo_mask));
            __m128i od = _mm_packus_epi16(_mm_srli_epi16(a, 8), _mm_srli_epi16(b, 8));
            __m128i pe = _mm_or_si128(_mm_slli_si128(ev, 1), _mm_srli_si128(prev_e, 15));
            __m128i po = _mm_or_si128(_mm_slli_si128(od, 1), _mm_srli_si128(prev_o, 15));
            _mm_storeu_si128((__m128i *)(void *)even, _mm_add_epi8(_mm_sub_epi8(ev, pe), bias));
            _mm_storeu_si128((__m128i *)(void *)odd, _mm_add_epi8(_mm_sub_epi8(od, po), bias));
            even += 16;
            odd += 16;
            prev_e = ev;
            prev_o = od;
        }
        le = (uint8_t)(_mm_extract_epi16(prev_e, 7) >> 8);
        lo = (uint8_t)(_mm_extract_epi16(prev_o, 7) >> 8);
    }
#endif
    for (; k + 2 <= m; k += 2) {
        *even++ = (uint8_t)(in[k] - le + 128u);
        le = in[k];
        *odd++ = (uint8_t)(in[k + 1] - lo + 128u);
        lo = in[k + 1];
    }
    if (k < m) {
        *even++ = (uint8_t)(in[k] - le + 128u);
        le = in[k];
    }
    z->even = even;
    z->odd = odd;
    z->last_even = le;
    z->last_odd = lo;
}

static void zip_finish(zip_stream *z)
{
    if (z->odd > z->odd_start)
        z->odd_start[0] = (uint8_t)(z->odd_start[0] - z->last_even + 128u);
}

/* pack_rows and mr_exr_zip_predict in one pass: each channel's row is
 * packed into row_buf (4 * width bytes, cache-resident) and predicted from
 * there into out, so the packed chunk is never written out whole. */
static void pack_predict_rows(const mr_film *film, const enc_layout *L, int y0, int h,
                              uint8_t *row_buf, uint8_t *out, size_t raw)
{
    size_t width = (size_t)film->width;
    bool f16c = have_f16c();
    zip_stream z;
    int row, c;

    zip_start(&z, out, raw);
    for (row = 0; row < h; row++) {
        size_t base = (size_t)(y0 + row) * width;
        for (c = 0; c < L->count; c++) {
            const chan_def *def = L->ch[c].def;
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
            if (def->type == EXR_PIXEL_UINT) { /* already the file's bytes */
                zip_piece(&z, (const uint8_t *)((const uint32_t *)def->plane + base), 4 * width);
                continue;
            }
#endif
            zip_piece(&z, row_buf, pack_channel_row(def, base, width, f16c, row_buf));
        }
    }
    zip_finish(&z);
}

/* Our convert_and_pack step in the library's pipeline (PIZ). */
static exr_result_t pack_chunk(exr_encode_pipeline_t *p)
{
    const enc_worker *w = p->encoding_user_data;
    const enc_batch *b = w->batch;
    const mr_film *film = b->film;
    size_t need = (size_t)p->chunk.height * (size_t)film->width * b->layout.pixel_bytes;

    if (!p->packed_buffer || p->packed_alloc_size < need || p->chunk.start_y < 0 ||
        p->chunk.height < 1 || p->chunk.start_y + p->chunk.height > film->height)
        return EXR_ERR_INVALID_ARGUMENT;
    p->packed_bytes = pack_rows(film, &b->layout, p->chunk.start_y, p->chunk.height,
                                p->packed_buffer);
    return EXR_ERR_SUCCESS;
}

/* The ZIP codec's byte order and predictor, applied to n packed bytes in
 * one pass: the chunk is split into its even-indexed bytes followed by its
 * odd-indexed bytes (t), and every byte of t but the first is stored as its
 * difference to the previous one plus 128 (mod 256). OpenEXR's decoder
 * undoes both after inflating (openexr internal_zip.c, ImfZip.cpp); the
 * result is what the library's own encoder hands to zlib. */
void mr_exr_zip_predict(const uint8_t *in, size_t n, uint8_t *out)
{
    zip_stream z;
    zip_start(&z, out, n);
    zip_piece(&z, in, n);
    zip_finish(&z);
}

/* Points the pipeline's channels at the chunk's rows and checks that the
 * library describes the layout we wrote the header for (PIZ). */
static exr_result_t setup_channels(enc_worker *w, const exr_chunk_info_t *cinfo)
{
    exr_encode_pipeline_t *p = &w->pipe;
    const enc_layout *L = &w->batch->layout;
    const mr_film *film = w->batch->film;
    int c;

    if (p->channel_count != L->count)
        return EXR_ERR_INVALID_ARGUMENT;
    for (c = 0; c < L->count; c++) {
        exr_coding_channel_info_t *ch = &p->channels[c];
        const chan_def *d = L->ch[c].def;
        if (!ch->channel_name || strcmp(ch->channel_name, d->name) != 0 ||
            ch->data_type != (uint16_t)d->type || ch->x_samples != 1 || ch->y_samples != 1 ||
            ch->width != film->width || ch->height != cinfo->height ||
            ch->bytes_per_element != (d->type == EXR_PIXEL_HALF ? 2 : 4))
            return EXR_ERR_INVALID_ARGUMENT;
        /* pack_chunk reads the film itself; these describe the film planes
         * truthfully (4-byte float or uint rows) because exr_encoding_run
         * validates them. */
        ch->encode_from_ptr = (const uint8_t *)((const uint32_t *)d->plane +
                                                (size_t)cinfo->start_y * (size_t)film->width);
        ch->user_data_type = (uint16_t)(d->type == EXR_PIXEL_UINT ? EXR_PIXEL_UINT
                                                                  : EXR_PIXEL_FLOAT);
        ch->user_bytes_per_element = 4;
        ch->user_pixel_stride = 4;
        ch->user_line_stride = 4 * film->width;
    }
    return EXR_ERR_SUCCESS;
}

/* PIZ: packs (our pack_chunk) and compresses one chunk through the
 * library's pipeline into s->data. */
static exr_result_t encode_chunk_library(enc_batch *b, enc_worker *w, enc_slot *s)
{
    exr_encode_pipeline_t *p = &w->pipe;
    exr_result_t rv;

    if (!w->ready) {
        s->step = "exr_encoding_initialize";
        rv = exr_encoding_initialize(b->ctxt, b->part, &s->cinfo, p);
        if (rv != EXR_ERR_SUCCESS)
            return rv;
        w->ready = true;
    } else {
        s->step = "exr_encoding_update";
        rv = exr_encoding_update(b->ctxt, b->part, &s->cinfo, p);
        if (rv != EXR_ERR_SUCCESS)
            return rv;
    }
    s->step = "exr_encoding_initialize (channel mismatch)";
    rv = setup_channels(w, &s->cinfo);
    if (rv != EXR_ERR_SUCCESS)
        return rv;
    if (!w->routines) {
        s->step = "exr_encoding_choose_default_routines";
        rv = exr_encoding_choose_default_routines(b->ctxt, b->part, p);
        if (rv != EXR_ERR_SUCCESS)
            return rv;
        /* Keep the library's compressor; pack ourselves; no waiting for our
         * turn and no writing from here (the default routines would write
         * the chunk, and insist on chunk order, from this thread). */
        p->convert_and_pack_fn = pack_chunk;
        p->yield_until_ready_fn = NULL;
        p->write_fn = NULL;
        p->encoding_user_data = w;
        w->routines = true;
    }
    s->step = "exr_encoding_run";
    rv = exr_encoding_run(b->ctxt, b->part, p);
    if (rv != EXR_ERR_SUCCESS)
        return rv;
    if (!p->compressed_buffer || p->compressed_bytes == 0)
        return EXR_ERR_INVALID_ARGUMENT;
    if (p->compressed_bytes > s->cap) {
        uint8_t *nd = realloc(s->data, p->compressed_bytes);
        s->step = "keeping an encoded chunk";
        if (!nd)
            return EXR_ERR_OUT_OF_MEMORY;
        s->data = nd;
        s->cap = p->compressed_bytes;
    }
    memcpy(s->data, p->compressed_buffer, p->compressed_bytes);
    s->size = p->compressed_bytes;
    return EXR_ERR_SUCCESS;
}

static bool grow(uint8_t **buf, size_t *cap, size_t need)
{
    uint8_t *nd;
    if (*cap >= need)
        return true;
    nd = realloc(*buf, need);
    if (!nd)
        return false;
    *buf = nd;
    *cap = need;
    return true;
}

/* Whether rows [y, y + h) of every channel written hold the same bits as
 * rows [y0, y0 + h) (film planes are 4-byte samples). */
static bool same_rows(const mr_film *film, const enc_layout *L, int y, int y0, int h)
{
    size_t w = (size_t)film->width, n = (size_t)h * w * 4;
    for (int c = 0; c < L->count; c++) {
        const uint8_t *p = L->ch[c].def->plane;
        if (memcmp(p + (size_t)y * w * 4, p + (size_t)y0 * w * 4, n) != 0)
            return false;
    }
    return true;
}

/* NONE, ZIP and ZIPS without the library's pipeline: the chunk is packed by
 * pack_rows or, for the ZIP codecs, packed, reordered and predicted as the
 * codec expects in one pass (pack_predict_rows) and deflated into the zlib format (which zlib's inflate, used by
 * OpenEXR's readers, decodes) by util/deflate.h or, at the levels that ask
 * for it, libdeflate. As the library does, a chunk that does not shrink is
 * stored packed: the readers take a chunk whose size equals its unpacked
 * size as uncompressed, so a compressed chunk must be strictly smaller.
 *
 * Empty background is most of a typical frame: a chunk whose film rows
 * hold the same bits as those of the last chunk this worker compressed
 * (rows of background, all alike) reuses that chunk's compressed bytes,
 * found by comparing the film before anything is packed. The bytes are the
 * same as compressing again (the packing and both compressors are
 * deterministic), so the file does not depend on which worker took which
 * chunk. */
static exr_result_t encode_chunk_own(enc_batch *b, enc_worker *w, enc_slot *s)
{
    const mr_film *film = b->film;
    size_t raw = (size_t)s->cinfo.height * (size_t)film->width * b->layout.pixel_bytes, got;
    int y = s->cinfo.start_y, h = s->cinfo.height;

    s->step = "packing a chunk (layout mismatch)";
    if (raw != s->cinfo.unpacked_size || raw == 0)
        return EXR_ERR_INVALID_ARGUMENT;
    s->step = "keeping an encoded chunk";
    if (b->ctype == EXR_COMPRESSION_NONE) {
        if (!grow(&s->data, &s->cap, raw))
            return EXR_ERR_OUT_OF_MEMORY;
        s->size = pack_rows(film, &b->layout, y, h, s->data);
        return EXR_ERR_SUCCESS;
    }
    if (w->last_h == h && same_rows(film, &b->layout, y, w->last_y, h)) {
        if (!grow(&s->data, &s->cap, w->last_size))
            return EXR_ERR_OUT_OF_MEMORY;
        memcpy(s->data, w->last_out, w->last_size);
        s->size = w->last_size;
        return EXR_ERR_SUCCESS;
    }
    if (!grow(&w->predicted, &w->predicted_cap, raw) ||
        !grow(&w->last_out, &w->last_cap, raw) ||
        (!w->row_buf && !(w->row_buf = malloc(4 * (size_t)film->width))))
        return EXR_ERR_OUT_OF_MEMORY;
    if (b->level < MR_ZIP_LEVEL_LIBDEFLATE && !w->fast) {
        s->step = "mr_deflate_new";
        if (!(w->fast = mr_deflate_new()))
            return EXR_ERR_OUT_OF_MEMORY;
    } else if (b->level >= MR_ZIP_LEVEL_LIBDEFLATE && !w->deflate) {
        s->step = "libdeflate_alloc_compressor";
        if (!(w->deflate = libdeflate_alloc_compressor(b->level)))
            return EXR_ERR_OUT_OF_MEMORY;
    }
    pack_predict_rows(film, &b->layout, y, h, w->row_buf, w->predicted, raw);
    /* Into last_out (chunk-sized, kept by the worker), then only the
     * compressed bytes to the slot. 0 when the stream would not fit in
     * raw - 1 bytes: store packed. A scanline is width * pixel_bytes bytes,
     * half of them even-indexed, so the byte above one in the predicted
     * halves is row bytes back. */
    w->last_h = 0; /* last_out is being overwritten */
    if (raw <= 1)
        got = 0;
    else if (w->fast)
        got = mr_deflate_zlib(w->fast, w->predicted, raw, b->row, w->last_out, raw - 1);
    else
        got = libdeflate_zlib_compress(w->deflate, w->predicted, raw, w->last_out, raw - 1);
    if (got == 0)
        got = pack_rows(film, &b->layout, y, h, w->last_out);
    s->step = "keeping an encoded chunk";
    if (!grow(&s->data, &s->cap, got))
        return EXR_ERR_OUT_OF_MEMORY;
    memcpy(s->data, w->last_out, got);
    s->size = got;
    w->last_size = got;
    w->last_y = y;
    w->last_h = h;
    return EXR_ERR_SUCCESS;
}

static exr_result_t encode_chunk(enc_batch *b, enc_worker *w, enc_slot *s)
{
    return b->ctype == EXR_COMPRESSION_PIZ ? encode_chunk_library(b, w, s)
                                           : encode_chunk_own(b, w, s);
}

static void encode_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    enc_batch *b = ctx;
    enc_worker *w = &b->workers[worker];
    exr_io *saved = t_sink;
    exr_io sink;
    size_t i;

    /* Library messages raised on this thread land in a private sink and are
     * copied to the chunk they belong to (see the file comment). */
    memset(&sink, 0, sizeof sink);
    t_sink = &sink;
    for (i = begin; i < end; i++) {
        enc_slot *s = &b->slots[i];
        if (atomic_load(&b->failed))
            break;
        sink.msg[0] = '\0';
        s->rv = encode_chunk(b, w, s);
        s->done = true;
        if (s->rv != EXR_ERR_SUCCESS) {
            snprintf(s->msg, sizeof s->msg, "%s", sink.msg);
            atomic_store(&b->failed, true);
        }
    }
    t_sink = saved;
}

/* The written header's channel list as an enc_layout: file order, each
 * channel one of the film's (ch[0, n)) with the type we asked for. */
static int read_layout(exr_context_t ctxt, int part, const chan_def *ch, int n, enc_layout *L,
                       const exr_io *io, mr_error *err)
{
    const exr_attr_chlist_t *chans = NULL;
    int c;

    memset(L, 0, sizeof *L);
    if (exr_get_channels(ctxt, part, &chans) != EXR_ERR_SUCCESS || !chans ||
        chans->num_channels != n)
        return mr_error_set(err, MR_ERR_FORMAT, "%s: EXR write: unexpected channel list",
                            io->name);
    for (c = 0; c < chans->num_channels; c++) {
        const exr_attr_chlist_entry_t *e = &chans->entries[c];
        int ci = chan_find(ch, n, e->name.str);
        if (ci < 0 || e->pixel_type != ch[ci].type)
            return mr_error_set(err, MR_ERR_FORMAT,
                                "%s: EXR write: unexpected channel '%s' in the header",
                                io->name, e->name.str ? e->name.str : "");
        L->ch[c].def = &ch[ci];
        L->pixel_bytes += e->pixel_type == EXR_PIXEL_HALF ? 2u : 4u;
    }
    L->count = chans->num_channels;
    return MR_OK;
}

/* ------------------------------------------------------------------ */
/* standard attributes                                                 */

/* An OpenEXR M44f (row vectors: p' = p M, translation in the last row) of
 * our column-vector matrix a (p' = a p). */
static exr_attr_m44f_t to_m44f(const double a[16])
{
    exr_attr_m44f_t m;
    for (int r = 0; r < 4; r++)
        for (int c = 0; c < 4; c++)
            m.m[r * 4 + c] = (float)a[c * 4 + r];
    return m;
}

static void mul4(const double a[16], const double b[16], double out[16])
{
    for (int r = 0; r < 4; r++)
        for (int c = 0; c < 4; c++) {
            double v = 0;
            for (int k = 0; k < 4; k++)
                v += a[r * 4 + k] * b[k * 4 + c];
            out[r * 4 + c] = v;
        }
}

/* World to OpenEXR camera space (+z the viewing direction) and to NDC, as
 * column-vector matrices, from the film's camera; and the screen window's
 * width on the z = 1 plane. The camera is rigid (rotation and
 * translation), so its inverse is the transposed rotation. */
static void camera_matrices(const mr_film *f, double w2c[16], double w2ndc[16], double *sw)
{
    const float *m = f->camera_to_world.m;
    double th = tan(0.5 * (double)f->yfov), aspect = (double)f->width / (double)f->height;
    double W = 2.0 * th * aspect, H = 2.0 * th;
    /* inverse of [R t; 0 1] is [R^T, -R^T t], then z flipped: our camera
     * looks down its -z, OpenEXR's down +z */
    for (int r = 0; r < 3; r++) {
        double flip = r == 2 ? -1.0 : 1.0, t = 0;
        for (int c = 0; c < 3; c++) {
            w2c[r * 4 + c] = flip * (double)m[c * 4 + r];
            t += (double)m[c * 4 + r] * (double)m[c * 4 + 3];
        }
        w2c[r * 4 + 3] = -flip * t;
    }
    w2c[12] = w2c[13] = w2c[14] = 0;
    w2c[15] = 1;
    /* NDC: x = X / (Z W) + 1/2, y = 1/2 - Y / (Z H) after the divide by
     * w = Z; z becomes 1 / Z (so the matrix stays invertible). */
    const double proj[16] = {1.0 / W, 0, 0.5, 0, 0, -1.0 / H, 0.5, 0, 0, 0, 0, 1, 0, 0, 1, 0};
    mul4(proj, w2c, w2ndc);
    *sw = W;
}

/* fps as the rational the framesPerSecond attribute holds: the simplest
 * fraction within 1e-9 relative (continued fractions; 24 -> 24/1,
 * 29.97 -> 2997/100, 30000/1001 -> 30000/1001). */
static exr_attr_rational_t fps_rational(double fps)
{
    double x = fps;
    long long h0 = 1, h1 = 0, k0 = 0, k1 = 1; /* convergents h/k */
    exr_attr_rational_t best = {(int32_t)lround(fps), 1};
    for (int i = 0; i < 32; i++) {
        double a = floor(x);
        long long h = (long long)a * h0 + h1, k = (long long)a * k0 + k1;
        if (h > INT32_MAX || k > (long long)UINT32_MAX)
            break;
        best.num = (int32_t)h;
        best.denom = (uint32_t)k;
        if (fabs((double)h / (double)k - fps) <= 1e-9 * fps || x - a < 1e-12)
            break;
        h1 = h0;
        h0 = h;
        k1 = k0;
        k0 = k;
        x = 1.0 / (x - a);
    }
    return best;
}

/* Appends name as a JSON string (quotes, backslashes and control bytes
 * escaped; UTF-8 passes as it is). out has room for 6 * strlen + 3. */
static size_t json_string(char *out, const char *name)
{
    size_t n = 0;
    out[n++] = '"';
    for (const unsigned char *p = (const unsigned char *)name; *p; p++) {
        if (*p == '"' || *p == '\\') {
            out[n++] = '\\';
            out[n++] = (char)*p;
        } else if (*p < 0x20 || *p == 0x7f) {
            n += (size_t)sprintf(out + n, "\\u%04x", *p);
        } else {
            out[n++] = (char)*p;
        }
    }
    out[n++] = '"';
    out[n] = '\0';
    return n;
}

const char *mr_crypto_name(const mr_job *job, int layer, size_t i, char buf[32])
{
    const char *name = layer == MR_CRYPTO_OBJECT ? job->objects[i].name : job->assets[i].name;
    if (name)
        return name;
    snprintf(buf, 32, "%s%zu", layer == MR_CRYPTO_OBJECT ? "object" : "asset", i);
    return buf;
}

/* The manifest of a Cryptomatte layer: {"name":"8 hex digits", ...}, each
 * name once (objects may share a name, and then share an id). NULL when
 * out of memory. */
static char *crypto_manifest(const mr_job *job, int layer)
{
    size_t count = layer == MR_CRYPTO_OBJECT ? job->object_count : job->asset_count, cap = 3, n;
    char buf[32], other_buf[32], *out;
    for (size_t i = 0; i < count; i++)
        cap += 6 * strlen(mr_crypto_name(job, layer, i, buf)) + 16;
    out = malloc(cap);
    if (!out)
        return NULL;
    n = 0;
    out[n++] = '{';
    for (size_t i = 0; i < count; i++) {
        const char *name = mr_crypto_name(job, layer, i, buf);
        bool seen = false;
        for (size_t j = 0; j < i && !seen; j++)
            seen = strcmp(mr_crypto_name(job, layer, j, other_buf), name) == 0;
        if (seen)
            continue;
        if (n > 1)
            out[n++] = ',';
        n += json_string(out + n, name);
        n += (size_t)sprintf(out + n, ":\"%08x\"", (unsigned)mr_cryptomatte_id_bits(name));
    }
    out[n++] = '}';
    out[n] = '\0';
    return out;
}

void mr_exr_meta_for_frame(mr_exr_meta *meta, const mr_job *job, const mr_frame_stats *st)
{
    struct passwd pw, *found = NULL;
    char buf[1024];

    memset(meta, 0, sizeof *meta);
    if (job) {
        snprintf(meta->job, sizeof meta->job, "%s", job->name ? job->name : "");
        meta->fps = job->fps;
        meta->source = job;
    }
    if (st) {
        meta->frame = st->frame;
        meta->time = st->time;
        meta->render_seconds = st->total_s;
        meta->scene_diagonal = st->scene_diagonal;
    }
    meta->capture_time = (int64_t)time(NULL);
    if (getpwuid_r(geteuid(), &pw, buf, sizeof buf, &found) == 0 && found && pw.pw_name)
        snprintf(meta->owner, sizeof meta->owner, "%s", pw.pw_name);
    else
        snprintf(meta->owner, sizeof meta->owner, "uid %u", (unsigned)geteuid());
}

/* The header attributes beyond the required ones (microray.h, "EXR"). */
static exr_result_t write_attributes(exr_context_t ctxt, int part, const mr_film *film,
                                     const mr_exr_meta *meta, const char **step)
{
    /* Rec. 709 primaries and D65 white: the linear RGB we shade in. */
    static const exr_attr_chromaticities_t rec709 = {0.64f, 0.33f, 0.30f, 0.60f,
                                                     0.15f, 0.06f, 0.3127f, 0.3290f};
    exr_result_t rv;

#define ATTR(call, what)                                                            \
    do {                                                                            \
        *step = (what);                                                             \
        if ((rv = (call)) != EXR_ERR_SUCCESS)                                       \
            return rv;                                                              \
    } while (0)

    ATTR(exr_attr_set_string(ctxt, part, "microray.version", MR_VERSION_STRING),
         "exr_attr_set_string(microray.version)");
    ATTR(exr_attr_set_chromaticities(ctxt, part, "chromaticities", &rec709),
         "exr_attr_set_chromaticities(chromaticities)");
    if (film->has_camera) {
        double w2c[16], w2ndc[16], sw;
        exr_attr_v2f_t center = {{{0.0f, 0.0f}}};
        camera_matrices(film, w2c, w2ndc, &sw);
        exr_attr_m44f_t a = to_m44f(w2c), b = to_m44f(w2ndc);
        ATTR(exr_attr_set_m44f(ctxt, part, "worldToCamera", &a),
             "exr_attr_set_m44f(worldToCamera)");
        ATTR(exr_attr_set_m44f(ctxt, part, "worldToNDC", &b), "exr_attr_set_m44f(worldToNDC)");
        ATTR(exr_set_screen_window_width(ctxt, part, (float)sw), "exr_set_screen_window_width");
        ATTR(exr_set_screen_window_center(ctxt, part, &center),
             "exr_set_screen_window_center");
    }
    if (film->aovs & MR_AOV_CRYPTOMATTE) {
        for (int l = 0; l < MR_CRYPTO_LAYERS; l++) {
            char key[16], name[64];
            const char *layer = k_crypto_layer[l];
            snprintf(key, sizeof key, "%08x", (unsigned)mr_murmur3_32(layer, strlen(layer), 0));
            key[7] = '\0';
            snprintf(name, sizeof name, "cryptomatte/%s/name", key);
            ATTR(exr_attr_set_string(ctxt, part, name, layer), "exr_attr_set_string(cryptomatte)");
            snprintf(name, sizeof name, "cryptomatte/%s/hash", key);
            ATTR(exr_attr_set_string(ctxt, part, name, "MurmurHash3_32"),
                 "exr_attr_set_string(cryptomatte)");
            snprintf(name, sizeof name, "cryptomatte/%s/conversion", key);
            ATTR(exr_attr_set_string(ctxt, part, name, "uint32_to_float32"),
                 "exr_attr_set_string(cryptomatte)");
            if (meta && meta->source) {
                char *manifest = crypto_manifest(meta->source, l);
                *step = "building a Cryptomatte manifest";
                if (!manifest)
                    return EXR_ERR_OUT_OF_MEMORY;
                snprintf(name, sizeof name, "cryptomatte/%s/manifest", key);
                rv = exr_attr_set_string(ctxt, part, name, manifest);
                free(manifest);
                ATTR(rv, "exr_attr_set_string(cryptomatte manifest)");
            }
        }
    }
    if (!meta)
        return EXR_ERR_SUCCESS;
    ATTR(exr_attr_set_string(ctxt, part, "microray.job", meta->job),
         "exr_attr_set_string(microray.job)");
    ATTR(exr_attr_set_int(ctxt, part, "microray.frame", meta->frame),
         "exr_attr_set_int(microray.frame)");
    ATTR(exr_attr_set_double(ctxt, part, "microray.time", meta->time),
         "exr_attr_set_double(microray.time)");
    ATTR(exr_attr_set_double(ctxt, part, "microray.renderSeconds", meta->render_seconds),
         "exr_attr_set_double(microray.renderSeconds)");
    ATTR(exr_attr_set_float(ctxt, part, "microray.sceneDiagonal", meta->scene_diagonal),
         "exr_attr_set_float(microray.sceneDiagonal)");
    if (meta->fps > 0) {
        exr_attr_rational_t r = fps_rational(meta->fps);
        ATTR(exr_attr_set_rational(ctxt, part, "framesPerSecond", &r),
             "exr_attr_set_rational(framesPerSecond)");
    }
    if (meta->owner[0])
        ATTR(exr_attr_set_string(ctxt, part, "owner", meta->owner), "exr_attr_set_string(owner)");
    if (meta->capture_time) {
        time_t t = (time_t)meta->capture_time;
        struct tm local;
        char date[96];
        *step = "localtime_r (capDate)";
        if (!localtime_r(&t, &local))
            return EXR_ERR_INVALID_ARGUMENT;
        snprintf(date, sizeof date, "%04d:%02d:%02d %02d:%02d:%02d", local.tm_year + 1900,
                 local.tm_mon + 1, local.tm_mday, local.tm_hour, local.tm_min, local.tm_sec);
        ATTR(exr_attr_set_string(ctxt, part, "capDate", date), "exr_attr_set_string(capDate)");
        ATTR(exr_attr_set_float(ctxt, part, "utcOffset", (float)-local.tm_gmtoff),
             "exr_attr_set_float(utcOffset)");
    }
    {
        char comments[256];
        snprintf(comments, sizeof comments,
                 "Rendered by microray %s: job %s, frame %d at %.6g s on the job's timeline",
                 MR_VERSION_STRING, meta->job[0] ? meta->job : "(unnamed)", meta->frame,
                 meta->time);
        ATTR(exr_attr_set_string(ctxt, part, "comments", comments),
             "exr_attr_set_string(comments)");
    }
#undef ATTR
    return EXR_ERR_SUCCESS;
}

static int write_impl(exr_io *io, const mr_film *film, const mr_exr_options *opt,
                      const mr_exr_meta *meta, mr_error *err)
{
    exr_context_initializer_t init = EXR_DEFAULT_CONTEXT_INITIALIZER;
    exr_context_t ctxt = NULL;
    exr_compression_t ctype = EXR_COMPRESSION_NONE;
    exr_result_t rv;
    enc_batch b;
    size_t nslots = 0, chunks, first, k, chunk_bytes;
    unsigned threads, t;
    int32_t lines = 0;
    int part = 0, level = 0, i, rc, nch;
    const char *step = "";
    chan_def ch[CH_MAX];

    memset(&b, 0, sizeof b);
    atomic_init(&b.failed, false);
    if ((rc = check_film(film, err)) < 0 || (rc = check_options(opt, &ctype, &level, err)) < 0 ||
        (rc = check_meta(meta, err)) < 0)
        return rc;
    threads = opt && opt->threads ? opt->threads : mr_cpu_count();
    if (threads > ENC_MAX_THREADS)
        threads = ENC_MAX_THREADS;

    init.error_handler_fn = on_exr_error;
    init.user_data = io;
    init.write_fn = io->fd >= 0 ? io_write_fd : io_write_mem;

#define EXR_TRY(call, what)                                                         \
    do {                                                                            \
        step = (what);                                                              \
        rv = (call);                                                                \
        if (rv != EXR_ERR_SUCCESS)                                                  \
            goto fail;                                                              \
    } while (0)

    EXR_TRY(exr_start_write(&ctxt, io->name, EXR_WRITE_FILE_DIRECTLY, &init),
            "exr_start_write");
    EXR_TRY(exr_add_part(ctxt, NULL, EXR_STORAGE_SCANLINE, &part), "exr_add_part");
    EXR_TRY(exr_initialize_required_attr_simple(ctxt, part, film->width, film->height,
                                                ctype),
            "exr_initialize_required_attr_simple");
    nch = film_channels(film, opt && opt->half_normals, ch);
    for (i = 0; i < nch; i++) {
        /* pLinear only steers the lossy B44 codec, which we never use; 0 is
         * what the C++ library writes by default. */
        EXR_TRY(exr_add_channel(ctxt, part, ch[i].name, ch[i].type,
                                EXR_PERCEPTUALLY_LOGARITHMIC, 1, 1),
                "exr_add_channel");
    }
    if ((rv = write_attributes(ctxt, part, film, meta, &step)) != EXR_ERR_SUCCESS)
        goto fail;

    EXR_TRY(exr_write_header(ctxt), "exr_write_header");
    EXR_TRY(exr_get_scanlines_per_chunk(ctxt, part, &lines), "exr_get_scanlines_per_chunk");
    if (lines < 1 || lines > 256) {
        rv = EXR_ERR_UNKNOWN;
        step = "exr_get_scanlines_per_chunk (unexpected value)";
        goto fail;
    }

    /* Chunks are encoded a batch at a time by all workers, then written in
     * chunk order by this thread, which is the only one that touches the
     * file and the chunk table. The bytes of a chunk depend on nothing but
     * its pixels, so the file is the same for every thread count. */
    if ((rc = read_layout(ctxt, part, ch, nch, &b.layout, io, err)) < 0)
        goto cleanup;
    b.film = film;
    b.ctype = ctype;
    b.level = level;
    b.row = (size_t)film->width * b.layout.pixel_bytes / 2;
    chunks = ((size_t)film->height + (size_t)lines - 1) / (size_t)lines;
    chunk_bytes = (size_t)lines * (size_t)film->width * b.layout.pixel_bytes;
    nslots = ENC_BATCH_BYTES / chunk_bytes;
    /* Several chunks per worker keep uneven chunks (sky compresses faster
     * than geometry) from idling workers at the end of a batch. */
    if (nslots < 8u * (size_t)threads)
        nslots = 8u * (size_t)threads;
    if (nslots > chunks)
        nslots = chunks;
    b.ctxt = ctxt;
    b.part = part;
    b.slots = calloc(nslots, sizeof *b.slots);
    b.workers = calloc(threads, sizeof *b.workers);
    if (!b.slots || !b.workers) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "%s: EXR write: out of memory", io->name);
        goto cleanup;
    }
    for (t = 0; t < threads; t++)
        b.workers[t].batch = &b;

    for (first = 0; first < chunks; first += nslots) {
        size_t n = chunks - first < nslots ? chunks - first : nslots;

        for (k = 0; k < n; k++) {
            enc_slot *s = &b.slots[k];
            int y = (int)((first + k) * (size_t)lines);
            EXR_TRY(exr_write_scanline_chunk_info(ctxt, part, y, &s->cinfo),
                    "exr_write_scanline_chunk_info");
            if (s->cinfo.start_y != y || s->cinfo.height < 1 || s->cinfo.height > lines ||
                y + s->cinfo.height > film->height) {
                rv = EXR_ERR_UNKNOWN;
                step = "exr_write_scanline_chunk_info (unexpected chunk)";
                goto fail;
            }
            s->done = false;
            s->rv = EXR_ERR_SUCCESS;
            s->step = "";
            s->msg[0] = '\0';
        }

        mr_parallel_for(threads, n, 1, encode_range, &b);

        if (atomic_load(&b.failed)) {
            /* Report the first failed chunk in file order. */
            for (k = 0; k < n; k++) {
                const enc_slot *s = &b.slots[k];
                if (s->done && s->rv != EXR_ERR_SUCCESS) {
                    rv = s->rv;
                    step = s->step;
                    snprintf(io->msg, sizeof io->msg, "%s", s->msg);
                    goto fail;
                }
            }
            rv = EXR_ERR_UNKNOWN;
            step = "encoding (no failed chunk recorded)";
            goto fail;
        }
        for (k = 0; k < n; k++) {
            const enc_slot *s = &b.slots[k];
            if (!s->done) {
                rv = EXR_ERR_UNKNOWN;
                step = "encoding (chunk skipped)";
                goto fail;
            }
            EXR_TRY(exr_write_scanline_chunk(ctxt, part, s->cinfo.start_y, s->data, s->size),
                    "exr_write_scanline_chunk");
        }
    }

    for (t = 0; t < threads; t++) {
        if (b.workers[t].ready) {
            b.workers[t].ready = false;
            EXR_TRY(exr_encoding_destroy(ctxt, &b.workers[t].pipe), "exr_encoding_destroy");
        }
    }
    step = "exr_finish";
    rv = exr_finish(&ctxt); /* writes the chunk offset table */
    if (rv != EXR_ERR_SUCCESS)
        goto fail;
    rc = MR_OK;
    goto cleanup;

#undef EXR_TRY

fail:
    rc = exr_fail(err, io, true, step, rv);
cleanup:
    if (b.workers) {
        for (t = 0; t < threads; t++) {
            if (b.workers[t].ready)
                exr_encoding_destroy(ctxt, &b.workers[t].pipe);
            mr_deflate_free(b.workers[t].fast);
            if (b.workers[t].deflate)
                libdeflate_free_compressor(b.workers[t].deflate);
            free(b.workers[t].predicted);
            free(b.workers[t].row_buf);
            free(b.workers[t].last_out);
        }
        free(b.workers);
    }
    if (b.slots) {
        for (k = 0; k < nslots; k++)
            free(b.slots[k].data);
        free(b.slots);
    }
    if (ctxt)
        exr_finish(&ctxt);
    return rc;
}

int mr_exr_write_file(const char *path, const mr_film *film, const mr_exr_options *opt,
                      const mr_exr_meta *meta, mr_error *err)
{
    exr_io io;
    exr_io *saved = t_sink;
    exr_compression_t ctype;
    mr_fs_atomic file;
    int level, rc;

    if (!path || !path[0])
        return mr_error_set(err, MR_ERR_INVALID, "EXR write: empty path");
    /* Validate before touching the file system. */
    if ((rc = check_film(film, err)) < 0 || (rc = check_options(opt, &ctype, &level, err)) < 0 ||
        (rc = check_meta(meta, err)) < 0)
        return rc;

    /* Encode into a unique temporary next to the target, renamed into place
     * once complete and synced (util/file_io.h): readers (the HTTP side)
     * never see a partial frame, and a failed write leaves an existing file
     * untouched. */
    if ((rc = mr_fs_atomic_begin(&file, path, path, err)) < 0)
        return rc;
    memset(&io, 0, sizeof io);
    io.name = path;
    io.fd = file.fd;

    t_sink = &io;
    rc = write_impl(&io, film, opt, meta, err);
    t_sink = saved;

    if (rc == MR_OK)
        return mr_fs_atomic_commit(&file, NULL, path, err);
    mr_fs_atomic_abort(&file);
    return rc;
}

int mr_exr_write_memory(uint8_t **data, size_t *size, const mr_film *film,
                        const mr_exr_options *opt, const mr_exr_meta *meta, mr_error *err)
{
    exr_io io;
    exr_io *saved = t_sink;
    int rc;

    if (!data || !size)
        return mr_error_set(err, MR_ERR_INVALID, "EXR write: output pointers are NULL");
    *data = NULL;
    *size = 0;
    memset(&io, 0, sizeof io);
    io.name = "<memory>";
    io.fd = -1;

    t_sink = &io;
    rc = write_impl(&io, film, opt, meta, err);
    t_sink = saved;

    if (rc != MR_OK) {
        free(io.data);
        return rc;
    }
    *data = io.data;
    *size = io.size;
    return MR_OK;
}

/* ------------------------------------------------------------------ */
/* reading                                                             */

static void read_meta(exr_context_t ctxt, mr_exr_meta *meta)
{
    const char *s = NULL;
    int32_t len = 0, iv;
    double dv;
    float fv;

    /* Absent or mistyped attributes simply leave the zero default. */
    if (exr_attr_get_string(ctxt, 0, "microray.job", &len, &s) == EXR_ERR_SUCCESS && s &&
        len >= 0) {
        size_t n = (size_t)len < sizeof meta->job - 1 ? (size_t)len : sizeof meta->job - 1;
        memcpy(meta->job, s, n);
        meta->job[n] = '\0';
    }
    if (exr_attr_get_int(ctxt, 0, "microray.frame", &iv) == EXR_ERR_SUCCESS)
        meta->frame = iv;
    if (exr_attr_get_double(ctxt, 0, "microray.time", &dv) == EXR_ERR_SUCCESS)
        meta->time = dv;
    if (exr_attr_get_double(ctxt, 0, "microray.renderSeconds", &dv) == EXR_ERR_SUCCESS)
        meta->render_seconds = dv;
    if (exr_attr_get_float(ctxt, 0, "microray.sceneDiagonal", &fv) == EXR_ERR_SUCCESS)
        meta->scene_diagonal = fv;
}

/* Whether a decoded channel goes into the film: a known name, full
 * resolution, and the chunk's size. */
static bool channel_wanted(const exr_coding_channel_info_t *ch, const mr_film *film,
                           const exr_chunk_info_t *cinfo, const chan_def *known, int nknown)
{
    return chan_find(known, nknown, ch->channel_name) >= 0 && ch->x_samples == 1 &&
           ch->y_samples == 1 && ch->width == film->width && ch->height == cinfo->height;
}

/* The passes (beyond MR_AOV_DEFAULT) and Cryptomatte ranks of a file's
 * channels: every name we write is recognised; others are skipped. */
static unsigned file_passes(const exr_attr_chlist_t *chans, int *ranks)
{
    mr_film every = {.aovs = MR_AOV_ALL, .crypto_ranks = MR_CRYPTO_MAX_RANKS};
    chan_def ch[CH_MAX];
    int n = film_channels(&every, false, ch);
    unsigned aovs = MR_AOV_DEFAULT;
    *ranks = 0;
    for (int i = 0; chans && i < chans->num_channels; i++) {
        const exr_attr_chlist_entry_t *e = &chans->entries[i];
        int ci = chan_find(ch, n, e->name.str);
        if (ci < 0 || e->x_sampling != 1 || e->y_sampling != 1)
            continue;
        aovs |= ch[ci].aov;
        if (ch[ci].rank + 1 > *ranks)
            *ranks = ch[ci].rank + 1;
    }
    return aovs;
}

static int read_impl(exr_io *io, mr_film **out, mr_exr_meta *meta, mr_error *err)
{
    uint8_t *scratch = NULL;
    size_t scratch_size = 0;
    exr_context_initializer_t init = EXR_DEFAULT_CONTEXT_INITIALIZER;
    exr_context_t ctxt = NULL;
    exr_decode_pipeline_t dec = EXR_DECODE_PIPELINE_INITIALIZER;
    bool dec_ready = false, routines_chosen = false;
    exr_storage_t storage;
    exr_attr_box2i_t dw;
    const exr_attr_chlist_t *chans = NULL;
    exr_result_t rv;
    mr_film *film = NULL;
    int64_t w64, h64;
    int32_t lines = 0;
    int count = 0, matched = 0, rc, i, ranks = 0, nknown = 0;
    unsigned aovs;
    chan_def known[CH_MAX];
    int64_t y;
    const char *step = "";

    init.error_handler_fn = on_exr_error;
    init.user_data = io;
    init.read_fn = io_read_fd;
    init.size_fn = io_size_fd;
    /* A damaged offset table is an error, not something to guess around. */
    init.flags = EXR_CONTEXT_FLAG_DISABLE_CHUNK_RECONSTRUCTION;

#define EXR_TRY(call, what)                                                         \
    do {                                                                            \
        step = (what);                                                              \
        rv = (call);                                                                \
        if (rv != EXR_ERR_SUCCESS)                                                  \
            goto fail;                                                              \
    } while (0)

    EXR_TRY(exr_start_read(&ctxt, io->name, &init), "exr_start_read");
    EXR_TRY(exr_get_count(ctxt, &count), "exr_get_count");
    if (count < 1) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: EXR file has no parts", io->name);
        goto cleanup;
    }
    EXR_TRY(exr_get_storage(ctxt, 0, &storage), "exr_get_storage");
    if (storage != EXR_STORAGE_SCANLINE) {
        rc = mr_error_set(err, MR_ERR_FORMAT,
                          "%s: EXR part 0 is %s, only flat scanline images are supported",
                          io->name,
                          storage == EXR_STORAGE_TILED           ? "tiled"
                          : storage == EXR_STORAGE_DEEP_SCANLINE ? "deep scanline"
                          : storage == EXR_STORAGE_DEEP_TILED    ? "deep tiled"
                                                                 : "of unknown storage");
        goto cleanup;
    }
    EXR_TRY(exr_get_data_window(ctxt, 0, &dw), "exr_get_data_window");
    w64 = (int64_t)dw.max.x - (int64_t)dw.min.x + 1;
    h64 = (int64_t)dw.max.y - (int64_t)dw.min.y + 1;
    if (w64 < 1 || h64 < 1) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: EXR data window (%d %d)-(%d %d) is empty",
                          io->name, dw.min.x, dw.min.y, dw.max.x, dw.max.y);
        goto cleanup;
    }
    if (w64 > MR_MAX_RESOLUTION || h64 > MR_MAX_RESOLUTION) {
        rc = mr_error_set(err, MR_ERR_LIMIT,
                          "%s: EXR image %lldx%lld exceeds the film cap of %d per side",
                          io->name, (long long)w64, (long long)h64, MR_MAX_RESOLUTION);
        goto cleanup;
    }
    EXR_TRY(exr_get_channels(ctxt, 0, &chans), "exr_get_channels");
    aovs = file_passes(chans, &ranks);
    rc = mr_film_new_aovs((int)w64, (int)h64, aovs, ranks, &film, err);
    if (rc < 0)
        goto cleanup;
    nknown = film_channels(film, false, known);
    if (meta) {
        memset(meta, 0, sizeof *meta);
        read_meta(ctxt, meta);
    }

    for (i = 0; chans && i < chans->num_channels; i++) {
        const exr_attr_chlist_entry_t *e = &chans->entries[i];
        if (chan_find(known, nknown, e->name.str) >= 0 && e->x_sampling == 1 &&
            e->y_sampling == 1)
            matched++;
    }
    if (matched == 0)
        goto done; /* nothing we know: an all-miss film, as documented */
    film->cleared = false; /* its planes get the file's values */

    EXR_TRY(exr_get_scanlines_per_chunk(ctxt, 0, &lines), "exr_get_scanlines_per_chunk");
    if (lines < 1) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: EXR reports %d scanlines per chunk",
                          io->name, lines);
        goto cleanup;
    }

    for (y = dw.min.y; y <= dw.max.y; y += lines) {
        exr_chunk_info_t cinfo;
        int c, used = 0;
        int64_t row;

        EXR_TRY(exr_read_scanline_chunk_info(ctxt, 0, (int)y, &cinfo),
                "exr_read_scanline_chunk_info");
        row = (int64_t)cinfo.start_y - dw.min.y;
        if (row < 0 || cinfo.height < 1 || row + cinfo.height > h64) {
            rc = mr_error_set(err, MR_ERR_FORMAT,
                              "%s: EXR chunk at scanline %lld has rows %d..+%d outside "
                              "the data window",
                              io->name, (long long)y, cinfo.start_y, cinfo.height);
            goto cleanup;
        }
        if (!dec_ready) {
            EXR_TRY(exr_decoding_initialize(ctxt, 0, &cinfo, &dec),
                    "exr_decoding_initialize");
            dec_ready = true;
        } else {
            EXR_TRY(exr_decoding_update(ctxt, 0, &cinfo, &dec), "exr_decoding_update");
        }
        /* Subsampled or unknown channels are decoded into a scratch
         * buffer and dropped. Not a NULL decode_to_ptr, which the API
         * allows: OpenEXRCore 3.1's unpackers for some channel layouts
         * write through it all the same (a SEGV at address 0, found by
         * tests/fuzz/fuzz_exr: uncompressed A plus two unknown UINT
         * channels). One buffer serves them all; its content is garbage. */
        size_t skip_need = 0;
        for (c = 0; c < dec.channel_count; c++) {
            const exr_coding_channel_info_t *ch = &dec.channels[c];
            if (!channel_wanted(ch, film, &cinfo, known, nknown) && ch->width > 0 &&
                ch->height > 0) {
                size_t need = (size_t)ch->width * (size_t)ch->height * 4u;
                skip_need = need > skip_need ? need : skip_need;
            }
        }
        if (skip_need > scratch_size) {
            uint8_t *grown = realloc(scratch, skip_need);
            if (!grown) {
                rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", io->name);
                goto cleanup;
            }
            scratch = grown;
            scratch_size = skip_need;
        }
        for (c = 0; c < dec.channel_count; c++) {
            exr_coding_channel_info_t *ch = &dec.channels[c];
            int ci = chan_find(known, nknown, ch->channel_name);
            if (!channel_wanted(ch, film, &cinfo, known, nknown)) {
                ch->decode_to_ptr = ch->width > 0 && ch->height > 0 ? scratch : NULL;
                ch->user_data_type = ch->data_type;
                ch->user_bytes_per_element = ch->bytes_per_element;
                ch->user_pixel_stride = ch->bytes_per_element;
                ch->user_line_stride = ch->width * ch->bytes_per_element;
                continue;
            }
            ch->decode_to_ptr = (uint8_t *)((uint32_t *)known[ci].plane +
                                            (size_t)row * (size_t)film->width);
            ch->user_data_type = (uint16_t)(known[ci].type == EXR_PIXEL_UINT ? EXR_PIXEL_UINT
                                                                             : EXR_PIXEL_FLOAT);
            ch->user_bytes_per_element = 4;
            ch->user_pixel_stride = 4;
            ch->user_line_stride = 4 * film->width;
            used++;
        }
        if (used == 0)
            continue;
        if (!routines_chosen) {
            EXR_TRY(exr_decoding_choose_default_routines(ctxt, 0, &dec),
                    "exr_decoding_choose_default_routines");
            routines_chosen = true;
        }
        EXR_TRY(exr_decoding_run(ctxt, 0, &dec), "exr_decoding_run");
    }

done:
    *out = film;
    film = NULL;
    rc = MR_OK;
    goto cleanup;

#undef EXR_TRY

fail:
    rc = exr_fail(err, io, false, step, rv);
cleanup:
    if (dec_ready)
        exr_decoding_destroy(ctxt, &dec);
    if (ctxt)
        exr_finish(&ctxt);
    mr_film_free(film);
    free(scratch);
    return rc;
}

int mr_exr_read_file(const char *path, mr_film **out, mr_exr_meta *meta, mr_error *err)
{
    exr_io io;
    exr_io *saved = t_sink;
    struct stat st;
    int rc;

    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "EXR read: out is NULL");
    *out = NULL;
    if (meta)
        memset(meta, 0, sizeof *meta);
    if (!path || !path[0])
        return mr_error_set(err, MR_ERR_INVALID, "EXR read: empty path");
    memset(&io, 0, sizeof io);
    io.name = path;
    io.fd = open(path, O_RDONLY | O_CLOEXEC);
    if (io.fd < 0)
        return mr_error_set(err, MR_ERR_IO, "%s: cannot open: %s", path, strerror(errno));
    if (fstat(io.fd, &st) != 0) {
        rc = mr_error_set(err, MR_ERR_IO, "%s: cannot stat: %s", path, strerror(errno));
        goto cleanup;
    }
    if (!S_ISREG(st.st_mode)) {
        rc = mr_error_set(err, MR_ERR_IO, "%s: not a regular file", path);
        goto cleanup;
    }
    io.file_size = (int64_t)st.st_size;

    t_sink = &io;
    rc = read_impl(&io, out, meta, err);
    t_sink = saved;
    if (rc != MR_OK && meta)
        memset(meta, 0, sizeof *meta);

cleanup:
    close(io.fd);
    return rc;
}
