/*
 * test_dmm_encode.c - hierarchical DMM encoding, the min/max pyramid and the
 * binary file (core/kinds/dmm/dmm_encode.h) on synthetic inputs (random and
 * extreme values, crafted shared edges) and on a real bake of a bumpy sphere
 * (the generator of test_dmm_bake.c, rebuilt here).
 *
 * Tolerances: decoding is integer arithmetic and must match the encoder
 * bit for bit (no tolerance). Against the float input, a lossless encode (all
 * correction shifts 0) is off by at most half a grid step, scale / 2, plus
 * the single float rounding of bias + scale * V (half an ulp of the result,
 * bounded here by FLT_EPSILON * max|d|).
 */
#include <float.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <cmocka.h>

#include "kinds/dmm/dmm_bake.h"
#include "kinds/dmm/dmm_encode.h"
#include "kinds/dmm/micromesh.h"
#include "util/crc32.h"
#include "util/le.h"

/* Deterministic generator (xorshift), so failures reproduce. */
static uint32_t rnd(uint64_t *s)
{
    *s ^= *s << 13;
    *s ^= *s >> 7;
    *s ^= *s << 17;
    return (uint32_t)(*s >> 11);
}

static float rndf(uint64_t *s, float lo, float hi)
{
    return lo + (hi - lo) * (float)(rnd(s) & 0xFFFFFF) / (float)0xFFFFFF;
}

/* Decodes every triangle and returns the max |decoded - input|. */
static double decode_error(const mr_dmm_encoded *enc, const float *disp)
{
    uint32_t vc = mr_umesh_vertex_count(enc->level);
    float out[561];
    double worst = 0;
    for (uint32_t t = 0; t < enc->triangle_count; t++) {
        assert_int_equal(mr_dmm_decode_floats(enc, t, out, NULL), MR_OK);
        for (uint32_t v = 0; v < vc; v++)
            worst = fmax(worst, fabs((double)out[v] - (double)disp[(size_t)t * vc + v]));
    }
    return worst;
}

static void test_record_bytes(void **state)
{
    (void)state;
    uint8_t bits[6];
    mr_dmm_default_bits(bits);
    /* level 3: 3*16 + (16 + 3*11) + (16 + 9*10) + (16 + 30*9) = 489 bits */
    assert_int_equal(mr_dmm_record_bytes(3, bits), 62);
    /* level 4: 489 + 16 + 108*8 = 1369 bits */
    assert_int_equal(mr_dmm_record_bytes(4, bits), 172);
    assert_int_equal(mr_dmm_record_bytes(0, bits), 6);
    assert_int_equal(mr_dmm_record_bytes(6, bits), 0);
    bits[2] = 1;
    /* widths above the level are ignored: 48 + 16 + 3*11 = 97 bits */
    assert_int_equal(mr_dmm_record_bytes(1, bits), 13);
    assert_int_equal(mr_dmm_record_bytes(2, bits), 0);
    bits[2] = 17;
    assert_int_equal(mr_dmm_record_bytes(2, bits), 0);
    bits[0] = 0;
    assert_int_equal(mr_dmm_record_bytes(0, bits), 0);
}

/* Wide corrections (bits[l] >= G + 1 fit any correction at shift 0): the
 * encode is lossless on the grid at every level 0..5. */
static void test_lossless_random(void **state)
{
    (void)state;
    uint64_t s = 12345;
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint8_t bits[6] = {11, 12, 12, 12, 12, 12};
        uint32_t count = 7, vc = mr_umesh_vertex_count(level);
        float *d = malloc(sizeof(float) * count * vc);
        assert_non_null(d);
        for (uint32_t i = 0; i < count * vc; i++)
            d[i] = rndf(&s, -0.3f, 0.7f);
        mr_dmm_encoded *enc = NULL;
        mr_dmm_encode_stats st;
        mr_error err = {0};
        assert_int_equal(mr_dmm_encode(level, bits, count, NULL, d, &enc, &st, &err), MR_OK);
        double tol = enc->scale * 0.5 + FLT_EPSILON * 0.7;
        assert_true(st.max_error <= tol);
        assert_true(st.rms_error <= st.max_error);
        assert_int_equal(st.clamped, 0);
        assert_int_equal(st.shifted, 0);
        /* the decoder reproduces the encoder's values exactly */
        assert_true(decode_error(enc, d) == st.max_error);
        free(d);
        mr_dmm_encoded_free(enc);
    }
}

/* Narrow corrections on noise force shifts; decoding still reproduces the
 * encoder, values stay on the grid, and the error is bounded by the shift
 * white noise needs (below). */
