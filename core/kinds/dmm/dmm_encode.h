/*
 * dmm_encode.h - second stage of the DMM baker (paper 000, issue 4 part 1):
 * hierarchical, quantised encoding of the per-micro-vertex displacements of
 * dmm_bake.h, the min/max displacement pyramid of the paper's Fig. 11, and a
 * validated binary file (docs/dmm-format.md).
 *
 * Levels per triangle: every base triangle has its own level 0..level (the
 * DMM's largest) and a decimation mask (micromesh.h: edges whose neighbour
 * is one level coarser), packed in one byte, mr_dmm_tri_info. Its record
 * takes mr_dmm_record_bytes(its level, bits); records follow each other.
 * The hierarchy below is the same at every level (a vertex new at level l
 * sits at edge parameter k / 2^l whatever the triangle's level), so a shared
 * edge between a level-l and a level-(l+1) triangle stores and decodes the
 * same values for its level <= l vertices on both sides.
 *
 * Encoding:
 *  - Value grid. Displacements are mapped to unsigned integers V in
 *    [0, 2^G - 1], G = bits[0], by d = bias + scale * V (evaluated in double,
 *    rounded once to float). bias and scale are shared by the whole DMM and
 *    stored in its header. They are deliberately NOT per triangle: a
 *    micro-vertex on a shared base edge must decode bit-identically on both
 *    triangles (issue 4 part 2), so every quantity it depends on must be data
 *    both triangles share. Per-triangle adaptivity comes from the per-level
 *    correction shifts below (a power-of-two scale of the corrections, chosen
 *    per triangle for the interior and per edge for edge vertices).
 *  - Level 0: the three corner values, G bits each (lossless on the grid).
 *  - Level l = 1..L: every new vertex is predicted as the rounded integer
 *    mean (p + q + 1) >> 1 of its two parent-edge neighbours (decoded values,
 *    so encoder and decoder agree exactly), and the correction
 *    c = V - prediction is stored as a bits[l]-bit two's complement q with a
 *    shift s (c ~ q << s). Four shifts per level: edge 0, 1, 2 (micromesh.h
 *    numbering) and interior. An edge shift is the smallest s for which every
 *    correction of that edge's new vertices fits; it is computed from the
 *    edge's values only, and the prediction of an edge vertex uses only edge
 *    vertices, so both triangles store and decode the same bits for the edge
 *    (whatever their orientation: the prediction is symmetric and rounding
 *    of q is symmetric about zero). Decoded values are clamped to the grid.
 *  - The quantisation error is at most scale / 2 when every shift is 0
 *    (lossless on the grid), else scale * (1/2 + 2^(s-1)) for the vertex's
 *    shift s, unless a correction had to be clamped (stats->clamped), plus
 *    the final float rounding.
 *
 * Pyramid (Fig. 11): sub-triangles of level l are numbered hierarchically,
 * the children of sub-triangle i being 4i .. 4i+3 at level l + 1. For a
 * sub-triangle with lattice corners (P0, P1, P2) and edge midpoints m01, m12,
 * m20 the children are (P0, m01, m20), (m01, P1, m12), (m20, m12, P2) and the
 * inverted middle one (m12, m20, m01). Level 0 is the base triangle
 * ((0,0), (n,0), (0,n)). An entry holds the min and max decoded value V of all
 * micro-vertices in the closed sub-triangle; levels are stored one after the
 * other, level l starting at entry (4^l - 1) / 3. mr_dmm_value_to_float is
 * monotone, so the float bounds are the converted integer bounds.
 */
#ifndef MR_DMM_ENCODE_H
#define MR_DMM_ENCODE_H

#include <float.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "kinds/dmm/micromesh.h"
#include "microray.h"

/* Widest value grid / correction width. */
#define MR_DMM_MAX_BITS 16u
/* Largest triangle count a file may declare (a cap so a corrupt header
 * cannot ask for gigabytes). */
#define MR_DMM_MAX_TRIANGLES (1u << 24)
/* Size of the fixed file header (docs/dmm-format.md). */
#define MR_DMM_HEADER_BYTES 48u

/* A triangle's level (bits 0..2) and decimation mask (bits 4..6). */
static inline uint8_t mr_dmm_tri_info(unsigned level, unsigned decimate)
{
    return (uint8_t)((level & 7u) | (decimate & 7u) << 4);
}
static inline unsigned mr_dmm_info_level(uint8_t info) { return info & 7u; }
static inline unsigned mr_dmm_info_decimate(uint8_t info) { return info >> 4 & 7u; }

typedef struct mr_dmm_encoded {
    unsigned level;                         /* largest triangle level, 0..MR_UMESH_MAX_LEVEL */
    uint8_t bits[MR_UMESH_MAX_LEVEL + 1];   /* bits[0] = G; bits[l] for l <= level; rest 0 */
    uint32_t triangle_count;
    uint32_t records_bytes;                 /* sum of the records' sizes */
    float bias;                             /* d = bias + scale * V */
    float scale;                            /* > 0 */
    uint8_t *tri_info;                      /* per triangle: mr_dmm_tri_info */
    uint32_t *record_offset;                /* per triangle: its record's first byte */
    uint8_t *records;                       /* records_bytes */
} mr_dmm_encoded;

