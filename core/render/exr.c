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
 *  - Colour is converted to half here (mr_float_to_half), not by the
 *    library, so rounding, clamping and NaN/Inf handling are ours and tested.
 *  - Library messages arrive through an error callback. In 3.1.5 calling
 *    exr_get_user_data() from that callback deadlocks (the failing call
 *    still holds the context lock; measured), so the callback reaches the
 *    message buffer of the current call through a thread-local pointer that
 *    is set on entry to each public function and restored on exit. The
 *    library delivers errors on the thread that caused them.
 */
#include "render/exr.h"

#include <openexr.h>

#include <errno.h>
#include <fcntl.h>
#include <float.h>
#include <limits.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

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

enum { CH_COUNT = 10 };

typedef struct chan_def {
    const char *name;
    exr_pixel_type_t type; /* type in the file */
} chan_def;

/* The order here is ours (film order); the file's order is by name. */
static const chan_def k_chans[CH_COUNT] = {
    {"R", EXR_PIXEL_HALF},          {"G", EXR_PIXEL_HALF},
    {"B", EXR_PIXEL_HALF},          {"A", EXR_PIXEL_HALF},
    {"Z", EXR_PIXEL_FLOAT},         {"N.X", EXR_PIXEL_FLOAT},
    {"N.Y", EXR_PIXEL_FLOAT},       {"N.Z", EXR_PIXEL_FLOAT},
    {"id.object", EXR_PIXEL_UINT},  {"id.primitive", EXR_PIXEL_UINT},
};

/* Film plane for table index i (float or uint32, both 4 bytes). */
static void *film_plane(const mr_film *film, int i)
{
    switch (i) {
    case 0: return film->r;
    case 1: return film->g;
    case 2: return film->b;
    case 3: return film->a;
    case 4: return film->z;
    case 5: return film->nx;
    case 6: return film->ny;
    case 7: return film->nz;
    case 8: return film->object_id;
    case 9: return film->prim_id;
    default: return NULL;
    }
}

static int chan_index(const char *name)
{
    int i;

    if (!name)
        return -1;
    for (i = 0; i < CH_COUNT; i++)
        if (strcmp(name, k_chans[i].name) == 0)
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
    int i;

    if (!film)
        return mr_error_set(err, MR_ERR_INVALID, "EXR write: film is NULL");
    if (film->width <= 0 || film->height <= 0 || film->width > MR_MAX_RESOLUTION ||
        film->height > MR_MAX_RESOLUTION ||
        (size_t)film->width * (size_t)film->height > (size_t)MR_MAX_PIXELS)
        return mr_error_set(err, MR_ERR_INVALID, "EXR write: bad film size %dx%d",
                            film->width, film->height);
    for (i = 0; i < CH_COUNT; i++)
        if (!film_plane(film, i))
            return mr_error_set(err, MR_ERR_INVALID, "EXR write: film plane %s is NULL",
                                k_chans[i].name);
    return MR_OK;
}

static int check_options(const mr_exr_options *opt, exr_compression_t *ctype, int *level,
                         mr_error *err)
{
    mr_exr_options o = {MR_COMPRESSION_NONE, 0};

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
    return MR_OK;
}

/* Converts rows [y0, y0 + lines) of channel ci into dst (HALF or FLOAT
 * samples, tightly packed) and returns the pointer the encoder reads. */
static const uint8_t *stage_rows(const mr_film *film, int ci, int y0, int lines,
                                 uint8_t *dst)
{
    size_t w = (size_t)film->width;
    size_t first = (size_t)y0 * w, count = (size_t)lines * w, k;
    const float *src = film_plane(film, ci);

    switch (k_chans[ci].type) {
    case EXR_PIXEL_HALF: {
        uint16_t *h = (uint16_t *)(void *)dst;
        for (k = 0; k < count; k++)
            h[k] = mr_float_to_half(src[first + k]);
        return dst;
    }
    case EXR_PIXEL_FLOAT: {
        float *f = (float *)(void *)dst;
        for (k = 0; k < count; k++)
            f[k] = sanitize_float(src[first + k]);
        return dst;
    }
    default: /* UINT: ids go out untouched, straight from the film */
        return (const uint8_t *)((const uint32_t *)film_plane(film, ci) + first);
    }
}

