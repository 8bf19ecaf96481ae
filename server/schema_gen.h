/*
 * schema_gen.h - the job schema's geometry-kind parts, generated from the
 * kinds' parameter tables (microray.h), so the schema given to
 * clients cannot drift from the parser that reads the same tables.
 *
 * Generated, in schemas/job.schema.json: "$defs"/"kind_<name>" (each kind's
 * parameter block), and in "$defs"/"object": the "kind" enum, one
 * "<name>": {"$ref"} property per kind block and its "dependentSchemas"
 * entry (a block needs its "kind"). Everything else in the file is written
 * by hand and kept as it is. `microrayd schema FILE` prints the updated
 * document, `--check` says whether FILE is current; `make schema` rewrites
 * the committed file and a test fails when it is stale.
 */
#ifndef MR_SCHEMA_GEN_H
#define MR_SCHEMA_GEN_H

#include <cJSON.h>

#include "microray.h"

/* The JSON Schema of one kind's parameter block (NULL on allocation
 * failure or a kind without parameters; a malformed schema_rules text is
 * reported in err). Caller frees with cJSON_Delete. */
cJSON *mr_schema_kind_block(const mr_kind *kind, mr_error *err);

/* Replaces the generated parts of a job schema document by those of every
 * registered kind, in registry order; stale "kind_*" blocks are removed. */
int mr_schema_update(cJSON *schema, mr_error *err);

/* The document as text in the committed file's style: two-space indents,
 * arrays of scalars on one line, a final newline. malloc'ed. */
char *mr_schema_print(const cJSON *doc);

/* microrayd schema FILE [--check] */
int mr_cmd_schema(int argc, char **argv);

#endif
