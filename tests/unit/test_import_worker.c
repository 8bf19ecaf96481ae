/*
 * test_import_worker.c - imports in a child process (server/import_worker.h)
 * and the asset blob that carries them back (mr_asset_blob_write/read).
 *
 * Real imports of real files (Debian's assimp test models), real fork,
 * real signals; what is checked:
 *  - the child's import is the in-process import, byte for byte (blobs of
 *    both are equal), for a skinned animated model, a refined one and one
 *    with cameras;
 *  - a broken file fails as it does in process (same code and message);
 *  - the limits: memory (a refinement that needs far more than the limit),
 *    wall clock, cancel, and a crash (the child killed by SIGSEGV) each
 *    end in an error that says which, and no child is left behind;
 *  - a 220-byte PLY whose face list declares 2e9 indices (issue 12 item 2:
 *    it grew past 12 GB in process) fails at the memory limit;
 *  - a blob cut short anywhere, or from another build, is refused.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <dirent.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/syscall.h>
#include <unistd.h>

#include "import_worker.h"
#include "microray.h"

#define MODELS "/usr/share/assimp/models"

static uint8_t *blob_of(const mr_asset *a, size_t *n)
{
    uint8_t *b = NULL;
    mr_error err = {0};
    if (mr_asset_blob_write(a, &b, n, &err) < 0)
        fail_msg("blob: %s", err.msg);
    return b;
}

static char worker_exe[2100]; /* the daemon's way: exec microrayd import-worker */

static void same_import_as(const char *path, const mr_refine_params *refine, const char *exe);

static void same_import(const char *path, const mr_refine_params *refine)
{
    same_import_as(path, refine, NULL);
}

static void same_import_as(const char *path, const mr_refine_params *refine, const char *exe)
{
    mr_error err = {0};
    mr_asset *here = NULL, *there = NULL;
    mr_asset_stage stage;
    if (mr_cache_import(path, refine, &here, &stage, &err) < 0)
        fail_msg("in process: %s", err.msg);
    mr_import_limits lim = {.memory_bytes = (size_t)1 << 30, .timeout_s = 120, .worker_exe = exe};
    if (mr_import_isolated(path, path, refine, &lim, NULL, NULL, &there, &stage, &err) < 0)
        fail_msg("in a child: %s", err.msg);
    size_t na, nb;
    uint8_t *a = blob_of(here, &na), *b = blob_of(there, &nb);
    assert_int_equal(na, nb);
    assert_memory_equal(a, b, na);
    assert_int_equal(mr_asset_triangle_count(here), mr_asset_triangle_count(there));
    free(a);
    free(b);
    mr_asset_free(here);
    mr_asset_free(there);
}

static void test_same_as_in_process(void **state)
{
    (void)state;
    same_import(MODELS "/X/BCN_Epileptic.X", NULL); /* skinned, animated */
    mr_refine_params r = {.rounds = 1, .amplitude = 0.01f, .frequency = 4, .octaves = 2, .seed = 7};
    same_import(MODELS "/X/BCN_Epileptic.X", &r);
    same_import(MODELS "/OBJ/box.obj", NULL);
}

/* The same through exec of the real binary (what the daemon does): the
 * result, the refine parameters on the command line (hex floats, so
 * bit-exact), and the memory limit on a fresh image. */
static void test_exec_mode(void **state)
{
    (void)state;
    const char *b = getenv("MR_BUILD_DIR");
    snprintf(worker_exe, sizeof worker_exe, "%s/microrayd", b ? b : "build");
    same_import_as(MODELS "/X/BCN_Epileptic.X", NULL, worker_exe);
    mr_refine_params r = {.rounds = 1, .amplitude = 0.01f, .frequency = 4.1f, .octaves = 2, .seed = 7};
    same_import_as(MODELS "/X/BCN_Epileptic.X", &r, worker_exe);
    mr_import_limits lim = {.memory_bytes = (size_t)64 << 20, .timeout_s = 120,
                            .worker_exe = worker_exe};
    mr_asset *a = NULL;
    mr_error err = {0};
    mr_refine_params heavy = {.rounds = 5};
    assert_int_equal(mr_import_isolated(MODELS "/X/BCN_Epileptic.X", "the dancer", &heavy, &lim,
                                        NULL, NULL, &a, NULL, &err),
                     MR_ERR_LIMIT);
    assert_non_null(strstr(err.msg, "used more than 64.0 MiB"));
    /* a binary that is not microrayd: the child's exec fails, and says so */
    lim.worker_exe = "/nonexistent/microrayd";
    assert_int_equal(mr_import_isolated(MODELS "/OBJ/box.obj", "box", NULL, &lim, NULL, NULL, &a,
                                        NULL, &err),
                     MR_ERR_IO);
    assert_non_null(strstr(err.msg, "exit 127"));
}

