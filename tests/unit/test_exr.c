/*
 * test_exr.c - film allocation and the OpenEXR writer/reader (film.h, exr.h).
 *
 * Everything runs against the real OpenEXRCore library and real files in a
 * private temporary directory; the files are also checked with Debian's
 * `exrheader` tool (package openexr), an independent reader built on the C++
 * library, so a file both our reader and exrheader accept is a real EXR.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <openexr.h>

#include <float.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "render/exr.h"
#include "render/film.h"

/* ------------------------------------------------------------------ */
/* helpers                                                             */

typedef struct fixture {
    char dir[64];
} fixture;

static int group_setup(void **state)
{
    fixture *fx = calloc(1, sizeof *fx);
    if (!fx)
        return -1;
    snprintf(fx->dir, sizeof fx->dir, "/tmp/mr_test_exr_XXXXXX");
    if (!mkdtemp(fx->dir)) {
        free(fx);
        return -1;
    }
    *state = fx;
    return 0;
}

static int group_teardown(void **state)
{
    fixture *fx = *state;
    char cmd[128];
    /* Only our own mkdtemp directory. */
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", fx->dir);
    if (system(cmd) != 0)
        fprintf(stderr, "could not remove %s\n", fx->dir);
    free(fx);
    return 0;
}

static void tmp_path(void **state, const char *name, char *out, size_t n)
{
    const fixture *fx = *state;
    snprintf(out, n, "%s/%s", fx->dir, name);
}

static uint8_t *read_all(const char *path, size_t *size)
{
    FILE *f = fopen(path, "rb");
    uint8_t *data = NULL;
    long n;

    assert_non_null(f);
    assert_int_equal(fseek(f, 0, SEEK_END), 0);
    n = ftell(f);
    assert_true(n >= 0);
    rewind(f);
    data = malloc((size_t)n + 1);
    assert_non_null(data);
    assert_int_equal(fread(data, 1, (size_t)n, f), (size_t)n);
    fclose(f);
    *size = (size_t)n;
    return data;
}

static void write_all(const char *path, const void *data, size_t n)
{
    FILE *f = fopen(path, "wb");
    assert_non_null(f);
    assert_int_equal(fwrite(data, 1, n, f), n);
    assert_int_equal(fclose(f), 0);
}

/* Runs a command and returns its stdout+stderr (malloc'ed). */
static char *run_capture(const char *cmd)
{
    FILE *p = popen(cmd, "r");
    char *buf = NULL;
    size_t len = 0, cap = 0, n;

    assert_non_null(p);
    for (;;) {
        if (cap - len < 4096) {
            cap = cap ? cap * 2 : 8192;
            buf = realloc(buf, cap);
            assert_non_null(buf);
        }
        n = fread(buf + len, 1, cap - len - 1, p);
        if (n == 0)
            break;
        len += n;
    }
    buf[len] = '\0';
    pclose(p);
    return buf;
}

enum { PW = 37, PH = 53 }; /* odd, and not a multiple of 16 or 32 rows */

/* A film whose every channel varies per pixel: colour spans half's
 * subnormal to near-max range and negatives, ids exceed 16 bits (a HALF or
 * 16-bit path would corrupt them), normals are negative. */
static mr_film *pattern_film(void)
{
    mr_film *f = NULL;
    mr_error err = {0};
    int x, y;

    assert_int_equal(mr_film_new(PW, PH, &f, &err), MR_OK);
    for (y = 0; y < PH; y++) {
        for (x = 0; x < PW; x++) {
            size_t i = (size_t)y * PW + (size_t)x;
            f->r[i] = (float)(x - 10) * 0.37f + (float)y * 0.0113f;
            f->g[i] = ldexpf(1.0f + (float)x * 0.01f, (y % 40) - 26);
            f->b[i] = 60000.0f * (float)x / (float)(PW - 1) + (float)y;
            f->a[i] = (float)(x + y) / (float)(PW + PH);
            f->z[i] = 1000.0f + (float)x * 0.5f + (float)y * 1e-3f;
            f->nx[i] = -0.6f + 0.01f * (float)x;
            f->ny[i] = -0.8f + 0.003f * (float)y;
            f->nz[i] = -(float)y / (float)PH;
            f->object_id[i] = 65536u + (uint32_t)x * 1000u + (uint32_t)y;
            f->prim_id[i] = (uint32_t)y * 100000u + (uint32_t)x + 70000u;
        }
    }
    f->object_id[0] = 0xFFFFFFFFu;
    f->object_id[1] = 0; /* a miss */
    return f;
}

static const mr_exr_meta k_meta = {.job = "job-42", .frame = 7, .time = 2.5,
                                   .render_seconds = 0.125, .scene_diagonal = 12.5f};

/* HALF check. Binary16 has 11 significant bits, so round-to-nearest is off
 * by at most half an ulp: relative 2^-11 for normal values (|v| >= 2^-14),
 * absolute 2^-25 (half the subnormal spacing 2^-24) below that. The read-back
 * value must also be bit-exactly our own rounding of v: the library may not
 * alter stored halves, and its HALF->FLOAT decode must agree with ours. */
static void check_half(float got, float v)
{
    float want = mr_half_to_float(mr_float_to_half(v));
    assert_true(isfinite(got));
    assert_memory_equal(&got, &want, sizeof got);
    if (fabsf(v) >= ldexpf(1.0f, -14))
        assert_true(fabsf(got - v) <= fabsf(v) * ldexpf(1.0f, -11));
    else
        assert_true(fabsf(got - v) <= ldexpf(1.0f, -25));
}

static void check_same_film(const mr_film *in, const mr_film *out)
{
    size_t i, n = (size_t)in->width * (size_t)in->height;

    assert_int_equal(out->width, in->width);
    assert_int_equal(out->height, in->height);
    for (i = 0; i < n; i++) {
        check_half(out->r[i], in->r[i]);
        check_half(out->g[i], in->g[i]);
        check_half(out->b[i], in->b[i]);
        check_half(out->a[i], in->a[i]);
        /* FLOAT and UINT channels are stored verbatim: exact. */
        assert_memory_equal(&out->z[i], &in->z[i], sizeof(float));
        assert_memory_equal(&out->nx[i], &in->nx[i], sizeof(float));
        assert_memory_equal(&out->ny[i], &in->ny[i], sizeof(float));
        assert_memory_equal(&out->nz[i], &in->nz[i], sizeof(float));
        assert_int_equal(out->object_id[i], in->object_id[i]);
        assert_int_equal(out->prim_id[i], in->prim_id[i]);
    }
}

/* ------------------------------------------------------------------ */
/* half conversion                                                     */

static void test_half_exhaustive_roundtrip(void **state)
{
    uint32_t h;
    (void)state;
    /* Every finite half survives half -> float -> half unchanged. */
    for (h = 0; h < 0x10000u; h++) {
        if (((h >> 10) & 0x1fu) == 0x1fu)
            continue; /* Inf/NaN patterns are never produced */
        assert_int_equal(mr_float_to_half(mr_half_to_float((uint16_t)h)), h);
    }
    assert_true(mr_half_to_float(0x7c00u) == INFINITY);
    assert_true(isnan(mr_half_to_float(0x7e00u)));
}

static void test_half_rounding_nearest_even(void **state)
{
    uint32_t bits;
    (void)state;
    /* Sweep float bit patterns from 0 to 65504 (every 4099th): the chosen half
     * must be a nearest one, and on an exact tie the even one. */
    for (bits = 0; bits <= 0x477fe000u; bits += 4099u) {
        float v, lo, mid, hi;
        uint16_t h;
        double dv, dmid, dlo, dhi;
        memcpy(&v, &bits, sizeof v);
        h = mr_float_to_half(v);
        mid = mr_half_to_float(h);
        dv = v;
        dmid = fabs(dv - mid);
        if (h > 0) {
            lo = mr_half_to_float((uint16_t)(h - 1));
            dlo = fabs(dv - lo);
            assert_true(dmid <= dlo);
            if (dmid == dlo)
                assert_int_equal(h & 1u, 0);
        }
        if (h < 0x7bffu) {
            hi = mr_half_to_float((uint16_t)(h + 1));
            dhi = fabs(dv - hi);
            assert_true(dmid <= dhi);
            if (dmid == dhi)
                assert_int_equal(h & 1u, 0);
        }
        /* Sign symmetry. */
        assert_int_equal(mr_float_to_half(-v), h | 0x8000u);
    }
}

static void test_half_special_values(void **state)
{
    (void)state;
    assert_int_equal(mr_float_to_half(1.0f), 0x3c00);
    assert_int_equal(mr_float_to_half(-2.0f), 0xc000);
    assert_int_equal(mr_float_to_half(65504.0f), 0x7bff);
    /* Ties: 1 + 2^-11 lies halfway between 1 and 1 + 2^-10 -> even (1.0);
     * 1 + 3 * 2^-11 lies between odd 0x3c01 and even 0x3c02 -> 0x3c02. */
    assert_int_equal(mr_float_to_half(1.0f + ldexpf(1.0f, -11)), 0x3c00);
    assert_int_equal(mr_float_to_half(1.0f + 3.0f * ldexpf(1.0f, -11)), 0x3c02);
    /* Subnormals: 2^-24 is the smallest; 2^-25 ties to even zero; just
     * above it rounds up. */
    assert_int_equal(mr_float_to_half(ldexpf(1.0f, -24)), 0x0001);
    assert_int_equal(mr_float_to_half(ldexpf(1.0f, -25)), 0x0000);
    assert_int_equal(mr_float_to_half(nextafterf(ldexpf(1.0f, -25), 1.0f)), 0x0001);
    assert_int_equal(mr_float_to_half(-ldexpf(1.0f, -30)), 0x8000);
    /* Largest subnormal rounding up into the smallest normal. */
    assert_int_equal(mr_float_to_half(ldexpf(1.0f, -14) - ldexpf(1.0f, -26)), 0x0400);
    /* Out of range and non-finite: always finite. */
    assert_int_equal(mr_float_to_half(65519.0f), 0x7bff);
    assert_int_equal(mr_float_to_half(65520.0f), 0x7bff);
    assert_int_equal(mr_float_to_half(1e30f), 0x7bff);
    assert_int_equal(mr_float_to_half(-1e30f), 0xfbff);
    assert_int_equal(mr_float_to_half(INFINITY), 0x7bff);
    assert_int_equal(mr_float_to_half(-INFINITY), 0xfbff);
    assert_int_equal(mr_float_to_half(NAN), 0x0000);
    assert_int_equal(mr_float_to_half(FLT_MAX), 0x7bff);
}

