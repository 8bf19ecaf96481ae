/*
 * preview.c - 8-bit sRGB PNG previews and contact sheets of a film's beauty
 * pass (microray.h, "PNG previews and contact sheets": the operator, the
 * thumbnail filter and the sheet layout are specified there, and the tests
 * check them pixel by pixel).
 *
 * Speed: the transfer function is not evaluated per pixel. Rounding
 * 255 srgb(v) to the nearest code is the same as counting the code
 * boundaries srgb^-1((k - 0.5) / 255), k = 1..255, that v reaches: a table
 * made per call (255 pow() calls) finds them with one lookup and one
 * comparison (code_of), exact up to the float rounding of the boundaries.
 *
 * PNG encoding is Debian's libpng with the UP filter on every row and
 * zlib's run-length strategy (Z_RLE). libpng's default (zlib level 6 and
 * its adaptive choice among the five filters, which tries them all on every
 * row) costs several times as much for files only a little smaller.
 * Measured with bench_preview on the skinned example's mid frame, one
 * core, medians of 7, the same run (the machine was shared, so the ratios
 * are what to trust): 1920x1080 UP+RLE 21-22 ms and 112 KiB, SUB+RLE 33-34
 * ms and 129 KiB, libpng's default 86-101 ms and 100 KiB; 640x360 UP+RLE
 * 2.6-3.6 ms and 21 KiB, the default 10 ms and 18 KiB. (Adaptive filters at
 * level 1 or 3: 58-105 ms and 138-143 KiB; the filters, not deflate, were
 * the cost.)
 */
#include <math.h>
#include <png.h>
#include <setjmp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <zlib.h>

#include "microray.h"


/* The sheet's greys (sRGB codes, microray.h). */
#define SHEET_BACKGROUND 16
#define SHEET_PENDING 56
#define SHEET_PENDING_CROSS 128
#define CHECKER_LIGHT 153
#define CHECKER_DARK 102
#define CHECKER_SQUARE 8

void mr_image8_free(mr_image8 *img)
{
    if (!img)
        return;
    free(img->px);
    memset(img, 0, sizeof *img);
}

static int image_alloc(mr_image8 *img, int width, int height, int channels, mr_error *err)
{
    memset(img, 0, sizeof *img);
    size_t n = (size_t)width * (size_t)height * (size_t)channels;
    img->px = malloc(n ? n : 1);
    if (!img->px)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory for a %dx%d preview", width, height);
    img->width = width;
    img->height = height;
    img->channels = channels;
    return MR_OK;
}

/* ---- the transfer function ----------------------------------------------- */

/* srgb^-1: the linear value of an encoded value s in [0, 1]. */

static double srgb_decode(double s)
{
    return s <= 0.04045 ? s / 12.92 : pow((s + 0.055) / 1.055, 2.4);
}

/* Code boundaries and a coarse index into them. Linear values closer than
 * 1 / TABLE_STEPS never straddle two boundaries (the narrowest code, at the
 * bottom of the curve, is 1 / (12.92 * 255) = 3.0e-4 wide), so the index
 * gives the code at the start of v's step and one comparison finishes it. */
#define TABLE_STEPS 4096
typedef struct code_table {
    float bound[257];              /* bound[k]: least linear value of code k (1..255); 257: +inf */
    uint8_t start[TABLE_STEPS];    /* code of k / TABLE_STEPS */
} code_table;

static void code_table_init(code_table *t)
{
    t->bound[0] = -INFINITY;
    for (int k = 1; k < 256; k++)
        t->bound[k] = (float)srgb_decode((k - 0.5) / 255.0);
    t->bound[256] = INFINITY;
    int code = 0;
    for (int i = 0; i < TABLE_STEPS; i++) {
        float v = (float)i / (float)TABLE_STEPS;
        while (v >= t->bound[code + 1])
            code++;
        t->start[i] = (uint8_t)code;
    }
}

/* round(255 srgb(clamp(v, 0, 1))); NaN gives 0. */
static inline uint8_t code_of(const code_table *t, float v)
{
    v = v > 0.0f ? (v < 1.0f ? v : 1.0f) : 0.0f; /* NaN -> 0 */
    int i = (int)(v * (float)TABLE_STEPS);
    unsigned k = t->start[i < TABLE_STEPS ? i : TABLE_STEPS - 1];
    return (uint8_t)(k + (v >= t->bound[k + 1]));
}

