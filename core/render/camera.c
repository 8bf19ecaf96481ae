/*
 * camera.c - camera path evaluation and primary ray directions (camera.h).
 */
#include "render/camera.h"

mr_quat mr_camera_key_rotation(const mr_camera_key *key, mr_vec3 up)
{
    if (key->has_target)
        return mr_quat_look_rotation(mr_v3_sub(key->target, key->position), up);
    return mr_quat_normalize(key->rotation);
}

static mr_camera camera_at_key(const mr_camera_path *path, size_t i)
{
    const mr_camera_key *k = &path->keys[i];
    return (mr_camera){k->position, mr_camera_key_rotation(k, path->up), k->yfov};
}

mr_camera mr_camera_path_eval(const mr_camera_path *path, double t)
{
    size_t n = path->key_count;
    if (n == 0)
        return (mr_camera){mr_v3(0, 0, 0), mr_quat_identity(), (float)(MR_DEFAULT_YFOV_DEG * M_PI / 180)};
    if (n == 1 || t <= path->keys[0].t)
        return camera_at_key(path, 0);
    if (t >= path->keys[n - 1].t)
        return camera_at_key(path, n - 1);

    /* Segment [i, i+1] containing t: the last key with keys[i].t <= t. */
    size_t lo = 0, hi = n - 1;
    while (hi - lo > 1) {
        size_t mid = lo + (hi - lo) / 2;
        if (path->keys[mid].t <= t)
            lo = mid;
        else
            hi = mid;
    }
    const mr_camera_key *k1 = &path->keys[lo], *k2 = &path->keys[lo + 1];
    float u = (float)((t - k1->t) / (k2->t - k1->t));

    mr_camera c;
    if (path->interp == MR_INTERP_CATMULL_ROM) {
        const mr_camera_key *k0 = lo > 0 ? &path->keys[lo - 1] : k1;
        const mr_camera_key *k3 = lo + 2 < n ? &path->keys[lo + 2] : k2;
        c.position = mr_catmull_rom(k0->position, k1->position, k2->position, k3->position, u);
    } else {
        c.position = mr_v3_lerp(k1->position, k2->position, u);
    }
    c.rotation = mr_quat_slerp(mr_camera_key_rotation(k1, path->up),
                               mr_camera_key_rotation(k2, path->up), u);
    c.yfov = k1->yfov + (k2->yfov - k1->yfov) * u;
    return c;
}

mr_vec3 mr_camera_ray_dir(const mr_camera *cam, int width, int height, double px, double py)
{
    mr_camera_rays r = mr_camera_rays_setup(cam, width, height);
    return mr_camera_rays_dir(&r, (float)px, (float)py);
}

mr_camera_rays mr_camera_rays_setup(const mr_camera *cam, int width, int height)
{
    double th = tan(0.5 * (double)cam->yfov);
    double aspect = (double)width / (double)height;
    /* Film point (px, py) maps to camera-space (x, y, -1) with
     * x = (2 px / w - 1) th aspect and y = (1 - 2 py / h) th. */
    mr_vec3 right = mr_quat_rotate(cam->rotation, mr_v3(1, 0, 0));
    mr_vec3 up = mr_quat_rotate(cam->rotation, mr_v3(0, 1, 0));
    mr_vec3 fwd = mr_quat_rotate(cam->rotation, mr_v3(0, 0, -1));
    float sx = (float)(2.0 * th * aspect / width), sy = (float)(2.0 * th / height);
    mr_camera_rays r;
    r.origin = cam->position;
    r.step_x = mr_v3_scale(right, sx);
    r.step_y = mr_v3_scale(up, -sy);
    r.corner = mr_v3_add(fwd, mr_v3_add(mr_v3_scale(right, (float)(-th * aspect)), mr_v3_scale(up, (float)th)));
    return r;
}

mr_px_scale mr_camera_px_scale(const mr_camera *cam, int width, int height)
{
    if (width <= 0 || height <= 0)
        return (mr_px_scale){.none = true};
    double th = tan(0.5 * (double)cam->yfov), tw = th * (double)width / (double)height;
    double pixel = 2.0 * th / (double)height; /* a pixel's size at depth 1 */
    return (mr_px_scale){cam->position, mr_quat_rotate(cam->rotation, mr_v3(0, 0, -1)),
                         sqrt(1.0 + th * th + tw * tw) / pixel, false};
}

double mr_px_scale_box(const mr_px_scale *s, mr_vec3 lo, mr_vec3 hi)
{
    if (s->none)
        return INFINITY;
    /* the nearest corner's depth: the centre's less the half extents
     * along the view axis */
    const double f[3] = {s->forward.x, s->forward.y, s->forward.z};
    const double l[3] = {lo.x, lo.y, lo.z}, h[3] = {hi.x, hi.y, hi.z};
    const double p[3] = {s->position.x, s->position.y, s->position.z};
    double zmin = 0;
    for (int i = 0; i < 3; i++)
        zmin += f[i] * (0.5 * (l[i] + h[i]) - p[i]) - fabs(f[i]) * 0.5 * (h[i] - l[i]);
    return zmin > 0 ? s->k / zmin : INFINITY;
}

double mr_camera_px_per_unit(const mr_camera *cam, int width, int height, mr_vec3 lo, mr_vec3 hi)
{
    mr_px_scale s = mr_camera_px_scale(cam, width, height);
    return mr_px_scale_box(&s, lo, hi);
}
