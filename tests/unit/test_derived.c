/*
 * test_derived.c - the derived-data cache itself (core/util/derived.h),
 * through a toy kind written here the way a new kind would be: a "tally"
 * (n numbers derived from a seed) with its own file format, parse,
 * serialise and builder, and nothing else. Real files in a temp dir:
 *  - the key builder hashes exactly the documented little-endian stream
 *    (tag with its NUL, version, revision, values, mesh parts, nodes);
 *  - paths are <dir>/<64 hex>.<ext>; the envelope's checks name offsets;
 *  - miss (missing file: built, stored, directories made 0755, file 0644,
 *    no temporary left), then hit (not built again, file not rewritten);
 *  - junk, truncated, flipped header or payload bits, empty, another key,
 *    another version, another request's result under this key, a file
 *    above the size cap: each a miss, rebuilt and replaced (a new inode),
 *    then a hit;
 *  - a FIFO in the file's place is a miss without blocking and is replaced;
 *    a directory in its place is a miss every time, the build still
 *    returned;
 *  - an unwritable cache directory: the build succeeds, nothing is kept;
 *    the direct store reports MR_ERR_IO naming the blocker;
 *  - the builder's error is the caller's, and nothing is stored; no
 *    directory: build only; a serialiser that would store a file its key
 *    never finds is refused.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <cmocka.h>

#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#define TMP_DIR_TEMPLATE "/tmp/mr-derived-XXXXXX"
#include "../support/file_fixture.h"
#include "util/derived.h"
#include "util/le.h"

/* ---- the toy kind: a tally file, version 3
 *   0  8  magic "MRTALY\0\n"     16 4 count n        24 32 key
 *   8  4  version 3              20 4 seed           56 4  reserved 0
 *   12 4  header_bytes 64                            60 4  header CRC
 *   64 4n values, then the CRC-32 of the values */

#define TALLY_HEADER 64u
static const mr_derived_format tally_format = {
    .name = "tally file", .ext = "tally", .magic = {'M', 'R', 'T', 'A', 'L', 'Y', 0, '\n'},
    .version = 3, .header_bytes = TALLY_HEADER, .key_at = 24, .max_bytes = 1u << 20};

typedef struct tally {
    uint32_t seed, n;     /* the request */
    uint32_t *values;     /* the result: n values */
    int builds, parses;   /* how often each ran */
    int fail_build;       /* build returns this (0: builds) */
    bool foreign_key;     /* serialise puts another key in the header */
} tally;

static uint32_t value_of(uint32_t seed, uint32_t i) { return seed * 2654435761u + i * 40503u; }

static int parse_tally(mr_derived_reader *r, void *out)
{
    tally *t = out;
    int rc = mr_derived_header_check(r);
    if (rc < 0)
        return rc;
    uint32_t n = mr_le_get_u32(r->buf + 16), seed = mr_le_get_u32(r->buf + 20);
    if (r->size != TALLY_HEADER + 4ull * n + 4)
        return mr_derived_bad(r->format, r->err, "count %u at byte offset 16 (the file has %zu "
                              "bytes)", n, r->size);
    if (mr_le_get_u32(r->buf + 56) != 0)
        return mr_derived_bad(r->format, r->err, "reserved field at byte offset 56 is not 0");
    size_t at = TALLY_HEADER + 4u * n;
    if (mr_le_get_u32(r->buf + at) != mr_crc32(r->buf + TALLY_HEADER, 4u * n))
        return mr_derived_bad(r->format, r->err, "values checksum mismatch at byte offset %zu",
                              at);
    if (!r->keep)
        return MR_OK;
    /* the request's fit: another seed or count is not this tally */
    if (seed != t->seed || n != t->n)
        return mr_derived_bad(r->format, r->err, "seed %u at byte offset 20: not this request's",
                              seed);
    uint32_t *v = malloc((n ? n : 1) * sizeof *v);
    if (!v)
        return mr_error_set(r->err, MR_ERR_NOMEM, "tally: out of memory");
    for (uint32_t i = 0; i < n; i++)
        v[i] = mr_le_get_u32(r->buf + TALLY_HEADER + 4 * i);
    t->values = v;
    return MR_OK;
}

static int tally_parse(void *ctx, const uint8_t *buf, size_t size, mr_error *err)
{
    tally *t = ctx;
    t->parses++;
    return mr_derived_parse(&tally_format, buf, size, parse_tally, t, err);
}

