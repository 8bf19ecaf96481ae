/*
 * microray.h - public API of libmicroray, the core renderer.
 *
 * Everything that renders lives behind this header and the module headers it
 * pulls in: no HTTP, no SQL and no JSON in core/. The daemon and the one-shot
 * command (server/) turn job JSON into the plain structs of core/job.h and
 * drive a renderer frame by frame.
 *
 * Conventions (see ../shared/ARCHITECTURE.md):
 *  - functions that can fail return int: MR_OK (0) or a negative mr_err, and
 *    write a human-readable message into the caller's mr_error;
 *  - handles are opaque, created by mr_x_new() and released by mr_x_free();
 *  - there is no global error state.
 */
#ifndef MICRORAY_H
#define MICRORAY_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#define MR_VERSION_STRING "0.1.0"

/* Error codes. Negative so "if (rc < 0)" reads naturally. */
typedef enum mr_err {
    MR_OK = 0,
    MR_ERR_NOMEM = -1,     /* allocation failed */
    MR_ERR_INVALID = -2,   /* bad argument or bad input data */
    MR_ERR_IO = -3,        /* file could not be read or written */
    MR_ERR_FORMAT = -4,    /* file read but its content is broken or unsupported */
    MR_ERR_EMBREE = -5,    /* Embree reported an error */
    MR_ERR_LIMIT = -6,     /* a documented size cap was exceeded */
    MR_ERR_CANCELLED = -7, /* the caller asked to stop */
    MR_ERR_NOT_FOUND = -8, /* a named thing (clip, joint, node, job, asset) does not exist */
    MR_ERR_CONFLICT = -9   /* the request contradicts stored state (e.g. idempotency key reuse) */
} mr_err;

/* Where a failing call leaves its message. Callers own it (often on the stack). */
typedef struct mr_error {
    int code;       /* the mr_err returned */
    char msg[512];  /* NUL-terminated, never empty after a failure */
} mr_error;

/* Records code and a printf-style message in err (which may be NULL); returns code. */
int mr_error_set(mr_error *err, int code, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 3, 4)))
#endif
    ;

/* Puts a printf-style prefix in front of the message already in err (for
 * adding where a failure happened, e.g. a JSON pointer); keeps the code and
 * returns it. */
int mr_error_prefix(mr_error *err, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 2, 3)))
#endif
    ;

/* Static name of an error code, e.g. "MR_ERR_FORMAT". */
const char *mr_err_name(int code);

#endif /* MICRORAY_H */
