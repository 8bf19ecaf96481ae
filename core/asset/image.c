/*
 * image.c - PNG, JPEG and OpenEXR images decoded into one channel of
 * samples (image.h says what the samples are and what input is refused).
 *
 * Each decoder reads from memory (the import has read the whole file
 * through mr_fs_read_capped, which refuses anything above the asset file
 * cap) and checks the header's size against the caps before it allocates
 * a row. libpng and libjpeg report errors by longjmp: their decoders keep
 * every pointer that must be freed in a struct that outlives the jump.
 */
#include "asset/image.h"

#include <stdio.h> /* before jpeglib.h, which uses FILE */

#include <jpeglib.h>
#include <math.h>
#include <openexr.h>
#include <png.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "asset/asset.h"
#include "util/dup.h"

/* ---- common ----------------------------------------------------------------- */

static const uint8_t PNG_MAGIC[8] = {0x89, 'P', 'N', 'G', 0x0d, 0x0a, 0x1a, 0x0a};
static const uint8_t EXR_MAGIC[4] = {0x76, 0x2f, 0x31, 0x01};

mr_image_format mr_image_sniff(const uint8_t *data, size_t size)
{
    if (!data)
        return MR_IMAGE_NONE;
    if (size >= 8 && memcmp(data, PNG_MAGIC, 8) == 0)
        return MR_IMAGE_PNG;
    if (size >= 3 && data[0] == 0xff && data[1] == 0xd8 && data[2] == 0xff)
        return MR_IMAGE_JPEG;
    if (size >= 4 && memcmp(data, EXR_MAGIC, 4) == 0)
        return MR_IMAGE_EXR;
    return MR_IMAGE_NONE;
}

const char *mr_image_format_name(mr_image_format f)
{
    switch (f) {
    case MR_IMAGE_PNG: return "PNG";
    case MR_IMAGE_JPEG: return "JPEG";
    case MR_IMAGE_EXR: return "EXR";
    default: return "unknown";
    }
}

double mr_image_unit(const mr_image *img)
{
    return img->type == MR_SAMPLE_U8 ? 255.0 : img->type == MR_SAMPLE_U16 ? 65535.0 : 1.0;
}

size_t mr_image_bytes(const mr_image *img)
{
    return img ? sizeof *img + (size_t)img->width * img->height * (size_t)img->type : 0;
}

void mr_image_free(mr_image *img)
{
    if (!img)
        return;
    free(img->samples);
    free(img);
}

/* The caps, checked before anything is allocated for the pixels. */
static int check_size(const char *what, const char *format, uint64_t w, uint64_t h, mr_error *err)
{
    if (w == 0 || h == 0)
        return mr_error_set(err, MR_ERR_FORMAT, "%s: %s image of %llux%llu pixels is empty", what,
                            format, (unsigned long long)w, (unsigned long long)h);
    if (w > MR_MAX_IMAGE_SIDE || h > MR_MAX_IMAGE_SIDE || w * h > MR_MAX_IMAGE_PIXELS)
        return mr_error_set(err, MR_ERR_LIMIT,
                            "%s: %s image of %llux%llu pixels is over the cap (%u per side, %u "
                            "pixels)",
                            what, format, (unsigned long long)w, (unsigned long long)h,
                            MR_MAX_IMAGE_SIDE, MR_MAX_IMAGE_PIXELS);
    return MR_OK;
}

static mr_image *image_alloc(uint32_t w, uint32_t h, mr_sample_type type)
{
    mr_image *img = calloc(1, sizeof *img);
    if (!img)
        return NULL;
    img->width = w;
    img->height = h;
    img->type = type;
    img->samples = calloc((size_t)w * h, (size_t)type);
    if (!img->samples) {
        free(img);
        return NULL;
    }
    return img;
}