/* ------------------------------------------------------------------ */
/* film                                                                */

static void test_film_caps(void **state)
{
    mr_film *f = NULL;
    mr_error err = {0};
    (void)state;

    assert_int_equal(mr_film_new(8193, 1, &f, &err), MR_ERR_LIMIT);
    assert_null(f);
    assert_non_null(strstr(err.msg, "8193x1"));
    assert_int_equal(mr_film_new(1, 8193, &f, &err), MR_ERR_LIMIT);
    assert_non_null(strstr(err.msg, "1x8193"));
    /* Both sides within 8192 but the product above 4096 * 4096. */
    assert_int_equal(mr_film_new(4097, 4096, &f, &err), MR_ERR_LIMIT);
    assert_non_null(strstr(err.msg, "4097x4096"));
    assert_int_equal(mr_film_new(8192, 8192, &f, &err), MR_ERR_LIMIT);
    assert_int_equal(mr_film_new(0, 5, &f, &err), MR_ERR_INVALID);
    assert_int_equal(mr_film_new(5, -1, &f, &err), MR_ERR_INVALID);
    assert_int_equal(mr_film_new(-2147483647 - 1, -2147483647 - 1, &f, &err),
                     MR_ERR_INVALID);
    assert_int_equal(mr_film_new(2147483647, 2147483647, &f, &err), MR_ERR_LIMIT);
    assert_int_equal(mr_film_new(4, 4, NULL, &err), MR_ERR_INVALID);
    assert_null(f);

    /* Passes: at least one, and only known ones; a film has the planes of
     * its passes and no others; Cryptomatte ranks are even, 2..6. */
    assert_int_equal(mr_film_new_aovs(4, 4, 0, 0, &f, &err), MR_ERR_INVALID);
    assert_int_equal(mr_film_new_aovs(4, 4, MR_AOV_Z | 0x80u, 0, &f, &err), MR_ERR_INVALID);
    assert_null(f);
    assert_int_equal(mr_film_new_aovs(4, 4, MR_AOV_P | MR_AOV_CRYPTOMATTE, 3, &f, &err), MR_OK);
    assert_true(f->px && f->py && f->pz && !f->r && !f->z && !f->nx && !f->tx && !f->object_id);
    assert_int_equal(f->crypto_ranks, 4);
    assert_true(f->crypto[MR_CRYPTO_ASSET][7] && !f->crypto[MR_CRYPTO_ASSET][8]);
    mr_film_free(f);
    assert_int_equal(mr_film_new_aovs(4, 4, MR_AOV_T, 0, &f, &err), MR_OK);
    assert_true(f->tx && f->ty && f->tz && !f->px && !f->nx && !f->r && f->tx[15] == 0.0f);
    assert_int_equal(mr_film_bytes(4, 4, MR_AOV_T, 0), 4 * 4 * 3 * 4);
    mr_film_free(f);
    assert_int_equal(mr_film_new_aovs(4, 4, MR_AOV_CRYPTOMATTE, 100, &f, &err), MR_OK);
    assert_int_equal(f->crypto_ranks, MR_CRYPTO_MAX_RANKS);
    mr_film_free(f);
    f = NULL;

    /* The longest allowed side works and starts zeroed. */
    assert_int_equal(mr_film_new(8192, 1, &f, &err), MR_OK);
    assert_int_equal(f->width, 8192);
    assert_true(f->z[8191] == MR_DEPTH_MISS && f->prim_id[8191] == 0); /* all miss */
    mr_film_free(f);
    mr_film_free(NULL);
}

static void test_film_clear(void **state)
{
    mr_film *f = pattern_film();
    size_t i, n = (size_t)PW * PH;
    (void)state;

    mr_film_clear(f);
    for (i = 0; i < n; i++) {
        assert_true(f->r[i] == 0.0f && f->g[i] == 0.0f && f->b[i] == 0.0f &&
                    f->a[i] == 0.0f && f->z[i] == MR_DEPTH_MISS && f->nx[i] == 0.0f &&
                    f->ny[i] == 0.0f && f->nz[i] == 0.0f);
        assert_int_equal(f->object_id[i], 0);
        assert_int_equal(f->prim_id[i], 0);
    }
    mr_film_clear(NULL);
    mr_film_free(f);
}

/* ------------------------------------------------------------------ */
/* round trips                                                         */

static void check_exrheader(const char *path, const char *compression_line)
{
    /* In the file's (sorted) order, as exrheader prints them. */
    static const char *const chans[] = {
        "    A, 16-bit floating-point, sampling 1 1\n",
        "    B, 16-bit floating-point, sampling 1 1\n",
        "    G, 16-bit floating-point, sampling 1 1\n",
        "    N.X, 32-bit floating-point, sampling 1 1\n",
        "    N.Y, 32-bit floating-point, sampling 1 1\n",
        "    N.Z, 32-bit floating-point, sampling 1 1\n",
        "    R, 16-bit floating-point, sampling 1 1\n",
        "    Z, 32-bit floating-point, sampling 1 1\n",
        "    id.object, 32-bit unsigned integer, sampling 1 1\n",
        "    id.primitive, 32-bit unsigned integer, sampling 1 1\n",
    };
    char cmd[512], *out, *prev, *p;
    size_t i, lines = 0;

    snprintf(cmd, sizeof cmd, "exrheader '%s' 2>&1", path);
    out = run_capture(cmd);
    prev = out;
    for (i = 0; i < sizeof chans / sizeof chans[0]; i++) {
        p = strstr(out, chans[i]);
        if (!p)
            fail_msg("exrheader output lacks \"%s\":\n%s", chans[i], out);
        assert_true(p >= prev);
        prev = p;
    }
    for (p = out; (p = strstr(p, ", sampling ")) != NULL; p++)
        lines++;
    assert_int_equal(lines, 10);
    assert_non_null(strstr(out, "dataWindow (type box2i): (0 0) - (36 52)\n"));
    assert_non_null(strstr(out, "displayWindow (type box2i): (0 0) - (36 52)\n"));
    if (!strstr(out, compression_line))
        fail_msg("exrheader output lacks \"%s\":\n%s", compression_line, out);
    assert_non_null(strstr(out, "microray.version (type string): \"" MR_VERSION_STRING "\""));
    assert_non_null(strstr(out, "microray.job (type string): \"job-42\""));
    assert_non_null(strstr(out, "microray.frame (type int): 7\n"));
    assert_non_null(strstr(out, "microray.time (type double): 2.5\n"));
    assert_non_null(strstr(out, "microray.renderSeconds (type double): 0.125\n"));
    assert_non_null(strstr(out, "microray.sceneDiagonal (type float): 12.5\n"));
    free(out);
}

static void roundtrip(void **state, mr_compression c, int zip_level, const char *name,
                      const char *compression_line)
{
    char path[256];
    mr_film *in = pattern_film(), *out = NULL;
    mr_exr_options opt = {c, zip_level, 0, false};
    mr_exr_meta meta;
    mr_error err = {0};
    uint8_t *mem = NULL, *file = NULL;
    size_t mem_size = 0, file_size = 0;
    int rc;

    tmp_path(state, name, path, sizeof path);
    rc = mr_exr_write_file(path, in, &opt, &k_meta, &err);
    if (rc != MR_OK)
        fail_msg("write %s: %s", name, err.msg);

    memset(&meta, 0xAB, sizeof meta);
    rc = mr_exr_read_file(path, &out, &meta, &err);
    if (rc != MR_OK)
        fail_msg("read %s: %s", name, err.msg);
    check_same_film(in, out);
    assert_false(out->cleared); /* the file's values: a render must write every plane */
    assert_string_equal(meta.job, "job-42");
    assert_int_equal(meta.frame, 7);
    assert_true(meta.time == 2.5);
    assert_true(meta.render_seconds == 0.125);
    assert_true(meta.scene_diagonal == 12.5f);

    check_exrheader(path, compression_line);

    /* The memory writer produces exactly the bytes of the file writer. */
    assert_int_equal(mr_exr_write_memory(&mem, &mem_size, in, &opt, &k_meta, &err), MR_OK);
    file = read_all(path, &file_size);
    assert_int_equal(mem_size, file_size);
    assert_memory_equal(mem, file, file_size);
    if (c == MR_COMPRESSION_NONE) /* 4 half + 6 four-byte channels per pixel */
        assert_true(file_size > (size_t)PW * PH * 32u);

    free(mem);
    free(file);
    mr_film_free(in);
    mr_film_free(out);
}

static void test_roundtrip_none(void **state)
{
    roundtrip(state, MR_COMPRESSION_NONE, 0, "none.exr",
              "compression (type compression): none\n");
}

static void test_roundtrip_zip(void **state)
{
    roundtrip(state, MR_COMPRESSION_ZIP, 0, "zip.exr",
              "compression (type compression): zip, multi-scanline blocks\n");
}

static void test_roundtrip_zip_level9(void **state)
{
    roundtrip(state, MR_COMPRESSION_ZIP, 9, "zip9.exr",
              "compression (type compression): zip, multi-scanline blocks\n");
}

static void test_roundtrip_zips(void **state)
{
    roundtrip(state, MR_COMPRESSION_ZIPS, 1, "zips.exr",
              "compression (type compression): zip, individual scanlines\n");
}

static void test_roundtrip_piz(void **state)
{
    roundtrip(state, MR_COMPRESSION_PIZ, 0, "piz.exr",
              "compression (type compression): piz\n");
}

static void test_zip_level_changes_output(void **state)
{
    /* Levels below MR_ZIP_LEVEL_LIBDEFLATE are our one deflate: the same
     * bytes for each (and for 0, the default); from there on libdeflate's
     * levels, which must reach it: 6 and 9 give different streams, and
     * neither is ours. */
    mr_film *in = pattern_film();
    uint8_t *m[10] = {NULL};
    size_t sz[10] = {0};
    mr_error err = {0};
    (void)state;

    for (int level = 0; level <= 9; level++) {
        mr_exr_options o = {MR_COMPRESSION_ZIP, level, 0, false};
        assert_int_equal(mr_exr_write_memory(&m[level], &sz[level], in, &o, &k_meta, &err),
                         MR_OK);
    }
    for (int level = 1; level < MR_ZIP_LEVEL_LIBDEFLATE; level++) {
        assert_int_equal(sz[level], sz[0]);
        if (memcmp(m[level], m[0], sz[0]) != 0)
            fail_msg("zip level %d differs from the default", level);
    }
    assert_true(sz[6] != sz[9] || memcmp(m[6], m[9], sz[6]) != 0);
    assert_true(sz[6] != sz[0] || memcmp(m[6], m[0], sz[0]) != 0);
    for (int level = 0; level <= 9; level++)
        free(m[level]);
    mr_film_free(in);
}

