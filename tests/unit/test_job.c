/*
 * test_job.c - the job JSON parser (server/job_json.c) and mr_job_free().
 *
 * (1) A table of malformed jobs, each a small edit of one valid base job,
 *     with the exact JSON pointer and a piece of the message it must give.
 * (2) Valid jobs and the exact struct values they must produce (defaults,
 *     frame times, radians, TRS matrices, normalised directions, ...).
 * (3) Caps that need large generated inputs, raw NUL bytes, nesting.
 * (4) Every examples/NAME.json (under $MR_SOURCE_DIR, else the current
 *     directory) must parse.
 *
 * Inputs are handed to the parser in exactly-sized heap buffers without a
 * NUL terminator, so an over-read shows up under AddressSanitizer, and
 * every failing case runs through the parser's cleanup path, so leaks show
 * up under LeakSanitizer.
 *
 * Tolerances: values the parser computes in double and stores as float are
 * compared with the same double computation cast to float: exact. Values the
 * test derives another way (quaternion to matrix by mr_mat4_from_trs on a
 * separately normalised quaternion, float normalisation) allow 1e-6
 * absolute, a few float ulps on O(1) numbers.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <dirent.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "../support/bad_jobs.h"
#include "job_json.h"
#include "kinds/dmm/dmm_kind.h"
#include "kinds/mesh/mesh_kind.h"
#include "kinds/svo/svo_kind.h"

#define PI 3.14159265358979323846

/* An object's parameter block, as its kind's struct. */
static const mr_dmm_params *dmm_of(const mr_job *job, size_t i)
{
    assert_ptr_equal(job->objects[i].kind, &mr_kind_dmm);
    assert_non_null(job->objects[i].params);
    return (const mr_dmm_params *)job->objects[i].params;
}

static const mr_svo_params *svo_of(const mr_job *job, size_t i)
{
    assert_ptr_equal(job->objects[i].kind, &mr_kind_svo);
    assert_non_null(job->objects[i].params);
    return (const mr_svo_params *)job->objects[i].params;
}

/* Job text is written with single quotes (JSON itself never uses them) and
 * turned into double quotes here, to keep the table readable. */
static char *dq(const char *s, size_t *len)
{
    size_t n = strlen(s);
    char *d = malloc(n ? n : 1);
    assert_non_null(d);
    for (size_t i = 0; i < n; i++)
        d[i] = s[i] == '\'' ? '"' : s[i];
    *len = n;
    return d;
}

/* Parses raw bytes from an unterminated exact-size copy. */
static int parse_bytes(const char *bytes, size_t n, mr_job **job, mr_job_error *err)
{
    char *buf = malloc(n ? n : 1);
    assert_non_null(buf);
    memcpy(buf, bytes, n);
    int rc = mr_job_parse(buf, n, job, err);
    free(buf);
    return rc;
}

static int parse_q(const char *quoted, mr_job **job, mr_job_error *err)
{
    size_t n;
    char *buf = dq(quoted, &n);
    int rc = mr_job_parse(buf, n, job, err);
    free(buf);
    return rc;
}

static mr_job *parse_ok(const char *quoted)
{
    mr_job *job = NULL;
    mr_job_error err;
    int rc = parse_q(quoted, &job, &err);
    if (rc != MR_OK)
        fail_msg("expected success, got %s at '%s': %s", mr_err_name(rc), err.pointer, err.message);
    assert_non_null(job);
    return job;
}


static void test_malformed_table(void **state)
{
    (void)state;
    size_t failures = 0, n = sizeof BAD / sizeof BAD[0];
    assert_true(n >= 40);
    for (size_t i = 0; i < n; i++) {
        mr_job *job = (mr_job *)&failures; /* must be reset to NULL */
        mr_job_error err;
        int rc = parse_q(BAD[i].json, &job, &err);
        bool ok = rc == BAD[i].rc && job == NULL && strcmp(err.pointer, BAD[i].pointer) == 0 &&
                  strstr(err.message, BAD[i].msg) != NULL;
        if (!ok) {
            failures++;
            print_error("case %zu: %s\n  want %s '%s' ...%s...\n  got  %s '%s' %s\n", i,
                        BAD[i].json, mr_err_name(BAD[i].rc), BAD[i].pointer, BAD[i].msg,
                        mr_err_name(rc), err.pointer, err.message);
        }
        if (rc == MR_OK)
            mr_job_free(job);
    }
    assert_int_equal(failures, 0);
}

/* Collecting every problem (mr_job_check): over the whole table, the first
 * problem is mr_job_parse's (code, pointer, message) and it is marked
 * syntax exactly when the body is not one JSON text (the 400 of the HTTP
 * rule); a syntax problem is the only one. */
static void test_check_first_problem_and_syntax(void **state)
{
    (void)state;
    size_t failures = 0, n = sizeof BAD / sizeof BAD[0];
    for (size_t i = 0; i < n; i++) {
        size_t len;
        char *buf = dq(BAD[i].json, &len);
        mr_job *job = NULL;
        mr_job_error err;
        mr_job_problems all;
        int rc1 = mr_job_parse(buf, len, &job, &err);
        int rc2 = mr_job_check(buf, len, &job, &all);
        free(buf);
        bool syntax = bad_job_is_syntax(&BAD[i]);
        bool ok = rc1 == rc2 && job == NULL && all.count >= 1 &&
                  !strcmp(all.items[0].pointer, err.pointer) &&
                  !strcmp(all.items[0].message, err.message) && all.items[0].syntax == syntax &&
                  err.syntax == syntax && (!syntax || all.count == 1);
        if (!ok) {
            failures++;
            print_error("case %zu: %s\n  parse: %s '%s' %s (syntax %d)\n  check: %s, %zu problems, "
                        "first '%s' %s (syntax %d), table says syntax %d\n",
                        i, BAD[i].json, mr_err_name(rc1), err.pointer, err.message, err.syntax,
                        mr_err_name(rc2), all.count, all.items[0].pointer, all.items[0].message,
                        all.items[0].syntax, syntax);
        }
    }
    assert_int_equal(failures, 0);
}

