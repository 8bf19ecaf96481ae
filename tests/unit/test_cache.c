/*
 * test_cache.c - the scene cache: hits and misses by key, reference counts
 * that protect assets in use, least-recently-used eviction under the cap,
 * refined imports as entries of their own (keyed by file and refine
 * parameters) and the triangle cap on refinement. Real model files from
 * Debian's assimp-testmodels; the over-the-cap mesh is a generated OBJ.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "asset/asset.h"
#include "cache.h"

#define MODEL_A "/usr/share/assimp/models/X/BCN_Epileptic.X"
#define MODEL_B "/usr/share/assimp/models/Collada/human.zae"
#define MODEL_C "/usr/share/assimp/models/SMD/WusonSMD.smd"
#define MODEL_A_TRIANGLES 5126 /* BCN_Epileptic.X as imported */

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

static mr_asset *acquire_refined(mr_cache *c, const char *key, const char *path,
                                 const mr_refine_params *p, bool *hit)
{
    mr_asset *a = NULL;
    double saved;
    mr_error err = {0};
    if (mr_cache_acquire_refined(c, key, path, p, NULL, &a, hit, &saved, NULL, &err) < 0)
        fail_msg("%s", err.msg);
    return a;
}

static void test_refined_entries(void **state)
{
    (void)state;
    mr_cache *c = NULL;
    mr_error err = {0};
    assert_int_equal(mr_cache_new((size_t)1 << 30, &c, &err), MR_OK);
    bool hit;
    mr_asset *plain = acquire_refined(c, "a", MODEL_A, NULL, &hit);
    assert_false(hit);
    assert_int_equal(plain->triangle_count, MODEL_A_TRIANGLES);

    /* One Loop round: a different entry with 4x the triangles, skeleton
     * and clips carried over. */
    mr_refine_params r1 = {.rounds = 1, .frequency = 8, .octaves = 3, .seed = 1, .threads = 0};
    mr_asset *a1 = acquire_refined(c, "a", MODEL_A, &r1, &hit);
    assert_false(hit);
    assert_ptr_not_equal(a1, plain);
    assert_int_equal(a1->triangle_count, 4 * MODEL_A_TRIANGLES);
    assert_int_equal(a1->mesh_count, plain->mesh_count);
    assert_int_equal(a1->node_count, plain->node_count);
    assert_int_equal(a1->clip_count, plain->clip_count);
    for (size_t i = 0; i < a1->mesh_count; i++)
        assert_int_equal(a1->meshes[i].joint_count, plain->meshes[i].joint_count);

    /* The same parameters share it; the thread count is not a parameter,
     * and neither are the noise fields while the amplitude is 0. */
    mr_refine_params same = {.rounds = 1, .frequency = 3, .octaves = 7, .seed = 99, .threads = 1};
    assert_ptr_equal(acquire_refined(c, "a", MODEL_A, &same, &hit), a1);
    assert_true(hit);

    /* Detail, and detail with another seed: two more entries. */
    mr_refine_params d1 = r1;
    d1.amplitude = 0.01f;
    mr_asset *ad = acquire_refined(c, "a", MODEL_A, &d1, &hit);
    assert_false(hit);
    mr_refine_params d2 = d1;
    d2.seed = 2;
    mr_asset *ad2 = acquire_refined(c, "a", MODEL_A, &d2, &hit);
    assert_false(hit);
    assert_ptr_not_equal(ad, a1);
    assert_ptr_not_equal(ad2, ad);
    assert_int_equal(ad->triangle_count, 4 * MODEL_A_TRIANGLES);
    /* octaves 0 and 1 are both one band: one entry */
    mr_refine_params o0 = d1, o1 = d1;
    o0.octaves = 0;
    o1.octaves = 1;
    mr_asset *ao = acquire_refined(c, "a", MODEL_A, &o0, &hit);
    assert_false(hit);
    assert_ptr_equal(acquire_refined(c, "a", MODEL_A, &o1, &hit), ao);
    assert_true(hit);
    /* The detail really was applied: same topology as the undisplaced
     * refinement, every vertex within the amplitude of it (plus 1e-6 for
     * float rounding of coordinates of order 1), some moved. */
    bool moved = false;
    for (size_t i = 0; i < ad->mesh_count; i++) {
        const mr_mesh *m = &ad->meshes[i], *m0 = &a1->meshes[i];
        assert_int_equal(m->vertex_count, m0->vertex_count);
        for (size_t v = 0; v < (size_t)m->vertex_count * 3; v += 3) {
            double dx = m->positions[v] - m0->positions[v],
                   dy = m->positions[v + 1] - m0->positions[v + 1],
                   dz = m->positions[v + 2] - m0->positions[v + 2];
            double d = sqrt(dx * dx + dy * dy + dz * dz);
            assert_true(d <= 0.01 + 1e-6);
            moved |= d > 0;
        }
    }
    assert_true(moved);

    /* 0 rounds without detail changes nothing: the plain import's entry. */
    mr_refine_params none = {.rounds = 0, .frequency = 8, .octaves = 3, .seed = 1};
    assert_ptr_equal(acquire_refined(c, "a", MODEL_A, &none, &hit), plain);
    assert_true(hit);
    assert_ptr_equal(acquire(c, "a", MODEL_A, &hit), plain);
    assert_true(hit);
    /* Another file hash with the same refinement is another entry. */
    mr_asset *b1 = acquire_refined(c, "b", MODEL_A, &r1, &hit);
    assert_false(hit);
    assert_ptr_not_equal(b1, a1);

    mr_cache_stats st;
    mr_cache_stats_get(c, &st);
    assert_int_equal(st.entries, 6); /* plain, r1, d1, d2, octaves 0/1, b + r1 */
    assert_int_equal(st.misses, 6);
    assert_int_equal(st.hits, 4);
    assert_int_equal(st.bytes, mr_asset_memory(plain) + mr_asset_memory(a1) +
                                   mr_asset_memory(ad) + mr_asset_memory(ad2) +
                                   mr_asset_memory(ao) + mr_asset_memory(b1));
    mr_asset *held[] = {plain, a1, a1, ad, ad2, ao, ao, plain, plain, b1};
    for (size_t i = 0; i < sizeof held / sizeof held[0]; i++)
        mr_cache_release(c, held[i]);
    mr_cache_free(c);
}

