/*
 * checkpoint.h - snapshots of a SEQUENTIAL kind's state (a simulation)
 * on disk, so that a resumed or retried job replays from the nearest one
 * instead of from frame 0 (the frame-order contract of kinds/kind.h).
 *
 * The renderer stores, after every checkpoint_every-th frame, the state
 * after frames 0..N-1 (N = frames applied) of each object whose kind
 * keeps checkpoints, in the kind's derived-data folder (<cache root>/<kind
 * name>/, the one folder a render worker may write besides: server/
 * sandbox.h), through the one derived-data cache (util/derived.h): written
 * to a temporary file, fsynced and renamed, so a crash leaves the old file
 * or the new one. Asked for frame N out of order, it restores the newest
 * checkpoint at or before N that loads, and replays only the frames after
 * it; nothing loads: it rewinds and replays from frame 0, as before.
 *
 * Key: SHA-256 of the tag "microray checkpoint", MR_CHECKPOINT_VERSION, the
 * kind's name, the kind's checkpoint_id (everything the state depends on:
 * asset content, parameters, transform, the kind's state format version)
 * and N. File (docs/derived-cache.md envelope; extension "mrckpt"):
 *
 *   offset size field
 *   0      8    magic "MRCKPT\r\n"
 *   8      4    version (MR_CHECKPOINT_VERSION)
 *   12     4    header_bytes (140)
 *   16     8    frames N
 *   24     8    payload bytes P
 *   32     4    payload CRC-32
 *   36     32   kind name, NUL-padded
 *   68     32   the kind's checkpoint_id
 *   100    32   key
 *   132    4    zero
 *   136    4    header CRC-32
 *   140    P    the kind's state (its checkpoint_save)
 *
 * Validation, in order: the envelope (size, magic, version, header_bytes,
 * header CRC), the key, then frames, kind name and id equal to the
 * request, size = 140 + P, the payload CRC, and last the kind's own
 * checkpoint_load, which checks what it reads and changes nothing unless
 * it accepts all of it. Any refusal is a miss: the renderer tries the
 * next older checkpoint, and the refused file is removed so the replay
 * that passes its frame writes it again (a file already present under a
 * key is otherwise kept: the key fixes its content). A checkpoint that cannot be written (a full disk)
 * costs a later resume some replay, never the frame.
 */
#ifndef MR_CHECKPOINT_H
#define MR_CHECKPOINT_H

#include <stdint.h>

#include "kinds/kind.h"

#define MR_CHECKPOINT_VERSION 1u

/* Whether objects of kind k keep checkpoints in dir (a kind folder, may
 * be NULL: no). */
bool mr_checkpoint_kept(const mr_kind *k, const mr_geom *g, const char *dir);
/* Stores g's state after `frames` frames under dir, unless a file is
 * already there. */
int mr_checkpoint_store(const char *dir, const mr_kind *k, const mr_geom *g, uint64_t frames,
                        mr_error *err);
/* Restores g's state after `frames` frames from dir: MR_ERR_IO when there
 * is no such file, MR_ERR_FORMAT when it is refused (g unchanged), else
 * the kind's error. */
int mr_checkpoint_load(const char *dir, const mr_kind *k, mr_geom *g, uint64_t frames, mr_error *err);
/* The file's path (malloc'ed) for g's state after `frames` frames. */
int mr_checkpoint_path(const char *dir, const mr_kind *k, const mr_geom *g, uint64_t frames,
                       char **path, mr_error *err);

#endif