/* Independent problems in one job are all reported, in reading order; what
 * depends on a part that failed is not reported again. */
static void test_check_collects_every_problem(void **state)
{
    (void)state;
    static const char job[] =
        "{'assets':{'m':{'path':'/a.gltf'},'b a d':{'path':'/b.gltf'}},"
        "'objects':[{'asset':'m','color':[1,2]},{'asset':'ghost'},"
        "{'asset':'m','kind':'voxels','svo':{'depth':99}},"
        "{'asset':'m','kind':'svo','svo':{'depth':99,'method':'bend'}}],"
        "'camera':{'path':[{'t':0,'position':[0,0,5],'target':[0,0,0],'yfov':500},"
        "{'t':1,'position':[0,0,5],'target':[0,0,0]}]},"
        "'frames':{'end':1},'output':{'width':0,'height':540,'samples':2000},'extra':1}";
    static const char *const pointers[] = {
        "/extra",                  /* unknown field */
        "/assets/b a d",           /* asset name */
        "/objects/0/color",        /* 2 numbers */
        "/objects/1/asset",        /* no such asset */
        "/objects/2/kind",         /* unknown kind: its block is not read */
        "/objects/3/svo/depth",    /* each field of a kind block */
        "/objects/3/svo/method",
        "/camera/path/0/yfov",     /* the next key's time is compared with nothing */
        "/output/width",
        "/output/samples",
    };
    size_t len;
    char *buf = dq(job, &len);
    mr_job *out = NULL;
    mr_job_problems all;
    int rc = mr_job_check(buf, len, &out, &all);
    free(buf);
    assert_int_equal(rc, MR_ERR_INVALID);
    assert_null(out);
    size_t want = sizeof pointers / sizeof *pointers;
    assert_int_equal(all.count, want);
    assert_int_equal(all.more, 0);
    for (size_t i = 0; i < want; i++)
        assert_string_equal(all.items[i].pointer, pointers[i]);
    /* without collecting, the first one only */
    mr_job_error err;
    buf = dq(job, &len);
    assert_int_equal(mr_job_parse(buf, len, &out, &err), MR_ERR_INVALID);
    free(buf);
    assert_string_equal(err.pointer, "/extra");
}

/* The brief's own example, word for word. */
static void test_message_format(void **state)
{
    (void)state;
    mr_job *job;
    mr_job_error err;
    assert_int_equal(parse_q("{" BASE ",'output':{'width':0}}", &job, &err), MR_ERR_INVALID);
    assert_string_equal(err.pointer, "/output/width");
    assert_string_equal(err.message, "expected an integer in 1..8192, got 0");
}

static void assert_mat_eq(const mr_mat4 *a, const mr_mat4 *b, float tol)
{
    for (int i = 0; i < 16; i++)
        if (!(fabsf(a->m[i] - b->m[i]) <= tol))
            fail_msg("matrix element %d: got %.9g, want %.9g (tol %g)", i, a->m[i], b->m[i], tol);
}

static mr_vec3 unit_d(double x, double y, double z)
{
    double l = sqrt(x * x + y * y + z * z);
    return mr_v3((float)(x / l), (float)(y / l), (float)(z / l));
}

static void assert_v3_eq(mr_vec3 a, mr_vec3 b)
{
    if (a.x != b.x || a.y != b.y || a.z != b.z)
        fail_msg("got (%.9g, %.9g, %.9g), want (%.9g, %.9g, %.9g)", a.x, a.y, a.z, b.x, b.y, b.z);
}

/* Every form of number RFC 8259 allows still reads, to the same value. */
static void test_rfc_numbers(void **state)
{
    (void)state;
    mr_job *job = parse_ok(WITH_OBJECT("{'asset':'m','color':[0.5,1e-1,-0],'transform':"
                                       "{'translation':[-0,2.5e0,1E+2]}}"));
    const mr_object_desc *o = &job->objects[0];
    assert_true(o->color.x == 0.5f && o->color.y == 0.1f && o->color.z == 0.0f);
    assert_true(o->transform.m[3] == 0.0f && o->transform.m[7] == 2.5f &&
                o->transform.m[11] == 100.0f);
    mr_job_free(job);
}

/* "tolerance_px": the job's is every object's default, an object's own (or
 * null: off) overrides it; absent everywhere: 0, off. */
static void test_tolerance(void **state)
{
    (void)state;
    mr_job *job = parse_ok("{" NO_OBJECTS ",'tolerance_px':2.5,'objects':[{'asset':'m'},"
                           "{'asset':'m','tolerance_px':0.25},{'asset':'m','tolerance_px':null}]}");
    assert_true(job->tolerance_px == 2.5);
    assert_true(job->objects[0].tolerance_px == 2.5);
    assert_true(job->objects[1].tolerance_px == 0.25);
    assert_true(job->objects[2].tolerance_px == 0);
    mr_job_free(job);
    job = parse_ok("{" NO_OBJECTS ",'objects':[{'asset':'m'},{'asset':'m','tolerance_px':1000}]}");
    assert_true(job->tolerance_px == 0 && job->objects[0].tolerance_px == 0);
    assert_true(job->objects[1].tolerance_px == MR_MAX_TOLERANCE_PX);
    mr_job_free(job);
}