static void test_broken_file_as_in_process(void **state)
{
    (void)state;
    const char *path = MODELS "/invalid/malformed.obj";
    mr_error here = {0}, there = {0};
    mr_asset *a = NULL;
    mr_asset_stage s1, s2;
    int rc1 = mr_cache_import(path, NULL, &a, &s1, &here);
    assert_true(rc1 < 0);
    int rc2 = mr_import_isolated(path, path, NULL, NULL, NULL, NULL, &a, &s2, &there);
    assert_int_equal(rc2, rc1);
    assert_null(a);
    assert_int_equal(s2, s1);
    assert_string_equal(there.msg, here.msg);
}

/* No child of this process is left (every one was waited for). */
static void no_children(void)
{
    char path[64];
    snprintf(path, sizeof path, "/proc/self/task/%ld/children", (long)syscall(SYS_gettid));
    FILE *f = fopen(path, "r");
    assert_non_null(f);
    int c = fgetc(f);
    fclose(f);
    assert_int_equal(c, EOF);
}

/* Five Loop rounds of the dancer: ~7 M triangles, hundreds of MB and some
 * seconds; every limit below cuts it short. */
static const mr_refine_params HEAVY = {.rounds = 5};

static void test_memory_limit(void **state)
{
    (void)state;
    mr_import_limits lim = {.memory_bytes = (size_t)64 << 20, .timeout_s = 120};
    mr_asset *a = NULL;
    mr_error err = {0};
    double t0 = mr_now();
    int rc = mr_import_isolated(MODELS "/X/BCN_Epileptic.X", "the dancer", &HEAVY, &lim, NULL,
                                NULL, &a, NULL, &err);
    print_message("[ limit    ] %.2f s: %s\n", mr_now() - t0, err.msg);
    assert_int_equal(rc, MR_ERR_LIMIT);
    assert_null(a);
    assert_non_null(strstr(err.msg, "import of the dancer used more than 64.0 MiB"));
    no_children();
}

static void test_timeout(void **state)
{
    (void)state;
    mr_import_limits lim = {.memory_bytes = 0, .timeout_s = 0.3};
    mr_asset *a = NULL;
    mr_error err = {0};
    double t0 = mr_now();
    int rc = mr_import_isolated(MODELS "/X/BCN_Epileptic.X", "the dancer", &HEAVY, &lim, NULL,
                                NULL, &a, NULL, &err);
    double s = mr_now() - t0;
    assert_int_equal(rc, MR_ERR_LIMIT);
    assert_non_null(strstr(err.msg, "took longer than 0.3 s"));
    assert_true(s < 5); /* killed at the deadline, not at the import's end */
    no_children();
}

typedef struct poke {
    int calls;
    int signal; /* 0: just answer "interrupted" on the 4th call */
} poke;

/* Polled by the parent every 50 ms while the child imports. */
static bool interrupt_child(void *user)
{
    poke *p = user;
    if (++p->calls < 4)
        return false;
    if (!p->signal)
        return true;
    char path[64];
    snprintf(path, sizeof path, "/proc/self/task/%ld/children", (long)syscall(SYS_gettid));
    FILE *f = fopen(path, "r");
    int pid = 0;
    if (f && fscanf(f, "%d", &pid) == 1 && pid > 0 && p->calls == 4)
        kill(pid, p->signal);
    if (f)
        fclose(f);
    return false;
}

static void test_cancel(void **state)
{
    (void)state;
    poke p = {0};
    mr_asset *a = NULL;
    mr_error err = {0};
    double t0 = mr_now();
    int rc = mr_import_isolated(MODELS "/X/BCN_Epileptic.X", "the dancer", &HEAVY, NULL,
                                interrupt_child, &p, &a, NULL, &err);
    assert_int_equal(rc, MR_ERR_CANCELLED);
    assert_non_null(strstr(err.msg, "import of the dancer cancelled"));
    assert_true(mr_now() - t0 < 2);
    no_children();
}

/* The child dies mid-import: of a crash (SIGSEGV), or killed (SIGKILL:
 * what the kernel's OOM killer or an operator's kill -9 does). */
