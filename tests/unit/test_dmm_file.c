/*
 * test_dmm_file.c - the baked-DMM file and the bake cache
 * (core/kinds/dmm/dmm_file.c, docs/dmm-format.md "Baked DMM file"):
 *  - a real skinned bake (BCN_Epileptic.X, 3 meshes) survives a round trip
 *    through a file bit for bit, and writing is canonical;
 *  - every truncation and every single-bit flip of a small file is refused
 *    with MR_ERR_FORMAT naming a byte offset;
 *  - field corruptions behind a valid checksum (counts, indices, NaN,
 *    joints, sizes, flags) are refused and name the documented offset;
 *  - the writer refuses data its reader would refuse;
 *  - cache keys follow exactly the inputs the bake reads, and a cache file
 *    that does not fit the asset or key is a miss.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <cmocka.h>

#include <dirent.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "../support/bcn_fixture.h"
#include "../support/grid_fixture.h"
#include "asset/asset.h"
#include "kinds/dmm/dmm_file.h"
#include "util/crc32.h"
#include "util/le.h"


/* ---- fixtures */

static char tmp_dir[64];

static int setup(void **state)
{
    (void)state;
    snprintf(tmp_dir, sizeof tmp_dir, "/tmp/mr-dmm-file-XXXXXX");
    return mkdtemp(tmp_dir) ? 0 : -1;
}

static int teardown(void **state)
{
    (void)state;
    char cmd[128];
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", tmp_dir);
    return system(cmd) == 0 ? 0 : -1;
}

/* An n x n height field over [-1, 1]^2 with smooth bumps; with skin, two
 * joints blended along x (slots 2.. unused: joint 0, weight 0). */
static mr_asset *make_field(unsigned n, bool skin)
{
    mr_error err = {0};
    mr_asset *asset = grid_field(n, 0.1f, 5, 4, &err);
    if (!asset)
        fail_msg("asset: %s", err.msg);
    if (skin) {
        mr_mesh *m = &asset->meshes[0];
        m->joint_count = 2;
        m->joint_nodes = calloc(2, sizeof(int));
        m->inverse_bind = malloc(2 * sizeof(mr_mat4));
        m->joints = calloc((size_t)m->vertex_count * MR_MAX_INFLUENCES, sizeof(uint16_t));
        m->weights = calloc((size_t)m->vertex_count * MR_MAX_INFLUENCES, sizeof(float));
        assert_true(m->joint_nodes && m->inverse_bind && m->joints && m->weights);
        m->inverse_bind[0] = m->inverse_bind[1] = mr_mat4_identity();
        for (uint32_t i = 0; i < m->vertex_count; i++) {
            float w = 0.5f + 0.5f * m->positions[i * 3];
            m->joints[i * MR_MAX_INFLUENCES] = 0;
            m->joints[i * MR_MAX_INFLUENCES + 1] = 1;
            m->weights[i * MR_MAX_INFLUENCES] = 1 - w;
            m->weights[i * MR_MAX_INFLUENCES + 1] = w;
        }
    }
    return asset;
}

static mr_dmm_bake_params params(unsigned level, float ratio)
{
    mr_dmm_bake_params bp = mr_dmm_bake_params_default();
    bp.level = level;
    bp.target_ratio = ratio;
    return bp;
}

/* Bakes and encodes every mesh of asset into a file struct that owns them;
 * meshes without triangles stay empty. */
