/*
 * json_reader.h - reading untrusted JSON into C values with a JSON pointer
 * and an "expected X, got Y" message for the first problem: the generic
 * half of the job parser (job_json.c holds the job grammar).
 *
 * cJSON quirks handled here:
 *  - it keeps duplicate keys: json_check_fields / json_check_unique_keys;
 *  - overflowing literals (1e999) become inf: every number must be finite;
 *  - "\u0000" decodes to a NUL that silently truncates the string: a private
 *    copy of the input has it rewritten to "\u0001" first
 *    (json_parse_document), so the control-character check catches it with
 *    the right pointer;
 *  - it skips any byte <= 0x20 as whitespace (NUL included) and stops at the
 *    end of the first value: raw NUL bytes are refused up front and the tail
 *    after the value is checked, by length (the input need not be
 *    NUL-terminated).
 */
#ifndef MR_JSON_READER_H
#define MR_JSON_READER_H

#include <cJSON.h>
#include <stdbool.h>
#include <stddef.h>

#include "microray.h"

/* A problem found: where and what. */
typedef struct mr_json_error {
    char pointer[512]; /* RFC 6901 pointer to the offending value; "" = root */
    char message[512]; /* what was expected and what was found */
    bool syntax;       /* the text is not one JSON value (malformed JSON, bad UTF-8, a
                          NUL byte, data after the value): nothing else was read */
} mr_json_error;

/* Every problem of a document, when a reader collects them rather than
 * stopping at the first: the first MR_JSON_ERRORS_MAX in reading order
 * (items[0] is the one a first-problem reader reports), then a count. */
#define MR_JSON_ERRORS_MAX 32
typedef struct mr_json_errors {
    size_t count;   /* kept in items */
    size_t more;    /* found beyond those */
    mr_json_error items[MR_JSON_ERRORS_MAX];
} mr_json_errors;

/* The JSON pointer of the value being read, and where errors go.
 *
 * Collecting every problem: with `all` set, a reader goes on after a
 * problem at the points that say so (GO_ON_AT_KEY and the like: a field,
 * an element of a list, a section), so one pass reports each independent
 * problem; what depends on a part that failed is skipped there rather than
 * reported again. Within such a part, reading stops at its first problem.
 * Running out of memory always stops. Without `all` (the default) the
 * first problem ends reading, as before. */
typedef struct mr_json_ctx {
    mr_json_error *err;   /* the first problem */
    mr_json_errors *all;  /* NULL: stop at the first problem */
    int first_rc;         /* collecting: the code of the first problem gone on from */
    bool failed;          /* the last GO_ON_* part failed (and reading went on) */
    char ptr[sizeof(((mr_json_error *)0)->pointer)];
    size_t len;
    bool nul_escapes; /* prescan() rewrote some "\u0000" to "\u0001" */
} mr_json_ctx;

/* JSON_NUM_FLOAT: stored as a 32-bit float, which must be within the
 * range too (1e-300 in (0, 1] rounds to 0). */
enum { JSON_NUM_INT = 1u, JSON_NUM_LO_OPEN = 2u, JSON_NUM_HI_OPEN = 4u, JSON_NUM_FLOAT = 8u };

typedef struct json_num_spec {
    double lo, hi;
    unsigned flags;
    const char *expect; /* NULL: derived from lo, hi and flags */
} json_num_spec;

#define TRY(expr)                                                                        \
    do {                                                                                 \
        int rc_ = (expr);                                                                \
        if (rc_ < 0)                                                                     \
            return rc_;                                                                  \
    } while (0)

/* Runs expr with /key (or /index) appended to the pointer; on failure the
 * pointer stays, since the error has already copied it. */
#define AT_KEY(c, key, expr)                                                             \
    do {                                                                                 \
        size_t mark_ = json_push_key((c), (key));                                        \
        TRY(expr);                                                                       \
        json_pop((c), mark_);                                                            \
    } while (0)

#define AT_INDEX(c, i, expr)                                                             \
    do {                                                                                 \
        size_t mark_ = json_push_index((c), (i));                                        \
        TRY(expr);                                                                       \
        json_pop((c), mark_);                                                            \
    } while (0)

/* Appends a problem found outside the reader (a later check of the same
 * document) to all: kept while there is room, counted after. */
void json_errors_add(mr_json_errors *all, const char *pointer, const char *message);

/* Whether reading may go on after a part failed with rc: collecting, and
 * not out of memory (records rc as the result if it is the first). */
bool json_go_on(mr_json_ctx *c, int rc);

/* Runs expr (with /key or /index appended for the _AT_ forms) as a part
 * reading may go on after (see mr_json_ctx): the pointer is restored
 * either way, c->failed says whether the part failed, and a failure that
 * cannot be gone on from is returned. */