/* Writes an OBJ grid of n x n quads (2 n^2 triangles) to path. */
static void write_grid(const char *path, int n)
{
    FILE *f = fopen(path, "w");
    assert_non_null(f);
    for (int y = 0; y <= n; y++)
        for (int x = 0; x <= n; x++)
            fprintf(f, "v %d %d 0\n", x, y);
    for (int y = 0; y < n; y++)
        for (int x = 0; x < n; x++) {
            int a = y * (n + 1) + x + 1, b = a + 1, d = a + n + 1, e = d + 1;
            fprintf(f, "f %d %d %d\nf %d %d %d\n", a, b, e, a, e, d);
        }
    assert_int_equal(fclose(f), 0);
}

static void test_refine_over_the_cap(void **state)
{
    (void)state;
    /* 182^2 * 2 = 66248 triangles: 4 rounds (x256) give 16959488, just over
     * MR_MAX_ASSET_TRIANGLES (16777216); refused before any refinement. */
    char dir[] = "/tmp/mr_test_cache_XXXXXX", path[64];
    assert_non_null(mkdtemp(dir));
    snprintf(path, sizeof path, "%s/grid.obj", dir);
    write_grid(path, 182);
    mr_cache *c = NULL;
    mr_error err = {0};
    assert_int_equal(mr_cache_new((size_t)1 << 30, &c, &err), MR_OK);
    mr_refine_params p = {.rounds = 4, .frequency = 8, .octaves = 3, .seed = 1};
    mr_asset *a = NULL;
    bool hit;
    double saved;
    mr_asset_stage stage = MR_ASSET_STAGE_LOAD;
    assert_int_equal(mr_cache_acquire_refined(c, "g", path, &p, NULL, &a, &hit, &saved, &stage, &err),
                     MR_ERR_LIMIT);
    assert_null(a);
    /* the worker points at "refine" because the stage says so */
    assert_int_equal(stage, MR_ASSET_STAGE_REFINE);
    assert_int_equal(strncmp(err.msg, "4 rounds would turn the 66248 triangles of", 42), 0);
    assert_non_null(strstr(err.msg, "into 16959488, more than the 16777216 an asset may have"));
    mr_cache_stats st;
    mr_cache_stats_get(c, &st);
    assert_int_equal(st.entries, 0);
    /* Without a cache: the same check. */
    err = (mr_error){0};
    stage = MR_ASSET_STAGE_LOAD;
    assert_int_equal(mr_cache_import(path, &p, &a, &stage, &err), MR_ERR_LIMIT);
    assert_null(a);
    assert_int_equal(stage, MR_ASSET_STAGE_REFINE);
    /* One round fewer fits the cap (not run: 4 million triangles); the
     * plain import works and is not a refine error. */
    assert_int_equal(mr_cache_import(path, NULL, &a, NULL, &err), MR_OK);
    assert_int_equal(a->triangle_count, 66248);
    mr_asset_free(a);
    /* a broken file fails as an import, not a refinement */
    err = (mr_error){0};
    stage = MR_ASSET_STAGE_REFINE;
    assert_int_equal(mr_cache_import("/usr/share/assimp/models/invalid/empty.obj", &p, &a, &stage,
                                     &err), MR_ERR_FORMAT);
    assert_int_equal(stage, MR_ASSET_STAGE_LOAD);
    /* also through the cache, and for a missing file */
    stage = MR_ASSET_STAGE_REFINE;
    assert_int_equal(mr_cache_acquire_refined(c, "nope", "/nonexistent/x.obj", &p, NULL, &a, &hit, &saved,
                                              &stage, &err), MR_ERR_IO);
    assert_int_equal(stage, MR_ASSET_STAGE_LOAD);
    mr_cache_free(c);
    assert_int_equal(unlink(path), 0);
    assert_int_equal(rmdir(dir), 0);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_hits_and_misses),
        cmocka_unit_test(test_lru_eviction_spares_assets_in_use),
        cmocka_unit_test(test_refined_entries),
        cmocka_unit_test(test_refine_over_the_cap),
    };
    return cmocka_run_group_tests_name("cache", tests, NULL, NULL);
}