static void test_defaults(void **state)
{
    (void)state;
    mr_job *job = parse_ok("{" BASE "}");
    mr_mat4 id = mr_mat4_identity();
    assert_string_equal(job->name, "job");
    assert_int_equal(job->asset_count, 1);
    assert_string_equal(job->assets[0].name, "m");
    assert_string_equal(job->assets[0].path, "/a.gltf");
    assert_int_equal(job->object_count, 1);
    const mr_object_desc *o = &job->objects[0];
    assert_string_equal(o->name, "object0");
    assert_int_equal(o->asset, 0);
    assert_ptr_equal(o->kind, &mr_kind_mesh);
    assert_null(o->params); /* the mesh kind takes no parameters */
    assert_mat_eq(&o->transform, &id, 0);
    assert_v3_eq(o->color, mr_v3(0.8f, 0.8f, 0.8f));
    assert_int_equal(o->pose_count, 0);
    assert_null(o->poses);
    /* Absent "lights": one default sun. */
    assert_int_equal(job->light_count, 1);
    assert_v3_eq(job->lights[0].direction, unit_d(-0.4, -1, -0.6));
    assert_v3_eq(job->lights[0].color, mr_v3(1, 1, 1));
    assert_v3_eq(job->ambient, mr_v3(0.15f, 0.15f, 0.15f));
    assert_v3_eq(job->background, mr_v3(0.1f, 0.1f, 0.12f));
    assert_true(job->background_alpha == 0.0f); /* transparent since issue 13 */
    /* Camera. */
    assert_int_equal(job->camera.source, MR_CAMERA_SOURCE_PATH);
    const mr_camera_path *p = &job->camera.path;
    assert_int_equal(p->interp, MR_INTERP_CATMULL_ROM);
    assert_v3_eq(p->up, mr_v3(0, 1, 0));
    assert_int_equal(p->key_count, 1);
    assert_true(p->keys[0].t == 0);
    assert_v3_eq(p->keys[0].position, mr_v3(0, 0, 5));
    assert_true(p->keys[0].has_target);
    assert_v3_eq(p->keys[0].target, mr_v3(0, 0, 0));
    assert_true(p->keys[0].yfov == (float)(45 * (PI / 180)));
    assert_null(job->camera.node_name);
    /* Frames: end 1 at 24 fps is 25 frames, i/24 s. */
    assert_true(job->fps == 24);
    assert_int_equal(job->frame_count, 25);
    for (size_t i = 0; i < 25; i++)
        assert_true(job->frame_times[i] == (double)i / 24);
    /* Output. */
    assert_int_equal(job->output.width, 640);
    assert_int_equal(job->output.height, 360);
    assert_int_equal(job->output.spp, 1);
    assert_true(job->output.shadows);
    assert_int_equal(job->output.seed, 0);
    assert_int_equal(job->output.exr.compression, MR_COMPRESSION_ZIP);
    assert_int_equal(job->output.exr.zip_level, 4);
    assert_int_equal(job->output.aovs, MR_AOV_RGBA | MR_AOV_Z | MR_AOV_N | MR_AOV_ID);
    assert_false(job->output.exr.half_normals);
    assert_int_equal(mr_output_crypto_ranks(&job->output), 0);
    mr_job_free(job);
}

