/*
 * files.h - the server's bounded whole-file read (NUL-terminated, for job
 * files). Atomic writes, mkdir -p and dirname are core's, the same for
 * every writer: util/file_io.h.
 */
#ifndef MR_FILES_H
#define MR_FILES_H

#include "microray.h"

/* Reads a whole file (at most max_bytes; MR_ERR_LIMIT beyond) into a
 * malloc'ed, NUL-terminated buffer. */
int mr_file_read(const char *path, size_t max_bytes, char **data, size_t *size, mr_error *err);

#endif
