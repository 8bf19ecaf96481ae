/*
 * test_springmass_sim.c - the spring-mass solver (core/kinds/springmass/
 * sim.h): the stability bound and its substeps (and that the bound is where
 * instability really starts), bit-identical states for any thread count and
 * vector width, pins moving rigidly, energy that does not grow without a
 * driver, divergence reported as an error, the state's bytes round trip,
 * and the job block's refusals naming their fields.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include <stdio.h>

#include "../support/springmass_fixture.h"
#include "job_json.h"

/* A grid filling a sphere of radius 1, ~n nodes; the simulation owns it. */
static sm_sim *sphere_sim(const mr_springmass_params *p, uint32_t nodes, unsigned threads)
{
    sm_mesh m;
    sm_mesh_sphere(&m, 0, 0, 0, 1.0, 24, 48);
    sm_grid g;
    mr_error err;
    if (sm_grid_build(m.pos, m.vertex_count, m.tri, m.triangle_count, 0, nodes, 0, threads, &g, &err) < 0)
        fail_msg("grid: %s", err.msg);
    sm_mesh_free(&m);
    sm_sim *s = NULL;
    if (sm_sim_new(&g, p, threads, &s, &err) < 0)
        fail_msg("sim: %s", err.msg);
    return s;
}

static uint8_t *state_of(const sm_sim *s, size_t *n)
{
    *n = sm_sim_state_bytes(s);
    uint8_t *b = malloc(*n);
    sm_sim_state_save(s, b);
    return b;
}

static void test_substeps(void **state)
{
    (void)state;
    mr_springmass_params p = sm_default_params();
    p.mass = 0.01f;
    p.stiffness = p.shear_stiffness = 1000;
    double hc;
    p.dt = 1e-3f;
    assert_int_equal(sm_substeps(&p, &hc), 1);
    assert_true(fabs(hc / sqrt((double)p.mass / 3000) - 1) < 1e-12);
    p.dt = 2e-3f; /* 2e-3 / (0.9 x 1.826e-3) = 1.22 */
    assert_int_equal(sm_substeps(&p, NULL), 2);
    p.stiffness = p.shear_stiffness = 1e7f;
    p.dt = 1.0f / 360;
    uint32_t n = sm_substeps(&p, &hc);
    assert_int_equal(n, (uint32_t)ceil(p.dt / (0.9 * hc)));
    assert_true(sm_substeps(&p, NULL) > 100);
    p.stiffness = p.shear_stiffness = 1e9f; /* 1,690 substeps: refused */
    assert_int_equal(sm_substeps(&p, NULL), 0);
    p.stiffness = p.shear_stiffness = 0; /* no springs: no bound */
    assert_int_equal(sm_substeps(&p, &hc), 1);
    assert_true(isinf(hc));
}

/* Undamped, weightless, perturbed by 1e-4 of a spacing (so the springs
 * are all but linear), one substep per step whatever the bound says: at
 * 0.97 h_crit nothing grows over 2,000 steps; at 1.03 h_crit the mode of
 * planes moving against each other along an axis (eigenvalue 4 k_s +
 * 8 k_d, sim.h) grows until it is reported. */
static void test_bound_is_tight(void **state)
{
    (void)state;
    mr_springmass_params p = sm_default_params();
    p.gravity = mr_v3(0, 0, 0);
    p.damping = 0;
    p.mass = 0.01f;
    p.stiffness = 1000;
    p.shear_stiffness = 500;
    double hc;
    p.dt = 1e-3f;
    sm_substeps(&p, &hc);
    mr_error err;
    for (int above = 0; above < 2; above++) {
        p.dt = (float)(hc * (above ? 1.03 : 0.97));
        sm_sim *s = sphere_sim(&p, 3000, 2);
        sm_sim_set_substeps(s, 1, 2);
        sm_sim_perturb(s, 1e-4f * (float)sm_sim_grid(s)->h, 7, 2);
        int rc = MR_OK;
        for (int f = 0; f < 100 && rc == MR_OK; f++)
            rc = sm_sim_advance(s, 20, 2, &err);
        if (above) {
            assert_int_equal(rc, MR_ERR_INVALID);
            assert_non_null(strstr(err.msg, "the simulation diverged"));
            /* and stays failed, with the same message, until reset */
            char first[sizeof err.msg];
            snprintf(first, sizeof first, "%s", err.msg);
            assert_int_equal(sm_sim_advance(s, 1, 2, &err), MR_ERR_INVALID);
            assert_string_equal(err.msg, first);
            sm_sim_reset(s, 2);
            assert_int_equal(sm_sim_advance(s, 1, 2, &err), MR_OK);
        } else {
            if (rc != MR_OK)
                fail_msg("below the bound: %s", err.msg);
            assert_true(sm_sim_measure(s)->max_strain < 0.01);
        }
        sm_sim_free(s);
    }
}

