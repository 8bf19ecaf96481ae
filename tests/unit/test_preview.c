/*
 * test_preview.c - PNG previews, thumbnails and contact sheets
 * (render/preview.c; the operator is documented in microray.h).
 *
 * Films with known values are encoded by the core and decoded by libpng's
 * own low-level reader (tests/support/png_fixture.h), and every pixel is
 * checked against the documented formula evaluated in double, to 1 code
 * value (why 1: png_fixture.h). The sweep test shows the off-by-ones are
 * only values within float rounding of a code boundary.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "microray.h"
#include "../support/file_fixture.h"
#include "../support/png_fixture.h"

/* xorshift32: a fixed sequence, so every run checks the same pixels. */
static uint32_t rng_state = 12345u;
static float rnd(void)
{
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 17;
    rng_state ^= rng_state << 5;
    return (float)(rng_state >> 8) / 16777216.0f;
}

static mr_film *new_film(int w, int h)
{
    mr_film *f = NULL;
    mr_error err = {0};
    if (mr_film_new(w, h, &f, &err) < 0)
        fail_msg("%s", err.msg);
    return f;
}

static fx_png encode_decode(const mr_image8 *img)
{
    uint8_t *data = NULL;
    size_t size = 0;
    mr_error err = {0};
    if (mr_png_encode(img, &data, &size, &err) < 0)
        fail_msg("%s", err.msg);
    fx_png png = fx_png_read(data, size);
    free(data);
    assert_true(png.srgb);
    return png;
}

static fx_png preview_png(const mr_film *f)
{
    mr_image8 img;
    mr_error err = {0};
    if (mr_preview_from_film(f, &img, &err) < 0)
        fail_msg("%s", err.msg);
    assert_int_equal(img.channels, 4);
    fx_png png = encode_decode(&img);
    mr_image8_free(&img);
    return png;
}

/* Rows of pixel kinds a frame can hold: opaque ramps past white, nothing
 * (alpha 0 with colour left in it), partial coverage, emission beyond its
 * alpha, negatives, NaN and Inf, the linear toe of the curve, alpha above 1. */
static void test_known_values(void **state)
{
    (void)state;
    const int W = 67, H = 48;
    mr_film *f = new_film(W, H);
    for (int y = 0; y < H; y++)
        for (int x = 0; x < W; x++) {
            size_t i = (size_t)y * W + (size_t)x;
            float t = (float)x / (float)(W - 1), a = 1.0f, c[3] = {t * 1.2f, t, t * t};
            switch (y % 8) {
            case 0: break;
            case 1: a = 0.0f; c[0] = rnd(); c[1] = rnd(); c[2] = 0.5f; break;
            case 2: a = rnd(); for (int k = 0; k < 3; k++) c[k] = a * rnd(); break;
            case 3: a = 0.25f * rnd(); for (int k = 0; k < 3; k++) c[k] = a + rnd(); break;
            case 4: c[0] = -t; c[1] = -1e-3f; a = 0.5f; break;
            case 5: c[0] = NAN; c[1] = INFINITY; c[2] = -INFINITY; a = x % 3 ? 0.5f : NAN; break;
            case 6: for (int k = 0; k < 3; k++) c[k] = 0.006f * rnd(); break;
            default: a = 1.0f + rnd(); break;
            }
            f->r[i] = c[0];
            f->g[i] = c[1];
            f->b[i] = c[2];
            f->a[i] = a;
        }
    fx_png png = preview_png(f);
    size_t off = fx_check_preview(&png, f);
    /* spot checks of the rules themselves, independent of fx_preview_expect */
    const uint8_t *p = png.px;
    assert_memory_equal(p + ((size_t)1 * W + 5) * 4, "\0\0\0\0", 4);  /* alpha 0: nothing */
    assert_int_equal(p[((size_t)0 * W + (W - 1)) * 4 + 0], 255);   /* 1.2 clips to white */
    assert_int_equal(p[((size_t)0 * W + (W - 1)) * 4 + 3], 255);
    assert_int_equal(p[((size_t)5 * W + 1) * 4 + 0], 0);           /* NaN -> 0 */
    assert_int_equal(p[((size_t)5 * W + 1) * 4 + 1], 255);         /* +Inf -> 255 */
    assert_int_equal(p[((size_t)5 * W + 1) * 4 + 3], 128);         /* alpha 0.5 */
    assert_int_equal(p[((size_t)5 * W + 0) * 4 + 3], 0);           /* alpha NaN -> 0 */
    print_message("known values: %d pixels, %zu channel values off by one\n", W * H, off);
    assert_true(off <= (size_t)(W * H * 4) / 100);
    fx_png_free(&png);
    mr_film_free(f);
}