static void test_full_job(void **state)
{
    (void)state;
    mr_job *job = parse_ok(
        "{'name':'caf\\u00e9 run','frames':{'fps':30,'times':[0,0.5,2]},"
        "'assets':{'hero':{'path':'/m/hero.gltf'},'set.v2-final_A':{'path':'/m/set.obj'}},"
        "'objects':["
        " {'name':'hero','asset':'hero','kind':'mesh','color':[1,0.5,0],"
        "  'transform':{'translation':[1,2,3],'rotation':[0,0,2,2],'scale':[2,3,4]},"
        "  'pose':[{'clip':'walk','speed':2,'offset':0.25,'loop':false},"
        "          {'clip':3,'time':1.25},"
        "          {'joints':{'arm/l':{'rotation':[0,1,0,0]},'h~ead':{'matrix':"
        "             [1,0,0,5, 0,1,0,6, 0,0,1,7, 0,0,0,1]}}}]},"
        " {'asset':'set.v2-final_A',"
        "  'transform':{'matrix':[0,-1,0,10, 1,0,0,20, 0,0,1,30, 0,0,0,1]},"
        "  'pose':{'clip':'idle'}},"
        " {'asset':'hero','transform':{'translation':[1e6,-1e6,1e6]}},"
        " {'asset':'hero','transform':{'scale':[1e-4,1e-4,1e-4]}}],"
        "'lights':[{'direction':[0,-2,0],'color':[1,0.5,0.25],'intensity':4},"
        "          {'direction':[1,1,1]}],"
        "'ambient':[0,0.25,1000],'background':{'color':[1,2,3],'alpha':1},"
        "'camera':{'interpolation':'linear','up':[0,0,2],'yfov':60,'path':["
        "  {'t':-1,'position':[0,0,5],'rotation':[0,0,0,3]},"
        "  {'t':0.5,'position':[1,0,5],'target':[0,0,0],'yfov':30}]},"
        "'output':{'width':1920,'height':1080,'samples':16,'shadows':false,'seed':4294967295,"
        "'compression':'piz','zip_level':9,'aovs':['cryptomatte','z','p'],'normals':'half'}}");
    assert_string_equal(job->name, "caf\xc3\xa9 run");
    assert_int_equal(job->asset_count, 2);
    assert_string_equal(job->assets[1].name, "set.v2-final_A");
    assert_string_equal(job->assets[1].path, "/m/set.obj");
    /* Explicit times. */
    assert_true(job->fps == 30);
    assert_int_equal(job->frame_count, 3);
    assert_true(job->frame_times[0] == 0 && job->frame_times[1] == 0.5 &&
                job->frame_times[2] == 2);
    assert_int_equal(job->object_count, 4);

    const mr_object_desc *o = &job->objects[0];
    assert_string_equal(o->name, "hero");
    assert_int_equal(o->asset, 0);
    assert_v3_eq(o->color, mr_v3(1, 0.5f, 0));
    const float h = (float)(1 / sqrt(2.0));
    mr_mat4 want = mr_mat4_from_trs(mr_v3(1, 2, 3), (mr_quat){0, 0, h, h}, mr_v3(2, 3, 4));
    assert_mat_eq(&o->transform, &want, 1e-6f);
    /* Rotation of 90 degrees about z, then scale: column 0 is (0, 2, 0). */
    assert_true(fabsf(o->transform.m[4] - 2) < 1e-6f && fabsf(o->transform.m[0]) < 1e-6f);
    assert_true(o->transform.m[3] == 1 && o->transform.m[7] == 2 && o->transform.m[11] == 3);
    /* Per-frame poses. */
    assert_int_equal(o->pose_count, 3);
    const mr_pose_desc *p = o->poses;
    assert_true(p[0].has_clip && !p[0].has_time && !p[0].loop);
    assert_string_equal(p[0].clip_name, "walk");
    assert_true(p[0].speed == 2 && p[0].offset == 0.25);
    assert_int_equal(p[0].joint_count, 0);
    assert_true(p[1].has_clip && p[1].has_time && p[1].loop);
    assert_null(p[1].clip_name);
    assert_int_equal(p[1].clip_index, 3);
    assert_true(p[1].time == 1.25 && p[1].speed == 1 && p[1].offset == 0);
    assert_false(p[2].has_clip);
    assert_null(p[2].clip_name);
    assert_int_equal(p[2].joint_count, 2);
    assert_string_equal(p[2].joints[0].joint, "arm/l");
    want = mr_mat4_from_trs(mr_v3(0, 0, 0), (mr_quat){0, 1, 0, 0}, mr_v3(1, 1, 1));
    assert_mat_eq(&p[2].joints[0].local, &want, 1e-6f);
    assert_string_equal(p[2].joints[1].joint, "h~ead");
    want = mr_mat4_identity();
    want.m[3] = 5, want.m[7] = 6, want.m[11] = 7;
    assert_mat_eq(&p[2].joints[1].local, &want, 0);

    o = &job->objects[1];
    assert_string_equal(o->name, "object1");
    assert_int_equal(o->asset, 1);
    const float rowm[16] = {0, -1, 0, 10, 1, 0, 0, 20, 0, 0, 1, 30, 0, 0, 0, 1};
    memcpy(want.m, rowm, sizeof rowm);
    assert_mat_eq(&o->transform, &want, 0);
    assert_int_equal(o->pose_count, 1);
    assert_string_equal(o->poses[0].clip_name, "idle");
    assert_true(o->poses[0].loop && o->poses[0].speed == 1);
    /* Large translations and small uniform scales are invertible transforms. */
    assert_true(job->objects[2].transform.m[3] == 1e6f);
    assert_true(job->objects[3].transform.m[0] == 1e-4f);

    /* Lights: unit direction, colour already times intensity. */
    assert_int_equal(job->light_count, 2);
    assert_v3_eq(job->lights[0].direction, mr_v3(0, -1, 0));
    assert_v3_eq(job->lights[0].color, mr_v3(4, 2, 1));
    assert_v3_eq(job->lights[1].direction, unit_d(1, 1, 1));
    assert_v3_eq(job->lights[1].color, mr_v3(1, 1, 1));
    assert_v3_eq(job->ambient, mr_v3(0, 0.25f, 1000));
    assert_v3_eq(job->background, mr_v3(1, 2, 3));
    assert_true(job->background_alpha == 1); /* an opaque background, asked for */

    /* Camera: radians, normalised rotation and up, per-key yfov default. */
    const mr_camera_path *cp = &job->camera.path;
    assert_int_equal(cp->interp, MR_INTERP_LINEAR);
    assert_v3_eq(cp->up, mr_v3(0, 0, 1));
    assert_int_equal(cp->key_count, 2);
    assert_true(cp->keys[0].t == -1 && !cp->keys[0].has_target);
    assert_true(cp->keys[0].rotation.w == 1 && cp->keys[0].rotation.x == 0);
    assert_true(cp->keys[0].yfov == (float)(60 * (PI / 180)));
    assert_true(cp->keys[1].t == 0.5 && cp->keys[1].has_target);
    assert_v3_eq(cp->keys[1].position, mr_v3(1, 0, 5));
    assert_true(cp->keys[1].yfov == (float)(30 * (PI / 180)));

    assert_int_equal(job->output.width, 1920);
    assert_int_equal(job->output.height, 1080);
    assert_int_equal(job->output.spp, 16);
    assert_false(job->output.shadows);
    assert_true(job->output.seed == 4294967295u);
    assert_int_equal(job->output.exr.compression, MR_COMPRESSION_PIZ);
    assert_int_equal(job->output.exr.zip_level, 9);
    assert_int_equal(job->output.aovs, MR_AOV_CRYPTOMATTE | MR_AOV_Z | MR_AOV_P);
    assert_true(job->output.exr.half_normals);
    assert_int_equal(mr_output_crypto_ranks(&job->output), 6); /* 16 samples, capped */
    mr_job_free(job);
}

