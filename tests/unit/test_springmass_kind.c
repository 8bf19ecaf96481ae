/*
 * test_springmass_kind.c - the spring-mass kind through the renderer (a
 * real model, assimp's Wuson): frames rendered out of order restore the
 * newest checkpoint at or before them (render/checkpoint.h) and replay the
 * rest, bit-identical to the in-order run; a damaged checkpoint is refused,
 * removed and written again, and the next older one is used; another
 * parameter is another state id; the thread count changes no bit (the
 * tangent pass too); the
 * kind's stats fields; a pose and a diverging simulation are errors that
 * name the object.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <unistd.h>

#include "../support/file_fixture.h"
#include "../support/film_fixture.h"
#include "job_json.h"
#include "render/checkpoint.h"
#include "render/device.h"
#include "render/renderer.h"
#include "kinds/springmass/springmass_kind.h"

#define FRAMES 10

static const char *JOB_FMT =
    "{\"name\":\"sm\",\"assets\":{\"w\":{\"path\":\"/usr/share/assimp/models/PLY/Wuson.ply\"}},"
    "\"objects\":[{\"asset\":\"w\",\"kind\":\"springmass\",\"springmass\":{\"nodes\":1200,"
    "\"stiffness\":%s,\"checkpoint_every\":3,\"mapping\":\"%s\","
    "\"pins\":[{\"box_max\":[1,0.2,2]}],"
    "\"probes\":[{\"radius\":0.35,\"path\":[{\"t\":0,\"position\":[0,1.9,0]},"
    "{\"t\":0.375,\"position\":[0,1.1,0.3]}]}]}%s}],"
    "\"lights\":[{\"direction\":[-0.4,-0.8,-0.6]}],"
    "\"camera\":{\"path\":[{\"t\":0,\"position\":[4,1.5,1],\"target\":[0,0.7,0]}]},"
    "\"frames\":{\"fps\":24,\"start\":0,\"end\":0.375},"
    "\"output\":{\"width\":64,\"height\":48,\"samples\":1}}";

static mr_job *job_with(const char *stiffness, const char *mapping, const char *extra)
{
    char text[2048];
    snprintf(text, sizeof text, JOB_FMT, stiffness, mapping, extra);
    mr_job *job = NULL;
    mr_job_error e;
    if (mr_job_parse(text, strlen(text), &job, &e) < 0)
        fail_msg("%s: %s", e.pointer, e.message);
    assert_int_equal(job->frame_count, FRAMES);
    return job;
}

typedef struct run {
    mr_device *dev;
    mr_asset *asset;
    mr_renderer *r;
    mr_film *film;
} run;

static void run_open(run *x, const mr_job *job, unsigned threads, const char *cache)
{
    mr_error err;
    memset(x, 0, sizeof *x);
    assert_int_equal(mr_device_new(threads, &x->dev, &err), MR_OK);
    assert_int_equal(mr_asset_load(job->assets[0].path, &x->asset, &err), MR_OK);
    mr_renderer_options opt = {.cache_dir = cache};
    if (mr_renderer_new(x->dev, job, &x->asset, &opt, &x->r, &err) < 0)
        fail_msg("renderer: %s", err.msg);
    /* the default passes and the tangents (map.h carries them) */
    assert_int_equal(mr_film_new_aovs(64, 48, MR_AOV_DEFAULT | MR_AOV_T, 0, &x->film, &err), MR_OK);
}

static void run_close(run *x)
{
    mr_film_free(x->film);
    mr_renderer_free(x->r);
    mr_asset_free(x->asset);
    mr_device_free(x->dev);
}

/* Every plane of the film, concatenated. */
static uint8_t *film_bytes(const mr_film *f, size_t *n)
{
    size_t px = (size_t)f->width * f->height;
    const float *planes[] = {f->r, f->g, f->b, f->a, f->z, f->nx, f->ny, f->nz, f->tx, f->ty, f->tz};
    *n = px * (11 * sizeof(float) + 2 * sizeof(uint32_t));
    uint8_t *b = malloc(*n), *p = b;
    for (size_t k = 0; k < 11; k++, p += px * sizeof(float))
        memcpy(p, planes[k], px * sizeof(float));
    memcpy(p, f->object_id, px * sizeof(uint32_t));
    memcpy(p + px * sizeof(uint32_t), f->prim_id, px * sizeof(uint32_t));
    return b;
}

static uint8_t *render(run *x, size_t frame, mr_frame_stats *st, size_t *n)
{
    mr_error err;
    if (mr_renderer_render(x->r, frame, x->film, st, &err) < 0)
        fail_msg("frame %zu: %s", frame, err.msg);
    return film_bytes(x->film, n);
}