/* Every 1/65535 step of [0, 1] (and a little beyond): the codes are round(255
 * srgb(v)) exactly but where v lies within float rounding of a boundary. */
static void test_sweep_is_exact_but_at_boundaries(void **state)
{
    (void)state;
    mr_film *f = new_film(256, 257);
    size_t n = 256u * 257u;
    for (size_t i = 0; i < n; i++) {
        f->r[i] = (float)i / 65535.0f;
        f->g[i] = (float)((double)i / 65535.0 * 0.01); /* the toe, finely */
        f->b[i] = 0.5f * f->r[i];
        f->a[i] = 1.0f;
    }
    fx_png png = preview_png(f);
    size_t off = fx_check_preview(&png, f);
    for (size_t i = 0; i < n; i++)
        for (int k = 0; k < 3; k++) {
            double v = k == 0 ? f->r[i] : k == 1 ? f->g[i] : f->b[i];
            int want = fx_code(v), got = png.px[i * 4 + (size_t)k];
            if (got == want)
                continue;
            /* off by one only next to a boundary: srgb(v) within 1e-6 of (k +- 0.5) / 255 */
            double s = 255.0 * fx_srgb(v > 1 ? 1 : v);
            double boundary = floor(s) + 0.5;
            if (fabs(s - boundary) > 255e-6 && fabs(s - (boundary - 1)) > 255e-6)
                fail_msg("v = %.9g: code %d, want %d, not at a boundary (255 srgb = %.9f)", v, got,
                         want, s);
        }
    print_message("sweep: %zu values, %zu at a boundary off by one\n", n * 3, off);
    fx_png_free(&png);
    mr_film_free(f);
}

static void test_thumbnail_filter(void **state)
{
    (void)state;
    int tw, th;
    mr_preview_thumb_size(1920, 1080, &tw, &th);
    assert_true(tw == 160 && th == 90);
    mr_preview_thumb_size(1080, 1920, &tw, &th);
    assert_true(tw == 90 && th == 160);
    mr_preview_thumb_size(100, 50, &tw, &th); /* never enlarged */
    assert_true(tw == 100 && th == 50);
    mr_preview_thumb_size(1, 8192, &tw, &th);
    assert_true(tw == 1 && th == 160);
    mr_preview_thumb_size(8192, 1, &tw, &th);
    assert_true(tw == 160 && th == 1);

    /* 333 x 187 -> 160 x 90: boxes of 2 or 3 pixels each way; partial
     * coverage, holes and a transparent band over the checkerboard */
    mr_film *f = new_film(333, 187);
    for (size_t i = 0; i < 333u * 187u; i++) {
        float a = (i / 333) % 40 < 10 ? 0.0f : rnd() < 0.2f ? rnd() : 1.0f;
        f->a[i] = a;
        f->r[i] = a * rnd();
        f->g[i] = a * rnd() * 1.5f;
        f->b[i] = a * 0.2f;
    }
    mr_image8 thumb;
    mr_error err = {0};
    assert_int_equal(mr_preview_thumbnail(f, &thumb, &err), MR_OK);
    assert_true(thumb.width == 160 && thumb.height == 90 && thumb.channels == 3);
    fx_png png = encode_decode(&thumb);
    size_t off = fx_check_thumb(&png, 0, 0, f, 160, 90);
    print_message("thumbnail: %zu channel values off by one\n", off);
    /* a transparent pixel shows the checkerboard: light at the top left */
    assert_int_equal(png.px[0], 153);
    assert_int_equal(png.px[(size_t)8 * 3], 102);
    fx_png_free(&png);
    mr_image8_free(&thumb);
    mr_film_free(f);
}