static void test_lossy_random(void **state)
{
    (void)state;
    uint64_t s = 777;
    uint8_t bits[6];
    mr_dmm_default_bits(bits);
    for (unsigned level = 1; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t count = 5, vc = mr_umesh_vertex_count(level);
        float *d = malloc(sizeof(float) * count * vc);
        assert_non_null(d);
        for (uint32_t i = 0; i < count * vc; i++)
            d[i] = rndf(&s, -1.0f, 1.0f);
        mr_dmm_encoded *enc = NULL;
        mr_dmm_encode_stats st;
        assert_int_equal(mr_dmm_encode(level, bits, count, NULL, d, &enc, &st, NULL), MR_OK);
        assert_true(decode_error(enc, d) == st.max_error);
        /* white noise needs corrections of up to 2^G steps (G = bits[0]);
         * the narrowest width used, bits[level], covers them at shift
         * G + 1 - bits[level]: error <= 2^(G - bits[level]) steps + rounding
         * (16.5 steps for the former {11, .., 7} at level 5) */
        double steps = (double)(1u << (bits[0] - bits[level])) + 0.5;
        assert_true(st.max_error <= enc->scale * steps + FLT_EPSILON);
        uint16_t v[561];
        for (uint32_t t = 0; t < count; t++) {
            assert_int_equal(mr_dmm_decode_values(enc, t, v, NULL), MR_OK);
            for (uint32_t i = 0; i < vc; i++)
                assert_true(v[i] <= (1u << bits[0]) - 1u);
        }
        free(d);
        mr_dmm_encoded_free(enc);
    }
}

/* Lattice index of step k along edge e (as test_dmm_bake.c walks edges). */
static uint32_t edge_vertex(unsigned level, int e, uint32_t k)
{
    uint32_t n = mr_umesh_segments(level);
    return e == 0   ? mr_umesh_vertex_index(level, k, 0)
           : e == 1 ? mr_umesh_vertex_index(level, n - k, k)
                    : mr_umesh_vertex_index(level, 0, n - k);
}

/* Two triangles share an edge (walked in opposite directions, as in a
 * consistently wound mesh) with identical edge displacements; everything
 * else differs, with much stronger noise inside so the interior shifts
 * differ from the edge shifts. Edge vertices must decode bit-identically,
 * for every pair of edge slots and every level. */
static void test_watertight_edges(void **state)
{
    (void)state;
    uint64_t s = 99;
    uint8_t bits[6];
    mr_dmm_default_bits(bits);
    for (unsigned level = 1; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t n = mr_umesh_segments(level), vc = mr_umesh_vertex_count(level);
        for (int e = 0; e < 3; e++)
            for (int f = 0; f < 3; f++) {
                float d[2 * 561];
                for (uint32_t i = 0; i < 2 * vc; i++)
                    d[i] = rndf(&s, -1.0f, 1.0f);
                for (uint32_t k = 0; k <= n; k++) {
                    /* smooth-ish edge data with a bit of noise */
                    float x = 0.1f * sinf((float)k * 0.7f) + rndf(&s, -0.01f, 0.01f);
                    d[edge_vertex(level, e, k)] = x;
                    d[vc + edge_vertex(level, f, n - k)] = x;
                }
                mr_dmm_encoded *enc = NULL;
                assert_int_equal(mr_dmm_encode(level, bits, 2, NULL, d, &enc, NULL, NULL), MR_OK);
                uint16_t v0[561], v1[561];
                assert_int_equal(mr_dmm_decode_values(enc, 0, v0, NULL), MR_OK);
                assert_int_equal(mr_dmm_decode_values(enc, 1, v1, NULL), MR_OK);
                for (uint32_t k = 0; k <= n; k++)
                    assert_int_equal(v0[edge_vertex(level, e, k)],
                                     v1[edge_vertex(level, f, n - k)]);
                mr_dmm_encoded_free(enc);
            }
    }
}

/* A level-l triangle next to a level-(l+1) one whose shared edge is
 * decimated (per-triangle levels): the edge's displacements are a function
 * of the edge parameter (what the baker measures from bit-identical points),
 * the fine side's odd edge vertices get unrelated values (they are
 * collapsed). The level-l vertices of the edge must decode to the same
 * values on both sides, for every pair of edge slots and every level. */
