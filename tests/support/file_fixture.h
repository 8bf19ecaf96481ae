/*
 * file_fixture.h - what tests on real files share: the cmocka group fixture
 * of a fresh directory tmp_dir under /tmp (named after TMP_DIR_TEMPLATE,
 * which may be defined before the include), removed with everything in it
 * when the group ends (pass file_fixture_setup and file_fixture_teardown to
 * cmocka_run_group_tests), and whole-file helpers that fail the test rather
 * than return errors. Include after <cmocka.h>.
 */
#ifndef MR_TEST_FILE_FIXTURE_H
#define MR_TEST_FILE_FIXTURE_H

#include <dirent.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

#ifndef TMP_DIR_TEMPLATE
#define TMP_DIR_TEMPLATE "/tmp/mr-test-XXXXXX"
#endif

static char tmp_dir[64];

static int file_fixture_setup(void **state)
{
    (void)state;
    snprintf(tmp_dir, sizeof tmp_dir, "%s", TMP_DIR_TEMPLATE);
    return mkdtemp(tmp_dir) ? 0 : -1;
}

static int file_fixture_teardown(void **state)
{
    (void)state;
    char cmd[128];
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", tmp_dir);
    return system(cmd) == 0 ? 0 : -1;
}

/* path holds exactly the n bytes at b afterwards. */
static inline void file_put(const char *path, const void *b, size_t n)
{
    FILE *fp = fopen(path, "wb");
    assert_non_null(fp);
    assert_int_equal(fwrite(b, 1, n, fp), n);
    fclose(fp);
}

/* The whole file, malloc'ed (one byte more, so a 0-byte file works). */
static inline uint8_t *file_get(const char *path, size_t *n)
{
    FILE *fp = fopen(path, "rb");
    assert_non_null(fp);
    struct stat st;
    assert_int_equal(fstat(fileno(fp), &st), 0);
    *n = (size_t)st.st_size;
    uint8_t *b = malloc(*n + 1);
    assert_non_null(b);
    assert_int_equal(fread(b, 1, *n, fp), *n);
    fclose(fp);
    return b;
}

/* Entries of dir whose name contains `contains` ("" for all), not . or .. */
static inline size_t file_count(const char *dir, const char *contains)
{
    DIR *d = opendir(dir);
    assert_non_null(d);
    size_t n = 0;
    for (struct dirent *e; (e = readdir(d));)
        if (strcmp(e->d_name, ".") && strcmp(e->d_name, "..") && strstr(e->d_name, contains))
            n++;
    closedir(d);
    return n;
}

#endif /* MR_TEST_FILE_FIXTURE_H */