static void test_sheet_frames_and_layout(void **state)
{
    (void)state;
    size_t idx[MR_SHEET_MAX_FRAMES];
    assert_int_equal(mr_contact_sheet_frames(0, idx), 0);
    assert_int_equal(mr_contact_sheet_frames(49, idx), 49);
    assert_true(idx[0] == 0 && idx[48] == 48);
    assert_int_equal(mr_contact_sheet_frames(64, idx), 64);
    assert_int_equal(idx[63], 63);
    size_t sizes[] = {65, 100, 1000, 100000};
    for (size_t s = 0; s < 4; s++) {
        assert_int_equal(mr_contact_sheet_frames(sizes[s], idx), MR_SHEET_MAX_FRAMES);
        assert_int_equal(idx[0], 0);
        assert_int_equal(idx[63], sizes[s] - 1);
        for (int i = 1; i < 64; i++)
            assert_true(idx[i] > idx[i - 1]);
    }
    mr_sheet_layout l;
    mr_contact_sheet_layout(49, 160, 90, &l);
    assert_true(l.columns == 7 && l.rows == 7 && l.width == 4 + 7 * 164 && l.height == 4 + 7 * 94);
    mr_contact_sheet_layout(10, 160, 90, &l);
    assert_true(l.columns == 4 && l.rows == 3);
    mr_contact_sheet_layout(64, 160, 90, &l);
    assert_true(l.columns == 8 && l.rows == 8);
    mr_contact_sheet_layout(1, 20, 10, &l);
    assert_true(l.columns == 1 && l.rows == 1 && l.width == 28 && l.height == 18);
    int x, y;
    mr_contact_sheet_layout(5, 20, 10, &l);
    mr_contact_sheet_cell(&l, 4, &x, &y);
    assert_true(x == 4 + 24 && y == 4 + 14);
}

static uint8_t grey_at(const mr_image8 *img, int x, int y)
{
    const uint8_t *p = img->px + ((size_t)y * (size_t)img->width + (size_t)x) * 3;
    assert_true(p[0] == p[1] && p[1] == p[2]);
    return p[0];
}

static void test_sheet_cells(void **state)
{
    (void)state;
    mr_image8 sheet, thumb;
    mr_error err = {0};
    assert_int_equal(mr_contact_sheet_new(5, 20, 10, &sheet, &err), MR_OK);
    assert_true(sheet.width == 76 && sheet.height == 32 && sheet.channels == 3);
    /* gutters, a pending cell's grey and its diagonals */
    assert_int_equal(grey_at(&sheet, 0, 0), 16);
    assert_int_equal(grey_at(&sheet, 24, 10), 16);
    assert_int_equal(grey_at(&sheet, 4, 4), 128);       /* top left corner: a diagonal */
    assert_int_equal(grey_at(&sheet, 4 + 19, 4), 128);  /* top right */
    assert_int_equal(grey_at(&sheet, 4 + 19, 13), 128); /* bottom right */
    assert_int_equal(grey_at(&sheet, 4 + 10, 4), 56);
    assert_int_equal(grey_at(&sheet, 4 + 2, 4 + 5), 56);
    /* the unused sixth cell is background */
    assert_int_equal(grey_at(&sheet, 4 + 2 * 24 + 5, 4 + 14 + 5), 16);

    mr_film *f = new_film(20, 10);
    for (size_t i = 0; i < 200; i++) {
        f->r[i] = f->a[i] = 1.0f;
        f->g[i] = f->b[i] = 0.0f;
    }
    assert_int_equal(mr_preview_thumbnail(f, &thumb, &err), MR_OK);
    assert_int_equal(mr_contact_sheet_put(&sheet, 4, &thumb, &err), MR_OK);
    for (int y = 0; y < 10; y++)
        for (int x = 0; x < 20; x++) {
            const uint8_t *p = sheet.px + ((size_t)(18 + y) * 76 + (size_t)(28 + x)) * 3;
            assert_true(p[0] == 255 && p[1] == 0 && p[2] == 0);
        }
    assert_int_equal(grey_at(&sheet, 27, 18), 16); /* the gutter left of it */
    assert_int_equal(mr_contact_sheet_put(&sheet, 6, &thumb, &err), MR_ERR_INVALID);
    mr_image8 wrong = thumb;
    wrong.width = 19;
    assert_int_equal(mr_contact_sheet_put(&sheet, 0, &wrong, &err), MR_ERR_INVALID);
    assert_int_equal(mr_contact_sheet_new(0, 20, 10, &wrong, &err),
                     MR_ERR_INVALID);
    assert_int_equal(mr_contact_sheet_new(65, 20, 10, &wrong, &err), MR_ERR_INVALID);
    mr_image8_free(&thumb);
    mr_image8_free(&sheet);
    mr_film_free(f);
}

