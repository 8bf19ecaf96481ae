/*
 * camera.h - pinhole cameras and camera paths. The path types (mr_camera_path,
 * mr_camera_key, mr_interp), the camera (mr_camera), its rays and their caps
 * are public: microray.h.
 *
 * A camera looks down its local -Z with +Y up (glTF's convention); its
 * orientation is a unit quaternion mapping camera space to world space.
 * A path is a list of keyframes sorted by time; between keys, position is
 * interpolated linearly or with uniform Catmull-Rom (end keys duplicated as
 * their own neighbours), orientation by slerp, field of view linearly.
 * Before the first key and after the last the path holds still.
 * A key gives its orientation either as a rotation or as a target point
 * (looked at with the path's up vector); targets are turned into rotations
 * at the key, so both kinds interpolate the same way.
 */
#ifndef MR_CAMERA_H
#define MR_CAMERA_H

#include <xmmintrin.h>

#include "math/mr_math.h"
#include "microray.h"

/* mr_camera, mr_camera_path_eval and the ray setup (mr_camera_rays,
 * mr_camera_rays_setup, mr_camera_rays_dir) are public: microray.h. */

/* mr_camera_rays_dir for eight film points (px[i], py[i]) at once, into
 * dx, dy, dz: the same operations in the same order lane by lane (SSE's
 * add, multiply, square root and divide round as the scalar ones do), so
 * each lane is bit for bit the scalar's (tests/unit/test_camera.c). The
 * renderer's primary packets. */
static inline void mr_camera_rays_dir8(const mr_camera_rays *r, const float px[8],
                                       const float py[8], float dx[8], float dy[8], float dz[8])
{
    const float c[3] = {r->corner.x, r->corner.y, r->corner.z};
    const float sx[3] = {r->step_x.x, r->step_x.y, r->step_x.z};
    const float sy[3] = {r->step_y.x, r->step_y.y, r->step_y.z};
    float *out[3] = {dx, dy, dz};
    for (int h = 0; h < 8; h += 4) {
        __m128 X = _mm_loadu_ps(px + h), Y = _mm_loadu_ps(py + h), d[3];
        for (int k = 0; k < 3; k++)
            d[k] = _mm_add_ps(_mm_add_ps(_mm_set1_ps(c[k]), _mm_mul_ps(X, _mm_set1_ps(sx[k]))),
                              _mm_mul_ps(Y, _mm_set1_ps(sy[k])));
        __m128 len2 = _mm_add_ps(_mm_add_ps(_mm_mul_ps(d[0], d[0]), _mm_mul_ps(d[1], d[1])),
                                 _mm_mul_ps(d[2], d[2]));
        __m128 s = _mm_div_ps(_mm_set1_ps(1.0f), _mm_sqrt_ps(len2));
        for (int k = 0; k < 3; k++)
            _mm_storeu_ps(out[k] + h, _mm_mul_ps(d[k], s));
    }
}

/* Orientation a key asks for (its rotation, or a look-at of its target). */
mr_quat mr_camera_key_rotation(const mr_camera_key *key, mr_vec3 up);

/* The same for one ray, without a setup (tests, one-off rays). */
mr_vec3 mr_camera_ray_dir(const mr_camera *cam, int width, int height, double px, double py);

/* Level of detail: the most pixels a segment of unit length anywhere in the
 * world-space box [lo, hi] can span on a width x height film of cam, where
 * it is in view. A point at depth Z moved by d lands (d_xy - (x/Z) d_z) /
 * (Z * pixel) away, at most |d| sqrt(1 + (x/Z)^2 + (y/Z)^2) / (Z * pixel);
 * in view, x/Z and y/Z are within the frustum's half-widths, and Z is at
 * least the box's nearest depth (a corner's). INFINITY when the box
 * reaches the camera's plane. */
double mr_camera_px_per_unit(const mr_camera *cam, int width, int height, mr_vec3 lo, mr_vec3 hi);

/* The same for many boxes of one frame (a kind placing each of its base
 * triangles): what does not depend on the box, once. */
typedef struct mr_px_scale {
    mr_vec3 position, forward;
    double k;     /* pixels per unit at depth 1 */
    bool none;    /* an empty film: every box INFINITY */
} mr_px_scale;
mr_px_scale mr_camera_px_scale(const mr_camera *cam, int width, int height);
double mr_px_scale_box(const mr_px_scale *s, mr_vec3 lo, mr_vec3 hi);

#endif