static void test_meta_absent(void **state)
{
    char path[256], cmd[512], *out;
    mr_film *in = pattern_film(), *back = NULL;
    mr_exr_meta meta;
    mr_error err = {0};

    tmp_path(state, "nometa.exr", path, sizeof path);
    assert_int_equal(mr_exr_write_file(path, in, NULL, NULL, &err), MR_OK);
    memset(&meta, 0x5A, sizeof meta);
    assert_int_equal(mr_exr_read_file(path, &back, &meta, &err), MR_OK);
    assert_string_equal(meta.job, "");
    assert_int_equal(meta.frame, 0);
    assert_true(meta.time == 0.0 && meta.render_seconds == 0.0 && meta.scene_diagonal == 0.0f);
    check_same_film(in, back);
    mr_film_free(back);
    back = NULL;
    /* meta is optional for the reader too. */
    assert_int_equal(mr_exr_read_file(path, &back, NULL, &err), MR_OK);

    snprintf(cmd, sizeof cmd, "exrheader '%s' 2>&1", path);
    out = run_capture(cmd);
    assert_non_null(strstr(out, "microray.version (type string)"));
    assert_null(strstr(out, "microray.job"));
    assert_non_null(strstr(out, "compression (type compression): none\n"));
    free(out);
    mr_film_free(in);
    mr_film_free(back);
}

static void test_nonfinite_become_finite(void **state)
{
    char path[256];
    mr_film *in = NULL, *out = NULL;
    mr_exr_options opt = {MR_COMPRESSION_ZIP, 0, 0, false};
    mr_error err = {0};
    const float bad[4] = {NAN, INFINITY, -INFINITY, 1e30f};
    size_t i, n;
    (void)state;

    assert_int_equal(mr_film_new(4, 3, &in, &err), MR_OK);
    n = 12;
    for (i = 0; i < n; i++) {
        float v = bad[i % 4];
        in->r[i] = in->g[i] = in->b[i] = in->a[i] = v;
        in->z[i] = in->nx[i] = in->ny[i] = in->nz[i] = v;
    }
    tmp_path(state, "nonfinite.exr", path, sizeof path);
    assert_int_equal(mr_exr_write_file(path, in, &opt, NULL, &err), MR_OK);
    assert_int_equal(mr_exr_read_file(path, &out, NULL, &err), MR_OK);
    for (i = 0; i < n; i++) {
        const float *half_planes[4] = {out->r, out->g, out->b, out->a};
        const float *float_planes[4] = {out->z, out->nx, out->ny, out->nz};
        static const float want_half[4] = {0.0f, 65504.0f, -65504.0f, 65504.0f};
        static const float want_float[4] = {0.0f, FLT_MAX, -FLT_MAX, 1e30f};
        int k;
        for (k = 0; k < 4; k++) {
            assert_true(isfinite(half_planes[k][i]));
            assert_true(half_planes[k][i] == want_half[i % 4]);
            assert_true(isfinite(float_planes[k][i]));
            assert_true(float_planes[k][i] == want_float[i % 4]);
        }
    }
    mr_film_free(in);
    mr_film_free(out);
}

/* One row per chunk keeps the smallest image (1x1) and the largest chunk
 * count (NONE, 1 line per chunk) covered. */
static void test_tiny_and_tall(void **state)
{
    static const mr_compression cs[] = {MR_COMPRESSION_NONE, MR_COMPRESSION_ZIP,
                                        MR_COMPRESSION_ZIPS, MR_COMPRESSION_PIZ};
    static const int sizes[][2] = {{1, 1}, {1, 70}, {70, 1}};
    char path[256];
    mr_error err = {0};
    size_t s, c, i;

    tmp_path(state, "tiny.exr", path, sizeof path);
    for (s = 0; s < 3; s++) {
        for (c = 0; c < 4; c++) {
            mr_film *in = NULL, *out = NULL;
            mr_exr_options opt = {cs[c], 0, 0, false};
            size_t n = (size_t)sizes[s][0] * (size_t)sizes[s][1];
            assert_int_equal(mr_film_new(sizes[s][0], sizes[s][1], &in, &err), MR_OK);
            for (i = 0; i < n; i++) {
                in->r[i] = (float)i * 0.25f;
                in->z[i] = (float)i + 0.5f;
                in->prim_id[i] = (uint32_t)i * 65537u;
            }
            assert_int_equal(mr_exr_write_file(path, in, &opt, &k_meta, &err), MR_OK);
            assert_int_equal(mr_exr_read_file(path, &out, NULL, &err), MR_OK);
            check_same_film(in, out);
            mr_film_free(in);
            mr_film_free(out);
        }
    }
}

/* ------------------------------------------------------------------ */
/* foreign files                                                       */

static void quiet(exr_const_context_t c, exr_result_t code, const char *msg)
{
    (void)c;
    (void)code;
    (void)msg;
}

/* Writes, with the C API directly, a 3x2 image whose data window starts at
 * (10, 20) and that has only R (FLOAT), Z (HALF), id.object and an unknown
 * channel "foo": what a third-party tool might hand us. */
static void write_foreign(const char *path)
{
    exr_context_initializer_t init = EXR_DEFAULT_CONTEXT_INITIALIZER;
    exr_context_t ctxt = NULL;
    exr_encode_pipeline_t enc = EXR_ENCODE_PIPELINE_INITIALIZER;
    exr_attr_box2i_t win = {{{{10, 20}}}, {{{12, 21}}}};
    exr_attr_v2f_t center = {{{0.0f, 0.0f}}};
    float r[2][3] = {{1.5f, -2.0f, 3.25f}, {4.0f, 5.0f, 6.0f}};
    uint16_t z[2][3], foo[2][3];
    uint32_t ids[2][3] = {{100000u, 0u, 7u}, {8u, 9u, 4000000000u}};
    int part, y, c;

    for (y = 0; y < 2; y++)
        for (c = 0; c < 3; c++) {
            z[y][c] = mr_float_to_half(10.0f * (float)y + (float)c + 0.5f);
            foo[y][c] = mr_float_to_half(-1.0f);
        }
    init.error_handler_fn = quiet;
    assert_int_equal(exr_start_write(&ctxt, path, EXR_WRITE_FILE_DIRECTLY, &init), 0);
    assert_int_equal(exr_add_part(ctxt, NULL, EXR_STORAGE_SCANLINE, &part), 0);
    assert_int_equal(exr_initialize_required_attr(ctxt, part, &win, &win, 1.0f, &center,
                                                  1.0f, EXR_LINEORDER_INCREASING_Y,
                                                  EXR_COMPRESSION_NONE),
                     0);
    assert_int_equal(exr_add_channel(ctxt, part, "R", EXR_PIXEL_FLOAT, 0, 1, 1), 0);
    assert_int_equal(exr_add_channel(ctxt, part, "Z", EXR_PIXEL_HALF, 0, 1, 1), 0);
    assert_int_equal(exr_add_channel(ctxt, part, "foo", EXR_PIXEL_HALF, 0, 1, 1), 0);
    assert_int_equal(exr_add_channel(ctxt, part, "id.object", EXR_PIXEL_UINT, 0, 1, 1), 0);
    assert_int_equal(exr_write_header(ctxt), 0);
    for (y = 0; y < 2; y++) {
        exr_chunk_info_t ci;
        assert_int_equal(exr_write_scanline_chunk_info(ctxt, part, 20 + y, &ci), 0);
        if (y == 0)
            assert_int_equal(exr_encoding_initialize(ctxt, part, &ci, &enc), 0);
        else
            assert_int_equal(exr_encoding_update(ctxt, part, &ci, &enc), 0);
        for (c = 0; c < enc.channel_count; c++) {
            exr_coding_channel_info_t *ch = &enc.channels[c];
            const char *nm = ch->channel_name;
            int bpe = ch->bytes_per_element;
            if (!strcmp(nm, "R"))
                ch->encode_from_ptr = (const uint8_t *)r[y];
            else if (!strcmp(nm, "Z"))
                ch->encode_from_ptr = (const uint8_t *)z[y];
            else if (!strcmp(nm, "foo"))
                ch->encode_from_ptr = (const uint8_t *)foo[y];
            else
                ch->encode_from_ptr = (const uint8_t *)ids[y];
            ch->user_data_type = ch->data_type;
            ch->user_bytes_per_element = (int16_t)bpe;
            ch->user_pixel_stride = bpe;
            ch->user_line_stride = bpe * 3;
        }
        if (y == 0)
            assert_int_equal(exr_encoding_choose_default_routines(ctxt, part, &enc), 0);
        assert_int_equal(exr_encoding_run(ctxt, part, &enc), 0);
    }
    assert_int_equal(exr_encoding_destroy(ctxt, &enc), 0);
    assert_int_equal(exr_finish(&ctxt), 0);
}

static void test_foreign_channels_by_name(void **state)
{
    char path[256];
    mr_film *f = NULL;
    mr_exr_meta meta;
    mr_error err = {0};
    int x, y;

    tmp_path(state, "foreign.exr", path, sizeof path);
    write_foreign(path);
    memset(&meta, 0x11, sizeof meta);
    assert_int_equal(mr_exr_read_file(path, &f, &meta, &err), MR_OK);
    assert_int_equal(f->width, 3);
    assert_int_equal(f->height, 2);
    /* No microray attributes: meta is all zero. */
    assert_string_equal(meta.job, "");
    assert_int_equal(meta.frame, 0);
    assert_true(f->r[0] == 1.5f && f->r[1] == -2.0f && f->r[2] == 3.25f);
    assert_true(f->r[3] == 4.0f && f->r[5] == 6.0f);
    for (y = 0; y < 2; y++)
        for (x = 0; x < 3; x++) {
            size_t i = (size_t)y * 3 + (size_t)x;
            /* HALF Z converted to float; these values are exact in half. */
            assert_true(f->z[i] == 10.0f * (float)y + (float)x + 0.5f);
            /* Absent channels stay zero; "foo" went nowhere. */
            assert_true(f->g[i] == 0.0f && f->b[i] == 0.0f && f->a[i] == 0.0f);
            assert_true(f->nx[i] == 0.0f && f->ny[i] == 0.0f && f->nz[i] == 0.0f);
            assert_int_equal(f->prim_id[i], 0);
        }
    assert_int_equal(f->object_id[0], 100000u);
    assert_int_equal(f->object_id[5], 4000000000u);
    mr_film_free(f);
}

/* ------------------------------------------------------------------ */
/* parallel encoding                                                   */

enum { BW = 1024, BH = 520 };

