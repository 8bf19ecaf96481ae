/*
 * fs.h - small file-system steps that durable storage is built from:
 * writing every byte to a descriptor, making a directory's entries durable,
 * and removing a directory of plain files. The daemon's store (frame and
 * asset files, job directories) is their first user; they are not tied to
 * it. (Whole-file reads, atomic replace-by-rename and mkdir -p are
 * file_io.h's.) Messages name the path: "cannot fsync directory '<dir>':
 * <strerror>".
 */
#ifndef MR_FS_H
#define MR_FS_H

#include <stddef.h>

#include "microray.h"

/* Writes size bytes to fd, retrying short writes and EINTR. 0, or -1 with
 * errno set. */
int mr_fs_write_all(int fd, const void *data, size_t size);

/* fsync of a directory, so that entries created or renamed in it survive
 * a crash. MR_ERR_IO. */
int mr_fs_fsync_dir(const char *dir, mr_error *err);

/* Removes the files in dir, then dir itself; a missing dir is fine. A file
 * that appears while it is emptied (a writer racing the removal) keeps the
 * directory without an error: that writer owns cleaning up after itself.
 * MR_ERR_IO naming the first entry that could not be removed. */
int mr_fs_remove_dir(const char *dir, mr_error *err);

#endif
