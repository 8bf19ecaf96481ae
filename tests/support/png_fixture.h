/*
 * png_fixture.h - what the preview tests share: PNGs read with libpng's own
 * low-level reader (not core's mr_png_decode, so a test does not check the
 * encoder with its own twin), and the preview operator, thumbnail filter and
 * contact-sheet greys of microray.h written again in double precision from
 * that documentation. Header-only; include after <cmocka.h> and microray.h.
 *
 * Tolerance of every pixel check: 1 code value. The encoder works in float
 * (halves read from an EXR, C / a in float, code boundaries rounded to
 * float) and the reference here in double, so a value within a float ulp of
 * a code boundary (k - 0.5) / 255 may round to either neighbour; nothing
 * else may differ (fx_check_* also report how many pixels were off by one).
 */
#ifndef MR_TEST_PNG_FIXTURE_H
#define MR_TEST_PNG_FIXTURE_H

#include <math.h>
#include <png.h>
#include <setjmp.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct fx_png {
    int width, height, channels;
    bool srgb;       /* an sRGB chunk is present */
    uint8_t *px;     /* channels bytes per pixel, row 0 at the top */
} fx_png;

typedef struct fx_png_src {
    const uint8_t *data;
    size_t size, pos;
} fx_png_src;

static void fx_png_read_fn(png_structp png, png_bytep out, png_size_t n)
{
    fx_png_src *s = png_get_io_ptr(png);
    if (n > s->size - s->pos)
        png_error(png, "truncated");
    memcpy(out, s->data + s->pos, n);
    s->pos += n;
}

/* Decodes an 8-bit RGB or RGBA PNG (anything else fails the test). */
static inline fx_png fx_png_read(const void *data, size_t size)
{
    fx_png out = {0};
    fx_png_src src = {data, size, 0};
    png_structp png = png_create_read_struct(PNG_LIBPNG_VER_STRING, NULL, NULL, NULL);
    assert_non_null(png);
    png_infop info = png_create_info_struct(png);
    assert_non_null(info);
    png_bytep *volatile rows = NULL;
    if (setjmp(png_jmpbuf(png))) {
        png_destroy_read_struct(&png, &info, NULL);
        fail_msg("libpng could not read the PNG (%zu bytes)", size);
    }
    png_set_read_fn(png, &src, fx_png_read_fn);
    png_read_info(png, info);
    int depth = png_get_bit_depth(png, info), type = png_get_color_type(png, info);
    if (depth != 8 || (type != PNG_COLOR_TYPE_RGB && type != PNG_COLOR_TYPE_RGB_ALPHA))
        fail_msg("PNG of bit depth %d and colour type %d, want 8-bit RGB or RGBA", depth, type);
    int intent = 0;
    out.srgb = png_get_sRGB(png, info, &intent) != 0;
    out.width = (int)png_get_image_width(png, info);
    out.height = (int)png_get_image_height(png, info);
    out.channels = type == PNG_COLOR_TYPE_RGB_ALPHA ? 4 : 3;
    size_t stride = png_get_rowbytes(png, info);
    assert_int_equal(stride, (size_t)out.width * (size_t)out.channels);
    out.px = malloc(stride * (size_t)out.height);
    rows = malloc(sizeof *rows * (size_t)out.height);
    assert_non_null(out.px);
    assert_non_null(rows);
    for (int y = 0; y < out.height; y++)
        rows[y] = out.px + (size_t)y * stride;
    png_read_image(png, rows);
    png_read_end(png, NULL);
    png_destroy_read_struct(&png, &info, NULL);
    free(rows);
    return out;
}

static inline void fx_png_free(fx_png *p)
{
    free(p->px);
    memset(p, 0, sizeof *p);
}

/* ---- the documented operator, in double ---------------------------------- */

static inline double fx_srgb(double v)
{
    return v <= 0.0031308 ? 12.92 * v : 1.055 * pow(v, 1.0 / 2.4) - 0.055;
}

static inline double fx_linear(double s)
{
    return s <= 0.04045 ? s / 12.92 : pow((s + 0.055) / 1.055, 2.4);
}

/* round(255 srgb(clamp(c, 0, 1))), NaN as 0. */
static inline int fx_code(double c)
{
    if (!(c > 0))
        c = 0;
    if (c > 1)
        c = 1;
    return (int)floor(255.0 * fx_srgb(c) + 0.5);
}

