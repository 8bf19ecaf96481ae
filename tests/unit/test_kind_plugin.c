/*
 * test_kind_plugin.c - a geometry kind added from outside core: the
 * test_sphere kind of tests/support/sphere_kind.h, registered by one line,
 * goes through every generic path a built-in kind does:
 *   - the registry (lookup, a name taken twice refused);
 *   - the server's generic block reader (defaults, values, JSON pointers and
 *     messages of bad values, a block without its kind, the kind list in
 *     the "kind" error);
 *   - the schema generator (its block and the kind enum) and the OpenAPI
 *     document's frame stats (its fields);
 *   - the renderer and worker, with its derived data kept in
 *     <cache root>/test_sphere/ and read back by the next job;
 *   - the frame-order contract: frames rendered out of order (a resumed or
 *     retried job) are bit-identical to the uninterrupted run's;
 *   - its own per-frame stats fields in stats.json.
 * No file outside tests/ knows the kind.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <dirent.h>
#include <sys/stat.h>
#include <unistd.h>

#include "../support/sphere_kind.h"
#include "job_json.h"
#include "render/renderer.h"
#include "schema_gen.h"
#include "stats_json.h"
#include "stats_openapi.h"
#include "worker.h"

#define BOX "/usr/share/assimp/models/OBJ/box.obj"

static const char *job_text(const char *object, char *buf, size_t n)
{
    snprintf(buf, n,
             "{\"assets\": {\"a\": {\"path\": \"" BOX "\"}},"
             " \"objects\": [%s],"
             " \"camera\": {\"path\": [{\"t\": 0, \"position\": [0, 0, 4], \"target\": [0, 0, 0]}]},"
             " \"lights\": [{\"direction\": [-0.3, -0.5, -1]}],"
             " \"frames\": {\"fps\": 4, \"start\": 0, \"end\": 1.5},"
             " \"output\": {\"width\": 48, \"height\": 32, \"samples\": 1}}",
             object);
    return buf;
}

static int parse_object(const char *object, mr_job **job, mr_job_error *e)
{
    char buf[2048];
    job_text(object, buf, sizeof buf);
    return mr_job_parse(buf, strlen(buf), job, e);
}

static void expect_error(const char *object, const char *pointer, const char *message)
{
    mr_job *job = NULL;
    mr_job_error e = {0};
    int rc = parse_object(object, &job, &e);
    if (rc == MR_OK)
        fail_msg("accepted: %s", object);
    assert_null(job);
    assert_string_equal(e.pointer, pointer);
    if (!strstr(e.message, message))
        fail_msg("message \"%s\" lacks \"%s\"", e.message, message);
}

static int setup(void **state)
{
    mr_error err = {0};
    (void)state;
    return mr_kind_register(&test_sphere_kind, &err) == MR_OK ? 0 : -1;
}

static void test_registry(void **state)
{
    (void)state;
    mr_error err = {0};
    assert_ptr_equal(mr_kind_find("test_sphere"), &test_sphere_kind);
    assert_ptr_equal(mr_kind_at(mr_kind_count() - 1), &test_sphere_kind);
    assert_int_equal(mr_kind_register(&test_sphere_kind, &err), MR_ERR_CONFLICT);
    mr_kind nameless = test_sphere_kind;
    nameless.name = "";
    assert_int_equal(mr_kind_register(&nameless, &err), MR_ERR_INVALID);
    mr_kind no_rewind = test_sphere_kind;
    no_rewind.name = "test_sphere_2";
    no_rewind.rewind = NULL; /* SEQUENTIAL needs it */
    assert_int_equal(mr_kind_register(&no_rewind, &err), MR_ERR_INVALID);
    assert_null(mr_kind_find("test_sphere_2"));
    /* a job may hold every kind: their stats fields must fit one frame */
    mr_kind wordy = test_sphere_kind;
    wordy.name = "test_sphere_3";
    wordy.stat_count = MR_FRAME_EXTRAS_MAX;
    assert_int_equal(mr_kind_register(&wordy, &err), MR_ERR_LIMIT);
    assert_null(mr_kind_find("test_sphere_3"));
    size_t fields = 0;
    for (size_t i = 0; i < mr_kind_count(); i++)
        fields += mr_kind_stat_count(mr_kind_at(i));
    assert_true(fields + MR_FRAME_EXTRAS_CALLER <= MR_FRAME_EXTRAS_MAX);
}

