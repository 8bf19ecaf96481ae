/*
 * test_svo_file.c - the `.mrsvo` file and the voxelisation cache
 * (core/kinds/svo/svo_file.c, docs/svo-format.md):
 *  - real voxelised octrees (the BCN rig, depths 6-8, surface and solid)
 *    survive a round trip bit for bit, writing is deterministic and
 *    canonical, leaf keys are never stored, and an independent serializer
 *    written here from the document produces the library's exact bytes;
 *  - every truncation and every single-bit flip of a small file is refused
 *    with MR_ERR_FORMAT naming a byte offset;
 *  - crafted files with valid checksums but bad fields or structure are
 *    refused naming the documented offset and field; the writer refuses
 *    what the reader would;
 *  - cache keys follow depth, mode, albedo and the geometry; miss, store,
 *    hit equal to a fresh voxelisation; corrupt, foreign or mismatching
 *    files are misses and get replaced; an unwritable cache falls back.
 * Prints bytes per voxel of the BCN files (measured, never asserted).
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
#include "asset/asset.h"
#include "kinds/svo/svo_build.h"
#include "kinds/svo/svo_file.h"
#include "kinds/svo/voxelize.h"
#include "util/crc32.h"
#include "util/le.h"

/* ---- fixtures */

static char tmp_dir[64];

static int setup(void **state)
{
    (void)state;
    snprintf(tmp_dir, sizeof tmp_dir, "/tmp/mr-svo-file-XXXXXX");
    return mkdtemp(tmp_dir) ? 0 : -1;
}

static int teardown(void **state)
{
    (void)state;
    char cmd[128];
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", tmp_dir);
    return system(cmd) == 0 ? 0 : -1;
}

static size_t count_files(const char *dir, const char *contains)
{
    DIR *d = opendir(dir);
    assert_non_null(d);
    size_t n = 0;
    for (struct dirent *e; (e = readdir(d));)
        if (strstr(e->d_name, contains))
            n++;
    closedir(d);
    return n;
}

static mr_svo *voxelize(const mr_asset *a, unsigned depth, mr_svo_voxelize_mode mode, bool keys)
{
    mr_svo_voxelize_params p = {.depth = depth, .mode = mode, .threads = 2,
                                .keep_leaf_keys = keys};
    mr_svo *s = NULL;
    mr_error err = {0};
    if (mr_svo_voxelize(a, &p, &s, &err) != MR_OK)
        fail_msg("voxelize: %s", err.msg);
    return s;
}

/* Every field and array, bit for bit (leaf_keys aside). */
static void assert_same_svo(const mr_svo *a, const mr_svo *b)
{
    assert_int_equal(a->depth, b->depth);
    assert_memory_equal(&a->origin, &b->origin, sizeof a->origin);
    assert_memory_equal(&a->size, &b->size, sizeof a->size);
    assert_int_equal(a->node_count, b->node_count);
    assert_int_equal(a->leaf_count, b->leaf_count);
    assert_int_equal(a->palette_count, b->palette_count);
    size_t n = a->node_count;
    if (n) {
        assert_memory_equal(a->first_node, b->first_node, n * sizeof *a->first_node);
        assert_memory_equal(a->first_leaf, b->first_leaf, n * sizeof *a->first_leaf);
        assert_memory_equal(a->child_mask, b->child_mask, n);
        assert_memory_equal(a->leaf_mask, b->leaf_mask, n);
    }
    if (a->leaf_count)
        assert_memory_equal(a->leaves, b->leaves, a->leaf_count * sizeof *a->leaves);
    if (a->palette_count)
        assert_memory_equal(a->palette, b->palette, a->palette_count * sizeof *a->palette);
}

static void write_buf(const mr_svo *s, const mr_svo_file_meta *meta, uint8_t **buf, size_t *size)
{
    mr_error err = {0};
    if (mr_svo_file_write_meta(s, meta, buf, size, &err) != MR_OK)
        fail_msg("write: %s", err.msg);
}

static mr_svo *read_buf(const uint8_t *buf, size_t size)
{
    mr_svo *r = NULL;
    mr_error err = {0};
    if (mr_svo_file_read(buf, size, &r, &err) != MR_OK)
        fail_msg("read: %s", err.msg);
    return r;
}

/* ---- an independent serializer, written from docs/svo-format.md (with
 * the shared byte order and CRC helpers, util/le.h and util/crc32.h, which
 * test_util_io checks against the documented bytes and a bit-by-bit CRC) */

/* Offsets of the arrays for counts n, l, pc (the document's table). */
typedef struct offs {
    size_t fn, fl, cm, lm, lv, pal, crc, end;
} offs;

static offs offs_of(uint32_t n, uint32_t l, uint32_t pc)
{
    offs o;
    o.fn = 100;
    o.fl = o.fn + 4 * (size_t)n;
    o.cm = o.fl + 4 * (size_t)n;
    o.lm = o.cm + n;
    o.lv = o.lm + n;
    o.pal = o.lv + 4 * (size_t)l;
    o.crc = o.pal + 16 * (size_t)pc;
    o.end = o.crc + 4;
    return o;
}

static void fix_header_crc(uint8_t *b) { mr_le_put_u32(b + 96, mr_crc32(b, 96)); }

