/* file_io.c - capped whole-file reads, atomic writes, mkdir -p, removal (file_io.h). */
#include "util/file_io.h"

#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

char *mr_fs_dir_of(const char *path)
{
    const char *slash = strrchr(path, '/');
    if (!slash)
        return strdup(".");
    return strndup(path, slash > path ? (size_t)(slash - path) : 1);
}

/* A failed write for want of space is told apart (MR_ERR_NO_SPACE): the
 * daemon pauses its queue on it instead of failing frame after frame. */
static int io_code(int e)
{
    return e == ENOSPC || e == EDQUOT ? MR_ERR_NO_SPACE : MR_ERR_IO;
}

/* fsync of a directory, so entries just made or renamed in it survive a
 * crash. EINVAL: file systems that cannot sync a directory. */
static int fsync_dir(const char *dir, const char *what, mr_error *err)
{
    int dfd = open(dir, O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (dfd < 0)
        return mr_error_set(err, io_code(errno), "%s: fsync of directory %s: %s", what, dir,
                            strerror(errno));
    int rc = MR_OK;
    if (fsync(dfd) != 0 && errno != EINVAL)
        rc = mr_error_set(err, io_code(errno), "%s: fsync of directory %s: %s", what, dir,
                          strerror(errno));
    close(dfd);
    return rc;
}

int mr_fs_make_dirs(const char *dir, const char *what, mr_error *err)
{
    if (!dir || !dir[0])
        return mr_error_set(err, MR_ERR_INVALID, "%s: empty directory name", what);
    char *d = strdup(dir);
    if (!d)
        return mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", what);
    int rc = MR_OK;
    size_t n = strlen(d);
    for (size_t i = 1; i <= n && rc == MR_OK; i++) {
        if (d[i] != '/' && d[i] != '\0')
            continue;
        char saved = d[i];
        d[i] = '\0';
        if (mkdir(d, 0755) == 0) {
            /* new: its entry in the parent is durable only once the parent
             * is synced */
            char *parent = mr_fs_dir_of(d);
            rc = parent ? fsync_dir(parent, what, err)
                        : mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", what);
            free(parent);
        } else if (errno != EEXIST) {
            rc = mr_error_set(err, io_code(errno), "%s: cannot create directory %s: %s", what, d,
                              strerror(errno));
        }
        d[i] = saved;
    }
    struct stat st;
    if (rc == MR_OK && (stat(dir, &st) != 0 || !S_ISDIR(st.st_mode)))
        rc = mr_error_set(err, MR_ERR_IO, "%s: %s is not a directory", what, dir);
    free(d);
    return rc;
}

int mr_fs_atomic_begin(mr_fs_atomic *a, const char *path, const char *what, mr_error *err)
{
    *a = (mr_fs_atomic){.fd = -1};
    if (!path || !path[0])
        return mr_error_set(err, MR_ERR_INVALID, "%s: no path", what);
    size_t n = strlen(path);
    char *tmp = malloc(n + sizeof ".tmpXXXXXX");
    char *target = strdup(path);
    char *dir = mr_fs_dir_of(path);
    int rc = MR_OK, fd = -1;
    if (!tmp || !target || !dir) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", what);
        goto fail;
    }
    /* unique per writer: two jobs may store the same cache entry, or two
     * renders the same frame, at once; the last rename wins */
    memcpy(tmp, path, n);
    memcpy(tmp + n, ".tmpXXXXXX", sizeof ".tmpXXXXXX");
    if ((fd = mkstemp(tmp)) < 0) {
        rc = mr_error_set(err, io_code(errno), "%s: cannot create %s: %s", what, tmp, strerror(errno));
        goto fail;
    }
    /* held until the write ends, so a sweep can tell a live writer's
     * temporary from one a killed writer left (mr_fs_atomic_abandoned);
     * the kernel drops it with the process. Best effort: where the file
     * system has no locks, no temporary looks abandoned. */
    (void)flock(fd, LOCK_EX | LOCK_NB);
    /* mkstemp's 0600 would hide a cache or a frame from other users */
    if (fcntl(fd, F_SETFD, FD_CLOEXEC) != 0 || fchmod(fd, 0644) != 0) {
        rc = mr_error_set(err, MR_ERR_IO, "%s: cannot set up %s: %s", what, tmp, strerror(errno));
        close(fd);
        unlink(tmp);
        goto fail;
    }
    *a = (mr_fs_atomic){.fd = fd, .tmp = tmp, .path = target, .dir = dir};
    return MR_OK;
fail:
    free(tmp);
    free(target);
    free(dir);
    return rc;
}

