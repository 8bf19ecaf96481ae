/*
 * test_bench_report.c - bench/report.sh (issue 16 part 4) on a known set of
 * points, with the real gnuplot: the report names the machine, has a plot
 * (a PNG file gnuplot wrote) and a table per kind and scene, marks exactly
 * the Pareto front (one front per scene, or per level where each level's
 * error is against its own reference), shows a reference's 0 error as
 * such, and carries the benchmarks' output.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include "daemon_fixture.h"

static void write_file(const char *path, const char *text)
{
    FILE *f = fopen(path, "w");
    assert_non_null(f);
    fputs(text, f);
    fclose(f);
}

/* The table row of method m at level l, or NULL. */
static const char *row(const char *report, const char *m, const char *l)
{
    char key[128];
    snprintf(key, sizeof key, "\n| %s | %s | ", m, l);
    return strstr(report, key);
}

static bool on_front(const char *report, const char *m, const char *l)
{
    const char *r = row(report, m, l);
    assert_non_null(r);
    const char *end = strchr(r + 1, '\n');
    const char *yes = strstr(r, "| yes |");
    return yes && (!end || yes < end);
}

static void test_report_of_known_points(void **state)
{
    (void)state;
    char points[600], log[600], out[600], cmd[4000], path[700];
    snprintf(points, sizeof points, "%s/points.tsv", fx_tmp);
    snprintf(log, sizeof log, "%s/bench.log", fx_tmp);
    snprintf(out, sizeof out, "%s/out", fx_tmp);
    /* scene A, one truth for every level: fast-and-coarse and slow-and-fine
     * are both on the front, "slow" (slower and worse than b2) is not */
    write_file(points, "k\tscene A\tfast\t1\t1\terr\t0.1\t\n"
                       "k\tscene A\tfast\t2\t2\terr\t0.01\t\n"
                       "k\tscene A\tslow\t1\t3\terr\t0.05\t\n"
                       "k\tscene A\tslow\t2\t8\terr\t0.001\t\n"
                       /* scene B, errors against each level's reference */
                       "k\tscene B\tref\t1\t5\terr\t0\t1\n"
                       "k\tscene B\tapprox\t1\t2\terr\t0.2\t1\n"
                       "k\tscene B\tref\t2\t50\terr\t0\t2\n"
                       "k\tscene B\tapprox\t2\t60\terr\t0.3\t2\n");
    write_file(log, "the benchmarks' own lines\n");
    snprintf(cmd, sizeof cmd, "bash '%s/bench/report.sh' '%s' '%s' '%s' 2>/dev/null", fx_src_dir,
             points, log, out);
    assert_int_equal(system(cmd), 0);
    snprintf(path, sizeof path, "%s/report.md", out);
    char *r = fx_slurp(path, NULL);
    assert_non_null(r);
    assert_non_null(strstr(r, "cores"));
    assert_non_null(strstr(r, "the benchmarks' own lines"));
    assert_non_null(strstr(r, "![k: scene A](plots/k-scene-A.png)"));
    assert_non_null(strstr(r, "![k: scene B](plots/k-scene-B.png)"));
    /* gnuplot wrote the plots: PNG signatures */
    static const char *const PNGS[] = {"k-scene-A.png", "k-scene-B.png"};
    for (int i = 0; i < 2; i++) {
        snprintf(path, sizeof path, "%s/plots/%s", out, PNGS[i]);
        char *png = fx_slurp(path, NULL);
        assert_non_null(png);
        assert_memory_equal(png, "\x89PNG", 4);
        free(png);
    }
    /* scene A: one front */
    assert_true(on_front(r, "fast", "1"));
    assert_true(on_front(r, "fast", "2"));
    assert_false(on_front(r, "slow", "1"));
    assert_true(on_front(r, "slow", "2"));
    /* scene B: a front per level; the reference's 0 reads as such */
    assert_true(on_front(r, "approx", "1"));
    assert_true(on_front(r, "ref", "1"));
    assert_true(on_front(r, "ref", "2"));
    assert_false(on_front(r, "approx", "2"));
    assert_non_null(strstr(row(r, "ref", "2"), "0 (reference)"));
    /* nothing but the plots is left beside them */
    snprintf(cmd, sizeof cmd, "test $(ls '%s/plots' | wc -l) -eq 2", out);
    assert_int_equal(system(cmd), 0);
    free(r);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_report_of_known_points),
    };
    return cmocka_run_group_tests_name("bench_report", tests, fx_dirs_setup, fx_dirs_teardown);
}
