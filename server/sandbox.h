/*
 * sandbox.h - what a render worker may touch on disk (issue 12: "no access
 * to the data directory beyond what it needs").
 *
 * Once it has started, a render worker confines itself with Linux's
 * Landlock: from then on (and in every import child it starts) it may
 *   - read and execute the system's files (/usr, /lib*, /bin, /sbin, /etc,
 *     /proc, /sys, /dev) and its own binary;
 *   - read the asset roots and the uploaded assets (DATA/assets);
 *   - read and write each geometry kind's derived-data folder (DATA/<kind>,
 *     created here);
 * and nothing else: not the daemon's database, not the frames, not the
 * rest of the file system. A model that names a file outside its folder is
 * refused before this (asset.h); this is the floor under that.
 *
 * On a kernel without Landlock the worker runs unconfined (the daemon
 * still refuses such paths itself); mr_sandbox_apply says so.
 */
#ifndef MR_SANDBOX_H
#define MR_SANDBOX_H

#include <stdbool.h>
#include <stddef.h>

#include "microray.h"

/* Confines the calling process (and its future children) as above.
 * Returns MR_OK when confined, MR_ERR_NOT_FOUND when the kernel has no
 * Landlock (nothing done), another error when a rule could not be set (the
 * process may then be half-confined: the caller should exit). exe may be
 * NULL. */
int mr_sandbox_apply(const char *data_dir, const char *const *asset_roots, size_t root_count,
                     const char *exe, mr_error *err);

#endif