/* A scene with every force and constraint: gravity, damping, a static pin,
 * a moving pin, a probe crossing the body, a point force and wind. */
static mr_springmass_params busy_params(mr_springmass_pin *pins, mr_springmass_pin_key *keys,
                                        mr_springmass_probe *probe, mr_springmass_probe_key *pk,
                                        mr_springmass_force *forces)
{
    mr_springmass_params p = sm_default_params();
    p.dt = 1.0f / 240; /* 2 substeps */
    pins[0] = (mr_springmass_pin){.box_min = {-2, -2, -2}, .box_max = {2, -0.7f, 2}};
    keys[0] = (mr_springmass_pin_key){0, {0, 0, 0}, {0, 0, 0, 1}};
    keys[1] = (mr_springmass_pin_key){0.2f, {0.1f, 0.2f, 0}, {0, 0.0998f, 0, 0.995f}};
    pins[1] = (mr_springmass_pin){.box_min = {-2, 0.7f, -2}, .box_max = {2, 2, 2}, .path = keys, .path_count = 2};
    pk[0] = (mr_springmass_probe_key){0, {-1.5f, 0.1f, 0}};
    pk[1] = (mr_springmass_probe_key){0.25f, {1.5f, 0.1f, 0}};
    *probe = (mr_springmass_probe){.radius = 0.3f, .path = pk, .path_count = 2};
    forces[0] = (mr_springmass_force){MR_SPRINGMASS_FORCE_POINT, {0.9f, 0, 0}, {0, 5, 0}, 0, 0.1f};
    forces[1] = (mr_springmass_force){MR_SPRINGMASS_FORCE_WIND, {0, 0, 0}, {0.01f, 0, 0.02f}, 0.05f, 1};
    p.pins = pins;
    p.pin_count = 2;
    p.probes = probe;
    p.probe_count = 1;
    p.forces = forces;
    p.force_count = 2;
    return p;
}

/* The same bits whatever the thread count and the kernel's vector width. */
static void test_deterministic(void **state)
{
    (void)state;
    mr_springmass_pin pins[2];
    mr_springmass_pin_key keys[2];
    mr_springmass_probe probe;
    mr_springmass_probe_key pk[2];
    mr_springmass_force forces[2];
    mr_springmass_params p = busy_params(pins, keys, &probe, pk, forces);
    const unsigned threads[] = {1, 2, 3, 1, 2};
    const int widths[] = {0, 0, 0, 1, 4};
    uint8_t *ref = NULL;
    size_t ref_n = 0;
    mr_error err;
    for (size_t run = 0; run < sizeof threads / sizeof *threads; run++) {
        sm_sim_force_width(widths[run]);
        sm_sim *s = sphere_sim(&p, 2500, threads[run]);
        for (int f = 0; f < 6; f++)
            if (sm_sim_advance(s, 10, threads[run], &err) < 0)
                fail_msg("run %zu: %s", run, err.msg);
        size_t n;
        uint8_t *b = state_of(s, &n);
        if (!ref) {
            ref = b;
            ref_n = n;
            /* it moved: not a trivially equal rest state */
            assert_true(sm_sim_measure(s)->kinetic > 0);
        } else {
            assert_int_equal(n, ref_n);
            if (memcmp(b, ref, n) != 0)
                fail_msg("run %zu (%u threads, width %d) differs from run 0", run, threads[run], widths[run]);
            free(b);
        }
        sm_sim_free(s);
    }
    sm_sim_force_width(8);
    sm_sim *s = sphere_sim(&p, 2500, 2);
    for (int f = 0; f < 6; f++)
        assert_int_equal(sm_sim_advance(s, 10, 2, &err), MR_OK);
    size_t n;
    uint8_t *b = state_of(s, &n);
    assert_memory_equal(b, ref, n);
    free(b);
    sm_sim_free(s);
    sm_sim_force_width(0);
    free(ref);
}

/* Every node pinned to a rotating, translating path: each node is the rigid
 * motion of its rest position (float rounding: < 1e-6 of the size). */