static mr_dmm_file *bake_all(const mr_asset *a, const mr_dmm_bake_params *bp)
{
    mr_dmm_file *f = calloc(1, sizeof *f);
    assert_non_null(f);
    f->level = bp->level;
    mr_dmm_default_bits(f->bits);
    for (unsigned l = bp->level + 1; l <= MR_UMESH_MAX_LEVEL; l++)
        f->bits[l] = 0;
    memset(f->key, 0xA5, sizeof f->key);
    f->mesh_count = (uint32_t)a->mesh_count;
    f->meshes = calloc(a->mesh_count, sizeof *f->meshes);
    assert_non_null(f->meshes);
    uint8_t bits[MR_UMESH_MAX_LEVEL + 1];
    mr_dmm_default_bits(bits);
    mr_error err = {0};
    for (size_t i = 0; i < a->mesh_count; i++) {
        mr_dmm_file_mesh *m = &f->meshes[i];
        m->source_vertex_count = a->meshes[i].vertex_count;
        m->source_joint_count = a->meshes[i].joint_count;
        if (a->meshes[i].triangle_count == 0)
            continue;
        if (mr_dmm_bake_run(&a->meshes[i], bp, &m->bake, &err) < 0)
            fail_msg("bake mesh %zu: %s", i, err.msg);
        if (mr_dmm_encode(bp->level, bits, m->bake->base_triangle_count, m->bake->tri_info, m->bake->displacements,
                          &m->encoded, NULL, &err) < 0)
            fail_msg("encode mesh %zu: %s", i, err.msg);
    }
    return f;
}

static void write_buf(const mr_dmm_file *f, uint8_t **buf, size_t *size)
{
    mr_error err = {0};
    if (mr_dmm_file_write(f, buf, size, &err) < 0)
        fail_msg("write: %s", err.msg);
}

static void assert_same_bake(const mr_dmm_file_mesh *a, const mr_dmm_file_mesh *b)
{
    assert_int_equal(a->source_vertex_count, b->source_vertex_count);
    assert_int_equal(a->source_joint_count, b->source_joint_count);
    assert_int_equal(a->bake == NULL, b->bake == NULL);
    if (!a->bake)
        return;
    const mr_dmm_bake *x = a->bake, *y = b->bake;
    uint32_t nv = x->base_vertex_count, nt = x->base_triangle_count;
    assert_int_equal(x->level, y->level);
    assert_int_equal(x->micro_vertex_count, y->micro_vertex_count);
    assert_int_equal(nv, y->base_vertex_count);
    assert_int_equal(nt, y->base_triangle_count);
    assert_memory_equal(x->base_positions, y->base_positions, (size_t)nv * 3 * sizeof(float));
    assert_memory_equal(x->base_directions, y->base_directions, (size_t)nv * 3 * sizeof(float));
    assert_memory_equal(x->base_indices, y->base_indices, (size_t)nt * 3 * sizeof(uint32_t));
    assert_memory_equal(x->base_source, y->base_source, (size_t)nv * sizeof(uint32_t));
    assert_int_equal(x->joints == NULL, y->joints == NULL);
    if (x->joints) {
        assert_memory_equal(x->joints, y->joints, (size_t)nv * MR_MAX_INFLUENCES * 2);
        assert_memory_equal(x->weights, y->weights, (size_t)nv * MR_MAX_INFLUENCES * 4);
    }
    assert_null(y->displacements); /* not stored: the encoding is what renders */
    assert_memory_equal(x->tri_info, y->tri_info, nt);
    assert_int_equal(x->fallback_count, y->fallback_count);
    assert_int_equal(x->sample_count, y->sample_count);
    assert_memory_equal(&x->rms_distance, &y->rms_distance, sizeof(double));
    assert_memory_equal(&x->max_distance, &y->max_distance, sizeof(double));
    assert_memory_equal(&x->simplify_error, &y->simplify_error, sizeof(float));
    const mr_dmm_encoded *e = a->encoded, *g = b->encoded;
    assert_int_equal(e->level, g->level);
    assert_memory_equal(e->bits, g->bits, sizeof e->bits);
    assert_int_equal(e->triangle_count, g->triangle_count);
    assert_int_equal(e->records_bytes, g->records_bytes);
    assert_memory_equal(e->tri_info, g->tri_info, e->triangle_count);
    assert_memory_equal(&e->bias, &g->bias, sizeof(float));
    assert_memory_equal(&e->scale, &g->scale, sizeof(float));
    assert_memory_equal(e->records, g->records, e->records_bytes);
}

