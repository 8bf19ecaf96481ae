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

/* Unit direction of the ray through film point (px, py) in pixels, (0,0)
 * being the top-left corner of the image and (width, height) the
 * bottom-right one. */
mr_vec3 mr_camera_ray_dir(const mr_camera *cam, int width, int height, double px, double py);

#endif