int mr_image_new(uint32_t width, uint32_t height, mr_sample_type type, mr_image **out,
                 mr_error *err)
{
    *out = NULL;
    int rc = check_size("generated image", "a", width, height, err);
    if (rc < 0)
        return rc;
    if (type != MR_SAMPLE_U8 && type != MR_SAMPLE_U16 && type != MR_SAMPLE_F32)
        return mr_error_set(err, MR_ERR_INVALID, "generated image: unknown sample type %d", (int)type);
    if (!(*out = image_alloc(width, height, type)))
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory for a %ux%u image", width, height);
    (*out)->file_channels = 1;
    return MR_OK;
}

/* Rec. 709 luminance of integer samples, kept an integer (image.h). */
static inline uint32_t luma_int(uint32_t r, uint32_t g, uint32_t b)
{
    return (2126u * r + 7152u * g + 722u * b + 5000u) / 10000u;
}

/* One decoded row of `channels` interleaved integer samples (8 or 16 bit)
 * into the image's row y. */
static void put_row_int(mr_image *img, uint32_t y, const uint8_t *row, unsigned channels)
{
    uint32_t w = img->width;
    if (img->type == MR_SAMPLE_U8) {
        uint8_t *o = (uint8_t *)img->samples + (size_t)y * w;
        for (uint32_t x = 0; x < w; x++) {
            const uint8_t *p = row + (size_t)x * channels;
            o[x] = channels >= 3 ? (uint8_t)luma_int(p[0], p[1], p[2]) : p[0];
        }
    } else {
        const uint16_t *r16 = (const uint16_t *)(const void *)row;
        uint16_t *o = (uint16_t *)img->samples + (size_t)y * w;
        for (uint32_t x = 0; x < w; x++) {
            const uint16_t *p = r16 + (size_t)x * channels;
            o[x] = channels >= 3 ? (uint16_t)luma_int(p[0], p[1], p[2]) : p[0];
        }
    }
}

/* ---- PNG (libpng) ------------------------------------------------------------ */

typedef struct png_src {
    const uint8_t *data;
    size_t size, at;
    char msg[256];
    uint8_t *row;       /* freed by the caller after a longjmp too */
    mr_image *img;
} png_src;

static void png_read_mem(png_structp png, png_bytep out, png_size_t n)
{
    png_src *s = png_get_io_ptr(png);
    if (n > s->size - s->at)
        png_error(png, "the file ends early (truncated)");
    memcpy(out, s->data + s->at, n);
    s->at += n;
}

static void png_on_error(png_structp png, png_const_charp msg)
{
    png_src *s = png_get_error_ptr(png);
    if (!s->msg[0])
        snprintf(s->msg, sizeof s->msg, "%s", msg);
    png_longjmp(png, 1);
}

static void png_on_warning(png_structp png, png_const_charp msg)
{
    (void)png, (void)msg; /* ancillary-chunk complaints do not change the samples */
}