static inline float clamp_alpha(float a)
{
    return a > 0.0f ? (a < 1.0f ? a : 1.0f) : 0.0f; /* NaN -> 0 */
}

static bool has_beauty(const mr_film *film)
{
    return film && film->r && film->g && film->b && film->a && film->width > 0 && film->height > 0;
}

int mr_preview_from_film(const mr_film *film, mr_image8 *out, mr_error *err)
{
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "mr_preview_from_film: out is NULL");
    memset(out, 0, sizeof *out);
    if (!has_beauty(film))
        return mr_error_set(err, MR_ERR_INVALID, "the frame has no R, G, B, A pass to preview");
    int rc = image_alloc(out, film->width, film->height, 4, err);
    if (rc < 0)
        return rc;
    code_table t;
    code_table_init(&t);
    size_t n = (size_t)film->width * (size_t)film->height;
    uint8_t *p = out->px;
    for (size_t i = 0; i < n; i++, p += 4) {
        float a = clamp_alpha(film->a[i]);
        float r = 0.0f, g = 0.0f, b = 0.0f;
        if (a >= 1.0f) {
            r = film->r[i];
            g = film->g[i];
            b = film->b[i];
        } else if (a > 0.0f) {
            r = film->r[i] / a;
            g = film->g[i] / a;
            b = film->b[i] / a;
        }
        p[0] = code_of(&t, r);
        p[1] = code_of(&t, g);
        p[2] = code_of(&t, b);
        p[3] = (uint8_t)(a * 255.0f + 0.5f);
    }
    return MR_OK;
}

/* ---- thumbnails and contact sheets --------------------------------------- */

void mr_preview_thumb_size(int width, int height, int *thumb_w, int *thumb_h)
{
    double w = width > 0 ? width : 1, h = height > 0 ? height : 1;
    double s = fmin(fmin((double)MR_THUMB_MAX_SIDE / w, (double)MR_THUMB_MAX_SIDE / h), 1.0);
    long tw = lround(w * s), th = lround(h * s);
    *thumb_w = tw < 1 ? 1 : (int)tw;
    *thumb_h = th < 1 ? 1 : (int)th;
}

static inline float finite_or_0(float v)
{
    return isfinite(v) ? v : 0.0f;
}

int mr_preview_thumbnail(const mr_film *film, mr_image8 *out, mr_error *err)
{
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "mr_preview_thumbnail: out is NULL");
    memset(out, 0, sizeof *out);
    if (!has_beauty(film))
        return mr_error_set(err, MR_ERR_INVALID, "the frame has no R, G, B, A pass to preview");
    int tw, th;
    mr_preview_thumb_size(film->width, film->height, &tw, &th);
    int rc = image_alloc(out, tw, th, 3, err);
    if (rc < 0)
        return rc;
    code_table t;
    code_table_init(&t);
    const float light = (float)srgb_decode(CHECKER_LIGHT / 255.0);
    const float dark = (float)srgb_decode(CHECKER_DARK / 255.0);
    const int64_t W = film->width, H = film->height;
    for (int y = 0; y < th; y++) {
        int64_t y0 = y * H / th, y1 = (y + 1) * H / th;
        for (int x = 0; x < tw; x++) {
            int64_t x0 = x * W / tw, x1 = (x + 1) * W / tw;
            double sr = 0, sg = 0, sb = 0, sa = 0;
            for (int64_t sy = y0; sy < y1; sy++) {
                size_t row = (size_t)(sy * W);
                for (int64_t sx = x0; sx < x1; sx++) {
                    size_t i = row + (size_t)sx;
                    sr += finite_or_0(film->r[i]);
                    sg += finite_or_0(film->g[i]);
                    sb += finite_or_0(film->b[i]);
                    sa += finite_or_0(film->a[i]);
                }
            }
            double inv = 1.0 / (double)((y1 - y0) * (x1 - x0));
            float a = clamp_alpha((float)(sa * inv));
            float under = (((x / CHECKER_SQUARE) + (y / CHECKER_SQUARE)) & 1) ? dark : light;
            float behind = (1.0f - a) * under;
            uint8_t *p = out->px + ((size_t)y * (size_t)tw + (size_t)x) * 3;
            p[0] = code_of(&t, (float)(sr * inv) + behind);
            p[1] = code_of(&t, (float)(sg * inv) + behind);
            p[2] = code_of(&t, (float)(sb * inv) + behind);
        }
    }
    return MR_OK;
}