static void test_crash(void **state)
{
    (void)state;
    const int sigs[] = {SIGSEGV, SIGKILL};
    const char *const says[] = {"import of the dancer crashed the importer (SIGSEGV)",
                                "import of the dancer crashed the importer (SIGKILL, killed: out "
                                "of memory?)"};
    for (int k = 0; k < 2; k++) {
        poke p = {.signal = sigs[k]};
        mr_asset *a = NULL;
        mr_error err = {0};
        int rc = mr_import_isolated(MODELS "/X/BCN_Epileptic.X", "the dancer", &HEAVY, NULL,
                                    interrupt_child, &p, &a, NULL, &err);
        assert_int_equal(rc, MR_ERR_FORMAT);
        assert_null(a);
        if (!strstr(err.msg, says[k]))
            fail_msg("%s", err.msg);
        no_children();
    }
}

/* issue 12 item 2: a binary PLY of one face whose index list claims 2e9
 * entries; assimp believes it. */
static void test_ply_face_list_bomb(void **state)
{
    (void)state;
    char path[] = "/tmp/test_import_worker.XXXXXX";
    int fd = mkstemp(path);
    assert_true(fd >= 0);
    const char head[] = "ply\nformat binary_little_endian 1.0\nelement vertex 3\n"
                        "property float x\nproperty float y\nproperty float z\nelement face 1\n"
                        "property list uint int vertex_indices\nend_header\n";
    const float v[9] = {0, 0, 0, 1, 0, 0, 0, 1, 0};
    const uint32_t count = 2000000000u;
    const int32_t idx[3] = {0, 1, 2};
    assert_true(write(fd, head, sizeof head - 1) == (ssize_t)(sizeof head - 1));
    assert_true(write(fd, v, sizeof v) == (ssize_t)sizeof v);
    assert_true(write(fd, &count, sizeof count) == (ssize_t)sizeof count);
    assert_true(write(fd, idx, sizeof idx) == (ssize_t)sizeof idx);
    close(fd);
    mr_import_limits lim = {.memory_bytes = (size_t)256 << 20, .timeout_s = 120};
    mr_asset *a = NULL;
    mr_error err = {0};
    double t0 = mr_now();
    int rc = mr_import_isolated(path, "bomb.ply", NULL, &lim, NULL, NULL, &a, NULL, &err);
    print_message("[ bomb     ] %.2f s: %s\n", mr_now() - t0, err.msg);
    unlink(path);
    assert_int_equal(rc, MR_ERR_LIMIT);
    assert_non_null(strstr(err.msg, "used more than 256.0 MiB"));
    no_children();
}

static void test_blob_damage(void **state)
{
    (void)state;
    mr_asset *a = NULL;
    mr_error err = {0};
    assert_int_equal(mr_asset_load(MODELS "/X/BCN_Epileptic.X", &a, &err), MR_OK);
    size_t n;
    uint8_t *b = blob_of(a, &n);
    mr_asset *back = NULL;
    assert_int_equal(mr_asset_blob_read(b, n, &back, &err), MR_OK);
    mr_asset_free(back);
    /* cut short anywhere (every byte of the head, then a stride through
     * the arrays, and the last bytes): refused, nothing overread (ASan) */
    for (size_t len = 0; len < n; len += len < 4096 ? 1 : 997) {
        back = NULL;
        int rc = mr_asset_blob_read(b, len, &back, &err);
        if (rc != MR_ERR_FORMAT)
            fail_msg("a blob cut at %zu of %zu bytes read as %d", len, n, rc);
        assert_null(back);
    }
    assert_int_equal(mr_asset_blob_read(b, n - 1, &back, &err), MR_ERR_FORMAT);
    /* one byte too many, or another build's header */
    uint8_t *longer = malloc(n + 1);
    memcpy(longer, b, n);
    longer[n] = 0;
    assert_int_equal(mr_asset_blob_read(longer, n + 1, &back, &err), MR_ERR_FORMAT);
    longer[8] ^= 1; /* sizeof(mr_asset) */
    assert_int_equal(mr_asset_blob_read(longer, n, &back, &err), MR_ERR_FORMAT);
    free(longer);
    free(b);
    mr_asset_free(a);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_same_as_in_process),
        cmocka_unit_test(test_exec_mode),
        cmocka_unit_test(test_broken_file_as_in_process),
        cmocka_unit_test(test_memory_limit),
        cmocka_unit_test(test_timeout),
        cmocka_unit_test(test_cancel),
        cmocka_unit_test(test_crash),
        cmocka_unit_test(test_ply_face_list_bomb),
        cmocka_unit_test(test_blob_damage),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
