/*
 * test_util_io.c - the shared helpers of microray's file formats
 * (core/util/le.h, crc32.h, file_io.h and sha256.h's little-endian feed):
 *  - CRC-32 known answer ("123456789" -> 0xCBF43926) and agreement with a
 *    bit-by-bit reference written here from the definition;
 *  - little-endian put/get: exact byte order at unaligned offsets and
 *    bit-exact round trips (-0, NaN payloads, extremes);
 *  - the SHA-256 feed hashes exactly the little-endian byte stream, across
 *    its buffer boundary and with raw bytes in between;
 *  - atomic write replaces content, leaves no temporary (also when it
 *    fails) and makes the file world-readable; two writers of one target
 *    (streamed, interleaved) each get their own temporary; commit under
 *    another name only in the same directory; abort leaves nothing; capped read takes a file at
 *    the cap, refuses one above it, a FIFO (without blocking), a directory
 *    and a missing file; mkdir -p and the directory part of a path.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <cmocka.h>

#include <dirent.h>
#include <fcntl.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "util/crc32.h"
#include "util/file_io.h"
#include "util/le.h"
#include "util/sha256.h"

static char tmp_dir[64];

static int setup(void **state)
{
    (void)state;
    snprintf(tmp_dir, sizeof tmp_dir, "/tmp/mr-util-io-XXXXXX");
    return mkdtemp(tmp_dir) ? 0 : -1;
}

static int teardown(void **state)
{
    (void)state;
    char cmd[128];
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", tmp_dir);
    return system(cmd) == 0 ? 0 : -1;
}

static uint64_t rng_next(uint64_t *s)
{
    uint64_t z = (*s += 0x9e3779b97f4a7c15ull);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
}

/* ---- CRC-32 */

/* The definition, one bit at a time (no table). */
static uint32_t crc_reference(const uint8_t *p, size_t n)
{
    uint32_t c = 0xFFFFFFFFu;
    for (size_t i = 0; i < n; i++) {
        c ^= p[i];
        for (int k = 0; k < 8; k++)
            c = (c & 1u) ? (c >> 1) ^ 0xEDB88320u : c >> 1;
    }
    return ~c;
}

static void test_crc32(void **state)
{
    (void)state;
    assert_int_equal(mr_crc32("123456789", 9), 0xCBF43926u);
    assert_int_equal(mr_crc32("", 0), 0u);
    assert_int_equal(mr_crc32("a", 1), 0xE8B7BE43u);
    uint8_t buf[4099];
    uint64_t s = 7;
    for (size_t i = 0; i < sizeof buf; i++)
        buf[i] = (uint8_t)rng_next(&s);
    for (size_t n = 0; n <= sizeof buf; n += n < 70 ? 1 : 511)
        assert_int_equal(mr_crc32(buf, n), crc_reference(buf, n));
    for (size_t at = 1; at < 16; at++) /* starts off any alignment (libdeflate's vector loop) */
        assert_int_equal(mr_crc32(buf + at, sizeof buf - at), crc_reference(buf + at, sizeof buf - at));
    /* any single flipped bit changes it */
    uint32_t whole = mr_crc32(buf, 64);
    for (unsigned bit = 0; bit < 64 * 8; bit++) {
        buf[bit / 8] ^= (uint8_t)(1u << (bit % 8));
        assert_int_not_equal(mr_crc32(buf, 64), whole);
        buf[bit / 8] ^= (uint8_t)(1u << (bit % 8));
    }
}

/* ---- little-endian fields */

