/*
 * file_io.h - the whole-file reads, crash-safe writes, mkdir -p and removal of
 * microray's file formats, disk caches (baked DMMs, .mrdmm, .mrsvo) and
 * the daemon's files, in one place so every file gets the same guarantees:
 *  - a read never blocks on a FIFO planted under the name, refuses
 *    anything but a regular file, and refuses a file above the format's
 *    cap before allocating for it;
 *  - a write never leaves a half-written file under the final name, even
 *    after a crash, and two writers of the same name never collide.
 * The server writes through these too (frames, uploads, stats.json, port
 * files); server/files.h keeps only its NUL-terminated job-file read.
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

/* mkdir -p dir with mode 0755; existing directories are fine. A directory
 * it creates is durable when it returns (its parent is fsynced), so a file
 * renamed into it later survives a crash too. MR_ERR_INVALID for an empty
 * name; MR_ERR_IO when a component cannot be made or dir is not a directory
 * in the end. */
int mr_fs_make_dirs(const char *dir, const char *what, mr_error *err);

/* The one atomic write of microray (core formats, caches, frames, uploads,
 * stats.json, port files): bytes go to a unique <path>.tmpXXXXXX in the
 * target's directory (mode 0644; two writers of one target never share a
 * temporary), which appears under the final name only by commit: fsync of
 * the file, rename, fsync of the directory so the rename survives a crash.
 * Nothing half-written is ever visible under the final name, and the
 * temporary never outlives a failed or aborted write. For writers that
 * stream (EXR encoding, uploads whose name is their hash):
 *     mr_fs_atomic a;
 *     begin(&a, path) -> write(&a, ...) or write(2) to a.fd ... ->
 *     commit(&a, NULL or another name in the same directory) | abort(&a)
 * Every error names `what` and the file, and the failing step. */
typedef struct mr_fs_atomic {
    int fd;     /* the temporary, open for writing; -1 once ended */
    char *tmp;  /* its name */
    char *path; /* the target given to begin */
    char *dir;  /* the directory of both */
} mr_fs_atomic;

/* Creates the temporary next to path. On failure *a needs no abort. */
int mr_fs_atomic_begin(mr_fs_atomic *a, const char *path, const char *what, mr_error *err);
/* Appends size bytes to the temporary (retrying short writes). */
int mr_fs_atomic_write(mr_fs_atomic *a, const void *buf, size_t size, const char *what,
                       mr_error *err);
/* fsync, close, rename onto path (NULL: begin's path; otherwise a name in
 * the same directory), fsync of the directory. Ends the write either way:
 * on failure the temporary is removed and the target untouched. */
int mr_fs_atomic_commit(mr_fs_atomic *a, const char *path, const char *what, mr_error *err);
/* Ends an unfinished write: closes and removes the temporary. Safe on an
 * ended or zeroed-after-failed-begin *a. */
void mr_fs_atomic_abort(mr_fs_atomic *a);

/* begin + write + commit of one buffer. */
int mr_fs_write_atomic(const char *path, const void *buf, size_t size, const char *what,
                       mr_error *err);

/* Removes the files in dir, then dir itself; a missing dir is fine. A file
 * that appears while it is emptied (a writer racing the removal) keeps the
 * directory without an error: that writer owns cleaning up after itself.
 * MR_ERR_IO naming the first entry that could not be removed. */
int mr_fs_remove_dir(const char *dir, mr_error *err);

/* Reads the whole regular file path (at most max bytes) into a malloc'ed
 * buffer (*buf, *size; a 0-byte file gives a 1-byte allocation). A file
 * that shrinks while read comes back shorter: the caller's parser then
 * sees the truncated file it now is. MR_ERR_IO: cannot open or read, not a
 * regular file (FIFOs are refused without blocking); MR_ERR_FORMAT: larger
 * than max, refused before reading; MR_ERR_NOMEM. */
int mr_fs_read_capped(const char *path, uint64_t max, uint8_t **buf, size_t *size,
                      const char *what, mr_error *err);

#endif