/* Serializes s as the document says, whatever its values. */
static uint8_t *serialize(const mr_svo *s, uint32_t flags, const uint8_t *key, size_t *size)
{
    const uint32_t n = s->node_count, l = s->leaf_count, pc = s->palette_count;
    offs o = offs_of(n, l, pc);
    uint8_t *b = calloc(1, o.end);
    assert_non_null(b);
    memcpy(b, "MRSVO\0\r\n", 8);
    mr_le_put_u32(b + 8, 1);
    mr_le_put_u32(b + 12, 100);
    mr_le_put_u32(b + 16, flags);
    mr_le_put_u32(b + 20, s->depth);
    mr_le_put_f32(b + 24, s->origin.x);
    mr_le_put_f32(b + 28, s->origin.y);
    mr_le_put_f32(b + 32, s->origin.z);
    mr_le_put_f32(b + 36, s->size);
    mr_le_put_u32(b + 40, n);
    mr_le_put_u32(b + 44, l);
    mr_le_put_u32(b + 48, pc);
    uint64_t payload = o.crc - o.fn;
    mr_le_put_u32(b + 56, (uint32_t)payload);
    mr_le_put_u32(b + 60, (uint32_t)(payload >> 32));
    if (key)
        memcpy(b + 64, key, 32);
    fix_header_crc(b);
    for (uint32_t i = 0; i < n; i++) {
        mr_le_put_u32(b + o.fn + 4 * i, s->first_node[i]);
        mr_le_put_u32(b + o.fl + 4 * i, s->first_leaf[i]);
        b[o.cm + i] = s->child_mask[i];
        b[o.lm + i] = s->leaf_mask[i];
    }
    for (uint32_t i = 0; i < l; i++) {
        b[o.lv + 4 * i] = s->leaves[i].normal[0];
        b[o.lv + 4 * i + 1] = s->leaves[i].normal[1];
        mr_le_put_u16(b + o.lv + 4 * i + 2, s->leaves[i].attr);
    }
    for (uint32_t i = 0; i < pc; i++) {
        uint8_t *q = b + o.pal + 16 * i;
        memcpy(q, s->palette[i].albedo, 3);
        q[3] = s->palette[i].mesh;
        for (int k = 0; k < 4; k++) {
            mr_le_put_u16(q + 4 + 2 * k, s->palette[i].joints[k]);
            q[12 + k] = s->palette[i].weights[k];
        }
    }
    mr_le_put_u32(b + o.crc, mr_crc32(b + o.fn, o.crc - o.fn));
    *size = o.end;
    return b;
}

/* ---- round trips of real voxelisations */

static void test_round_trip_bcn(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    static const struct { unsigned depth; mr_svo_voxelize_mode mode; } cases[] = {
        {6, MR_SVO_VOXELIZE_SURFACE}, {7, MR_SVO_VOXELIZE_SURFACE},
        {8, MR_SVO_VOXELIZE_SURFACE}, {7, MR_SVO_VOXELIZE_SOLID}};
    for (size_t c = 0; c < sizeof cases / sizeof *cases; c++) {
        mr_svo *s = voxelize(a, cases[c].depth, cases[c].mode, true);
        assert_non_null(s->leaf_keys);
        mr_svo_file_meta meta = {.flags = MR_SVO_FILE_VOXELIZED |
                                          (cases[c].mode == MR_SVO_VOXELIZE_SOLID ? MR_SVO_FILE_SOLID : 0)};
        for (unsigned i = 0; i < MR_DERIVED_KEY_BYTES; i++)
            meta.key[i] = (uint8_t)(i * 7 + c);
        uint8_t *b1 = NULL, *b2 = NULL, *b3 = NULL;
        size_t s1 = 0, s2 = 0, s3 = 0;
        write_buf(s, &meta, &b1, &s1);
        /* the documented size, and the document's own serialization */
        assert_int_equal(s1, 104 + 10 * (size_t)s->node_count + 4 * (size_t)s->leaf_count +
                                 16 * (size_t)s->palette_count);
        size_t sd = 0;
        uint8_t *bd = serialize(s, meta.flags, meta.key, &sd);
        assert_int_equal(sd, s1);
        assert_memory_equal(bd, b1, s1);
        free(bd);
        /* deterministic: the same octree writes the same bytes again, with
         * or without leaf keys (never stored) */
        write_buf(s, &meta, &b2, &s2);
        assert_int_equal(s1, s2);
        assert_memory_equal(b1, b2, s1);
        mr_svo_drop_leaf_keys(s);
        free(b2);
        write_buf(s, &meta, &b2, &s2);
        assert_memory_equal(b1, b2, s1);

        mr_svo *r = NULL;
        mr_svo_file_meta back;
        mr_error err = {0};
        if (mr_svo_file_read_meta(b1, s1, &r, &back, &err) != MR_OK)
            fail_msg("read: %s", err.msg);
        assert_same_svo(s, r);
        assert_null(r->leaf_keys);
        assert_int_equal(back.flags, meta.flags);
        assert_memory_equal(back.key, meta.key, MR_DERIVED_KEY_BYTES);
        /* canonical: what was read writes the same bytes */
        write_buf(r, &meta, &b3, &s3);
        assert_int_equal(s3, s1);
        assert_memory_equal(b3, b1, s1);
        print_message("BCN %s depth %u: %u leaves, %u nodes, %u palette entries: %zu bytes, "
                      "%.2f bytes per voxel\n",
                      cases[c].mode == MR_SVO_VOXELIZE_SOLID ? "solid" : "surface",
                      cases[c].depth, s->leaf_count, s->node_count, s->palette_count, s1,
                      (double)s1 / s->leaf_count);
        free(b1);
        free(b2);
        free(b3);
        mr_svo_voxelize_free(r);
        mr_svo_voxelize_free(s);
    }

    /* through a file: atomic write leaves no temporary, mode 0644 */
    mr_svo *s = voxelize(a, 6, MR_SVO_VOXELIZE_SURFACE, false);
    char path[128];
    snprintf(path, sizeof path, "%s/bcn.mrsvo", tmp_dir);
    mr_error err = {0};
    assert_int_equal(mr_svo_file_write_path(s, path, &err), MR_OK);
    assert_int_equal(mr_svo_file_write_path(s, path, &err), MR_OK); /* over an existing file */
    assert_int_equal(count_files(tmp_dir, ".tmp"), 0);
    struct stat st;
    assert_int_equal(stat(path, &st), 0);
    assert_int_equal(st.st_mode & 0777, 0644);
    mr_svo *r = NULL;
    if (mr_svo_file_read_path(path, &r, &err) != MR_OK)
        fail_msg("read %s: %s", path, err.msg);
    assert_same_svo(s, r);
    mr_svo_voxelize_free(r);
    mr_svo_voxelize_free(s);
    mr_asset_free(a);
}