static void test_checkpoints(void **state)
{
    (void)state;
    char cache[128], kind_dir[160];
    snprintf(cache, sizeof cache, "%s/cache", tmp_dir);
    snprintf(kind_dir, sizeof kind_dir, "%s/springmass", cache);
    mr_job *job = job_with("1000", "triangle_basis_curvature", "");
    uint8_t *ref[FRAMES];
    size_t n = 0;
    mr_frame_stats st;
    /* in order, with checkpoints after frames 3, 6 and 9 */
    run a;
    run_open(&a, job, 2, cache);
    for (size_t k = 0; k < FRAMES; k++) {
        ref[k] = render(&a, k, &st, &n);
        assert_int_equal(st.replay_frames, 0);
        assert_true(fx_frame_extra(&st, "sim_steps") == (k ? 15 : 0));
        assert_true(fx_frame_extra(&st, "sim_nodes") > 1100 && fx_frame_extra(&st, "sim_nodes") < 1300);
        assert_true(fx_frame_extra(&st, "sim_substeps") >= 2);
        if (k)
            assert_true(memcmp(ref[k], ref[k - 1], n) != 0); /* it moves */
    }
    run_close(&a);
    assert_int_equal(file_count(kind_dir, ".mrckpt"), 3);

    /* a fresh renderer (a new worker after a crash) asked for frame 8: it
     * restores the checkpoint after 6 frames and replays frames 6 and 7 */
    run b;
    run_open(&b, job, 1, cache);
    size_t m;
    uint8_t *got = render(&b, 8, &st, &m);
    assert_int_equal(st.replay_checkpoint, 6);
    assert_int_equal(st.replay_frames, 2);
    assert_memory_equal(got, ref[8], n);
    free(got);
    /* back to frame 4: checkpoint 3, one frame replayed */
    got = render(&b, 4, &st, &m);
    assert_int_equal(st.replay_checkpoint, 3);
    assert_int_equal(st.replay_frames, 1);
    assert_memory_equal(got, ref[4], n);
    free(got);
    run_close(&b);

    /* a damaged checkpoint (one payload byte) is refused and removed; the
     * older one is used, and the replay passing frame 6 writes it again */
    char *path = NULL;
    run c;
    run_open(&c, job, 2, cache);
    DIR *d = opendir(kind_dir);
    size_t damaged = 0;
    for (struct dirent *e; (e = readdir(d));) {
        if (!strstr(e->d_name, ".mrckpt"))
            continue;
        char p[512];
        snprintf(p, sizeof p, "%s/%s", kind_dir, e->d_name);
        size_t sz;
        uint8_t *bytes = file_get(p, &sz);
        /* the frames field (offset 16) says which checkpoint this is */
        uint64_t frames = 0;
        for (int i = 7; i >= 0; i--)
            frames = frames << 8 | bytes[16 + i];
        if (frames == 6) {
            bytes[sz - 5] ^= 0x40;
            file_put(p, bytes, sz);
            damaged++;
            path = strdup(p);
        }
        free(bytes);
    }
    closedir(d);
    assert_int_equal(damaged, 1);
    got = render(&c, 8, &st, &m);
    assert_int_equal(st.replay_checkpoint, 3);
    assert_int_equal(st.replay_frames, 5);
    assert_memory_equal(got, ref[8], n);
    free(got);
    /* written again by the replay, and good: a fresh renderer uses it */
    assert_int_equal(access(path, F_OK), 0);
    run_close(&c);
    run e2;
    run_open(&e2, job, 2, cache);
    got = render(&e2, 7, &st, &m);
    assert_int_equal(st.replay_checkpoint, 6);
    assert_memory_equal(got, ref[7], n);
    free(got);
    run_close(&e2);
    free(path);

    /* another stiffness is another simulation: no checkpoint of this one fits */
    mr_job *other = job_with("800", "triangle_basis_curvature", "");
    run f;
    run_open(&f, other, 2, cache);
    got = render(&f, 8, &st, &m);
    assert_int_equal(st.replay_checkpoint, 0);
    assert_int_equal(st.replay_frames, 7); /* 1..7: frame 0 came first, for the tree (renderer.c) */
    assert_true(memcmp(got, ref[8], n) != 0);
    free(got);
    run_close(&f);
    mr_job_free(other);

    for (size_t k = 0; k < FRAMES; k++)
        free(ref[k]);
    mr_job_free(job);
}


/* Three workers one after the other on one cache, each starting where the
 * last stopped (a daemon killed, then a worker killed): every frame equals
 * the in-order run's, also those from checkpoints written by a worker that
 * itself started from one. */