static int tally_serialise(void *ctx, const uint8_t key[MR_DERIVED_KEY_BYTES], uint8_t **buf,
                           size_t *size, mr_error *err)
{
    const tally *t = ctx;
    uint8_t *b = NULL, other[MR_DERIVED_KEY_BYTES];
    mr_derived_reader *check = NULL;
    uint64_t total = TALLY_HEADER + 4ull * t->n + 4;
    int rc = mr_derived_buffer(&tally_format, total, &b, &check, err);
    if (rc < 0)
        return rc;
    mr_le_put_u32(b + 16, t->n);
    mr_le_put_u32(b + 20, t->seed);
    memcpy(other, key, sizeof other);
    other[0] ^= 1;
    mr_derived_header_seal(&tally_format, t->foreign_key ? other : key, b);
    for (uint32_t i = 0; i < t->n; i++)
        mr_le_put_u32(b + TALLY_HEADER + 4 * i, t->values[i]);
    mr_le_put_u32(b + total - 4, mr_crc32(b + TALLY_HEADER, 4u * t->n));
    if ((rc = parse_tally(check, NULL)) < 0) {
        rc = mr_derived_readback_failed(&tally_format, rc, err);
        free(b);
    } else {
        *buf = b;
        *size = (size_t)total;
    }
    free(check);
    return rc;
}

static int tally_build(void *ctx, mr_error *err)
{
    tally *t = ctx;
    t->builds++;
    if (t->fail_build)
        return mr_error_set(err, t->fail_build, "tally build: refused on purpose");
    t->values = malloc((t->n ? t->n : 1) * sizeof *t->values);
    if (!t->values)
        return mr_error_set(err, MR_ERR_NOMEM, "tally: out of memory");
    for (uint32_t i = 0; i < t->n; i++)
        t->values[i] = value_of(t->seed, i);
    return MR_OK;
}

static const mr_derived_ops tally_ops = {
    .parse = tally_parse, .serialise = tally_serialise, .build = tally_build};

static void tally_key(const tally *t, uint8_t key[MR_DERIVED_KEY_BYTES])
{
    mr_derived_key_builder kb;
    mr_derived_key_begin(&kb, "microray test tally", tally_format.version, 1);
    mr_derived_key_u32(&kb, t->seed);
    mr_derived_key_u32(&kb, t->n);
    mr_derived_key_end(&kb, key);
}

/* One get through the cache in dir; the values are checked, then freed. */
static bool get(tally *t, const char *dir)
{
    uint8_t key[MR_DERIVED_KEY_BYTES];
    tally_key(t, key);
    bool hit = true; /* get must say */
    mr_error err = {0};
    t->values = NULL;
    if (mr_derived_get(dir, key, &tally_format, &tally_ops, t, &hit, &err) != MR_OK)
        fail_msg("get: %s", err.msg);
    assert_non_null(t->values);
    for (uint32_t i = 0; i < t->n; i++)
        assert_int_equal(t->values[i], value_of(t->seed, i));
    free(t->values);
    t->values = NULL;
    return hit;
}

static char *path_of(const tally *t, const char *dir)
{
    uint8_t key[MR_DERIVED_KEY_BYTES];
    tally_key(t, key);
    char *path = NULL;
    mr_error err = {0};
    assert_int_equal(mr_derived_path(dir, key, tally_format.ext, &path, &err), MR_OK);
    return path;
}

static ino_t inode(const char *path)
{
    struct stat st;
    assert_int_equal(lstat(path, &st), 0);
    return st.st_ino;
}

static void fix_header_crc(uint8_t *b)
{
    mr_le_put_u32(b + TALLY_HEADER - 4, mr_crc32(b, TALLY_HEADER - 4));
}

/* ---- the key builder */

