/*
 * image.h - images as assets: height textures and tiling exemplars
 * (issue 14). PNG (8 and 16 bit, libpng), JPEG (libjpeg-turbo) and
 * single-channel or RGB OpenEXR (the OpenEXR 3 C API) are decoded into one
 * channel of samples, which is all a height needs:
 *  - one channel (grey, grey + alpha, an EXR "Y" or an EXR's only channel):
 *    that channel;
 *  - colour (RGB, RGBA, palette): Rec. 709 luminance 0.2126 R + 0.7152 G +
 *    0.0722 B, in integers for 8 and 16 bit samples ((2126 R + 7152 G + 722 B
 *    + 5000) / 10000, so they stay exact integers) and in float for EXR;
 *  - alpha is ignored.
 * Integer samples are kept as they are (8 or 16 bits: the height source
 * divides by 255 or 65535), EXR samples as float (HALF and UINT converted).
 * Rows are stored top row first, as in the file; users of the samples
 * (kinds/displaced) say how rows map to texture coordinates.
 *
 * Bad input: sizes are capped before anything is allocated (the public
 * MR_MAX_IMAGE_SIDE and MR_MAX_IMAGE_PIXELS), truncated or corrupt files
 * fail (libjpeg's "premature end" and corrupt-data warnings are errors
 * here, not grey pixels), non-finite EXR samples and unusable channel sets
 * are refused, and every message names the file.
 */
#ifndef MR_IMAGE_H
#define MR_IMAGE_H

#include <stdbool.h>
#include <stdint.h>

#include "microray.h"

typedef enum mr_sample_type {
    MR_SAMPLE_U8 = 1,  /* bytes per sample */
    MR_SAMPLE_U16 = 2,
    MR_SAMPLE_F32 = 4
} mr_sample_type;

typedef enum mr_image_format {
    MR_IMAGE_NONE = 0,
    MR_IMAGE_PNG,
    MR_IMAGE_JPEG,
    MR_IMAGE_EXR
} mr_image_format;

typedef struct mr_image {
    uint32_t width, height;
    uint32_t file_channels;   /* channels the file had (1..4; EXR: its channel count) */
    mr_image_format format;
    mr_sample_type type;
    void *samples;            /* width * height, row-major, top row first */
} mr_image;

/* The format whose signature starts data (at least 8 bytes are looked at
 * when there are so many), or MR_IMAGE_NONE. */
mr_image_format mr_image_sniff(const uint8_t *data, size_t size);
const char *mr_image_format_name(mr_image_format f);

/* Decodes data (the whole file) into a new image; `what` (the file's name)
 * starts every message. MR_ERR_FORMAT for damaged, truncated or unsupported
 * files, MR_ERR_LIMIT beyond the caps, MR_ERR_NOMEM. */
int mr_image_decode(const uint8_t *data, size_t size, const char *what, mr_image **out,
                    mr_error *err);

/* Sample (x, y) as a number: integers as they are (0..255 or 0..65535),
 * floats as stored. Row y = 0 is the top row. */
static inline double mr_image_sample(const mr_image *img, uint32_t x, uint32_t y)
{
    size_t i = (size_t)y * img->width + x;
    switch (img->type) {
    case MR_SAMPLE_U8: return ((const uint8_t *)img->samples)[i];
    case MR_SAMPLE_U16: return ((const uint16_t *)img->samples)[i];
    default: return ((const float *)img->samples)[i];
    }
}

/* The value a sample of this type means 1.0 (255, 65535 or 1). */
double mr_image_unit(const mr_image *img);

/* A new image of the given size and type with zeroed samples (tests,
 * generated fixtures). */
int mr_image_new(uint32_t width, uint32_t height, mr_sample_type type, mr_image **out,
                 mr_error *err);
size_t mr_image_bytes(const mr_image *img);
void mr_image_free(mr_image *img);

/* An asset holding img (taken over, also on failure) under `path`. */
int mr_asset_from_image(const char *path, mr_image *img, mr_asset **out, mr_error *err);

#endif
