/*
 * space_guard.h - what the daemon does when its disk fills up (issue 12
 * item 5).
 *
 * Without it a full disk turned into an endless loop: the frame's file
 * could not be written, nor could sqlite record the failure, so the frame
 * was retried thousands of times a minute while the API showed nothing
 * wrong; and with sqlite unable to write, not even a DELETE could free
 * space, and a restart exited.
 *
 * The guard keeps a reserve: a file of reserve bytes (DATA/space.reserve)
 * written while there is room. The first write that fails for want of
 * space (MR_ERR_NO_SPACE) is reported here: the guard deletes the reserve,
 * which gives sqlite room to record the failure and to delete jobs, and
 * says the disk is full until polling finds at least twice the reserve free
 * again, when it writes the reserve back. The daemon pauses its queue
 * meanwhile and keeps answering reads and deletes (daemon.c). A start on
 * a full disk releases the reserve before the store opens, so it starts
 * (paused) instead of exiting.
 */
#ifndef MR_SPACE_GUARD_H
#define MR_SPACE_GUARD_H

#include <stdbool.h>
#include <stddef.h>

#include "microray.h"

typedef struct mr_space_guard mr_space_guard;

#define MR_SPACE_RESERVE_NAME "space.reserve"

/* Keeps DIR/space.reserve of reserve_bytes (0: no reserve, only the state).
 * A disk too full for it starts the guard full. */
int mr_space_guard_open(const char *dir, size_t reserve_bytes, mr_space_guard **out,
                        mr_error *err);
void mr_space_guard_close(mr_space_guard *g);

/* A write failed for want of space (why: its message). Returns true when
 * this report turned the guard full (the caller logs it once). */
bool mr_space_guard_report(mr_space_guard *g, const char *why);
/* The write that failed wanted `bytes` (a frame's file): polling then
 * waits for that much free beyond twice the reserve, so the queue does
 * not resume only to fail the same write again. */
void mr_space_guard_need(mr_space_guard *g, size_t bytes);
/* Whether the file system has `bytes` free (statvfs: a quota does not
 * show there). */
bool mr_space_guard_has_room(mr_space_guard *g, size_t bytes);
/* Whether the disk is full; why (may be NULL) gets the first report. */
bool mr_space_guard_full(mr_space_guard *g, char *why, size_t size);
/* When full: if at least twice the reserve (and what the failed write
 * wanted) is free, writes the reserve back and clears the state. Returns
 * true when it did (the caller resumes). */
bool mr_space_guard_poll(mr_space_guard *g);

#endif