size_t mr_contact_sheet_frames(size_t frame_count, size_t index[MR_SHEET_MAX_FRAMES])
{
    if (frame_count <= MR_SHEET_MAX_FRAMES) {
        for (size_t i = 0; i < frame_count; i++)
            index[i] = i;
        return frame_count;
    }
    for (size_t i = 0; i < MR_SHEET_MAX_FRAMES; i++)
        index[i] = i * (frame_count - 1) / (MR_SHEET_MAX_FRAMES - 1);
    return MR_SHEET_MAX_FRAMES;
}

void mr_contact_sheet_layout(size_t count, int thumb_w, int thumb_h, mr_sheet_layout *out)
{
    int columns = 1;
    while ((size_t)columns * (size_t)columns < count)
        columns++;
    int rows = count ? (int)((count + (size_t)columns - 1) / (size_t)columns) : 1;
    out->columns = columns;
    out->rows = rows;
    out->cell_w = thumb_w;
    out->cell_h = thumb_h;
    out->width = MR_SHEET_GUTTER + columns * (thumb_w + MR_SHEET_GUTTER);
    out->height = MR_SHEET_GUTTER + rows * (thumb_h + MR_SHEET_GUTTER);
}

void mr_contact_sheet_cell(const mr_sheet_layout *l, size_t i, int *x, int *y)
{
    *x = MR_SHEET_GUTTER + (int)(i % (size_t)l->columns) * (l->cell_w + MR_SHEET_GUTTER);
    *y = MR_SHEET_GUTTER + (int)(i / (size_t)l->columns) * (l->cell_h + MR_SHEET_GUTTER);
}

static void put_grey(mr_image8 *img, int x, int y, uint8_t v)
{
    memset(img->px + ((size_t)y * (size_t)img->width + (size_t)x) * 3, v, 3);
}

int mr_contact_sheet_new(size_t count, int thumb_w, int thumb_h, mr_image8 *sheet, mr_error *err)
{
    if (!sheet)
        return mr_error_set(err, MR_ERR_INVALID, "mr_contact_sheet_new: sheet is NULL");
    memset(sheet, 0, sizeof *sheet);
    if (count < 1 || count > MR_SHEET_MAX_FRAMES || thumb_w < 1 || thumb_h < 1 ||
        thumb_w > MR_THUMB_MAX_SIDE || thumb_h > MR_THUMB_MAX_SIDE)
        return mr_error_set(err, MR_ERR_INVALID,
                            "contact sheet of %zu cells of %dx%d: expected 1..%d cells of at "
                            "most %dx%d",
                            count, thumb_w, thumb_h, MR_SHEET_MAX_FRAMES, MR_THUMB_MAX_SIDE,
                            MR_THUMB_MAX_SIDE);
    mr_sheet_layout l;
    mr_contact_sheet_layout(count, thumb_w, thumb_h, &l);
    int rc = image_alloc(sheet, l.width, l.height, 3, err);
    if (rc < 0)
        return rc;
    memset(sheet->px, SHEET_BACKGROUND, (size_t)l.width * (size_t)l.height * 3);
    int n = thumb_w > thumb_h ? thumb_w : thumb_h;
    for (size_t i = 0; i < count; i++) {
        int cx, cy;
        mr_contact_sheet_cell(&l, i, &cx, &cy);
        for (int y = 0; y < thumb_h; y++)
            memset(sheet->px + ((size_t)(cy + y) * (size_t)l.width + (size_t)cx) * 3,
                   SHEET_PENDING, (size_t)thumb_w * 3);
        for (int k = 0; k < n; k++) {
            int x = n > 1 ? (int)((int64_t)k * (thumb_w - 1) / (n - 1)) : 0;
            int y = n > 1 ? (int)((int64_t)k * (thumb_h - 1) / (n - 1)) : 0;
            put_grey(sheet, cx + x, cy + y, SHEET_PENDING_CROSS);
            put_grey(sheet, cx + thumb_w - 1 - x, cy + y, SHEET_PENDING_CROSS);
        }
    }
    return MR_OK;
}

