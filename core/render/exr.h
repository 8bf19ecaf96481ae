/*
 * exr.h - OpenEXR output and input through the OpenEXR 3 C API (openexr.h).
 *
 * A frame is one scanline part with these channels (EXR stores them sorted by
 * name; we always match channels by name, never by position):
 *   R G B A            HALF   linear, premultiplied colour
 *   Z                  FLOAT  distance along the ray, 0 = miss
 *   N.X N.Y N.Z        FLOAT  world-space normal
 *   id.object          UINT   1-based object index, 0 = miss
 *   id.primitive       UINT   primitive index within the object
 * and header attributes (string unless noted):
 *   microray.version, microray.job, microray.frame (int), microray.time
 *   (double, seconds on the job's timeline), microray.renderSeconds (double),
 *   microray.sceneDiagonal (float: bounding-box diagonal of the scene, the
 *   unit depth errors are expressed in).
 */
#ifndef MR_EXR_H
#define MR_EXR_H

#include "render/film.h"

typedef enum mr_compression {
    MR_COMPRESSION_NONE = 0,
    MR_COMPRESSION_ZIP,   /* 16 scanlines per chunk */
    MR_COMPRESSION_ZIPS,  /* 1 scanline per chunk */
    MR_COMPRESSION_PIZ
} mr_compression;

#define MR_ZIP_LEVEL_DEFAULT 4

typedef struct mr_exr_options {
    mr_compression compression;
    int zip_level; /* 1..9, used by ZIP/ZIPS; 0 means MR_ZIP_LEVEL_DEFAULT */
    /* Threads that encode (pack + compress) chunks; 0 = all online cores,
     * values above 256 act as 256. The written bytes are the same for every
     * value, so this is purely a speed setting. */
    unsigned threads;
} mr_exr_options;

typedef struct mr_exr_meta {
    char job[128];          /* job name or id, may be empty */
    int frame;              /* frame index within the job */
    double time;            /* frame time on the job's timeline, seconds */
    double render_seconds;  /* wall time spent rendering this frame */
    float scene_diagonal;   /* > 0 */
} mr_exr_meta;

/* Name of a compression as used in jobs ("none", "zip", "zips", "piz"). */
const char *mr_compression_name(mr_compression c);
/* Parses a name as above; returns false for anything else. */
bool mr_compression_parse(const char *name, mr_compression *out);

/* IEEE 754 binary16 conversions used for the HALF channels.
 * mr_float_to_half rounds to nearest, ties to even; finite values beyond the
 * half range clamp to +-65504, +-Inf clamps to +-65504 and NaN becomes 0, so
 * the result is always finite. mr_half_to_float is exact (every half is a
 * float); it returns Inf/NaN only for half Inf/NaN bit patterns. */
uint16_t mr_float_to_half(float f);
float mr_half_to_float(uint16_t h);

/* opt may be NULL (same as a zeroed struct: no compression, default level,
 * all cores);
 * meta may be NULL (only microray.version is written). NaN/Inf pixels are
 * written as finite values (colour as above; Z and N: NaN -> 0,
 * +-Inf -> +-FLT_MAX). */

/* Writes film to path atomically (util/file_io.h mr_fs_atomic: a unique
 * temporary next to path, fsynced and renamed over it on success, then the
 * directory synced), so nobody sees a partial frame, a failed write leaves
 * an existing file at path untouched and a crash loses no finished frame. */
int mr_exr_write_file(const char *path, const mr_film *film, const mr_exr_options *opt,
                      const mr_exr_meta *meta, mr_error *err);
/* Writes film into a malloc'ed buffer (*data, *size); caller frees *data. */
int mr_exr_write_memory(uint8_t **data, size_t *size, const mr_film *film,
                        const mr_exr_options *opt, const mr_exr_meta *meta, mr_error *err);
/* Reads a microray EXR (any compression the library decodes) into a new film.
 * Missing channels are left zero; meta may be NULL. Fails with MR_ERR_FORMAT
 * for files that are not scanline EXR images. */
int mr_exr_read_file(const char *path, mr_film **out, mr_exr_meta *meta, mr_error *err);

#endif
