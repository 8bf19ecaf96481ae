/*
 * import_worker.c - mr_import_isolated: start an import child (child.h),
 * read the asset back (import_worker.h).
 *
 * The daemon's child execs `microrayd import-worker`, a fresh image with no
 * lock a daemon thread could have held; single-threaded callers (tests,
 * harnesses) may let the forked child import in the parent's image.
 *
 * The result travels as one message on a pipe: a header (status, failing
 * stage, message length, blob length), the message, the blob. The parent
 * reads it while the child writes (no pipe-buffer deadlock) and judges the
 * child by its exit: a complete message and exit 0 is a result; anything
 * else (a signal, a limit, a short message) is an error naming what
 * happened.
 */
#define _GNU_SOURCE
#include "import_worker.h"

#include "child.h"

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>


#define POLL_MS 50
#define RESULT_FD MR_CHILD_FD

typedef struct result_header {
    int32_t rc;
    int32_t stage;
    uint32_t message_len;
    uint32_t pad;
    uint64_t blob_len;
} result_header;

void mr_import_limits_default(mr_import_limits *out)
{
    long pages = sysconf(_SC_PHYS_PAGES), page = sysconf(_SC_PAGESIZE);
    size_t quarter = pages > 0 && page > 0 ? (size_t)pages * (size_t)page / 4 : 0;
    size_t gib = (size_t)1 << 30;
    out->memory_bytes = quarter > gib ? quarter : gib;
    out->timeout_s = 300;
}

static bool write_all(int fd, const void *p, size_t n)
{
    const uint8_t *b = p;
    while (n > 0) {
        ssize_t w = write(fd, b, n);
        if (w < 0 && errno == EINTR)
            continue;
        if (w <= 0)
            return false;
        b += w;
        n -= (size_t)w;
    }
    return true;
}

int mr_import_worker_run(const char *path, const mr_refine_params *refine)
{
    mr_error e = {0};
    mr_asset *asset = NULL;
    mr_asset_stage stage = MR_ASSET_STAGE_LOAD;
    uint8_t *blob = NULL;
    size_t blob_len = 0;
    int rc = mr_cache_import(path, refine, &asset, &stage, &e);
    if (rc == MR_OK)
        rc = mr_asset_blob_write(asset, &blob, &blob_len, &e);
    result_header h = {.rc = rc, .stage = (int32_t)stage};
    if (rc < 0) {
        h.message_len = (uint32_t)strnlen(e.msg, sizeof e.msg);
        blob_len = 0;
    }
    h.blob_len = blob_len;
    bool ok = write_all(RESULT_FD, &h, sizeof h) && write_all(RESULT_FD, e.msg, h.message_len) &&
              write_all(RESULT_FD, blob, blob_len);
    /* freed, though the process ends next: an exec'ed worker exits through
     * main, where a sanitizer build's leak check would fail it */
    free(blob);
    mr_asset_free(asset);
    return ok ? 0 : 122;
}

typedef struct fork_only {
    const char *path;
    const mr_refine_params *refine;
} fork_only;

static int import_here(void *user)
{
    fork_only *f = user;
    return mr_import_worker_run(f->path, f->refine);
}

typedef enum verdict { RAN, CANCELLED, TIMED_OUT, TOO_BIG } verdict;