static void test_watertight_mixed_levels(void **state)
{
    (void)state;
    uint64_t s = 7;
    uint8_t bits[6];
    mr_dmm_default_bits(bits);
    for (unsigned level = 0; level < MR_UMESH_MAX_LEVEL; level++) {
        uint32_t nc = mr_umesh_segments(level), nf = 2 * nc;
        uint32_t stride = mr_umesh_vertex_count(level + 1);
        for (int e = 0; e < 3; e++)
            for (int f = 0; f < 3; f++) {
                float d[2 * 561];
                for (uint32_t i = 0; i < 2 * stride; i++)
                    d[i] = rndf(&s, -1.0f, 1.0f);
                for (uint32_t k = 0; k <= nf; k++) {
                    float x = 0.1f * sinf((float)k * 0.35f) + rndf(&s, -0.01f, 0.01f);
                    if (k % 2 == 0)
                        d[edge_vertex(level, e, k / 2)] = x;
                    d[stride + edge_vertex(level + 1, f, nf - k)] = x;
                }
                const uint8_t info[2] = {mr_dmm_tri_info(level, 0),
                                         mr_dmm_tri_info(level + 1, 1u << f)};
                mr_dmm_encoded *enc = NULL;
                assert_int_equal(mr_dmm_encode(level + 1, bits, 2, info, d, &enc, NULL, NULL),
                                 MR_OK);
                assert_int_equal(mr_dmm_tri_level(enc, 0), level);
                assert_int_equal(mr_dmm_tri_decimate(enc, 1), 1u << f);
                assert_int_equal(enc->records_bytes, mr_dmm_record_bytes(level, bits) +
                                                         mr_dmm_record_bytes(level + 1, bits));
                uint16_t v0[561], v1[561];
                assert_int_equal(mr_dmm_decode_values(enc, 0, v0, NULL), MR_OK);
                assert_int_equal(mr_dmm_decode_values(enc, 1, v1, NULL), MR_OK);
                for (uint32_t k = 0; k <= nc; k++)
                    assert_int_equal(v0[edge_vertex(level, e, k)],
                                     v1[edge_vertex(level + 1, f, nf - 2 * k)]);
                mr_dmm_encoded_free(enc);
            }
    }
}

/* Values at the limits of the grid and of float. */
static void test_extremes(void **state)
{
    (void)state;
    uint8_t bits[6];
    mr_dmm_default_bits(bits);
    mr_dmm_encoded *enc = (mr_dmm_encoded *)&bits; /* must be reset to NULL on failure */
    mr_dmm_encode_stats st;
    mr_error err = {0};
    float d[45];
    /* constant: zero range decodes exactly */
    for (int i = 0; i < 45; i++)
        d[i] = 0.25f;
    assert_int_equal(mr_dmm_encode(3, bits, 1, NULL, d, &enc, &st, &err), MR_OK);
    assert_true(st.max_error == 0);
    mr_dmm_encoded_free(enc);
    /* the whole float range: finite scale, min and max decode exactly */
    for (int i = 0; i < 45; i++)
        d[i] = i % 2 ? FLT_MAX : -FLT_MAX;
    assert_int_equal(mr_dmm_encode(3, bits, 1, NULL, d, &enc, &st, &err), MR_OK);
    float out[45];
    assert_int_equal(mr_dmm_decode_floats(enc, 0, out, NULL), MR_OK);
    assert_true(out[0] == -FLT_MAX);
    for (int i = 0; i < 45; i++)
        assert_true(isfinite(out[i]));
    mr_dmm_encoded_free(enc);
    /* ...but not with a 1-bit grid, whose step would overflow float */
    uint8_t one[6] = {1, 2, 2, 2, 0, 0};
    assert_int_equal(mr_dmm_encode(3, one, 1, NULL, d, &enc, &st, &err), MR_ERR_INVALID);
    assert_null(enc);
    /* 16-bit grid with 2-bit corrections on noise: shifts saturate, some
     * corrections clamp; still exact decode and values on the grid */
    uint64_t s = 5;
    uint8_t narrow[6] = {16, 2, 2, 2, 2, 2};
    static float big[3 * 561];
    for (int i = 0; i < 3 * 561; i++)
        big[i] = rndf(&s, -5.0f, 5.0f);
    assert_int_equal(mr_dmm_encode(5, narrow, 3, NULL, big, &enc, &st, &err), MR_OK);
    assert_true(decode_error(enc, big) == st.max_error);
    mr_dmm_encoded_free(enc);
    /* bad input */
    d[3] = NAN;
    assert_int_equal(mr_dmm_encode(3, bits, 1, NULL, d, &enc, &st, &err), MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "not finite"));
    d[3] = INFINITY;
    assert_int_equal(mr_dmm_encode(3, bits, 1, NULL, d, &enc, &st, &err), MR_ERR_INVALID);
    d[3] = 0;
    assert_int_equal(mr_dmm_encode(6, bits, 1, NULL, d, &enc, &st, &err), MR_ERR_INVALID);
    assert_int_equal(mr_dmm_encode(3, bits, 0, NULL, d, &enc, &st, &err), MR_ERR_INVALID);
    assert_int_equal(mr_dmm_encode(3, bits, 1, NULL, NULL, &enc, &st, &err), MR_ERR_INVALID);
    assert_null(enc);
}

