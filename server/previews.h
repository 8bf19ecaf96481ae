/*
 * previews.h - PNG previews of a job's stored frames for the HTTP API
 * (GET /v1/jobs/{id}/frames/{n}.png, the same with Accept: image/png, and
 * GET /v1/jobs/{id}/contact-sheet.png): made from the frames' EXRs by core
 * (mr_preview_*, render/preview.c; only R, G, B, A are used) and cached
 * next to them in DATA/frames/<id>/, so each picture is made once:
 *   NNNN.png                a frame's full-size preview
 *   NNNN.thumb.png          its contact-sheet thumbnail
 *   contact-sheet-KEY.png   the sheet; KEY (16 hex digits of a SHA-256)
 *                           names what it shows: the frame count and which
 *                           of its frames were done. Writing one removes
 *                           the older ones.
 * A cached file is used only when it is not older than its EXR (and a
 * thumbnail only when it decodes to the size expected); else it is made
 * again. A finished frame's EXR never changes, so in practice each picture
 * is made once; a sheet is remade when one of its frames finished since,
 * from the cached thumbnails plus the EXRs of the newly finished frames.
 * Caching is best effort: when a file cannot be written (disk full, a job
 * deletion racing us) the picture is still answered from memory, and a file
 * left behind by such a race goes with the orphaned folder at the next
 * start (mr_store_recover). Deleting a job removes the folder and all of it.
 *
 * Every call is split into a cheap "cached" half and a "build" half that
 * reads EXRs, so the caller can bound how many builds run at once (the HTTP
 * front end keeps them off most of its threads).
 */
#ifndef MR_PREVIEWS_H
#define MR_PREVIEWS_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "microray.h"

/* What to answer: an open file (fd >= 0, size bytes) or bytes in memory. */
typedef struct mr_preview_body {
    int fd;
    uint8_t *data; /* malloc'ed, when fd < 0 */
    size_t size;
} mr_preview_body;

/* Closes or frees what the body holds (after a response took neither). */
void mr_preview_body_free(mr_preview_body *b);

/* The cached preview of the frame whose EXR is exr_path, when there is a
 * fresh one: true with out->fd set. */
bool mr_preview_frame_cached(const char *exr_path, mr_preview_body *out);

/* Makes the preview from the EXR (and caches it when may_cache):
 * MR_ERR_NOT_FOUND when the EXR is gone (a job deleted meanwhile);
 * MR_ERR_FORMAT or MR_ERR_IO, naming the file, when it cannot be read. */
int mr_preview_frame_build(const char *exr_path, bool may_cache, mr_preview_body *out,
                           mr_error *err);

/* What a contact sheet shows (mr_contact_sheet_frames) and which of those
 * frames are done: exr[i] is frame index[i]'s EXR path, NULL while it is not
 * finished. Filled by the caller, which owns the paths. */
typedef struct mr_sheet_plan {
    size_t frame_count;                 /* frames of the job */
    size_t count;                       /* cells */
    size_t index[MR_SHEET_MAX_FRAMES];
    char *exr[MR_SHEET_MAX_FRAMES];
    char key[17];                       /* mr_sheet_plan_key */
} mr_sheet_plan;

/* Computes plan->key from the frame count and the done flags. */
void mr_sheet_plan_key(mr_sheet_plan *plan);

/* The cached sheet of plan->key: true with out->fd set. */
bool mr_preview_sheet_cached(const mr_sheet_plan *plan, mr_preview_body *out);

/* Draws the sheet of frames width x height (the job's output size): cached
 * thumbnails where fresh, else thumbnails of the EXRs (at most
 * MR_SHEET_MAX_FRAMES reads); caches what it made when may_cache. Fails
 * naming the frame whose EXR cannot be read (MR_ERR_FORMAT, MR_ERR_IO;
 * *bad_frame set), MR_ERR_NOT_FOUND when one is gone. */
int mr_preview_sheet_build(const mr_sheet_plan *plan, int width, int height, bool may_cache,
                           mr_preview_body *out, size_t *bad_frame, mr_error *err);

#endif