static int write_impl(exr_io *io, const mr_film *film, const mr_exr_options *opt,
                      const mr_exr_meta *meta, mr_error *err)
{
    exr_context_initializer_t init = EXR_DEFAULT_CONTEXT_INITIALIZER;
    exr_context_t ctxt = NULL;
    exr_encode_pipeline_t enc = EXR_ENCODE_PIPELINE_INITIALIZER;
    bool enc_ready = false;
    exr_compression_t ctype = EXR_COMPRESSION_NONE;
    exr_result_t rv;
    uint8_t *scratch = NULL;
    size_t slot_bytes;
    int32_t lines = 0;
    int part = 0, level = 0, i, y, rc;
    const char *step = "";

    if ((rc = check_film(film, err)) < 0 || (rc = check_options(opt, &ctype, &level, err)) < 0 ||
        (rc = check_meta(meta, err)) < 0)
        return rc;

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
    for (i = 0; i < CH_COUNT; i++) {
        /* pLinear only steers the lossy B44 codec, which we never use; 0 is
         * what the C++ library writes by default. */
        EXR_TRY(exr_add_channel(ctxt, part, k_chans[i].name, k_chans[i].type,
                                EXR_PERCEPTUALLY_LOGARITHMIC, 1, 1),
                "exr_add_channel");
    }
    if (ctype == EXR_COMPRESSION_ZIP || ctype == EXR_COMPRESSION_ZIPS)
        EXR_TRY(exr_set_zip_compression_level(ctxt, part, level),
                "exr_set_zip_compression_level");

    EXR_TRY(exr_attr_set_string(ctxt, part, "microray.version", MR_VERSION_STRING),
            "exr_attr_set_string(microray.version)");
    if (meta) {
        EXR_TRY(exr_attr_set_string(ctxt, part, "microray.job", meta->job),
                "exr_attr_set_string(microray.job)");
        EXR_TRY(exr_attr_set_int(ctxt, part, "microray.frame", meta->frame),
                "exr_attr_set_int(microray.frame)");
        EXR_TRY(exr_attr_set_double(ctxt, part, "microray.time", meta->time),
                "exr_attr_set_double(microray.time)");
        EXR_TRY(exr_attr_set_double(ctxt, part, "microray.renderSeconds",
                                    meta->render_seconds),
                "exr_attr_set_double(microray.renderSeconds)");
        EXR_TRY(exr_attr_set_float(ctxt, part, "microray.sceneDiagonal",
                                   meta->scene_diagonal),
                "exr_attr_set_float(microray.sceneDiagonal)");
    }

    EXR_TRY(exr_write_header(ctxt), "exr_write_header");
    EXR_TRY(exr_get_scanlines_per_chunk(ctxt, part, &lines), "exr_get_scanlines_per_chunk");
    if (lines < 1 || lines > 256) {
        rv = EXR_ERR_UNKNOWN;
        step = "exr_get_scanlines_per_chunk (unexpected value)";
        goto fail;
    }

    /* One 4-byte slot per channel and chunk; half channels use half of it. */
    slot_bytes = (size_t)lines * (size_t)film->width * 4u;
    scratch = malloc(slot_bytes * CH_COUNT);
    if (!scratch) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "%s: EXR write: out of memory", io->name);
        goto cleanup;
    }

    for (y = 0; y < film->height; y += lines) {
        exr_chunk_info_t cinfo;
        int c;

        EXR_TRY(exr_write_scanline_chunk_info(ctxt, part, y, &cinfo),
                "exr_write_scanline_chunk_info");
        if (cinfo.start_y != y || cinfo.height < 1 || cinfo.height > lines ||
            y + cinfo.height > film->height) {
            rv = EXR_ERR_UNKNOWN;
            step = "exr_write_scanline_chunk_info (unexpected chunk)";
            goto fail;
        }
        if (!enc_ready) {
            EXR_TRY(exr_encoding_initialize(ctxt, part, &cinfo, &enc),
                    "exr_encoding_initialize");
            enc_ready = true;
        } else {
            EXR_TRY(exr_encoding_update(ctxt, part, &cinfo, &enc), "exr_encoding_update");
        }
        if (enc.channel_count != CH_COUNT) {
            rv = EXR_ERR_UNKNOWN;
            step = "exr_encoding_initialize (channel count)";
            goto fail;
        }
        for (c = 0; c < enc.channel_count; c++) {
            exr_coding_channel_info_t *ch = &enc.channels[c];
            int ci = chan_index(ch->channel_name);
            int bpe;
            if (ci < 0 || ch->width != film->width || ch->height != cinfo.height) {
                rv = EXR_ERR_UNKNOWN;
                step = "exr_encoding_initialize (channel mismatch)";
                goto fail;
            }
            bpe = k_chans[ci].type == EXR_PIXEL_HALF ? 2 : 4;
            ch->encode_from_ptr =
                stage_rows(film, ci, y, cinfo.height, scratch + (size_t)ci * slot_bytes);
            ch->user_data_type = (uint16_t)k_chans[ci].type;
            ch->user_bytes_per_element = (int16_t)bpe;
            ch->user_pixel_stride = bpe;
            ch->user_line_stride = bpe * film->width;
        }
        if (y == 0)
            EXR_TRY(exr_encoding_choose_default_routines(ctxt, part, &enc),
                    "exr_encoding_choose_default_routines");
        EXR_TRY(exr_encoding_run(ctxt, part, &enc), "exr_encoding_run");
    }

    EXR_TRY(exr_encoding_destroy(ctxt, &enc), "exr_encoding_destroy");
    enc_ready = false;
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
    if (enc_ready)
        exr_encoding_destroy(ctxt, &enc);
    if (ctxt)
        exr_finish(&ctxt);
    free(scratch);
    return rc;
}