/* ---- a small octree with leaves at three levels and a skinned palette */

static mr_svo *small_svo(void)
{
    /* depth 3: a level-1 leaf (child 0 of the root), a level-2 leaf and
     * finest leaves under child 1, finest and level-2 leaves under child 7 */
    static const mr_svo_key keys[] = {{0, 1},   {64, 2},  {73, 3},  {75, 3},
                                      {127, 3}, {448, 3}, {456, 2}, {511, 3}};
    const size_t n = sizeof keys / sizeof *keys;
    const mr_svo_attr pal[3] = {
        {{204, 204, 204}, 0, {0, 0, 0, 0}, {0, 0, 0, 0}},
        {{10, 20, 30}, 1, {3, 1, 0, 0}, {200, 55, 0, 0}},
        {{255, 0, 0}, 0, {0, 0, 0, 0}, {0, 0, 0, 0}},
    };
    mr_svo_leaf leaves[8];
    for (size_t i = 0; i < n; i++) {
        mr_svo_normal_encode(mr_v3((float)i - 3.5f, 1.0f, (float)(i % 3) - 1.0f), leaves[i].normal);
        leaves[i].attr = (uint16_t)(i % 3);
    }
    mr_svo *s = calloc(1, sizeof *s);
    assert_non_null(s);
    mr_error err = {0};
    if (mr_svo_build(keys, leaves, n, 3, mr_v3(-1.5f, 0.25f, 2.0f), 3.0f, pal, 3, 1, s, &err) != MR_OK)
        fail_msg("build: %s", err.msg);
    mr_svo_drop_leaf_keys(s);
    return s;
}

static void expect_format(const uint8_t *buf, size_t size, const char *what)
{
    mr_svo *r = NULL;
    mr_error err = {0};
    int rc = mr_svo_file_read(buf, size, &r, &err);
    if (rc != MR_ERR_FORMAT)
        fail_msg("%s: got %s (%s)", what, mr_err_name(rc), err.msg);
    assert_null(r);
    if (!strstr(err.msg, "byte offset"))
        fail_msg("%s: message names no offset: %s", what, err.msg);
}

static void test_truncations_and_bit_flips(void **state)
{
    (void)state;
    mr_svo *s = small_svo();
    uint8_t *buf = NULL;
    size_t size = 0;
    write_buf(s, NULL, &buf, &size);
    print_message("small file: %u nodes, %u leaves, %zu bytes\n", s->node_count, s->leaf_count,
                  size);
    mr_svo *r = read_buf(buf, size);
    assert_same_svo(s, r);
    mr_svo_voxelize_free(r);

    char what[64];
    for (size_t n = 0; n < size; n++) {
        snprintf(what, sizeof what, "truncated to %zu", n);
        expect_format(buf, n, what);
    }
    uint8_t *longer = calloc(1, size + 1);
    assert_non_null(longer);
    memcpy(longer, buf, size);
    expect_format(longer, size + 1, "one trailing byte");
    free(longer);
    /* every byte is under a CRC-32 (or is one), which detects every
     * single-bit error */
    for (size_t i = 0; i < size; i++)
        for (int bit = 0; bit < 8; bit++) {
            buf[i] ^= (uint8_t)(1u << bit);
            snprintf(what, sizeof what, "bit %d of byte %zu flipped", bit, i);
            expect_format(buf, size, what);
            buf[i] ^= (uint8_t)(1u << bit);
        }
    /* header and payload flips name their own checksum */
    mr_error err = {0};
    buf[41] ^= 0x10;
    assert_int_equal(mr_svo_file_read(buf, size, &r, &err), MR_ERR_FORMAT);
    assert_non_null(strstr(err.msg, "header checksum mismatch at byte offset 96"));
    buf[41] ^= 0x10;
    buf[size - 10] ^= 0x01;
    assert_int_equal(mr_svo_file_read(buf, size, &r, &err), MR_ERR_FORMAT);
    char needle[64];
    snprintf(needle, sizeof needle, "payload checksum mismatch at byte offset %zu", size - 4);
    assert_non_null(strstr(err.msg, needle));
    free(buf);
    mr_svo_voxelize_free(s);
}

/* ---- valid checksums, bad content */

/* Whether msg says "byte offset <want>" (the whole number). */
static bool names_offset(const char *msg, size_t want)
{
    char needle[48];
    int n = snprintf(needle, sizeof needle, "byte offset %zu", want);
    for (const char *at = msg; (at = strstr(at, needle)); at++)
        if (at[n] < '0' || at[n] > '9')
            return true;
    return false;
}

/* Reads buf expecting MR_ERR_FORMAT whose message names "byte offset
 * <want>" and contains field. */
static void expect_bad(const uint8_t *buf, size_t size, size_t want, const char *field,
                       const char *what)
{
    mr_svo *r = NULL;
    mr_error err = {0};
    int rc = mr_svo_file_read(buf, size, &r, &err);
    char needle[48];
    snprintf(needle, sizeof needle, "byte offset %zu", want);
    if (rc != MR_ERR_FORMAT || !names_offset(err.msg, want) || !strstr(err.msg, field))
        fail_msg("%s: got %s '%s', want MR_ERR_FORMAT naming %s and '%s'", what, mr_err_name(rc),
                 err.msg, needle, field);
    assert_null(r);
}

