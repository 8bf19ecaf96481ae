/* file_io.c - capped whole-file reads, atomic writes, mkdir -p (file_io.h). */
#include "util/file_io.h"

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

char *mr_fs_dir_of(const char *path)
{
    const char *slash = strrchr(path, '/');
    if (!slash)
        return strdup(".");
    return strndup(path, slash > path ? (size_t)(slash - path) : 1);
}

int mr_fs_make_dirs(const char *dir, const char *what, mr_error *err)
{
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
        if (mkdir(d, 0755) != 0 && errno != EEXIST)
            rc = mr_error_set(err, MR_ERR_IO, "%s: cannot create directory %s: %s", what, d,
                              strerror(errno));
        d[i] = saved;
    }
    struct stat st;
    if (rc == MR_OK && (stat(dir, &st) != 0 || !S_ISDIR(st.st_mode)))
        rc = mr_error_set(err, MR_ERR_IO, "%s: %s is not a directory", what, dir);
    free(d);
    return rc;
}

int mr_fs_write_atomic(const char *path, const void *buf, size_t size, const char *what,
                       mr_error *err)
{
    if (!path || !path[0])
        return mr_error_set(err, MR_ERR_INVALID, "%s: no path", what);
    if (!buf && size)
        return mr_error_set(err, MR_ERR_INVALID, "%s: no data", what);
    int rc = MR_OK, fd = -1;
    const uint8_t *bytes = buf;
    size_t n = strlen(path);
    char *tmp = malloc(n + sizeof ".tmpXXXXXX");
    char *dir = mr_fs_dir_of(path);
    if (!tmp || !dir) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "%s: out of memory", what);
        goto done;
    }
    /* unique per writer: two jobs may store the same cache entry at once;
     * the last rename wins, with the same content */
    memcpy(tmp, path, n);
    memcpy(tmp + n, ".tmpXXXXXX", sizeof ".tmpXXXXXX");
    if ((fd = mkstemp(tmp)) < 0) {
        rc = mr_error_set(err, MR_ERR_IO, "%s: cannot create %s: %s", what, tmp,
                          strerror(errno));
        free(tmp);
        tmp = NULL; /* nothing to remove */
        goto done;
    }
    (void)fchmod(fd, 0644); /* mkstemp's 0600 would hide a cache from other users */
    for (size_t off = 0; off < size;) {
        ssize_t w = write(fd, bytes + off, size - off);
        if (w < 0 && errno == EINTR)
            continue;
        if (w <= 0) {
            rc = mr_error_set(err, MR_ERR_IO, "%s: writing %s: %s", what, tmp,
                              w < 0 ? strerror(errno) : "no progress");
            goto done;
        }
        off += (size_t)w;
    }
    if (fsync(fd) != 0) {
        rc = mr_error_set(err, MR_ERR_IO, "%s: fsync %s: %s", what, tmp, strerror(errno));
        goto done;
    }
    int c = close(fd);
    fd = -1;
    if (c != 0) {
        rc = mr_error_set(err, MR_ERR_IO, "%s: close %s: %s", what, tmp, strerror(errno));
        goto done;
    }
    if (rename(tmp, path) != 0) {
        rc = mr_error_set(err, MR_ERR_IO, "%s: rename %s to %s: %s", what, tmp, path,
                          strerror(errno));
        goto done;
    }
    free(tmp);
    tmp = NULL;
    /* the rename itself is durable only once the directory is synced;
     * EINVAL: file systems that cannot sync a directory */
    int dfd = open(dir, O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (dfd < 0 || (fsync(dfd) != 0 && errno != EINVAL))
        rc = mr_error_set(err, MR_ERR_IO, "%s: fsync of directory %s: %s", what, dir,
                          strerror(errno));
    if (dfd >= 0)
        close(dfd);
done:
    if (fd >= 0)
        close(fd);
    if (tmp)
        unlink(tmp);
    free(tmp);
    free(dir);
    return rc;
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
