/*
 * test_util.c - the small helpers of core/util that are not about files:
 *  - hex.h: known answers for every nibble value, the empty input, and the
 *    spelling check (uppercase, short, long, NULL and non-digits refused);
 *  - dup.h: copies are equal and distinct, NULL and empty inputs give what
 *    the header promises, and a byte range keeps an embedded NUL;
 *  - fs.h: write-all puts every byte in the file, a directory fsync works
 *    and names a missing directory, removal empties and removes a
 *    directory and accepts one that is already gone;
 *  - clock.h: mr_now and mr_now_ms never go backwards and agree with each
 *    other.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "util/clock.h"
#include "util/dup.h"
#include "util/file_io.h"
#include "util/hex.h"

static void test_hex_encode(void **state)
{
    (void)state;
    uint8_t all[16];
    for (int i = 0; i < 16; i++)
        all[i] = (uint8_t)(i * 17); /* 00, 11, ..., ff: every digit in both nibbles */
    char out[33];
    mr_hex_encode(all, sizeof all, out);
    assert_string_equal(out, "00112233445566778899aabbccddeeff");
    static const uint8_t mixed[] = {0x0f, 0xf0, 0x7a, 0xa7};
    mr_hex_encode(mixed, sizeof mixed, out);
    assert_string_equal(out, "0ff07aa7");
    out[0] = 'x';
    mr_hex_encode(mixed, 0, out);
    assert_string_equal(out, "");
}

static void test_hex_is_lower(void **state)
{
    (void)state;
    assert_true(mr_hex_is_lower("0123456789abcdef", 16));
    assert_true(mr_hex_is_lower("", 0));
    assert_false(mr_hex_is_lower("0123456789ABCDEF", 16));
    assert_false(mr_hex_is_lower("0123456789abcde", 16));   /* short */
    assert_false(mr_hex_is_lower("0123456789abcdef0", 16)); /* long */
    assert_false(mr_hex_is_lower("0123456789abcdeg", 16));
    assert_false(mr_hex_is_lower("../x", 4));
    assert_false(mr_hex_is_lower(NULL, 0));
}

static void test_dup(void **state)
{
    (void)state;
    const char *name = "bone0";
    char *s = mr_strdup(name);
    assert_non_null(s);
    assert_ptr_not_equal(s, name);
    assert_string_equal(s, name);
    free(s);
    assert_null(mr_strdup(NULL));
    s = mr_strdup("");
    assert_string_equal(s, "");
    free(s);

    static const uint32_t v[3] = {1, 0xdeadbeef, 3};
    uint32_t *c = mr_memdup(v, sizeof v);
    assert_non_null(c);
    assert_memory_equal(c, v, sizeof v);
    free(c);
    assert_null(mr_memdup(NULL, 4));
    assert_null(mr_memdup(v, 0));

    /* a text column may hold a NUL: all n bytes are copied, then one more */
    s = mr_memdup_str("ab\0cd", 5);
    assert_non_null(s);
    assert_memory_equal(s, "ab\0cd", 6);
    free(s);
    s = mr_memdup_str("abc", 2);
    assert_string_equal(s, "ab");
    free(s);
    s = mr_memdup_str(NULL, 0);
    assert_string_equal(s, "");
    free(s);
}

static void test_fs(void **state)
{
    (void)state;
    char dir[64] = "/tmp/mr-util-fs-XXXXXX", path[128];
    assert_non_null(mkdtemp(dir));
    static char big[300000];
    for (size_t i = 0; i < sizeof big; i++)
        big[i] = (char)(i * 7);
    for (int k = 0; k < 3; k++) {
        snprintf(path, sizeof path, "%s/f%d", dir, k);
        mr_error werr = {0};
        assert_int_equal(mr_fs_write_atomic(path, big, sizeof big, "test", &werr), MR_OK);
        struct stat st;
        assert_int_equal(stat(path, &st), 0);
        assert_int_equal(st.st_size, sizeof big);
    }
    mr_error err = {0};
    assert_int_equal(mr_fs_remove_dir(dir, &err), MR_OK);
    assert_int_not_equal(access(dir, F_OK), 0);
    assert_int_equal(mr_fs_remove_dir(dir, &err), MR_OK); /* gone already */
    /* a directory that cannot be opened (a regular file) names itself */
    snprintf(path, sizeof path, "%s.file", dir);
    assert_int_equal(mr_fs_write_atomic(path, big, 1, "test", &err), MR_OK);
    assert_int_equal(mr_fs_remove_dir(path, &err), MR_ERR_IO);
    assert_non_null(strstr(err.msg, path));
    unlink(path);
}

static void test_clock(void **state)
{
    (void)state;
    double s0 = mr_now();
    int64_t m0 = mr_now_ms();
    double last = s0;
    for (int i = 0; i < 100000; i++) {
        double t = mr_now();
        assert_true(t >= last);
        last = t;
    }
    int64_t m1 = mr_now_ms();
    double s1 = mr_now();
    assert_true(m1 >= m0);
    /* The same clock: the milliseconds lie within the seconds readings. */
    assert_true((double)m0 >= s0 * 1e3 - 1.0 && (double)m1 <= s1 * 1e3 + 1.0);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_hex_encode),
        cmocka_unit_test(test_hex_is_lower),
        cmocka_unit_test(test_dup),
        cmocka_unit_test(test_fs),
        cmocka_unit_test(test_clock),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
