/*
 * deflate.h - a fast zlib-format (RFC 1950 / 1951) compressor for rows of
 * image bytes: what the EXR writer hands its ZIP and ZIPS chunks to.
 *
 * Why not a general-purpose library: after OpenEXR's ZIP predictor a
 * rendered frame is mostly long runs (background, empty passes), and a
 * general match finder pays for every byte a match covers (libdeflate
 * about 1.5 ns a byte even on a run of one value; that was three quarters
 * of a frame's encode). The repeats in these bytes sit at a few known
 * distances: 1, 2 and 4 (runs of one value, of a float's two even or two
 * odd bytes) and one row back (the same channel in the scanline above).
 * This encoder tries only those, 16 positions at a time where none
 * repeats, extends a match 16 bytes at a time and never revisits the
 * bytes it covers; the tokens then get their own Huffman codes per block
 * (dynamic blocks of at most MR_DEFLATE_BLOCK tokens). On the example's
 * frames this is 4-5x faster than libdeflate level 4 and 2-3 % smaller
 * (README, "EXR encode"). A hash of recent strings, as general encoders
 * have, found matches worth under 0.5 % there for a third of the time, so
 * there is none: content whose repeats lie elsewhere (textures) is what
 * libdeflate's levels are for (MR_ZIP_LEVEL_LIBDEFLATE).
 *
 * The output is an ordinary zlib stream: any inflater (zlib's, OpenEXR's
 * readers) decodes it. It depends only on the input bytes and the row
 * length: the same input gives the same bytes on every machine and thread.
 */
#ifndef MR_DEFLATE_H
#define MR_DEFLATE_H

#include <stddef.h>
#include <stdint.h>

/* The most tokens (literals and matches) one dynamic block codes. */
#define MR_DEFLATE_BLOCK 16384

/* Reusable scratch (the tokens and counts of a block): one per thread. */
typedef struct mr_deflate mr_deflate;

/* NULL when out of memory. */
mr_deflate *mr_deflate_new(void);
void mr_deflate_free(mr_deflate *d);

/* Compresses in[0, n) into out[0, cap) as one zlib stream. row is the
 * distance from a byte to the one above it in the image (0: no rows).
 * Returns the stream's length, or 0 when it does not fit in cap bytes
 * (out then holds garbage). */
size_t mr_deflate_zlib(mr_deflate *d, const uint8_t *in, size_t n, size_t row, uint8_t *out,
                       size_t cap);

#endif