/* The daemon's fields: uploaded assets by id, queue priority, retries. */
static void test_daemon_fields(void **state)
{
    (void)state;
    mr_job *job = parse_ok("{'assets':{'m':{'id':'" "0123456789abcdef0123456789abcdef0123456789abcdef0123456789abcdef" "'}},"
                           "'objects':[{'asset':'m'}]," CAMERA "," FRAMES ",'priority':-7,'max_retries':0,"
                           "'notify':'https://farm.example:8443/hooks/render?job=1'}");
    assert_null(job->assets[0].path);
    assert_string_equal(job->assets[0].id, "0123456789abcdef0123456789abcdef0123456789abcdef0123456789abcdef");
    assert_int_equal(job->priority, -7);
    assert_int_equal(job->max_retries, 0);
    assert_string_equal(job->notify, "https://farm.example:8443/hooks/render?job=1");
    mr_job_free(job);
    job = parse_ok("{" BASE "}");
    assert_null(job->notify);
    assert_null(job->assets[0].id);
    assert_int_equal(job->priority, 0);
    assert_int_equal(job->max_retries, 2);
    mr_job_free(job);
}

static void test_frame_ranges(void **state)
{
    (void)state;
    /* start 1, end 2 at 10 fps: 11 frames at 1 + i/10. */
    mr_job *job = parse_ok("{" NO_FRAMES ",'frames':{'fps':10,'start':1,'end':2}}");
    assert_int_equal(job->frame_count, 11);
    for (size_t i = 0; i < 11; i++)
        assert_true(job->frame_times[i] == 1 + (double)i / 10);
    mr_job_free(job);
    /* 0.29 * 100 is 28.999999999999996 in doubles: the 1e-9 keeps frame 29. */
    job = parse_ok("{" NO_FRAMES ",'frames':{'fps':100,'end':0.29}}");
    assert_int_equal(job->frame_count, 30);
    assert_true(job->frame_times[29] == 29.0 / 100);
    mr_job_free(job);
    /* A range that ends between frames stops at the last whole one. */
    job = parse_ok("{" NO_FRAMES ",'frames':{'fps':4,'start':-1,'end':0.6}}");
    assert_int_equal(job->frame_count, 7);
    assert_true(job->frame_times[0] == -1 && job->frame_times[6] == 0.5);
    mr_job_free(job);
    /* start == end is one frame. */
    job = parse_ok("{" NO_FRAMES ",'frames':{'start':3,'end':3}}");
    assert_int_equal(job->frame_count, 1);
    assert_true(job->frame_times[0] == 3);
    mr_job_free(job);
    /* Exactly MR_MAX_FRAMES is allowed. */
    job = parse_ok("{" NO_FRAMES ",'frames':{'fps':1000,'end':99.999}}");
    assert_int_equal(job->frame_count, MR_MAX_FRAMES);
    mr_job_free(job);
}