bool mr_fs_atomic_abandoned(int dirfd, const char *name, char *target, size_t size)
{
    const size_t n = strlen(name), suffix = sizeof ".tmpXXXXXX" - 1;
    if (n <= suffix || memcmp(name + n - suffix, ".tmp", 4) != 0)
        return false;
    const int fd = openat(dirfd, name, O_RDONLY | O_CLOEXEC | O_NOFOLLOW);
    if (fd < 0)
        return false;
    const bool free_to_take = flock(fd, LOCK_EX | LOCK_NB) == 0;
    close(fd);
    if (free_to_take && target)
        snprintf(target, size, "%.*s", (int)(n - suffix), name);
    return free_to_take;
}

int mr_fs_atomic_write(mr_fs_atomic *a, const void *buf, size_t size, const char *what,
                       mr_error *err)
{
    if (!a->tmp || a->fd < 0)
        return mr_error_set(err, MR_ERR_INVALID, "%s: no write in progress", what);
    if (!buf && size)
        return mr_error_set(err, MR_ERR_INVALID, "%s: no data", what);
    const uint8_t *bytes = buf;
    for (size_t off = 0; off < size;) {
        ssize_t w = write(a->fd, bytes + off, size - off);
        if (w < 0 && errno == EINTR)
            continue;
        if (w <= 0)
            return mr_error_set(err, w < 0 ? io_code(errno) : MR_ERR_IO, "%s: writing %s: %s",
                                what, a->tmp, w < 0 ? strerror(errno) : "no progress");
        off += (size_t)w;
    }
    return MR_OK;
}

int mr_fs_atomic_commit(mr_fs_atomic *a, const char *path, const char *what, mr_error *err)
{
    int rc = MR_OK;
    char *dir = NULL;
    if (!a->tmp || a->fd < 0) {
        rc = mr_error_set(err, MR_ERR_INVALID, "%s: no write in progress", what);
        goto done;
    }
    const char *target = path ? path : a->path;
    /* a rename across directories would leave the synced one the wrong one */
    if (path && (!(dir = mr_fs_dir_of(path)) || strcmp(dir, a->dir) != 0)) {
        rc = dir ? mr_error_set(err, MR_ERR_INVALID, "%s: %s is not in the directory of %s", what,
                                path, a->tmp)
                 : mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", what);
        goto done;
    }
    if (fsync(a->fd) != 0) {
        rc = mr_error_set(err, io_code(errno), "%s: fsync %s: %s", what, a->tmp, strerror(errno));
        goto done;
    }
    /* close can report a delayed write error (NFS): the data is not safe.
     * A second descriptor keeps the temporary's lock (mr_fs_atomic_begin)
     * until it is renamed: a sweep never takes a live write for dead. */
    const int held = dup(a->fd);
    int c = close(a->fd);
    a->fd = held;
    if (c != 0) {
        rc = mr_error_set(err, io_code(errno), "%s: close %s: %s", what, a->tmp, strerror(errno));
        goto done;
    }
    if (rename(a->tmp, target) != 0) {
        rc = mr_error_set(err, io_code(errno), "%s: rename %s to %s: %s", what, a->tmp, target,
                          strerror(errno));
        goto done;
    }
    free(a->tmp);
    a->tmp = NULL; /* renamed: nothing left to remove */
    /* the rename itself is durable only once the directory is synced */
    rc = fsync_dir(a->dir, what, err);
done:
    free(dir);
    mr_fs_atomic_abort(a);
    return rc;
}

void mr_fs_atomic_abort(mr_fs_atomic *a)
{
    if (!a)
        return;
    if (a->fd >= 0 && a->path) /* (after a commit: the descriptor that held the lock;
                                  a zeroed handle's 0 is no descriptor of it) */
        close(a->fd);
    if (a->tmp) /* tmp marks a write not renamed into place */
        unlink(a->tmp);
    free(a->tmp);
    free(a->path);
    free(a->dir);
    *a = (mr_fs_atomic){.fd = -1};
}