static void test_le_layout(void **state)
{
    (void)state;
    uint8_t b[17] = {0};
    /* odd offsets: no alignment assumed */
    mr_le_put_u16(b + 1, 0x0102);
    mr_le_put_u32(b + 3, 0x03040506u);
    mr_le_put_u64(b + 7, 0x0708090A0B0C0D0Eull);
    const uint8_t want[17] = {0, 2, 1, 6, 5, 4, 3, 0x0E, 0x0D, 0x0C, 0x0B, 0x0A, 9, 8, 7, 0, 0};
    assert_memory_equal(b, want, sizeof want);
    assert_int_equal(mr_le_get_u16(b + 1), 0x0102);
    assert_int_equal(mr_le_get_u32(b + 3), 0x03040506u);
    assert_true(mr_le_get_u64(b + 7) == 0x0708090A0B0C0D0Eull);
    mr_le_put_f32(b + 1, 1.0f); /* 0x3F800000 */
    const uint8_t one[4] = {0, 0, 0x80, 0x3F};
    assert_memory_equal(b + 1, one, 4);
    mr_le_put_f64(b + 5, -2.0); /* 0xC000000000000000 */
    const uint8_t two[8] = {0, 0, 0, 0, 0, 0, 0, 0xC0};
    assert_memory_equal(b + 5, two, 8);
    assert_int_equal(mr_f32_bits(-0.0f), 0x80000000u);
}

static void test_le_round_trip(void **state)
{
    (void)state;
    uint8_t b[11];
    uint64_t s = 11;
    const uint16_t u16s[] = {0, 1, 0x00FF, 0xFF00, UINT16_MAX};
    for (size_t i = 0; i < sizeof u16s / sizeof u16s[0]; i++) {
        mr_le_put_u16(b + 1, u16s[i]);
        assert_int_equal(mr_le_get_u16(b + 1), u16s[i]);
    }
    for (int i = 0; i < 1000; i++) {
        uint64_t v = rng_next(&s);
        mr_le_put_u32(b + 1, (uint32_t)v);
        assert_int_equal(mr_le_get_u32(b + 1), (uint32_t)v);
        mr_le_put_u64(b + 3, v);
        assert_true(mr_le_get_u64(b + 3) == v);
        /* every bit pattern, NaNs included, survives as a float */
        float f;
        uint32_t fb = (uint32_t)(v >> 32);
        memcpy(&f, &fb, sizeof f);
        mr_le_put_f32(b + 1, f);
        assert_int_equal(mr_f32_bits(mr_le_get_f32(b + 1)), fb);
        double d;
        memcpy(&d, &v, sizeof d);
        mr_le_put_f64(b + 3, d);
        double back = mr_le_get_f64(b + 3);
        assert_memory_equal(&back, &d, sizeof d);
    }
    mr_le_put_u32(b, UINT32_MAX);
    assert_int_equal(mr_le_get_u32(b), UINT32_MAX);
    mr_le_put_u64(b, UINT64_MAX);
    assert_true(mr_le_get_u64(b) == UINT64_MAX);
    mr_le_put_f32(b, -0.0f);
    assert_true(signbit(mr_le_get_f32(b)) && mr_le_get_f32(b) == 0.0f);
    mr_le_put_f64(b, -INFINITY);
    assert_true(isinf(mr_le_get_f64(b)) && mr_le_get_f64(b) < 0);
}

/* ---- SHA-256 little-endian feed */