static size_t count_files(const char *dir, const char *contains)
{
    DIR *d = opendir(dir);
    assert_non_null(d);
    size_t n = 0;
    for (struct dirent *e; (e = readdir(d));)
        n += e->d_name[0] != '.' && strstr(e->d_name, contains) != NULL;
    closedir(d);
    return n;
}

/* ---- round trip of a real bake */

static void test_round_trip_real_skinned(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    mr_error err = {0};
    assert_true(a->mesh_count >= 2);
    mr_dmm_bake_params bp = params(2, 0.25f);
    mr_dmm_file *f = bake_all(a, &bp);
    bool skinned = false;
    for (uint32_t i = 0; i < f->mesh_count; i++)
        skinned |= f->meshes[i].bake && f->meshes[i].bake->joints;
    assert_true(skinned); /* the joints and weights path is exercised */

    char path[128];
    snprintf(path, sizeof path, "%s/bcn.dmm", tmp_dir);
    assert_int_equal(mr_dmm_file_write_path(f, path, &err), MR_OK);
    /* the temporary file was renamed away; the file is readable by others */
    assert_int_equal(count_files(tmp_dir, ".tmp"), 0);
    struct stat st;
    assert_int_equal(stat(path, &st), 0);
    assert_int_equal(st.st_mode & 0777, 0644);

    mr_dmm_file *r = NULL;
    if (mr_dmm_file_read_path(path, &r, &err) < 0)
        fail_msg("read: %s", err.msg);
    assert_int_equal(r->level, f->level);
    assert_memory_equal(r->bits, f->bits, sizeof f->bits);
    assert_memory_equal(r->key, f->key, sizeof f->key);
    assert_int_equal(r->mesh_count, f->mesh_count);
    for (uint32_t i = 0; i < f->mesh_count; i++)
        assert_same_bake(&f->meshes[i], &r->meshes[i]);

    /* canonical: what was read writes back to the same bytes */
    uint8_t *b1 = NULL, *b2 = NULL;
    size_t s1 = 0, s2 = 0;
    write_buf(f, &b1, &s1);
    write_buf(r, &b2, &s2);
    assert_int_equal(s1, s2);
    assert_int_equal(s1, (size_t)st.st_size);
    assert_memory_equal(b1, b2, s1);
    print_message("BCN_Epileptic level 2: %u meshes, %zu bytes\n", f->mesh_count, s1);
    free(b1);
    free(b2);
    mr_dmm_file_free(r);
    mr_dmm_file_free(f);
    mr_asset_free(a);
}

/* ---- a small file: one skinned mesh, one without triangles */

static mr_dmm_file *small_file(mr_asset **asset_out)
{
    mr_asset *a = make_field(5, true);
    mr_dmm_bake_params bp = params(1, 0.5f);
    mr_dmm_file *f = bake_all(a, &bp);
    /* a second mesh section without a DMM (an asset mesh without triangles) */
    mr_dmm_file_mesh *m = realloc(f->meshes, 2 * sizeof *m);
    assert_non_null(m);
    f->meshes = m;
    f->meshes[1] = (mr_dmm_file_mesh){.source_vertex_count = 7, .source_joint_count = 0};
    f->mesh_count = 2;
    assert_non_null(f->meshes[0].bake->joints);
    if (asset_out)
        *asset_out = a;
    else
        mr_asset_free(a);
    return f;
}

static void expect_format(const uint8_t *buf, size_t size, const char *what)
{
    mr_dmm_file *r = NULL;
    mr_error err = {0};
    int rc = mr_dmm_file_read(buf, size, &r, &err);
    if (rc != MR_ERR_FORMAT)
        fail_msg("%s: got %s (%s)", what, mr_err_name(rc), err.msg);
    assert_null(r);
    if (!strstr(err.msg, "byte offset"))
        fail_msg("%s: message names no offset: %s", what, err.msg);
}

