/*
 * test_hard_report.c - `make hard`'s own machinery: hard_report.h's HARD
 * lines and scripts/run-hard.sh's verdict, end to end. The test program
 * copies itself as the only "hard-case program" of a scratch build tree
 * (TMP/tests/hard/test_fake) and runs the real script on that tree; with
 * MR_HARD_FAKE set the program is that fake, whose one case does what the
 * variable says:
 *   pass     a figure within its tolerance          -> exit 0, row "ok"
 *   fail     a figure outside it                    -> exit 1, row "FAIL"
 *   nan      a NaN figure                           -> exit 1, NaN/Inf met
 *   silent   passes without reporting a figure      -> exit 1
 *   asan     reads past a heap block: AddressSanitizer stops the program
 *            (in a build without ASan the fake prints the line ASan would
 *            and exits 1, so the script's detection is still what is
 *            tested)                                 -> exit 1, reported
 * plus the pass/fail arithmetic of hard_holds and hard_max on NaN.
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
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#define HARD_KIND "fake"
#define TMP_DIR_TEMPLATE "/tmp/mr-hard-XXXXXX"
#include "../support/file_fixture.h"
#include "../support/hard_report.h"

/* ---- the fake hard-case program */

static const char *fake_mode;

static void test_fake_case(void **state)
{
    (void)state;
    if (!strcmp(fake_mode, "pass")) {
        HARD_CHECK("other", 1, "<=", 2, "a fake figure");
    } else if (!strcmp(fake_mode, "fail")) {
        HARD_CHECK("error", 5, "<=", 2, "a fake figure");
    } else if (!strcmp(fake_mode, "nan")) {
        HARD_CHECK("error", NAN, "<=", 1, "a fake figure");
    } else if (!strcmp(fake_mode, "asan")) {
        HARD_CHECK("other", 1, "<=", 2, "a fake figure");
#if defined(__SANITIZE_ADDRESS__)
        char *volatile p = malloc(8);
        volatile char c = p[8]; /* one past the block: ASan reports and stops the program */
        (void)c;
        free(p);
#else
        fprintf(stderr, "==1==ERROR: AddressSanitizer: heap-buffer-overflow (as ASan would report it)\n");
        exit(1);
#endif
    }
    /* "silent": nothing reported */
}

static int run_fake(void)
{
    const struct CMUnitTest tests[] = {cmocka_unit_test(test_fake_case)};
    return cmocka_run_group_tests_name("fake", tests, NULL, NULL);
}

/* ---- the script on a scratch tree holding the fake */

/* tmp_dir (file_fixture.h) is the tree: tmp_dir/tests/hard/test_fake. */
static int setup(void **state)
{
    if (file_fixture_setup(state) < 0)
        return -1;
    char cmd[512];
    snprintf(cmd, sizeof cmd, "mkdir -p '%s/tests/hard' && cp /proc/%d/exe '%s/tests/hard/test_fake'", tmp_dir,
             (int)getpid(), tmp_dir);
    return system(cmd) == 0 ? 0 : -1;
}

static char *last_out; /* the last run's output, freed by the next run and teardown */

static int teardown(void **state)
{
    free(last_out);
    return file_fixture_teardown(state);
}

/* Runs scripts/run-hard.sh on the tree with the fake in mode; returns its
 * exit status, its output (the report and where the logs are) in *out. */
static int run_script(const char *mode, const char **out)
{
    const char *src = getenv("MR_SOURCE_DIR");
    char cmd[1024], path[128];
    snprintf(path, sizeof path, "%s/out.txt", tmp_dir);
    snprintf(cmd, sizeof cmd, "MR_HARD_FAKE=%s bash '%s/scripts/run-hard.sh' '%s' >'%s' 2>&1", mode,
             src ? src : ".", tmp_dir, path);
    int rc = system(cmd);
    assert_true(WIFEXITED(rc));
    size_t len = 0;
    free(last_out);
    last_out = (char *)file_get(path, &len);
    last_out[len] = 0; /* file_get allocates a byte more */
    *out = last_out;
    return WEXITSTATUS(rc);
}

static void expect_in(const char *out, const char *what)
{
    if (!strstr(out, what))
        fail_msg("run-hard.sh's output lacks \"%s\":\n%s", what, out);
}

static void test_passing_figure(void **state)
{
    (void)state;
    const char *out;
    assert_int_equal(run_script("pass", &out), 0);
    expect_in(out, "## fake");
    expect_in(out, "| test_fake_case | other | a fake figure | 1 | <= 2 | ok |");
    expect_in(out, "| test_fake | fake | 1 | 0 | 1 |");
    expect_in(out, "every figure within its tolerance");
}

static void test_failing_figure(void **state)
{
    (void)state;
    const char *out;
    assert_int_not_equal(run_script("fail", &out), 0);
    expect_in(out, "| test_fake_case | error | a fake figure | 5 | <= 2 | FAIL |");
    expect_in(out, "(case failed: test_fake_case: a fake figure is 5, not <= 2)");
    expect_in(out, "1 cases failed or crashed; 1 figures outside their tolerance");
}

static void test_nan_figure(void **state)
{
    (void)state;
    const char *out;
    assert_int_not_equal(run_script("nan", &out), 0);
    expect_in(out, "| a fake figure | nan | <= 1 | FAIL |");
    expect_in(out, "| yes: test_fake_case: a fake figure |");
}

static void test_case_without_figure(void **state)
{
    (void)state;
    const char *out;
    assert_int_not_equal(run_script("silent", &out), 0);
    expect_in(out, "| test_fake_case | | (no figure reported) | | | FAIL |");
    expect_in(out, "cases without figures: test_fake_case");
}

static void test_sanitizer_report(void **state)
{
    (void)state;
    const char *out;
    assert_int_not_equal(run_script("asan", &out), 0);
    expect_in(out, "ERROR: AddressSanitizer: heap-buffer-overflow");
    expect_in(out, "sanitizer reports: test_fake");
}

/* What a figure is held to: the comparison, and a NaN passing none. */
static void test_holds(void **state)
{
    (void)state;
    assert_int_equal(hard_holds(1, "<", 2), 1);
    assert_int_equal(hard_holds(2, "<", 2), 0);
    assert_int_equal(hard_holds(2, "<=", 2), 1);
    assert_int_equal(hard_holds(2, "==", 2), 1);
    assert_int_equal(hard_holds(3, ">=", 2), 1);
    assert_int_equal(hard_holds(2, ">", 2), 0);
    assert_int_equal(hard_holds(1, "~", 2), -1);
    const char *ops[] = {"<", "<=", "==", ">=", ">"};
    for (int i = 0; i < 5; i++)
        assert_int_equal(hard_holds(NAN, ops[i], 0), 0);
    assert_true(isnan(hard_max(1, NAN)) && isnan(hard_max(NAN, 1)));
    assert_true(isnan(hard_min(1, NAN)) && isnan(hard_min(NAN, 1)));
    assert_true(hard_max(1, 2) == 2 && hard_min(1, 2) == 1);
}

int main(void)
{
    fake_mode = getenv("MR_HARD_FAKE");
    if (fake_mode)
        return run_fake();
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_holds),
        cmocka_unit_test(test_passing_figure),
        cmocka_unit_test(test_failing_figure),
        cmocka_unit_test(test_nan_figure),
        cmocka_unit_test(test_case_without_figure),
        cmocka_unit_test(test_sanitizer_report),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