/* Sign of the integer edge function: which side of (p, q) lattice point r is. */
static int64_t side(int64_t pa, int64_t pb, int64_t qa, int64_t qb, int64_t ra, int64_t rb)
{
    return (qa - pa) * (rb - pb) - (qb - pb) * (ra - pa);
}

static void test_pyramid(void **state)
{
    (void)state;
    uint64_t s = 4242;
    for (unsigned level = 0; level <= MR_UMESH_MAX_LEVEL; level++) {
        uint32_t vc = mr_umesh_vertex_count(level), tc = mr_umesh_triangle_count(level);
        uint16_t v[561], lo[1365], hi[1365];
        for (uint32_t i = 0; i < vc; i++)
            v[i] = (uint16_t)(rnd(&s) & 0x7FF);
        assert_int_equal(mr_dmm_pyramid_size(level), ((1u << (2 * level + 2)) - 1) / 3);
        assert_int_equal(mr_dmm_pyramid_build(level, v, lo, hi, NULL), MR_OK);
        /* bounds tight and containing: brute force over the lattice */
        for (unsigned l = 0; l <= level; l++) {
            uint32_t off = (uint32_t)(((1u << (2 * l)) - 1) / 3);
            for (uint32_t id = 0; id < (1u << (2 * l)); id++) {
                uint32_t a[3], b[3];
                assert_true(mr_dmm_subtri(level, l, id, a, b));
                uint16_t mn = UINT16_MAX, mx = 0;
                uint32_t covered = 0;
                for (uint32_t i = 0; i < vc; i++) {
                    uint32_t pa, pb;
                    mr_umesh_vertex_coords(level, i, &pa, &pb);
                    int64_t s0 = side(a[0], b[0], a[1], b[1], pa, pb);
                    int64_t s1 = side(a[1], b[1], a[2], b[2], pa, pb);
                    int64_t s2 = side(a[2], b[2], a[0], b[0], pa, pb);
                    if (!((s0 >= 0 && s1 >= 0 && s2 >= 0) || (s0 <= 0 && s1 <= 0 && s2 <= 0)))
                        continue;
                    covered++;
                    assert_true(v[i] >= lo[off + id] && v[i] <= hi[off + id]);
                    mn = v[i] < mn ? v[i] : mn;
                    mx = v[i] > mx ? v[i] : mx;
                }
                uint32_t side_len = 1u << (level - l);
                assert_int_equal(covered, (side_len + 1) * (side_len + 2) / 2);
                assert_int_equal(lo[off + id], mn);
                assert_int_equal(hi[off + id], mx);
            }
        }
        /* the leaves are exactly the micro-triangles, each once */
        uint32_t *tris = malloc(sizeof(uint32_t) * 3 * tc);
        uint8_t *seen = calloc(tc, 1);
        assert_non_null(tris);
        assert_non_null(seen);
        assert_int_equal(mr_umesh_triangles(level, 0, tris), tc);
        for (uint32_t id = 0; id < tc; id++) {
            uint32_t a[3], b[3], ix[3];
            mr_dmm_subtri(level, level, id, a, b);
            for (int k = 0; k < 3; k++)
                ix[k] = mr_umesh_vertex_index(level, a[k], b[k]);
            bool found = false;
            for (uint32_t t = 0; t < tc && !found; t++) {
                uint32_t *u = tris + 3 * t;
                bool same = true;
                for (int k = 0; k < 3; k++)
                    same = same && (ix[k] == u[0] || ix[k] == u[1] || ix[k] == u[2]);
                if (same && !seen[t])
                    seen[t] = 1, found = true;
            }
            assert_true(found);
        }
        free(tris);
        free(seen);
    }
    uint32_t a[3], b[3];
    assert_false(mr_dmm_subtri(3, 4, 0, a, b));
    assert_false(mr_dmm_subtri(3, 2, 16, a, b));
    assert_int_equal(mr_dmm_pyramid_size(6), 0);
}

/* ---- file */

static mr_dmm_encoded *small_encoded(uint32_t count)
{
    uint64_t s = 31;
    uint8_t bits[6];
    mr_dmm_default_bits(bits);
    float *d = malloc(sizeof(float) * 45 * count);
    assert_non_null(d);
    for (uint32_t i = 0; i < 45 * count; i++)
        d[i] = rndf(&s, -0.1f, 0.2f);
    mr_dmm_encoded *enc = NULL;
    assert_int_equal(mr_dmm_encode(3, bits, count, NULL, d, &enc, NULL, NULL), MR_OK);
    free(d);
    return enc;
}

