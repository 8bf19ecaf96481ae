/*
 * import_worker.h - asset imports in a child process, so that no model file
 * can take the daemon down with it (issue 12).
 *
 * assimp reads dozens of formats and believes their counts: a 220-byte PLY
 * can ask it for 24 GB, a deep glTF can overflow its recursion, a broken
 * file can crash it. The daemon therefore imports (and refines) in a forked
 * child with
 *   - a memory limit: the child's growth in resident memory is watched and
 *     the child killed beyond it (and, outside sanitizer builds, an
 *     address-space limit makes the big reservations fail at once);
 *   - a wall-clock deadline (and a CPU-time limit just past it);
 *   - no file descriptors but its result pipe, no core dump, and death
 *     with its parent thread;
 * and hands the asset back through a pipe (mr_asset_blob_write). A cancel or a
 * daemon stop kills the child at once. Whatever happens to the child, the
 * daemon gets an error that says so ("... used more than 2.0 GiB", "...
 * crashed the importer (SIGSEGV)") and keeps serving.
 */
#ifndef MR_IMPORT_WORKER_H
#define MR_IMPORT_WORKER_H

#include <stdbool.h>
#include <stddef.h>

#include "cache.h"
#include "microray.h"

typedef struct mr_import_limits {
    size_t memory_bytes; /* the import's own resident memory; 0: unlimited */
    double timeout_s;    /* wall clock; 0: unlimited */
    /* The microrayd binary to exec in the child (`microrayd import-worker`),
     * or NULL: the forked child imports itself. Exec is what a daemon
     * wants: after fork in a process of many threads, a lock another
     * thread held (an allocator's: seen with ASan's, whose child then hung
     * until the deadline) stays held in the child; a fresh image has none.
     * Forking alone serves single-threaded callers (tests, harnesses). */
    const char *worker_exe;
} mr_import_limits;

/* The defaults a daemon uses when none are given: a quarter of the
 * machine's memory (at least 1 GiB), and 300 s. */
void mr_import_limits_default(mr_import_limits *out);

/* mr_cache_import(path, refine) in a child process under lim. label names
 * the asset in messages (an upload's id rather than its path in the data
 * directory). interrupted (may be NULL) is polled every 50 ms: true kills
 * the child and returns MR_ERR_CANCELLED. */
int mr_import_isolated(const char *path, const char *label, const mr_refine_params *refine,
                       const mr_import_limits *lim, bool (*interrupted)(void *user), void *user,
                       mr_asset **out, mr_asset_stage *stage, mr_error *err);

/* The child's side: imports path (and refines it) and writes the result to
 * descriptor 3 for the parent. Returns the exit status (0: written). Used
 * by the forked child and by `microrayd import-worker PATH [--refine
 * ROUNDS AMPLITUDE FREQUENCY OCTAVES SEED THREADS]`, which runs only as
 * mr_import_isolated's child. */
int mr_import_worker_run(const char *path, const mr_refine_params *refine);
int mr_cmd_import_worker(int argc, char **argv);

#endif