static void test_chained_workers(void **state)
{
    (void)state;
    char cache[128], fresh[128];
    snprintf(cache, sizeof cache, "%s/chain", tmp_dir);
    snprintf(fresh, sizeof fresh, "%s/chain-ref", tmp_dir);
    mr_job *job = job_with("1000", "triangle_basis_curvature", "");
    mr_frame_stats st;
    uint8_t *ref[FRAMES];
    size_t n = 0, m;
    run a;
    run_open(&a, job, 2, fresh);
    for (size_t k = 0; k < FRAMES; k++)
        ref[k] = render(&a, k, &st, &n);
    run_close(&a);
    const size_t first[] = {0, 3, 6}, last[] = {3, 6, FRAMES};
    for (int w = 0; w < 3; w++) {
        run x;
        run_open(&x, job, 2, cache);
        for (size_t k = first[w]; k < last[w]; k++) {
            uint8_t *got = render(&x, k, &st, &m);
            if (memcmp(got, ref[k], n) != 0)
                fail_msg("worker %d, frame %zu (replayed %u from checkpoint %u) differs", w, k, st.replay_frames,
                         st.replay_checkpoint);
            free(got);
        }
        run_close(&x);
    }
    for (size_t k = 0; k < FRAMES; k++)
        free(ref[k]);
    mr_job_free(job);
}

/* The same frames for 1 and 2 threads, for every mapping. */
static void test_threads(void **state)
{
    (void)state;
    const char *mappings[] = {"one_to_one", "triangle_basis", "triangle_basis_curvature", "trilinear"};
    for (size_t k = 0; k < 4; k++) {
        mr_job *job = job_with("1000", mappings[k], "");
        uint8_t *bytes[2];
        size_t n;
        mr_frame_stats st;
        for (unsigned t = 1; t <= 2; t++) {
            run x;
            run_open(&x, job, t, NULL);
            for (size_t f = 0; f < 6; f++) {
                uint8_t *b = render(&x, f, &st, &n);
                if (f < 5)
                    free(b);
                else
                    bytes[t - 1] = b;
            }
            run_close(&x);
        }
        if (memcmp(bytes[0], bytes[1], n) != 0)
            fail_msg("%s: frame 5 differs between 1 and 2 threads", mappings[k]);
        free(bytes[0]);
        free(bytes[1]);
        mr_job_free(job);
    }
}

static void test_errors(void **state)
{
    (void)state;
    mr_error err;
    /* a pose: the simulation moves the object. The job's reader refuses
     * it, naming the field; the kind refuses one a program puts in the
     * job itself. */
    char text[2048];
    snprintf(text, sizeof text, JOB_FMT, "1000", "trilinear", ",\"pose\":{\"clip\":0}");
    mr_job *job = NULL;
    mr_job_error je;
    assert_int_equal(mr_job_parse(text, strlen(text), &job, &je), MR_ERR_INVALID);
    assert_string_equal(je.pointer, "/objects/0/pose");
    assert_non_null(strstr(je.message, "moves by itself"));
    job = job_with("1000", "trilinear", "");
    static mr_pose_desc pose = {.has_clip = true, .speed = 1, .loop = true};
    job->objects[0].poses = &pose; /* the test's: taken back before mr_job_free */
    job->objects[0].pose_count = 1;
    mr_device *dev;
    assert_int_equal(mr_device_new(1, &dev, &err), MR_OK);
    mr_asset *a;
    assert_int_equal(mr_asset_load(job->assets[0].path, &a, &err), MR_OK);
    mr_renderer *r = NULL;
    assert_int_equal(mr_renderer_new(dev, job, &a, NULL, &r, &err), MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "/objects/0/pose: a springmass object is moved by its simulation"));
    job->objects[0].poses = NULL;
    job->objects[0].pose_count = 0;
    mr_job_free(job);
    /* a pin dragged away faster than anything can follow: the springs
     * tear, and the frame says so instead of rendering the explosion */
    job = job_with("1000", "trilinear", "");
    mr_springmass_params *p = job->objects[0].params;
    static mr_springmass_pin_key keys[2] = {{0, {0, 0, 0}, {0, 0, 0, 1}}, {0.05f, {0, 500, 0}, {0, 0, 0, 1}}};
    p->pins[0].path = keys; /* the test's: taken back before mr_job_free */
    p->pins[0].path_count = 2;
    assert_int_equal(mr_renderer_new(dev, job, &a, NULL, &r, &err), MR_OK);
    mr_film *film;
    assert_int_equal(mr_film_new(64, 48, &film, &err), MR_OK);
    mr_frame_stats st;
    int rc = MR_OK;
    size_t f = 0;
    for (; f < FRAMES && rc == MR_OK; f++)
        rc = mr_renderer_render(r, f, film, &st, &err);
    assert_int_equal(rc, MR_ERR_INVALID);
    assert_non_null(strstr(err.msg, "/objects/0/springmass: the simulation diverged"));
    /* later frames fail the same way, without simulating */
    assert_int_equal(mr_renderer_render(r, f, film, &st, &err), MR_ERR_INVALID);
    mr_film_free(film);
    mr_renderer_free(r);
    p->pins[0].path = NULL;
    p->pins[0].path_count = 0;
    mr_job_free(job);
    mr_asset_free(a);
    mr_device_free(dev);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_checkpoints),
        cmocka_unit_test(test_chained_workers),
        cmocka_unit_test(test_threads),
        cmocka_unit_test(test_errors),
    };
    return cmocka_run_group_tests(tests, file_fixture_setup, file_fixture_teardown);
}