static void test_rigid_pins(void **state)
{
    (void)state;
    mr_springmass_params p = sm_default_params();
    mr_springmass_pin_key keys[2] = {{0, {0, 0, 0}, {0, 0, 0, 1}},
                                     {1, {0.5f, -0.25f, 1}, {0.2f, 0.4f, -0.1f, 0.8888194f}}};
    mr_springmass_pin pin = {.box_min = {-5, -5, -5}, .box_max = {5, 5, 5}, .pivot = {0.1f, 0.2f, 0.3f},
                             .has_pivot = true, .path = keys, .path_count = 2};
    p.pins = &pin;
    p.pin_count = 1;
    sm_sim *s = sphere_sim(&p, 2000, 2);
    mr_error err;
    assert_int_equal(sm_sim_advance(s, 180, 2, &err), MR_OK); /* t = 0.5 */
    const float *x[3], *r[3];
    sm_sim_positions(s, x);
    sm_sim_rest(s, r);
    mr_quat q = mr_quat_slerp(keys[0].rotation, mr_quat_normalize(keys[1].rotation), 0.5f);
    const sm_grid *g = sm_sim_grid(s);
    double worst = 0;
    for (size_t c = 0; c < g->cells; c++) {
        if (!g->active[c])
            continue;
        mr_vec3 d = mr_v3(r[0][c] - 0.1f, r[1][c] - 0.2f, r[2][c] - 0.3f);
        mr_vec3 e = mr_quat_rotate(mr_quat_normalize(q), d);
        double want[3] = {0.1 + e.x + 0.25, 0.2 + e.y - 0.125, 0.3 + e.z + 0.5};
        for (int a = 0; a < 3; a++)
            worst = fmax(worst, fabs(x[a][c] - want[a]));
    }
    assert_true(worst < 2e-6);
    assert_true(sm_sim_measure(s)->max_strain < 1e-5);
    assert_int_equal(sm_sim_measure(s)->inverted_cells, 0);
    sm_sim_free(s);
}

/* Nothing drives the system: the integrator's energy never grows. Free
 * fall and everything pinned, undamped, over 600 steps; a body hanging
 * from a pin, damped, comes to rest. */
static void test_energy(void **state)
{
    (void)state;
    mr_error err;
    mr_springmass_params p = sm_default_params();
    p.damping = 0;
    sm_sim *s = sphere_sim(&p, 1500, 2);
    double e0 = sm_sim_measure(s)->shadow;
    for (int f = 0; f < 40; f++) {
        assert_int_equal(sm_sim_advance(s, 15, 2, &err), MR_OK);
        const sm_measure *m = sm_sim_measure(s);
        /* free fall: the body does not deform but for float rounding (the
         * body drops 11 units, where a float's step is 1e-6: 1,200 rounded
         * substeps of a 0.14 spacing reach strains of 1e-4), and the energy
         * stays put to 1e-6 of the energy moved between kinetic and gravity */
        assert_true(m->shadow <= e0 + 1e-6 * (m->kinetic + fabs(m->gravity)) + 1e-12);
        if (!(m->max_strain < 1e-3))
            fail_msg("frame %d: strain %g", f, m->max_strain);
    }
    assert_true(sm_sim_measure(s)->kinetic > 0);
    sm_sim_free(s);
    /* everything pinned: nothing moves at all */
    mr_springmass_pin all = {.box_min = {-5, -5, -5}, .box_max = {5, 5, 5}};
    p.pins = &all;
    p.pin_count = 1;
    s = sphere_sim(&p, 1500, 2);
    double rest_spring = sm_sim_measure(s)->spring; /* float rest lengths: not quite 0 */
    assert_int_equal(sm_sim_advance(s, 600, 2, &err), MR_OK);
    assert_true(sm_sim_measure(s)->kinetic == 0 && sm_sim_measure(s)->spring == rest_spring);
    sm_sim_free(s);
    /* hanging from its top, damped: swings, then rests */
    mr_springmass_pin top = {.box_min = {-5, 0.75f, -5}, .box_max = {5, 5, 5}};
    p.pins = &top;
    p.damping = 0.05f;
    p.stiffness = p.shear_stiffness = 300;
    s = sphere_sim(&p, 1500, 2);
    double peak = 0, last = INFINITY;
    for (int f = 0; f < 200; f++) {
        assert_int_equal(sm_sim_advance(s, 15, 2, &err), MR_OK);
        peak = fmax(peak, sm_sim_measure(s)->kinetic);
        last = sm_sim_measure(s)->kinetic;
    }
    assert_true(peak > 0 && last < 1e-3 * peak);
    assert_true(sm_sim_measure(s)->spring > 0); /* it hangs stretched */
    sm_sim_free(s);
}