static void test_png_round_trip_and_damage(void **state)
{
    (void)state;
    mr_image8 img = {.width = 31, .height = 7, .channels = 4};
    img.px = malloc(31 * 7 * 4);
    for (size_t i = 0; i < 31 * 7 * 4; i++)
        img.px[i] = (uint8_t)(rnd() * 256.0f);
    for (int ch = 3; ch <= 4; ch++) {
        img.channels = ch;
        uint8_t *data = NULL;
        size_t size = 0;
        mr_error err = {0};
        assert_int_equal(mr_png_encode(&img, &data, &size, &err), MR_OK);
        mr_image8 back;
        assert_int_equal(mr_png_decode(data, size, "test", &back, &err), MR_OK);
        assert_true(back.width == 31 && back.height == 7 && back.channels == ch);
        assert_memory_equal(back.px, img.px, (size_t)31 * 7 * (size_t)ch);
        mr_image8_free(&back);
        /* truncated, a flipped byte in the image data, not a PNG at all */
        assert_int_equal(mr_png_decode(data, size / 2, "cut.png", &back, &err), MR_ERR_FORMAT);
        assert_non_null(strstr(err.msg, "cut.png"));
        data[size - 20] ^= 0x5a;
        assert_int_equal(mr_png_decode(data, size, "flipped.png", &back, &err), MR_ERR_FORMAT);
        assert_int_equal(mr_png_decode((const uint8_t *)"GIF89a", 6, "gif", &back, &err),
                         MR_ERR_FORMAT);
        assert_null(back.px);
        free(data);
    }
    mr_error err = {0};
    uint8_t *data = NULL;
    size_t size = 0;
    img.channels = 2;
    assert_int_equal(mr_png_encode(&img, &data, &size, &err), MR_ERR_INVALID);
    free(img.px);
}

static void test_no_beauty_pass(void **state)
{
    (void)state;
    mr_film *f = new_film(4, 4);
    float *a = f->a;
    f->a = NULL; /* a film without the RGBA pass */
    mr_image8 img;
    mr_error err = {0};
    assert_int_equal(mr_preview_from_film(f, &img, &err), MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "R, G, B, A"));
    assert_int_equal(mr_preview_thumbnail(f, &img, &err), MR_ERR_INVALID);
    f->a = a;
    mr_film_free(f);
}

static void test_write_film(void **state)
{
    (void)state;
    mr_film *f = new_film(9, 5);
    for (size_t i = 0; i < 45; i++) {
        f->a[i] = (float)i / 44.0f;
        f->g[i] = 0.5f * f->a[i];
    }
    char path[128];
    snprintf(path, sizeof path, "%s/0000.png", tmp_dir);
    mr_error err = {0};
    assert_int_equal(mr_png_write_film(path, f, &err), MR_OK);
    size_t n = 0;
    uint8_t *bytes = file_get(path, &n);
    fx_png png = fx_png_read(bytes, n);
    fx_check_preview(&png, f);
    fx_png_free(&png);
    free(bytes);
    /* an unwritable place names the file */
    assert_int_equal(mr_png_write_film("/proc/no/such/dir/x.png", f, &err), MR_ERR_IO);
    assert_non_null(strstr(err.msg, "/proc/no/such/dir"));
    mr_film_free(f);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_known_values),
        cmocka_unit_test(test_sweep_is_exact_but_at_boundaries),
        cmocka_unit_test(test_thumbnail_filter),
        cmocka_unit_test(test_sheet_frames_and_layout),
        cmocka_unit_test(test_sheet_cells),
        cmocka_unit_test(test_png_round_trip_and_damage),
        cmocka_unit_test(test_no_beauty_pass),
        cmocka_unit_test(test_write_film),
    };
    return cmocka_run_group_tests_name("preview", tests, file_fixture_setup, file_fixture_teardown);
}