int mr_import_isolated(const char *path, const char *label, const mr_refine_params *refine,
                       const mr_import_limits *lim, bool (*interrupted)(void *user), void *user,
                       mr_asset **out, mr_asset_stage *stage, mr_error *err)
{
    *out = NULL;
    if (stage)
        *stage = MR_ASSET_STAGE_LOAD;
    mr_import_limits none = {0};
    if (!lim)
        lim = &none;
    int fds[2];
    if (pipe2(fds, O_CLOEXEC) != 0)
        return mr_error_set(err, MR_ERR_IO, "import of %s: pipe: %s", label, strerror(errno));
    /* Everything the child needs is made here, before fork: after it the
     * child may only make async-signal-safe calls until it execs. */
    char rounds[16], amplitude[40], frequency[40], octaves[16], seed[16], threads[16];
    char *argv[12] = {"microrayd", "import-worker", (char *)path, NULL};
    if (refine) {
        snprintf(rounds, sizeof rounds, "%u", refine->rounds);
        snprintf(amplitude, sizeof amplitude, "%a", (double)refine->amplitude);
        snprintf(frequency, sizeof frequency, "%a", (double)refine->frequency);
        snprintf(octaves, sizeof octaves, "%u", refine->octaves);
        snprintf(seed, sizeof seed, "%u", (unsigned)refine->seed);
        snprintf(threads, sizeof threads, "%u", refine->threads);
        char *more[] = {"--refine", rounds, amplitude, frequency, octaves, seed, threads, NULL};
        memcpy(argv + 3, more, sizeof more);
    }
    /* the address space the import may take: on top of what is mapped
     * (the parent's image after fork, or a fresh image's libraries after
     * exec: 2 GiB covers them and the allocator's per-thread arenas),
     * with room for the import thread's stack */
    rlim_t as_limit = 0;
    if (lim->memory_bytes && !MR_SANITIZED) {
        size_t base = lim->worker_exe ? (size_t)2 << 30 : mr_child_memory(getpid(), false);
        as_limit = (rlim_t)(base + MR_ASSET_IMPORT_STACK_BYTES + lim->memory_bytes);
    }
    /* a backstop behind the parent's wall clock (SIGXCPU) */
    mr_child_limits child = {.address_space = (size_t)as_limit,
                             .cpu_seconds = lim->timeout_s > 0 ? (unsigned)ceil(lim->timeout_s) + 2 : 0};
    size_t rss_at_fork = lim->worker_exe ? 0 : mr_child_memory(getpid(), true);
    fork_only here = {.path = path, .refine = refine};
    pid_t pid = mr_child_spawn(lim->worker_exe, argv, fds[1], &child, import_here, &here);
    int spawn_errno = errno;
    close(fds[1]);
    if (pid < 0) {
        close(fds[0]);
        return mr_error_set(err, MR_ERR_IO, "import of %s: fork: %s", label, strerror(spawn_errno));
    }

    uint8_t *buf = NULL;
    size_t len = 0, cap = 0, peak = 0;
    verdict v = RAN;
    bool read_failed = false;
    double deadline = lim->timeout_s > 0 ? mr_now() + lim->timeout_s : 0;
    for (;;) {
        struct pollfd p = {.fd = fds[0], .events = POLLIN};
        int n = poll(&p, 1, POLL_MS);
        if (n < 0 && errno != EINTR) {
            read_failed = true;
            break;
        }
        if (n > 0) {
            if (cap - len < 65536) {
                size_t ncap = cap ? cap * 2 : 1 << 20;
                uint8_t *nb = realloc(buf, ncap);
                if (!nb) {
                    read_failed = true;
                    break;
                }
                buf = nb;
                cap = ncap;
            }
            ssize_t r = read(fds[0], buf + len, cap - len);
            if (r < 0 && errno == EINTR)
                continue;
            if (r <= 0) {
                read_failed = r < 0;
                break; /* EOF: the child is done (or dead) */
            }
            len += (size_t)r;
        }
        if (interrupted && interrupted(user)) {
            v = CANCELLED;
            break;
        }
        if (deadline > 0 && mr_now() > deadline) {
            v = TIMED_OUT;
            break;
        }
        size_t rss = mr_child_memory(pid, true);
        size_t grown = rss > rss_at_fork ? rss - rss_at_fork : 0;
        if (grown > peak)
            peak = grown;
        if (lim->memory_bytes && grown > lim->memory_bytes) {
            v = TOO_BIG;
            break;
        }
    }
    close(fds[0]);
    if (v != RAN || read_failed)
        kill(pid, SIGKILL);
    int status = mr_child_reap(pid);

    int rc = MR_OK;
    char limit[MR_BYTES_TEXT];
    mr_format_bytes(lim->memory_bytes, limit, sizeof limit);
    result_header h;
    if (v == CANCELLED) {
        rc = mr_error_set(err, MR_ERR_CANCELLED, "import of %s cancelled", label);
    } else if (v == TIMED_OUT || (WIFSIGNALED(status) && WTERMSIG(status) == SIGXCPU)) {
        rc = mr_error_set(err, MR_ERR_LIMIT, "import of %s took longer than %g s (the daemon's "
                          "--import-timeout)", label, lim->timeout_s);
    } else if (v == TOO_BIG) {
        rc = mr_error_set(err, MR_ERR_LIMIT, "import of %s used more than %s of memory (the "
                          "daemon's --import-memory-mb)", label, limit);
    } else if (WIFSIGNALED(status)) {
        char how[64];
        mr_child_describe_exit(status, how, sizeof how);
        rc = mr_error_set(err, MR_ERR_FORMAT, "import of %s crashed the importer (%s%s)", label,
                          how + strlen("killed by "),
                          WTERMSIG(status) == SIGKILL ? ", killed: out of memory?" : "");
    } else if (read_failed || !WIFEXITED(status) || WEXITSTATUS(status) != 0 || len < sizeof h) {
        rc = mr_error_set(err, MR_ERR_IO, "import of %s: the import process failed (exit %d)",
                          label, WIFEXITED(status) ? WEXITSTATUS(status) : -1);
    } else {
        memcpy(&h, buf, sizeof h);
        if (len != sizeof h + h.message_len + h.blob_len) {
            rc = mr_error_set(err, MR_ERR_IO, "import of %s: a torn result (%zu bytes)", label, len);
        } else if (h.rc < 0) {
            char msg[sizeof err->msg];
            snprintf(msg, sizeof msg, "%.*s", (int)h.message_len, (const char *)buf + sizeof h);
            if (strstr(msg, "bad_alloc") || h.rc == MR_ERR_NOMEM)
                rc = mr_error_set(err, MR_ERR_LIMIT, "import of %s used more than %s of memory (the "
                                  "daemon's --import-memory-mb): %s", label, limit, msg);
            else
                rc = mr_error_set(err, h.rc, "%s", msg);
            if (stage)
                *stage = (mr_asset_stage)h.stage;
        } else {
            rc = mr_asset_blob_read(buf + sizeof h + h.message_len, (size_t)h.blob_len, out, err);
            if (rc < 0)
                mr_error_prefix(err, "import of %s: ", label);
        }
    }
    free(buf);
    return rc;
}

/* `microrayd import-worker PATH [--refine R A F O S T]`: mr_import_isolated's
 * child after exec (its descriptor 3 is the result pipe). */
int mr_cmd_import_worker(int argc, char **argv)
{
    if (argc != 1 && !(argc == 8 && !strcmp(argv[1], "--refine"))) {
        fprintf(stderr, "microrayd import-worker: runs only as the daemon's import child\n");
        return 2;
    }
    mr_refine_params refine = {0};
    if (argc == 8) {
        refine.rounds = (unsigned)strtoul(argv[2], NULL, 10);
        refine.amplitude = (float)strtod(argv[3], NULL);
        refine.frequency = (float)strtod(argv[4], NULL);
        refine.octaves = (unsigned)strtoul(argv[5], NULL, 10);
        refine.seed = (uint32_t)strtoul(argv[6], NULL, 10);
        refine.threads = (unsigned)strtoul(argv[7], NULL, 10);
    }
    return mr_import_worker_run(argv[0], argc == 8 ? &refine : NULL);
}