/* A pin by node set: the nodes nearest to three points hold still (and
 * no other node), the ball hangs from them. */
static void test_node_set_pin(void **state)
{
    (void)state;
    mr_springmass_params p = sm_default_params();
    mr_springmass_pin_point points[3] = {{{0, 0.9f, 0}}, {{0.2f, 0.85f, 0}}, {{-0.2f, 0.85f, 0.1f}}};
    mr_springmass_pin pin = {.points = points, .point_count = 3, .points_only = true};
    p.pins = &pin;
    p.pin_count = 1;
    sm_sim *s = sphere_sim(&p, 1500, 2);
    mr_error err;
    assert_int_equal(sm_sim_advance(s, 60, 2, &err), MR_OK);
    const float *x[3], *r[3];
    sm_sim_positions(s, x);
    sm_sim_rest(s, r);
    const sm_grid *g = sm_sim_grid(s);
    size_t still = 0, moved = 0;
    for (size_t c = 0; c < g->cells; c++) {
        if (!g->active[c])
            continue;
        bool same = x[0][c] == r[0][c] && x[1][c] == r[1][c] && x[2][c] == r[2][c];
        still += same;
        moved += !same;
    }
    assert_int_equal(still, 3);
    assert_true(moved == g->nodes - 3);
    sm_sim_free(s);
}

static void test_state_round_trip(void **state)
{
    (void)state;
    mr_springmass_pin pins[2];
    mr_springmass_pin_key keys[2];
    mr_springmass_probe probe;
    mr_springmass_probe_key pk[2];
    mr_springmass_force forces[2];
    mr_springmass_params p = busy_params(pins, keys, &probe, pk, forces);
    mr_error err;
    sm_sim *a = sphere_sim(&p, 1500, 2), *b = sphere_sim(&p, 1500, 1);
    assert_int_equal(sm_sim_advance(a, 25, 2, &err), MR_OK);
    size_t n;
    uint8_t *mid = state_of(a, &n);
    assert_int_equal(n, 32 + 24 * sm_sim_grid(a)->nodes);
    assert_int_equal(sm_sim_advance(a, 25, 2, &err), MR_OK);
    /* b restored from the middle goes on exactly as a did */
    assert_int_equal(sm_sim_state_load(b, mid, n, 1, &err), MR_OK);
    assert_int_equal(sm_sim_steps(b), 25);
    assert_int_equal(sm_sim_advance(b, 25, 1, &err), MR_OK);
    size_t na, nb;
    uint8_t *sa = state_of(a, &na), *sb = state_of(b, &nb);
    assert_memory_equal(sa, sb, na);
    /* refusals leave the state alone */
    assert_int_equal(sm_sim_state_load(b, mid, n - 1, 1, &err), MR_ERR_FORMAT);
    uint8_t *bad = malloc(n);
    memcpy(bad, mid, n);
    float inf = INFINITY;
    memcpy(bad + 32 + 4 * 7, &inf, 4);
    assert_int_equal(sm_sim_state_load(b, bad, n, 1, &err), MR_ERR_FORMAT);
    assert_non_null(strstr(err.msg, "node 1"));
    free(sb);
    sb = state_of(b, &nb);
    assert_memory_equal(sa, sb, na);
    free(bad);
    free(mid);
    free(sa);
    free(sb);
    sm_sim_free(a);
    sm_sim_free(b);
}