static int decode_png(const uint8_t *data, size_t size, const char *what, mr_image **out,
                      mr_error *err)
{
    png_src s = {.data = data, .size = size};
    png_structp png = png_create_read_struct(PNG_LIBPNG_VER_STRING, &s, png_on_error,
                                             png_on_warning);
    png_infop info = png ? png_create_info_struct(png) : NULL;
    int rc = MR_OK;
    if (!png || !info) {
        png_destroy_read_struct(&png, &info, NULL);
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory starting libpng", what);
    }
    if (setjmp(png_jmpbuf(png))) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: damaged PNG: %s", what,
                          s.msg[0] ? s.msg : "(no reason given)");
        goto done;
    }
    png_set_read_fn(png, &s, png_read_mem);
    /* libpng allocates rows only after png_read_info, where check_size
     * refuses oversized headers with our cap's message; its own limit (far
     * above ours) only keeps absurd headers out of its arithmetic. Ancillary
     * chunks are capped too. */
    png_set_user_limits(png, 1u << 24, 1u << 24);
    png_set_chunk_malloc_max(png, 8u << 20);
    png_read_info(png, info);
    png_uint_32 w = png_get_image_width(png, info), h = png_get_image_height(png, info);
    if ((rc = check_size(what, "PNG", w, h, err)) < 0)
        goto done;
    int depth = png_get_bit_depth(png, info), ctype = png_get_color_type(png, info);
    unsigned file_channels = png_get_channels(png, info);
    if (ctype == PNG_COLOR_TYPE_PALETTE) {
        png_set_palette_to_rgb(png);
        file_channels = 3;
    }
    if (ctype == PNG_COLOR_TYPE_GRAY && depth < 8)
        png_set_expand_gray_1_2_4_to_8(png);
    if (depth == 16) {
        uint16_t probe = 1;
        if (*(uint8_t *)&probe == 1)
            png_set_swap(png); /* PNG is big-endian */
    }
    int passes = png_set_interlace_handling(png);
    png_read_update_info(png, info);
    unsigned channels = png_get_channels(png, info);
    int out_depth = png_get_bit_depth(png, info);
    if ((out_depth != 8 && out_depth != 16) || channels < 1 || channels > 4) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: PNG of %d-bit samples in %u channels is not "
                          "supported", what, out_depth, channels);
        goto done;
    }
    s.img = image_alloc(w, h, out_depth == 16 ? MR_SAMPLE_U16 : MR_SAMPLE_U8);
    s.row = malloc(png_get_rowbytes(png, info));
    if (!s.img || !s.row) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for a %ux%u PNG", what,
                          (unsigned)w, (unsigned)h);
        goto done;
    }
    s.img->file_channels = file_channels;
    s.img->format = MR_IMAGE_PNG;
    /* Interlaced images arrive in passes over the same rows: they are read
     * whole, then converted. */
    if (passes > 1) {
        size_t rowbytes = png_get_rowbytes(png, info);
        uint8_t *all = calloc((size_t)h, rowbytes);
        png_bytep *rows = malloc((size_t)h * sizeof *rows);
        if (!all || !rows) {
            free(all);
            free(rows);
            rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for an interlaced PNG", what);
            goto done;
        }
        for (png_uint_32 y = 0; y < h; y++)
            rows[y] = all + (size_t)y * rowbytes;
        free(s.row);
        s.row = all; /* freed below, also after a longjmp */
        png_read_image(png, rows);
        free(rows);
        for (png_uint_32 y = 0; y < h; y++)
            put_row_int(s.img, y, all + (size_t)y * rowbytes, channels);
    } else {
        for (png_uint_32 y = 0; y < h; y++) {
            png_read_row(png, s.row, NULL);
            put_row_int(s.img, y, s.row, channels);
        }
    }
    png_read_end(png, NULL);
    *out = s.img;
    s.img = NULL;
done:
    png_destroy_read_struct(&png, &info, NULL);
    free(s.row);
    mr_image_free(s.img);
    return rc;
}

/* ---- JPEG (libjpeg-turbo) ------------------------------------------------------ */

typedef struct jpeg_guard {
    struct jpeg_error_mgr pub;
    jmp_buf jump;
    char msg[JMSG_LENGTH_MAX + 64];
} jpeg_guard;

static void jpeg_on_error(j_common_ptr cinfo)
{
    jpeg_guard *g = (jpeg_guard *)cinfo->err;
    if (!g->msg[0])
        (*cinfo->err->format_message)(cinfo, g->msg);
    longjmp(g->jump, 1);
}

/* Warnings (level -1) include "premature end of data" (a truncated file,
 * which libjpeg would fill with grey) and corrupt-data reports: both are
 * errors for a height map. Trace messages (level >= 0) are ignored. */
static void jpeg_on_message(j_common_ptr cinfo, int level)
{
    if (level < 0)
        jpeg_on_error(cinfo);
}

/* A progressive file may declare thousands of scans over the same pixels
 * (a known way to make a small file cost minutes): more than this many is
 * refused. */
#define JPEG_MAX_SCANS 1000