#define GO_ON_PART(c, mark, expr)                                                        \
    do {                                                                                 \
        size_t mark_ = (mark);                                                           \
        int rc_ = (expr);                                                                \
        json_pop((c), mark_);                                                            \
        (c)->failed = rc_ < 0;                                                           \
        if (rc_ < 0 && !json_go_on((c), rc_))                                            \
            return rc_;                                                                  \
    } while (0)
#define GO_ON(c, expr) GO_ON_PART((c), (c)->len, (expr))
#define GO_ON_AT_KEY(c, key, expr) GO_ON_PART((c), json_push_key((c), (key)), (expr))
#define GO_ON_AT_INDEX(c, i, expr) GO_ON_PART((c), json_push_index((c), (i)), (expr))

/* Values stored as float must fit one, or they silently become inf. */
extern const json_num_spec JSON_SPEC_FLOAT;

/* The pointer: json_push_key / json_push_index append "/key" (RFC 6901
 * escaped, cut at a UTF-8 boundary when too long) and return the length
 * json_pop goes back to. */
size_t json_push_key(mr_json_ctx *c, const char *key);
size_t json_push_index(mr_json_ctx *c, size_t i);
void json_pop(mr_json_ctx *c, size_t mark);

/* Failures: copy the current pointer and a message into the context's
 * error and return code. json_fail_expected says "expected <expect>, got
 * <a short description of v>". */
int json_fail(mr_json_ctx *c, int code, const char *fmt, ...) __attribute__((format(printf, 3, 4)));
int json_fail_nomem(mr_json_ctx *c);
int json_fail_expected(mr_json_ctx *c, const char *expect, const cJSON *v);
/* s as a short quoted string (cut with "..."), and v described for a message. */
void json_quote(const char *s, char *buf, size_t n);
const char *json_describe(const cJSON *v, char *buf, size_t n);

/* in copied into out (size bytes, NUL included) as valid UTF-8: each byte
 * of an invalid sequence written as the four characters \xHH, so a message
 * that quotes what a client sent is still a JSON string it can read. A
 * multi-byte character that does not fit is cut before it. */
void json_utf8_text(const char *in, char *out, size_t size);

/* Scalars: a finite number within spec (integral with JSON_NUM_INT), a
 * boolean, one of names (its index), and the "one of: ..." text. */
void json_spec_text(const json_num_spec *s, char *buf, size_t n);
int json_get_num(mr_json_ctx *c, const cJSON *v, const json_num_spec *s, double *out);
int json_get_bool(mr_json_ctx *c, const cJSON *v, bool *out);
int json_get_choice(mr_json_ctx *c, const cJSON *v, const char *const *names, size_t count,
                    const char *expected, int *out);
void json_choices_text(const char *const *names, size_t count, char *buf, size_t n);

/* Strings kept by the caller: 1..max bytes of valid UTF-8 without control
 * characters, copied into *out (json_dup_string copies without checks). */
int json_check_text(mr_json_ctx *c, const char *s, size_t max);
int json_dup_string(mr_json_ctx *c, const char *s, char **out);
int json_get_string(mr_json_ctx *c, const cJSON *v, size_t max, char **out);

/* Objects: a member, the object itself, only known keys each at most once
 * (n allowed, at most 32), unique user-chosen keys (maps), a required key. */
const cJSON *json_field(const cJSON *obj, const char *key);
int json_want_object(mr_json_ctx *c, const cJSON *v, const char *expect);
int json_check_fields(mr_json_ctx *c, const cJSON *obj, const char *const *allowed, size_t n);
int json_check_unique_keys(mr_json_ctx *c, const cJSON *obj, size_t n);
int json_require(mr_json_ctx *c, const cJSON *obj, const char *key);

/* Fixed-size arrays of numbers, vectors, unit vectors and quaternions. */
int json_get_numbers(mr_json_ctx *c, const cJSON *v, size_t n, const json_num_spec *s,
                     const char *expect, double *out);
int json_get_vec3(mr_json_ctx *c, const cJSON *v, const json_num_spec *s, mr_vec3 *out);
int json_get_unit_vec3(mr_json_ctx *c, const cJSON *v, mr_vec3 *out);
int json_get_quat(mr_json_ctx *c, const cJSON *v, mr_quat *out);

/* The whole document: at most max bytes (need not be NUL-terminated) of
 * UTF-8 without NUL bytes and one JSON value with nothing after it; noun
 * names it in messages ("job"). On success *text_out is the private copy
 * cJSON parsed (free it after *root_out). */
int json_parse_document(mr_json_ctx *c, const char *json, size_t len, size_t max, const char *noun,
                        char **text_out, cJSON **root_out);

#endif
