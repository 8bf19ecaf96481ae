/*
 * test_sandbox.c - a render worker's confinement (server/sandbox.h) on the
 * real kernel: in a child process confined as a worker confines itself,
 * every kind of access the worker needs works and everything else in the
 * data directory and beyond is refused.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include "sandbox.h"

static char tmp[64];

static void write_file(const char *path)
{
    FILE *f = fopen(path, "w");
    assert_non_null(f);
    fputs("x", f);
    fclose(f);
}

static bool can_read(const char *path)
{
    int fd = open(path, O_RDONLY | O_CLOEXEC);
    if (fd >= 0)
        close(fd);
    return fd >= 0;
}

static bool can_create(const char *path)
{
    int fd = open(path, O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0644);
    if (fd >= 0)
        close(fd);
    return fd >= 0;
}

static bool can_run(const char *exe)
{
    pid_t pid = fork();
    if (pid == 0) {
        execl(exe, exe, (char *)NULL);
        _exit(127);
    }
    int st = 0;
    waitpid(pid, &st, 0);
    return WIFEXITED(st) && WEXITSTATUS(st) == 0;
}

/* The checks, run in the confined child; each failed one sets a bit. */
enum {
    SYSTEM_READ = 1, ROOT_READ = 2, UPLOAD_READ = 4, DERIVED_WRITE = 8, DERIVED_RENAME = 16,
    STORE_REFUSED = 32, FRAMES_REFUSED = 64, DATA_WRITE_REFUSED = 128, OUTSIDE_REFUSED = 256,
    RUN_SYSTEM = 512, NEW_KIND_FOLDER = 1024
};

static int confined_checks(const char *data, const char *root)
{
    char p[512], q[512];
    int failed = 0;
    failed |= can_read("/etc/passwd") ? 0 : SYSTEM_READ;
    snprintf(p, sizeof p, "%s/model.obj", root);
    failed |= can_read(p) ? 0 : ROOT_READ;
    snprintf(p, sizeof p, "%s/assets/0123", data);
    failed |= can_read(p) ? 0 : UPLOAD_READ;
    /* a derived-data file as util/file_io.h writes one: temporary, rename */
    snprintf(p, sizeof p, "%s/dmm/key.tmp", data);
    snprintf(q, sizeof q, "%s/dmm/key.dmm", data);
    failed |= can_create(p) ? 0 : DERIVED_WRITE;
    failed |= rename(p, q) == 0 && can_read(q) ? 0 : DERIVED_RENAME;
    snprintf(p, sizeof p, "%s/svo", data); /* made by the sandbox, writable */
    struct stat st;
    failed |= stat(p, &st) == 0 && S_ISDIR(st.st_mode) ? 0 : NEW_KIND_FOLDER;
    snprintf(p, sizeof p, "%s/microray.sqlite", data);
    failed |= !can_read(p) && errno == EACCES ? 0 : STORE_REFUSED;
    snprintf(p, sizeof p, "%s/frames/job/0000.exr", data);
    failed |= !can_read(p) && errno == EACCES ? 0 : FRAMES_REFUSED;
    snprintf(p, sizeof p, "%s/planted", data);
    failed |= !can_create(p) && errno == EACCES ? 0 : DATA_WRITE_REFUSED;
    snprintf(p, sizeof p, "%s/outside", tmp);
    failed |= !can_create(p) && !can_read("/root/.bashrc") ? 0 : OUTSIDE_REFUSED;
    failed |= can_run("/bin/true") ? 0 : RUN_SYSTEM;
    return failed;
}

static void test_worker_confinement(void **state)
{
    (void)state;
    char data[128], root[128], p[256];
    snprintf(data, sizeof data, "%s/data", tmp);
    snprintf(root, sizeof root, "%s/root", tmp);
    const char *dirs[] = {data, root, "assets", "dmm", "frames", "frames/job"};
    for (size_t i = 0; i < sizeof dirs / sizeof *dirs; i++) {
        if (i < 2)
            snprintf(p, sizeof p, "%s", dirs[i]);
        else
            snprintf(p, sizeof p, "%s/%s", data, dirs[i]);
        assert_int_equal(mkdir(p, 0755), 0);
    }
    snprintf(p, sizeof p, "%s/model.obj", root);
    write_file(p);
    snprintf(p, sizeof p, "%s/assets/0123", data);
    write_file(p);
    snprintf(p, sizeof p, "%s/microray.sqlite", data);
    write_file(p);
    snprintf(p, sizeof p, "%s/frames/job/0000.exr", data);
    write_file(p);

    int pipefd[2];
    assert_int_equal(pipe(pipefd), 0);
    pid_t pid = fork();
    if (pid == 0) {
        mr_error err = {0};
        const char *roots[] = {root};
        int rc = mr_sandbox_apply(data, roots, 1, NULL, &err);
        int failed = rc == MR_OK ? confined_checks(data, root) : -1;
        if (rc != MR_OK)
            fprintf(stderr, "%s\n", err.msg);
        if (write(pipefd[1], &rc, sizeof rc) != sizeof rc ||
            write(pipefd[1], &failed, sizeof failed) != sizeof failed)
            _exit(1);
        _exit(0);
    }
    close(pipefd[1]);
    int rc = 0, failed = 0;
    assert_int_equal(read(pipefd[0], &rc, sizeof rc), sizeof rc);
    assert_int_equal(read(pipefd[0], &failed, sizeof failed), sizeof failed);
    close(pipefd[0]);
    waitpid(pid, NULL, 0);
    if (rc == MR_ERR_NOT_FOUND) {
        print_message("[ sandbox  ] this kernel has no Landlock: render workers run unconfined\n");
        skip();
    }
    assert_int_equal(rc, MR_OK);
    if (failed)
        fail_msg("confined checks failed: 0x%x (see the enum)", failed);
    /* the parent, not confined, still sees everything */
    snprintf(p, sizeof p, "%s/microray.sqlite", data);
    assert_true(can_read(p));
}

static int setup(void **state)
{
    (void)state;
    snprintf(tmp, sizeof tmp, "/tmp/test_sandbox.XXXXXX");
    return mkdtemp(tmp) ? 0 : -1;
}

static int teardown(void **state)
{
    (void)state;
    char cmd[128];
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", tmp);
    return system(cmd) == 0 ? 0 : -1;
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_worker_confinement),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