/* A deep copy whose arrays the tests may change (and grow by one entry). */
static mr_svo copy_svo(const mr_svo *s)
{
    mr_svo c = *s;
    size_t n = s->node_count + 1, l = s->leaf_count + 1, p = s->palette_count + 1;
    c.first_node = calloc(n, 4);
    c.first_leaf = calloc(n, 4);
    c.child_mask = calloc(n, 1);
    c.leaf_mask = calloc(n, 1);
    c.leaves = calloc(l, sizeof *c.leaves);
    c.palette = calloc(p, sizeof *c.palette);
    c.leaf_keys = NULL;
    assert_true(c.first_node && c.first_leaf && c.child_mask && c.leaf_mask && c.leaves && c.palette);
    memcpy(c.first_node, s->first_node, s->node_count * 4);
    memcpy(c.first_leaf, s->first_leaf, s->node_count * 4);
    memcpy(c.child_mask, s->child_mask, s->node_count);
    memcpy(c.leaf_mask, s->leaf_mask, s->node_count);
    memcpy(c.leaves, s->leaves, s->leaf_count * sizeof *c.leaves);
    memcpy(c.palette, s->palette, s->palette_count * sizeof *c.palette);
    return c;
}

/* Serializes c with the test's own writer (valid checksums), expects the
 * reader to refuse it naming want and field, and the library's writer to
 * refuse c as MR_ERR_INVALID; frees c. */
static void refuse(mr_svo *c, size_t want, const char *field, const char *what)
{
    size_t size = 0;
    uint8_t *b = serialize(c, 0, NULL, &size);
    expect_bad(b, size, want, field, what);
    free(b);
    uint8_t *out = NULL;
    mr_error err = {0};
    int rc = mr_svo_file_write(c, &out, &size, &err);
    if (rc != MR_ERR_INVALID)
        fail_msg("%s: writer gave %s (%s)", what, mr_err_name(rc), err.msg);
    assert_null(out);
    mr_svo_free(c);
}

/* Level of every node (breadth-first layout: parents first). */
static void node_levels(const mr_svo *s, unsigned *level)
{
    level[0] = 0;
    for (uint32_t i = 0; i < s->node_count; i++) {
        unsigned inner = (unsigned)__builtin_popcount(s->child_mask[i] & ~s->leaf_mask[i]);
        for (unsigned k = 0; k < inner; k++)
            level[s->first_node[i] + k] = level[i] + 1;
    }
}

