/*
 * test_image.c - image assets (core/asset/image.c): PNG 8/16 bit in every
 * colour type, JPEG (a real exemplar from assimp-testmodels and files
 * written here by libjpeg), scanline EXR of every channel set the reader
 * takes and refuses; the caps, truncated and damaged files, and the trip
 * through the import worker's blob.
 *
 * Files are written with the libraries' own encoders (libpng, libjpeg,
 * OpenEXR's C API), never by the code under test. Integer formats must
 * decode exactly (luminance by the integer formula of image.h); JPEG is
 * lossy, so its samples are checked within 3 codes of what was written at
 * quality 100 (measured: at most 1 off for the smooth ramps used here).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <stdio.h>

#include <jpeglib.h>
#include <math.h>
#include <png.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "asset/asset.h"
#include "asset/image.h"
#include "util/crc32.h"
#define TMP_DIR_TEMPLATE "/tmp/mr-test-image-XXXXXX"
#include "../support/exr_image_fixture.h"
#include "../support/file_fixture.h"

#define CRACKED "/usr/share/assimp/models/IRRMesh/crackedground_1-6.jpg"

static void path_of(const char *name, char *out, size_t size)
{
    snprintf(out, size, "%s/%s", tmp_dir, name);
}

/* ---- writers --------------------------------------------------------------- */

/* A PNG of the given type from 16-bit-capable values (depth 8 uses the low
 * byte); channels by colour type. */
static void write_png(const char *path, int w, int h, int depth, int ctype, int interlace,
                      const uint16_t *values, int channels, const png_color *palette, int ncolors)
{
    FILE *f = fopen(path, "wb");
    assert_non_null(f);
    png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, NULL, NULL, NULL);
    png_infop info = png_create_info_struct(png);
    assert_non_null(png);
    if (setjmp(png_jmpbuf(png)))
        fail_msg("libpng failed writing %s", path);
    png_init_io(png, f);
    png_set_IHDR(png, info, (png_uint_32)w, (png_uint_32)h, depth, ctype, interlace,
                 PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
    if (palette)
        png_set_PLTE(png, info, palette, ncolors);
    png_write_info(png, info);
    if (depth == 16)
        png_set_swap(png);
    if (depth < 8)
        png_set_packing(png);
    int passes = png_set_interlace_handling(png);
    size_t bps = depth == 16 ? 2 : 1;
    uint8_t *row = malloc((size_t)w * channels * bps);
    for (int p = 0; p < passes; p++)
        for (int y = 0; y < h; y++) {
            for (int i = 0; i < w * channels; i++) {
                uint16_t v = values[(size_t)y * w * channels + i];
                if (bps == 2)
                    memcpy(row + i * 2, &v, 2);
                else
                    row[i] = (uint8_t)v;
            }
            png_write_row(png, row);
        }
    png_write_end(png, NULL);
    png_destroy_write_struct(&png, &info);
    free(row);
    fclose(f);
}

static void write_jpeg(const char *path, int w, int h, int components, const uint8_t *px)
{
    struct jpeg_compress_struct c;
    struct jpeg_error_mgr e;
    c.err = jpeg_std_error(&e);
    jpeg_create_compress(&c);
    FILE *f = fopen(path, "wb");
    assert_non_null(f);
    jpeg_stdio_dest(&c, f);
    c.image_width = (JDIMENSION)w;
    c.image_height = (JDIMENSION)h;
    c.input_components = components;
    c.in_color_space = components == 1 ? JCS_GRAYSCALE : JCS_RGB;
    jpeg_set_defaults(&c);
    jpeg_set_quality(&c, 100, TRUE);
    jpeg_start_compress(&c, TRUE);
    while (c.next_scanline < c.image_height) {
        JSAMPROW r = (JSAMPROW)(px + (size_t)c.next_scanline * w * components);
        jpeg_write_scanlines(&c, &r, 1);
    }
    jpeg_finish_compress(&c);
    jpeg_destroy_compress(&c);
    fclose(f);
}