/* Big enough that every compression takes several encoding batches at 1
 * and 2 threads (a batch is 8 MB of raw chunk data but at least 8 chunks
 * per thread: 256 rows of this width for NONE and ZIPS, 16 chunks of 16 rows
 * for ZIP, 8 or 16 chunks of 32 rows for PIZ), with a short last chunk (520
 * is no multiple of 16 or 32), noise so the
 * compressors have work to do, and special values in every float plane:
 * NaN, +-Inf, out-of-range colour, half ties, half subnormals, float
 * denormals and -0. They land at varying positions within 8-sample groups,
 * which covers both the vector and the scalar conversion paths. */
static mr_film *big_film(void)
{
    static const uint32_t special_bits[] = {
        0x7fc00000u, 0xffc00001u, 0x7f800000u, 0xff800000u, /* NaN, -NaN, +-Inf */
        0x7149f2cau, 0xf149f2cau,                           /* +-1e30 */
        0x477ff000u, 0x477fefffu,                           /* 65520, just below */
        0x3f801000u, 0x3f803000u,                           /* half ties 1+2^-11, 1+3*2^-11 */
        0x33800000u, 0x33000000u, 0x33000001u,              /* 2^-24, 2^-25, above it */
        0x387fc000u,                                        /* subnormal -> min normal */
        0x00000001u, 0x80400000u,                           /* float denormals */
        0x80000000u, 0x7f7fffffu,                           /* -0, FLT_MAX */
    };
    const size_t nspecial = sizeof special_bits / sizeof special_bits[0];
    mr_film *f = NULL;
    mr_error err = {0};
    uint32_t lcg = 99u;
    size_t i, n = (size_t)BW * BH;

    assert_int_equal(mr_film_new(BW, BH, &f, &err), MR_OK);
    for (i = 0; i < n; i++) {
        int x = (int)(i % BW), y = (int)(i / BW);
        float noise;
        lcg = lcg * 1664525u + 1013904223u;
        noise = (float)(lcg >> 16) / 65536.0f * 0.05f;
        f->r[i] = 0.5f + 0.4f * sinf((float)x * 0.01f) + noise;
        f->g[i] = (float)y / BH + noise;
        f->b[i] = ldexpf(noise, -(int)(x % 30)); /* down into half subnormals */
        f->a[i] = x < BW / 4 ? 0.0f : 1.0f;
        f->z[i] = x < BW / 4 ? 0.0f : 5.0f + (float)y * 0.01f + noise;
        f->nx[i] = cosf((float)x * 0.003f);
        f->ny[i] = sinf((float)x * 0.003f);
        f->nz[i] = -noise;
        f->object_id[i] = x < BW / 4 ? 0u : 1u + (uint32_t)(x / 500);
        f->prim_id[i] = (uint32_t)(x / 5 + (y / 5) * 1000) | (lcg & 0x80000000u);
        if (i % 97 == 0) {
            float *planes[8] = {f->r, f->g, f->b, f->a, f->z, f->nx, f->ny, f->nz};
            uint32_t bits = special_bits[(i / 97) % nspecial];
            memcpy(&planes[(i / 97) % 8][i], &bits, sizeof bits);
        }
    }
    return f;
}

/* What the writer documents for FLOAT planes: NaN -> 0, +-Inf -> +-FLT_MAX,
 * everything else bit for bit. */
static float expect_float(float v)
{
    if (isnan(v))
        return 0.0f;
    if (v > FLT_MAX)
        return FLT_MAX;
    if (v < -FLT_MAX)
        return -FLT_MAX;
    return v;
}

/* Read-back check for films with special values: exact bits, against the
 * documented conversions (check_same_film assumes finite input). */
static void check_encoded_film(const mr_film *in, const mr_film *out)
{
    const float *fin[8] = {in->r, in->g, in->b, in->a, in->z, in->nx, in->ny, in->nz};
    const float *fout[8] = {out->r, out->g, out->b, out->a, out->z, out->nx, out->ny, out->nz};
    size_t i, k, n = (size_t)in->width * (size_t)in->height;

    assert_int_equal(out->width, in->width);
    assert_int_equal(out->height, in->height);
    for (i = 0; i < n; i++) {
        for (k = 0; k < 8; k++) {
            float want = k < 4 ? mr_half_to_float(mr_float_to_half(fin[k][i]))
                               : expect_float(fin[k][i]);
            if (memcmp(&fout[k][i], &want, sizeof want) != 0)
                fail_msg("pixel %zu plane %zu: got %a, want %a", i, k, (double)fout[k][i],
                         (double)want);
        }
        assert_int_equal(out->object_id[i], in->object_id[i]);
        assert_int_equal(out->prim_id[i], in->prim_id[i]);
    }
}

typedef struct membuf {
    uint8_t *data;
    size_t size, cap;
} membuf;

static int64_t membuf_write(exr_const_context_t ctxt, void *user, const void *buf, uint64_t sz,
                            uint64_t offset, exr_stream_error_func_ptr_t error_cb)
{
    membuf *m = user;
    size_t end = (size_t)(offset + sz);
    (void)ctxt;
    (void)error_cb;
    if (end > m->cap) {
        size_t ncap = m->cap ? m->cap : 65536;
        while (ncap < end)
            ncap *= 2;
        m->data = realloc(m->data, ncap);
        assert_non_null(m->data);
        m->cap = ncap;
    }
    if ((size_t)offset > m->size)
        memset(m->data + m->size, 0, (size_t)offset - m->size);
    memcpy(m->data + offset, buf, (size_t)sz);
    if (end > m->size)
        m->size = end;
    return (int64_t)sz;
}

/* The frame as the plain single-threaded library pipeline writes it, which
 * is what mr_exr_write_* produced before encoding went parallel: the same
 * header calls in the same order, colour staged with mr_float_to_half, Z/N
 * sanitised, then the library's own packer and compressor, one chunk after
 * the other through one pipeline. Byte equality with this pins our packer
 * (vector paths included) to the library's layout. */
static uint8_t *reference_write(const mr_film *f, mr_compression c, int level,
                                const mr_exr_meta *meta, size_t *size)
{
    static const struct {
        const char *name;
        exr_pixel_type_t type;
    } chans[10] = {
        {"R", EXR_PIXEL_HALF},         {"G", EXR_PIXEL_HALF},  {"B", EXR_PIXEL_HALF},
        {"A", EXR_PIXEL_HALF},         {"Z", EXR_PIXEL_FLOAT}, {"N.X", EXR_PIXEL_FLOAT},
        {"N.Y", EXR_PIXEL_FLOAT},      {"N.Z", EXR_PIXEL_FLOAT},
        {"id.object", EXR_PIXEL_UINT}, {"id.primitive", EXR_PIXEL_UINT},
    };
    const float *fplanes[8] = {f->r, f->g, f->b, f->a, f->z, f->nx, f->ny, f->nz};
    const exr_compression_t ctypes[4] = {EXR_COMPRESSION_NONE, EXR_COMPRESSION_ZIP,
                                         EXR_COMPRESSION_ZIPS, EXR_COMPRESSION_PIZ};
    exr_context_initializer_t init = EXR_DEFAULT_CONTEXT_INITIALIZER;
    exr_context_t ctxt = NULL;
    exr_encode_pipeline_t enc = EXR_ENCODE_PIPELINE_INITIALIZER;
    membuf m = {NULL, 0, 0};
    size_t w = (size_t)f->width, n = w * (size_t)f->height, i;
    uint8_t *staged[10];
    int part = 0, lines = 0, y, c2, k;

    /* Whole planes in file types; the UINT planes are used as they are. */
    for (k = 0; k < 8; k++) {
        staged[k] = malloc(n * 4);
        assert_non_null(staged[k]);
        for (i = 0; i < n; i++) {
            if (k < 4) {
                uint16_t h = mr_float_to_half(fplanes[k][i]);
                memcpy(staged[k] + 2 * i, &h, 2);
            } else {
                float v = expect_float(fplanes[k][i]);
                memcpy(staged[k] + 4 * i, &v, 4);
            }
        }
    }
    staged[8] = (uint8_t *)f->object_id;
    staged[9] = (uint8_t *)f->prim_id;

    init.error_handler_fn = quiet;
    init.user_data = &m;
    init.write_fn = membuf_write;
    assert_int_equal(exr_start_write(&ctxt, "<reference>", EXR_WRITE_FILE_DIRECTLY, &init), 0);
    assert_int_equal(exr_add_part(ctxt, NULL, EXR_STORAGE_SCANLINE, &part), 0);
    assert_int_equal(exr_initialize_required_attr_simple(ctxt, part, f->width, f->height,
                                                         ctypes[c]),
                     0);
    for (k = 0; k < 10; k++)
        assert_int_equal(exr_add_channel(ctxt, part, chans[k].name, chans[k].type,
                                         EXR_PERCEPTUALLY_LOGARITHMIC, 1, 1),
                         0);
    if (c == MR_COMPRESSION_ZIP || c == MR_COMPRESSION_ZIPS)
        assert_int_equal(exr_set_zip_compression_level(ctxt, part,
                                                       level ? level : MR_ZIP_LEVEL_DEFAULT),
                         0);
    assert_int_equal(exr_attr_set_string(ctxt, part, "microray.version", MR_VERSION_STRING), 0);
    {
        /* the standard attributes a film without a camera and k_meta get */
        const exr_attr_chromaticities_t rec709 = {0.64f, 0.33f, 0.30f, 0.60f,
                                                  0.15f, 0.06f, 0.3127f, 0.3290f};
        char comments[256];
        snprintf(comments, sizeof comments,
                 "Rendered by microray %s: job %s, frame %d at %.6g s on the job's timeline",
                 MR_VERSION_STRING, meta->job, meta->frame, meta->time);
        assert_int_equal(exr_attr_set_chromaticities(ctxt, part, "chromaticities", &rec709), 0);
        assert_int_equal(exr_attr_set_string(ctxt, part, "microray.job", meta->job), 0);
        assert_int_equal(exr_attr_set_int(ctxt, part, "microray.frame", meta->frame), 0);
        assert_int_equal(exr_attr_set_double(ctxt, part, "microray.time", meta->time), 0);
        assert_int_equal(
            exr_attr_set_double(ctxt, part, "microray.renderSeconds", meta->render_seconds), 0);
        assert_int_equal(
            exr_attr_set_float(ctxt, part, "microray.sceneDiagonal", meta->scene_diagonal), 0);
        assert_int_equal(exr_attr_set_string(ctxt, part, "comments", comments), 0);
    }
    assert_int_equal(exr_write_header(ctxt), 0);
    assert_int_equal(exr_get_scanlines_per_chunk(ctxt, part, &lines), 0);

    for (y = 0; y < f->height; y += lines) {
        exr_chunk_info_t ci;
        assert_int_equal(exr_write_scanline_chunk_info(ctxt, part, y, &ci), 0);
        if (y == 0)
            assert_int_equal(exr_encoding_initialize(ctxt, part, &ci, &enc), 0);
        else
            assert_int_equal(exr_encoding_update(ctxt, part, &ci, &enc), 0);
        for (c2 = 0; c2 < enc.channel_count; c2++) {
            exr_coding_channel_info_t *ch = &enc.channels[c2];
            int bpe = ch->bytes_per_element;
            for (k = 0; k < 10 && strcmp(chans[k].name, ch->channel_name) != 0; k++)
                ;
            assert_true(k < 10);
            ch->encode_from_ptr = staged[k] + (size_t)y * w * (size_t)bpe;
            ch->user_data_type = ch->data_type;
            ch->user_bytes_per_element = (int16_t)bpe;
            ch->user_pixel_stride = bpe;
            ch->user_line_stride = bpe * f->width;
        }
        if (y == 0)
            assert_int_equal(exr_encoding_choose_default_routines(ctxt, part, &enc), 0);
        assert_int_equal(exr_encoding_run(ctxt, part, &enc), 0);
    }
    assert_int_equal(exr_encoding_destroy(ctxt, &enc), 0);
    assert_int_equal(exr_finish(&ctxt), 0);
    for (k = 0; k < 8; k++)
        free(staged[k]);
    *size = m.size;
    return m.data;
}

