/*
 * stats_json.h - job statistics as JSON (stats.json, the API's stats).
 * The format is documented in the README ("stats.json").
 */
#ifndef MR_STATS_JSON_H
#define MR_STATS_JSON_H

#include "worker.h"

/* stats.json of frames [first, stats->frame_count): a malloc'ed,
 * NUL-terminated document in *out. MR_ERR_NOMEM (and *out NULL) when any
 * part of it could not be built: never a document with frames or fields
 * left out. */
int mr_stats_to_json(const mr_job *job, const mr_job_stats *stats, size_t first, char **out,
                     mr_error *err);

/* One frame's statistics (an element of stats.json's "frames") as compact
 * JSON; malloc'ed, NULL when out of memory (never one with fields left out). */
char *mr_frame_stats_json(const mr_frame_stats *f);

#endif
