/* fs.c - write-all, directory fsync and removal (fs.h). */
#include "util/fs.h"

#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <string.h>
#include <unistd.h>

static int io_error(mr_error *err, const char *what, const char *path, int e)
{
    return mr_error_set(err, MR_ERR_IO, "%s '%s': %s", what, path, strerror(e));
}

int mr_fs_write_all(int fd, const void *data, size_t size)
{
    const unsigned char *p = data;
    while (size > 0) {
        ssize_t n = write(fd, p, size);
        if (n < 0) {
            if (errno == EINTR)
                continue;
            return -1;
        }
        p += n;
        size -= (size_t)n;
    }
    return 0;
}

int mr_fs_fsync_dir(const char *dir, mr_error *err)
{
    int fd = open(dir, O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (fd < 0)
        return io_error(err, "cannot open directory", dir, errno);
    if (fsync(fd) != 0) {
        int e = errno;
        close(fd);
        return io_error(err, "cannot fsync directory", dir, e);
    }
    close(fd);
    return MR_OK;
}

int mr_fs_remove_dir(const char *dir, mr_error *err)
{
    DIR *d = opendir(dir);
    if (!d)
        return errno == ENOENT ? MR_OK : io_error(err, "cannot open directory", dir, errno);
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
            rc = io_error(err, "cannot remove", p, e2);
        }
        errno = 0;
    }
    if (errno != 0 && rc == MR_OK)
        rc = io_error(err, "cannot read directory", dir, errno);
    closedir(d);
    if (rc < 0)
        return rc;
    /* ENOTEMPTY: a file appeared meanwhile (see fs.h) */
    if (rmdir(dir) != 0 && errno != ENOENT && errno != ENOTEMPTY)
        return io_error(err, "cannot remove directory", dir, errno);
    return MR_OK;
}
