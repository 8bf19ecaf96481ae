/*
 * test_render.c - the renderer against analytic answers: a unit sphere at a
 * known distance, finely tessellated with a pole facing the camera.
 *
 * Tolerances:
 *  - Z at the centre pixel: the centre ray passes exactly through the pole
 *    vertex, so the hit distance is d - 1 up to float rounding of the
 *    intersection (a few ulps of d): 1e-5 relative, as the issue asks.
 *  - Hit/miss boundary: a UV sphere of R rings and S segments lies inside the
 *    true sphere by at most 1 - cos(pi/S) + 1 - cos(pi/(2R)) in radius (edge
 *    midpoints); with S = 256, R = 128 that is < 1.6e-4, which moves the
 *    silhouette by at most that / (d cos(alpha)) radians. Pixels whose centre
 *    ray is further than 2e-4 rad from the analytic silhouette angle
 *    alpha = asin(1/d) must land on the right side.
 *  - Depth elsewhere: within the same radial deficit (1.6e-4 d-relative
 *    bound at grazing angles is looser; we use 2e-3 relative).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>
#include <cmocka.h>

#include "../support/film_fixture.h"
#include "../support/scene_fixture.h"

#define RINGS 128
#define SEGMENTS 256
#define W 101
#define H 101
#define DIST 4.0
#define YFOV_DEG 40.0

static mr_asset *make_sphere(void)
{
    uint32_t nv = (RINGS - 1) * SEGMENTS + 2, nt = 2 * SEGMENTS * (RINGS - 1);
    float *p = malloc(nv * 3 * sizeof(float));
    uint32_t *idx = malloc(nt * 3 * sizeof(uint32_t));
    assert_non_null(p);
    assert_non_null(idx);
    /* Poles on the Z axis: vertex 0 = (0,0,1) faces a camera on +Z. */
    p[0] = 0; p[1] = 0; p[2] = 1;
    for (int r = 1; r < RINGS; r++)
        for (int s = 0; s < SEGMENTS; s++) {
            double th = M_PI * r / RINGS, ph = 2 * M_PI * s / SEGMENTS;
            float *v = p + 3 * (1 + (r - 1) * SEGMENTS + s);
            v[0] = (float)(sin(th) * cos(ph));
            v[1] = (float)(sin(th) * sin(ph));
            v[2] = (float)cos(th);
        }
    uint32_t south = nv - 1;
    p[3 * south] = 0; p[3 * south + 1] = 0; p[3 * south + 2] = -1;
    uint32_t *t = idx;
    for (int s = 0; s < SEGMENTS; s++) {
        uint32_t a = 1 + s, b = 1 + (s + 1) % SEGMENTS;
        *t++ = 0; *t++ = a; *t++ = b;
    }
    for (int r = 1; r < RINGS - 1; r++)
        for (int s = 0; s < SEGMENTS; s++) {
            uint32_t a = 1 + (r - 1) * SEGMENTS + s, b = 1 + (r - 1) * SEGMENTS + (s + 1) % SEGMENTS;
            uint32_t c = a + SEGMENTS, d = b + SEGMENTS;
            *t++ = a; *t++ = c; *t++ = d;
            *t++ = a; *t++ = d; *t++ = b;
        }
    for (int s = 0; s < SEGMENTS; s++) {
        uint32_t a = 1 + (RINGS - 2) * SEGMENTS + s, b = 1 + (RINGS - 2) * SEGMENTS + (s + 1) % SEGMENTS;
        *t++ = a; *t++ = south; *t++ = b;
    }
    assert_int_equal((size_t)(t - idx), (size_t)nt * 3);
    mr_asset *a = NULL;
    mr_error err = {0};
    int rc = mr_asset_from_mesh("sphere", p, NULL, nv, idx, nt, &a, &err);
    if (rc != MR_OK)
        fail_msg("mr_asset_from_mesh: %s", err.msg);
    free(p);
    free(idx);
    return a;
}

