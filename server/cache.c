/* cache.c - LRU, reference-counted cache of imported assets (cache.h). */
#include "cache.h"

#include <inttypes.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "microray.h"

/* A file hash (64 hex) plus the refine suffix (about 70 bytes at most). */
#define KEY_MAX 256

typedef struct entry {
    char key[KEY_MAX];
    mr_asset *asset;
    size_t bytes;
    int refs;
    uint64_t last_use;  /* cache clock at the last acquire */
    double import_s;    /* what a hit saves */
    struct entry *next;
} entry;

struct mr_cache {
    pthread_mutex_t lock;
    size_t cap;
    entry *entries;
    uint64_t clock;
    mr_cache_stats stats;
};

int mr_cache_new(size_t cap_bytes, mr_cache **out, mr_error *err)
{
    mr_cache *c = calloc(1, sizeof *c);
    if (!c)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory creating the scene cache");
    pthread_mutex_init(&c->lock, NULL);
    c->cap = cap_bytes;
    *out = c;
    return MR_OK;
}

void mr_cache_free(mr_cache *c)
{
    if (!c)
        return;
    for (entry *e = c->entries, *next; e; e = next) {
        next = e->next;
        mr_asset_free(e->asset);
        free(e);
    }
    pthread_mutex_destroy(&c->lock);
    free(c);
}

/* Drops unreferenced entries, least recently used first, while over the cap.
 * Called with the lock held. */
static void evict(mr_cache *c)
{
    while (c->stats.bytes > c->cap) {
        entry **victim = NULL;
        for (entry **p = &c->entries; *p; p = &(*p)->next)
            if ((*p)->refs == 0 && (!victim || (*p)->last_use < (*victim)->last_use))
                victim = p;
        if (!victim)
            return; /* everything left is in use */
        entry *e = *victim;
        *victim = e->next;
        c->stats.bytes -= e->bytes;
        c->stats.entries--;
        c->stats.evictions++;
        mr_asset_free(e->asset);
        free(e);
    }
}

static entry *find(mr_cache *c, const char *key)
{
    for (entry *e = c->entries; e; e = e->next)
        if (strcmp(e->key, key) == 0)
            return e;
    return NULL;
}

/* The refinement that gives the same asset as *in with the fewest
 * distinguishing fields (cache.h lists the equivalences), or false when it
 * changes nothing. */
static bool refine_canonical(const mr_refine_params *in, mr_refine_params *out)
{
    if (in->rounds == 0 && in->amplitude == 0.0f)
        return false;
    *out = (mr_refine_params){.rounds = in->rounds, .threads = in->threads};
    if (in->amplitude != 0.0f) {
        out->amplitude = in->amplitude;
        out->frequency = in->frequency;
        out->octaves = in->octaves ? in->octaves : 1;
        out->seed = in->seed;
    }
    return true;
}

int mr_cache_import(const char *path, const mr_refine_params *refine, mr_asset **out,
                    mr_asset_stage *stage, mr_error *err)
{
    mr_asset *base = NULL;
    mr_asset_stage at = MR_ASSET_STAGE_LOAD;
    *out = NULL;
    int rc = mr_asset_load(path, &base, err);
    if (rc < 0 || !refine)
        goto done;
    at = MR_ASSET_STAGE_REFINE;
    if (refine->rounds > MR_REFINE_MAX_ROUNDS) {
        rc = mr_error_set(err, MR_ERR_INVALID, "%u rounds, at most %d", refine->rounds,
                          MR_REFINE_MAX_ROUNDS);
        goto done;
    }
    /* Every round splits every triangle in four, so the count is known
     * now: refuse before spending minutes and gigabytes on it. */
    size_t base_tris = mr_asset_triangle_count(base);
    uint64_t tris = (uint64_t)base_tris << (2 * refine->rounds);
    if (tris > MR_MAX_ASSET_TRIANGLES) {
        rc = mr_error_set(err, MR_ERR_LIMIT,
                          "%u rounds would turn the %zu triangles of %s into %llu, more "
                          "than the %u an asset may have",
                          refine->rounds, base_tris, path, (unsigned long long)tris,
                          MR_MAX_ASSET_TRIANGLES);
        goto done;
    }
    mr_asset *refined = NULL;
    if ((rc = mr_refine_asset(base, refine, &refined, err)) < 0) {
        mr_error_prefix(err, "%s: ", path);
        goto done;
    }
    mr_asset_free(base);
    base = refined;
done:
    if (rc < 0) {
        mr_asset_free(base);
        if (stage)
            *stage = at;
    } else {
        *out = base;
    }
    return rc;
}

