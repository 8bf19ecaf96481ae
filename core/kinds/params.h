/*
 * params.h - a geometry kind's job parameters, declared as a table.
 *
 * Each kind that takes parameters (a block named after the kind in a job
 * object: "<kind>": {...}) describes them once, here, as data: field name, type, range or
 * enum values, default, one-line description, and where the value lives in
 * the kind's own C struct. Everything else is derived from that table:
 *   - the server reads and validates the block generically (server/
 *     job_reader.c), with a JSON pointer and an "expected X, got Y" message
 *     for every bad value;
 *   - the job schema's kind blocks are generated from it (microrayd schema,
 *     `make schema`), so the schema cannot drift from the parser;
 *   - defaults are filled in and owned memory released generically
 *     (mr_params_defaults, mr_params_clear), so core/job.c knows no kind.
 * Rules a table cannot express (two fields that exclude each other, a
 * limit that depends on another field) are per-field `after` hooks, run
 * right after the field was read (or found absent), in table order, so the
 * first error in the document is the one reported.
 *
 * Storage by type: INT -> uint32_t (tables give lo >= 0), NUMBER -> float
 * (lo/hi within the float range), BOOL -> bool, ENUM -> int (index into
 * choices), TRANSFORM -> mr_mat4 (the job's transform grammar, identity by
 * default), POSE -> mr_pose_desc plus a bool at present_offset,
 * FLAG_OBJECT -> bool at offset, given as true/false or as an object of the
 * sub table's fields (stored in the same struct; the bool then becomes
 * true), ARRAY -> a pointer at offset to count elements of sub->size bytes,
 * the count a size_t at count_offset, 1..max_items of them.
 */
#ifndef MR_PARAMS_H
#define MR_PARAMS_H

#include <stdbool.h>
#include <stddef.h>

#include "microray.h"

typedef enum mr_param_type {
    MR_PARAM_INT = 0,
    MR_PARAM_NUMBER,
    MR_PARAM_BOOL,
    MR_PARAM_ENUM,
    MR_PARAM_FLAG_OBJECT,
    MR_PARAM_ARRAY,
    MR_PARAM_TRANSFORM,
    MR_PARAM_POSE
} mr_param_type;

/* mr_param.flags: open ends of a number's range. */
enum { MR_PARAM_LO_OPEN = 1u, MR_PARAM_HI_OPEN = 2u };

/* At most this many fields in one table (the reader tracks them in a
 * 32-bit set). */
#define MR_PARAM_MAX_FIELDS 32u

/* What an `after` hook reports: the field the pointer should end at
 * (relative to the block; "" for the block itself), code and message. */
typedef struct mr_param_error {
    int code;
    char field[64];
    char message[256];
} mr_param_error;

typedef struct mr_param_table mr_param_table;

typedef struct mr_param {
    const char *field;
    mr_param_type type;
    size_t offset;             /* of the value in the table's struct */
    double lo, hi;             /* INT, NUMBER: range */
    unsigned flags;            /* MR_PARAM_LO_OPEN | MR_PARAM_HI_OPEN */
    const char *const *choices; /* ENUM: names in the order of the stored int */
    size_t choice_count;
    double def;                /* default: the number, 0/1, or the enum index */
    const char *expect;        /* "expected ..." text instead of the generated one, or NULL */
    const char *description;   /* one line, for the schema and docs */
    const char *conflicts;     /* a later field of this table that may not be given with this one */
    const mr_param_table *sub; /* FLAG_OBJECT: its object's fields; ARRAY: an element's */
    size_t present_offset;     /* POSE: bool set when the pose is given */
    size_t count_offset;       /* ARRAY: size_t element count */
    size_t max_items;          /* ARRAY */
    /* Runs after the field was read or found absent (given[i]: field i of
     * the table was in the job). Returns MR_OK or fills err and returns its
     * code. May adjust other values (a default that depends on this one). */
    int (*after)(void *values, const bool *given, mr_param_error *err);
} mr_param;

struct mr_param_table {
    const mr_param *params;
    size_t count;
    size_t size;         /* bytes of the struct the values live in */
    const char *expect;  /* what the block is: "an object of <kind> parameters" */
    const char *plural;  /* ARRAY elements, for "an array of 1..N <plural>" */
    /* The after hooks' rules as JSON Schema keywords (the members of a JSON
     * object, e.g. "if"/"then"), merged into the generated block; NULL if
     * none. Text only: core parses no JSON. */
    const char *schema_rules;
};

/* Writes every default of t into values (sub tables included). */
void mr_params_defaults(const mr_param_table *t, void *values);
/* Releases what values own (arrays and the poses inside them), leaving
 * them empty; values itself is the caller's. Accepts partially read
 * values (NULL arrays, counts set as soon as arrays exist). */
void mr_params_clear(const mr_param_table *t, void *values);
/* A table's field by name, or NULL. */
const mr_param *mr_param_find(const mr_param_table *t, const char *field);
/* Index of `field` in t, or -1. */
int mr_param_index(const mr_param_table *t, const char *field);

/* Fills err (returns code): a helper for after hooks. */
int mr_param_fail(mr_param_error *err, int code, const char *field, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 4, 5)))
#endif
    ;

#endif
