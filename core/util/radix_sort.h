/*
 * radix_sort.h - LSD radix sort of voxel keys by (code, level), optionally
 * carrying a uint32 payload per key (paper 004, 4.2 "Morton codes": the
 * voxelizer and the per-frame rebuild sort keys with the index of the voxel
 * they came from).
 *
 * The sort is stable, so keys that compare equal keep their input order and
 * the output (payloads included) is the same for any thread count. 11-bit
 * digits; passes whose digit is the same for every key are skipped, so keys
 * of a depth-D octree with one level cost ceil(3D / 11) passes.
 */
#ifndef MR_SVO_RADIX_SORT_H
#define MR_SVO_RADIX_SORT_H

#include <stddef.h>
#include <stdint.h>

#include "microray.h"
#include "kinds/svo/svo.h"

/* Sorts keys[0, count) ascending by (code, level) in place. key_scratch:
 * NULL (allocated internally) or room for count keys, contents clobbered.
 * threads 0 = all online cores. Returns MR_OK or MR_ERR_NOMEM. */
int mr_svo_radix_sort(mr_svo_key *keys, size_t count, mr_svo_key *key_scratch,
                      unsigned threads, mr_error *err);

/* Same, moving payload[i] along with keys[i] (payload may be NULL: then
 * this is mr_svo_radix_sort). payload_scratch: NULL or room for count. */
int mr_svo_radix_sort_payload(mr_svo_key *keys, uint32_t *payload, size_t count,
                              mr_svo_key *key_scratch, uint32_t *payload_scratch,
                              unsigned threads, mr_error *err);

#endif /* MR_SVO_RADIX_SORT_H */