static void test_crafted_structure(void **state)
{
    (void)state;
    mr_svo *s = small_svo();
    const uint32_t N = s->node_count, L = s->leaf_count, P = s->palette_count;
    const offs o = offs_of(N, L, P);
    assert_true(N >= 5);
    /* the document's serialization of the untouched octree reads back */
    {
        size_t size = 0;
        uint8_t *b = serialize(s, 0, NULL, &size);
        mr_svo *r = read_buf(b, size);
        assert_same_svo(s, r);
        mr_svo_voxelize_free(r);
        free(b);
    }
    unsigned level[16];
    assert_true(N <= 16);
    node_levels(s, level);
    mr_svo c;

    /* a leaf bit outside the child bits */
    c = copy_svo(s);
    unsigned free_bit = 0;
    while (c.child_mask[0] >> free_bit & 1)
        free_bit++;
    c.leaf_mask[0] |= (uint8_t)(1u << free_bit);
    refuse(&c, o.lm, "leaf_mask", "leaf bit outside child_mask");
    /* a node without children */
    c = copy_svo(s);
    c.child_mask[3] = 0;
    c.leaf_mask[3] = 0;
    refuse(&c, o.cm + 3, "child_mask", "child_mask 0");
    /* first_leaf out of range, and off by one */
    c = copy_svo(s);
    c.first_leaf[N - 1] = 0xFFFFFFFFu;
    refuse(&c, o.fl + 4 * (N - 1), "first_leaf", "first_leaf far out of range");
    c = copy_svo(s);
    c.first_leaf[2] += 1;
    refuse(&c, o.fl + 8, "first_leaf", "first_leaf off by one");
    /* first_node not the breadth-first numbering (a child before its parent) */
    c = copy_svo(s);
    c.first_node[0] = 0;
    refuse(&c, o.fn, "first_node", "root as its own child");
    /* a palette index out of range */
    c = copy_svo(s);
    c.leaves[5].attr = (uint16_t)P;
    refuse(&c, o.lv + 5 * 4 + 2, "palette index", "palette index = palette_count");
    /* palette weights that do not sum to 255 */
    c = copy_svo(s);
    c.palette[1].weights[1] = 54;
    refuse(&c, o.pal + 16 + 12, "weights", "weights sum 254");
    /* an interior child at the finest level: a level-2 node (depth 3) whose
     * leaf children are made interior */
    uint32_t deep = 0;
    while (deep < N && !(level[deep] == 2 && s->leaf_mask[deep]))
        deep++;
    assert_true(deep < N);
    c = copy_svo(s);
    c.leaf_mask[deep] = 0;
    refuse(&c, o.cm + deep, "finest level", "interior child at the finest level");
    /* a node no node points at: one more node after the tree */
    c = copy_svo(s);
    c.node_count = N + 1;
    c.leaf_count = L + 1;
    c.child_mask[N] = 1;
    c.leaf_mask[N] = 1;
    c.first_node[N] = N;
    c.first_leaf[N] = L;
    refuse(&c, 40, "no node's child", "unreachable node");
    /* one leaf more than the nodes name */
    c = copy_svo(s);
    c.leaf_count = L + 1;
    refuse(&c, 44, "leaf_count", "unreferenced leaf");
    /* one node less: its parent's children run past node_count */
    c = copy_svo(s);
    c.node_count = N - 1;
    uint32_t parent = 0;
    for (uint32_t i = 0; i < N; i++) {
        unsigned inner = (unsigned)__builtin_popcount(s->child_mask[i] & ~s->leaf_mask[i]);
        if (inner && s->first_node[i] <= N - 1 && N - 1 < s->first_node[i] + inner)
            parent = i;
    }
    refuse(&c, offs_of(N - 1, L, P).fn + 4 * parent, "first_node", "child beyond node_count");
    /* leaves without nodes: only a root leaf can exist */
    c = copy_svo(s);
    c.node_count = 0;
    c.leaf_count = 2;
    refuse(&c, 44, "leaf_count", "two leaves, no nodes");
    /* header fields */
    c = copy_svo(s);
    c.depth = 0;
    refuse(&c, 20, "depth", "depth 0");
    c = copy_svo(s);
    c.depth = 22;
    refuse(&c, 20, "depth", "depth 22");
    c = copy_svo(s);
    c.size = NAN;
    refuse(&c, 36, "size", "size NaN");
    c = copy_svo(s);
    c.size = 0.0f;
    refuse(&c, 36, "size", "size 0");
    c = copy_svo(s);
    c.size = -INFINITY;
    refuse(&c, 36, "size", "size -inf");
    c = copy_svo(s);
    c.origin.y = INFINITY;
    refuse(&c, 28, "origin.y", "origin inf");
    c = copy_svo(s);
    c.palette_count = 0;
    refuse(&c, o.lv + 2, "palette index", "leaves without a palette");

    /* header bytes edited directly, header CRC fixed */
    size_t size = 0;
    uint8_t *g = serialize(s, 0, NULL, &size);
    static const struct { size_t at; uint32_t v; size_t want; const char *field; } hdr[] = {
        {8, 2, 8, "version"},
        {12, 96, 12, "header_bytes"},
        {16, 4, 16, "flags"},
        {16, MR_SVO_FILE_SOLID, 16, "flags"}, /* solid without voxelized */
        {48, MR_SVO_MAX_PALETTE + 1, 48, "palette_count"},
        {52, 1, 52, "reserved"},
        {56, 0, 56, "payload_bytes"},
        {60, 1, 56, "payload_bytes"},
        {40, 0xFFFFFFFFu, 56, "payload_bytes"}, /* counts and size disagree */
    };
    for (size_t i = 0; i < sizeof hdr / sizeof *hdr; i++) {
        uint8_t *b = malloc(size);
        assert_non_null(b);
        memcpy(b, g, size);
        mr_le_put_u32(b + hdr[i].at, hdr[i].v);
        fix_header_crc(b);
        char what[64];
        snprintf(what, sizeof what, "u32 %#x at %zu", hdr[i].v, hdr[i].at);
        expect_bad(b, size, hdr[i].want, hdr[i].field, what);
        free(b);
    }
    /* counts consistent with payload_bytes but not with the file size */
    {
        uint8_t *b = malloc(size);
        assert_non_null(b);
        memcpy(b, g, size);
        mr_le_put_u32(b + 44, L + 1);
        mr_le_put_u32(b + 56, (uint32_t)(o.crc - o.fn + 4));
        fix_header_crc(b);
        expect_bad(b, size, size, "truncated", "one leaf more than the bytes hold");
        /* counts that would need more than the limit */
        mr_le_put_u32(b + 40, 0xFFFFFFF0u);
        mr_le_put_u32(b + 44, 0xFFFFFFF0u);
        uint64_t payload = 0xFFFFFFF0ull * 14 + 16ull * P;
        mr_le_put_u32(b + 56, (uint32_t)payload);
        mr_le_put_u32(b + 60, (uint32_t)(payload >> 32));
        fix_header_crc(b);
        expect_bad(b, size, 40, "limit", "counts beyond the file limit");
        free(b);
    }
    /* magic */
    g[3] = 'X';
    expect_bad(g, size, 3, "magic", "bad magic");
    free(g);

    /* valid edge cases: an empty octree and a root leaf */
    mr_svo e = {.depth = 4, .origin = {0, 0, 0}, .size = 1.0f};
    uint8_t *b = NULL;
    write_buf(&e, NULL, &b, &size);
    assert_int_equal(size, 104);
    mr_svo *r = read_buf(b, size);
    assert_int_equal(r->leaf_count, 0);
    assert_int_equal(r->node_count, 0);
    mr_svo_voxelize_free(r);
    free(b);
    mr_svo_leaf rl = {{128, 128}, 0};
    mr_svo_attr ra = {{1, 2, 3}, 0, {0, 0, 0, 0}, {0, 0, 0, 0}};
    mr_svo root = {.depth = 2, .size = 2.0f, .leaf_count = 1, .palette_count = 1,
                   .leaves = &rl, .palette = &ra};
    write_buf(&root, NULL, &b, &size);
    r = read_buf(b, size);
    assert_same_svo(&root, r);
    mr_svo_voxelize_free(r);
    free(b);

    /* the writer's own argument checks */
    mr_error err = {0};
    assert_int_equal(mr_svo_file_write(NULL, &b, &size, &err), MR_ERR_INVALID);
    mr_svo holes = *s;
    holes.leaves = NULL;
    assert_int_equal(mr_svo_file_write(&holes, &b, &size, &err), MR_ERR_INVALID);
    assert_null(b);
    mr_svo_file_meta meta = {.flags = 8};
    assert_int_equal(mr_svo_file_write_meta(s, &meta, &b, &size, &err), MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "would not read back"));
    assert_int_equal(mr_svo_file_read(NULL, 5, &r, &err), MR_ERR_INVALID);
    mr_svo_voxelize_free(s);
}