static void test_key_stream(void **state)
{
    (void)state;
    /* begin = the tag with its NUL, version, revision (u32 LE) */
    uint8_t want[MR_DERIVED_KEY_BYTES], got[MR_DERIVED_KEY_BYTES];
    uint8_t stream[4096];
    size_t n = 0;
    memcpy(stream, "tag", 4);
    n = 4;
    mr_le_put_u32(stream + n, 7), n += 4;
    mr_le_put_u32(stream + n, 9), n += 4;
    mr_le_put_u32(stream + n, 0xA1B2C3D4u), n += 4;
    mr_le_put_u64(stream + n, 0x0102030405060708ull), n += 8;
    const float fl[2] = {-0.0f, 1.5f};
    mr_le_put_f32(stream + n, fl[0]), n += 4;
    mr_le_put_f32(stream + n, fl[1]), n += 4;
    mr_sha256 sha;
    mr_sha256_init(&sha);
    mr_sha256_update(&sha, stream, n);
    mr_sha256_final(&sha, want);
    mr_derived_key_builder kb;
    mr_derived_key_begin(&kb, "tag", 7, 9);
    mr_derived_key_u32(&kb, 0xA1B2C3D4u);
    mr_derived_key_u64(&kb, 0x0102030405060708ull);
    mr_derived_key_f32s(&kb, fl, 2);
    mr_derived_key_end(&kb, got);
    assert_memory_equal(want, got, sizeof want);
    /* tag, version and revision each change the key */
    uint8_t k[3][MR_DERIVED_KEY_BYTES];
    const char *tags[3] = {"tag", "tag", "tah"};
    const uint32_t ver[3] = {7, 8, 7};
    for (int i = 0; i < 3; i++) {
        mr_derived_key_begin(&kb, tags[i], ver[i], 9);
        mr_derived_key_end(&kb, k[i]);
    }
    mr_derived_key_begin(&kb, "tag", 7, 10);
    mr_derived_key_end(&kb, got);
    assert_memory_not_equal(k[0], k[1], sizeof k[0]);
    assert_memory_not_equal(k[0], k[2], sizeof k[0]);
    assert_memory_not_equal(k[0], got, sizeof got);

    /* mesh parts: the presence word and the arrays, in the documented order */
    float pos[6] = {0, 1, 2, 3, 4, 5}, nrm[6] = {0, 0, 1, 0, 0, 1};
    uint32_t idx[3] = {0, 1, 1};
    uint16_t joints[2 * MR_MAX_INFLUENCES] = {1, 0};
    float weights[2 * MR_MAX_INFLUENCES] = {1.0f};
    weights[MR_MAX_INFLUENCES] = 1.0f;
    mr_mesh m = {.vertex_count = 2, .triangle_count = 1, .positions = pos, .normals = nrm,
                 .indices = idx, .joint_count = 2, .joints = joints, .weights = weights};
    const unsigned all = MR_DERIVED_POSITIONS | MR_DERIVED_NORMALS | MR_DERIVED_INDICES |
                         MR_DERIVED_SKIN;
    assert_true(mr_derived_mesh_skinned(&m));
    assert_int_equal(mr_derived_mesh_parts(&m, all), 15);
    assert_int_equal(mr_derived_mesh_parts(&m, MR_DERIVED_INDICES | MR_DERIVED_SKIN), 12);
    n = 0;
    memcpy(stream, "m", 2), n = 2;
    mr_le_put_u32(stream + n, 1), n += 4;
    mr_le_put_u32(stream + n, 1), n += 4;
    mr_le_put_u32(stream + n, 2), n += 4; /* counts: vertices, triangles, joints */
    mr_le_put_u32(stream + n, 1), n += 4;
    mr_le_put_u32(stream + n, 2), n += 4;
    for (int i = 0; i < 6; i++)
        mr_le_put_f32(stream + n, pos[i]), n += 4;
    for (int i = 0; i < 3; i++)
        mr_le_put_u32(stream + n, idx[i]), n += 4;
    for (unsigned i = 0; i < 2 * MR_MAX_INFLUENCES; i++)
        mr_le_put_u16(stream + n, joints[i]), n += 2;
    for (unsigned i = 0; i < 2 * MR_MAX_INFLUENCES; i++)
        mr_le_put_f32(stream + n, weights[i]), n += 4;
    mr_sha256_init(&sha);
    mr_sha256_update(&sha, stream, n);
    mr_sha256_final(&sha, want);
    mr_derived_key_begin(&kb, "m", 1, 1);
    mr_derived_key_mesh_counts(&kb, &m);
    mr_derived_key_mesh_arrays(&kb, &m, MR_DERIVED_POSITIONS | MR_DERIVED_INDICES |
                                            MR_DERIVED_SKIN);
    mr_derived_key_end(&kb, got);
    assert_memory_equal(want, got, sizeof want);
    /* no joint count: not skinned, whatever the arrays; absent arrays are
     * not parts */
    m.joint_count = 0;
    m.normals = NULL;
    assert_false(mr_derived_mesh_skinned(&m));
    assert_int_equal(mr_derived_mesh_parts(&m, all), MR_DERIVED_POSITIONS | MR_DERIVED_INDICES);

    /* nodes: count (u64), then per node parent and 16 floats */
    mr_node nodes[2] = {{.parent = -1, .local = mr_mat4_identity()},
                        {.parent = 0, .local = mr_mat4_identity()}};
    nodes[1].local.m[3] = 2.5f;
    mr_asset a = {.node_count = 2, .nodes = nodes};
    n = 0;
    memcpy(stream, "n", 2), n = 2;
    mr_le_put_u32(stream + n, 1), n += 4;
    mr_le_put_u32(stream + n, 1), n += 4;
    mr_le_put_u64(stream + n, 2), n += 8;
    for (int i = 0; i < 2; i++) {
        mr_le_put_u32(stream + n, (uint32_t)nodes[i].parent), n += 4;
        for (int j = 0; j < 16; j++)
            mr_le_put_f32(stream + n, nodes[i].local.m[j]), n += 4;
    }
    mr_sha256_init(&sha);
    mr_sha256_update(&sha, stream, n);
    mr_sha256_final(&sha, want);
    mr_derived_key_begin(&kb, "n", 1, 1);
    mr_derived_key_nodes(&kb, &a);
    mr_derived_key_end(&kb, got);
    assert_memory_equal(want, got, sizeof want);
}

