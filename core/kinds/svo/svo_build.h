/*
 * svo_build.h - from sorted voxel keys to an octree (paper 004, 4.2):
 * duplicate/nesting compaction that keeps the coarsest voxel
 * (thesis 3.3 "sample level preservation", eq. 4.2.2 taken as "a coarser
 * voxel wins over the finer ones inside it"), then the octree nodes of
 * svo.h built level by level from the sorted unique codes, in parallel over
 * blocks of keys (svo_build.c; the thesis builds Karras' 2012 binary radix
 * tree first).
 *
 * Layout produced: nodes in breadth-first order (by level, then code), so
 * node 0 is the root and the interior children of every node are
 * consecutive; leaves ordered by (level, code), so a node's leaf children are
 * consecutive too. For surface voxels all at the finest level the leaves are
 * in Morton order. leaf_keys is filled (but for mr_svo_build_frame).
 */
#ifndef MR_SVO_BUILD_H
#define MR_SVO_BUILD_H

#include <stddef.h>
#include <stdint.h>

#include "microray.h"
#include "kinds/svo/svo.h"

/* Keys the build counts and writes as one task (a block); a block's keys
 * that add to a cell an earlier block opened do so after the loop. The
 * prefix sums over the nodes run in blocks of as many nodes. */
#define MR_SVO_BUILD_BLOCK 16384u

/* Compacts keys[0, count), sorted by (code, level) (mr_svo_radix_sort), in
 * place: drops exact duplicates and every key nested inside an earlier
 * (coarser or equal) key, so the first of each nest, which is the coarsest,
 * stays. kept_from (NULL or room for count) receives, for each kept key, the
 * index of the input key it is, so callers can compact payloads alongside.
 * Levels above depth, code bits at or above 3 * depth, codes not aligned to
 * their level (low 3 * (depth - level) bits set) and unsorted input give
 * MR_ERR_INVALID (*out_count is then 0, and the keys before the first
 * invalid one and their kept_from entries are already compacted); count
 * above 2^32 - 1 gives MR_ERR_LIMIT. */
int mr_svo_compact(mr_svo_key *keys, size_t count, unsigned depth, uint32_t *kept_from,
                   size_t *out_count, mr_error *err);

/* Builds *out (zeroed first; released by mr_svo_free) from count sorted,
 * compacted keys of an octree of the given depth (1..MR_SVO_MAX_DEPTH).
 * leaves[i] (NULL: normal +z, attr 0) belongs to keys[i]; its attr must be
 * below palette_count, so any key needs a palette. The palette is copied.
 * origin, size: the cube (size finite and > 0). threads 0 = all cores; the
 * result is the same for every thread count.
 * Errors: MR_ERR_INVALID (message says which key) for keys that are
 * unsorted, duplicated, nested, misaligned, beyond the depth or level,
 * attr out of range, bad depth or cube; MR_ERR_LIMIT above 2^32 - 1 keys or
 * nodes, MR_ERR_NOMEM. */
int mr_svo_build(const mr_svo_key *keys, const mr_svo_leaf *leaves, size_t count,
                 unsigned depth, mr_vec3 origin, float size,
                 const mr_svo_attr *palette, uint32_t palette_count,
                 unsigned threads, mr_svo *out, mr_error *err);

/* mr_svo_build for a per-frame octree of the resampling methods: out
 * shares palette instead of copying it, and has no leaf_keys (it is never
 * re-keyed). out->palette points at palette, which must outlive out and not
 * change while out is in use (out->palette_borrowed: mr_svo_free leaves it,
 * mr_svo_memory does not count it): a copy per instance was 245 KB for the
 * dancer, most of what an instance held. The keys were 16 bytes a leaf
 * written and freed every frame (36 MB at depth 12 for the dancer). */
int mr_svo_build_frame(const mr_svo_key *keys, const mr_svo_leaf *leaves, size_t count, unsigned depth,
                       mr_vec3 origin, float size, const mr_svo_attr *palette, uint32_t palette_count,
                       unsigned threads, mr_svo *out, mr_error *err);

#endif /* MR_SVO_BUILD_H */
