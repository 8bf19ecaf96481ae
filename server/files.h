/*
 * files.h - small file helpers for the server side: bounded whole-file
 * reads, atomic replace-by-rename writes (nothing half-written is ever
 * visible under the final name, even after a crash), mkdir -p.
 */
#ifndef MR_FILES_H
#define MR_FILES_H

#include "microray.h"

/* Reads a whole file (at most max_bytes; MR_ERR_LIMIT beyond) into a
 * malloc'ed, NUL-terminated buffer. */
int mr_file_read(const char *path, size_t max_bytes, char **data, size_t *size, mr_error *err);
/* Writes data to path.tmp, fsyncs it and renames it over path. */
int mr_file_write_atomic(const char *path, const void *data, size_t size, mr_error *err);
/* Creates dir and its parents (mode 0755); existing directories are fine. */
int mr_mkdir_p(const char *dir, mr_error *err);
/* Directory part of path ("." when there is none), into out. */
void mr_path_dirname(const char *path, char *out, size_t out_size);

#endif