/* ---- the path and the envelope */

static void test_path_and_envelope(void **state)
{
    (void)state;
    uint8_t key[MR_DERIVED_KEY_BYTES];
    for (unsigned i = 0; i < sizeof key; i++)
        key[i] = (uint8_t)(i * 37 + 1);
    char *path = NULL;
    mr_error err = {0};
    assert_int_equal(mr_derived_path("/c/d", key, "tally", &path, &err), MR_OK);
    assert_int_equal(strlen(path), 5 + 64 + 6);
    assert_memory_equal(path, "/c/d/0126", 9);
    assert_string_equal(path + 5 + 64, ".tally");
    for (int i = 0; i < 64; i++)
        assert_non_null(strchr("0123456789abcdef", path[5 + i]));
    free(path);
    assert_int_equal(mr_derived_path("", key, "tally", &path, &err), MR_ERR_INVALID);
    assert_null(path);
    assert_int_equal(mr_derived_path(NULL, key, "tally", &path, &err), MR_ERR_INVALID);
    assert_int_equal(mr_derived_path("/c", key, "", &path, &err), MR_ERR_INVALID);

    /* a sealed header checks out; each defect names its offset */
    tally t = {.seed = 5, .n = 3};
    assert_int_equal(tally_build(&t, &err), MR_OK);
    uint8_t *good = NULL;
    size_t size = 0;
    assert_int_equal(tally_serialise(&t, key, &good, &size, &err), MR_OK);
    assert_int_equal(size, TALLY_HEADER + 12 + 4);
    assert_memory_equal(good, "MRTALY\0\n", 8);
    assert_int_equal(mr_le_get_u32(good + 8), 3);
    assert_int_equal(mr_le_get_u32(good + 12), TALLY_HEADER);
    assert_memory_equal(good + 24, key, sizeof key);
    free(t.values);
    /* {byte, xor, fix the header CRC, bytes given (0: all), message} */
    const struct { size_t at; uint8_t x; bool fix_crc; size_t n; const char *want; } bad[] = {
        {0, 0, false, TALLY_HEADER - 1, "truncated header at byte offset 63"},
        {0, 0, false, 1, "truncated header at byte offset 1"},
        {5, 0x20, false, 0, "bad magic at byte offset 5"},
        {8, 1, true, 0, "unsupported version 2 at byte offset 8"},
        {12, 4, true, 0, "header_bytes 68 at byte offset 12"},
        {30, 0x08, false, 0, "header checksum mismatch at byte offset 60"},
    };
    for (size_t i = 0; i < sizeof bad / sizeof *bad; i++) {
        uint8_t *b = malloc(size);
        assert_non_null(b);
        memcpy(b, good, size);
        b[bad[i].at] ^= bad[i].x;
        if (bad[i].fix_crc)
            fix_header_crc(b);
        size_t n = bad[i].n ? bad[i].n : size;
        tally r = {.seed = 5, .n = 3};
        int rc = mr_derived_parse(&tally_format, b, n, parse_tally, &r, &err);
        if (rc != MR_ERR_FORMAT || !strstr(err.msg, bad[i].want) ||
            strncmp(err.msg, "tally file: ", 12) != 0)
            fail_msg("defect %zu: got %s '%s', want '%s'", i, mr_err_name(rc), err.msg,
                     bad[i].want);
        assert_null(r.values);
        free(b);
    }
    /* argument and writer checks */
    assert_int_equal(mr_derived_parse(&tally_format, NULL, 4, parse_tally, &t, &err),
                     MR_ERR_INVALID);
    uint8_t *b = NULL;
    mr_derived_reader *check = NULL;
    assert_int_equal(mr_derived_buffer(&tally_format, (1u << 20) + 1, &b, &check, &err),
                     MR_ERR_LIMIT);
    assert_null(b);
    assert_null(check);
    assert_int_equal(mr_derived_buffer(&tally_format, TALLY_HEADER - 1, &b, &check, &err),
                     MR_ERR_INVALID);
    mr_derived_format broken = tally_format;
    broken.key_at = 30; /* the key would overlap the header CRC at 60 */
    assert_int_equal(mr_derived_buffer(&broken, 100, &b, &check, &err), MR_ERR_INVALID);
    assert_null(b);
    mr_error_set(&err, MR_ERR_FORMAT, "inner");
    assert_int_equal(mr_derived_readback_failed(&tally_format, MR_ERR_FORMAT, &err),
                     MR_ERR_INVALID);
    assert_int_equal(err.code, MR_ERR_INVALID);
    assert_string_equal(err.msg, "tally file write: would not read back: inner");
    free(good);
}