static void assert_same(const mr_dmm_encoded *a, const mr_dmm_encoded *b)
{
    assert_int_equal(a->level, b->level);
    assert_memory_equal(a->bits, b->bits, sizeof a->bits);
    assert_int_equal(a->triangle_count, b->triangle_count);
    assert_int_equal(a->records_bytes, b->records_bytes);
    assert_memory_equal(a->tri_info, b->tri_info, a->triangle_count);
    assert_memory_equal(a->record_offset, b->record_offset, a->triangle_count * sizeof(uint32_t));
    assert_memory_equal(&a->bias, &b->bias, sizeof(float));
    assert_memory_equal(&a->scale, &b->scale, sizeof(float));
    assert_memory_equal(a->records, b->records, (size_t)a->records_bytes);
}

static void test_file_roundtrip(void **state)
{
    (void)state;
    mr_dmm_encoded *enc = small_encoded(9), *back = NULL;
    uint8_t *buf = NULL;
    size_t size = 0;
    mr_error err = {0};
    assert_int_equal(mr_dmm_write(enc, &buf, &size, &err), MR_OK);
    assert_int_equal(enc->records_bytes, 9 * mr_dmm_record_bytes(3, enc->bits));
    assert_int_equal(size, MR_DMM_HEADER_BYTES + 9 + enc->records_bytes + 4);
    assert_memory_equal(buf, "MRDMM\0\r\n", 8);
    assert_int_equal(mr_dmm_read(buf, size, &back, &err), MR_OK);
    assert_same(enc, back);
    mr_dmm_encoded_free(back);
    back = NULL;

    char dir[] = "/tmp/test_dmm_encode.XXXXXX";
    assert_non_null(mkdtemp(dir));
    char path[64];
    snprintf(path, sizeof path, "%s/a.mrdmm", dir);
    assert_int_equal(mr_dmm_write_file(enc, path, &err), MR_OK);
    assert_int_equal(mr_dmm_read_file(path, &back, &err), MR_OK);
    assert_same(enc, back);
    mr_dmm_encoded_free(back);
    /* overwrite in place, then a truncated file on disk */
    assert_int_equal(mr_dmm_write_file(enc, path, &err), MR_OK);
    FILE *f = fopen(path, "wb");
    assert_non_null(f);
    assert_int_equal(fwrite(buf, 1, size - 1, f), size - 1);
    fclose(f);
    assert_int_equal(mr_dmm_read_file(path, &back, &err), MR_ERR_FORMAT);
    assert_non_null(strstr(err.msg, "a.mrdmm"));
    assert_non_null(strstr(err.msg, "byte offset"));
    assert_null(back);
    unlink(path);
    assert_int_equal(mr_dmm_read_file(path, &back, &err), MR_ERR_IO);
    assert_int_equal(mr_dmm_read_file(dir, &back, &err), MR_ERR_IO);
    /* no temporary left behind, directory removable */
    assert_int_equal(rmdir(dir), 0);
    snprintf(path, sizeof path, "%s/missing/x", dir);
    assert_int_equal(mr_dmm_write_file(enc, path, &err), MR_ERR_IO);
    free(buf);
    mr_dmm_encoded_free(enc);
}

/* Reads a corrupted copy: must fail with MR_ERR_FORMAT, a message with the
 * byte offset (and want, if given), and no output. */
static void expect_format(const uint8_t *buf, size_t size, const char *want)
{
    mr_dmm_encoded *out = (mr_dmm_encoded *)&size;
    mr_error err = {0};
    int rc = mr_dmm_read(buf, size, &out, &err);
    if (rc != MR_ERR_FORMAT || !strstr(err.msg, "byte offset") || (want && !strstr(err.msg, want)))
        fail_msg("rc %d msg '%s' (wanted '%s')", rc, err.msg, want ? want : "");
    assert_null(out);
}