static void test_parse(void **state)
{
    (void)state;
    mr_job *job = NULL;
    mr_job_error e = {0};
    assert_int_equal(parse_object("{\"asset\": \"a\", \"kind\": \"test_sphere\"}", &job, &e), MR_OK);
    assert_ptr_equal(job->objects[0].kind, &test_sphere_kind);
    assert_float_equal(((test_sphere_params *)job->objects[0].params)->radius, 1.0f, 0);
    mr_job_free(job);
    assert_int_equal(parse_object("{\"asset\": \"a\", \"kind\": \"test_sphere\","
                                  " \"test_sphere\": {\"radius\": 0.25}}",
                                  &job, &e),
                     MR_OK);
    assert_float_equal(((test_sphere_params *)job->objects[0].params)->radius, 0.25f, 0);
    mr_job_free(job);

    expect_error("{\"asset\": \"a\", \"kind\": \"test_sphere\", \"test_sphere\": {\"radius\": 0}}",
                 "/objects/0/test_sphere/radius", "expected a number in (0, 100], got 0");
    expect_error("{\"asset\": \"a\", \"kind\": \"test_sphere\", \"test_sphere\": {\"radius\": \"1\"}}",
                 "/objects/0/test_sphere/radius", "got \"1\"");
    expect_error("{\"asset\": \"a\", \"kind\": \"test_sphere\", \"test_sphere\": {\"r\": 1}}",
                 "/objects/0/test_sphere/r", "unknown field; expected one of: radius");
    expect_error("{\"asset\": \"a\", \"kind\": \"test_sphere\", \"test_sphere\": [1]}",
                 "/objects/0/test_sphere", "expected an object of test_sphere parameters");
    expect_error("{\"asset\": \"a\", \"test_sphere\": {\"radius\": 1}}", "/objects/0/test_sphere",
                 "\"test_sphere\" parameters need \"kind\": \"test_sphere\"");
    expect_error("{\"asset\": \"a\", \"kind\": \"sphere\"}", "/objects/0/kind",
                 "one of: \"mesh\", \"dmm\", \"svo\", \"displaced\", \"springmass\", \"test_sphere\"");
    expect_error("{\"asset\": \"a\", \"kind\": \"test_sphere\", \"radius\": 1}", "/objects/0/radius",
                 "test_sphere, transform");
}

static void test_schema(void **state)
{
    (void)state;
    mr_error err = {0};
    cJSON *block = mr_schema_kind_block(&test_sphere_kind, &err);
    assert_non_null(block);
    const cJSON *radius = cJSON_GetObjectItem(cJSON_GetObjectItem(block, "properties"), "radius");
    assert_non_null(radius);
    assert_string_equal(cJSON_GetObjectItem(radius, "type")->valuestring, "number");
    assert_true(cJSON_GetObjectItem(radius, "exclusiveMinimum")->valuedouble == 0);
    assert_true(cJSON_GetObjectItem(radius, "maximum")->valuedouble == 100);
    assert_true(cJSON_GetObjectItem(radius, "default")->valuedouble == 1);
    assert_true(cJSON_IsFalse(cJSON_GetObjectItem(block, "additionalProperties")));
    cJSON_Delete(block);

    cJSON *doc = cJSON_Parse("{\"$defs\": {\"kind_gone\": {}, \"object\": {\"properties\": "
                             "{\"kind\": {}, \"gone\": {}, \"transform\": {}}, "
                             "\"dependentSchemas\": {\"gone\": {}}}}}");
    assert_int_equal(mr_schema_update(doc, &err), MR_OK);
    const cJSON *defs = cJSON_GetObjectItem(doc, "$defs");
    const cJSON *props = cJSON_GetObjectItem(cJSON_GetObjectItem(defs, "object"), "properties");
    assert_non_null(cJSON_GetObjectItem(defs, "kind_test_sphere"));
    assert_null(cJSON_GetObjectItem(defs, "kind_gone")); /* a stale kind's block goes */
    assert_null(cJSON_GetObjectItem(props, "gone"));
    const cJSON *ref = cJSON_GetObjectItem(props, "test_sphere");
    assert_string_equal(cJSON_GetObjectItem(ref, "$ref")->valuestring, "#/$defs/kind_test_sphere");
    assert_string_equal(ref->next->string, "transform"); /* blocks sit before "transform" */
    const cJSON *kinds = cJSON_GetObjectItem(cJSON_GetObjectItem(props, "kind"), "enum");
    assert_int_equal(cJSON_GetArraySize(kinds), (int)mr_kind_count());
    assert_string_equal(cJSON_GetArrayItem(kinds, (int)mr_kind_count() - 1)->valuestring,
                        "test_sphere");
    cJSON_Delete(doc);

    /* its stats fields are in the OpenAPI document's FrameStats */
    char *yaml = mr_stats_openapi_block();
    assert_non_null(yaml);
    assert_non_null(strstr(yaml, "        test_sphere_steps: { type: number, description: \"Kind "
                                 "test_sphere, summed over its objects: updates applied"));
    free(yaml);
}