static void jpeg_on_progress(j_common_ptr cinfo)
{
    if (cinfo->is_decompressor) {
        j_decompress_ptr d = (j_decompress_ptr)cinfo;
        if (d->input_scan_number > JPEG_MAX_SCANS) {
            jpeg_guard *g = (jpeg_guard *)cinfo->err;
            snprintf(g->msg, sizeof g->msg, "more than %d progressive scans", JPEG_MAX_SCANS);
            longjmp(g->jump, 1);
        }
    }
}

static int decode_jpeg(const uint8_t *data, size_t size, const char *what, mr_image **out,
                       mr_error *err)
{
    struct jpeg_decompress_struct cinfo;
    struct jpeg_progress_mgr progress = {.progress_monitor = jpeg_on_progress};
    jpeg_guard g;
    memset(&g, 0, sizeof g);
    /* volatile: changed between setjmp and a longjmp */
    mr_image *volatile img = NULL;
    uint8_t *volatile row = NULL;
    int rc = MR_OK;
    cinfo.err = jpeg_std_error(&g.pub);
    g.pub.error_exit = jpeg_on_error;
    g.pub.emit_message = jpeg_on_message;
    if (setjmp(g.jump)) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: damaged JPEG: %s", what,
                          g.msg[0] ? g.msg : "(no reason given)");
        goto done;
    }
    jpeg_create_decompress(&cinfo);
    cinfo.progress = &progress;
    cinfo.mem->max_memory_to_use = 512L << 20;
    jpeg_mem_src(&cinfo, data, (unsigned long)size);
    jpeg_read_header(&cinfo, TRUE);
    if ((rc = check_size(what, "JPEG", cinfo.image_width, cinfo.image_height, err)) < 0)
        goto done;
    unsigned file_channels = (unsigned)cinfo.num_components;
    if (cinfo.jpeg_color_space == JCS_CMYK || cinfo.jpeg_color_space == JCS_YCCK) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: CMYK JPEGs are not supported (grey or colour "
                          "only)", what);
        goto done;
    }
    cinfo.out_color_space = cinfo.jpeg_color_space == JCS_GRAYSCALE ? JCS_GRAYSCALE : JCS_RGB;
    jpeg_start_decompress(&cinfo);
    unsigned channels = (unsigned)cinfo.output_components;
    if (channels != 1 && channels != 3) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: JPEG decodes to %u components", what, channels);
        goto done;
    }
    img = image_alloc(cinfo.output_width, cinfo.output_height, MR_SAMPLE_U8);
    row = malloc((size_t)cinfo.output_width * channels);
    if (!img || !row) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for a %ux%u JPEG", what,
                          cinfo.output_width, cinfo.output_height);
        goto done;
    }
    img->file_channels = file_channels;
    img->format = MR_IMAGE_JPEG;
    while (cinfo.output_scanline < cinfo.output_height) {
        JSAMPROW rows[1] = {row};
        uint32_t y = cinfo.output_scanline;
        if (jpeg_read_scanlines(&cinfo, rows, 1) != 1) {
            rc = mr_error_set(err, MR_ERR_FORMAT, "%s: damaged JPEG: no data for row %u", what, y);
            goto done;
        }
        put_row_int(img, y, row, channels);
    }
    jpeg_finish_decompress(&cinfo);
    *out = img;
    img = NULL;
done:
    jpeg_destroy_decompress(&cinfo);
    free(row);
    mr_image_free(img);
    return rc;
}

/* ---- OpenEXR ------------------------------------------------------------------- */

typedef struct exr_mem {
    const uint8_t *data;
    size_t size;
} exr_mem;

/* The library's messages reach the decoder through a thread-local pointer:
 * calling exr_get_user_data() from the error callback deadlocks in 3.1.5
 * (render/exr.c measured it). */
static _Thread_local char *t_exr_msg;

static void exr_on_error(exr_const_context_t ctxt, exr_result_t code, const char *msg)
{
    (void)ctxt, (void)code;
    if (t_exr_msg && !t_exr_msg[0] && msg)
        snprintf(t_exr_msg, 256, "%s", msg);
}