/* ------------------------------------------------------------------ */
/* decoding chunks with the library                                    */

typedef struct memsrc {
    const uint8_t *data;
    size_t size;
} memsrc;

static int64_t memsrc_read(exr_const_context_t ctxt, void *user, void *buf, uint64_t sz,
                           uint64_t offset, exr_stream_error_func_ptr_t error_cb)
{
    const memsrc *m = user;
    (void)ctxt;
    (void)error_cb;
    if (offset >= m->size)
        return 0;
    if (sz > m->size - offset)
        sz = m->size - offset;
    memcpy(buf, m->data + offset, (size_t)sz);
    return (int64_t)sz;
}

static int64_t memsrc_size(exr_const_context_t ctxt, void *user)
{
    (void)ctxt;
    return (int64_t)((const memsrc *)user)->size;
}

typedef struct raw_sink {
    uint8_t *data;
    size_t size, cap;
} raw_sink;

/* Stands in for the library's unpacker: keeps the chunk exactly as the
 * library's decompressor left it (the packed scanline layout). */
static exr_result_t keep_unpacked(exr_decode_pipeline_t *d)
{
    raw_sink *r = d->decoding_user_data;
    size_t n = (size_t)d->chunk.unpacked_size;
    if (r->size + n > r->cap) {
        r->cap = (r->size + n) * 2;
        r->data = realloc(r->data, r->cap);
        assert_non_null(r->data);
    }
    memcpy(r->data + r->size, d->unpacked_buffer, n);
    r->size += n;
    return EXR_ERR_SUCCESS;
}

/* Every chunk of an EXR in memory, decompressed by OpenEXRCore's own
 * decoder (zlib inflate + the ZIP predictor and byte order for ZIP/ZIPS,
 * its wavelet and Huffman decoder for PIZ), concatenated in file order:
 * the packed scanline bytes (per scanline, channels in file order), which
 * do not depend on the codec or on how many scanlines a chunk holds. */
static uint8_t *decoded_chunk_bytes(const uint8_t *file, size_t size, size_t *out_size)
{
    exr_context_initializer_t init = EXR_DEFAULT_CONTEXT_INITIALIZER;
    exr_context_t ctxt = NULL;
    exr_decode_pipeline_t dec = EXR_DECODE_PIPELINE_INITIALIZER;
    memsrc src = {file, size};
    raw_sink sink = {NULL, 0, 0};
    exr_attr_box2i_t dw;
    int lines = 0, y;
    bool ready = false;

    init.error_handler_fn = quiet;
    init.user_data = &src;
    init.read_fn = memsrc_read;
    init.size_fn = memsrc_size;
    init.flags = EXR_CONTEXT_FLAG_DISABLE_CHUNK_RECONSTRUCTION;
    assert_int_equal(exr_start_read(&ctxt, "<memory>", &init), 0);
    assert_int_equal(exr_get_data_window(ctxt, 0, &dw), 0);
    assert_int_equal(exr_get_scanlines_per_chunk(ctxt, 0, &lines), 0);
    for (y = dw.min.y; y <= dw.max.y; y += lines) {
        exr_chunk_info_t ci;
        assert_int_equal(exr_read_scanline_chunk_info(ctxt, 0, y, &ci), 0);
        if (!ready) {
            assert_int_equal(exr_decoding_initialize(ctxt, 0, &ci, &dec), 0);
            /* No destinations: the library then reads and decompresses
             * every chunk into its own buffer (with all of them set, an
             * uncompressed file is read straight into the destinations,
             * past any unpacker), and keep_unpacked takes it from there. */
            for (int c = 0; c < dec.channel_count; c++)
                dec.channels[c].decode_to_ptr = NULL;
            assert_int_equal(exr_decoding_choose_default_routines(ctxt, 0, &dec), 0);
            dec.unpack_and_convert_fn = keep_unpacked;
            dec.decoding_user_data = &sink;
            ready = true;
        } else {
            assert_int_equal(exr_decoding_update(ctxt, 0, &ci, &dec), 0);
        }
        assert_int_equal(exr_decoding_run(ctxt, 0, &dec), 0);
    }
    assert_int_equal(exr_decoding_destroy(ctxt, &dec), 0);
    assert_int_equal(exr_finish(&ctxt), 0);
    *out_size = sink.size;
    return sink.data;
}

/* Files a and b hold byte-identical pixel data once OpenEXR decodes them. */
static void assert_chunks_decode_alike(const uint8_t *a, size_t a_size, const uint8_t *b,
                                       size_t b_size, const char *what)
{
    size_t na = 0, nb = 0, i;
    uint8_t *da = decoded_chunk_bytes(a, a_size, &na);
    uint8_t *db = decoded_chunk_bytes(b, b_size, &nb);
    assert_int_equal(na, nb);
    for (i = 0; i < na && da[i] == db[i]; i++)
        ;
    if (i < na)
        fail_msg("%s: decoded chunk byte %zu of %zu is %u, expected %u", what, i, na, da[i], db[i]);
    free(da);
    free(db);
}

/* Encoding runs on several threads, but the bytes must not depend on how
 * many: 1, 2, 3, all cores (0) and far more threads than cores or chunks
 * (clamped) all give the same bytes, from memory and from a file. NONE and
 * PIZ give the bytes of the library's own pipeline; ZIP and ZIPS, which we
 * deflate ourselves, decode to the same bytes as the library's. */
static void test_parallel_identical(void **state)
{
    static const struct {
        mr_compression c;
        int level;
        const char *line;
    } cases[] = {
        {MR_COMPRESSION_NONE, 0, "compression (type compression): none\n"},
        {MR_COMPRESSION_ZIP, 0, "compression (type compression): zip, multi-scanline blocks\n"},
        {MR_COMPRESSION_ZIP, MR_ZIP_LEVEL_LIBDEFLATE,
         "compression (type compression): zip, multi-scanline blocks\n"},
        {MR_COMPRESSION_ZIPS, 1, "compression (type compression): zip, individual scanlines\n"},
        {MR_COMPRESSION_PIZ, 0, "compression (type compression): piz\n"},
    };
    static const unsigned threads[] = {2, 3, 0, 1000};
    mr_film *in = big_film();
    size_t ci, ti;

    for (ci = 0; ci < sizeof cases / sizeof cases[0]; ci++) {
        mr_exr_options opt = {cases[ci].c, cases[ci].level, 1, false};
        mr_error err = {0};
        uint8_t *ref, *one = NULL, *file;
        size_t ref_size = 0, one_size = 0, file_size = 0;
        char name[32], path[256], cmd[512], *out;
        mr_film *back = NULL;

        ref = reference_write(in, cases[ci].c, cases[ci].level, &k_meta, &ref_size);
        assert_int_equal(mr_exr_write_memory(&one, &one_size, in, &opt, &k_meta, &err), MR_OK);
        if (cases[ci].c == MR_COMPRESSION_ZIP || cases[ci].c == MR_COMPRESSION_ZIPS) {
            /* Our own deflate: other compressed bytes, the same pixels. */
            assert_chunks_decode_alike(one, one_size, ref, ref_size,
                                       mr_compression_name(cases[ci].c));
        } else {
            assert_int_equal(one_size, ref_size);
            if (memcmp(one, ref, ref_size) != 0)
                fail_msg("%s: 1-thread output differs from the library pipeline's",
                         mr_compression_name(cases[ci].c));
        }

        for (ti = 0; ti < sizeof threads / sizeof threads[0]; ti++) {
            uint8_t *many = NULL;
            size_t many_size = 0;
            opt.threads = threads[ti];
            assert_int_equal(mr_exr_write_memory(&many, &many_size, in, &opt, &k_meta, &err),
                             MR_OK);
            assert_int_equal(many_size, one_size);
            if (memcmp(many, one, one_size) != 0)
                fail_msg("%s: %u threads differ from 1 thread", mr_compression_name(cases[ci].c),
                         threads[ti]);
            free(many);
        }

        /* The file writer, multi-threaded, too; and the result is a real EXR
         * to the C++ library and to our reader. */
        snprintf(name, sizeof name, "par_%s.exr", mr_compression_name(cases[ci].c));
        tmp_path(state, name, path, sizeof path);
        opt.threads = 2;
        assert_int_equal(mr_exr_write_file(path, in, &opt, &k_meta, &err), MR_OK);
        file = read_all(path, &file_size);
        assert_int_equal(file_size, one_size);
        assert_memory_equal(file, one, one_size);

        snprintf(cmd, sizeof cmd, "exrheader '%s' 2>&1", path);
        out = run_capture(cmd);
        if (!strstr(out, cases[ci].line) ||
            !strstr(out, "dataWindow (type box2i): (0 0) - (1023 519)\n") ||
            !strstr(out, "id.primitive, 32-bit unsigned integer, sampling 1 1\n"))
            fail_msg("exrheader output for %s:\n%s", path, out);
        free(out);

        assert_int_equal(mr_exr_read_file(path, &back, NULL, &err), MR_OK);
        check_encoded_film(in, back);

        mr_film_free(back);
        free(file);
        free(one);
        free(ref);
    }
    mr_film_free(in);
}