static void test_order_and_variants(void **state)
{
    (void)state;
    /* "objects" before "frames" in the text: the pose array still sees 2 frames. */
    mr_job *job = parse_ok("{'objects':[{'asset':'m','pose':[{'clip':0},{'clip':1}]}],"
                           "'frames':{'times':[5,1]}," ASSETS "," CAMERA "}");
    assert_int_equal(job->objects[0].pose_count, 2);
    assert_int_equal(job->objects[0].poses[1].clip_index, 1);
    assert_true(job->frame_times[0] == 5 && job->frame_times[1] == 1);
    mr_job_free(job);
    /* Raw UTF-8 (2- and 4-byte sequences) passes through unchanged. */
    job = parse_ok("{" BASE ",'name':'h\xc3\xa9ros \xf0\x9f\x8e\xac'}");
    assert_string_equal(job->name, "h\xc3\xa9ros \xf0\x9f\x8e\xac");
    mr_job_free(job);
    /* dmm objects: defaults, every field, base_triangles instead of a ratio. */
    job = parse_ok(WITH_OBJECT("{'asset':'m','kind':'dmm'},"
                               "{'asset':'m','kind':'dmm','dmm':{'level':5,'base_ratio':1,"
                               "'mode':'tessellated','intersector':'watertight'}},"
                               "{'asset':'m','kind':'dmm','dmm':{'level':0,'base_triangles':12}},"
                               "{'asset':'m','kind':'dmm','dmm':{'mode':'interpolated',"
                               "'normals':'matrix'}},"
                               "{'asset':'m','kind':'dmm','dmm':{'deformation':'interpolated'}},"
                               "{'asset':'m','kind':'dmm','dmm':{'mode':'base',"
                               "'deformation':'base','levels':'adaptive'}}"));
    assert_ptr_equal(job->objects[0].kind, &mr_kind_dmm);
    assert_int_equal(dmm_of(job, 0)->level, 3);
    assert_true(dmm_of(job, 0)->base_ratio == 0.25f);
    assert_int_equal(dmm_of(job, 0)->base_triangles, 0);
    assert_int_equal(dmm_of(job, 0)->mode, MR_DMM_TESSELLATED);
    assert_int_equal(dmm_of(job, 0)->intersector, MR_DMM_INTERSECT_EMBREE); /* the default */
    assert_int_equal(dmm_of(job, 1)->intersector, MR_DMM_INTERSECT_WATERTIGHT);
    assert_int_equal(dmm_of(job, 1)->level, 5);
    assert_true(dmm_of(job, 1)->base_ratio == 1.0f);
    assert_int_equal(dmm_of(job, 2)->level, 0);
    assert_int_equal(dmm_of(job, 2)->base_triangles, 12);
    assert_int_equal(dmm_of(job, 0)->deform, MR_DMM_DEFORM_BASE);
    assert_int_equal(dmm_of(job, 0)->normals, MR_DMM_NORMALS_SMOOTH); /* the default */
    /* mode interpolated implies its deformation */
    assert_int_equal(dmm_of(job, 3)->mode, MR_DMM_INTERPOLATED);
    assert_int_equal(dmm_of(job, 3)->deform, MR_DMM_DEFORM_INTERPOLATED);
    assert_int_equal(dmm_of(job, 3)->normals, MR_DMM_NORMALS_MATRIX);
    /* tessellated expands whichever deformation is asked for */
    assert_int_equal(dmm_of(job, 4)->mode, MR_DMM_TESSELLATED);
    assert_int_equal(dmm_of(job, 4)->deform, MR_DMM_DEFORM_INTERPOLATED);
    assert_int_equal(dmm_of(job, 5)->mode, MR_DMM_BASE);
    assert_int_equal(dmm_of(job, 5)->deform, MR_DMM_DEFORM_BASE);
    assert_int_equal(dmm_of(job, 5)->levels, MR_DMM_LEVELS_ADAPTIVE);
    assert_int_equal(dmm_of(job, 0)->levels, MR_DMM_LEVELS_UNIFORM);
    mr_job_free(job);
    /* svo objects: defaults and every field. */
    job = parse_ok(WITH_OBJECT("{'asset':'m','kind':'svo'},"
                               "{'asset':'m','kind':'svo','svo':{'depth':12,'method':'emit',"
                               "'delta':0.5,'cull':false,'skeleton':{'omega':0.05},"
                               "'instances':[{},{'transform':{'translation':[2,0,0]},"
                               "'pose':{'clip':0,'offset':0.5}}]}},"
                               "{'asset':'m','kind':'svo','svo':{'voxelize':'solid','depth':10,"
                               "'method':'resize','skeleton':true}}"));
    assert_ptr_equal(job->objects[0].kind, &mr_kind_svo);
    assert_int_equal(svo_of(job, 0)->depth, MR_SVO_DEFAULT_DEPTH);
    assert_int_equal(svo_of(job, 0)->method, MR_SVO_RIGID);
    assert_int_equal(svo_of(job, 0)->voxelize, MR_SVO_VOXELIZE_SURFACE);
    assert_true(svo_of(job, 0)->delta == MR_SVO_DEFAULT_DELTA);
    assert_true(svo_of(job, 0)->cull);
    assert_false(svo_of(job, 0)->skeleton);
    assert_int_equal(svo_of(job, 0)->instance_count, 0);
    const mr_svo_params *sd = svo_of(job, 1);
    assert_int_equal(sd->depth, 12);
    assert_int_equal(sd->method, MR_SVO_EMIT);
    assert_true(sd->delta == 0.5f);
    assert_false(sd->cull);
    assert_true(sd->skeleton);
    assert_true(sd->omega == 0.05f);
    assert_int_equal(sd->instance_count, 2);
    assert_false(sd->instances[0].has_pose);
    assert_true(sd->instances[0].transform.m[3] == 0.0f);
    assert_true(sd->instances[1].transform.m[3] == 2.0f);
    assert_true(sd->instances[1].has_pose);
    assert_int_equal(sd->instances[1].pose.clip_index, 0);
    assert_true(sd->instances[1].pose.offset == 0.5);
    assert_int_equal(svo_of(job, 2)->voxelize, MR_SVO_VOXELIZE_SOLID);
    assert_int_equal(svo_of(job, 2)->method, MR_SVO_RESIZE);
    assert_true(svo_of(job, 2)->skeleton);
    assert_true(svo_of(job, 2)->omega == 0.0f);
    mr_job_free(job);
    /* Present-but-empty lights means no lights. */
    job = parse_ok("{" BASE ",'lights':[]}");
    assert_int_equal(job->light_count, 0);
    assert_null(job->lights);
    mr_job_free(job);
}

static void test_asset_refine(void **state)
{
    (void)state;
    mr_job *job = parse_ok(
        "{" NO_ASSETS ",'assets':{"
        "'plain':{'path':'/a.x'},"
        "'m':{'path':'/a.x','refine':{}},"
        "'full':{'id':'0123456789abcdef0123456789abcdef0123456789abcdef0123456789abcdef',"
        "        'refine':{'seed':4294967295,'octaves':8,'frequency':0.5,'amplitude':0.125,"
        "                  'rounds':4}},"
        "'low':{'path':'/b.x','refine':{'rounds':0,'amplitude':1e9,'frequency':1e9,'octaves':0,"
        "                              'seed':0}}}}");
    assert_int_equal(job->asset_count, 4);
    const mr_asset_desc *a = job->assets;
    assert_false(a[0].refine);
    /* {} is every default */
    assert_true(a[1].refine);
    assert_int_equal(a[1].refine_params.rounds, MR_ASSET_REFINE_DEFAULT_ROUNDS);
    assert_int_equal(a[1].refine_params.rounds, 2);
    assert_true(a[1].refine_params.amplitude == 0.0f);
    assert_true(a[1].refine_params.frequency == 8.0f);
    assert_int_equal(a[1].refine_params.octaves, 3);
    assert_int_equal(a[1].refine_params.seed, 1);
    assert_int_equal(a[1].refine_params.threads, 0);
    /* every field, on an uploaded asset (exact binary fractions: no rounding) */
    assert_true(a[2].refine);
    assert_string_equal(a[2].id, "0123456789abcdef0123456789abcdef0123456789abcdef0123456789abcdef");
    assert_int_equal(a[2].refine_params.rounds, 4);
    assert_true(a[2].refine_params.amplitude == 0.125f);
    assert_true(a[2].refine_params.frequency == 0.5f);
    assert_int_equal(a[2].refine_params.octaves, 8);
    assert_int_equal(a[2].refine_params.seed, 4294967295u);
    /* the other ends of the ranges */
    assert_true(a[3].refine);
    assert_int_equal(a[3].refine_params.rounds, 0);
    assert_true(a[3].refine_params.amplitude == 1e9f);
    assert_true(a[3].refine_params.frequency == 1e9f);
    assert_int_equal(a[3].refine_params.octaves, 0);
    assert_int_equal(a[3].refine_params.seed, 0);
    mr_job_free(job);
}