static void test_read_path_errors(void **state)
{
    (void)state;
    mr_svo *r = NULL;
    mr_error err = {0};
    char path[128];
    snprintf(path, sizeof path, "%s/absent.mrsvo", tmp_dir);
    assert_int_equal(mr_svo_file_read_path(path, &r, &err), MR_ERR_IO);
    assert_int_equal(mr_svo_file_read_path(tmp_dir, &r, &err), MR_ERR_IO); /* a directory */
    snprintf(path, sizeof path, "%s/fifo.mrsvo", tmp_dir);
    assert_int_equal(mkfifo(path, 0600), 0);
    assert_int_equal(mr_svo_file_read_path(path, &r, &err), MR_ERR_IO); /* and no hang */
    snprintf(path, sizeof path, "%s/empty.mrsvo", tmp_dir);
    FILE *fp = fopen(path, "wb");
    assert_non_null(fp);
    fclose(fp);
    assert_int_equal(mr_svo_file_read_path(path, &r, &err), MR_ERR_FORMAT);
    assert_non_null(strstr(err.msg, path)); /* names the file */
    assert_non_null(strstr(err.msg, "byte offset 0"));
    /* larger than any valid file: refused before reading (a sparse file) */
    snprintf(path, sizeof path, "%s/huge.mrsvo", tmp_dir);
    fp = fopen(path, "wb");
    assert_non_null(fp);
    assert_int_equal(ftruncate(fileno(fp), (off_t)MR_SVO_FILE_MAX_BYTES + 1), 0);
    fclose(fp);
    assert_int_equal(mr_svo_file_read_path(path, &r, &err), MR_ERR_FORMAT);
    assert_non_null(strstr(err.msg, "byte offset"));
    unlink(path);
    assert_null(r);
    mr_svo *s = small_svo();
    snprintf(path, sizeof path, "%s/no/such/dir/x.mrsvo", tmp_dir);
    assert_int_equal(mr_svo_file_write_path(s, path, &err), MR_ERR_IO);
    assert_int_equal(mr_svo_file_write_path(s, "", &err), MR_ERR_INVALID);
    mr_svo_voxelize_free(s);
}

/* ---- the cache */

static void key_of(const mr_asset *a, const mr_svo_voxelize_params *p, uint8_t k[32])
{
    mr_svo_cache_key(a, p, k);
}

static void test_cache_key_inputs(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    assert_true(a->mesh_count >= 2);
    mr_svo_voxelize_params p = {.depth = 7, .mode = MR_SVO_VOXELIZE_SURFACE, .threads = 2};
    uint8_t k0[32], k[32];
    key_of(a, &p, k0);
    key_of(a, &p, k);
    assert_memory_equal(k0, k, 32); /* deterministic */
    /* not part of the key: threads, keep_leaf_keys */
    p.threads = 1;
    p.keep_leaf_keys = true;
    key_of(a, &p, k);
    assert_memory_equal(k0, k, 32);
    p.threads = 2;
    p.keep_leaf_keys = false;
    /* part of it: depth, mode, albedo (given or not, any component) */
    p.depth = 8;
    key_of(a, &p, k);
    assert_memory_not_equal(k0, k, 32);
    p.depth = 7;
    p.mode = MR_SVO_VOXELIZE_SOLID;
    key_of(a, &p, k);
    assert_memory_not_equal(k0, k, 32);
    p.mode = MR_SVO_VOXELIZE_SURFACE;
    float *alb = malloc(a->mesh_count * 3 * sizeof *alb);
    assert_non_null(alb);
    for (size_t i = 0; i < a->mesh_count * 3; i++)
        alb[i] = 0.8f;
    p.albedo = alb;
    uint8_t ka[32];
    key_of(a, &p, ka);
    assert_memory_not_equal(k0, ka, 32);
    alb[a->mesh_count * 3 - 1] = 0.5f; /* the last mesh's blue */
    key_of(a, &p, k);
    assert_memory_not_equal(ka, k, 32);
    p.albedo = NULL;
    free(alb);
    /* and the geometry the voxeliser reads */
    const mr_mesh *m = &a->meshes[1];
    float saved = m->positions[7];
    m->positions[7] = nextafterf(saved, INFINITY);
    key_of(a, &p, k);
    assert_memory_not_equal(k0, k, 32);
    m->positions[7] = saved;
    saved = m->normals[4];
    m->normals[4] = -saved;
    key_of(a, &p, k);
    assert_memory_not_equal(k0, k, 32);
    m->normals[4] = saved;
    uint32_t idx = m->indices[2];
    m->indices[2] = m->indices[0];
    key_of(a, &p, k);
    assert_memory_not_equal(k0, k, 32);
    m->indices[2] = idx;
    const mr_mesh *sk = NULL;
    for (size_t i = 0; i < a->mesh_count && !sk; i++)
        if (a->meshes[i].joint_count)
            sk = &a->meshes[i];
    assert_non_null(sk);
    saved = sk->weights[0];
    sk->weights[0] = saved * 0.5f;
    key_of(a, &p, k);
    assert_memory_not_equal(k0, k, 32);
    sk->weights[0] = saved;
    saved = a->nodes[0].local.m[3];
    a->nodes[0].local.m[3] = saved + 1.0f;
    key_of(a, &p, k);
    assert_memory_not_equal(k0, k, 32);
    a->nodes[0].local.m[3] = saved;
    /* not read: uvs and names */
    if (m->uvs) {
        m->uvs[0] += 0.5f;
        key_of(a, &p, k);
        assert_memory_equal(k0, k, 32);
        m->uvs[0] -= 0.5f;
    }
    key_of(a, &p, k);
    assert_memory_equal(k0, k, 32);
    /* NULL arguments: all zero */
    static const uint8_t zero[32] = {0};
    key_of(NULL, &p, k);
    assert_memory_equal(k, zero, 32);

    char *path = NULL;
    mr_error err = {0};
    assert_int_equal(mr_derived_path("/x/y", k0, mr_svo_file_format.ext, &path, &err), MR_OK);
    assert_int_equal(strlen(path), strlen("/x/y/") + 64 + strlen(".mrsvo"));
    char hex[3];
    snprintf(hex, sizeof hex, "%02x", k0[0]);
    assert_memory_equal(path + 5, hex, 2);
    assert_string_equal(path + 5 + 64, ".mrsvo");
    free(path);
    assert_int_equal(mr_derived_path("", k0, mr_svo_file_format.ext, &path, &err), MR_ERR_INVALID);
    assert_null(path);
    mr_asset_free(a);
}