static void test_sha256_feed(void **state)
{
    (void)state;
    /* more values than one 4096-byte buffer holds, in mixed widths */
    enum { N = 1500 };
    uint16_t a16[N];
    uint32_t a32[N];
    float af[N];
    uint64_t s = 3;
    for (size_t i = 0; i < N; i++) {
        uint64_t v = rng_next(&s);
        a16[i] = (uint16_t)v;
        a32[i] = (uint32_t)(v >> 16);
        af[i] = (float)(int32_t)(v >> 32) * 1e-3f;
    }
    af[0] = -0.0f;
    size_t total = 4 + 8 + 5 + N * (2 + 4 + 4) + 4;
    uint8_t *stream = malloc(total), *q = stream;
    assert_non_null(stream);
    mr_le_put_u32(q, 0xDEADBEEFu), q += 4;
    mr_le_put_u64(q, 0x0123456789ABCDEFull), q += 8;
    memcpy(q, "raw\0x", 5), q += 5;
    for (size_t i = 0; i < N; i++)
        mr_le_put_u16(q, a16[i]), q += 2;
    for (size_t i = 0; i < N; i++)
        mr_le_put_u32(q, a32[i]), q += 4;
    for (size_t i = 0; i < N; i++)
        mr_le_put_f32(q, af[i]), q += 4;
    mr_le_put_u32(q, 42), q += 4;
    assert_int_equal((size_t)(q - stream), total);
    uint8_t want[32], got[32];
    mr_sha256 sha;
    mr_sha256_init(&sha);
    mr_sha256_update(&sha, stream, total);
    mr_sha256_final(&sha, want);
    mr_sha256_feed feed;
    mr_sha256_feed_init(&feed);
    mr_sha256_feed_u32(&feed, 0xDEADBEEFu);
    mr_sha256_feed_u64(&feed, 0x0123456789ABCDEFull);
    mr_sha256_feed_bytes(&feed, "raw\0x", 5);
    mr_sha256_feed_u16s(&feed, a16, N);
    mr_sha256_feed_u32s(&feed, a32, N);
    mr_sha256_feed_f32s(&feed, af, N);
    mr_sha256_feed_u32s(&feed, (const uint32_t[]){42}, 1);
    mr_sha256_feed_final(&feed, got);
    assert_memory_equal(got, want, 32);
    free(stream);
    /* nothing fed: the digest of the empty string */
    char hex[65];
    mr_sha256_feed_init(&feed);
    mr_sha256_feed_final(&feed, got);
    mr_sha256_hex("", 0, hex);
    char got_hex[65];
    for (int i = 0; i < 32; i++)
        snprintf(got_hex + 2 * i, 3, "%02x", got[i]);
    assert_string_equal(got_hex, hex);
}

/* ---- files */

static size_t entries(const char *dir)
{
    DIR *d = opendir(dir);
    assert_non_null(d);
    size_t n = 0;
    for (struct dirent *e; (e = readdir(d));)
        n += strcmp(e->d_name, ".") != 0 && strcmp(e->d_name, "..") != 0;
    closedir(d);
    return n;
}

static void write_raw(const char *path, const void *data, size_t size)
{
    FILE *f = fopen(path, "wb");
    assert_non_null(f);
    assert_int_equal(fwrite(data, 1, size, f), size);
    fclose(f);
}

static void test_write_atomic(void **state)
{
    (void)state;
    char dir[128], path[160];
    snprintf(dir, sizeof dir, "%s/w", tmp_dir);
    assert_int_equal(mkdir(dir, 0755), 0);
    snprintf(path, sizeof path, "%s/out.bin", dir);
    mr_error err = {0};
    uint8_t *buf = NULL;
    size_t size = 0;
    assert_int_equal(mr_fs_write_atomic(path, "first version", 13, "t", &err), MR_OK);
    assert_int_equal(mr_fs_read_capped(path, 100, &buf, &size, "t", &err), MR_OK);
    assert_int_equal(size, 13);
    assert_memory_equal(buf, "first version", 13);
    free(buf);
    /* replaced by a shorter content: no tail of the old one */
    assert_int_equal(mr_fs_write_atomic(path, "new", 3, "t", &err), MR_OK);
    assert_int_equal(mr_fs_read_capped(path, 100, &buf, &size, "t", &err), MR_OK);
    assert_int_equal(size, 3);
    assert_memory_equal(buf, "new", 3);
    free(buf);
    assert_int_equal(entries(dir), 1); /* no temporary left */
    struct stat st;
    assert_int_equal(stat(path, &st), 0);
    assert_int_equal(st.st_mode & 0777, 0644);
    /* empty content is a valid file */
    assert_int_equal(mr_fs_write_atomic(path, NULL, 0, "t", &err), MR_OK);
    assert_int_equal(stat(path, &st), 0);
    assert_int_equal(st.st_size, 0);
    /* rename onto a directory fails after the temporary was written: it
     * is removed, the directory untouched */
    char sub[160];
    snprintf(sub, sizeof sub, "%s/sub", dir);
    assert_int_equal(mkdir(sub, 0755), 0);
    write_raw(path, "x", 1);
    char inner[200];
    snprintf(inner, sizeof inner, "%s/f", sub);
    write_raw(inner, "x", 1); /* a non-empty directory cannot be replaced */
    assert_int_equal(mr_fs_write_atomic(sub, "data", 4, "t", &err), MR_ERR_IO);
    assert_non_null(strstr(err.msg, "rename"));
    assert_int_equal(entries(dir), 2);
    /* a missing directory: MR_ERR_IO naming the step, nothing created */
    snprintf(path, sizeof path, "%s/no/such/x", dir);
    assert_int_equal(mr_fs_write_atomic(path, "x", 1, "t", &err), MR_ERR_IO);
    assert_non_null(strstr(err.msg, "cannot create"));
    assert_int_equal(mr_fs_write_atomic("", "x", 1, "t", &err), MR_ERR_INVALID);
    assert_int_equal(entries(dir), 2);
}