static int64_t exr_read_mem(exr_const_context_t ctxt, void *user, void *buffer, uint64_t sz,
                            uint64_t offset, exr_stream_error_func_ptr_t error_cb)
{
    (void)ctxt, (void)error_cb;
    const exr_mem *m = user;
    if (offset >= m->size)
        return 0;
    uint64_t n = m->size - offset < sz ? m->size - offset : sz;
    memcpy(buffer, m->data + offset, n);
    return (int64_t)n;
}

static int64_t exr_size_mem(exr_const_context_t ctxt, void *user)
{
    (void)ctxt;
    return (int64_t)((const exr_mem *)user)->size;
}

/* Which channels make the height: Y; else R, G, B (luminance); else the
 * only channel. Indices into the channel list, -1 when unused. */
static bool exr_pick(const exr_attr_chlist_t *chans, int pick[3], bool *luma)
{
    int y = -1, r = -1, g = -1, b = -1;
    for (int i = 0; i < chans->num_channels; i++) {
        const char *n = chans->entries[i].name.str;
        if (!strcmp(n, "Y"))
            y = i;
        else if (!strcmp(n, "R"))
            r = i;
        else if (!strcmp(n, "G"))
            g = i;
        else if (!strcmp(n, "B"))
            b = i;
    }
    pick[0] = pick[1] = pick[2] = -1;
    *luma = false;
    if (y >= 0) {
        pick[0] = y;
        return true;
    }
    if (r >= 0 && g >= 0 && b >= 0) {
        pick[0] = r, pick[1] = g, pick[2] = b;
        *luma = true;
        return true;
    }
    int others = 0, only = -1;
    for (int i = 0; i < chans->num_channels; i++)
        if (strcmp(chans->entries[i].name.str, "A") != 0)
            others++, only = i;
    if (others == 1) {
        pick[0] = only;
        return true;
    }
    return false;
}

