/*
 * cache.h - the scene cache: imported assets (and, as geometry kinds grow,
 * everything derived from them) kept in memory between jobs, keyed by the
 * content hash of the file plus the import parameters, under a memory cap
 * with least-recently-used eviction.
 *
 * Entries are reference counted: an asset in use by a running job is never
 * evicted (the cache may then exceed its cap until the job releases it).
 */
#ifndef MR_CACHE_H
#define MR_CACHE_H

#include "asset/asset.h"

typedef struct mr_cache mr_cache;

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
void mr_cache_release(mr_cache *c, mr_asset *asset);
void mr_cache_stats_get(mr_cache *c, mr_cache_stats *out);

#endif