/* ---- the policy */

static void test_miss_then_hit(void **state)
{
    (void)state;
    char root[128], dir[160];
    snprintf(root, sizeof root, "%s/hit", tmp_dir);
    snprintf(dir, sizeof dir, "%s/a/b", root); /* made with its parents */
    tally t = {.seed = 11, .n = 100};
    assert_false(get(&t, dir));
    assert_int_equal(t.builds, 1);
    char *path = path_of(&t, dir);
    struct stat st;
    assert_int_equal(stat(root, &st), 0);
    assert_int_equal(st.st_mode & 0777, 0755);
    assert_int_equal(stat(dir, &st), 0);
    assert_int_equal(st.st_mode & 0777, 0755);
    assert_int_equal(stat(path, &st), 0);
    assert_true(S_ISREG(st.st_mode));
    assert_int_equal(st.st_mode & 0777, 0644);
    assert_int_equal(st.st_size, TALLY_HEADER + 400 + 4);
    assert_int_equal(file_count(dir, ""), 1); /* no temporary left */
    ino_t ino = inode(path);
    /* hit: parsed, not built, not rewritten */
    assert_true(get(&t, dir));
    assert_true(get(&t, dir));
    assert_int_equal(t.builds, 1);
    assert_int_equal(t.parses, 2);
    assert_int_equal(inode(path), ino);
    /* another request is another file */
    tally u = {.seed = 12, .n = 100};
    assert_false(get(&u, dir));
    assert_true(get(&u, dir));
    assert_int_equal(file_count(dir, ".tally"), 2);
    /* the low-level load: a hit, a miss on another key (named) */
    uint8_t key[MR_DERIVED_KEY_BYTES];
    tally_key(&t, key);
    mr_error err = {0};
    assert_int_equal(mr_derived_load(path, key, &tally_format, &tally_ops, &t, &err), MR_OK);
    free(t.values);
    t.values = NULL;
    key[31] ^= 1;
    assert_int_equal(mr_derived_load(path, key, &tally_format, &tally_ops, &t, &err),
                     MR_ERR_FORMAT);
    assert_non_null(strstr(err.msg, "stored under another key (byte offset 24)"));
    assert_non_null(strstr(err.msg, path));
    assert_null(t.values);
    assert_int_equal(mr_derived_load(path, NULL, &tally_format, &tally_ops, &t, &err), MR_OK);
    free(t.values);
    t.values = NULL;
    free(path);
    path = path_of(&t, root);
    assert_int_equal(mr_derived_load(path, key, &tally_format, &tally_ops, &t, &err), MR_ERR_IO);
    free(path);
}