static void test_sphere_depth_and_silhouette(void **state)
{
    (void)state;
    scene_fixture s;
    fixture_init(&s, make_sphere(), mr_v3(0, 0, DIST), mr_v3(0, 0, 0), YFOV_DEG, W, H, 1);
    mr_frame_stats st;
    mr_film *f = fixture_render(&s, 0, &st);

    size_t c = (size_t)(H / 2) * W + W / 2;
    assert_int_equal(f->object_id[c], 1);
    double z = f->z[c];
    if (fabs(z - (DIST - 1)) > 1e-5 * (DIST - 1))
        fail_msg("centre Z %.9g, analytic %.9g", z, DIST - 1);
    /* The normal at the pole faces the camera. */
    assert_true(f->nz[c] > 0.9999f);

    double alpha = asin(1.0 / DIST), margin = 2e-4;
    double th = tan(0.5 * YFOV_DEG * M_PI / 180);
    size_t inside = 0, outside = 0;
    for (int y = 0; y < H; y++)
        for (int x = 0; x < W; x++) {
            size_t i = (size_t)y * W + x;
            double nx = (2.0 * (x + 0.5) / W - 1) * th, ny = (1 - 2.0 * (y + 0.5) / H) * th;
            double ang = atan(sqrt(nx * nx + ny * ny));
            if (ang < alpha - margin) {
                inside++;
                if (f->object_id[i] != 1)
                    fail_msg("pixel (%d,%d) at %.6f rad should hit (silhouette %.6f)", x, y, ang, alpha);
                /* Analytic distance to the unit sphere along this ray, and
                 * Z, the hit's camera-space depth: that times the cosine of
                 * the ray's angle to the view axis (up to 3 % less at the
                 * silhouette, so a distance along the ray fails here). */
                double b = DIST * cos(ang), zz = (b - sqrt(b * b - (DIST * DIST - 1))) * cos(ang);
                if (fabs(f->z[i] - zz) > 2e-3 * zz)
                    fail_msg("pixel (%d,%d) Z %.6f, analytic %.6f", x, y, f->z[i], zz);
                assert_true(f->a[i] == 1.0f);
            } else if (ang > alpha + margin) {
                outside++;
                if (f->object_id[i] != 0 || f->z[i] != MR_DEPTH_MISS)
                    fail_msg("pixel (%d,%d) at %.6f rad should miss (silhouette %.6f)", x, y, ang, alpha);
                assert_true(f->a[i] == 0.0f);
            }
        }
    /* Both regions are substantial, so the assertions above bite. */
    assert_true(inside > 1000);
    assert_true(outside > 1000);
    assert_int_equal(st.triangles, 2 * SEGMENTS * (RINGS - 1));
    assert_true(st.rays >= (uint64_t)W * H);
    assert_film_finite(f);
    mr_film_free(f);
    fixture_free(&s);
}

/* A small sphere off the film's centre: the film outside the scene's
 * projected bounding box is not traced (integrator.c scene_rect), and every
 * pixel still lands on the analytic side of the silhouette (the same
 * margin), seen along the renderer's own pixel rays. */
