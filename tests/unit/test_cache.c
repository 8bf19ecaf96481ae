/*
 * test_cache.c - the scene cache: hits and misses by key, reference counts
 * that protect assets in use, least-recently-used eviction under the cap.
 * Real model files from Debian's assimp-testmodels.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include "cache.h"

#define MODEL_A "/usr/share/assimp/models/X/BCN_Epileptic.X"
#define MODEL_B "/usr/share/assimp/models/Collada/human.zae"
#define MODEL_C "/usr/share/assimp/models/SMD/WusonSMD.smd"

static mr_asset *acquire(mr_cache *c, const char *key, const char *path, bool *hit)
{
    mr_asset *a = NULL;
    double saved;
    mr_error err = {0};
    if (mr_cache_acquire(c, key, path, &a, hit, &saved, &err) < 0)
        fail_msg("%s", err.msg);
    if (*hit)
        assert_true(saved > 0); /* a hit reports the import time it avoided */
    return a;
}

static void test_hits_and_misses(void **state)
{
    (void)state;
    mr_cache *c = NULL;
    mr_error err = {0};
    assert_int_equal(mr_cache_new((size_t)1 << 30, &c, &err), MR_OK);
    bool hit;
    mr_asset *a1 = acquire(c, "a", MODEL_A, &hit);
    assert_false(hit);
    mr_asset *a2 = acquire(c, "a", MODEL_A, &hit);
    assert_true(hit);
    assert_ptr_equal(a1, a2); /* the same import is shared */
    mr_asset *b = acquire(c, "b", MODEL_B, &hit);
    assert_false(hit);
    mr_cache_stats st;
    mr_cache_stats_get(c, &st);
    assert_int_equal(st.hits, 1);
    assert_int_equal(st.misses, 2);
    assert_int_equal(st.entries, 2);
    assert_int_equal(st.bytes, mr_asset_memory(a1) + mr_asset_memory(b));
    mr_cache_release(c, a1);
    mr_cache_release(c, a2);
    mr_cache_release(c, b);
    /* a broken file is an error and is not cached */
    mr_asset *x = NULL;
    double saved;
    assert_int_equal(mr_cache_acquire(c, "x", "/usr/share/assimp/models/invalid/empty.obj", &x, &hit, &saved, &err),
                     MR_ERR_FORMAT);
    mr_cache_stats_get(c, &st);
    assert_int_equal(st.entries, 2);
    mr_cache_free(c);
}

static void test_lru_eviction_spares_assets_in_use(void **state)
{
    (void)state;
    /* Measure the three assets, then give the cache room for about two. */
    mr_cache *probe = NULL;
    mr_error err = {0};
    assert_int_equal(mr_cache_new((size_t)1 << 30, &probe, &err), MR_OK);
    bool hit;
    size_t sa = mr_asset_memory(acquire(probe, "a", MODEL_A, &hit));
    size_t sb = mr_asset_memory(acquire(probe, "b", MODEL_B, &hit));
    size_t sc = mr_asset_memory(acquire(probe, "c", MODEL_C, &hit));
    mr_cache_stats st;
    mr_cache_stats_get(probe, &st);
    assert_int_equal(st.evictions, 0);
    mr_cache_free(probe); /* with references still held: freeing the cache frees them */

    size_t cap = sa + sb + sc - 1; /* all three never fit */
    mr_cache *c = NULL;
    assert_int_equal(mr_cache_new(cap, &c, &err), MR_OK);
    mr_asset *a = acquire(c, "a", MODEL_A, &hit);
    mr_asset *b = acquire(c, "b", MODEL_B, &hit);
    mr_cache_release(c, b);
    mr_cache_release(c, a); /* a is now the most recently used... */
    a = acquire(c, "a", MODEL_A, &hit); /* ...and in use again */
    assert_true(hit);
    mr_asset *cc = acquire(c, "c", MODEL_C, &hit);
    assert_false(hit);
    /* over the cap: b, unreferenced, goes; a and c are in use and stay */
    mr_cache_stats_get(c, &st);
    assert_int_equal(st.evictions, 1);
    assert_int_equal(st.entries, 2);
    assert_true(st.bytes <= cap);
    acquire(c, "a", MODEL_A, &hit);
    assert_true(hit);
    mr_asset *b2 = acquire(c, "b", MODEL_B, &hit);
    assert_false(hit); /* b was evicted: imported again */
    /* everything is in use now, so the cache may exceed its cap */
    mr_cache_stats_get(c, &st);
    assert_true(st.bytes > cap);
    mr_cache_release(c, a);
    mr_cache_release(c, a);
    mr_cache_release(c, cc);
    mr_cache_release(c, b2);
    /* released: back under the cap by evicting the least recently used */
    mr_cache_stats_get(c, &st);
    assert_true(st.bytes <= cap);
    mr_cache_free(c);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_hits_and_misses),
        cmocka_unit_test(test_lru_eviction_spares_assets_in_use),
    };
    return cmocka_run_group_tests_name("cache", tests, NULL, NULL);
}