/* The streamed form (mr_fs_atomic): two writers of one target at once each
 * get their own temporary in the target's directory, the last commit wins
 * with its complete bytes; commit under another name in the directory
 * (uploads named by their hash), never outside it; abort and every failed
 * step leave nothing behind. */
static void test_atomic_stream(void **state)
{
    (void)state;
    char dir[128], path[160], other[160];
    snprintf(dir, sizeof dir, "%s/s", tmp_dir);
    assert_int_equal(mkdir(dir, 0755), 0);
    snprintf(path, sizeof path, "%s/frame.exr", dir);
    mr_error err = {0};
    mr_fs_atomic a, b;
    assert_int_equal(mr_fs_atomic_begin(&a, path, "t", &err), MR_OK);
    assert_int_equal(mr_fs_atomic_begin(&b, path, "t", &err), MR_OK);
    assert_string_not_equal(a.tmp, b.tmp);
    assert_int_equal(strncmp(a.tmp, path, strlen(path)), 0); /* same directory */
    assert_int_equal(strncmp(b.tmp, path, strlen(path)), 0);
    assert_int_equal(entries(dir), 2);
    /* interleaved: each writer's bytes stay its own */
    assert_int_equal(mr_fs_atomic_write(&a, "aaaa", 4, "t", &err), MR_OK);
    assert_int_equal(mr_fs_atomic_write(&b, "bbbbbb", 6, "t", &err), MR_OK);
    assert_int_equal(mr_fs_atomic_write(&a, "AAAA", 4, "t", &err), MR_OK);
    assert_int_equal(mr_fs_atomic_commit(&a, NULL, "t", &err), MR_OK);
    uint8_t *buf = NULL;
    size_t size = 0;
    assert_int_equal(mr_fs_read_capped(path, 100, &buf, &size, "t", &err), MR_OK);
    assert_int_equal(size, 8);
    assert_memory_equal(buf, "aaaaAAAA", 8);
    free(buf);
    assert_int_equal(mr_fs_atomic_write(&b, "BB", 2, "t", &err), MR_OK);
    assert_int_equal(mr_fs_atomic_commit(&b, NULL, "t", &err), MR_OK);
    assert_int_equal(mr_fs_read_capped(path, 100, &buf, &size, "t", &err), MR_OK);
    assert_int_equal(size, 8);
    assert_memory_equal(buf, "bbbbbbBB", 8);
    free(buf);
    assert_int_equal(entries(dir), 1);
    /* an ended write takes no more bytes and no second commit */
    assert_int_equal(mr_fs_atomic_write(&a, "x", 1, "t", &err), MR_ERR_INVALID);
    assert_int_equal(mr_fs_atomic_commit(&a, NULL, "t", &err), MR_ERR_INVALID);
    mr_fs_atomic_abort(&a); /* harmless */

    /* committed under another name of the same directory */
    snprintf(other, sizeof other, "%s/by-hash", dir);
    assert_int_equal(mr_fs_atomic_begin(&a, path, "t", &err), MR_OK);
    assert_int_equal(mr_fs_atomic_write(&a, "hash", 4, "t", &err), MR_OK);
    assert_int_equal(mr_fs_atomic_commit(&a, other, "t", &err), MR_OK);
    assert_int_equal(mr_fs_read_capped(other, 100, &buf, &size, "t", &err), MR_OK);
    assert_int_equal(size, 4);
    free(buf);
    assert_int_equal(entries(dir), 2);
    /* ... but not elsewhere: refused, the temporary removed */
    snprintf(other, sizeof other, "%s/elsewhere", tmp_dir);
    assert_int_equal(mr_fs_atomic_begin(&a, path, "t", &err), MR_OK);
    assert_int_equal(mr_fs_atomic_commit(&a, other, "t", &err), MR_ERR_INVALID);
    assert_int_equal(access(other, F_OK), -1);
    assert_int_equal(entries(dir), 2);
    /* abort: nothing left, the target untouched */
    assert_int_equal(mr_fs_atomic_begin(&a, path, "t", &err), MR_OK);
    assert_int_equal(mr_fs_atomic_write(&a, "half", 4, "t", &err), MR_OK);
    mr_fs_atomic_abort(&a);
    assert_int_equal(entries(dir), 2);
    assert_int_equal(mr_fs_read_capped(path, 100, &buf, &size, "t", &err), MR_OK);
    assert_int_equal(size, 8);
    free(buf);
    /* a zeroed handle aborts harmlessly (closes no descriptor 0) */
    mr_fs_atomic z = {0};
    mr_fs_atomic_abort(&z);
    assert_int_not_equal(fcntl(0, F_GETFD), -1);
    /* begin in a missing directory: the error names the step, nothing to end */
    snprintf(other, sizeof other, "%s/no/such/f", dir);
    assert_int_equal(mr_fs_atomic_begin(&a, other, "w", &err), MR_ERR_IO);
    assert_non_null(strstr(err.msg, "w: cannot create"));
    assert_null(a.tmp);
    mr_fs_atomic_abort(&a);
}