/* Each bad file under the request's name: a miss, rebuilt and replaced
 * (renamed in: a new inode), then a hit. */
static void test_bad_files_replaced(void **state)
{
    (void)state;
    char dir[160];
    snprintf(dir, sizeof dir, "%s/bad", tmp_dir);
    tally t = {.seed = 21, .n = 50};
    assert_false(get(&t, dir));
    char *path = path_of(&t, dir);
    size_t size = 0;
    uint8_t *good = file_get(path, &size);
    uint8_t *b = malloc(size);
    assert_non_null(b);

    uint8_t junk[100];
    memset(junk, 0x5A, sizeof junk);
    /* another request's (valid) file under this name */
    tally other = {.seed = 22, .n = 50};
    uint8_t key[MR_DERIVED_KEY_BYTES], *foreign = NULL;
    size_t fsize = 0;
    tally_key(&t, key);
    mr_error err = {0};
    assert_int_equal(tally_build(&other, &err), MR_OK);
    assert_int_equal(tally_serialise(&other, key, &foreign, &fsize, &err), MR_OK);
    free(other.values);
    enum { JUNK, TRUNCATED, EMPTY, HEADER_BIT, PAYLOAD_BIT, OTHER_KEY, OTHER_VERSION, FOREIGN,
           COUNT };
    static const char *what[COUNT] = {"junk", "truncated", "empty", "a header bit",
                                      "a payload bit", "another key", "another version",
                                      "another request's tally"};
    for (int k = 0; k < COUNT; k++) {
        const uint8_t *bytes = b;
        size_t n = size;
        memcpy(b, good, size);
        switch (k) {
        case JUNK: bytes = junk, n = sizeof junk; break;
        case TRUNCATED: n = size - 5; break;
        case EMPTY: n = 0; break;
        case HEADER_BIT: b[17] ^= 0x04; break;
        case PAYLOAD_BIT: b[TALLY_HEADER + 33] ^= 0x80; break;
        case OTHER_KEY: b[24 + 7] ^= 0x10, fix_header_crc(b); break;
        case OTHER_VERSION: mr_le_put_u32(b + 8, 4), fix_header_crc(b); break;
        case FOREIGN: bytes = foreign, n = fsize; break;
        }
        file_put(path, bytes, n);
        ino_t bad_ino = inode(path);
        int builds = t.builds;
        if (get(&t, dir))
            fail_msg("%s: taken as a hit", what[k]);
        assert_int_equal(t.builds, builds + 1);
        assert_true(inode(path) != bad_ino);
        size_t now_size = 0;
        uint8_t *now = file_get(path, &now_size);
        assert_int_equal(now_size, size);
        assert_memory_equal(now, good, size); /* the same bytes as the first store */
        free(now);
        if (!get(&t, dir))
            fail_msg("%s: not replaced", what[k]);
        assert_int_equal(t.builds, builds + 1);
    }
    /* larger than the format's cap: refused before reading (a sparse file) */
    FILE *fp = fopen(path, "wb");
    assert_non_null(fp);
    assert_int_equal(ftruncate(fileno(fp), (off_t)tally_format.max_bytes + 1), 0);
    fclose(fp);
    assert_int_equal(mr_derived_load(path, key, &tally_format, &tally_ops, &t, &err),
                     MR_ERR_FORMAT);
    assert_non_null(strstr(err.msg, "byte offset"));
    assert_false(get(&t, dir));
    assert_true(get(&t, dir));
    assert_int_equal(file_count(dir, ""), 1);
    free(foreign);
    free(b);
    free(good);
    free(path);
}

/* A FIFO under the name must not block the job and is replaced by the
 * store; a directory under it cannot be replaced: a miss every time. */