static int decode_exr(const uint8_t *data, size_t size, const char *what, mr_image **out,
                      mr_error *err)
{
    exr_mem mem = {data, size};
    char msg[256] = "";
    char *saved = t_exr_msg;
    t_exr_msg = msg;
    exr_context_initializer_t init = EXR_DEFAULT_CONTEXT_INITIALIZER;
    init.error_handler_fn = exr_on_error;
    init.user_data = &mem;
    init.read_fn = exr_read_mem;
    init.size_fn = exr_size_mem;
    init.flags = EXR_CONTEXT_FLAG_DISABLE_CHUNK_RECONSTRUCTION;
    exr_context_t ctxt = NULL;
    exr_decode_pipeline_t dec = EXR_DECODE_PIPELINE_INITIALIZER;
    bool dec_ready = false, routines = false;
    float *planes = NULL;
    uint8_t *scratch = NULL;
    size_t scratch_size = 0;
    mr_image *img = NULL;
    int rc = MR_OK, count = 0, pick[3];
    bool luma;
    exr_result_t rv;
    const char *step = "";
    exr_storage_t storage;
    exr_attr_box2i_t dw;
    const exr_attr_chlist_t *chans = NULL;
    int32_t lines = 0;

#define EXR_TRY(call, what_step)                                                        \
    do {                                                                                \
        step = (what_step);                                                             \
        if ((rv = (call)) != EXR_ERR_SUCCESS)                                           \
            goto fail;                                                                  \
    } while (0)

    EXR_TRY(exr_start_read(&ctxt, what, &init), "reading the header");
    EXR_TRY(exr_get_count(ctxt, &count), "counting parts");
    if (count < 1) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: EXR file has no parts", what);
        goto done;
    }
    EXR_TRY(exr_get_storage(ctxt, 0, &storage), "reading the storage");
    if (storage != EXR_STORAGE_SCANLINE) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: EXR part 0 is %s; height textures must be "
                          "scanline images", what,
                          storage == EXR_STORAGE_TILED ? "tiled" : "deep");
        goto done;
    }
    EXR_TRY(exr_get_data_window(ctxt, 0, &dw), "reading the data window");
    int64_t w = (int64_t)dw.max.x - dw.min.x + 1, h = (int64_t)dw.max.y - dw.min.y + 1;
    if (w < 1 || h < 1) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: EXR data window is empty", what);
        goto done;
    }
    if ((rc = check_size(what, "EXR", (uint64_t)w, (uint64_t)h, err)) < 0)
        goto done;
    EXR_TRY(exr_get_channels(ctxt, 0, &chans), "reading the channels");
    if (!chans || !exr_pick(chans, pick, &luma)) {
        char names[160] = "";
        size_t used = 0;
        for (int i = 0; chans && i < chans->num_channels && used + 1 < sizeof names; i++) {
            int n = snprintf(names + used, sizeof names - used, "%s%s", i ? ", " : "",
                             chans->entries[i].name.str);
            used += n > 0 ? (size_t)n : 0;
        }
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: EXR with %d channels (%s): a height needs a "
                          "\"Y\" channel, \"R\", \"G\" and \"B\", or a single channel", what,
                          chans ? chans->num_channels : 0, used ? names : "none");
        goto done;
    }
    for (int k = 0; k < 3; k++)
        if (pick[k] >= 0 && (chans->entries[pick[k]].x_sampling != 1 ||
                             chans->entries[pick[k]].y_sampling != 1)) {
            rc = mr_error_set(err, MR_ERR_FORMAT, "%s: EXR channel \"%s\" is subsampled", what,
                              chans->entries[pick[k]].name.str);
            goto done;
        }
    EXR_TRY(exr_get_scanlines_per_chunk(ctxt, 0, &lines), "reading the chunk size");
    if (lines < 1) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: EXR reports %d scanlines per chunk", what, lines);
        goto done;
    }
    size_t npix = (size_t)w * (size_t)h;
    int nplanes = luma ? 3 : 1;
    planes = calloc(npix * (size_t)nplanes, sizeof(float));
    img = image_alloc((uint32_t)w, (uint32_t)h, MR_SAMPLE_F32);
    if (!planes || !img) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for a %lldx%lld EXR", what,
                          (long long)w, (long long)h);
        goto done;
    }
    img->file_channels = (uint32_t)chans->num_channels;
    img->format = MR_IMAGE_EXR;
    for (int64_t y = dw.min.y; y <= dw.max.y; y += lines) {
        exr_chunk_info_t cinfo;
        EXR_TRY(exr_read_scanline_chunk_info(ctxt, 0, (int)y, &cinfo), "reading a chunk");
        int64_t row = (int64_t)cinfo.start_y - dw.min.y;
        if (row < 0 || cinfo.height < 1 || row + cinfo.height > h) {
            rc = mr_error_set(err, MR_ERR_FORMAT, "%s: EXR chunk at scanline %lld lies outside "
                              "the data window", what, (long long)y);
            goto done;
        }
        if (!dec_ready) {
            EXR_TRY(exr_decoding_initialize(ctxt, 0, &cinfo, &dec), "starting the decoder");
            dec_ready = true;
        } else {
            EXR_TRY(exr_decoding_update(ctxt, 0, &cinfo, &dec), "decoding");
        }
        /* unwanted channels into a scratch buffer (never a NULL pointer:
         * render/exr.c found 3.1's unpackers write through it anyway) */
        size_t need = 0;
        for (int c = 0; c < dec.channel_count; c++) {
            const exr_coding_channel_info_t *ch = &dec.channels[c];
            size_t n = (size_t)(ch->width > 0 ? ch->width : 0) * (size_t)(ch->height > 0 ? ch->height : 0) * 4u;
            need = n > need ? n : need;
        }
        if (need > scratch_size) {
            uint8_t *grown = realloc(scratch, need);
            if (!grown) {
                rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", what);
                goto done;
            }
            scratch = grown;
            scratch_size = need;
        }
        for (int c = 0; c < dec.channel_count; c++) {
            exr_coding_channel_info_t *ch = &dec.channels[c];
            int plane = -1;
            for (int k = 0; k < nplanes; k++)
                if (pick[k] >= 0 && !strcmp(ch->channel_name, chans->entries[pick[k]].name.str))
                    plane = k;
            if (plane < 0 || ch->width != w || ch->height != cinfo.height) {
                ch->decode_to_ptr = ch->width > 0 && ch->height > 0 ? scratch : NULL;
                ch->user_data_type = ch->data_type;
                ch->user_bytes_per_element = ch->bytes_per_element;
                ch->user_pixel_stride = ch->bytes_per_element;
                ch->user_line_stride = ch->width * ch->bytes_per_element;
                if (plane >= 0) {
                    rc = mr_error_set(err, MR_ERR_FORMAT, "%s: EXR channel \"%s\" has a chunk of "
                                      "the wrong size", what, ch->channel_name);
                    goto done;
                }
                continue;
            }
            ch->decode_to_ptr = (uint8_t *)(planes + (size_t)plane * npix + (size_t)row * (size_t)w);
            ch->user_data_type = EXR_PIXEL_FLOAT;
            ch->user_bytes_per_element = 4;
            ch->user_pixel_stride = 4;
            ch->user_line_stride = 4 * (int32_t)w;
        }
        if (!routines) {
            EXR_TRY(exr_decoding_choose_default_routines(ctxt, 0, &dec), "choosing decoders");
            routines = true;
        }
        EXR_TRY(exr_decoding_run(ctxt, 0, &dec), "decoding");
    }
    float *o = img->samples;
    for (size_t i = 0; i < npix; i++) {
        float v = luma ? 0.2126f * planes[i] + 0.7152f * planes[npix + i] +
                             0.0722f * planes[2 * npix + i]
                       : planes[i];
        if (!isfinite(v)) {
            rc = mr_error_set(err, MR_ERR_FORMAT, "%s: EXR pixel (%zu, %zu) is not finite (%g)",
                              what, i % (size_t)w, i / (size_t)w, (double)v);
            goto done;
        }
        o[i] = v;
    }
    *out = img;
    img = NULL;
    goto done;