static void test_sphere_off_centre(void **state)
{
    (void)state;
    const double dist = 12.0;
    scene_fixture s;
    fixture_init(&s, make_sphere(), mr_v3(0, 0, (float)dist), mr_v3(2.6f, 2.0f, 0), YFOV_DEG, W, H, 1);
    mr_frame_stats st;
    mr_film *f = fixture_render(&s, 0, &st);
    mr_camera cam = {.position = s.key.position, .rotation = mr_camera_key_rotation(&s.key, mr_v3(0, 1, 0)),
                     .yfov = s.key.yfov};
    double alpha = asin(1.0 / dist), margin = 2e-4;
    size_t inside = 0, outside = 0;
    for (int y = 0; y < H; y++)
        for (int x = 0; x < W; x++) {
            mr_vec3 d = mr_camera_ray_dir(&cam, W, H, x + 0.5, y + 0.5);
            /* the angle to the sphere's centre, straight down -z from the eye */
            double c = -(double)d.z / sqrt((double)d.x * d.x + (double)d.y * d.y + (double)d.z * d.z);
            double ang = acos(fmin(1.0, c));
            size_t i = (size_t)y * W + x;
            if (ang < alpha - margin) {
                inside++;
                if (f->object_id[i] != 1)
                    fail_msg("pixel (%d,%d) at %.6f rad should hit (silhouette %.6f)", x, y, ang, alpha);
            } else if (ang > alpha + margin) {
                outside++;
                if (f->object_id[i] != 0 || f->z[i] != MR_DEPTH_MISS || f->a[i] != 0.0f)
                    fail_msg("pixel (%d,%d) at %.6f rad should miss (silhouette %.6f)", x, y, ang, alpha);
            }
        }
    assert_true(inside > 200 && outside > 5000);
    /* the sphere's box covers a few hundred pixels: far fewer primary rays
     * than pixels, plus one shadow ray per hit */
    assert_true(st.rays < (uint64_t)W * H / 4);
    mr_film_free(f);
    fixture_free(&s);
}

/* The same frame with every pixel traced (mr_renderer_options
 * trace_every_pixel): the same bits in every plane, Cryptomatte included,
 * over a coloured, half-transparent background and 4 jittered samples, so
 * the pixels answered untraced (whole tiles and packets outside the scene's
 * projected box) hold exactly what a traced miss would. */
static void test_untraced_misses_are_misses(void **state)
{
    (void)state;
    scene_fixture s;
    fixture_init(&s, make_sphere(), mr_v3(0, 0, 12), mr_v3(2.6f, 2.0f, 0), YFOV_DEG, 150, 90, 4);
    s.job.background = mr_v3(0.2f, 0.3f, 0.4f);
    s.job.background_alpha = 0.5f;
    s.job.output.aovs = MR_AOV_ALL;
    mr_film *f[2];
    uint64_t rays[2];
    for (int every = 0; every < 2; every++) {
        mr_error err = {0};
        mr_device *dev = NULL;
        mr_renderer *r = NULL;
        mr_renderer_options opt = {.trace_every_pixel = every};
        mr_frame_stats st;
        if (mr_device_new(2, &dev, &err) < 0 || mr_renderer_new(dev, &s.job, &s.asset, &opt, &r, &err) < 0 ||
            mr_job_film_new(&s.job, &f[every], &err) < 0 || mr_renderer_render(r, 0, f[every], &st, &err) < 0)
            fail_msg("%s", err.msg);
        assert_true(f[every]->crypto_ranks > 0);
        rays[every] = st.rays;
        mr_renderer_free(r);
        mr_device_free(dev);
    }
    fx_assert_same_pixels(f[0], f[1], "untraced misses against traced ones");
    assert_true(rays[0] * 4 < rays[1]); /* most of the film was not traced */
    mr_film_free(f[0]);
    mr_film_free(f[1]);
    fixture_free(&s);
}

/* Every plane of f (MR_AOV_ALL, Cryptomatte's too) set to bytes b. */
static void fill_planes(mr_film *f, int b)
{
    const size_t n = (size_t)f->width * f->height * 4u;
    float *planes[] = {f->r, f->g, f->b, f->a, f->z, f->nx, f->ny, f->nz,
                       f->px, f->py, f->pz, f->tx, f->ty, f->tz};
    for (size_t k = 0; k < sizeof planes / sizeof *planes; k++)
        memset(planes[k], b, n);
    memset(f->object_id, b, n);
    memset(f->prim_id, b, n);
    for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
        for (int k = 0; k < 2 * f->crypto_ranks; k++)
            memset(f->crypto[l][k], b, n);
}