static void test_file_corruptions(void **state)
{
    (void)state;
    mr_dmm_encoded *enc = small_encoded(5);
    uint8_t *buf = NULL;
    size_t size = 0;
    assert_int_equal(mr_dmm_write(enc, &buf, &size, NULL), MR_OK);
    uint8_t *c = malloc(size + 16);
    assert_non_null(c);

    /* every truncation */
    for (size_t n = 0; n < size; n++) {
        memcpy(c, buf, n);
        expect_format(c, n, NULL);
    }
    /* oversized: trailing bytes */
    memcpy(c, buf, size);
    memset(c + size, 0, 16);
    expect_format(c, size + 1, "trailing");
    expect_format(c, size + 16, "trailing");
    /* every single-byte corruption (each bit pattern flip) anywhere */
    for (size_t i = 0; i < size; i++)
        for (int bit = 0; bit < 8; bit += 3) {
            memcpy(c, buf, size);
            c[i] ^= (uint8_t)(1u << bit);
            expect_format(c, size, NULL);
        }

    /* semantic corruptions with a recomputed header checksum, so each field
     * check is reached: {offset, 32-bit value, expected message part} */
    struct {
        size_t off;
        uint32_t value;
        const char *want;
    } table[] = {
        {8, 1, "version"},
        {8, 0, "version"},
        {12, 64, "header size"},
        {16, 6, "level"},
        {16, 0xFFFFFFFFu, "level"},
        {20, 0x00000000u, "bit width"},          /* bits[0] = 0 */
        {20, 0x0101110Bu, "offset 21"},          /* bits[1] = 0x11 > 16 */
        {24, 0x00000107u, "offset 24"},          /* bits[4] set above level 3 */
        {28, 0, "triangle count"},
        {28, MR_DMM_MAX_TRIANGLES + 1, "triangle count"},
        {28, MR_DMM_MAX_TRIANGLES, "truncated"}, /* declares far more than present */
        {28, 4, "trailing"},
        {32, 5 * 62 + 1, "truncated"},          /* records size disagrees with the file */
        {36, 0x7FC00000u, "bias"},               /* NaN */
        {40, 0x7F800000u, "scale"},              /* inf */
        {40, 0xBF800000u, "scale"},              /* -1 */
        {40, 0, "scale"},
    };
    for (size_t k = 0; k < sizeof table / sizeof table[0]; k++) {
        memcpy(c, buf, size);
        mr_le_put_u32(c + table[k].off, table[k].value);
        mr_le_put_u32(c + 44, mr_crc32(c, 44));
        expect_format(c, size, table[k].want);
    }
    /* a record byte changed: the record checksum names its own offset */
    memcpy(c, buf, size);
    c[MR_DMM_HEADER_BYTES + 7] ^= 0x40;
    char want[32];
    snprintf(want, sizeof want, "offset %zu", size - 4);
    expect_format(c, size, want);
    /* wrong magic */
    memcpy(c, buf, size);
    c[3] = 'X';
    expect_format(c, size, "magic");

    mr_dmm_encoded *out = NULL;
    assert_int_equal(mr_dmm_read(NULL, 5, &out, NULL), MR_ERR_INVALID);
    free(c);
    free(buf);
    mr_dmm_encoded_free(enc);
}

/* ---- a real bake: bumpy sphere (see test_dmm_bake.c for the surface) */

static double radius_of(double x, double y, double z)
{
    return 1.0 + 0.03 * (sin(4 * x) * cos(3 * y) + 0.5 * sin(5 * z));
}

static void make_sphere(mr_mesh *m, uint32_t n)
{
    memset(m, 0, sizeof *m);
    m->name = "bumpy";
    m->vertex_count = 6 * (n + 1) * (n + 1);
    m->triangle_count = 6 * n * n * 2;
    m->positions = malloc(sizeof(float) * 3 * m->vertex_count);
    m->indices = malloc(sizeof(uint32_t) * 3 * m->triangle_count);
    assert_non_null(m->positions);
    assert_non_null(m->indices);
    uint32_t v = 0, t = 0;
    for (int face = 0; face < 6; face++) {
        int axis = face / 2;
        float sign = face % 2 ? -1.0f : 1.0f;
        uint32_t base = v;
        for (uint32_t j = 0; j <= n; j++)
            for (uint32_t i = 0; i <= n; i++, v++) {
                float c[3];
                c[axis] = sign;
                c[(axis + 1) % 3] = (float)(2 * (int)i - (int)n) / (float)n;
                c[(axis + 2) % 3] = (float)(2 * (int)j - (int)n) / (float)n;
                double l = sqrt((double)c[0] * c[0] + (double)c[1] * c[1] + (double)c[2] * c[2]);
                double x = c[0] / l, y = c[1] / l, z = c[2] / l, r = radius_of(x, y, z);
                m->positions[3 * v] = (float)(r * x);
                m->positions[3 * v + 1] = (float)(r * y);
                m->positions[3 * v + 2] = (float)(r * z);
            }
        for (uint32_t j = 0; j < n; j++)
            for (uint32_t i = 0; i < n; i++) {
                uint32_t a = base + j * (n + 1) + i, b = a + 1, cc = a + n + 1, d = cc + 1;
                uint32_t q[6] = {a, b, d, a, d, cc};
                for (int h = 0; h < 2; h++, t++) {
                    uint32_t *ix = m->indices + 3 * t;
                    memcpy(ix, q + 3 * h, sizeof(uint32_t) * 3);
                    const float *p0 = m->positions + 3 * ix[0], *p1 = m->positions + 3 * ix[1],
                                *p2 = m->positions + 3 * ix[2];
                    mr_vec3 e1 = mr_v3(p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]);
                    mr_vec3 e2 = mr_v3(p2[0] - p0[0], p2[1] - p0[1], p2[2] - p0[2]);
                    if (mr_v3_dot(mr_v3_cross(e1, e2), mr_v3(p0[0], p0[1], p0[2])) < 0) {
                        uint32_t tmp = ix[1];
                        ix[1] = ix[2], ix[2] = tmp;
                    }
                }
            }
    }
}

