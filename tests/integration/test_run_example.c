/*
 * test_run_example.c - `make run` (scripts/run-example.sh) leaves nothing
 * behind (issue 19): it runs a fresh daemon on a data directory of its own
 * under $TMPDIR and removes it at the end, also when interrupted like a
 * Ctrl-C (SIGINT to its process group), and never writes into
 * ~/.local/share/microray. Before, every run added its frames there (about
 * 20 MB) and a run after a Ctrl-C first finished the old job.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <errno.h>

#include "daemon_fixture.h"

static char home[400], tmpdir[400], job_path[400], out_dir[400];

/* Starts the script in a process group of its own (as a terminal would run
 * it), its output in log; returns its pid. */
static pid_t start_script(const char *job, const char *log)
{
    FILE *f = fopen(job_path, "w");
    assert_non_null(f);
    fputs(job, f);
    fclose(f);
    pid_t pid = fork();
    if (pid == 0) {
        setpgid(0, 0);
        FILE *o = freopen(log, "w", stdout);
        FILE *e = freopen(log, "a", stderr);
        (void)o, (void)e;
        setenv("HOME", home, 1);
        setenv("TMPDIR", tmpdir, 1);
        setenv("MICRORAY_RUN_JOB", job_path, 1);
        setenv("MICRORAY_RUN_OUT", out_dir, 1);
        unsetenv("MICRORAY_DATA");
        unsetenv("XDG_DATA_HOME");
        char script[2200];
        snprintf(script, sizeof script, "%s/scripts/run-example.sh", fx_src_dir);
        execl("/bin/bash", "bash", script, fx_build_dir, (char *)NULL);
        _exit(127);
    }
    setpgid(pid, pid);
    return pid;
}

static int wait_status(pid_t pid)
{
    int st = 0;
    waitpid(pid, &st, 0);
    return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
}

static int entries(const char *dir)
{
    DIR *d = opendir(dir);
    if (!d)
        return -1;
    int n = 0;
    for (struct dirent *e; (e = readdir(d));)
        n += strcmp(e->d_name, ".") && strcmp(e->d_name, "..");
    closedir(d);
    return n;
}

/* Nothing of the run is left: its data directory is gone from $TMPDIR and
 * nothing was written below $HOME. */
static void assert_nothing_left(const char *log)
{
    char *text = fx_slurp(log, NULL);
    if (entries(tmpdir) != 0)
        fail_msg("%s is not empty after the run: %s", tmpdir, text);
    if (entries(home) != 0)
        fail_msg("the run wrote below $HOME (%s): %s", home, text);
    free(text);
}

static void test_run_cleans_up(void **state)
{
    (void)state;
    char log[600];
    snprintf(log, sizeof log, "%s/run.log", fx_tmp);
    char *job = fx_small_job(2, 64, NULL);
    pid_t pid = start_script(job, log);
    free(job);
    int st = wait_status(pid);
    char *text = fx_slurp(log, NULL);
    if (st != 0)
        fail_msg("run-example.sh exited %d: %s", st, text);
    free(text);
    char frame[600];
    snprintf(frame, sizeof frame, "%s/0002.exr", out_dir);
    struct stat sb;
    assert_int_equal(stat(frame, &sb), 0);
    assert_nothing_left(log);
}

/* Ctrl-C in the middle: the client, the script and the daemon end, and the
 * data directory goes with them. */
static void test_run_interrupted_cleans_up(void **state)
{
    (void)state;
    char log[600];
    snprintf(log, sizeof log, "%s/run-int.log", fx_tmp);
    snprintf(out_dir, sizeof out_dir, "%s/out-interrupted", fx_tmp);
    char *job = fx_small_job(400, 240, NULL);
    pid_t pid = start_script(job, log);
    free(job);
    /* wait until the job renders: a frame arrived in the output folder */
    char frame[600];
    snprintf(frame, sizeof frame, "%s/0000.exr", out_dir);
    struct stat sb;
    for (int i = 0; i < 1200 && stat(frame, &sb) != 0; i++)
        fx_sleep_ms(50);
    assert_int_equal(stat(frame, &sb), 0);
    char *text = fx_slurp(log, NULL);
    const char *p = strstr(text, "(pid ");
    assert_non_null(p);
    pid_t daemon = (pid_t)atoi(p + 5);
    free(text);
    assert_true(daemon > 0);
    kill(-pid, SIGINT); /* what a terminal's Ctrl-C does */
    int st = wait_status(pid);
    assert_int_equal(st, 130);
    /* the daemon was the script's child: stopped and reaped by it */
    assert_int_equal(kill(daemon, 0), -1);
    assert_int_equal(errno, ESRCH);
    assert_nothing_left(log);
}

static int setup(void **state)
{
    (void)state;
    fx_init_dirs();
    snprintf(home, sizeof home, "%s/home", fx_tmp);
    snprintf(tmpdir, sizeof tmpdir, "%s/tmp", fx_tmp);
    snprintf(job_path, sizeof job_path, "%s/job.json", fx_tmp);
    snprintf(out_dir, sizeof out_dir, "%s/out", fx_tmp);
    assert_int_equal(mkdir(home, 0755), 0);
    assert_int_equal(mkdir(tmpdir, 0755), 0);
    return 0;
}

static int teardown(void **state)
{
    (void)state;
    return fx_cleanup_dirs() ? 0 : -1;
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_run_cleans_up),
        cmocka_unit_test(test_run_interrupted_cleans_up),
    };
    return cmocka_run_group_tests_name("run_example", tests, setup, teardown);
}
