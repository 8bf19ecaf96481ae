/*
 * fuzz_derived.c - libFuzzer harness of the derived-data readers: the
 * voxelised octree (`<key>.mrsvo`, mr_svo_file_read) and the baked
 * displaced micro-mesh (`<key>.dmm`, mr_dmm_file_read, which reads each
 * mesh's encoded displacements with mr_dmm_read), the files a daemon keeps
 * in its data directory and `microrayd render --cache DIR` in DIR, and
 * reads back on the next job (docs/derived-cache.md).
 *
 * An input's first byte picks the reader (even: octree, odd: bake); the
 * rest is the file. The fuzzing build takes every checksum as matching
 * (FUZZING_BUILD_MODE_UNSAFE_FOR_PRODUCTION, util/crc32.h), so inputs reach
 * the fields behind the checksums: what a reader accepts there must be
 * safe to use, whatever wrote it. So what a job does with a cache file
 * follows an accepted one:
 *  - an octree: its leaves' box fitted (mr_svo_fit_occupied), its pieces
 *    (mr_svo_subtrees, the rigid method's), rays at it from 26 directions,
 *    whole and from each of a few pieces, one hit's normal and palette
 *    entry read, and its extreme matrices' tree (mr_svo_extremes_build, the
 *    deforming methods');
 *  - a bake: every triangle of every mesh decoded (mr_dmm_decode_values)
 *    and its min/max pyramid built (mr_dmm_pyramid_build), up to 4,096
 *    triangles.
 * A reader's contract is checked too: MR_OK exactly when it returns a
 * result, and an error is MR_ERR_FORMAT, MR_ERR_LIMIT or MR_ERR_NOMEM with
 * a message.
 *
 * Seeds (tests/fuzz/corpus/fuzz_derived/): octrees of a small bumpy field
 * (surface at depths 3 and 5, solid at 4) and its bake at levels 1 and 2,
 * written by `fuzz_derived -seeds DIR`.
 */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "kinds/dmm/dmm_bake.h"
#include "kinds/dmm/dmm_encode.h"
#include "kinds/dmm/dmm_file.h"
#include "kinds/dmm/micromesh.h"
#include "kinds/svo/deform.h"
#include "kinds/svo/svo_file.h"
#include "kinds/svo/svo_trace.h"
#include "kinds/svo/voxelize.h"
#include "microray.h"
#include "../support/grid_fixture.h"
#include "fuzz_seeds.h"

static void die(const char *what)
{
    fprintf(stderr, "fuzz_derived: %s\n", what);
    abort();
}

/* A reader's contract: MR_OK with what it read, or one of the documented
 * codes, with a message and nothing read. True when it read something. */
static bool reader_read(int rc, bool has_result, const mr_error *err)
{
    if (rc == MR_OK) {
        if (!has_result)
            die("a reader returned MR_OK without a result");
        return true;
    }
    if (has_result)
        die("a reader failed but handed back a result");
    if (rc != MR_ERR_FORMAT && rc != MR_ERR_LIMIT && rc != MR_ERR_NOMEM)
        die("a reader failed with an undocumented code");
    if (!memchr(err->msg, '\0', sizeof err->msg) || !err->msg[0])
        die("a reader failed without a message");
    return false;
}

/* ---- the octree */

/* A hit as the renderer uses it: its leaf's normal and palette entry. */
static void use_hit(const mr_svo *svo, const mr_svo_hit *h)
{
    if (!(h->leaf < svo->leaf_count) || h->level > svo->depth)
        die("a hit outside the octree");
    const mr_svo_leaf *leaf = &svo->leaves[h->leaf];
    mr_vec3 n = mr_svo_normal_decode(leaf->normal);
    if (!isfinite(n.x) || !isfinite(n.y) || !isfinite(n.z))
        die("a leaf's normal decodes to a non-finite vector");
    if (svo->palette_count && leaf->attr < svo->palette_count) {
        volatile uint8_t a = svo->palette[leaf->attr].albedo[0];
        (void)a;
    }
}