/* A film rendered into frame after frame keeps a record of the blocks that
 * hold a miss's values (mr_film's misses) and a frame writes only where
 * that changes: over a camera that sweeps the sphere across the film,
 * under a coloured, half-transparent background, 2 jittered samples and
 * every pass, each frame of the one film holds exactly the bits of the same
 * frame rendered into a new film. A new background (another renderer, the
 * same film) is written everywhere; a pixel written behind the renderer's
 * back stays (the record is the film's), and mr_film_clear forgets the
 * record, after which the frame is whole again. A film of other contents
 * (mr_film.cleared false) gets every plane; a film said to be cleared gets
 * only the planes where a miss leaves something else. */
static void test_film_remembers_misses(void **state)
{
    (void)state;
    scene_fixture s;
    fixture_init(&s, make_sphere(), mr_v3(0, 0, 12), mr_v3(0, 0, 0), YFOV_DEG, 150, 90, 2);
    mr_camera_key keys[2] = {s.key, s.key};
    keys[0].position = mr_v3(-3, 1, 12), keys[0].target = mr_v3(-3, 1, 0);
    keys[1].t = 1, keys[1].position = mr_v3(3, -1, 12), keys[1].target = mr_v3(3, -1, 0);
    double times[6] = {0, 0.2, 0.4, 0.6, 0.8, 1};
    s.job.camera.path.keys = keys, s.job.camera.path.key_count = 2;
    s.job.frame_times = times, s.job.frame_count = 6;
    s.job.background = mr_v3(0.2f, 0.3f, 0.4f);
    s.job.background_alpha = 0.5f;
    s.job.output.aovs = MR_AOV_ALL;
    mr_job other = s.job; /* the same scene over another background */
    other.background = mr_v3(0.5f, 0.1f, 0.0f);
    mr_error err = {0};
    mr_device *dev = NULL;
    mr_renderer *r = NULL, *r2 = NULL;
    mr_film *kept = NULL;
    mr_frame_stats st;
    if (mr_device_new(2, &dev, &err) < 0 || mr_renderer_new(dev, &s.job, &s.asset, NULL, &r, &err) < 0 ||
        mr_renderer_new(dev, &other, &s.asset, NULL, &r2, &err) < 0 ||
        mr_job_film_new(&s.job, &kept, &err) < 0)
        fail_msg("%s", err.msg);
    /* frames 0..5, then 5..0 back: blocks the sphere leaves and enters */
    for (int k = 0; k < 12; k++) {
        const size_t frame = (size_t)(k < 6 ? k : 11 - k);
        mr_film *fresh = NULL;
        if (mr_job_film_new(&s.job, &fresh, &err) < 0 ||
            mr_renderer_render(r, frame, kept, &st, &err) < 0 ||
            mr_renderer_render(r, frame, fresh, &st, &err) < 0)
            fail_msg("frame %zu: %s", frame, err.msg);
        assert_non_null(kept->misses);
        char what[64];
        snprintf(what, sizeof what, "frame %zu (pass %d) into the kept film", frame, k);
        fx_assert_same_pixels(kept, fresh, what);
        mr_film_free(fresh);
    }
    /* a film of other contents that the renderer knows nothing of: every
     * plane written; one said to be cleared keeps what a miss would write
     * there already (a background pixel's normal, 0), and only that */
    mr_film *junk = NULL, *fresh3 = NULL;
    if (mr_job_film_new(&s.job, &junk, &err) < 0 || mr_job_film_new(&s.job, &fresh3, &err) < 0)
        fail_msg("%s", err.msg);
    assert_true(junk->cleared && fresh3->cleared);
    fill_planes(junk, 0x5a);
    junk->cleared = false;
    if (mr_renderer_render(r, 3, junk, &st, &err) < 0 || mr_renderer_render(r, 3, fresh3, &st, &err) < 0)
        fail_msg("%s", err.msg);
    assert_false(junk->cleared || fresh3->cleared);
    fx_assert_same_pixels(junk, fresh3, "frame 3 into a film of other contents");
    mr_film_clear(junk);
    const size_t far = (size_t)junk->width * junk->height - 1; /* a background pixel */
    assert_int_equal(fresh3->object_id[far], 0);
    assert_true(fresh3->nx[far] == 0.0f && fresh3->r[far] != 0.0f);
    junk->nx[far] = 5.0f, junk->r[far] = 5.0f; /* behind the renderer's back, the flag kept */
    if (mr_renderer_render(r, 3, junk, &st, &err) < 0)
        fail_msg("%s", err.msg);
    assert_true(junk->nx[far] == 5.0f);     /* a miss's 0: held by a cleared film */
    assert_true(junk->r[far] == fresh3->r[far]); /* the background: written */
    mr_film_free(junk);
    mr_film_free(fresh3);
    /* a background pixel written behind the renderer's back */
    const size_t corner = 0;
    assert_int_equal(kept->object_id[corner], 0);
    const float red = kept->r[corner];
    kept->r[corner] = 7.0f;
    if (mr_renderer_render(r, 0, kept, &st, &err) < 0)
        fail_msg("%s", err.msg);
    assert_true(kept->r[corner] == 7.0f); /* not written again: the record says it holds a miss */
    mr_film_clear(kept);
    assert_null(kept->misses);
    if (mr_renderer_render(r, 0, kept, &st, &err) < 0)
        fail_msg("%s", err.msg);
    assert_true(kept->r[corner] == red);
    /* another background into the same film: every block written */
    mr_film *fresh = NULL;
    if (mr_job_film_new(&other, &fresh, &err) < 0 || mr_renderer_render(r2, 3, kept, &st, &err) < 0 ||
        mr_renderer_render(r2, 3, fresh, &st, &err) < 0)
        fail_msg("%s", err.msg);
    fx_assert_same_pixels(kept, fresh, "another background into the kept film");
    mr_film_free(fresh);
    mr_film_free(kept);
    mr_renderer_free(r);
    mr_renderer_free(r2);
    mr_device_free(dev);
    fixture_free(&s);
}

