/*
 * stats_openapi.h - the API's schema of a frame's statistics, generated
 * from the frame-stats field table (render/frame_stats.h) so that the
 * document cannot list other fields than the writer writes.
 *
 * schemas/openapi.yaml holds the generated text between two marker lines
 * (MR_STATS_OPENAPI_BEGIN / _END): the component schemas Seconds (the
 * "seconds" group, which the job totals and medians reuse) and FrameStats.
 * `make openapi` rewrites that block (tools/openapi_stats.c); the unit test
 * test_stats_json fails while the document differs from what the table
 * gives, naming the command.
 */
#ifndef MR_STATS_OPENAPI_H
#define MR_STATS_OPENAPI_H

#include <stdbool.h>

#include "microray.h"

#define MR_STATS_OPENAPI_BEGIN \
    "    # BEGIN frame stats, generated from core/render/frame_stats.c by `make openapi`\n"
#define MR_STATS_OPENAPI_END "    # END frame stats\n"

/* The block, marker lines included (malloc'ed; NULL when out of memory). */
char *mr_stats_openapi_block(void);

/* Compares the block in the YAML document at path with the generated one
 * (*stale tells whether they differ) and, when write is set, replaces it
 * (atomically). MR_ERR_FORMAT when the document lacks the markers. */
int mr_stats_openapi_update(const char *path, bool write, bool *stale, mr_error *err);

#endif