static mr_asset *load_ok(const char *path)
{
    mr_asset *a = NULL;
    mr_error err = {0};
    int rc = mr_asset_load(path, &a, &err);
    if (rc != MR_OK)
        fail_msg("%s: %s", path, err.msg);
    assert_true(mr_asset_is_image(a));
    assert_int_equal(a->mesh_count, 0);
    return a;
}

static void load_fails(const char *path, int code, const char *needle)
{
    mr_asset *a = NULL;
    mr_error err = {0};
    int rc = mr_asset_load(path, &a, &err);
    assert_null(a);
    if (rc != code || !strstr(err.msg, path) || (needle && !strstr(err.msg, needle)))
        fail_msg("%s: expected %s mentioning the file and \"%s\", got %s: %s", path,
                 mr_err_name(code), needle ? needle : "", mr_err_name(rc), err.msg);
}

/* ---- PNG ---------------------------------------------------------------------- */

static uint32_t luma(uint32_t r, uint32_t g, uint32_t b) { return (2126 * r + 7152 * g + 722 * b + 5000) / 10000; }

static void test_png_grey_8_and_16(void **state)
{
    (void)state;
    enum { W = 13, H = 7 };
    uint16_t v[W * H];
    for (int i = 0; i < W * H; i++)
        v[i] = (uint16_t)(i * 977 % 65536);
    char p8[300], p16[300];
    path_of("g8.png", p8, sizeof p8);
    path_of("g16.png", p16, sizeof p16);
    uint16_t v8[W * H];
    for (int i = 0; i < W * H; i++)
        v8[i] = v[i] & 0xff;
    write_png(p8, W, H, 8, PNG_COLOR_TYPE_GRAY, PNG_INTERLACE_NONE, v8, 1, NULL, 0);
    write_png(p16, W, H, 16, PNG_COLOR_TYPE_GRAY, PNG_INTERLACE_NONE, v, 1, NULL, 0);
    mr_asset *a8 = load_ok(p8), *a16 = load_ok(p16);
    assert_int_equal(a8->image->type, MR_SAMPLE_U8);
    assert_int_equal(a16->image->type, MR_SAMPLE_U16);
    assert_int_equal(a8->image->width, W);
    assert_int_equal(a8->image->height, H);
    for (int y = 0; y < H; y++)
        for (int x = 0; x < W; x++) {
            assert_int_equal(mr_image_sample(a8->image, x, y), v8[y * W + x]);
            assert_int_equal(mr_image_sample(a16->image, x, y), v[y * W + x]);
        }
    assert_true(mr_image_unit(a16->image) == 65535.0);
    mr_asset_free(a8);
    mr_asset_free(a16);
}