static void trace_octree(const mr_svo *svo)
{
    float lo[3], hi[3];
    if (!mr_svo_bounds(svo, lo, hi)) {
        lo[0] = lo[1] = lo[2] = 0.0f;
        hi[0] = hi[1] = hi[2] = 1.0f;
    }
    const mr_vec3 c = mr_v3(0.5f * (lo[0] + hi[0]), 0.5f * (lo[1] + hi[1]), 0.5f * (lo[2] + hi[2]));
    const float reach = 2.0f * (fabsf(hi[0] - lo[0]) + fabsf(hi[1] - lo[1]) + fabsf(hi[2] - lo[2])) + 1.0f;
    mr_svo_subtree *pieces = NULL;
    uint32_t piece_count = 0;
    mr_error err;
    const unsigned piece_level = svo->depth > 2 ? 2 : svo->depth - 1;
    if (svo->depth >= 1 && mr_svo_subtrees(svo, piece_level, &pieces, &piece_count, &err) != MR_OK)
        pieces = NULL, piece_count = 0;
    for (int dx = -1; dx <= 1; dx++)
        for (int dy = -1; dy <= 1; dy++)
            for (int dz = -1; dz <= 1; dz++) {
                if (!dx && !dy && !dz)
                    continue;
                const mr_vec3 d = mr_v3((float)dx, (float)dy + 0.25f * (float)dz, (float)dz);
                const mr_vec3 o = mr_v3(c.x - reach * d.x, c.y - reach * d.y, c.z - reach * d.z);
                mr_svo_hit h;
                if (mr_svo_intersect(svo, o, d, 0.0f, INFINITY, &h))
                    use_hit(svo, &h);
                (void)mr_svo_occluded(svo, o, d, 0.0f, INFINITY);
                for (uint32_t p = 0; p < piece_count && p < 16; p++) {
                    if (mr_svo_intersect_subtree(svo, &pieces[p], o, d, 0.0f, INFINITY, &h))
                        use_hit(svo, &h);
                    mr_vec3 org[2] = {o, c}, dir[2] = {d, d};
                    float t0[2] = {0.0f, 0.0f}, t1[2] = {INFINITY, INFINITY};
                    mr_svo_hit hits[2];
                    uint32_t found = mr_svo_intersect_rays(svo, &pieces[p], 2, org, dir, t0, t1, NULL, hits);
                    for (unsigned k = 0; k < 2; k++)
                        if (found & (1u << k))
                            use_hit(svo, &hits[k]);
                }
            }
    free(pieces);
}

static void read_octree(const uint8_t *data, size_t size)
{
    mr_svo *svo = NULL;
    mr_error err = {0};
    int rc = mr_svo_file_read(data, size, &svo, &err);
    if (!reader_read(rc, svo != NULL, &err))
        return;
    if (svo->has_occupied || mr_svo_fit_occupied(svo, &err) == MR_OK)
        trace_octree(svo);
    mr_svo_extremes ex;
    memset(&ex, 0, sizeof ex);
    if (mr_svo_extremes_build(svo, &ex, &err) == MR_OK)
        mr_svo_extremes_free(&ex);
    mr_svo_voxelize_free(svo);
}

/* ---- the bake */

static void read_bake(const uint8_t *data, size_t size)
{
    mr_dmm_file *f = NULL;
    mr_error err = {0};
    int rc = mr_dmm_file_read(data, size, &f, &err);
    if (!reader_read(rc, f != NULL, &err))
        return;
    uint32_t budget = 4096;
    for (uint32_t m = 0; m < f->mesh_count && budget; m++) {
        const mr_dmm_encoded *enc = f->meshes[m].encoded;
        if (!enc)
            continue;
        for (uint32_t t = 0; t < enc->triangle_count && budget; t++, budget--) {
            const unsigned level = mr_dmm_tri_level(enc, t);
            if (level > enc->level)
                die("a triangle's level above its encoding's");
            uint16_t values[2048], minv[2048], maxv[2048];
            if (mr_umesh_vertex_count(level) > 2048 || mr_dmm_pyramid_size(level) > 2048)
                die("a level past the buffers (MR_UMESH_MAX_LEVEL grew?)");
            if (mr_dmm_decode_values(enc, t, values, &err) == MR_OK)
                (void)mr_dmm_pyramid_build(level, values, minv, maxv, &err);
        }
    }
    mr_dmm_file_free(f);
}

