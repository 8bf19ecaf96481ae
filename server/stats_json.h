/*
 * stats_json.h - job statistics as JSON (stats.json, the API's stats),
 * written and read by the frame-stats field table (render/frame_stats.h).
 * The format is documented in the README ("stats.json") and in
 * schemas/openapi.yaml (FrameStats, generated from the same table).
 */
#ifndef MR_STATS_JSON_H
#define MR_STATS_JSON_H

#include <cJSON.h>

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

/* The table's fields of one frame object back into *f (frame = index);
 * missing or mistyped fields are 0, derived ones and extras are not read
 * (the stored text carries them). */
void mr_frame_stats_from_json(const cJSON *o, size_t index, mr_frame_stats *f);

/* The stats.json document (as a cJSON tree, *out) of frames given as their
 * frame objects (in frame order; each with its "frame" index), as stored by
 * the daemon or written in partial stats files: totals and medians
 * computed by the one writer above, every frame object shown as given
 * (kinds' extras and other fields kept). Used by the daemon's job stats
 * and by `microrayd stats-merge`. */
int mr_stats_from_frames(const mr_job *job, cJSON *const *frames, size_t n, unsigned threads,
                         cJSON **out, mr_error *err);

#endif
