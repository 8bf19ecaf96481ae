/*
 * client.h - what every part of the `microray` command-line client shares:
 * exit codes, the error record, small file and JSON helpers.
 *
 * The client is a separate small program (libcurl + cJSON only) so it can be
 * copied to a workstation without the renderer; it therefore does not include
 * core/ or server/ headers and keeps its own copy of the version string.
 * Like the core, functions that can fail return 0 or a negative number and
 * fill a caller's mrc_error; here the negative number is minus the exit code
 * the failure should end the program with, so errors need no translation on
 * their way up to main().
 */
#ifndef MRC_CLIENT_H
#define MRC_CLIENT_H

#include <stdarg.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include <cJSON.h>

/* Kept equal to MR_VERSION_STRING in core/microray.h by hand (see above). */
#define MRC_VERSION "0.1.0"
#define MRC_DEFAULT_SERVER "http://127.0.0.1:8470"

/* Exit codes; docs/client.md and --help list them. */
enum {
    MRC_EXIT_OK = 0,
    MRC_EXIT_JOB_FAILED = 1, /* --wait: the job failed or was canceled */
    MRC_EXIT_USAGE = 2,      /* bad command line */
    MRC_EXIT_REJECTED = 3,   /* the server answered 4xx */
    MRC_EXIT_SERVER = 4,     /* server unreachable, 5xx or a broken answer */
    MRC_EXIT_LOCAL = 5       /* a local file could not be read or written */
};

typedef struct mrc_error {
    int code;       /* one of MRC_EXIT_*, 0 when nothing failed */
    char msg[1024]; /* printed as "microray: <msg>" */
} mrc_error;

/* Records the failure and returns -code, so "return mrc_fail(...)" reads well. */
int mrc_fail(mrc_error *err, int code, const char *fmt, ...)
    __attribute__((format(printf, 3, 4)));

/* Monotonic seconds, for durations and progress: CLOCK_MONOTONIC like the
 * core's mr_now (util/clock.h), which the client does not link. */
double mrc_now(void);

/* Copies src into dst (always terminated), replacing control characters
 * with '?': text from the server must not be able to drive the terminal. */
void mrc_sanitize(char *dst, size_t size, const char *src);

/* Reads a whole file ("-" = stdin) into a malloc'ed, NUL-terminated buffer.
 * Files larger than `limit` bytes are refused. */
int mrc_read_file(const char *path, size_t limit, char **data, size_t *len, mrc_error *err);

/* mkdir -p with mode 0777 (the umask applies). */
int mrc_mkdirs(const char *dir, mrc_error *err);

/* A job id as it may appear in a URL path: 1..128 of [A-Za-z0-9_-].
 * Checked before use so a typo cannot reach another route ("../x"). */
bool mrc_valid_id(const char *id);

/* Byte counts for humans: "812 B", "3.4 KiB", "1.2 GiB". */
void mrc_format_bytes(char *dst, size_t size, double bytes);
/* Durations for humans: "3.1 s", "2m05s", "1h07m". */
void mrc_format_seconds(char *dst, size_t size, double seconds);

/* JSON getters that tolerate anything: a missing key, a wrong type or an
 * out-of-range number yields the default (numbers are range-checked before
 * conversion because casting a huge double to an integer is undefined). */
long long mrc_json_int(const cJSON *obj, const char *key, long long def, long long lo, long long hi);
double mrc_json_num(const cJSON *obj, const char *key, double def);
const char *mrc_json_str(const cJSON *obj, const char *key); /* NULL unless a string */

/* A timestamp field ("created", ...) for display: strings as they are
 * (sanitized), numbers as seconds since the epoch in UTC, else "-". */
void mrc_format_time_field(char *dst, size_t size, const cJSON *obj, const char *key);

#endif