int mr_contact_sheet_put(mr_image8 *sheet, size_t i, const mr_image8 *thumb, mr_error *err)
{
    if (!sheet || !sheet->px || !thumb || !thumb->px || thumb->channels != 3 ||
        sheet->channels != 3)
        return mr_error_set(err, MR_ERR_INVALID, "mr_contact_sheet_put: missing or non-RGB image");
    /* The layout is recovered from the sheet: cells are the thumbnail's size. */
    int tw = thumb->width, th = thumb->height;
    int columns = (sheet->width - MR_SHEET_GUTTER) / (tw + MR_SHEET_GUTTER);
    int rows = (sheet->height - MR_SHEET_GUTTER) / (th + MR_SHEET_GUTTER);
    mr_sheet_layout l = {.columns = columns, .rows = rows, .cell_w = tw, .cell_h = th,
                         .width = sheet->width, .height = sheet->height};
    if (columns < 1 || rows < 1 || MR_SHEET_GUTTER + columns * (tw + MR_SHEET_GUTTER) != sheet->width ||
        MR_SHEET_GUTTER + rows * (th + MR_SHEET_GUTTER) != sheet->height ||
        i >= (size_t)columns * (size_t)rows)
        return mr_error_set(err, MR_ERR_INVALID,
                            "a %dx%d thumbnail does not fit cell %zu of a %dx%d contact sheet", tw, th,
                            i, sheet->width, sheet->height);
    int cx, cy;
    mr_contact_sheet_cell(&l, i, &cx, &cy);
    for (int y = 0; y < th; y++)
        memcpy(sheet->px + ((size_t)(cy + y) * (size_t)sheet->width + (size_t)cx) * 3,
               thumb->px + (size_t)y * (size_t)tw * 3, (size_t)tw * 3);
    return MR_OK;
}

/* ---- PNG through libpng --------------------------------------------------- */

typedef struct png_sink {
    uint8_t *data;
    size_t len, cap;
    char msg[200]; /* libpng's error message, if any */
} png_sink;

static void sink_write(png_structp png, png_bytep bytes, png_size_t n)
{
    png_sink *s = png_get_io_ptr(png);
    if (s->len + n > s->cap) {
        size_t cap = s->cap ? s->cap : 4096;
        while (cap < s->len + n)
            cap *= 2;
        uint8_t *d = realloc(s->data, cap);
        if (!d)
            png_error(png, "out of memory");
        s->data = d;
        s->cap = cap;
    }
    memcpy(s->data + s->len, bytes, n);
    s->len += n;
}

static void sink_flush(png_structp png)
{
    (void)png;
}

static void on_png_error(png_structp png, png_const_charp msg)
{
    png_sink *s = png_get_error_ptr(png);
    snprintf(s->msg, sizeof s->msg, "%s", msg ? msg : "libpng error");
    png_longjmp(png, 1);
}

static void on_png_warning(png_structp png, png_const_charp msg)
{
    (void)png;
    (void)msg;
}

/* The libpng part, apart so that nothing the caller owns lives across the
 * setjmp; false on a libpng error (the message in s->msg). */