/* The predictor as OpenEXR's ZIP encoder states it, in two steps: split
 * into even and odd bytes, then replace each byte after the first by its
 * difference to the previous one plus 128. */
static void zip_predict_reference(const uint8_t *in, size_t n, uint8_t *out)
{
    size_t h = (n + 1) / 2, i;
    uint8_t prev;
    for (i = 0; i < n; i++)
        out[i % 2 ? h + i / 2 : i / 2] = in[i];
    if (n == 0)
        return;
    prev = out[0];
    for (i = 1; i < n; i++) {
        uint8_t cur = out[i];
        out[i] = (uint8_t)(cur - prev + 128u);
        prev = cur;
    }
}

/* The vector predictor against the stated definition, for every length
 * up to 300 (every tail and the block edges of the 32-byte loop) and a
 * long odd length, on random bytes and on runs. */
static void test_zip_predict_matches_definition(void **state)
{
    enum { LONG = 100003 };
    uint8_t *in = malloc(LONG), *want = malloc(LONG), *got = malloc(LONG + 1);
    uint32_t lcg = 7u;
    size_t n, i;
    (void)state;
    assert_true(in && want && got);
    for (i = 0; i < LONG; i++) {
        lcg = lcg * 1664525u + 1013904223u;
        in[i] = i % 1000 < 600 ? (uint8_t)(lcg >> 24) : (uint8_t)(i / 1000);
    }
    for (n = 0; n <= LONG; n = n < 300 ? n + 1 : LONG) {
        zip_predict_reference(in, n, want);
        got[n] = 0x5A; /* guard byte */
        mr_exr_zip_predict(in, n, got);
        if (n && memcmp(got, want, n) != 0) {
            for (i = 0; got[i] == want[i]; i++)
                ;
            fail_msg("length %zu: byte %zu is %u, expected %u", n, i, got[i], want[i]);
        }
        assert_int_equal(got[n], 0x5A); /* nothing written past n */
        if (n == LONG)
            break;
    }
    free(in);
    free(want);
    free(got);
}

/* A film of the given passes (Cryptomatte with 4 ranks) with varied
 * values (and ids) in every plane, of any size. */
static mr_film *varied_film(int w, int h, uint32_t seed, unsigned aovs)
{
    mr_film *f = NULL;
    mr_error err = {0};
    size_t i, n = (size_t)w * (size_t)h;
    assert_int_equal(mr_film_new_aovs(w, h, aovs, 4, &f, &err), MR_OK);
    for (i = 0; i < n; i++) {
        seed = seed * 1664525u + 1013904223u;
        float u = (float)(seed >> 8) / 16777216.0f;
        if (f->r) {
            f->r[i] = u;
            f->g[i] = 1.0f - u;
            f->b[i] = (float)(i % 7);
            f->a[i] = i % 3 ? 1.0f : 0.0f;
        }
        if (f->z)
            f->z[i] = 2.0f + u;
        if (f->nx) {
            f->nx[i] = u - 0.5f;
            f->ny[i] = 0.25f;
            f->nz[i] = -u;
        }
        if (f->px) {
            f->px[i] = 100.0f * u;
            f->py[i] = -3.0f;
            f->pz[i] = (float)i;
        }
        if (f->tx) {
            f->tx[i] = 0.5f - u;
            f->ty[i] = -0.125f * (float)(i % 5);
            f->tz[i] = u * u;
        }
        if (f->object_id) {
            f->object_id[i] = seed >> 30;
            f->prim_id[i] = seed;
        }
        for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
            for (int k = 0; k < 2 * f->crypto_ranks; k++)
                f->crypto[l][k][i] = k % 2 ? u / (float)(k + 1) : (float)(seed >> (k + l));
    }
    return f;
}

/* The frame's channels as this test states them (the writer has its own
 * table): names, file types and the planes behind them. */
typedef struct ref_chan {
    char name[32];
    exr_pixel_type_t type;
    const void *plane; /* float, or uint32 for UINT */
} ref_chan;

static int ref_channels(const mr_film *f, bool half_normals, ref_chan ch[64])
{
    int n = 0;
#define ADD(nm, t, p) (snprintf(ch[n].name, sizeof ch[n].name, "%s", nm), ch[n].type = (t), ch[n++].plane = (p))
    if (f->aovs & MR_AOV_RGBA) {
        ADD("R", EXR_PIXEL_HALF, f->r);
        ADD("G", EXR_PIXEL_HALF, f->g);
        ADD("B", EXR_PIXEL_HALF, f->b);
        ADD("A", EXR_PIXEL_HALF, f->a);
    }
    if (f->aovs & MR_AOV_Z)
        ADD("Z", EXR_PIXEL_FLOAT, f->z);
    if (f->aovs & MR_AOV_N) {
        ADD("N.X", half_normals ? EXR_PIXEL_HALF : EXR_PIXEL_FLOAT, f->nx);
        ADD("N.Y", half_normals ? EXR_PIXEL_HALF : EXR_PIXEL_FLOAT, f->ny);
        ADD("N.Z", half_normals ? EXR_PIXEL_HALF : EXR_PIXEL_FLOAT, f->nz);
    }
    if (f->aovs & MR_AOV_P) {
        ADD("P.X", EXR_PIXEL_FLOAT, f->px);
        ADD("P.Y", EXR_PIXEL_FLOAT, f->py);
        ADD("P.Z", EXR_PIXEL_FLOAT, f->pz);
    }
    if (f->aovs & MR_AOV_T) {
        ADD("T.X", EXR_PIXEL_FLOAT, f->tx);
        ADD("T.Y", EXR_PIXEL_FLOAT, f->ty);
        ADD("T.Z", EXR_PIXEL_FLOAT, f->tz);
    }
    if (f->aovs & MR_AOV_ID) {
        ADD("id.object", EXR_PIXEL_UINT, f->object_id);
        ADD("id.primitive", EXR_PIXEL_UINT, f->prim_id);
    }
    for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
        for (int k = 0; k < 2 * f->crypto_ranks; k++) {
            char name[32];
            snprintf(name, sizeof name, "%s%02d.%c", l ? "CryptoAsset" : "CryptoObject", k / 4,
                     "RGBA"[k % 4]);
            ADD(name, EXR_PIXEL_FLOAT, f->crypto[l][k]);
        }
#undef ADD
    return n;
}

/* An uncompressed file of the film's passes written by the library's own
 * pipeline (its packer), from planes staged in file types with our
 * documented conversions: the packed bytes every codec must decode to. */
static uint8_t *reference_write_passes(const mr_film *f, bool half_normals, size_t *size)
{
    ref_chan ch[64];
    int nch = ref_channels(f, half_normals, ch), part = 0, y, c, k;
    size_t w = (size_t)f->width, n = w * (size_t)f->height, i;
    uint8_t *staged[64];
    exr_context_initializer_t init = EXR_DEFAULT_CONTEXT_INITIALIZER;
    exr_context_t ctxt = NULL;
    exr_encode_pipeline_t enc = EXR_ENCODE_PIPELINE_INITIALIZER;
    membuf m = {NULL, 0, 0};

    for (k = 0; k < nch; k++) {
        staged[k] = malloc(n * 4);
        assert_non_null(staged[k]);
        for (i = 0; i < n; i++) {
            if (ch[k].type == EXR_PIXEL_HALF) {
                uint16_t h = mr_float_to_half(((const float *)ch[k].plane)[i]);
                memcpy(staged[k] + 2 * i, &h, 2);
            } else if (ch[k].type == EXR_PIXEL_FLOAT) {
                float v = expect_float(((const float *)ch[k].plane)[i]);
                memcpy(staged[k] + 4 * i, &v, 4);
            } else {
                memcpy(staged[k] + 4 * i, (const uint32_t *)ch[k].plane + i, 4);
            }
        }
    }
    init.error_handler_fn = quiet;
    init.user_data = &m;
    init.write_fn = membuf_write;
    assert_int_equal(exr_start_write(&ctxt, "<reference>", EXR_WRITE_FILE_DIRECTLY, &init), 0);
    assert_int_equal(exr_add_part(ctxt, NULL, EXR_STORAGE_SCANLINE, &part), 0);
    assert_int_equal(exr_initialize_required_attr_simple(ctxt, part, f->width, f->height,
                                                         EXR_COMPRESSION_NONE),
                     0);
    for (k = 0; k < nch; k++)
        assert_int_equal(exr_add_channel(ctxt, part, ch[k].name, ch[k].type,
                                         EXR_PERCEPTUALLY_LOGARITHMIC, 1, 1),
                         0);
    assert_int_equal(exr_write_header(ctxt), 0);
    for (y = 0; y < f->height; y++) {
        exr_chunk_info_t ci;
        assert_int_equal(exr_write_scanline_chunk_info(ctxt, part, y, &ci), 0);
        if (y == 0)
            assert_int_equal(exr_encoding_initialize(ctxt, part, &ci, &enc), 0);
        else
            assert_int_equal(exr_encoding_update(ctxt, part, &ci, &enc), 0);
        for (c = 0; c < enc.channel_count; c++) {
            exr_coding_channel_info_t *cc = &enc.channels[c];
            int bpe = cc->bytes_per_element;
            for (k = 0; k < nch && strcmp(ch[k].name, cc->channel_name) != 0; k++)
                ;
            assert_true(k < nch);
            cc->encode_from_ptr = staged[k] + (size_t)y * w * (size_t)bpe;
            cc->user_data_type = cc->data_type;
            cc->user_bytes_per_element = (int16_t)bpe;
            cc->user_pixel_stride = bpe;
            cc->user_line_stride = bpe * f->width;
        }
        if (y == 0)
            assert_int_equal(exr_encoding_choose_default_routines(ctxt, part, &enc), 0);
        assert_int_equal(exr_encoding_run(ctxt, part, &enc), 0);
    }
    assert_int_equal(exr_encoding_destroy(ctxt, &enc), 0);
    assert_int_equal(exr_finish(&ctxt), 0);
    for (k = 0; k < nch; k++)
        free(staged[k]);
    *size = m.size;
    return m.data;
}

/* The chunks we compress ourselves decode, with OpenEXR's own decoder, to
 * exactly the bytes the library packs, for every codec at odd sizes: one
 * pixel (a chunk too small to shrink: stored packed), one column of 17 rows
 * (a 16-row ZIP chunk and a 1-row one), 4097x3 (a chunk wider than any
 * vector block, shorter than a ZIP chunk), and a frame of background with
 * one band of detail (chunks that repeat the previous one reuse its bytes,
 * across the band and with a short last chunk). OpenEXR's C++ library
 * (exrmultiview reads every channel of every chunk) reads them too. */