int mr_cache_acquire(mr_cache *c, const char *key, const char *path, mr_asset **out, bool *hit,
                     double *saved_s, mr_error *err)
{
    return mr_cache_acquire_refined(c, key, path, NULL, NULL, out, hit, saved_s, NULL, err);
}

int mr_cache_acquire_refined(mr_cache *c, const char *key, const char *path,
                             const mr_refine_params *refine, const mr_cache_importer *importer,
                             mr_asset **out, bool *hit, double *saved_s, mr_asset_stage *stage,
                             mr_error *err)
{
    *out = NULL;
    *hit = false;
    *saved_s = 0;
    mr_refine_params canon;
    bool refined = refine && refine_canonical(refine, &canon);
    char full[KEY_MAX];
    int n;
    /* %a prints a float (promoted to double) exactly, so equal keys mean
     * bit-equal parameters. The suffix starts with '/', which no file hash
     * or upload id contains. */
    if (refined)
        n = snprintf(full, sizeof full, "%s/refine:r%u,a%a,f%a,o%u,s%" PRIu32, key, canon.rounds,
                     (double)canon.amplitude, (double)canon.frequency, canon.octaves, canon.seed);
    else
        n = snprintf(full, sizeof full, "%s", key);
    if (stage)
        *stage = MR_ASSET_STAGE_LOAD; /* until the import says otherwise */
    if (n < 0 || (size_t)n >= sizeof full)
        return mr_error_set(err, MR_ERR_INVALID, "cache key too long");
    pthread_mutex_lock(&c->lock);
    entry *e = find(c, full);
    if (e) {
        e->refs++;
        e->last_use = ++c->clock;
        c->stats.hits++;
        c->stats.saved_s += e->import_s;
        *out = e->asset;
        *hit = true;
        *saved_s = e->import_s;
        pthread_mutex_unlock(&c->lock);
        return MR_OK;
    }
    c->stats.misses++;
    pthread_mutex_unlock(&c->lock);

    /* Import (and refine) without the lock: other jobs keep using the cache
     * meanwhile. */
    double t0 = mr_now();
    mr_asset *a = NULL;
    const mr_refine_params *how = refined ? &canon : NULL;
    int rc = importer ? importer->import(importer->user, path, how, &a, stage, err)
                      : mr_cache_import(path, how, &a, stage, err);
    if (rc < 0)
        return rc;
    double import_s = mr_now() - t0;

    pthread_mutex_lock(&c->lock);
    e = find(c, full);
    if (e) { /* someone imported the same file meanwhile: use theirs */
        e->refs++;
        e->last_use = ++c->clock;
        *out = e->asset;
        pthread_mutex_unlock(&c->lock);
        mr_asset_free(a);
        return MR_OK;
    }
    e = calloc(1, sizeof *e);
    if (!e) {
        pthread_mutex_unlock(&c->lock);
        mr_asset_free(a);
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory caching %s", path);
    }
    snprintf(e->key, sizeof e->key, "%s", full);
    e->asset = a;
    e->bytes = mr_asset_memory(a);
    e->refs = 1;
    e->last_use = ++c->clock;
    e->import_s = import_s;
    e->next = c->entries;
    c->entries = e;
    c->stats.bytes += e->bytes;
    c->stats.entries++;
    evict(c);
    *out = a;
    pthread_mutex_unlock(&c->lock);
    return MR_OK;
}

void mr_cache_release(mr_cache *c, mr_asset *asset)
{
    if (!asset)
        return;
    pthread_mutex_lock(&c->lock);
    for (entry *e = c->entries; e; e = e->next)
        if (e->asset == asset) {
            if (e->refs > 0)
                e->refs--;
            break;
        }
    evict(c);
    pthread_mutex_unlock(&c->lock);
}

void mr_cache_stats_get(mr_cache *c, mr_cache_stats *out)
{
    pthread_mutex_lock(&c->lock);
    *out = c->stats;
    pthread_mutex_unlock(&c->lock);
}