/* ---- rendering */

typedef struct captured {
    size_t count;
    float *rgba[16];
    mr_frame_stats stats[16];
} captured;

static size_t film_floats(const mr_film *f) { return (size_t)f->width * (size_t)f->height; }

static float *copy_film(const mr_film *f)
{
    size_t n = film_floats(f);
    float *c = malloc(n * 5 * sizeof(float));
    assert_non_null(c);
    memcpy(c, f->r, n * sizeof(float));
    memcpy(c + n, f->g, n * sizeof(float));
    memcpy(c + 2 * n, f->b, n * sizeof(float));
    memcpy(c + 3 * n, f->a, n * sizeof(float));
    memcpy(c + 4 * n, f->z, n * sizeof(float));
    return c;
}

static int capture_frame(void *user, size_t index, const mr_film *film, mr_frame_stats *stats,
                         mr_error *err)
{
    captured *c = user;
    assert_true(index < 16);
    c->rgba[index] = copy_film(film);
    c->stats[index] = *stats;
    c->count++;
    return MR_OK;
}

static mr_job *sphere_job(void)
{
    mr_job *job = NULL;
    mr_job_error e = {0};
    int rc = parse_object("{\"asset\": \"a\", \"kind\": \"test_sphere\", \"test_sphere\": "
                          "{\"radius\": 0.8}}",
                          &job, &e);
    if (rc < 0)
        fail_msg("%s: %s", e.pointer, e.message);
    assert_int_equal(job->frame_count, 7);
    return job;
}

static void make_temp_dir(char *dir, size_t n)
{
    snprintf(dir, n, "/tmp/mr-kind-plugin-XXXXXX");
    assert_non_null(mkdtemp(dir));
}

static void remove_tree(const char *dir)
{
    char cmd[600];
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", dir);
    assert_int_equal(system(cmd), 0);
}

static int count_files(const char *dir, const char *ext)
{
    DIR *d = opendir(dir);
    int n = 0;
    if (!d)
        return -1;
    for (struct dirent *e; (e = readdir(d));) {
        size_t len = strlen(e->d_name), el = strlen(ext);
        n += len > el && strcmp(e->d_name + len - el, ext) == 0;
    }
    closedir(d);
    return n;
}

static void free_captured(captured *c)
{
    for (size_t i = 0; i < 16; i++)
        free(c->rgba[i]);
}

/* The worker renders every frame in order; its derived data lands in
 * ROOT/test_sphere/ and the next job reads it back (the stats say so). */