static void test_camera_node(void **state)
{
    (void)state;
    mr_job *job = parse_ok("{" OBJECTS "," FRAMES ",'assets':{'m':{'path':'a'},'cams':"
                           "{'path':'c.gltf'}},'camera':{'node':{'asset':'cams','name':'Cam/1'}}}");
    assert_int_equal(job->camera.source, MR_CAMERA_SOURCE_NODE);
    assert_int_equal(job->camera.node_asset, 1);
    assert_string_equal(job->camera.node_name, "Cam/1");
    assert_int_equal(job->camera.path.key_count, 0);
    assert_null(job->camera.path.keys);
    mr_job_free(job);
}

static void expect_error(const char *bytes, size_t n, int rc_want, const char *ptr,
                         const char *msg)
{
    mr_job *job = NULL;
    mr_job_error err;
    int rc = parse_bytes(bytes, n, &job, &err);
    if (rc != rc_want || job != NULL || strcmp(err.pointer, ptr) != 0 || !strstr(err.message, msg))
        fail_msg("want %s '%s' ...%s..., got %s '%s' %s", mr_err_name(rc_want), ptr, msg,
                 mr_err_name(rc), err.pointer, err.message);
}

/* Builds "{<BASE minus one section>, <prefix> item,item,... <suffix>}" with
 * count copies of item, double-quoted. */
static char *repeat_job(const char *head, const char *item_fmt, size_t count, const char *tail,
                        size_t *len)
{
    size_t cap = strlen(head) + strlen(tail) + count * (strlen(item_fmt) + 24) + 8, n = 0;
    char *buf = malloc(cap);
    assert_non_null(buf);
    n += (size_t)snprintf(buf + n, cap - n, "%s", head);
    for (size_t i = 0; i < count; i++) {
        if (i)
            buf[n++] = ',';
        n += (size_t)snprintf(buf + n, cap - n, item_fmt, i, i);
    }
    n += (size_t)snprintf(buf + n, cap - n, "%s", tail);
    for (size_t i = 0; i < n; i++)
        if (buf[i] == '\'')
            buf[i] = '"';
    *len = n;
    return buf;
}

static void test_caps(void **state)
{
    (void)state;
    size_t n;
    char *s;

    s = repeat_job("{" BASE ",'lights':[", "{'direction':[0,-1,%zu]}", 65, "]}", &n);
    expect_error(s, n, MR_ERR_LIMIT, "/lights", "expected at most 64 lights, got 65");
    free(s);
    s = repeat_job("{" BASE ",'lights':[", "{'direction':[0,-1,%zu]}", 64, "]}", &n);
    {
        mr_job *job = NULL;
        assert_int_equal(parse_bytes(s, n, &job, NULL), MR_OK);
        assert_int_equal(job->light_count, 64);
        mr_job_free(job);
    }
    free(s);

    s = repeat_job("{" NO_FRAMES ",'frames':{'times':[", "%zu", MR_MAX_FRAMES + 1, "]}}", &n);
    expect_error(s, n, MR_ERR_LIMIT, "/frames", "expected at most 100000 frames, got 100001");
    free(s);

    s = repeat_job("{" NO_ASSETS ",'assets':{", "'a%zu':{'path':'p%zu'}", MR_MAX_ASSETS + 1, "}}",
                   &n);
    expect_error(s, n, MR_ERR_LIMIT, "/assets", "expected at most 256 assets, got 257");
    free(s);

    s = repeat_job("{" NO_OBJECTS ",'objects':[", "{'asset':'m','name':'o%zu%zu'}",
                   MR_MAX_OBJECTS + 1, "]}", &n);
    expect_error(s, n, MR_ERR_LIMIT, "/objects", "expected at most 1024 objects, got 1025");
    free(s);

    s = repeat_job("{" NO_OBJECTS ",'objects':[{'asset':'m','pose':{'joints':{", "'j%zu_%zu':{}",
                   MR_MAX_JOINT_OVERRIDES + 1, "}}}]}", &n);
    expect_error(s, n, MR_ERR_LIMIT, "/objects/0/pose/joints",
                 "expected at most 1024 joints, got 1025");
    free(s);

    s = repeat_job("{" NO_CAMERA ",'camera':{'path':[",
                   "{'t':%zu,'position':[0,0,%zu],'rotation':[0,0,0,1]}", MR_MAX_CAMERA_KEYS + 1,
                   "]}}", &n);
    expect_error(s, n, MR_ERR_LIMIT, "/camera/path",
                 "expected at most 10000 camera keys, got 10001");
    free(s);

    /* 10000 keys are fine and the times are checked all the way. */
    s = repeat_job("{" NO_CAMERA ",'camera':{'path':[",
                   "{'t':%zu,'position':[0,0,%zu],'rotation':[0,0,0,1]}", MR_MAX_CAMERA_KEYS,
                   "]}}", &n);
    {
        mr_job *job = NULL;
        assert_int_equal(parse_bytes(s, n, &job, NULL), MR_OK);
        assert_int_equal(job->camera.path.key_count, MR_MAX_CAMERA_KEYS);
        assert_true(job->camera.path.keys[9999].t == 9999);
        mr_job_free(job);
    }
    free(s);

    /* A duplicated allowed key repeated many times fails fast and exactly. */
    s = repeat_job("{" BASE ",'output':{", "'width':1%zu%zu", 100000, "}}", &n);
    expect_error(s, n, MR_ERR_INVALID, "/output/width", "duplicate field \"width\"");
    free(s);

    /* Over 16 MiB: refused before parsing (contents irrelevant). */
    n = (size_t)MR_JOB_MAX_BYTES + 1;
    s = malloc(n);
    assert_non_null(s);
    memset(s, ' ', n);
    {
        mr_job *job = NULL;
        mr_job_error err;
        assert_int_equal(mr_job_parse(s, n, &job, &err), MR_ERR_LIMIT);
        assert_null(job);
        assert_string_equal(err.pointer, "");
        assert_non_null(strstr(err.message, "at most 16777216 bytes"));
    }
    free(s);
}

