/*
 * space_guard.c - the disk-space reserve and the "disk full" state
 * (space_guard.h).
 */
#include "space_guard.h"

#include <errno.h>
#include <fcntl.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/statvfs.h>
#include <unistd.h>

struct mr_space_guard {
    pthread_mutex_t lock;
    char *dir, *reserve_path;
    size_t reserve_bytes;
    size_t need; /* what the write that failed wanted, while full */
    bool full;
    char why[512];
};

/* The reserve's bytes really written (fallocate could leave them to a
 * later write on some file systems) and synced. */
static int write_reserve(const mr_space_guard *g, mr_error *err)
{
    if (g->reserve_bytes == 0)
        return MR_OK;
    char tmp[4200];
    snprintf(tmp, sizeof tmp, "%s.tmp", g->reserve_path);
    int fd = open(tmp, O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0600);
    if (fd < 0)
        return mr_error_set(err, errno == ENOSPC || errno == EDQUOT ? MR_ERR_NO_SPACE : MR_ERR_IO,
                            "disk reserve %s: %s", tmp, strerror(errno));
    static const char zeros[65536];
    int rc = MR_OK;
    for (size_t left = g->reserve_bytes; left > 0 && rc == MR_OK;) {
        size_t n = left < sizeof zeros ? left : sizeof zeros;
        ssize_t w = write(fd, zeros, n);
        if (w < 0 && errno == EINTR)
            continue;
        if (w <= 0)
            rc = mr_error_set(err, w < 0 && (errno == ENOSPC || errno == EDQUOT) ? MR_ERR_NO_SPACE : MR_ERR_IO,
                              "disk reserve %s: %s", tmp, w < 0 ? strerror(errno) : "no progress");
        else
            left -= (size_t)w;
    }
    if (rc == MR_OK && fsync(fd) != 0)
        rc = mr_error_set(err, errno == ENOSPC ? MR_ERR_NO_SPACE : MR_ERR_IO, "disk reserve %s: %s",
                          tmp, strerror(errno));
    close(fd);
    if (rc == MR_OK && rename(tmp, g->reserve_path) != 0)
        rc = mr_error_set(err, MR_ERR_IO, "disk reserve %s: %s", g->reserve_path, strerror(errno));
    if (rc < 0)
        unlink(tmp);
    return rc;
}

static size_t free_bytes(const char *dir)
{
    struct statvfs s;
    if (statvfs(dir, &s) != 0)
        return 0;
    return (size_t)s.f_bavail * (size_t)s.f_frsize;
}

/* Under the lock. */
static bool enter_full(mr_space_guard *g, const char *why)
{
    if (g->full)
        return false;
    g->full = true;
    snprintf(g->why, sizeof g->why, "%s", why);
    unlink(g->reserve_path); /* room for sqlite to record this and to delete */
    return true;
}

int mr_space_guard_open(const char *dir, size_t reserve_bytes, mr_space_guard **out,
                        mr_error *err)
{
    *out = NULL;
    mr_space_guard *g = calloc(1, sizeof *g);
    if (!g)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    size_t n = strlen(dir) + sizeof "/" MR_SPACE_RESERVE_NAME;
    g->dir = strdup(dir);
    g->reserve_path = malloc(n);
    if (!g->dir || !g->reserve_path) {
        free(g->dir);
        free(g->reserve_path);
        free(g);
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    }
    snprintf(g->reserve_path, n, "%s/%s", dir, MR_SPACE_RESERVE_NAME);
    g->reserve_bytes = reserve_bytes;
    pthread_mutex_init(&g->lock, NULL);
    struct stat st;
    bool have = stat(g->reserve_path, &st) == 0 && (size_t)st.st_size == reserve_bytes;
    if (have && free_bytes(dir) < reserve_bytes) {
        /* a full disk since the last run: the reserve is what lets this
         * start open the store and recover */
        enter_full(g, "no space left on device at start-up");
    } else if (!have) {
        mr_error e = {0};
        int rc = write_reserve(g, &e);
        if (rc == MR_ERR_NO_SPACE)
            enter_full(g, e.msg);
        else if (rc < 0) {
            mr_space_guard_close(g);
            *err = e;
            return rc;
        }
    }
    *out = g;
    return MR_OK;
}

void mr_space_guard_close(mr_space_guard *g)
{
    if (!g)
        return;
    pthread_mutex_destroy(&g->lock);
    free(g->dir);
    free(g->reserve_path);
    free(g);
}

bool mr_space_guard_report(mr_space_guard *g, const char *why)
{
    pthread_mutex_lock(&g->lock);
    bool entered = enter_full(g, why);
    pthread_mutex_unlock(&g->lock);
    return entered;
}

bool mr_space_guard_has_room(mr_space_guard *g, size_t bytes)
{
    return free_bytes(g->dir) >= bytes;
}

void mr_space_guard_need(mr_space_guard *g, size_t bytes)
{
    pthread_mutex_lock(&g->lock);
    if (g->full && bytes > g->need)
        g->need = bytes;
    pthread_mutex_unlock(&g->lock);
}

bool mr_space_guard_full(mr_space_guard *g, char *why, size_t size)
{
    pthread_mutex_lock(&g->lock);
    bool full = g->full;
    if (why && size)
        snprintf(why, size, "%s", full ? g->why : "");
    pthread_mutex_unlock(&g->lock);
    return full;
}

bool mr_space_guard_poll(mr_space_guard *g)
{
    pthread_mutex_lock(&g->lock);
    bool full = g->full;
    size_t want = 2 * g->reserve_bytes > (size_t)1 << 20 ? 2 * g->reserve_bytes : (size_t)1 << 20;
    want += g->need;
    pthread_mutex_unlock(&g->lock);
    if (!full || free_bytes(g->dir) < want)
        return false;
    mr_error e = {0};
    if (write_reserve(g, &e) < 0)
        return false; /* filled again meanwhile: next poll */
    pthread_mutex_lock(&g->lock);
    g->full = false;
    g->need = 0;
    g->why[0] = '\0';
    pthread_mutex_unlock(&g->lock);
    return true;
}
