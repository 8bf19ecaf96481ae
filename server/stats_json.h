/*
 * stats_json.h - job statistics as JSON (stats.json, the API's stats).
 * The format is documented in the README ("stats.json").
 */
#ifndef MR_STATS_JSON_H
#define MR_STATS_JSON_H

#include "worker.h"

/* Returns a malloc'ed, NUL-terminated JSON document, or NULL when out of
 * memory. Frames [first, stats->frame_count) are included. */
char *mr_stats_to_json(const mr_job *job, const mr_job_stats *stats, size_t first);

/* One frame's statistics (an element of stats.json's "frames") as compact
 * JSON; malloc'ed, NULL when out of memory. */
char *mr_frame_stats_json(const mr_frame_stats *f);

#endif
