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
#include "util/murmur3.h"

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

/* MurmurHash3_x86_32 against published test vectors (the set widely used
 * to check ports of Appleby's reference code: empty input with three
 * seeds, the endianness probe 21 43 65 87, every tail length of zero bytes
 * and of 21 43 65 87, and strings with seed 0x9747b28c), and the
 * Cryptomatte ids of the specification's own example manifest. */
static void test_murmur3(void **state)
{
    static const struct {
        const char *data;
        size_t len;
        uint32_t seed, want;
    } v[] = {
        {"", 0, 0, 0},
        {"", 0, 1, 0x514e28b7u},
        {"", 0, 0xffffffffu, 0x81f16f39u},
        {"\xff\xff\xff\xff", 4, 0, 0x76293b50u},
        {"\x21\x43\x65\x87", 4, 0, 0xf55b516bu},
        {"\x21\x43\x65\x87", 4, 0x5082edeeu, 0x2362f9deu},
        {"\x21\x43\x65", 3, 0, 0x7e4a8634u},
        {"\x21\x43", 2, 0, 0xa0f7b07au},
        {"\x21", 1, 0, 0x72661cf4u},
        {"\0\0\0\0", 4, 0, 0x2362f9deu},
        {"\0\0\0", 3, 0, 0x85f0b427u},
        {"\0\0", 2, 0, 0x30f4c306u},
        {"\0", 1, 0, 0x514e28b7u},
        {"aaaa", 4, 0x9747b28cu, 0x5a97808au},
        {"aaa", 3, 0x9747b28cu, 0x283e0130u},
        {"aa", 2, 0x9747b28cu, 0x5d211726u},
        {"a", 1, 0x9747b28cu, 0x7fa09ea6u},
        {"abcd", 4, 0x9747b28cu, 0xf0478627u},
        {"abc", 3, 0x9747b28cu, 0xc84a62ddu},
        {"ab", 2, 0x9747b28cu, 0x74875592u},
        {"Hello, world!", 13, 0x9747b28cu, 0x24884cbau},
        {"Hello, world!", 13, 1234, 0xfaf6cdb3u},
        {"Hello, world!", 13, 4321, 0xbf505788u},
    };
    (void)state;
    for (size_t i = 0; i < sizeof v / sizeof v[0]; i++) {
        uint32_t got = mr_murmur3_32(v[i].data, v[i].len, v[i].seed);
        if (got != v[i].want)
            fail_msg("vector %zu (%zu bytes, seed %08x): %08x, expected %08x", i, v[i].len,
                     v[i].seed, got, v[i].want);
    }
    /* The Cryptomatte specification's example manifest:
     * {"bunny":"13851a76", "default":"42c9679f"}, CryptoMaterial
     * {"bunny_porcelain_mat":"b24b26d4"}. */
    assert_int_equal(mr_cryptomatte_id_bits("bunny"), 0x13851a76u);
    assert_int_equal(mr_cryptomatte_id_bits("default"), 0x42c9679fu);
    assert_int_equal(mr_cryptomatte_id_bits("bunny_porcelain_mat"), 0xb24b26d4u);
    float f = mr_cryptomatte_id("bunny");
    uint32_t bits;
    memcpy(&bits, &f, sizeof bits);
    assert_int_equal(bits, 0x13851a76u);
    /* uint32_to_float32: the exponent is clamped to 1..254 (no denormal,
     * Inf or NaN id), sign and mantissa are kept. */
    assert_int_equal(mr_cryptomatte_bits(0x00000001u), 0x00800001u);
    assert_int_equal(mr_cryptomatte_bits(0x807fffffu), 0x80ffffffu);
    assert_int_equal(mr_cryptomatte_bits(0x7f800000u), 0x7f000000u);
    assert_int_equal(mr_cryptomatte_bits(0xffc01234u), 0xff401234u);
    assert_int_equal(mr_cryptomatte_bits(0x3f800000u), 0x3f800000u);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_hex_encode),
        cmocka_unit_test(test_hex_is_lower),
        cmocka_unit_test(test_dup),
        cmocka_unit_test(test_fs),
        cmocka_unit_test(test_clock),
        cmocka_unit_test(test_murmur3),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