static void test_truncations_and_bit_flips(void **state)
{
    (void)state;
    mr_dmm_file *f = small_file(NULL);
    uint8_t *buf = NULL;
    size_t size = 0;
    write_buf(f, &buf, &size);
    print_message("small file: %zu bytes\n", size);
    mr_dmm_file *r = NULL;
    mr_error err = {0};
    assert_int_equal(mr_dmm_file_read(buf, size, &r, &err), MR_OK);
    assert_null(r->meshes[1].bake);
    assert_null(r->meshes[1].encoded);
    assert_same_bake(&f->meshes[0], &r->meshes[0]);
    mr_dmm_file_free(r);

    char what[64];
    for (size_t n = 0; n < size; n++) {
        snprintf(what, sizeof what, "truncated to %zu", n);
        expect_format(buf, n, what);
    }
    uint8_t *longer = malloc(size + 1);
    assert_non_null(longer);
    memcpy(longer, buf, size);
    longer[size] = 0;
    expect_format(longer, size + 1, "one trailing byte");
    free(longer);
    /* every byte is under a CRC-32 (or is one), which detects any single-bit
     * error: every flip of every bit must be refused */
    for (size_t i = 0; i < size; i++)
        for (int bit = 0; bit < 8; bit++) {
            buf[i] ^= (uint8_t)(1u << bit);
            snprintf(what, sizeof what, "bit %d of byte %zu flipped", bit, i);
            expect_format(buf, size, what);
            buf[i] ^= (uint8_t)(1u << bit);
        }
    free(buf);
    mr_dmm_file_free(f);
}

/* ---- corruptions behind valid checksums */

/* Offsets of the small file's sections, from the documented layout. */
typedef struct layout {
    size_t mesh0, arrays0, arrays_crc0, block0, mesh1;
    uint32_t nv, nt;
} layout;

static layout layout_of(const uint8_t *buf)
{
    layout l;
    l.mesh0 = 68;
    l.nv = mr_le_get_u32(buf + l.mesh0 + 20);
    l.nt = mr_le_get_u32(buf + l.mesh0 + 24);
    l.arrays0 = l.mesh0 + 96;
    uint64_t arrays = mr_le_get_u32(buf + l.mesh0 + 72), block = mr_le_get_u32(buf + l.mesh0 + 80);
    assert_int_equal(arrays, (uint64_t)l.nv * (28 + 48) + (uint64_t)l.nt * 12);
    l.arrays_crc0 = l.arrays0 + arrays;
    l.block0 = l.arrays_crc0 + 4;
    l.mesh1 = l.block0 + block;
    return l;
}

static void fix_crcs(uint8_t *buf, const layout *l)
{
    mr_le_put_u32(buf + 64, mr_crc32(buf, 64));
    mr_le_put_u32(buf + l->mesh0 + 92, mr_crc32(buf + l->mesh0, 92));
    mr_le_put_u32(buf + l->arrays_crc0, mr_crc32(buf + l->arrays0, l->arrays_crc0 - l->arrays0));
    mr_le_put_u32(buf + l->mesh1 + 92, mr_crc32(buf + l->mesh1, 92));
}

/* Sets the u32 at off to v, fixes every checksum, expects MR_ERR_FORMAT with
 * "byte offset <want>" in the message. */
static void corrupt(const uint8_t *good, size_t size, size_t off, uint32_t v, size_t want,
                    const char *what)
{
    uint8_t *buf = malloc(size);
    assert_non_null(buf);
    memcpy(buf, good, size);
    layout l = layout_of(good);
    mr_le_put_u32(buf + off, v);
    fix_crcs(buf, &l);
    mr_dmm_file *r = NULL;
    mr_error err = {0};
    int rc = mr_dmm_file_read(buf, size, &r, &err);
    char needle[48];
    snprintf(needle, sizeof needle, "byte offset %zu", want);
    if (rc != MR_ERR_FORMAT || !strstr(err.msg, needle))
        fail_msg("%s: got %s '%s', want MR_ERR_FORMAT naming %s", what, mr_err_name(rc), err.msg,
                 needle);
    assert_null(r);
    free(buf);
}