/* A temporary of the old fixed name (<path>.tmp) left or held by another
 * writer must not be written through: the final file is only this write's. */
static void test_write_atomic_ignores_foreign_tmp(void **state)
{
    (void)state;
    char dir[128], path[160], tmp[170];
    snprintf(dir, sizeof dir, "%s/f", tmp_dir);
    assert_int_equal(mkdir(dir, 0755), 0);
    snprintf(path, sizeof path, "%s/out", dir);
    snprintf(tmp, sizeof tmp, "%s.tmp", path);
    FILE *other = fopen(tmp, "w"); /* another writer, mid-write */
    assert_non_null(other);
    mr_error err = {0};
    assert_int_equal(mr_fs_write_atomic(path, "mine", 4, "t", &err), MR_OK);
    fputs("theirs, later", other);
    fclose(other);
    uint8_t *buf = NULL;
    size_t size = 0;
    assert_int_equal(mr_fs_read_capped(path, 100, &buf, &size, "t", &err), MR_OK);
    assert_int_equal(size, 4);
    assert_memory_equal(buf, "mine", 4);
    free(buf);
}

static void test_read_capped(void **state)
{
    (void)state;
    char path[160];
    mr_error err = {0};
    uint8_t *buf = (uint8_t *)&err, data[100];
    size_t size = 99;
    for (size_t i = 0; i < sizeof data; i++)
        data[i] = (uint8_t)(i * 7);
    snprintf(path, sizeof path, "%s/capped.bin", tmp_dir);
    write_raw(path, data, sizeof data);
    /* exactly at the cap: read; one byte over: refused before reading */
    assert_int_equal(mr_fs_read_capped(path, 100, &buf, &size, "t", &err), MR_OK);
    assert_int_equal(size, 100);
    assert_memory_equal(buf, data, 100);
    free(buf);
    assert_int_equal(mr_fs_read_capped(path, 99, &buf, &size, "capped", &err), MR_ERR_FORMAT);
    assert_null(buf);
    assert_int_equal(size, 0);
    assert_non_null(strstr(err.msg, "capped"));
    assert_non_null(strstr(err.msg, path));
    assert_non_null(strstr(err.msg, "byte offset 99"));
    /* an empty file: a buffer, size 0 */
    write_raw(path, data, 0);
    assert_int_equal(mr_fs_read_capped(path, 100, &buf, &size, "t", &err), MR_OK);
    assert_non_null(buf);
    assert_int_equal(size, 0);
    free(buf);
    /* a FIFO with no writer: refused at once, not waited on */
    snprintf(path, sizeof path, "%s/fifo", tmp_dir);
    assert_int_equal(mkfifo(path, 0600), 0);
    assert_int_equal(mr_fs_read_capped(path, 100, &buf, &size, "t", &err), MR_ERR_IO);
    assert_non_null(strstr(err.msg, "not a regular file"));
    assert_null(buf);
    assert_int_equal(mr_fs_read_capped(tmp_dir, 100, &buf, &size, "t", &err), MR_ERR_IO);
    snprintf(path, sizeof path, "%s/absent", tmp_dir);
    assert_int_equal(mr_fs_read_capped(path, 100, &buf, &size, "t", &err), MR_ERR_IO);
    assert_null(buf);
}

