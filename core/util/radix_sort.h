/*
 * radix_sort.h - the stable LSD radix sorts of voxel keys (paper 004, 4.2
 * "Morton codes"): the voxelizer and the per-frame rebuild sort keys with
 * the index of the voxel they came from.
 *
 * Two key layouts, one scheme. mr_svo_radix_sort sorts the 16-byte
 * mr_svo_key by (code, level), optionally carrying a uint32 payload per key.
 * mr_radix_sort_u64 sorts 64-bit keys with a payload, such as mr_svo_keys
 * packed into one word (mr_svo_key_pack): half the bytes to move, and level
 * and code sorted together in fewer passes, which is what the per-frame
 * resampling of deformed octrees wants (most of its time is the sort).
 *
 * Both sorts are stable, so keys that compare equal keep their input order
 * and the output (payloads included) is the same for any thread count.
 * Passes over digits that are the same for every key are skipped.
 */
#ifndef MR_SVO_RADIX_SORT_H
#define MR_SVO_RADIX_SORT_H

#include <stddef.h>
#include <stdint.h>

#include "microray.h"
#include "kinds/svo/svo.h"

/* ---- 16-byte keys --------------------------------------------------------
 * 11-bit digits; keys of a depth-D octree with one level cost
 * ceil(3D / 11) passes. */

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

/* ---- packed keys ---------------------------------------------------------
 * An mr_svo_key as one uint64: code << MR_SVO_KEY_PACK_LEVEL_BITS | level.
 * Packed keys order like (code, level); they hold levels below 32 and the
 * codes of octrees up to MR_SVO_KEY_PACK_MAX_DEPTH deep (3 * 19 + 5 <= 64). */
#define MR_SVO_KEY_PACK_LEVEL_BITS 5u
#define MR_SVO_KEY_PACK_MAX_DEPTH ((64u - MR_SVO_KEY_PACK_LEVEL_BITS) / 3u)

static inline uint64_t mr_svo_key_pack(uint64_t code, uint32_t level)
{
    return code << MR_SVO_KEY_PACK_LEVEL_BITS | level;
}

static inline mr_svo_key mr_svo_key_unpack(uint64_t packed)
{
    mr_svo_key k;
    k.code = packed >> MR_SVO_KEY_PACK_LEVEL_BITS;
    k.level = (uint32_t)(packed & ((1u << MR_SVO_KEY_PACK_LEVEL_BITS) - 1u));
    return k;
}

/* ---- 64-bit keys ---------------------------------------------------------
 * Digits of at most 10 bits, spread evenly over the bits that vary: 2^10
 * buckets of 8 + 4 bytes stay in L2 while scattering. */

/* One sort of 64-bit keys with a uint32 payload each. */
typedef struct mr_radix_u64 {
    uint64_t *keys, *key_scratch;         /* count each; both clobbered */
    uint32_t *payload, *payload_scratch;  /* count each; both clobbered */
    size_t count;
    /* The bits in which keys differ: every key must agree with every other
     * outside them. OR ^ AND over all keys, which callers gather while
     * writing the keys; only these bits are sorted on. */
    uint64_t varying;
    /* NULL, or room for count keys: the last pass then writes the sorted
     * keys there unpacked (mr_svo_key_unpack) instead of as uint64; there
     * is always a pass then, even when nothing varies. */
    mr_svo_key *unpack;
    /* mr_radix_sort_u64_hist_words() counts, or NULL: allocated by the
     * sort. A per-frame caller keeps them in its workspace. */
    uint32_t *hist;
    unsigned threads;                     /* 0 = all online cores */
    /* Results. The passes alternate between the arrays and the sort copies
     * nothing back: these point at whichever of keys / key_scratch and
     * payload / payload_scratch hold the sorted order (sorted_keys is NULL
     * when the keys went to unpack). */
    uint64_t *sorted_keys;
    uint32_t *sorted_payload;
} mr_radix_u64;

/* How many uint32 counts sort s needs in s->hist (from count, varying,
 * unpack and threads). */
size_t mr_radix_sort_u64_hist_words(const mr_radix_u64 *s);

/* Sorts s->keys ascending, stable, moving each payload with its key, and
 * sets s->sorted_keys / s->sorted_payload. MR_ERR_INVALID for missing
 * arrays, MR_ERR_LIMIT beyond 2^32 - 1 keys, MR_ERR_NOMEM. */
int mr_radix_sort_u64(mr_radix_u64 *s, mr_error *err);

#endif /* MR_SVO_RADIX_SORT_H */