static void test_worker_and_cache(void **state)
{
    (void)state;
    char root[64], path[600];
    make_temp_dir(root, sizeof root);
    mr_device *dev = NULL;
    mr_error err = {0};
    assert_int_equal(mr_device_new(2, &dev, &err), MR_OK);
    mr_job *job = sphere_job();
    for (int run = 0; run < 2; run++) {
        captured c = {0};
        mr_job_stats stats = {0};
        mr_worker_io io = {.user = &c, .frame_done = capture_frame, .cache_dir = root};
        if (mr_worker_run(dev, job, &io, &stats, &err) < 0)
            fail_msg("run %d: %s", run, err.msg);
        assert_int_equal(c.count, 7);
        /* one file, <root>/test_sphere/<key>.sphere */
        snprintf(path, sizeof path, "%s/test_sphere", root);
        assert_int_equal(count_files(path, ".sphere"), 1);
        /* the sphere is in the frame: the centre pixel is hit */
        float alpha = c.rgba[3][3 * 48 * 32 + 16 * 48 + 24];
        assert_true(alpha > 0.99f);
        /* its stats fields: the second job read the sphere from the cache,
         * in order every frame is one more step */
        for (size_t i = 0; i < 7; i++) {
            const mr_frame_stats *f = &c.stats[i];
            assert_int_equal(f->extra_count, 3);
            assert_string_equal(f->extras[0].name, "test_sphere_scale");
            assert_true(f->extras[1].value == (double)(i + 1));
            /* a creation figure (once): on the first frame only */
            assert_true(f->extras[2].value == (run == 1 && i == 0 ? 1.0 : 0.0));
        }
        /* and in stats.json, from the worker's own figures */
        char *json = NULL;
        assert_int_equal(mr_stats_to_json(job, &stats, 0, &json, &err), MR_OK);
        cJSON *doc = cJSON_Parse(json);
        const cJSON *last = cJSON_GetArrayItem(cJSON_GetObjectItem(doc, "frames"), 6);
        assert_true(cJSON_GetObjectItem(last, "test_sphere_steps")->valuedouble == 7);
        const cJSON *first = cJSON_GetArrayItem(cJSON_GetObjectItem(doc, "frames"), 0);
        assert_true(cJSON_GetObjectItem(first, "test_sphere_cache_hit")->valuedouble == run);
        assert_true(cJSON_GetObjectItem(last, "test_sphere_cache_hit")->valuedouble == 0);
        assert_true(cJSON_GetObjectItem(last, "test_sphere_scale")->valuedouble > 0);
        cJSON_Delete(doc);
        free(json);
        free_captured(&c);
        mr_job_stats_free(&stats);
    }
    mr_job_free(job);
    mr_device_free(dev);
    remove_tree(root);
}

/* A job's objects of one kind add up per field as the field says: the
 * simulated scale (the same for both spheres) is the largest, the steps
 * are summed. */
static void test_stats_combine(void **state)
{
    (void)state;
    mr_device *dev = NULL;
    mr_error err = {0};
    assert_int_equal(mr_device_new(2, &dev, &err), MR_OK);
    mr_job *job = NULL;
    mr_job_error e = {0};
    if (parse_object("{\"asset\": \"a\", \"kind\": \"test_sphere\", \"test_sphere\": "
                     "{\"radius\": 0.8}}, {\"asset\": \"a\", \"kind\": \"test_sphere\", "
                     "\"test_sphere\": {\"radius\": 0.3}}",
                     &job, &e) < 0)
        fail_msg("%s: %s", e.pointer, e.message);
    const mr_asset *asset = NULL;
    mr_asset *a = NULL;
    assert_int_equal(mr_asset_load(BOX, &a, &err), MR_OK);
    asset = a;
    mr_job *one = sphere_job();
    mr_renderer *r = NULL, *r1 = NULL;
    assert_int_equal(mr_renderer_new(dev, job, (mr_asset *const *)&asset, NULL, &r, &err), MR_OK);
    assert_int_equal(mr_renderer_new(dev, one, (mr_asset *const *)&asset, NULL, &r1, &err), MR_OK);
    mr_film *film = NULL;
    assert_int_equal(mr_film_new(48, 32, &film, &err), MR_OK);
    mr_frame_stats st, st1;
    for (size_t i = 0; i < 3; i++) {
        assert_int_equal(mr_renderer_render(r, i, film, &st, &err), MR_OK);
        assert_int_equal(mr_renderer_render(r1, i, film, &st1, &err), MR_OK);
        assert_int_equal(st.extra_count, 3);
        assert_true(st1.extras[0].value != 0);
        assert_true(st.extras[0].value == st1.extras[0].value); /* the largest, not the sum */
        assert_true(st.extras[1].value == 2.0 * st1.extras[1].value);
    }
    mr_film_free(film);
    mr_renderer_free(r);
    mr_renderer_free(r1);
    mr_asset_free(a);
    mr_job_free(job);
    mr_job_free(one);
    mr_device_free(dev);
}