static void test_cache_miss_store_hit(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    char dir[160];
    snprintf(dir, sizeof dir, "%s/cache/a/b", tmp_dir); /* created with its parents */
    mr_svo_voxelize_params p = {.depth = 7, .mode = MR_SVO_VOXELIZE_SURFACE, .threads = 2};
    mr_svo *fresh = voxelize(a, 7, MR_SVO_VOXELIZE_SURFACE, false);
    mr_error err = {0};
    mr_svo *s = NULL;
    bool hit = true;

    /* the low-level calls: a miss is MR_ERR_IO, then store, then hit */
    uint8_t key[32];
    mr_svo_cache_key(a, &p, key);
    char *path = NULL;
    assert_int_equal(mr_derived_path(dir, key, mr_svo_file_format.ext, &path, &err), MR_OK);
    assert_int_equal(mr_svo_cache_load(path, key, &s, &err), MR_ERR_IO);
    assert_null(s);

    /* through mr_svo_voxelize_cached: miss and store */
    assert_int_equal(mr_svo_voxelize_cached(a, &p, dir, &s, &hit, &err), MR_OK);
    assert_false(hit);
    assert_same_svo(fresh, s);
    assert_null(s->leaf_keys);
    mr_svo_voxelize_free(s);
    assert_int_equal(count_files(dir, ".mrsvo"), 1);
    assert_int_equal(count_files(dir, ".tmp"), 0);
    mr_svo *r = NULL;
    mr_svo_file_meta meta;
    uint8_t *buf = NULL;
    size_t size = 0;
    {
        FILE *fp = fopen(path, "rb");
        assert_non_null(fp);
        struct stat st;
        assert_int_equal(fstat(fileno(fp), &st), 0);
        size = (size_t)st.st_size;
        buf = malloc(size);
        assert_non_null(buf);
        assert_int_equal(fread(buf, 1, size, fp), size);
        fclose(fp);
    }
    assert_int_equal(mr_svo_file_read_meta(buf, size, &r, &meta, &err), MR_OK);
    assert_int_equal(meta.flags, MR_SVO_FILE_VOXELIZED); /* surface, recorded */
    assert_memory_equal(meta.key, key, 32);
    mr_svo_voxelize_free(r);
    free(buf);

    /* hit: equal to the fresh voxelisation */
    assert_int_equal(mr_svo_voxelize_cached(a, &p, dir, &s, &hit, &err), MR_OK);
    assert_true(hit);
    assert_same_svo(fresh, s);
    assert_null(s->leaf_keys);
    mr_svo_voxelize_free(s);
    assert_int_equal(mr_svo_cache_load(path, key, &s, &err), MR_OK);
    assert_same_svo(fresh, s);
    mr_svo_voxelize_free(s);
    /* a hit with keep_leaf_keys has the keys a fresh voxelisation keeps */
    p.keep_leaf_keys = true;
    mr_svo *fresh_keys = voxelize(a, 7, MR_SVO_VOXELIZE_SURFACE, true);
    assert_int_equal(mr_svo_voxelize_cached(a, &p, dir, &s, &hit, &err), MR_OK);
    assert_true(hit);
    assert_non_null(s->leaf_keys);
    for (uint32_t i = 0; i < fresh->leaf_count; i++) { /* fields: the struct has padding */
        assert_true(s->leaf_keys[i].code == fresh_keys->leaf_keys[i].code);
        assert_int_equal(s->leaf_keys[i].level, fresh_keys->leaf_keys[i].level);
    }
    mr_svo_voxelize_free(s);
    mr_svo_voxelize_free(fresh_keys);
    p.keep_leaf_keys = false;
    /* the key in the file is compared */
    uint8_t other[32];
    memcpy(other, key, 32);
    other[31] ^= 1;
    assert_int_equal(mr_svo_cache_load(path, other, &s, &err), MR_ERR_FORMAT);
    assert_non_null(strstr(err.msg, "another key"));
    assert_null(s);

    /* another depth, mode or albedo is another file */
    p.mode = MR_SVO_VOXELIZE_SOLID;
    assert_int_equal(mr_svo_voxelize_cached(a, &p, dir, &s, &hit, &err), MR_OK);
    assert_false(hit);
    assert_true(s->leaf_count > fresh->leaf_count);
    mr_svo_voxelize_free(s);
    p.mode = MR_SVO_VOXELIZE_SURFACE;
    p.depth = 6;
    assert_int_equal(mr_svo_voxelize_cached(a, &p, dir, &s, &hit, &err), MR_OK);
    assert_false(hit);
    assert_int_equal(s->depth, 6);
    mr_svo_voxelize_free(s);
    assert_int_equal(count_files(dir, ".mrsvo"), 3);
    p.depth = 7;

    /* no cache dir: plain voxelisation */
    assert_int_equal(mr_svo_voxelize_cached(a, &p, NULL, &s, &hit, &err), MR_OK);
    assert_false(hit);
    assert_same_svo(fresh, s);
    mr_svo_voxelize_free(s);
    /* parameters the voxeliser refuses are refused, not looked up */
    p.depth = 0;
    assert_int_equal(mr_svo_voxelize_cached(a, &p, dir, &s, &hit, &err), MR_ERR_INVALID);
    assert_null(s);
    assert_non_null(strstr(err.msg, "depth 0"));
    free(path);
    mr_svo_voxelize_free(fresh);
    mr_asset_free(a);
}

static void write_file(const char *path, const uint8_t *b, size_t n)
{
    FILE *fp = fopen(path, "wb");
    assert_non_null(fp);
    assert_int_equal(fwrite(b, 1, n, fp), n);
    fclose(fp);
}