static void test_png_colour_types(void **state)
{
    (void)state;
    enum { W = 9, H = 5 };
    uint16_t rgb[W * H * 3], rgba16[W * H * 4], ga[W * H * 2], idx[W * H], bits[W * H];
    png_color pal[4] = {{0, 0, 0}, {255, 0, 0}, {0, 255, 0}, {10, 20, 250}};
    for (int i = 0; i < W * H; i++) {
        for (int c = 0; c < 3; c++)
            rgb[i * 3 + c] = (uint16_t)((i * 37 + c * 91) % 256);
        for (int c = 0; c < 4; c++)
            rgba16[i * 4 + c] = (uint16_t)((i * 4099 + c * 12345) % 65536);
        ga[i * 2] = (uint16_t)(i * 5 % 256);
        ga[i * 2 + 1] = 77;
        idx[i] = (uint16_t)(i % 4);
        bits[i] = (uint16_t)(i % 2);
    }
    char p[5][300];
    path_of("rgb.png", p[0], 300);
    path_of("rgba16.png", p[1], 300);
    path_of("ga.png", p[2], 300);
    path_of("pal.png", p[3], 300);
    path_of("bits.png", p[4], 300);
    write_png(p[0], W, H, 8, PNG_COLOR_TYPE_RGB, PNG_INTERLACE_NONE, rgb, 3, NULL, 0);
    write_png(p[1], W, H, 16, PNG_COLOR_TYPE_RGBA, PNG_INTERLACE_NONE, rgba16, 4, NULL, 0);
    write_png(p[2], W, H, 8, PNG_COLOR_TYPE_GRAY_ALPHA, PNG_INTERLACE_NONE, ga, 2, NULL, 0);
    write_png(p[3], W, H, 2, PNG_COLOR_TYPE_PALETTE, PNG_INTERLACE_NONE, idx, 1, pal, 4);
    write_png(p[4], W, H, 1, PNG_COLOR_TYPE_GRAY, PNG_INTERLACE_NONE, bits, 1, NULL, 0);
    mr_asset *a[5];
    for (int k = 0; k < 5; k++)
        a[k] = load_ok(p[k]);
    assert_int_equal(a[0]->image->file_channels, 3);
    assert_int_equal(a[1]->image->type, MR_SAMPLE_U16);
    for (int i = 0; i < W * H; i++) {
        int x = i % W, y = i / W;
        assert_int_equal(mr_image_sample(a[0]->image, x, y), luma(rgb[i * 3], rgb[i * 3 + 1], rgb[i * 3 + 2]));
        assert_int_equal(mr_image_sample(a[1]->image, x, y),
                         luma(rgba16[i * 4], rgba16[i * 4 + 1], rgba16[i * 4 + 2]));
        assert_int_equal(mr_image_sample(a[2]->image, x, y), ga[i * 2]);
        const png_color *c = &pal[idx[i]];
        assert_int_equal(mr_image_sample(a[3]->image, x, y), luma(c->red, c->green, c->blue));
        /* 1-bit grey expands to 0 and 255 */
        assert_int_equal(mr_image_sample(a[4]->image, x, y), bits[i] ? 255 : 0);
    }
    for (int k = 0; k < 5; k++)
        mr_asset_free(a[k]);
}

static void test_png_interlaced(void **state)
{
    (void)state;
    enum { W = 31, H = 17 };
    uint16_t v[W * H];
    for (int i = 0; i < W * H; i++)
        v[i] = (uint16_t)((i * 7919) % 65536);
    char p[300];
    path_of("adam7.png", p, sizeof p);
    write_png(p, W, H, 16, PNG_COLOR_TYPE_GRAY, PNG_INTERLACE_ADAM7, v, 1, NULL, 0);
    mr_asset *a = load_ok(p);
    for (int i = 0; i < W * H; i++)
        assert_int_equal(mr_image_sample(a->image, i % W, i / W), v[i]);
    mr_asset_free(a);
}

/* Rewrites the IHDR's width and height and its CRC. */
static void patch_ihdr(uint8_t *png, uint32_t w, uint32_t h)
{
    uint8_t *ihdr = png + 8; /* length(4) "IHDR"(4) data(13) crc(4) */
    for (int i = 0; i < 4; i++) {
        ihdr[8 + i] = (uint8_t)(w >> (24 - 8 * i));
        ihdr[12 + i] = (uint8_t)(h >> (24 - 8 * i));
    }
    uint32_t crc = mr_crc32(ihdr + 4, 17);
    for (int i = 0; i < 4; i++)
        ihdr[21 + i] = (uint8_t)(crc >> (24 - 8 * i));
}

static void test_png_bad_input(void **state)
{
    (void)state;
    enum { W = 40, H = 30 };
    uint16_t v[W * H];
    for (int i = 0; i < W * H; i++)
        v[i] = (uint16_t)(i * 31 % 256);
    char p[300], q[300];
    path_of("whole.png", p, sizeof p);
    write_png(p, W, H, 8, PNG_COLOR_TYPE_GRAY, PNG_INTERLACE_NONE, v, 1, NULL, 0);
    size_t n;
    uint8_t *b = file_get(p, &n);
    /* truncated at several places: header, inside IDAT, before IEND */
    size_t cuts[] = {12, 30, n / 2, n - 13};
    for (size_t k = 0; k < sizeof cuts / sizeof cuts[0]; k++) {
        path_of("cut.png", q, sizeof q);
        file_put(q, b, cuts[k]);
        load_fails(q, MR_ERR_FORMAT, "PNG");
    }
    /* a bit flipped in the image data: the zlib or CRC check catches it */
    uint8_t *c = malloc(n);
    memcpy(c, b, n);
    c[n / 2] ^= 0x10;
    path_of("flip.png", q, sizeof q);
    file_put(q, c, n);
    load_fails(q, MR_ERR_FORMAT, "PNG");
    /* sizes over the caps, refused from the header */
    memcpy(c, b, n);
    patch_ihdr(c, MR_MAX_IMAGE_SIDE + 1, 1);
    path_of("wide.png", q, sizeof q);
    file_put(q, c, n);
    load_fails(q, MR_ERR_LIMIT, "cap");
    patch_ihdr(c, 8193, 8193);
    path_of("many.png", q, sizeof q);
    file_put(q, c, n);
    load_fails(q, MR_ERR_LIMIT, "cap");
    free(c);
    free(b);
}

