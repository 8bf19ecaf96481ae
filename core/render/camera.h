/*
 * camera.h - pinhole cameras and camera paths. The path types (mr_camera_path,
 * mr_camera_key, mr_interp) and their caps are public: microray.h.
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

#include "math/mr_math.h"
#include "microray.h"

/* The camera at one instant. */
typedef struct mr_camera {
    mr_vec3 position;
    mr_quat rotation;
    float yfov;
} mr_camera;

/* Camera of the path at time t. */
mr_camera mr_camera_path_eval(const mr_camera_path *path, double t);

/* Orientation a key asks for (its rotation, or a look-at of its target). */
mr_quat mr_camera_key_rotation(const mr_camera_key *key, mr_vec3 up);

/* A camera set up for one film size: ray directions are a corner plus
 * multiples of per-pixel steps, so generating a ray costs a few multiply-adds
 * and one normalisation (no trigonometry per ray). */
typedef struct mr_camera_rays {
    mr_vec3 origin;
    mr_vec3 corner;  /* direction through film point (0, 0), unnormalised */
    mr_vec3 step_x;  /* change per pixel to the right */
    mr_vec3 step_y;  /* change per pixel downwards */
} mr_camera_rays;

mr_camera_rays mr_camera_rays_setup(const mr_camera *cam, int width, int height);

/* Unit direction of the ray through film point (px, py) in pixels, (0,0)
 * being the top-left corner of the image and (width, height) the
 * bottom-right one. */
static inline mr_vec3 mr_camera_rays_dir(const mr_camera_rays *r, float px, float py)
{
    mr_vec3 d = mr_v3(r->corner.x + px * r->step_x.x + py * r->step_y.x,
                      r->corner.y + px * r->step_x.y + py * r->step_y.y,
                      r->corner.z + px * r->step_x.z + py * r->step_y.z);
    return mr_v3_scale(d, 1.0f / mr_v3_len(d));
}

/* The same for one ray, without a setup (tests, one-off rays). */
mr_vec3 mr_camera_ray_dir(const mr_camera *cam, int width, int height, double px, double py);

#endif