static inline double fx_clamp_alpha(double a)
{
    return a > 0 ? (a < 1 ? a : 1) : 0;
}

/* The preview's RGBA codes of one premultiplied linear pixel. */
static inline void fx_preview_expect(double R, double G, double B, double A, int out[4])
{
    double a = fx_clamp_alpha(A);
    double c[3] = {0, 0, 0};
    if (a >= 1) {
        c[0] = R, c[1] = G, c[2] = B;
    } else if (a > 0) {
        c[0] = R / a, c[1] = G / a, c[2] = B / a;
    }
    for (int k = 0; k < 3; k++)
        out[k] = fx_code(c[k]);
    out[3] = (int)floor(255.0 * a + 0.5);
}

/* Every pixel of png (the full-size preview) against the film through
 * fx_preview_expect, to 1 code; returns how many channel values were off by
 * one (for the caller to bound or report). */
static inline size_t fx_check_preview(const fx_png *png, const mr_film *f)
{
    assert_int_equal(png->width, f->width);
    assert_int_equal(png->height, f->height);
    assert_int_equal(png->channels, 4);
    size_t off_by_one = 0;
    for (int y = 0; y < f->height; y++)
        for (int x = 0; x < f->width; x++) {
            size_t i = (size_t)y * (size_t)f->width + (size_t)x;
            int want[4];
            fx_preview_expect(f->r[i], f->g[i], f->b[i], f->a[i], want);
            for (int k = 0; k < 4; k++) {
                int got = png->px[i * 4 + (size_t)k], d = abs(got - want[k]);
                if (d > 1)
                    fail_msg("pixel (%d, %d) channel %d: %d, want %d (R G B A = %g %g %g %g)", x, y,
                             k, got, want[k], f->r[i], f->g[i], f->b[i], f->a[i]);
                off_by_one += d == 1;
            }
        }
    return off_by_one;
}

static inline double fx_finite(double v)
{
    return isfinite(v) ? v : 0.0;
}

/* Thumbnail pixel (x, y) of a tw x th thumbnail of f (microray.h: box mean
 * of premultiplied linear pixels over a checkerboard of 8-pixel squares,
 * codes 153 and 102, light at the top left). */
static inline void fx_thumb_expect(const mr_film *f, int tw, int th, int x, int y, int out[3])
{
    long long W = f->width, H = f->height;
    long long x0 = x * W / tw, x1 = (x + 1) * W / tw, y0 = y * H / th, y1 = (y + 1) * H / th;
    double s[4] = {0, 0, 0, 0};
    for (long long sy = y0; sy < y1; sy++)
        for (long long sx = x0; sx < x1; sx++) {
            size_t i = (size_t)(sy * W + sx);
            s[0] += fx_finite(f->r[i]);
            s[1] += fx_finite(f->g[i]);
            s[2] += fx_finite(f->b[i]);
            s[3] += fx_finite(f->a[i]);
        }
    double n = (double)((x1 - x0) * (y1 - y0));
    double a = fx_clamp_alpha(s[3] / n);
    double under = fx_linear((((x / 8) + (y / 8)) & 1 ? 102 : 153) / 255.0);
    for (int k = 0; k < 3; k++)
        out[k] = fx_code(s[k] / n + (1 - a) * under);
}

/* The thumbnail at (ox, oy) of image img (RGB, e.g. a contact sheet) against
 * f, to 1 code; returns the count of off-by-one values. */
static inline size_t fx_check_thumb(const fx_png *img, int ox, int oy, const mr_film *f, int tw,
                                    int th)
{
    assert_int_equal(img->channels, 3);
    size_t off_by_one = 0;
    for (int y = 0; y < th; y++)
        for (int x = 0; x < tw; x++) {
            int want[3];
            fx_thumb_expect(f, tw, th, x, y, want);
            const uint8_t *p = img->px + ((size_t)(oy + y) * (size_t)img->width + (size_t)(ox + x)) * 3;
            for (int k = 0; k < 3; k++) {
                int d = abs(p[k] - want[k]);
                if (d > 1)
                    fail_msg("thumbnail pixel (%d, %d) channel %d: %d, want %d", x, y, k, p[k], want[k]);
                off_by_one += d == 1;
            }
        }
    return off_by_one;
}

#endif