static void test_not_a_regular_file(void **state)
{
    (void)state;
    char dir[160];
    snprintf(dir, sizeof dir, "%s/special", tmp_dir);
    assert_int_equal(mkdir(dir, 0755), 0);
    tally t = {.seed = 31, .n = 10};
    char *path = path_of(&t, dir);
    assert_int_equal(mkfifo(path, 0644), 0);
    alarm(60); /* a blocking open would hang here: fail instead */
    assert_false(get(&t, dir));
    alarm(0);
    struct stat st;
    assert_int_equal(lstat(path, &st), 0);
    assert_true(S_ISREG(st.st_mode));
    assert_true(get(&t, dir));
    assert_int_equal(t.builds, 1);

    assert_int_equal(unlink(path), 0);
    assert_int_equal(mkdir(path, 0755), 0);
    for (int round = 0; round < 2; round++)
        assert_false(get(&t, dir));
    assert_int_equal(t.builds, 3);
    assert_int_equal(lstat(path, &st), 0);
    assert_true(S_ISDIR(st.st_mode));
    assert_int_equal(file_count(dir, ".tmp"), 0);
    free(path);
}

/* A file where the directory should be (effective as root too, which
 * ignores permission bits): every get builds and succeeds; the direct
 * store says why it could not. */
static void test_unwritable(void **state)
{
    (void)state;
    char blocker[160], dir[200];
    snprintf(blocker, sizeof blocker, "%s/blocker", tmp_dir);
    file_put(blocker, "x", 1);
    snprintf(dir, sizeof dir, "%s/cache", blocker);
    tally t = {.seed = 41, .n = 20};
    assert_false(get(&t, dir));
    assert_false(get(&t, dir));
    assert_int_equal(t.builds, 2);
    uint8_t key[MR_DERIVED_KEY_BYTES];
    tally_key(&t, key);
    char *path = path_of(&t, dir);
    mr_error err = {0};
    assert_int_equal(tally_build(&t, &err), MR_OK);
    assert_int_equal(mr_derived_store(path, key, &tally_format, &tally_ops, &t, &err), MR_ERR_IO);
    assert_non_null(strstr(err.msg, blocker));
    free(t.values);
    free(path);
}

static void test_build_errors_and_no_cache(void **state)
{
    (void)state;
    char dir[160];
    snprintf(dir, sizeof dir, "%s/errors", tmp_dir);
    tally t = {.seed = 51, .n = 5, .fail_build = MR_ERR_LIMIT};
    uint8_t key[MR_DERIVED_KEY_BYTES];
    tally_key(&t, key);
    mr_error err = {0};
    bool hit = true;
    /* the builder's error is the caller's; nothing is stored */
    assert_int_equal(mr_derived_get(dir, key, &tally_format, &tally_ops, &t, &hit, &err),
                     MR_ERR_LIMIT);
    assert_false(hit);
    assert_string_equal(err.msg, "tally build: refused on purpose");
    struct stat st;
    assert_int_equal(stat(dir, &st), -1);
    /* no directory: build only */
    t.fail_build = 0;
    assert_false(get(&t, NULL));
    assert_false(get(&t, ""));
    assert_false(get(&t, NULL));
    assert_int_equal(t.builds, 4);
    assert_int_equal(t.parses, 0);
    assert_int_equal(mr_derived_get(dir, NULL, &tally_format, &tally_ops, &t, &hit, &err), MR_OK);
    assert_false(hit);
    free(t.values);
    t.values = NULL;
    assert_int_equal(stat(dir, &st), -1);
    /* a file its key would never find is not stored: the get still
     * returns the build, and the next one builds again */
    t.foreign_key = true;
    assert_false(get(&t, dir));
    assert_false(get(&t, dir));
    assert_int_equal(t.builds, 7);
    char *path = path_of(&t, dir);
    assert_int_equal(stat(path, &st), -1);
    assert_int_equal(tally_build(&t, &err), MR_OK);
    assert_int_equal(mr_derived_store(path, key, &tally_format, &tally_ops, &t, &err),
                     MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "would not be found under its key"));
    assert_int_equal(stat(path, &st), -1);
    free(t.values);
    free(path);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_key_stream),
        cmocka_unit_test(test_path_and_envelope),
        cmocka_unit_test(test_miss_then_hit),
        cmocka_unit_test(test_bad_files_replaced),
        cmocka_unit_test(test_not_a_regular_file),
        cmocka_unit_test(test_unwritable),
        cmocka_unit_test(test_build_errors_and_no_cache),
    };
    return cmocka_run_group_tests(tests, file_fixture_setup, file_fixture_teardown);
}
