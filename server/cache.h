/*
 * cache.h - the scene cache: imported assets (and, as geometry kinds grow,
 * everything derived from them) kept in memory between jobs, keyed by the
 * content hash of the file plus the import parameters, under a memory cap
 * with least-recently-used eviction.
 *
 * Refined imports (an asset's "refine" in the job) are entries of their own,
 * refined once when they are imported.
 *
 * Entries are reference counted: an asset in use by a running job is never
 * evicted (the cache may then exceed its cap until the job releases it).
 */
#ifndef MR_CACHE_H
#define MR_CACHE_H

#include "microray.h"

typedef struct mr_cache mr_cache;

/* Which step of getting an asset failed (mr_cache_import and
 * mr_cache_acquire_refined set it when they fail): reading and importing
 * the file, or refining the import. The worker points its error at the
 * asset's "path"/"id" or at its "refine" by it. */
typedef enum mr_asset_stage {
    MR_ASSET_STAGE_LOAD,   /* the file: missing, unreadable, broken, over a cap */
    MR_ASSET_STAGE_REFINE  /* its "refine" parameters or the refinement itself */
} mr_asset_stage;

typedef struct mr_cache_stats {
    uint64_t hits, misses, evictions;
    size_t bytes, entries;
    double saved_s; /* import seconds that hits avoided */
} mr_cache_stats;

int mr_cache_new(size_t cap_bytes, mr_cache **out, mr_error *err);
/* Frees every entry; no asset may still be acquired. */
void mr_cache_free(mr_cache *c);

/* The asset for the file at path, whose content hash is key (hex). On a
 * miss the file is imported and cached. *hit tells which; on a hit
 * *saved_s is the import time avoided (0 on a miss). Release with
 * mr_cache_release. */
int mr_cache_acquire(mr_cache *c, const char *key, const char *path, mr_asset **out, bool *hit,
                     double *saved_s, mr_error *err);
/* mr_cache_acquire of a refined import: the entry holds the file's import
 * refined by mr_refine_asset (done once, on the miss), keyed by key plus the
 * refine parameters, so other parameters never share it and the same ones
 * always do. refine NULL is the plain import (mr_cache_acquire). Parameters
 * that give the same result share one key: params->threads is ignored
 * (refinement is bit-identical for any thread count); with amplitude 0 the
 * noise fields are; octaves 0 counts as 1; and 0 rounds with amplitude 0
 * (the input unchanged) is the plain import's entry. */
/* How a miss imports: NULL means mr_cache_import in this process; the
 * daemon passes one that imports in a child process (import_worker.h). */
typedef struct mr_cache_importer {
    int (*import)(void *user, const char *path, const mr_refine_params *refine, mr_asset **out,
                  mr_asset_stage *stage, mr_error *err);
    void *user;
} mr_cache_importer;
int mr_cache_acquire_refined(mr_cache *c, const char *key, const char *path,
                             const mr_refine_params *refine, const mr_cache_importer *importer,
                             mr_asset **out, bool *hit, double *saved_s, mr_asset_stage *stage,
                             mr_error *err);
void mr_cache_release(mr_cache *c, mr_asset *asset);
void mr_cache_stats_get(mr_cache *c, mr_cache_stats *out);

/* What a miss does, for callers without a cache (the one-shot renderer):
 * mr_asset_load, then, with refine (may be NULL), mr_refine_asset. A refined
 * asset whose triangles would exceed MR_MAX_ASSET_TRIANGLES fails with
 * MR_ERR_LIMIT before any work. On failure *stage (stage may be NULL) says
 * which step failed; messages name the file and say what is wrong, without
 * a pointer (the caller knows which field the stage is). */
int mr_cache_import(const char *path, const mr_refine_params *refine, mr_asset **out,
                    mr_asset_stage *stage, mr_error *err);

#endif