/* Every shared base edge decodes bit-identically on both triangles. */
static uint32_t check_shared_edges(const mr_dmm_bake *b, const mr_dmm_encoded *enc)
{
    uint32_t n = mr_umesh_segments(b->level), pairs = 0, vc = b->micro_vertex_count;
    uint16_t *all = malloc(sizeof(uint16_t) * vc * b->base_triangle_count);
    assert_non_null(all);
    for (uint32_t t = 0; t < b->base_triangle_count; t++)
        assert_int_equal(mr_dmm_decode_values(enc, t, all + (size_t)t * vc, NULL), MR_OK);
    for (uint32_t t = 0; t < b->base_triangle_count; t++)
        for (int e = 0; e < 3; e++) {
            uint32_t u = b->base_indices[3 * t + e], w = b->base_indices[3 * t + (e + 1) % 3];
            for (uint32_t s = t + 1; s < b->base_triangle_count; s++)
                for (int f = 0; f < 3; f++) {
                    if (b->base_indices[3 * s + f] != w || b->base_indices[3 * s + (f + 1) % 3] != u)
                        continue;
                    pairs++;
                    for (uint32_t k = 0; k <= n; k++)
                        assert_int_equal(all[(size_t)t * vc + edge_vertex(b->level, e, k)],
                                         all[(size_t)s * vc + edge_vertex(b->level, f, n - k)]);
                }
        }
    free(all);
    return pairs;
}

static void test_bumpy_sphere(void **state)
{
    (void)state;
    mr_mesh m;
    make_sphere(&m, 40);
    for (unsigned level = 3; level <= 4; level++) {
        mr_dmm_bake_params p = mr_dmm_bake_params_default();
        p.target_triangles = 400;
        p.level = level;
        p.threads = 2;
        mr_dmm_bake *b = NULL;
        mr_error err = {0};
        assert_int_equal(mr_dmm_bake_run(&m, &p, &b, &err), MR_OK);
        uint8_t bits[6];
        mr_dmm_default_bits(bits);
        mr_dmm_encoded *enc = NULL;
        mr_dmm_encode_stats st;
        assert_int_equal(
            mr_dmm_encode(level, bits, b->base_triangle_count, b->tri_info, b->displacements, &enc, &st, &err),
            MR_OK);
        double dmax = 0;
        for (size_t i = 0; i < (size_t)b->base_triangle_count * b->micro_vertex_count; i++)
            dmax = fmax(dmax, fabs(b->displacements[i]));
        print_message("level %u: %u base triangles, %u B/base triangle, %.3f bits/micro-triangle, "
                      "grid step %.3g, quantisation error max %.3g rms %.3g (%.3g%% / %.3g%% of "
                      "max |d| %.3g), clamped %llu\n",
                      level, b->base_triangle_count, enc->records_bytes / b->base_triangle_count,
                      8.0 * enc->records_bytes / b->base_triangle_count /
                          mr_umesh_triangle_count(level),
                      enc->scale,
                      st.max_error, st.rms_error, 100 * st.max_error / dmax,
                      100 * st.rms_error / dmax, dmax, (unsigned long long)st.clamped);
        print_message("  %llu of %llu corrections shifted (max shift %u)\n",
                      (unsigned long long)st.shifted,
                      (unsigned long long)b->base_triangle_count *
                          (b->micro_vertex_count - 3),
                      st.max_shift);
        /* grid rounding (half a step) plus the rounding of a shifted
         * correction (half of 2^max_shift steps), plus the float rounding */
        double bound = enc->scale * (0.5 + (st.max_shift ? 0.5 * (1u << st.max_shift) : 0)) +
                       FLT_EPSILON * dmax;
        assert_int_equal(st.clamped, 0);
        /* a correction spans at most the whole range (G + 1 bits signed),
         * so no shift passes G + 1 - bits[l] at any level l */
        unsigned widest = 0;
        for (unsigned l = 1; l <= level; l++)
            widest = bits[0] + 1u - bits[l] > widest ? bits[0] + 1u - bits[l] : widest;
        assert_true(st.max_shift <= widest);
        /* the 16-bit grid's shifts adapt the step to each group's
         * corrections: on this smooth surface the error stays below 0.1 %
         * (max) and 0.01 % (rms) of the largest displacement (measured
         * 0.05 % and 0.0065 %); the 11-bit grid it replaced had one step,
         * range / 2047, for all: about the same max, 0.03 % rms */
        assert_true(st.max_error <= 1e-3 * dmax);
        assert_true(st.rms_error <= 1e-4 * dmax);
        assert_true(st.max_error <= bound);
        assert_true(decode_error(enc, b->displacements) == st.max_error);
        assert_int_equal(check_shared_edges(b, enc) * 2, b->base_triangle_count * 3);

        /* the pyramid of every triangle contains its decoded displacements */
        uint16_t v[561], lo[1365], hi[1365];
        for (uint32_t t = 0; t < b->base_triangle_count; t++) {
            assert_int_equal(mr_dmm_decode_values(enc, t, v, NULL), MR_OK);
            assert_int_equal(mr_dmm_pyramid_build(level, v, lo, hi, NULL), MR_OK);
            for (uint32_t i = 0; i < b->micro_vertex_count; i++)
                assert_true(v[i] >= lo[0] && v[i] <= hi[0]);
        }
        /* file round trip of a real bake */
        uint8_t *buf = NULL;
        size_t size = 0;
        mr_dmm_encoded *back = NULL;
        assert_int_equal(mr_dmm_write(enc, &buf, &size, &err), MR_OK);
        assert_int_equal(mr_dmm_read(buf, size, &back, &err), MR_OK);
        assert_same(enc, back);
        free(buf);
        mr_dmm_encoded_free(back);
        mr_dmm_encoded_free(enc);
        mr_dmm_bake_free(b);
    }
    free(m.positions);
    free(m.indices);
}