/* ---- JPEG ----------------------------------------------------------------------- */

static void test_jpeg_real_exemplar(void **state)
{
    (void)state;
    mr_asset *a = load_ok(CRACKED);
    const mr_image *img = a->image;
    assert_int_equal(img->width, 400);
    assert_int_equal(img->height, 400);
    assert_int_equal(img->type, MR_SAMPLE_U8);
    assert_int_equal(img->file_channels, 3);
    assert_int_equal(img->format, MR_IMAGE_JPEG);
    double sum = 0;
    unsigned lo = 255, hi = 0;
    for (uint32_t y = 0; y < img->height; y++)
        for (uint32_t x = 0; x < img->width; x++) {
            unsigned s = (unsigned)mr_image_sample(img, x, y);
            sum += s;
            lo = s < lo ? s : lo;
            hi = s > hi ? s : hi;
        }
    /* a ground texture: neither flat nor saturated */
    assert_true(hi - lo > 100);
    double mean = sum / (400.0 * 400.0);
    assert_true(mean > 30 && mean < 225);
    uint32_t w, h;
    assert_true(mr_asset_image_size(a, &w, &h));
    assert_int_equal(w, 400);
    mr_asset_free(a);

    /* truncated copies: libjpeg's "premature end" is an error, not grey */
    size_t n;
    uint8_t *b = file_get(CRACKED, &n);
    char q[300];
    path_of("cut.jpg", q, sizeof q);
    size_t cuts[] = {4, 200, n / 2, n - 2};
    for (size_t k = 0; k < sizeof cuts / sizeof cuts[0]; k++) {
        file_put(q, b, cuts[k]);
        load_fails(q, MR_ERR_FORMAT, "JPEG");
    }
    free(b);
}

static void test_jpeg_written(void **state)
{
    (void)state;
    enum { W = 48, H = 20 };
    uint8_t grey[W * H], rgb[W * H * 3];
    for (int y = 0; y < H; y++)
        for (int x = 0; x < W; x++) {
            grey[y * W + x] = (uint8_t)(x * 5 + y);
            rgb[(y * W + x) * 3] = (uint8_t)(x * 5);
            rgb[(y * W + x) * 3 + 1] = (uint8_t)(y * 12);
            rgb[(y * W + x) * 3 + 2] = (uint8_t)(200 - x);
        }
    char pg[300], pc[300];
    path_of("grey.jpg", pg, sizeof pg);
    path_of("rgb.jpg", pc, sizeof pc);
    write_jpeg(pg, W, H, 1, grey);
    write_jpeg(pc, W, H, 3, rgb);
    mr_asset *g = load_ok(pg), *c = load_ok(pc);
    assert_int_equal(g->image->file_channels, 1);
    assert_int_equal(c->image->file_channels, 3);
    int worst = 0;
    for (int i = 0; i < W * H; i++) {
        int dg = abs((int)mr_image_sample(g->image, i % W, i / W) - grey[i]);
        int want = (int)luma(rgb[i * 3], rgb[i * 3 + 1], rgb[i * 3 + 2]);
        int dc = abs((int)mr_image_sample(c->image, i % W, i / W) - want);
        worst = dg > worst ? dg : worst;
        worst = dc > worst ? dc : worst;
    }
    assert_true(worst <= 3);
    mr_asset_free(g);
    mr_asset_free(c);

    /* a frame header claiming 20000 x 20000: over the cap, refused before
     * any pixel is allocated */
    size_t n;
    uint8_t *b = file_get(pg, &n);
    size_t sof = 0;
    for (size_t i = 2; i + 9 < n; i++)
        if (b[i] == 0xff && (b[i + 1] == 0xc0 || b[i + 1] == 0xc2)) {
            sof = i;
            break;
        }
    assert_true(sof > 0);
    b[sof + 5] = 20000 >> 8, b[sof + 6] = 20000 & 0xff; /* height */
    b[sof + 7] = 20000 >> 8, b[sof + 8] = 20000 & 0xff; /* width */
    char q[300];
    path_of("huge.jpg", q, sizeof q);
    file_put(q, b, n);
    load_fails(q, MR_ERR_LIMIT, "cap");
    free(b);
}

