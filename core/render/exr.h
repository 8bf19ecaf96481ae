/*
 * exr.h - what only core and the tests use of the OpenEXR writer and
 * reader: the HALF conversions, the ZIP codec's predictor and the names
 * Cryptomatte ids are made from. The EXR layout of a frame, its options
 * and the write/read calls are public: microray.h.
 */
#ifndef MR_EXR_H
#define MR_EXR_H

#include "microray.h"

/* IEEE 754 binary16 conversions used for the HALF channels.
 * mr_float_to_half rounds to nearest, ties to even; finite values beyond the
 * half range clamp to +-65504, +-Inf clamps to +-65504 and NaN becomes 0, so
 * the result is always finite. mr_half_to_float is exact (every half is a
 * float); it returns Inf/NaN only for half Inf/NaN bit patterns. */
uint16_t mr_float_to_half(float f);
float mr_half_to_float(uint16_t h);

/* The ZIP codec's byte reordering and predictor over n packed chunk bytes
 * (what OpenEXR's ZIP and ZIPS encoders hand to deflate): out[0 .. (n+1)/2)
 * are the even-indexed bytes of in, the rest the odd-indexed ones, and every
 * byte but the first then holds its difference to the one before it plus
 * 128, mod 256. in and out must not overlap. */
void mr_exr_zip_predict(const uint8_t *in, size_t n, uint8_t *out);

/* The name Cryptomatte layer `layer` (MR_CRYPTO_OBJECT, MR_CRYPTO_ASSET)
 * gives item i (an object, or an asset) of job: the object's or the
 * asset's name; "object<i>" for an object a hand-built job left unnamed
 * (the parser names every object). buf backs the made-up name. */
const char *mr_crypto_name(const mr_job *job, int layer, size_t i, char buf[32]);

#endif