/* Level/decimation bytes: refused when invalid by the encoder, and by the
 * reader with a checksum that matches (a writer with a bug), naming the
 * byte; a valid byte of another level makes the records size disagree. */
static void test_level_bytes(void **state)
{
    (void)state;
    uint8_t bits[6];
    mr_dmm_default_bits(bits);
    float d[3 * 45] = {0};
    for (int i = 0; i < 3 * 45; i++)
        d[i] = 0.01f * (float)(i % 17);
    const uint8_t bad_infos[] = {0x04, 0x08, 0x10, 0x80, mr_dmm_tri_info(3, 0) | 0x08};
    mr_error err = {0};
    for (size_t k = 0; k < sizeof bad_infos; k++) {
        uint8_t info[3] = {mr_dmm_tri_info(3, 0), bad_infos[k], mr_dmm_tri_info(1, 5)};
        mr_dmm_encoded *enc = (mr_dmm_encoded *)&err;
        assert_int_equal(mr_dmm_encode(3, bits, 3, info, d, &enc, NULL, &err), MR_ERR_INVALID);
        assert_null(enc);
        assert_non_null(strstr(err.msg, "triangle 1"));
    }
    uint8_t info[3] = {mr_dmm_tri_info(3, 2), mr_dmm_tri_info(0, 0), mr_dmm_tri_info(2, 7)};
    mr_dmm_encoded *enc = NULL, *back = NULL;
    assert_int_equal(mr_dmm_encode(3, bits, 3, info, d, &enc, NULL, &err), MR_OK);
    uint8_t *buf = NULL;
    size_t size = 0;
    assert_int_equal(mr_dmm_write(enc, &buf, &size, &err), MR_OK);
    assert_int_equal(mr_dmm_read(buf, size, &back, &err), MR_OK);
    assert_same(enc, back);
    mr_dmm_encoded_free(back);
    const struct {
        uint8_t byte;
        const char *want;
    } cases[] = {{0x04, "offset 49"}, {0x18, "offset 49"}, {0x80, "offset 49"},
                 {mr_dmm_tri_info(1, 0), "records size"}};
    uint8_t *c = malloc(size);
    assert_non_null(c);
    for (size_t k = 0; k < sizeof cases / sizeof cases[0]; k++) {
        memcpy(c, buf, size);
        c[MR_DMM_HEADER_BYTES + 1] = cases[k].byte;
        mr_le_put_u32(c + size - 4, mr_crc32(c + MR_DMM_HEADER_BYTES, size - 4 - MR_DMM_HEADER_BYTES));
        expect_format(c, size, cases[k].want);
    }
    free(c);
    free(buf);
    mr_dmm_encoded_free(enc);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_record_bytes),     cmocka_unit_test(test_lossless_random),
        cmocka_unit_test(test_lossy_random),     cmocka_unit_test(test_watertight_edges),
        cmocka_unit_test(test_extremes),         cmocka_unit_test(test_pyramid),
        cmocka_unit_test(test_file_roundtrip),   cmocka_unit_test(test_file_corruptions),
        cmocka_unit_test(test_bumpy_sphere),     cmocka_unit_test(test_watertight_mixed_levels),
        cmocka_unit_test(test_level_bytes),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
