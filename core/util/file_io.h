/*
 * file_io.h - the whole-file reads, crash-safe writes and mkdir -p of
 * microray's core file formats and disk caches (baked DMMs, .mrdmm,
 * .mrsvo), in one place so every format gets the same guarantees:
 *  - a read never blocks on a FIFO planted under the name, refuses
 *    anything but a regular file, and refuses a file above the format's
 *    cap before allocating for it;
 *  - a write never leaves a half-written file under the final name, even
 *    after a crash, and two writers of the same name never collide.
 * server/files.h has the server's own variants (NUL-terminated reads,
 * MR_ERR_LIMIT); core cannot depend on server, so these live here.
 * `what` starts every error message ("svo file", "dmm cache", ...).
 */
#ifndef MR_FILE_IO_H
#define MR_FILE_IO_H

#include <stddef.h>
#include <stdint.h>

#include "microray.h"

/* Directory part of path, malloc'ed: "." without a slash, "/" for "/x".
 * NULL when out of memory. */
char *mr_fs_dir_of(const char *path);

/* mkdir -p dir with mode 0755; existing directories are fine. MR_ERR_IO
 * when a component cannot be made or dir is not a directory in the end. */
int mr_fs_make_dirs(const char *dir, const char *what, mr_error *err);

/* Writes size bytes to path atomically: a unique <path>.tmpXXXXXX in the
 * same directory (mode 0644), fsync, rename over path, fsync of the
 * directory so the rename survives a crash. The temporary never outlives
 * the call. MR_ERR_IO names the failing step. */
int mr_fs_write_atomic(const char *path, const void *buf, size_t size, const char *what,
                       mr_error *err);

/* Reads the whole regular file path (at most max bytes) into a malloc'ed
 * buffer (*buf, *size; a 0-byte file gives a 1-byte allocation). A file
 * that shrinks while read comes back shorter: the caller's parser then
 * sees the truncated file it now is. MR_ERR_IO: cannot open or read, not a
 * regular file (FIFOs are refused without blocking); MR_ERR_FORMAT: larger
 * than max, refused before reading; MR_ERR_NOMEM. */
int mr_fs_read_capped(const char *path, uint64_t max, uint8_t **buf, size_t *size,
                      const char *what, mr_error *err);

#endif