static bool from_frame_4(void *user, size_t index) { return index >= 4; }

/* Frame n of a SEQUENTIAL kind is the same whether frames 0..n-1 were just
 * rendered, skipped (a job resumed at n), or rendered after n (a retry). */
static void test_frame_order(void **state)
{
    (void)state;
    mr_device *dev = NULL;
    mr_error err = {0};
    assert_int_equal(mr_device_new(2, &dev, &err), MR_OK);
    mr_job *job = sphere_job();
    captured in_order = {0};
    mr_job_stats stats = {0};
    mr_worker_io io = {.user = &in_order, .frame_done = capture_frame};
    assert_int_equal(mr_worker_run(dev, job, &io, &stats, &err), MR_OK);
    mr_job_stats_free(&stats);
    size_t n = 48 * 32 * 5 * sizeof(float);
    /* the state really changes from frame to frame */
    assert_true(memcmp(in_order.rgba[1], in_order.rgba[5], n) != 0);

    /* the worker resuming a job at frame 4 (the daemon after a crash skips
     * the frames already done, through io.wanted) */
    captured resumed = {0};
    mr_worker_io resume = {.user = &resumed, .frame_done = capture_frame, .wanted = from_frame_4};
    assert_int_equal(mr_worker_run(dev, job, &resume, &stats, &err), MR_OK);
    mr_job_stats_free(&stats);
    assert_int_equal(resumed.count, 3);
    for (size_t i = 4; i < 7; i++) {
        if (memcmp(resumed.rgba[i], in_order.rgba[i], n) != 0)
            fail_msg("frame %zu of a job resumed at frame 4 differs from the in-order run", i);
        assert_true(resumed.stats[i].extras[1].value == (double)(i + 1)); /* replayed steps */
    }
    free_captured(&resumed);

    const mr_asset *asset = NULL;
    mr_asset *a = NULL;
    assert_int_equal(mr_asset_load(BOX, &a, &err), MR_OK);
    asset = a;
    mr_renderer *r = NULL;
    assert_int_equal(mr_renderer_new(dev, job, (mr_asset *const *)&asset, NULL, &r, &err), MR_OK);
    mr_film *film = NULL;
    assert_int_equal(mr_film_new(48, 32, &film, &err), MR_OK);
    mr_frame_stats st;
    const size_t order[] = {5, 2, 2, 6, 0, 3};
    for (size_t k = 0; k < sizeof order / sizeof order[0]; k++) {
        size_t i = order[k];
        assert_int_equal(mr_renderer_render(r, i, film, &st, &err), MR_OK);
        float *got = copy_film(film);
        if (memcmp(got, in_order.rgba[i], n) != 0)
            fail_msg("frame %zu rendered out of order (step %zu) differs from the in-order run", i,
                     k);
        free(got);
    }
    mr_film_free(film);
    mr_renderer_free(r);
    mr_asset_free(a);
    free_captured(&in_order);
    mr_job_free(job);
    mr_device_free(dev);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_registry),
        cmocka_unit_test(test_parse),
        cmocka_unit_test(test_schema),
        cmocka_unit_test(test_worker_and_cache),
        cmocka_unit_test(test_frame_order),
        cmocka_unit_test(test_stats_combine),
    };
    return cmocka_run_group_tests(tests, setup, NULL);
}