/* Quantisation error of an encode against its float input. */
typedef struct mr_dmm_encode_stats {
    double max_error;     /* max |decoded - input| over all micro-vertices */
    double rms_error;
    uint64_t clamped;     /* corrections that did not fit even at the largest shift */
    uint64_t shifted;     /* corrections stored with a shift > 0 (lossy) */
    unsigned max_shift;   /* largest shift used; error <= scale * (1/2 + 2^(max_shift-1)) */
} mr_dmm_encode_stats;

/* Default bits per level {16, 11, 10, 9, 8, 7} into bits. The grid gets
 * the full 16 bits: its step is range / 65535 for the whole DMM, and the
 * micro-edges of level 5 are 1/32 of a base edge, so an 11-bit grid (the
 * default until issue 13) left quantisation steps of 4 % of a level-5
 * micro-edge on the bench dancer's torso (normals off by about 1 degree
 * on average, more than what level 5 gained over level 4). The grid width
 * costs only the three corner values of a record (15 bits more per base
 * triangle); the corrections keep their widths, since a finer grid only
 * makes the rare corrections that do not fit shift (lossy by 2^(s-1)
 * steps of the finer grid). */
void mr_dmm_default_bits(uint8_t bits[MR_UMESH_MAX_LEVEL + 1]);

/* Bytes of one triangle record, 0 for an invalid level / bit widths (bits[0]
 * in 1..16, bits[1..level] in 2..16). */
uint32_t mr_dmm_record_bytes(unsigned level, const uint8_t bits[MR_UMESH_MAX_LEVEL + 1]);

/* Encodes triangle_count triangles of displacements, mr_umesh_vertex_count
 * (level) floats per triangle (micromesh.h vertex order, triangle after
 * triangle, e.g. mr_dmm_bake.displacements). tri_info gives each triangle's
 * level (<= level) and decimation mask; NULL = every triangle at `level`,
 * none decimated. A triangle of a lower level uses the first
 * mr_umesh_vertex_count(its level) floats of its block. bits entries above
 * level are ignored. stats may be NULL. MR_ERR_INVALID for bad parameters or
 * non-finite input, MR_ERR_LIMIT when the records would pass 2 GiB,
 * MR_ERR_NOMEM. *out is NULL on failure. */
int mr_dmm_encode(unsigned level, const uint8_t bits[MR_UMESH_MAX_LEVEL + 1],
                  uint32_t triangle_count, const uint8_t *tri_info, const float *disp,
                  mr_dmm_encoded **out, mr_dmm_encode_stats *stats, mr_error *err);

void mr_dmm_encoded_free(mr_dmm_encoded *enc);

/* Level and decimation mask of triangle tri (tri < triangle_count). */
unsigned mr_dmm_tri_level(const mr_dmm_encoded *enc, uint32_t tri);
unsigned mr_dmm_tri_decimate(const mr_dmm_encoded *enc, uint32_t tri);

/* Decodes triangle tri to grid values V (mr_umesh_vertex_count(its level)
 * of them, micromesh.h order). Pure integer arithmetic: bit-exact
 * everywhere. */
int mr_dmm_decode_values(const mr_dmm_encoded *enc, uint32_t tri, uint16_t *values,
                         mr_error *err);
/* Grid value to displacement: bias + scale * V in double, clamped to the
 * finite float range (scale is rounded, so a range near FLT_MAX could
 * otherwise overflow), rounded once. Inline: the traversal's boxes take
 * their displacement bounds from it too (dmm_trace.c). */
static inline float mr_dmm_value_to_float(const mr_dmm_encoded *enc, uint16_t v)
{
    double d = (double)enc->bias + (double)enc->scale * (double)v;
    return (float)(d > FLT_MAX ? FLT_MAX : d < -FLT_MAX ? -FLT_MAX : d);
}
/* Decodes triangle tri to float displacements. */
int mr_dmm_decode_floats(const mr_dmm_encoded *enc, uint32_t tri, float *out, mr_error *err);

/* Entries of a pyramid down to level L: (4^(L+1) - 1) / 3; 0 for a bad level. */
uint32_t mr_dmm_pyramid_size(unsigned level);
/* Lattice corners (a[k], b[k]), k = 0..2, of sub-triangle id at sublevel
 * (0..level) of a level-`level` micro-mesh, in the order of the header
 * comment. false for bad arguments. */
bool mr_dmm_subtri(unsigned level, unsigned sublevel, uint32_t id, uint32_t a[3], uint32_t b[3]);
/* Builds the pyramid of one triangle from its decoded values: minv and maxv
 * get mr_dmm_pyramid_size(level) entries. MR_ERR_INVALID for a bad level. */
int mr_dmm_pyramid_build(unsigned level, const uint16_t *values, uint16_t *minv, uint16_t *maxv,
                         mr_error *err);

/* Serialises to a malloc'ed buffer (*buf owned by the caller). */
int mr_dmm_write(const mr_dmm_encoded *enc, uint8_t **buf, size_t *size, mr_error *err);
/* Writes path via a temporary file in the same directory, fsync and rename. */
int mr_dmm_write_file(const mr_dmm_encoded *enc, const char *path, mr_error *err);
/* Parses and fully validates a buffer; any defect gives MR_ERR_FORMAT with a
 * message naming the byte offset. */
int mr_dmm_read(const uint8_t *buf, size_t size, mr_dmm_encoded **out, mr_error *err);
/* Reads a file (MR_ERR_IO if it cannot be read; larger than the largest
 * valid file: MR_ERR_FORMAT) and parses it with mr_dmm_read. */
int mr_dmm_read_file(const char *path, mr_dmm_encoded **out, mr_error *err);

#endif /* MR_DMM_ENCODE_H */