/* ---- seeds */

static void write_seed(const char *dir, const char *name, uint8_t pick, const uint8_t *buf, size_t size)
{
    char path[1024];
    snprintf(path, sizeof path, "%s/%s", dir, name);
    FILE *out = fopen(path, "wb");
    if (!out || fwrite(&pick, 1, 1, out) != 1 || fwrite(buf, 1, size, out) != size || fclose(out) != 0)
        die("cannot write a seed");
}

static void write_seeds(const char *dir)
{
    mr_error err = {0};
    mr_asset *a = grid_field(6, 0.2f, 4, 3, &err);
    if (!a)
        die(err.msg);
    static const struct {
        unsigned depth;
        mr_svo_voxelize_mode mode;
        const char *name;
    } octrees[] = {{3, MR_SVO_VOXELIZE_SURFACE, "svo-surface-3"},
                   {5, MR_SVO_VOXELIZE_SURFACE, "svo-surface-5"},
                   {4, MR_SVO_VOXELIZE_SOLID, "svo-solid-4"}};
    for (size_t i = 0; i < sizeof octrees / sizeof octrees[0]; i++) {
        mr_svo_voxelize_params p = {.depth = octrees[i].depth, .mode = octrees[i].mode, .threads = 1};
        mr_svo *s = NULL;
        uint8_t *buf = NULL;
        size_t size = 0;
        if (mr_svo_voxelize(a, &p, &s, &err) != MR_OK || mr_svo_file_write(s, &buf, &size, &err) != MR_OK)
            die(err.msg);
        write_seed(dir, octrees[i].name, 0, buf, size);
        free(buf);
        mr_svo_voxelize_free(s);
    }
    for (unsigned level = 1; level <= 2; level++) {
        mr_dmm_bake_params bp = mr_dmm_bake_params_default();
        bp.level = level;
        bp.target_ratio = 0.5f;
        mr_dmm_file f = {.level = level, .mesh_count = 1};
        mr_dmm_default_bits(f.bits);
        for (unsigned l = level + 1; l <= MR_UMESH_MAX_LEVEL; l++)
            f.bits[l] = 0;
        mr_dmm_file_mesh mesh = {.source_vertex_count = a->meshes[0].vertex_count};
        f.meshes = &mesh;
        uint8_t *buf = NULL;
        size_t size = 0;
        if (mr_dmm_bake_run(&a->meshes[0], &bp, &mesh.bake, &err) != MR_OK ||
            mr_dmm_encode(level, f.bits, mesh.bake->base_triangle_count, mesh.bake->tri_info,
                          mesh.bake->displacements, &mesh.encoded, NULL, &err) != MR_OK ||
            mr_dmm_file_write(&f, &buf, &size, &err) != MR_OK)
            die(err.msg);
        char name[32];
        snprintf(name, sizeof name, "dmm-level-%u", level);
        write_seed(dir, name, 1, buf, size);
        free(buf);
        mr_dmm_encoded_free(mesh.encoded);
        mr_dmm_bake_free(mesh.bake);
    }
    mr_asset_free(a);
}

int LLVMFuzzerInitialize(int *argc, char ***argv)
{
    fuzz_seeds_option(*argc, *argv, write_seeds);
    return 0;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    if (size < 1)
        return 0;
    if (data[0] & 1u)
        read_bake(data + 1, size - 1);
    else
        read_octree(data + 1, size - 1);
    return 0;
}