#undef EXR_TRY
fail:
    rc = mr_error_set(err, MR_ERR_FORMAT, "%s: damaged EXR (%s): %s", what, step,
                      msg[0] ? msg : exr_get_default_error_message(rv));
done:
    if (dec_ready)
        exr_decoding_destroy(ctxt, &dec);
    if (ctxt)
        exr_finish(&ctxt);
    t_exr_msg = saved;
    free(planes);
    free(scratch);
    mr_image_free(img);
    return rc;
}

/* ---- entry points ---------------------------------------------------------------- */

int mr_image_decode(const uint8_t *data, size_t size, const char *what, mr_image **out,
                    mr_error *err)
{
    *out = NULL;
    if (!what)
        what = "image";
    switch (mr_image_sniff(data, size)) {
    case MR_IMAGE_PNG: return decode_png(data, size, what, out, err);
    case MR_IMAGE_JPEG: return decode_jpeg(data, size, what, out, err);
    case MR_IMAGE_EXR: return decode_exr(data, size, what, out, err);
    default:
        return mr_error_set(err, MR_ERR_FORMAT, "%s: not a PNG, JPEG or EXR image", what);
    }
}

int mr_asset_from_image(const char *path, mr_image *img, mr_asset **out, mr_error *err)
{
    *out = NULL;
    mr_asset *a = calloc(1, sizeof *a);
    if (!a || !(a->path = mr_strdup(path ? path : ""))) {
        free(a);
        mr_image_free(img);
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", path ? path : "image");
    }
    a->image = img;
    *out = a;
    return MR_OK;
}