/* Corrupt, foreign and mismatching files are misses and are replaced. */
static void test_cache_bad_files_replaced(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    char dir[160];
    snprintf(dir, sizeof dir, "%s/cache2", tmp_dir);
    mr_svo_voxelize_params p = {.depth = 6, .mode = MR_SVO_VOXELIZE_SURFACE, .threads = 2};
    mr_svo *fresh = voxelize(a, 6, MR_SVO_VOXELIZE_SURFACE, false);
    uint8_t key[32];
    mr_svo_cache_key(a, &p, key);
    char *path = NULL;
    mr_error err = {0};
    assert_int_equal(mr_derived_path(dir, key, mr_svo_file_format.ext, &path, &err), MR_OK);
    mr_svo *s = NULL;
    bool hit = false;
    assert_int_equal(mr_svo_voxelize_cached(a, &p, dir, &s, &hit, &err), MR_OK);
    assert_false(hit);
    mr_svo_voxelize_free(s);
    uint8_t *good = NULL;
    size_t size = 0;
    mr_svo_file_meta meta = {.flags = MR_SVO_FILE_VOXELIZED};
    memcpy(meta.key, key, 32);
    write_buf(fresh, &meta, &good, &size);

    /* each bad file in turn: a miss, then the file is good again (a hit) */
    uint8_t junk[64];
    memset(junk, 0xA5, sizeof junk);
    uint8_t *flipped = malloc(size);
    assert_non_null(flipped);
    memcpy(flipped, good, size);
    flipped[size / 2] ^= 0x40;
    mr_svo *small = small_svo(); /* under the right key, but not this asset's */
    uint8_t *foreign = NULL, *unmoded = NULL, *otherkey = NULL;
    size_t fsize = 0, usize = 0, osize = 0;
    write_buf(small, &meta, &foreign, &fsize);
    mr_svo_file_meta none = {.flags = 0};
    memcpy(none.key, key, 32);
    write_buf(fresh, &none, &unmoded, &usize);
    mr_svo_file_meta wrong = meta;
    wrong.key[0] ^= 0xFF;
    write_buf(fresh, &wrong, &otherkey, &osize);
    const struct { const uint8_t *b; size_t n; const char *what; } bad[] = {
        {junk, sizeof junk, "junk"},
        {good, size / 3, "truncated"},
        {flipped, size, "a flipped bit"},
        {foreign, fsize, "another octree (depth 3, not this asset's)"},
        {unmoded, usize, "mode not recorded"},
        {otherkey, osize, "another key"},
        {good, 0, "empty"},
    };
    for (size_t i = 0; i < sizeof bad / sizeof *bad; i++) {
        write_file(path, bad[i].b, bad[i].n);
        hit = true;
        if (mr_svo_voxelize_cached(a, &p, dir, &s, &hit, &err) != MR_OK)
            fail_msg("%s: %s", bad[i].what, err.msg);
        if (hit)
            fail_msg("%s: taken as a hit", bad[i].what);
        assert_same_svo(fresh, s);
        mr_svo_voxelize_free(s);
        assert_int_equal(mr_svo_voxelize_cached(a, &p, dir, &s, &hit, &err), MR_OK);
        if (!hit)
            fail_msg("%s: not replaced", bad[i].what);
        assert_same_svo(fresh, s);
        mr_svo_voxelize_free(s);
    }
    /* the low-level load calls a broken file MR_ERR_FORMAT */
    write_file(path, junk, sizeof junk);
    assert_int_equal(mr_svo_cache_load(path, key, &s, &err), MR_ERR_FORMAT);
    assert_null(s);
    /* and mr_svo_cache_store replaces it (flags 0: not a voxeliser hit) */
    assert_int_equal(mr_svo_cache_store(path, key, fresh, &err), MR_OK);
    assert_int_equal(mr_svo_cache_load(path, key, &s, &err), MR_OK);
    assert_same_svo(fresh, s);
    mr_svo_voxelize_free(s);
    free(flipped);
    free(foreign);
    free(unmoded);
    free(otherkey);
    free(good);
    free(path);
    mr_svo_voxelize_free(small);
    mr_svo_voxelize_free(fresh);
    mr_asset_free(a);
}

/* A cache that cannot be written (a file where the directory should be:
 * also effective as root, which ignores permission bits) costs nothing but
 * the store: the voxelisation is returned. The store itself reports it. */
static void test_cache_unwritable(void **state)
{
    (void)state;
    mr_asset *a = bcn_load();
    char blocker[160], dir[200];
    snprintf(blocker, sizeof blocker, "%s/blocker", tmp_dir);
    write_file(blocker, (const uint8_t *)"x", 1);
    snprintf(dir, sizeof dir, "%s/cache", blocker);
    mr_svo_voxelize_params p = {.depth = 6, .mode = MR_SVO_VOXELIZE_SURFACE, .threads = 2};
    mr_svo *fresh = voxelize(a, 6, MR_SVO_VOXELIZE_SURFACE, false);
    mr_svo *s = NULL;
    bool hit = true;
    mr_error err = {0};
    for (int round = 0; round < 2; round++) {
        assert_int_equal(mr_svo_voxelize_cached(a, &p, dir, &s, &hit, &err), MR_OK);
        assert_false(hit);
        assert_same_svo(fresh, s);
        mr_svo_voxelize_free(s);
    }
    uint8_t key[32];
    mr_svo_cache_key(a, &p, key);
    char *path = NULL;
    assert_int_equal(mr_derived_path(dir, key, mr_svo_file_format.ext, &path, &err), MR_OK);
    assert_int_equal(mr_svo_cache_store(path, key, fresh, &err), MR_ERR_IO);
    assert_non_null(strstr(err.msg, blocker));
    free(path);
    mr_svo_voxelize_free(fresh);
    mr_asset_free(a);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_round_trip_bcn),
        cmocka_unit_test(test_truncations_and_bit_flips),
        cmocka_unit_test(test_crafted_structure),
        cmocka_unit_test(test_read_path_errors),
        cmocka_unit_test(test_cache_key_inputs),
        cmocka_unit_test(test_cache_miss_store_hit),
        cmocka_unit_test(test_cache_bad_files_replaced),
        cmocka_unit_test(test_cache_unwritable),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