/* The job block: defaults, and refusals naming the field. */
static void test_job_block(void **state)
{
    (void)state;
#define JOB(block)                                                                                 \
    "{\"assets\":{\"m\":{\"path\":\"/a.ply\"}},\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0,5],"  \
    "\"target\":[0,0,0]}]},\"frames\":{\"end\":1},\"objects\":[{\"asset\":\"m\",\"kind\":"         \
    "\"springmass\",\"springmass\":" block "}]}"
    static const struct {
        const char *json, *pointer, *msg;
    } bad[] = {
        {JOB("{\"dt\":0.01,\"stiffness\":1e9}"), "/objects/0/springmass/dt",
         "needs more than 1000 substeps under the stability bound"},
        {JOB("{\"spacing\":0.1,\"nodes\":100}"), "/objects/0/springmass/nodes", "give either \"spacing\" or \"nodes\""},
        {JOB("{\"steps_per_frame\":100000,\"stiffness\":1e6}"), "/objects/0/springmass/steps_per_frame",
         "per frame, more than 100000"},
        {JOB("{\"mapping\":\"bilinear\"}"), "/objects/0/springmass/mapping", "\"trilinear\""},
        {JOB("{\"gravity\":[0,-9.81]}"), "/objects/0/springmass/gravity", "expected an array of 3 numbers"},
        {JOB("{\"gravity\":[0,-9.81,1e7]}"), "/objects/0/springmass/gravity/2", "got 10000000"},
        {JOB("{\"pins\":[{\"path\":[{\"t\":1},{\"t\":0.5}]}]}"), "/objects/0/springmass/pins/0/path",
         "keys must have increasing t"},
        {JOB("{\"pins\":[{\"path\":[{\"translation\":[0,0,0]}]}]}"), "/objects/0/springmass/pins/0/path/0",
         "a path key needs \"t\""},
        {JOB("{\"pins\":[{\"path\":[{\"t\":0,\"rotation\":[0,0,0,0]}]}]}"),
         "/objects/0/springmass/pins/0/path/0/rotation", "non-zero quaternion"},
        {JOB("{\"pins\":[{\"box_min\":[0,0,0],\"box_max\":[1,-1,1]}]}"), "/objects/0/springmass/pins/0/box_max",
         "box_max >= box_min"},
        {JOB("{\"probes\":[{\"radius\":0.1}]}"), "/objects/0/springmass/probes/0", "a probe needs a path"},
        {JOB("{\"probes\":[{\"path\":[{\"t\":0}]}]}"), "/objects/0/springmass/probes/0/path/0",
         "a probe key needs \"position\""},
        {JOB("{\"forces\":[{\"type\":\"wind\",\"start\":2,\"end\":1}]}"), "/objects/0/springmass/forces/0/end",
         "expected end > start"},
        {JOB("{\"mass\":0}"), "/objects/0/springmass/mass", "got 0"},
    };
    for (size_t i = 0; i < sizeof bad / sizeof *bad; i++) {
        mr_job *job = NULL;
        mr_job_error err;
        int rc = mr_job_parse(bad[i].json, strlen(bad[i].json), &job, &err);
        if (rc == MR_OK || strcmp(err.pointer, bad[i].pointer) != 0 || !strstr(err.message, bad[i].msg))
            fail_msg("case %zu: got %d '%s' %s", i, rc, err.pointer, err.message);
    }
    /* the defaults, and the shear stiffness following the stiffness */
    const char *ok = JOB("{\"stiffness\":250,\"pins\":[{\"box_max\":[1,0,1]}],\"probes\":[{\"path\":[{\"t\":0,"
                         "\"position\":[0,2,0]}]}]}");
    mr_job *job = NULL;
    mr_job_error err;
    assert_int_equal(mr_job_parse(ok, strlen(ok), &job, &err), MR_OK);
    const mr_springmass_params *p = job->objects[0].params;
    assert_true(p->stiffness == 250 && p->shear_stiffness == 250);
    assert_true(p->nodes == 4096 && p->spacing == 0 && p->steps_per_frame == 15);
    assert_true(p->gravity.y == -9.81f && p->mapping == MR_SPRINGMASS_TRIANGLE_CURVATURE);
    assert_int_equal(p->pin_count, 1);
    assert_true(p->pins[0].box_min.x == -1e9f && !p->pins[0].has_pivot);
    assert_true(p->probes[0].radius == 0.1f && p->probes[0].path[0].position.y == 2);
    assert_false(p->pins[0].points_only);
    mr_job_free(job);
    /* a node set alone, and with a box */
    const char *sets[] = {JOB("{\"pins\":[{\"points\":[{\"position\":[0,1,0]}]}]}"),
                          JOB("{\"pins\":[{\"box_max\":[1,0,1],\"points\":[{\"position\":[0,1,0]}]}]}")};
    for (int k = 0; k < 2; k++) {
        assert_int_equal(mr_job_parse(sets[k], strlen(sets[k]), &job, &err), MR_OK);
        p = job->objects[0].params;
        assert_int_equal(p->pins[0].point_count, 1);
        assert_int_equal(p->pins[0].points_only, k == 0);
        mr_job_free(job);
    }
#undef JOB
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_substeps),    cmocka_unit_test(test_bound_is_tight),
        cmocka_unit_test(test_deterministic), cmocka_unit_test(test_rigid_pins),
        cmocka_unit_test(test_energy),      cmocka_unit_test(test_node_set_pin),
        cmocka_unit_test(test_state_round_trip),
        cmocka_unit_test(test_job_block),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