/* ---- EXR ------------------------------------------------------------------------- */

static void test_exr_channel_sets(void **state)
{
    (void)state;
    enum { W = 11, H = 6 };
    float a[W * H], b[W * H], c[W * H];
    for (int i = 0; i < W * H; i++) {
        a[i] = (float)i * 0.25f - 3.0f; /* exact in half too */
        b[i] = (float)(i % 7) * 0.5f;
        c[i] = 100.0f - (float)i;
    }
    char p[300];
    /* Y (half) among other channels: Y wins */
    {
        const char *names[] = {"A", "Y", "Z"};
        exr_pixel_type_t types[] = {EXR_PIXEL_HALF, EXR_PIXEL_HALF, EXR_PIXEL_FLOAT};
        const float *planes[] = {b, a, c};
        path_of("y.exr", p, sizeof p);
        assert_true(fx_exr_write(p, W, H, 3, names, types, planes));
        mr_asset *x = load_ok(p);
        assert_int_equal(x->image->type, MR_SAMPLE_F32);
        assert_int_equal(x->image->file_channels, 3);
        for (int i = 0; i < W * H; i++)
            assert_true(mr_image_sample(x->image, i % W, i / W) == a[i]);
        mr_asset_free(x);
    }
    /* one channel of any name (plus alpha): that channel */
    {
        const char *names[] = {"height", "A"};
        exr_pixel_type_t types[] = {EXR_PIXEL_FLOAT, EXR_PIXEL_HALF};
        const float *planes[] = {c, b};
        path_of("one.exr", p, sizeof p);
        assert_true(fx_exr_write(p, W, H, 2, names, types, planes));
        mr_asset *x = load_ok(p);
        for (int i = 0; i < W * H; i++)
            assert_true(mr_image_sample(x->image, i % W, i / W) == c[i]);
        mr_asset_free(x);
    }
    /* R, G, B: Rec. 709 luminance in float */
    {
        const char *names[] = {"B", "G", "R"};
        exr_pixel_type_t types[] = {EXR_PIXEL_FLOAT, EXR_PIXEL_FLOAT, EXR_PIXEL_UINT};
        for (int i = 0; i < W * H; i++)
            c[i] = (float)(i * 3);
        const float *planes[] = {a, b, c};
        path_of("rgb.exr", p, sizeof p);
        assert_true(fx_exr_write(p, W, H, 3, names, types, planes));
        mr_asset *x = load_ok(p);
        for (int i = 0; i < W * H; i++) {
            float want = 0.2126f * c[i] + 0.7152f * b[i] + 0.0722f * a[i];
            assert_true(fabs(mr_image_sample(x->image, i % W, i / W) - want) <= 1e-5 * (1 + fabs(want)));
        }
        mr_asset_free(x);
    }
    /* channels that make no height: refused, naming them */
    {
        const char *names[] = {"U", "V"};
        exr_pixel_type_t types[] = {EXR_PIXEL_FLOAT, EXR_PIXEL_FLOAT};
        const float *planes[] = {a, b};
        path_of("uv.exr", p, sizeof p);
        assert_true(fx_exr_write(p, W, H, 2, names, types, planes));
        load_fails(p, MR_ERR_FORMAT, "U, V");
    }
    /* a NaN: refused, naming the pixel */
    {
        a[3 * W + 5] = NAN;
        const char *names[] = {"Y"};
        exr_pixel_type_t types[] = {EXR_PIXEL_FLOAT};
        const float *planes[] = {a};
        path_of("nan.exr", p, sizeof p);
        assert_true(fx_exr_write(p, W, H, 1, names, types, planes));
        load_fails(p, MR_ERR_FORMAT, "(5, 3)");
        size_t n;
        a[3 * W + 5] = 0;
        assert_true(fx_exr_write(p, W, H, 1, names, types, planes));
        uint8_t *bytes = file_get(p, &n);
        char q[300];
        path_of("cut.exr", q, sizeof q);
        file_put(q, bytes, n - 40);
        load_fails(q, MR_ERR_FORMAT, "EXR");
        file_put(q, bytes, 20);
        load_fails(q, MR_ERR_FORMAT, "EXR");
        free(bytes);
    }
}