static void test_raw_bytes(void **state)
{
    (void)state;
    size_t n;
    char *s = dq("{" BASE ",'name':'ab'}", &n);
    /* A raw NUL byte in a string, then one after the document. */
    char *nul = strstr(s, "ab");
    nul[1] = '\0';
    expect_error(s, n, MR_ERR_INVALID, "", "NUL byte at byte offset");
    free(s);
    s = dq("{" BASE "}", &n);
    char *t = malloc(n + 1);
    memcpy(t, s, n);
    t[n] = '\0';
    expect_error(t, n + 1, MR_ERR_INVALID, "", "NUL byte at byte offset");
    free(t);
    free(s);
    /* Nesting beyond cJSON's limit is malformed JSON, not a stack overflow. */
    n = 5000;
    s = malloc(n);
    memset(s, '[', n);
    expect_error(s, n, MR_ERR_INVALID, "", "malformed JSON");
    free(s);
    /* A pointer to a very long unknown key is cut, not overflowed. */
    {
        size_t klen = 3000, cap = klen + 600;
        char *big = malloc(cap);
        size_t m = (size_t)snprintf(big, cap, "{\"");
        memset(big + m, '~', klen);
        m += klen;
        m += (size_t)snprintf(big + m, cap - m, "\":1}");
        mr_job *job = NULL;
        mr_job_error err;
        assert_int_equal(parse_bytes(big, m, &job, &err), MR_ERR_INVALID);
        assert_true(strlen(err.pointer) < sizeof err.pointer);
        assert_true(strncmp(err.pointer, "/~0~0~0", 7) == 0);
        free(big);
    }
    /* NULL arguments. */
    mr_job *job = NULL;
    assert_int_equal(mr_job_parse(NULL, 5, &job, NULL), MR_ERR_INVALID);
    assert_int_equal(mr_job_parse("{}", 2, NULL, NULL), MR_ERR_INVALID);
    mr_job_free(NULL);
}

/* (3): every shipped example must parse. */
static void test_examples(void **state)
{
    (void)state;
    const char *root = getenv("MR_SOURCE_DIR");
    char dir[4096];
    snprintf(dir, sizeof dir, "%s/examples", root && *root ? root : ".");
    DIR *d = opendir(dir);
    if (!d) {
        print_message("no %s directory: nothing to check\n", dir);
        return;
    }
    struct dirent *e;
    size_t checked = 0, failures = 0;
    while ((e = readdir(d)) != NULL) {
        size_t l = strlen(e->d_name);
        if (l < 6 || strcmp(e->d_name + l - 5, ".json") != 0)
            continue;
        char path[8192];
        snprintf(path, sizeof path, "%s/%s", dir, e->d_name);
        FILE *f = fopen(path, "rb");
        assert_non_null(f);
        fseek(f, 0, SEEK_END);
        long size = ftell(f);
        fseek(f, 0, SEEK_SET);
        assert_true(size >= 0);
        char *buf = malloc((size_t)size + 1);
        assert_non_null(buf);
        assert_int_equal(fread(buf, 1, (size_t)size, f), (size_t)size);
        fclose(f);
        mr_job *job = NULL;
        mr_job_error err;
        int rc = parse_bytes(buf, (size_t)size, &job, &err);
        if (rc != MR_OK) {
            failures++;
            print_error("%s: %s at '%s': %s\n", path, mr_err_name(rc), err.pointer, err.message);
        }
        mr_job_free(job);
        free(buf);
        checked++;
    }
    closedir(d);
    print_message("checked %zu example job(s) in %s\n", checked, dir);
    assert_int_equal(failures, 0);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_malformed_table),
        cmocka_unit_test(test_check_first_problem_and_syntax),
        cmocka_unit_test(test_check_collects_every_problem), cmocka_unit_test(test_rfc_numbers), cmocka_unit_test(test_message_format),
        cmocka_unit_test(test_defaults),        cmocka_unit_test(test_full_job),
        cmocka_unit_test(test_frame_ranges),    cmocka_unit_test(test_order_and_variants),
        cmocka_unit_test(test_camera_node),     cmocka_unit_test(test_caps),
        cmocka_unit_test(test_raw_bytes),       cmocka_unit_test(test_examples),
        cmocka_unit_test(test_daemon_fields),
        cmocka_unit_test(test_tolerance),   cmocka_unit_test(test_asset_refine),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
