/*
 * job_json.h - job JSON (docs/job-format.md, schemas/job.schema.json) to the
 * JSON-free structs of microray.h.
 *
 * The parser is the daemon's only gate for untrusted jobs, so it validates
 * everything the renderer relies on (ranges, caps, references between
 * fields, frame-count-dependent arrays) and reports the first problem as an
 * RFC 6901 JSON pointer plus a short "expected ..., got ..." message that an
 * HTTP layer can hand back to the user as it is.
 */
#ifndef MR_JOB_JSON_H
#define MR_JOB_JSON_H

#include "microray.h"
#include "json_reader.h"

/* Largest job document accepted, in bytes; larger inputs give MR_ERR_LIMIT. */
#define MR_JOB_MAX_BYTES (16u * 1024u * 1024u)

/* The first problem in a job: its JSON pointer and message. */
typedef mr_json_error mr_job_error;

/* Parses and validates len bytes of job JSON (need not be NUL-terminated).
 * On success returns MR_OK and a new job in *out (free with mr_job_free()).
 * On failure *out is NULL, nothing is leaked, err (may be NULL) names the
 * first problem, and the result is
 *   MR_ERR_INVALID  malformed JSON or a value that breaks the format,
 *   MR_ERR_LIMIT    input over MR_JOB_MAX_BYTES, or more assets, objects,
 *                   lights, joints, camera keys, frames or pixels than the
 *                   caps of microray.h allow,
 *   MR_ERR_NOMEM    out of memory.
 * Problems are looked for in a fixed order, so the same input always
 * reports the same error. Thread-safe apart from cJSON's own unsynchronised
 * write of its (unused here) global error position. */
int mr_job_parse(const char *json, size_t len, mr_job **out, mr_job_error *err);

/* Every problem of a job, not only the first (json_reader.h: reading goes
 * on after a field, a list element or a section that failed, and skips
 * what depends on it). */
typedef mr_json_errors mr_job_problems;

/* mr_job_parse collecting every problem into *all (all->items[0] is the
 * one mr_job_parse reports, and the result is its code). A document that
 * is not JSON has exactly one problem, marked syntax. */
int mr_job_check(const char *json, size_t len, mr_job **out, mr_job_problems *all);

#endif