static void test_field_corruptions(void **state)
{
    (void)state;
    mr_dmm_file *f = small_file(NULL);
    uint8_t *g = NULL;
    size_t n = 0;
    write_buf(f, &g, &n);
    layout l = layout_of(g);
    /* the checksum fixer itself is right: an untouched copy reads */
    uint8_t *copy = malloc(n);
    assert_non_null(copy);
    memcpy(copy, g, n);
    fix_crcs(copy, &l);
    assert_memory_equal(copy, g, n);
    free(copy);
    size_t m0 = l.mesh0, m1 = l.mesh1;
    uint32_t nv = l.nv, nt = l.nt;

    corrupt(g, n, 16, 0, 16, "mesh count 0");
    corrupt(g, n, 16, 3, n, "a third mesh the bytes do not hold: truncated");
    corrupt(g, n, 16, 0xFFFFFFFFu, 16, "huge mesh count");
    corrupt(g, n, 20, 6, 20, "level 6");
    corrupt(g, n, 24, 0, 24, "value width 0");
    corrupt(g, n, m0 + 4, 1, m0 + 4, "mesh index");
    corrupt(g, n, m0 + 8, 4, m0 + 8, "unknown flag");
    corrupt(g, n, m0 + 8, 2, m0 + 8, "skinned without a bake");
    corrupt(g, n, m0 + 28, 1, m0 + 28, "reserved field");
    corrupt(g, n, m0 + 12, MR_MAX_ASSET_VERTICES + 1, m0 + 12, "source vertex count over cap");
    corrupt(g, n, m0 + 12, nv - 1, m0 + 20, "more base than source vertices");
    corrupt(g, n, m0 + 16, 0, m0 + 8, "skinned but no source joints");
    corrupt(g, n, m0 + 20, 2, m0 + 20, "base vertex count 2");
    corrupt(g, n, m0 + 20, nv + 1, m0 + 72, "base vertex count vs array size");
    corrupt(g, n, m0 + 24, 0, m0 + 24, "base triangle count 0");
    corrupt(g, n, m0 + 24, MR_DMM_MAX_TRIANGLES + 1, m0 + 24, "triangle count over cap");
    corrupt(g, n, m0 + 24, nt + 1, m0 + 72, "triangle count vs array size");
    corrupt(g, n, m0 + 32, 0xFFFFFFFFu, m0 + 32, "fallback count beyond micro-vertices");
    corrupt(g, n, m0 + 40, 1, m0 + 40, "sample count");
    corrupt(g, n, m0 + 52, 0x7FF80000u, m0 + 48, "NaN rms distance");
    corrupt(g, n, m0 + 60, 0xFFF00000u, m0 + 56, "-inf max distance");
    corrupt(g, n, m0 + 64, 0x7FC00000u, m0 + 64, "NaN simplify error");
    corrupt(g, n, m0 + 72, 4, m0 + 72, "array size");
    corrupt(g, n, m0 + 76, 1, m0 + 72, "array size, high word");
    corrupt(g, n, m0 + 80, 52, m0 + 80, "block size");
    /* arrays: positions, directions, indices, sources, joints, weights */
    size_t pos = l.arrays0, dir = pos + nv * 12, idx = dir + nv * 12, src = idx + nt * 12;
    size_t joints = src + nv * 4, weights = joints + nv * MR_MAX_INFLUENCES * 2;
    corrupt(g, n, pos + 8, 0x7FC00000u, pos + 8, "NaN position");
    corrupt(g, n, dir + 12 * (nv - 1), 0x7F800000u, dir + 12 * (nv - 1), "inf direction");
    corrupt(g, n, idx + 4, nv, idx + 4, "index = vertex count");
    corrupt(g, n, idx + 12 * (nt - 1) + 8, 0xFFFFFFFFu, idx + 12 * (nt - 1) + 8, "huge index");
    corrupt(g, n, src, 25, src, "source vertex beyond the 25 of a 5x5 field");
    /* joint 1 of vertex 0 has a nonzero weight unless x = -1 maps it to 0:
     * slot 0 (weight 1 - w) of the vertex with the largest x is used */
    uint32_t vmax = 0;
    for (uint32_t v = 0; v < nv; v++)
        if (f->meshes[0].bake->weights[v * MR_MAX_INFLUENCES] != 0) {
            vmax = v;
            break;
        }
    size_t jslot = joints + (size_t)vmax * MR_MAX_INFLUENCES * 2; /* u16; and its neighbour */
    uint32_t pair = mr_le_get_u32(g + jslot);
    corrupt(g, n, jslot, (pair & 0xFFFF0000u) | 2u, jslot, "used joint 2 of 2");
    /* an unused slot (weight 0) may name any joint: not an error */
    {
        uint8_t *buf = malloc(n);
        assert_non_null(buf);
        memcpy(buf, g, n);
        size_t unused = joints + (size_t)vmax * MR_MAX_INFLUENCES * 2 + 6; /* slots 3, 4 */
        mr_le_put_u32(buf + unused, 0xFFFFFFFFu);
        fix_crcs(buf, &l);
        mr_dmm_file *r = NULL;
        mr_error err = {0};
        assert_int_equal(mr_dmm_file_read(buf, n, &r, &err), MR_OK);
        mr_dmm_file_free(r);
        free(buf);
    }
    corrupt(g, n, weights + 4, 0x7FC00000u, weights + 4, "NaN weight");
    /* the embedded block: its own checks, offsets relative to it */
    corrupt(g, n, l.block0 + 16, 2, l.block0, "block level vs header");
    /* the empty section must be empty */
    corrupt(g, n, m1 + 20, 3, m1 + 20, "vertices in a mesh without a DMM");
    corrupt(g, n, m1 + 72, 12, m1 + 72, "arrays in a mesh without a DMM");
    free(g);
    mr_dmm_file_free(f);
}

