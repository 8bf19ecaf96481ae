/*
 * camera.h - pinhole cameras and camera paths.
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

#define MR_MAX_CAMERA_KEYS 10000
/* Vertical field of view when a job or a camera node does not give one. */
#define MR_DEFAULT_YFOV_DEG 45.0

typedef enum mr_interp { MR_INTERP_LINEAR = 0, MR_INTERP_CATMULL_ROM } mr_interp;

typedef struct mr_camera_key {
    double t;          /* seconds, strictly increasing along the path */
    mr_vec3 position;
    bool has_target;   /* orientation from target (else from rotation) */
    mr_vec3 target;
    mr_quat rotation;
    float yfov;        /* vertical field of view, radians, in (0, pi) */
} mr_camera_key;

/* The camera at one instant. */
typedef struct mr_camera {
    mr_vec3 position;
    mr_quat rotation;
    float yfov;
} mr_camera;

typedef struct mr_camera_path {
    mr_interp interp;
    mr_vec3 up;        /* for target keys; default +Y */
    size_t key_count;  /* >= 1 */
    mr_camera_key *keys;
} mr_camera_path;

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