static void test_make_dirs(void **state)
{
    (void)state;
    char dir[160], file[200];
    mr_error err = {0};
    snprintf(dir, sizeof dir, "%s/a/b/c", tmp_dir);
    assert_int_equal(mr_fs_make_dirs(dir, "t", &err), MR_OK);
    struct stat st;
    assert_int_equal(stat(dir, &st), 0);
    assert_true(S_ISDIR(st.st_mode));
    assert_int_equal(mr_fs_make_dirs(dir, "t", &err), MR_OK); /* exists: fine */
    snprintf(file, sizeof file, "%s/plain", dir);
    write_raw(file, "x", 1);
    assert_int_equal(mr_fs_make_dirs(file, "t", &err), MR_ERR_IO);
    char below[240];
    snprintf(below, sizeof below, "%s/below", file); /* a file in the way */
    assert_int_equal(mr_fs_make_dirs(below, "mk", &err), MR_ERR_IO);
    assert_non_null(strstr(err.msg, "mk: "));
    assert_int_equal(mr_fs_make_dirs("", "mk", &err), MR_ERR_INVALID);
}

static void test_dir_of(void **state)
{
    (void)state;
    const char *cases[][2] = {{"x", "."},     {"/x", "/"},   {"a/b/c", "a/b"},
                              {"a/", "a"},    {"/a/b", "/a"}, {"./f", "."}};
    for (size_t i = 0; i < sizeof cases / sizeof cases[0]; i++) {
        char *d = mr_fs_dir_of(cases[i][0]);
        assert_non_null(d);
        assert_string_equal(d, cases[i][1]);
        free(d);
    }
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_crc32),
        cmocka_unit_test(test_le_layout),
        cmocka_unit_test(test_le_round_trip),
        cmocka_unit_test(test_sha256_feed),
        cmocka_unit_test(test_write_atomic),
        cmocka_unit_test(test_atomic_stream),
        cmocka_unit_test(test_write_atomic_ignores_foreign_tmp),
        cmocka_unit_test(test_read_capped),
        cmocka_unit_test(test_make_dirs),
        cmocka_unit_test(test_dir_of),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