static void test_writer_refuses_what_reader_would(void **state)
{
    (void)state;
    mr_dmm_file *f = small_file(NULL);
    mr_dmm_bake *b = f->meshes[0].bake;
    uint8_t *buf = NULL;
    size_t size = 0;
    mr_error err = {0};

    uint32_t saved = b->base_indices[5];
    b->base_indices[5] = b->base_vertex_count;
    assert_int_equal(mr_dmm_file_write(f, &buf, &size, &err), MR_ERR_INVALID);
    assert_null(buf);
    assert_non_null(strstr(err.msg, "base index"));
    b->base_indices[5] = saved;

    float p = b->base_positions[4];
    b->base_positions[4] = NAN;
    assert_int_equal(mr_dmm_file_write(f, &buf, &size, &err), MR_ERR_INVALID);
    b->base_positions[4] = p;

    f->meshes[0].source_vertex_count = 3; /* base vertices cannot outnumber their source */
    assert_int_equal(mr_dmm_file_write(f, &buf, &size, &err), MR_ERR_INVALID);
    f->meshes[0].source_vertex_count = 25;

    f->level = 2; /* the encoding is level 1 */
    assert_int_equal(mr_dmm_file_write(f, &buf, &size, &err), MR_ERR_INVALID);
    f->level = 1;

    mr_dmm_encoded *e = f->meshes[0].encoded;
    f->meshes[0].encoded = NULL;
    assert_int_equal(mr_dmm_file_write(f, &buf, &size, &err), MR_ERR_INVALID);
    f->meshes[0].encoded = e;

    char path[128];
    snprintf(path, sizeof path, "%s/no/such/dir/x.dmm", tmp_dir);
    assert_int_equal(mr_dmm_file_write_path(f, path, &err), MR_ERR_IO);
    assert_int_equal(mr_dmm_file_write(f, &buf, &size, &err), MR_OK);
    free(buf);
    mr_dmm_file_free(f);
}

static void test_read_path_errors(void **state)
{
    (void)state;
    mr_dmm_file *r = NULL;
    mr_error err = {0};
    char path[128];
    snprintf(path, sizeof path, "%s/absent.dmm", tmp_dir);
    assert_int_equal(mr_dmm_file_read_path(path, &r, &err), MR_ERR_IO);
    assert_int_equal(mr_dmm_file_read_path(tmp_dir, &r, &err), MR_ERR_IO); /* a directory */
    snprintf(path, sizeof path, "%s/empty.dmm", tmp_dir);
    FILE *fp = fopen(path, "wb");
    assert_non_null(fp);
    fclose(fp);
    assert_int_equal(mr_dmm_file_read_path(path, &r, &err), MR_ERR_FORMAT);
    assert_non_null(strstr(err.msg, path)); /* names the file */
    assert_null(r);
}