static void test_self_compressed_chunks_decode(void **state)
{
    /* ZIP and ZIPS with our deflate (level 0: the default) and libdeflate's. */
    static const struct {
        mr_compression c;
        int level;
    } cs[] = {{MR_COMPRESSION_NONE, 0}, {MR_COMPRESSION_ZIP, 0},
              {MR_COMPRESSION_ZIP, MR_ZIP_LEVEL_LIBDEFLATE}, {MR_COMPRESSION_ZIPS, 0},
              {MR_COMPRESSION_ZIPS, 9}, {MR_COMPRESSION_PIZ, 0}};
    static const int sizes[][2] = {{1, 1}, {1, 17}, {4097, 3}, {64, 70}};
    size_t s, c;

    for (s = 0; s < sizeof sizes / sizeof sizes[0]; s++) {
        int w = sizes[s][0], h = sizes[s][1];
        mr_film *in = varied_film(w, h, 11u + (uint32_t)s, MR_AOV_DEFAULT);
        if (w == 64) {
            /* background but for rows 20..29 */
            for (size_t i = 0; i < (size_t)w * (size_t)h; i++) {
                int y = (int)(i / (size_t)w);
                if (y < 20 || y >= 30) {
                    in->r[i] = in->g[i] = in->b[i] = 0.25f;
                    in->a[i] = 1.0f;
                    in->z[i] = MR_DEPTH_MISS;
                    in->nx[i] = in->ny[i] = in->nz[i] = 0.0f;
                    in->object_id[i] = in->prim_id[i] = 0;
                }
            }
        }
        for (c = 0; c < sizeof cs / sizeof cs[0]; c++) {
            mr_exr_options opt = {cs[c].c, cs[c].level, 2, false};
            mr_error err = {0};
            uint8_t *ours = NULL, *ref;
            size_t ours_size = 0, ref_size = 0;
            char what[64], path[256], view[256], cmd[1024], *out;
            mr_film *back = NULL;

            snprintf(what, sizeof what, "%s level %d %dx%d", mr_compression_name(cs[c].c),
                     cs[c].level, w, h);
            assert_int_equal(mr_exr_write_memory(&ours, &ours_size, in, &opt, &k_meta, &err),
                             MR_OK);
            ref = reference_write(in, MR_COMPRESSION_NONE, 0, &k_meta, &ref_size);
            assert_chunks_decode_alike(ours, ours_size, ref, ref_size, what);
            free(ref);

            tmp_path(state, "self.exr", path, sizeof path);
            tmp_path(state, "self_view.exr", view, sizeof view);
            write_all(path, ours, ours_size);
            assert_int_equal(mr_exr_read_file(path, &back, NULL, &err), MR_OK);
            check_same_film(in, back);
            mr_film_free(back);
            back = NULL;
            /* C++: a two-view copy keeps the default view's R G B A Z under
             * their names (the layered N.* and id.* get the view's name in
             * them); every chunk of ours was inflated to make it. */
            snprintf(cmd, sizeof cmd, "exrmultiview -z none left '%s' right '%s' '%s' 2>&1",
                     path, path, view);
            out = run_capture(cmd);
            if (out[0])
                fail_msg("%s: exrmultiview: %s", what, out);
            free(out);
            assert_int_equal(mr_exr_read_file(view, &back, NULL, &err), MR_OK);
            for (size_t i = 0; i < (size_t)w * (size_t)h; i++) {
                check_half(back->r[i], in->r[i]);
                check_half(back->a[i], in->a[i]);
                assert_memory_equal(&back->z[i], &in->z[i], sizeof(float));
            }
            mr_film_free(back);
            free(ours);
        }
        mr_film_free(in);
    }
}

/* The same for other choices of passes (issue 13: output.aovs) and half
 * normals: every pass at once, and a few alone, at the odd sizes. */
static void test_self_compressed_passes_decode(void **state)
{
    static const mr_compression cs[] = {MR_COMPRESSION_NONE, MR_COMPRESSION_ZIP,
                                        MR_COMPRESSION_ZIPS, MR_COMPRESSION_PIZ};
    static const int sizes[][2] = {{1, 1}, {1, 17}, {4097, 3}};
    static const struct {
        unsigned aovs;
        bool half_normals;
    } sets[] = {
        {MR_AOV_ALL, false},
        {MR_AOV_ALL, true},
        {MR_AOV_Z | MR_AOV_P, false},
        {MR_AOV_T | MR_AOV_RGBA, false},
        {MR_AOV_N, true},
        {MR_AOV_CRYPTOMATTE | MR_AOV_ID, false},
    };
    (void)state;
    for (size_t s = 0; s < sizeof sizes / sizeof sizes[0]; s++)
        for (size_t p = 0; p < sizeof sets / sizeof sets[0]; p++) {
            mr_film *in = varied_film(sizes[s][0], sizes[s][1], 5u + (uint32_t)(s * 7 + p),
                                      sets[p].aovs);
            size_t ref_size = 0;
            uint8_t *ref = reference_write_passes(in, sets[p].half_normals, &ref_size);
            for (size_t c = 0; c < sizeof cs / sizeof cs[0]; c++) {
                mr_exr_options opt = {cs[c], 0, 2, sets[p].half_normals};
                mr_error err = {0};
                uint8_t *ours = NULL;
                size_t ours_size = 0;
                char what[96];
                snprintf(what, sizeof what, "%s %dx%d passes 0x%x%s", mr_compression_name(cs[c]),
                         sizes[s][0], sizes[s][1], sets[p].aovs,
                         sets[p].half_normals ? " half normals" : "");
                if (mr_exr_write_memory(&ours, &ours_size, in, &opt, &k_meta, &err) != MR_OK)
                    fail_msg("%s: %s", what, err.msg);
                assert_chunks_decode_alike(ours, ours_size, ref, ref_size, what);
                free(ours);
            }
            free(ref);
            mr_film_free(in);
        }
}

/* A valid one-row EXR (one HALF channel "Z") of the given width. */
static void write_row(const char *path, int width)
{
    exr_context_initializer_t init = EXR_DEFAULT_CONTEXT_INITIALIZER;
    exr_context_t ctxt = NULL;
    exr_encode_pipeline_t enc = EXR_ENCODE_PIPELINE_INITIALIZER;
    exr_chunk_info_t ci;
    uint16_t *row = calloc((size_t)width, sizeof *row);
    int part;

    assert_non_null(row);
    init.error_handler_fn = quiet;
    assert_int_equal(exr_start_write(&ctxt, path, EXR_WRITE_FILE_DIRECTLY, &init), 0);
    assert_int_equal(exr_add_part(ctxt, NULL, EXR_STORAGE_SCANLINE, &part), 0);
    assert_int_equal(
        exr_initialize_required_attr_simple(ctxt, part, width, 1, EXR_COMPRESSION_NONE), 0);
    assert_int_equal(exr_add_channel(ctxt, part, "Z", EXR_PIXEL_HALF, 0, 1, 1), 0);
    assert_int_equal(exr_write_header(ctxt), 0);
    assert_int_equal(exr_write_scanline_chunk_info(ctxt, part, 0, &ci), 0);
    assert_int_equal(exr_encoding_initialize(ctxt, part, &ci, &enc), 0);
    enc.channels[0].encode_from_ptr = (const uint8_t *)row;
    enc.channels[0].user_data_type = EXR_PIXEL_HALF;
    enc.channels[0].user_bytes_per_element = 2;
    enc.channels[0].user_pixel_stride = 2;
    enc.channels[0].user_line_stride = 2 * width;
    assert_int_equal(exr_encoding_choose_default_routines(ctxt, part, &enc), 0);
    assert_int_equal(exr_encoding_run(ctxt, part, &enc), 0);
    assert_int_equal(exr_encoding_destroy(ctxt, &enc), 0);
    assert_int_equal(exr_finish(&ctxt), 0);
    free(row);
}

static void test_read_respects_caps(void **state)
{
    char path[256];
    mr_film *f = NULL;
    mr_error err = {0};

    /* Valid EXR, but wider than the film cap: MR_ERR_LIMIT, not a crash or
     * a huge allocation. */
    tmp_path(state, "wide.exr", path, sizeof path);
    write_row(path, MR_MAX_RESOLUTION + 1);
    assert_int_equal(mr_exr_read_file(path, &f, NULL, &err), MR_ERR_LIMIT);
    assert_null(f);
    assert_non_null(strstr(err.msg, "8193x1"));
    /* At the cap it reads. */
    write_row(path, MR_MAX_RESOLUTION);
    assert_int_equal(mr_exr_read_file(path, &f, NULL, &err), MR_OK);
    assert_int_equal(f->width, MR_MAX_RESOLUTION);
    mr_film_free(f);
}

/* ------------------------------------------------------------------ */
/* broken input                                                        */

static void expect_format(const char *path)
{
    mr_film *f = (mr_film *)(uintptr_t)1; /* must be reset to NULL */
    mr_exr_meta meta;
    mr_error err = {0};
    int rc;

    memset(&meta, 0x7F, sizeof meta);
    rc = mr_exr_read_file(path, &f, &meta, &err);
    if (rc != MR_ERR_FORMAT)
        fail_msg("%s: expected MR_ERR_FORMAT, got %s (%s)", path, mr_err_name(rc), err.msg);
    assert_null(f);
    assert_int_equal(err.code, MR_ERR_FORMAT);
    assert_non_null(strstr(err.msg, path));
    assert_int_equal(meta.frame, 0); /* meta not left half-filled */
}

/* An uncompressed file with A and two channels we do not know (their
 * names damaged): OpenEXRCore 3.1 unpacked the unknown ones through the
 * NULL pointer that means "skip" and crashed (found by tests/fuzz/fuzz_exr;
 * the file is its crasher). They go to a scratch buffer now; A is read. */
static void test_unknown_channels_skipped(void **state)
{
    (void)state;
    const char *src = getenv("MR_SOURCE_DIR");
    char path[1024];
    snprintf(path, sizeof path, "%s/tests/fuzz/crashers/fuzz_exr/"
             "crash-949785ba205eaa2fc1674046455672b2577e46d5", src ? src : ".");
    mr_film *f = NULL;
    mr_error err = {0};
    assert_int_equal(mr_exr_read_file(path, &f, NULL, &err), MR_OK);
    assert_non_null(f);
    assert_int_equal(f->width, 114);
    assert_int_equal(f->height, 1);
    mr_film_free(f);
}