int mr_fs_write_atomic(const char *path, const void *buf, size_t size, const char *what,
                       mr_error *err)
{
    if (!buf && size)
        return mr_error_set(err, MR_ERR_INVALID, "%s: no data", what);
    mr_fs_atomic a;
    int rc = mr_fs_atomic_begin(&a, path, what, err);
    if (rc < 0)
        return rc;
    if ((rc = mr_fs_atomic_write(&a, buf, size, what, err)) < 0) {
        mr_fs_atomic_abort(&a);
        return rc;
    }
    return mr_fs_atomic_commit(&a, NULL, what, err);
}

int mr_fs_read_capped(const char *path, uint64_t max, uint8_t **buf, size_t *size,
                      const char *what, mr_error *err)
{
    *buf = NULL;
    *size = 0;
    /* O_NONBLOCK: a FIFO planted under the name must not block the caller;
     * it is refused below as not a regular file */
    int fd = open(path, O_RDONLY | O_NONBLOCK | O_CLOEXEC);
    if (fd < 0)
        return mr_error_set(err, MR_ERR_IO, "%s: cannot open %s: %s", what, path,
                            strerror(errno));
    int rc = MR_OK;
    uint8_t *data = NULL;
    struct stat st;
    if (fstat(fd, &st) != 0) {
        rc = mr_error_set(err, MR_ERR_IO, "%s: cannot stat %s: %s", what, path, strerror(errno));
        goto done;
    }
    if (!S_ISREG(st.st_mode)) {
        rc = mr_error_set(err, MR_ERR_IO, "%s: %s is not a regular file", what, path);
        goto done;
    }
    if (st.st_size < 0 || (uint64_t)st.st_size > max) {
        rc = mr_error_set(err, MR_ERR_FORMAT,
                          "%s %s: %lld bytes, more than any valid file (limit %llu, from byte "
                          "offset %llu on)", what, path, (long long)st.st_size,
                          (unsigned long long)max, (unsigned long long)max);
        goto done;
    }
    size_t want = (size_t)st.st_size, got = 0;
    if (!(data = malloc(want ? want : 1))) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory for %zu bytes", what, want);
        goto done;
    }
    while (got < want) {
        ssize_t r = read(fd, data + got, want - got);
        if (r < 0 && errno == EINTR)
            continue;
        if (r < 0) {
            rc = mr_error_set(err, MR_ERR_IO, "%s: reading %s: %s", what, path, strerror(errno));
            goto done;
        }
        if (r == 0)
            break; /* shrank since fstat */
        got += (size_t)r;
    }
    *buf = data;
    *size = got;
    data = NULL;
done:
    free(data);
    close(fd);
    return rc;
}

int mr_fs_remove_dir(const char *dir, mr_error *err)
{
    DIR *d = opendir(dir);
    if (!d)
        return errno == ENOENT ? MR_OK : mr_error_set(err, MR_ERR_IO, "cannot open directory '%s': %s", dir, strerror(errno));
    int rc = MR_OK;
    struct dirent *e;
    errno = 0;
    while ((e = readdir(d)) != NULL) {
        if (strcmp(e->d_name, ".") == 0 || strcmp(e->d_name, "..") == 0)
            continue;
        if (unlinkat(dirfd(d), e->d_name, 0) != 0 && errno != ENOENT && rc == MR_OK) {
            char p[4096];
            int e2 = errno;
            int n = snprintf(p, sizeof p, "%s/%s", dir, e->d_name);
            if (n < 0 || (size_t)n >= sizeof p)
                snprintf(p, sizeof p, "%s/...", dir);
            rc = mr_error_set(err, MR_ERR_IO, "cannot remove '%s': %s", p, strerror(e2));
        }
        errno = 0;
    }
    if (errno != 0 && rc == MR_OK)
        rc = mr_error_set(err, MR_ERR_IO, "cannot read directory '%s': %s", dir, strerror(errno));
    closedir(d);
    if (rc < 0)
        return rc;
    /* ENOTEMPTY: a file appeared meanwhile (see file_io.h) */
    if (rmdir(dir) != 0 && errno != ENOENT && errno != ENOTEMPTY)
        return mr_error_set(err, MR_ERR_IO, "cannot remove directory '%s': %s", dir, strerror(errno));
    return MR_OK;
}