/* A microray frame (R G B A Z N id channels) reads as its luminance. */
static void test_exr_frame_as_height(void **state)
{
    (void)state;
    mr_film *f = NULL;
    mr_error err;
    assert_int_equal(mr_film_new(6, 4, &f, &err), MR_OK);
    for (int i = 0; i < 24; i++) {
        f->r[i] = 0.5f;
        f->g[i] = (float)i / 8.0f;
        f->b[i] = 2.0f;
        f->z[i] = 7.0f;
    }
    char p[300];
    path_of("frame.exr", p, sizeof p);
    assert_int_equal(mr_exr_write_file(p, f, NULL, NULL, &err), MR_OK);
    mr_asset *a = load_ok(p);
    for (int i = 0; i < 24; i++) {
        /* the frame's colour is half: these values are exact in half */
        float want = 0.2126f * 0.5f + 0.7152f * ((float)i / 8.0f) + 0.0722f * 2.0f;
        assert_true(fabs(mr_image_sample(a->image, i % 6, i / 6) - want) < 1e-6);
    }
    mr_asset_free(a);
    mr_film_free(f);
}

/* ---- as assets ------------------------------------------------------------------- */

static void test_image_blob_round_trip(void **state)
{
    (void)state;
    mr_asset *a = load_ok(CRACKED);
    uint8_t *blob = NULL;
    size_t n = 0;
    mr_error err;
    assert_int_equal(mr_asset_blob_write(a, &blob, &n, &err), MR_OK);
    mr_asset *b = NULL;
    assert_int_equal(mr_asset_blob_read(blob, n, &b, &err), MR_OK);
    assert_non_null(b->image);
    assert_int_equal(b->image->width, 400);
    assert_int_equal(b->image->format, MR_IMAGE_JPEG);
    assert_memory_equal(a->image->samples, b->image->samples, 400 * 400);
    assert_int_equal(mr_asset_memory(b), mr_asset_memory(a));
    assert_true(mr_asset_memory(a) >= 400 * 400);
    /* every shorter blob is refused, never overread */
    for (size_t cut = 0; cut < n; cut += n / 97 + 1) {
        mr_asset *c = NULL;
        assert_int_equal(mr_asset_blob_read(blob, cut, &c, &err), MR_ERR_FORMAT);
        assert_null(c);
    }
    /* a sample type no image has */
    mr_asset_free(b);
    free(blob);

    /* an image cannot be refined into a model */
    mr_refine_params rp = {.rounds = 1};
    mr_asset *r = NULL;
    assert_int_equal(mr_refine_asset(a, &rp, &r, &err), MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "image"));
    mr_asset_free(a);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_png_grey_8_and_16),
        cmocka_unit_test(test_png_colour_types),
        cmocka_unit_test(test_png_interlaced),
        cmocka_unit_test(test_png_bad_input),
        cmocka_unit_test(test_jpeg_real_exemplar),
        cmocka_unit_test(test_jpeg_written),
        cmocka_unit_test(test_exr_channel_sets),
        cmocka_unit_test(test_exr_frame_as_height),
        cmocka_unit_test(test_image_blob_round_trip),
    };
    return cmocka_run_group_tests(tests, file_fixture_setup, file_fixture_teardown);
}