/* ---- the cache */

static void key_of(const mr_asset *a, const mr_dmm_bake_params *bp, uint8_t key[32])
{
    uint8_t bits[MR_UMESH_MAX_LEVEL + 1];
    mr_dmm_default_bits(bits);
    mr_dmm_cache_key(a, bp, bits, key);
}

static void test_cache_key_inputs(void **state)
{
    (void)state;
    mr_asset *a = make_field(6, true);
    mr_dmm_bake_params bp = params(2, 0.3f);
    uint8_t k0[32], k[32];
    key_of(a, &bp, k0);
    key_of(a, &bp, k);
    assert_memory_equal(k0, k, 32);
    /* not inputs of the bake: threads, normals, uvs, names */
    bp.threads = 3;
    a->meshes[0].normals[0] += 1.0f;
    key_of(a, &bp, k);
    assert_memory_equal(k0, k, 32);
    bp.threads = 0;
    /* inputs: each changes the key */
#define CHANGES(stmt, undo)                                                                       \
    do {                                                                                          \
        stmt;                                                                                     \
        key_of(a, &bp, k);                                                                        \
        if (memcmp(k0, k, 32) == 0)                                                               \
            fail_msg("key ignores: %s", #stmt);                                                   \
        undo;                                                                                     \
        key_of(a, &bp, k);                                                                        \
        assert_memory_equal(k0, k, 32);                                                           \
    } while (0)
    CHANGES(bp.level = 3, bp.level = 2);
    CHANGES(bp.target_ratio = 0.31f, bp.target_ratio = 0.3f);
    CHANGES(bp.target_triangles = 10, bp.target_triangles = 0);
    CHANGES(bp.max_error = 0.01f, bp.max_error = 0);
    CHANGES(bp.max_displacement = 1, bp.max_displacement = 0);
    float *p = a->meshes[0].positions;
    uint32_t bitsof;
    memcpy(&bitsof, &p[7], 4);
    CHANGES(bitsof ^= 1; memcpy(&p[7], &bitsof, 4), bitsof ^= 1; memcpy(&p[7], &bitsof, 4));
    uint32_t *ix = a->meshes[0].indices;
    CHANGES((ix[0] ^= ix[1], ix[1] ^= ix[0], ix[0] ^= ix[1]),
            (ix[0] ^= ix[1], ix[1] ^= ix[0], ix[0] ^= ix[1]));
    CHANGES(a->meshes[0].joints[10] = 1, a->meshes[0].joints[10] = 0); /* an unused slot: still an input */
    CHANGES(a->meshes[0].weights[0] += 0.25f, a->meshes[0].weights[0] -= 0.25f);
    CHANGES(a->meshes[0].joint_count = 3, a->meshes[0].joint_count = 2);
#undef CHANGES
    /* and the encoding widths */
    uint8_t bits[MR_UMESH_MAX_LEVEL + 1];
    mr_dmm_default_bits(bits);
    bits[2] = 9;
    mr_dmm_cache_key(a, &bp, bits, k);
    assert_true(memcmp(k0, k, 32) != 0);

    char *path = NULL;
    mr_error err = {0};
    assert_int_equal(mr_derived_path("/x/y", k0, mr_dmm_file_format.ext, &path, &err), MR_OK);
    assert_int_equal(strlen(path), strlen("/x/y/") + 64 + strlen(".dmm"));
    assert_int_equal(strncmp(path, "/x/y/", 5), 0);
    for (int i = 0; i < 64; i++)
        assert_non_null(strchr("0123456789abcdef", path[5 + i]));
    assert_string_equal(path + 69, ".dmm");
    free(path);
    mr_asset_free(a);
}

static void test_cache_store_and_load(void **state)
{
    (void)state;
    mr_asset *a = make_field(6, true);
    mr_dmm_bake_params bp = params(2, 0.3f);
    mr_dmm_file *f = bake_all(a, &bp);
    uint8_t key[32];
    key_of(a, &bp, key);
    uint8_t bits[MR_UMESH_MAX_LEVEL + 1];
    mr_dmm_default_bits(bits);
    char dir[128], *path = NULL;
    mr_error err = {0};
    snprintf(dir, sizeof dir, "%s/cache/a/b", tmp_dir); /* created with its parents */
    assert_int_equal(mr_derived_path(dir, key, mr_dmm_file_format.ext, &path, &err), MR_OK);

    mr_dmm_bake *bakes[1] = {NULL};
    mr_dmm_encoded *enc[1] = {NULL};
    assert_int_equal(mr_dmm_cache_load(path, key, a, 2, bits, bakes, enc, &err), MR_ERR_IO);
    mr_dmm_bake *src_b[1] = {f->meshes[0].bake};
    mr_dmm_encoded *src_e[1] = {f->meshes[0].encoded};
    if (mr_dmm_cache_store(path, key, a, 2, bits, src_b, src_e, &err) < 0)
        fail_msg("store: %s", err.msg);
    struct stat st;
    assert_int_equal(stat(dir, &st), 0);
    assert_int_equal(st.st_mode & 0777, 0755);

    if (mr_dmm_cache_load(path, key, a, 2, bits, bakes, enc, &err) < 0)
        fail_msg("load: %s", err.msg);
    mr_dmm_file_mesh got = {.source_vertex_count = 36, .source_joint_count = 2,
                            .bake = bakes[0], .encoded = enc[0]};
    assert_same_bake(&f->meshes[0], &got);
    mr_dmm_bake_free(bakes[0]);
    mr_dmm_encoded_free(enc[0]);

    /* misses: another key, level or widths, or an asset it does not fit */
    uint8_t other[32];
    memcpy(other, key, 32);
    other[31] ^= 1;
    assert_int_equal(mr_dmm_cache_load(path, other, a, 2, bits, bakes, enc, &err), MR_ERR_FORMAT);
    assert_null(bakes[0]);
    assert_int_equal(mr_dmm_cache_load(path, key, a, 3, bits, bakes, enc, &err), MR_ERR_FORMAT);
    bits[1] = 12;
    assert_int_equal(mr_dmm_cache_load(path, key, a, 2, bits, bakes, enc, &err), MR_ERR_FORMAT);
    bits[1] = 11;
    mr_asset *moved = make_field(6, true);
    uint32_t s = f->meshes[0].bake->base_source[0];
    moved->meshes[0].positions[s * 3 + 2] += 1.0f;
    assert_int_equal(mr_dmm_cache_load(path, key, moved, 2, bits, bakes, enc, &err), MR_ERR_FORMAT);
    assert_non_null(strstr(err.msg, "base vertex"));
    mr_asset *rigid = make_field(6, false);
    assert_int_equal(mr_dmm_cache_load(path, key, rigid, 2, bits, bakes, enc, &err), MR_ERR_FORMAT);
    mr_asset *bigger = make_field(7, true);
    assert_int_equal(mr_dmm_cache_load(path, key, bigger, 2, bits, bakes, enc, &err), MR_ERR_FORMAT);
    assert_null(bakes[0]);
    assert_null(enc[0]);
    mr_asset_free(moved);
    mr_asset_free(rigid);
    mr_asset_free(bigger);
    free(path);
    mr_dmm_file_free(f);
    mr_asset_free(a);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_round_trip_real_skinned),
        cmocka_unit_test(test_truncations_and_bit_flips),
        cmocka_unit_test(test_field_corruptions),
        cmocka_unit_test(test_writer_refuses_what_reader_would),
        cmocka_unit_test(test_read_path_errors),
        cmocka_unit_test(test_cache_key_inputs),
        cmocka_unit_test(test_cache_store_and_load),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