static void test_bad_files(void **state)
{
    char path[256], good[256];
    static const char text[] = "this is a text file, not an EXR image\n";
    mr_film *in = pattern_film(), *f = NULL;
    mr_exr_options opt = {MR_COMPRESSION_ZIP, 0, 0, false};
    mr_error err = {0};
    uint8_t *data = NULL, *junk = NULL;
    size_t size = 0, i;
    uint32_t lcg = 12345u;

    /* Missing file and a directory are I/O errors, not format errors. */
    tmp_path(state, "missing.exr", path, sizeof path);
    assert_int_equal(mr_exr_read_file(path, &f, NULL, &err), MR_ERR_IO);
    assert_non_null(strstr(err.msg, "missing.exr"));
    tmp_path(state, "", path, sizeof path);
    assert_int_equal(mr_exr_read_file(path, &f, NULL, &err), MR_ERR_IO);
    assert_int_equal(mr_exr_read_file(NULL, &f, NULL, &err), MR_ERR_INVALID);
    assert_int_equal(mr_exr_read_file(path, NULL, NULL, &err), MR_ERR_INVALID);

    tmp_path(state, "text.exr", path, sizeof path);
    write_all(path, text, sizeof text - 1);
    expect_format(path);

    tmp_path(state, "empty.exr", path, sizeof path);
    write_all(path, "", 0);
    expect_format(path);

    /* Valid magic followed by noise. */
    junk = malloc(4096);
    assert_non_null(junk);
    junk[0] = 0x76; junk[1] = 0x2f; junk[2] = 0x31; junk[3] = 0x01;
    for (i = 4; i < 4096; i++) {
        lcg = lcg * 1664525u + 1013904223u;
        junk[i] = (uint8_t)(lcg >> 24);
    }
    tmp_path(state, "noise.exr", path, sizeof path);
    write_all(path, junk, 4096);
    expect_format(path);

    /* Truncations of a good file: inside the magic, the header, the offset
     * table, the pixel data, and one byte short. */
    tmp_path(state, "good.exr", good, sizeof good);
    assert_int_equal(mr_exr_write_file(good, in, &opt, &k_meta, &err), MR_OK);
    data = read_all(good, &size);
    {
        /* The offset table (4 chunks of 16 rows) sits right before the first
         * chunk, so its first entry is its own position + 32. */
        size_t table = 0;
        for (i = 8; i + 8 <= size && !table; i++) {
            uint64_t v = 0;
            int k;
            for (k = 7; k >= 0; k--)
                v = (v << 8) | data[i + (size_t)k];
            if (v == (uint64_t)i + 32u)
                table = i;
        }
        assert_true(table > 300);
        const size_t cuts[] = {2, 8, 60, 300, table, table + 4, table + 31,
                               size / 2, size - 1};
        for (i = 0; i < sizeof cuts / sizeof cuts[0]; i++) {
            char name[64];
            snprintf(name, sizeof name, "cut%zu.exr", cuts[i]);
            tmp_path(state, name, path, sizeof path);
            write_all(path, data, cuts[i]);
            expect_format(path);
        }
    }

    /* Garbage over the pixel data in the middle of the file: zlib or the
     * chunk headers must catch it. */
    {
        uint8_t *bad = malloc(size);
        assert_non_null(bad);
        memcpy(bad, data, size);
        for (i = size / 2; i < size / 2 + 64; i++)
            bad[i] = 0xA5;
        tmp_path(state, "garbled.exr", path, sizeof path);
        write_all(path, bad, size);
        expect_format(path);
        free(bad);
    }

    free(data);
    free(junk);
    mr_film_free(in);
}

static void test_tiled_rejected(void **state)
{
    char good[256], tiled[256], cmd[700], *out;
    mr_film *in = pattern_film(), *f = NULL;
    mr_error err = {0};

    tmp_path(state, "for_tiling.exr", good, sizeof good);
    tmp_path(state, "tiled.exr", tiled, sizeof tiled);
    assert_int_equal(mr_exr_write_file(good, in, NULL, &k_meta, &err), MR_OK);
    /* A real tiled EXR, made by the OpenEXR tool from our own file. */
    snprintf(cmd, sizeof cmd, "exrmaketiled '%s' '%s' 2>&1", good, tiled);
    out = run_capture(cmd);
    free(out);
    assert_int_equal(access(tiled, R_OK), 0);
    assert_int_equal(mr_exr_read_file(tiled, &f, NULL, &err), MR_ERR_FORMAT);
    assert_null(f);
    assert_non_null(strstr(err.msg, "tiled"));
    mr_film_free(in);
}

static void test_write_errors(void **state)
{
    char path[256];
    mr_film *in = pattern_film();
    mr_film hollow;
    mr_exr_options bad_level = {MR_COMPRESSION_ZIP, 10, 0, false};
    mr_exr_options bad_comp = {(mr_compression)42, 0, 0, false};
    mr_exr_meta bad_meta = k_meta;
    mr_error err = {0};
    uint8_t *mem = (uint8_t *)(uintptr_t)1;
    size_t size = 99;

    tmp_path(state, "werr.exr", path, sizeof path);
    assert_int_equal(mr_exr_write_file(path, NULL, NULL, NULL, &err), MR_ERR_INVALID);
    assert_int_equal(access(path, F_OK), -1); /* nothing left behind */
    assert_int_equal(mr_exr_write_file(path, in, &bad_level, NULL, &err), MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "zip_level"));
    assert_int_equal(access(path, F_OK), -1);
    assert_int_equal(mr_exr_write_file(path, in, &bad_comp, NULL, &err), MR_ERR_INVALID);
    bad_meta.time = NAN;
    assert_int_equal(mr_exr_write_file(path, in, NULL, &bad_meta, &err), MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "meta.time"));
    assert_int_equal(mr_exr_write_file("", in, NULL, NULL, &err), MR_ERR_INVALID);
    assert_int_equal(mr_exr_write_file(NULL, in, NULL, NULL, &err), MR_ERR_INVALID);

    /* A hand-made film with a missing plane or a size beyond the caps. */
    hollow = *in;
    hollow.nz = NULL;
    assert_int_equal(mr_exr_write_memory(&mem, &size, &hollow, NULL, NULL, &err),
                     MR_ERR_INVALID);
    assert_null(mem);
    assert_int_equal(size, 0);
    assert_non_null(strstr(err.msg, "N.Z"));
    hollow = *in;
    hollow.width = 9000;
    assert_int_equal(mr_exr_write_memory(&mem, &size, &hollow, NULL, NULL, &err),
                     MR_ERR_INVALID);
    assert_int_equal(mr_exr_write_memory(NULL, &size, in, NULL, NULL, &err), MR_ERR_INVALID);

    /* Unwritable location: an I/O error naming the path. */
    tmp_path(state, "no/such/dir/x.exr", path, sizeof path);
    assert_int_equal(mr_exr_write_file(path, in, NULL, NULL, &err), MR_ERR_IO);
    assert_non_null(strstr(err.msg, "no/such/dir/x.exr"));

    /* A failed write leaves an existing file untouched. */
    tmp_path(state, "keep.exr", path, sizeof path);
    write_all(path, "precious", 8);
    assert_int_equal(mr_exr_write_file(path, in, &bad_level, NULL, &err), MR_ERR_INVALID);
    {
        size_t n = 0;
        uint8_t *kept = read_all(path, &n);
        assert_int_equal(n, 8);
        assert_memory_equal(kept, "precious", 8);
        free(kept);
    }
    /* The final rename fails when the target is a directory: I/O error, and
     * the temporary file is cleaned up. */
    tmp_path(state, "adir.exr", path, sizeof path);
    assert_int_equal(mkdir(path, 0755), 0);
    assert_int_equal(mr_exr_write_file(path, in, NULL, NULL, &err), MR_ERR_IO);
    assert_non_null(strstr(err.msg, "rename"));
    {
        const fixture *fx = *state;
        char cmd[256], *out;
        snprintf(cmd, sizeof cmd, "find '%s' -name '*.tmp*'", fx->dir);
        out = run_capture(cmd);
        assert_string_equal(out, ""); /* no temporary files left anywhere */
        free(out);
    }

    mr_film_free(in);
}

static void test_compression_names(void **state)
{
    mr_compression c = MR_COMPRESSION_PIZ;
    (void)state;

    assert_string_equal(mr_compression_name(MR_COMPRESSION_NONE), "none");
    assert_string_equal(mr_compression_name(MR_COMPRESSION_ZIP), "zip");
    assert_string_equal(mr_compression_name(MR_COMPRESSION_ZIPS), "zips");
    assert_string_equal(mr_compression_name(MR_COMPRESSION_PIZ), "piz");
    assert_true(mr_compression_parse("zips", &c));
    assert_int_equal(c, MR_COMPRESSION_ZIPS);
    assert_true(mr_compression_parse("none", &c));
    assert_int_equal(c, MR_COMPRESSION_NONE);
    /* DWAA is not implemented by the 3.1.5 C library; names are exact. */
    assert_false(mr_compression_parse("dwaa", &c));
    assert_false(mr_compression_parse("ZIP", &c));
    assert_false(mr_compression_parse("", &c));
    assert_false(mr_compression_parse(NULL, &c));
    assert_int_equal(c, MR_COMPRESSION_NONE);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_half_exhaustive_roundtrip),
        cmocka_unit_test(test_half_rounding_nearest_even),
        cmocka_unit_test(test_half_special_values),
        cmocka_unit_test(test_film_caps),
        cmocka_unit_test(test_film_clear),
        cmocka_unit_test(test_roundtrip_none),
        cmocka_unit_test(test_roundtrip_zip),
        cmocka_unit_test(test_roundtrip_zip_level9),
        cmocka_unit_test(test_roundtrip_zips),
        cmocka_unit_test(test_roundtrip_piz),
        cmocka_unit_test(test_zip_level_changes_output),
        cmocka_unit_test(test_meta_absent),
        cmocka_unit_test(test_nonfinite_become_finite),
        cmocka_unit_test(test_tiny_and_tall),
        cmocka_unit_test(test_foreign_channels_by_name),
        cmocka_unit_test(test_read_respects_caps),
        cmocka_unit_test(test_parallel_identical),
        cmocka_unit_test(test_zip_predict_matches_definition),
        cmocka_unit_test(test_self_compressed_chunks_decode),
        cmocka_unit_test(test_self_compressed_passes_decode),
        cmocka_unit_test(test_bad_files),
        cmocka_unit_test(test_unknown_channels_skipped),
        cmocka_unit_test(test_tiled_rejected),
        cmocka_unit_test(test_write_errors),
        cmocka_unit_test(test_compression_names),
    };
    return cmocka_run_group_tests(tests, group_setup, group_teardown);
}