static bool png_encode_rows(const mr_image8 *img, png_sink *s)
{
    png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, s, on_png_error,
                                              on_png_warning);
    if (!png) {
        snprintf(s->msg, sizeof s->msg, "out of memory");
        return false;
    }
    png_infop info = png_create_info_struct(png);
    if (!info) {
        png_destroy_write_struct(&png, NULL);
        snprintf(s->msg, sizeof s->msg, "out of memory");
        return false;
    }
    if (setjmp(png_jmpbuf(png))) {
        png_destroy_write_struct(&png, &info);
        return false;
    }
    png_set_write_fn(png, s, sink_write, sink_flush);
    png_set_IHDR(png, info, (png_uint_32)img->width, (png_uint_32)img->height, 8,
                 img->channels == 4 ? PNG_COLOR_TYPE_RGB_ALPHA : PNG_COLOR_TYPE_RGB,
                 PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
    png_set_sRGB_gAMA_and_cHRM(png, info, PNG_sRGB_INTENT_PERCEPTUAL);
    png_set_filter(png, PNG_FILTER_TYPE_BASE, PNG_FILTER_UP);
    png_set_compression_strategy(png, Z_RLE); /* the level does not matter to Z_RLE */
    png_write_info(png, info);
    size_t stride = (size_t)img->width * (size_t)img->channels;
    for (int y = 0; y < img->height; y++)
        png_write_row(png, img->px + (size_t)y * stride);
    png_write_end(png, NULL);
    png_destroy_write_struct(&png, &info);
    return true;
}

int mr_png_encode(const mr_image8 *img, uint8_t **data, size_t *size, mr_error *err)
{
    if (!data || !size)
        return mr_error_set(err, MR_ERR_INVALID, "mr_png_encode: missing argument");
    *data = NULL;
    *size = 0;
    if (!img || !img->px || img->width < 1 || img->height < 1 ||
        (img->channels != 3 && img->channels != 4))
        return mr_error_set(err, MR_ERR_INVALID, "mr_png_encode: not an 8-bit RGB or RGBA image");
    png_sink s = {0};
    /* most frames compress several times; a first guess saves reallocations */
    s.cap = (size_t)img->width * (size_t)img->height * (size_t)img->channels / 4 + 1024;
    s.data = malloc(s.cap);
    if (!s.data)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory encoding a PNG");
    if (!png_encode_rows(img, &s)) {
        free(s.data);
        return mr_error_set(err, strcmp(s.msg, "out of memory") ? MR_ERR_INVALID : MR_ERR_NOMEM,
                            "PNG encoding failed: %s", s.msg);
    }
    *data = s.data;
    *size = s.len;
    return MR_OK;
}

int mr_png_decode(const uint8_t *data, size_t size, const char *what, mr_image8 *out, mr_error *err)
{
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "mr_png_decode: out is NULL");
    memset(out, 0, sizeof *out);
    what = what ? what : "PNG";
    png_image im;
    memset(&im, 0, sizeof im);
    im.version = PNG_IMAGE_VERSION;
    if (!data || !png_image_begin_read_from_memory(&im, data, size)) {
        int rc = mr_error_set(err, MR_ERR_FORMAT, "%s: not a PNG image (%s)", what, im.message);
        png_image_free(&im);
        return rc;
    }
    if (im.width < 1 || im.height < 1 || im.width > MR_MAX_RESOLUTION ||
        im.height > MR_MAX_RESOLUTION || (size_t)im.width * im.height > MR_MAX_PIXELS) {
        png_image_free(&im);
        return mr_error_set(err, MR_ERR_FORMAT, "%s: %ux%u pixels, over the film caps", what,
                            (unsigned)im.width, (unsigned)im.height);
    }
    int channels = (im.format & PNG_FORMAT_FLAG_ALPHA) ? 4 : 3;
    im.format = channels == 4 ? PNG_FORMAT_RGBA : PNG_FORMAT_RGB;
    int rc = image_alloc(out, (int)im.width, (int)im.height, channels, err);
    if (rc < 0) {
        png_image_free(&im);
        return rc;
    }
    if (!png_image_finish_read(&im, NULL, out->px, 0, NULL)) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: damaged PNG (%s)", what, im.message);
        png_image_free(&im);
        mr_image8_free(out);
        return rc;
    }
    return MR_OK;
}

int mr_png_write_film(const char *path, const mr_film *film, mr_error *err)
{
    mr_image8 img;
    uint8_t *data = NULL;
    size_t size = 0;
    int rc = mr_preview_from_film(film, &img, err);
    if (rc == MR_OK)
        rc = mr_png_encode(&img, &data, &size, err);
    mr_image8_free(&img);
    if (rc == MR_OK)
        rc = mr_fs_write_atomic(path, data, size, "png preview", err);
    free(data);
    return rc;
}
