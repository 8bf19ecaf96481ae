/*
 * scene_fixture.h - a one-object, one-frame job built in memory, and a helper
 * that renders it, for tests that check the renderer against analytic
 * answers. Header-only: each test program includes it once.
 */
#ifndef MR_TEST_SCENE_FIXTURE_H
#define MR_TEST_SCENE_FIXTURE_H

#include <stdlib.h>
#include <string.h>

#include "asset/asset.h"
#include "kinds/mesh/mesh_kind.h"
#include "render/renderer.h"

typedef struct scene_fixture {
    mr_job job;
    mr_object_desc object;
    mr_asset_desc asset_desc;
    mr_camera_key key;
    mr_light_desc light;
    double time;
    mr_asset *asset;
} scene_fixture;

/* asset is owned by the fixture afterwards (fixture_free releases it). The
 * camera sits at eye looking at target with vertical fov yfov_deg; one light
 * shines along -Z; shadows on; no ambient beyond 0.1. */
static void fixture_init(scene_fixture *s, mr_asset *asset, mr_vec3 eye, mr_vec3 target, double yfov_deg,
                         int width, int height, int spp)
{
    memset(s, 0, sizeof *s);
    s->asset = asset;
    s->asset_desc = (mr_asset_desc){.name = "fixture", .path = "(memory)"};
    s->object = (mr_object_desc){.name = "fixture", .asset = 0, .kind = &mr_kind_mesh,
                                 .transform = mr_mat4_identity(), .color = mr_v3(0.8f, 0.8f, 0.8f)};
    s->key = (mr_camera_key){.t = 0, .position = eye, .has_target = true, .target = target,
                             .yfov = (float)(yfov_deg * M_PI / 180)};
    s->light = (mr_light_desc){mr_v3(0, 0, -1), mr_v3(1, 1, 1)};
    mr_job *j = &s->job;
    j->name = "fixture";
    j->asset_count = 1; j->assets = &s->asset_desc;
    j->object_count = 1; j->objects = &s->object;
    j->light_count = 1; j->lights = &s->light;
    j->ambient = mr_v3(0.1f, 0.1f, 0.1f);
    j->background = mr_v3(0, 0, 0);
    j->background_alpha = 0;
    j->camera = (mr_camera_desc){.source = MR_CAMERA_SOURCE_PATH,
                                 .path = {.interp = MR_INTERP_LINEAR, .up = mr_v3(0, 1, 0), .key_count = 1, .keys = &s->key}};
    j->fps = 24;
    j->frame_count = 1;
    j->frame_times = &s->time;
    j->output = (mr_output_desc){.width = width, .height = height, .spp = spp, .shadows = true, .seed = 7,
                                 .exr = {.compression = MR_COMPRESSION_ZIP, .zip_level = 4}};
}

static void fixture_free(scene_fixture *s) { mr_asset_free(s->asset); }

/* Renders frame 0 with the given thread count (0 = all cores). */
static mr_film *fixture_render(scene_fixture *s, unsigned threads, mr_frame_stats *st)
{
    mr_error err = {0};
    mr_device *dev = NULL;
    mr_renderer *r = NULL;
    mr_film *film = NULL;
    if (mr_device_new(threads, &dev, &err) < 0)
        fail_msg("device: %s", err.msg);
    if (mr_renderer_new(dev, &s->job, &s->asset, NULL, &r, &err) < 0)
        fail_msg("renderer: %s", err.msg);
    if (mr_film_new(s->job.output.width, s->job.output.height, &film, &err) < 0)
        fail_msg("film: %s", err.msg);
    if (mr_renderer_render(r, 0, film, st, &err) < 0)
        fail_msg("render: %s", err.msg);
    mr_renderer_free(r);
    mr_device_free(dev);
    return film;
}

/* How many values of the film's float planes (colour, alpha, depth,
 * normal) are NaN or Inf; prints the first. */
static inline size_t film_nonfinite(const mr_film *f)
{
    size_t n = (size_t)f->width * f->height, bad = 0;
    const float *planes[] = {f->r, f->g, f->b, f->a, f->z, f->nx, f->ny, f->nz};
    for (size_t p = 0; p < 8; p++)
        for (size_t i = 0; i < n; i++)
            if (!isfinite(planes[p][i]) && bad++ == 0)
                print_error("plane %zu pixel %zu is not finite\n", p, i);
    return bad;
}

/* Fails the test if any float plane of the film holds NaN or Inf. */
static inline void assert_film_finite(const mr_film *f)
{
    size_t bad = film_nonfinite(f);
    if (bad)
        fail_msg("%zu values of the film are not finite", bad);
}

#endif
