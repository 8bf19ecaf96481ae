/*
 * compare.h - error metrics between a frame and a reference frame of the same
 * camera (../shared/ARCHITECTURE.md, "Error metrics"). Every geometry kind
 * reports its accuracy with these figures.
 *
 * A pixel is "hit" when its object_id is non-zero.
 *  - coverage_pct: pixels hit in exactly one frame, as % of pixels hit in either
 *    (0 when neither frame hits anything);
 *  - depth_rmse, depth_max: RMSE and max of |Za - Zb| over pixels hit in both,
 *    divided by scene_diagonal;
 *  - normal_mean_deg, normal_max_deg: angle between the normals over pixels
 *    hit in both (acos clamped to [-1, 1]);
 *  - holes: pixels the reference b hits, together with all 8 neighbours (so
 *    not on its silhouette), that a misses: gaps inside the reference's
 *    silhouette, as opposed to a silhouette that is a little off;
 *  - psnr_rgb: 10 log10(1 / MSE) over R, G, B of all pixels, colours clamped to
 *    [0, 1] first; reported as 999 when the images are identical (MSE = 0),
 *    which keeps JSON free of infinities.
 */
#ifndef MR_COMPARE_H
#define MR_COMPARE_H

#include "render/film.h"

#define MR_PSNR_IDENTICAL 999.0

typedef struct mr_compare_result {
    size_t pixels;            /* width * height */
    size_t hit_either, hit_both, hit_one;
    size_t holes;
    double coverage_pct;
    double depth_rmse, depth_max;  /* relative to scene_diagonal */
    double normal_mean_deg, normal_max_deg;
    double psnr_rgb;
} mr_compare_result;

/* Fails with MR_ERR_INVALID when sizes differ or scene_diagonal is not a
 * positive finite number. */
int mr_film_compare(const mr_film *a, const mr_film *b, double scene_diagonal,
                    mr_compare_result *out, mr_error *err);

#endif