static void test_same_bytes_any_thread_count(void **state)
{
    (void)state;
    scene_fixture s;
    /* jittered samples must not depend on the worker */
    fixture_init(&s, make_sphere(), mr_v3(0, 0, DIST), mr_v3(0, 0, 0), YFOV_DEG, W, H, 4);
    mr_frame_stats st;
    mr_film *a = fixture_render(&s, 1, &st), *b = fixture_render(&s, 2, &st);
    size_t n = (size_t)W * H;
    float *pa[] = {a->r, a->g, a->b, a->a, a->z, a->nx, a->ny, a->nz};
    float *pb[] = {b->r, b->g, b->b, b->a, b->z, b->nx, b->ny, b->nz};
    for (size_t k = 0; k < 8; k++)
        assert_memory_equal(pa[k], pb[k], n * sizeof(float));
    assert_memory_equal(a->object_id, b->object_id, n * sizeof(uint32_t));
    assert_memory_equal(a->prim_id, b->prim_id, n * sizeof(uint32_t));
    /* Supersampling produced fractional alpha on the silhouette. */
    size_t partial = 0;
    for (size_t i = 0; i < n; i++)
        partial += a->a[i] > 0 && a->a[i] < 1;
    assert_true(partial > 10);
    mr_film_free(a);
    mr_film_free(b);
    fixture_free(&s);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_sphere_depth_and_silhouette),
        cmocka_unit_test(test_sphere_off_centre),
        cmocka_unit_test(test_untraced_misses_are_misses),
        cmocka_unit_test(test_same_bytes_any_thread_count),
        cmocka_unit_test(test_film_remembers_misses),
    };
    return cmocka_run_group_tests_name("render", tests, NULL, NULL);
}