int mr_exr_write_file(const char *path, const mr_film *film, const mr_exr_options *opt,
                      const mr_exr_meta *meta, mr_error *err)
{
    exr_io io;
    exr_io *saved = t_sink;
    exr_compression_t ctype;
    char *tmp = NULL;
    size_t tmp_len;
    int level, rc;

    if (!path || !path[0])
        return mr_error_set(err, MR_ERR_INVALID, "EXR write: empty path");
    /* Validate before touching the file system. */
    if ((rc = check_film(film, err)) < 0 || (rc = check_options(opt, &ctype, &level, err)) < 0 ||
        (rc = check_meta(meta, err)) < 0)
        return rc;

    /* Write next to the target and rename into place: readers (the HTTP
     * side) never see a partial frame, and a failed write leaves an existing
     * file untouched. pid + the address of this call's frame make the name
     * unique among concurrent writers; O_EXCL refuses any leftover. */
    tmp_len = strlen(path) + 64;
    tmp = malloc(tmp_len);
    if (!tmp)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", path);
    snprintf(tmp, tmp_len, "%s.%ld.%lx.tmp", path, (long)getpid(),
             (unsigned long)(uintptr_t)&io);

    memset(&io, 0, sizeof io);
    io.name = path;
    io.fd = open(tmp, O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0644);
    if (io.fd < 0) {
        rc = mr_error_set(err, MR_ERR_IO, "%s: cannot create %s: %s", path, tmp,
                          strerror(errno));
        goto cleanup;
    }

    t_sink = &io;
    rc = write_impl(&io, film, opt, meta, err);
    t_sink = saved;

    if (close(io.fd) != 0 && rc == MR_OK)
        rc = mr_error_set(err, MR_ERR_IO, "%s: close failed: %s", path, strerror(errno));
    if (rc == MR_OK && rename(tmp, path) != 0)
        rc = mr_error_set(err, MR_ERR_IO, "%s: cannot rename %s into place: %s", path, tmp,
                          strerror(errno));
    if (rc != MR_OK)
        unlink(tmp);

cleanup:
    free(tmp);
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

static int read_impl(exr_io *io, mr_film **out, mr_exr_meta *meta, mr_error *err)
{
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
    int count = 0, matched = 0, rc, i;
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
    rc = mr_film_new((int)w64, (int)h64, &film, err);
    if (rc < 0)
        goto cleanup;
    if (meta) {
        memset(meta, 0, sizeof *meta);
        read_meta(ctxt, meta);
    }

    EXR_TRY(exr_get_channels(ctxt, 0, &chans), "exr_get_channels");
    for (i = 0; chans && i < chans->num_channels; i++) {
        const exr_attr_chlist_entry_t *e = &chans->entries[i];
        if (chan_index(e->name.str) >= 0 && e->x_sampling == 1 && e->y_sampling == 1)
            matched++;
    }
    if (matched == 0)
        goto done; /* nothing we know: an all-zero film, as documented */

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
        for (c = 0; c < dec.channel_count; c++) {
            exr_coding_channel_info_t *ch = &dec.channels[c];
            int ci = chan_index(ch->channel_name);
            /* Subsampled or unknown channels are skipped (NULL pointer). */
            if (ci < 0 || ch->x_samples != 1 || ch->y_samples != 1 ||
                ch->width != film->width || ch->height != cinfo.height) {
                ch->decode_to_ptr = NULL;
                continue;
            }
            ch->decode_to_ptr = (uint8_t *)((uint32_t *)film_plane(film, ci) +
                                            (size_t)row * (size_t)film->width);
            ch->user_data_type = (uint16_t)(k_chans[ci].type == EXR_PIXEL_UINT
                                                ? EXR_PIXEL_UINT
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
