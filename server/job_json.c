/*
 * job_json.c - the job grammar: validates job JSON and turns it into the
 * structs of microray.h.
 *
 * Hand-written rather than driven by a JSON Schema library because the
 * daemon must answer with one precise JSON pointer and a short message, and
 * must refuse what a schema cannot express (strictly increasing key times,
 * pose arrays matching the frame count, invertible matrices, references to
 * asset names, caps with their own error code). schemas/job.schema.json
 * describes the same format for clients: change both together.
 *
 * The generic reading (pointers, messages, scalars, strings, keys, cJSON's
 * quirks) is json_reader.h; this file is the job grammar. Kind blocks are
 * read from each kind's parameter table (microray.h).
 *
 * Every value is stored into the (zeroed) job as soon as it is allocated, so
 * an error anywhere is cleaned up by the single mr_job_free() in
 * mr_job_parse().
 */
#include "job_json.h"

#include "json_reader.h"
#include "microray.h"

#include <float.h>
#include <limits.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define DEG_TO_RAD (3.14159265358979323846 / 180.0)
#define MAX_ASSET_NAME 64

#define COUNT_OF(a) (sizeof(a) / sizeof((a)[0]))

/* Positions, translations, scales and matrix entries. Far beyond any scene,
 * but well inside what Embree accepts for ray origins (about 1.8e19), so a
 * valid job can never trip Embree's ray validity checks. */
static const json_num_spec SPEC_COORD = {-1e9, 1e9, 0, "a number with |x| <= 1e9"};
/* Times on the job's timeline and clip times, seconds: differences of two
 * stay finite, so interpolation can never divide inf by inf. */
static const json_num_spec SPEC_TIME = {-1e9, 1e9, 0, "a time in seconds with |t| <= 1e9"};
static const json_num_spec SPEC_SPEED = {-1e6, 1e6, 0, NULL};
static const json_num_spec SPEC_COLOR = {0, 1000, 0, NULL};
static const json_num_spec SPEC_ALPHA = {0, 1, 0, NULL};
static const json_num_spec SPEC_FPS = {0, 1000, JSON_NUM_LO_OPEN, NULL};
static const json_num_spec SPEC_YFOV = {0.001, 179.9, 0, "a field of view in degrees in [0.001, 179.9]"};
static const json_num_spec SPEC_SIZE = {1, MR_MAX_RESOLUTION, JSON_NUM_INT, NULL};
static const json_num_spec SPEC_SPP = {1, MR_MAX_SPP, JSON_NUM_INT, NULL};
static const json_num_spec SPEC_SEED = {0, 4294967295.0, JSON_NUM_INT, NULL};
static const json_num_spec SPEC_ZIP = {1, 9, JSON_NUM_INT, NULL};

/* mr_mat4_inverse judges affine matrices by their 3x3 part alone, so large
 * translations are fine; a finite inverse guards against overflow. */
static bool affine_invertible(const mr_mat4 *m)
{
    mr_mat4 inv;
    return mr_mat4_inverse(m, &inv) && mr_mat4_is_finite(&inv);
}

static const char *const TRANSFORM_FIELDS[] = {"translation", "rotation", "scale", "matrix"};

/* {"translation","rotation","scale"} (any subset) or {"matrix": [16]}. */
static int get_transform(mr_json_ctx *c, const cJSON *v, mr_mat4 *out)
{
    TRY(json_want_object(c, v,
                    "a transform object ({\"translation\", \"rotation\", \"scale\"} or "
                    "{\"matrix\"})"));
    TRY(json_check_fields(c, v, TRANSFORM_FIELDS, COUNT_OF(TRANSFORM_FIELDS)));
    const cJSON *t = json_field(v, "translation"), *r = json_field(v, "rotation"), *s = json_field(v, "scale"),
                *m = json_field(v, "matrix");
    if (m && (t || r || s))
        return json_fail(c, MR_ERR_INVALID, "expected either \"matrix\" or "
                                       "\"translation\"/\"rotation\"/\"scale\", got both forms");
    if (m) {
        double d[16];
        AT_KEY(c, "matrix",
               json_get_numbers(c, m, 16, &SPEC_COORD, "an array of 16 numbers (row-major 4x4)", d));
        /* mr_mat4_point() ignores w, so a projective last row would be
         * silently dropped: refuse it. 1e-6 forgives exporters' rounding. */
        if (fabs(d[12]) > 1e-6 || fabs(d[13]) > 1e-6 || fabs(d[14]) > 1e-6 ||
            fabs(d[15] - 1) > 1e-6) {
            json_push_key(c, "matrix");
            return json_fail(c, MR_ERR_INVALID,
                        "expected an affine matrix with last row [0, 0, 0, 1], got [%.9g, %.9g, "
                        "%.9g, %.9g]",
                        d[12], d[13], d[14], d[15]);
        }
        for (int i = 0; i < 12; i++)
            out->m[i] = (float)d[i];
        out->m[12] = out->m[13] = out->m[14] = 0.0f;
        out->m[15] = 1.0f;
        if (!affine_invertible(out)) {
            json_push_key(c, "matrix");
            return json_fail(c, MR_ERR_INVALID, "expected an invertible matrix, got a singular one");
        }
        return MR_OK;
    }
    mr_vec3 tv = mr_v3(0, 0, 0), sv = mr_v3(1, 1, 1);
    mr_quat q = mr_quat_identity();
    if (t)
        AT_KEY(c, "translation", json_get_vec3(c, t, &SPEC_COORD, &tv));
    if (r)
        AT_KEY(c, "rotation", json_get_quat(c, r, &q));
    if (s) {
        double d[3];
        AT_KEY(c, "scale", json_get_numbers(c, s, 3, &SPEC_COORD, "an array of 3 numbers", d));
        for (size_t i = 0; i < 3; i++)
            if (d[i] == 0) {
                json_push_key(c, "scale");
                json_push_index(c, i);
                return json_fail(c, MR_ERR_INVALID, "expected a non-zero scale, got 0");
            }
        sv = mr_v3((float)d[0], (float)d[1], (float)d[2]);
    }
    *out = mr_mat4_from_trs(tv, q, sv);
    if (!mr_mat4_is_finite(out) || !affine_invertible(out))
        return json_fail(c, MR_ERR_INVALID,
                    "expected an invertible transform, got a numerically singular one "
                    "(scales too far apart or below float precision)");
    return MR_OK;
}

/* ------------------------------------------------------------------------ */
/* Top-level sections.                                                      */

static const char *const ASSET_FIELDS[] = {"path", "id", "refine"};
static const char *const REFINE_FIELDS[] = {"rounds", "amplitude", "frequency", "octaves", "seed"};
static const json_num_spec SPEC_REFINE_ROUNDS = {0, MR_ASSET_REFINE_MAX_ROUNDS, JSON_NUM_INT, NULL};
static const json_num_spec SPEC_REFINE_OCTAVES = {0, MR_ASSET_REFINE_MAX_OCTAVES, JSON_NUM_INT, NULL};
/* Mesh units, like coordinates (SPEC_COORD): |displacement| <= amplitude. */
static const json_num_spec SPEC_REFINE_AMPLITUDE = {0, 1e9, 0, "a number in 0..1e9 (mesh units)"};
static const json_num_spec SPEC_REFINE_FREQUENCY = {0, 1e9, JSON_NUM_LO_OPEN,
                                               "a number in (0, 1e9] (noise cells per mesh unit)"};

static bool asset_name_ok(const char *s)
{
    size_t n = 0;
    for (; s[n]; n++) {
        char ch = s[n];
        bool ok = (ch >= 'A' && ch <= 'Z') || (ch >= 'a' && ch <= 'z') ||
                  (ch >= '0' && ch <= '9') || ch == '_' || ch == '.' || ch == '-';
        if (!ok || n >= MAX_ASSET_NAME)
            return false;
    }
    return n > 0;
}

static bool hex64(const char *s)
{
    size_t n = 0;
    for (; s[n]; n++)
        if (!((s[n] >= '0' && s[n] <= '9') || (s[n] >= 'a' && s[n] <= 'f')) || n >= 64)
            return false;
    return n == 64;
}

/* An asset's "refine" parameters (microray.h), every field
 * optional. The frequency is stored as float and must stay positive there:
 * refine.h refuses a zero frequency with a non-zero amplitude, which would
 * otherwise only surface when the job runs. */
static int parse_refine(mr_json_ctx *c, const cJSON *v, mr_refine_params *p)
{
    TRY(json_want_object(c, v, "an object of refine parameters"));
    TRY(json_check_fields(c, v, REFINE_FIELDS, COUNT_OF(REFINE_FIELDS)));
    const cJSON *rounds = json_field(v, "rounds"), *amp = json_field(v, "amplitude"),
                *freq = json_field(v, "frequency"), *oct = json_field(v, "octaves"), *seed = json_field(v, "seed");
    double x;
    *p = (mr_refine_params){.rounds = MR_ASSET_REFINE_DEFAULT_ROUNDS,
                            .amplitude = 0.0f,
                            .frequency = MR_ASSET_REFINE_DEFAULT_FREQUENCY,
                            .octaves = MR_ASSET_REFINE_DEFAULT_OCTAVES,
                            .seed = MR_ASSET_REFINE_DEFAULT_SEED};
    if (rounds) {
        AT_KEY(c, "rounds", json_get_num(c, rounds, &SPEC_REFINE_ROUNDS, &x));
        p->rounds = (unsigned)x;
    }
    if (amp) {
        AT_KEY(c, "amplitude", json_get_num(c, amp, &SPEC_REFINE_AMPLITUDE, &x));
        p->amplitude = (float)x;
    }
    if (freq) {
        AT_KEY(c, "frequency", json_get_num(c, freq, &SPEC_REFINE_FREQUENCY, &x));
        if (!((float)x > 0.0f)) {
            json_push_key(c, "frequency");
            return json_fail(c, MR_ERR_INVALID,
                        "expected a number in (0, 1e9] that stays above 0 as a 32-bit float, "
                        "got %.15g",
                        x);
        }
        p->frequency = (float)x;
    }
    if (oct) {
        AT_KEY(c, "octaves", json_get_num(c, oct, &SPEC_REFINE_OCTAVES, &x));
        p->octaves = (unsigned)x;
    }
    if (seed) {
        AT_KEY(c, "seed", json_get_num(c, seed, &SPEC_SEED, &x));
        p->seed = (uint32_t)x;
    }
    return MR_OK;
}

/* One asset's description: a server-side {"path"} or the content hash of an
 * uploaded asset, {"id"} (exactly one of the two), optionally "refine"d. */
static int parse_asset(mr_json_ctx *c, const cJSON *v, mr_asset_desc *a)
{
    TRY(json_want_object(c, v, "an asset object {\"path\": ...} or {\"id\": ...}"));
    TRY(json_check_fields(c, v, ASSET_FIELDS, COUNT_OF(ASSET_FIELDS)));
    const cJSON *path = json_field(v, "path"), *id = json_field(v, "id"), *refine = json_field(v, "refine");
    if (!path == !id)
        return json_fail(c, MR_ERR_INVALID, "expected exactly one of \"path\" (a file on the server) or "
                                       "\"id\" (an uploaded asset's SHA-256)");
    if (path) {
        AT_KEY(c, "path", json_get_string(c, path, MR_MAX_PATH, &a->path));
    } else {
        AT_KEY(c, "id", json_get_string(c, id, 64, &a->id));
        if (!hex64(a->id)) {
            json_push_key(c, "id");
            return json_fail(c, MR_ERR_INVALID, "expected 64 lowercase hex digits (the SHA-256 POST /v1/assets returned)");
        }
    }
    if (refine) {
        AT_KEY(c, "refine", parse_refine(c, refine, &a->refine_params));
        a->refine = true;
    }
    return MR_OK;
}

static int parse_assets(mr_json_ctx *c, const cJSON *v, mr_job *job)
{
    TRY(json_want_object(c, v, "an object mapping asset names to assets"));
    size_t n = (size_t)cJSON_GetArraySize(v);
    if (n == 0)
        return json_fail(c, MR_ERR_INVALID, "expected 1..%d assets, got none", MR_MAX_ASSETS);
    if (n > MR_MAX_ASSETS)
        return json_fail(c, MR_ERR_LIMIT, "expected at most %d assets, got %zu", MR_MAX_ASSETS, n);
    GO_ON(c, json_check_unique_keys(c, v, n));
    job->assets = calloc(n, sizeof *job->assets);
    if (!job->assets)
        return json_fail_nomem(c);
    job->asset_count = n;
    size_t i = 0;
    for (const cJSON *a = v->child; a; a = a->next, i++) {
        const char *name = a->string ? a->string : "";
        size_t mark = json_push_key(c, name);
        if (!asset_name_ok(name)) {
            char q[128];
            json_quote(name, q, sizeof q);
            GO_ON_PART(c, mark, json_fail(c, MR_ERR_INVALID,
                                          "expected an asset name matching [A-Za-z0-9_.-]{1,%d}, got %s",
                                          MAX_ASSET_NAME, q));
            continue;
        }
        TRY(json_dup_string(c, name, &job->assets[i].name));
        GO_ON_PART(c, mark, parse_asset(c, a, &job->assets[i]));
    }
    return MR_OK;
}

static int find_asset(mr_json_ctx *c, const cJSON *v, const mr_job *job, size_t *out)
{
    if (!cJSON_IsString(v) || !v->valuestring)
        return json_fail_expected(c, "the name of an asset (a string)", v);
    for (size_t i = 0; i < job->asset_count; i++)
        if (job->assets[i].name && strcmp(job->assets[i].name, v->valuestring) == 0) {
            *out = i;
            return MR_OK;
        }
    return json_fail_expected(c, "the name of an entry in \"assets\"", v);
}

static const char *const FRAMES_FIELDS[] = {"fps", "start", "end", "times"};

static int parse_frames(mr_json_ctx *c, const cJSON *v, mr_job *job)
{
    TRY(json_want_object(c, v, "a frames object"));
    TRY(json_check_fields(c, v, FRAMES_FIELDS, COUNT_OF(FRAMES_FIELDS)));
    const cJSON *fps_v = json_field(v, "fps"), *start_v = json_field(v, "start"), *end_v = json_field(v, "end"),
                *times_v = json_field(v, "times");
    double fps = 24, start = 0, end = 0;
    if (fps_v)
        AT_KEY(c, "fps", json_get_num(c, fps_v, &SPEC_FPS, &fps));
    job->fps = fps;
    if (end_v && times_v) {
        json_push_key(c, "times");
        return json_fail(c, MR_ERR_INVALID, "\"times\" cannot be combined with \"end\"");
    }
    if (!end_v && !times_v)
        return json_fail(c, MR_ERR_INVALID, "missing required field: \"end\" or \"times\"");
    if (times_v) {
        if (start_v) {
            json_push_key(c, "start");
            return json_fail(c, MR_ERR_INVALID,
                        "\"start\" cannot be combined with \"times\" (list the times instead)");
        }
        if (!cJSON_IsArray(times_v) || cJSON_GetArraySize(times_v) == 0) {
            char expect[64];
            json_push_key(c, "times");
            snprintf(expect, sizeof expect, "an array of 1..%d times in seconds", MR_MAX_FRAMES);
            return json_fail_expected(c, expect, times_v);
        }
        size_t n = (size_t)cJSON_GetArraySize(times_v);
        if (n > MR_MAX_FRAMES)
            return json_fail(c, MR_ERR_LIMIT, "expected at most %d frames, got %zu", MR_MAX_FRAMES, n);
        job->frame_times = malloc(n * sizeof *job->frame_times);
        if (!job->frame_times)
            return json_fail_nomem(c);
        job->frame_count = n;
        size_t mark = json_push_key(c, "times"), i = 0;
        for (const cJSON *t = times_v->child; t; t = t->next, i++)
            AT_INDEX(c, i, json_get_num(c, t, &SPEC_TIME, &job->frame_times[i]));
        json_pop(c, mark);
        return MR_OK;
    }
    if (start_v)
        AT_KEY(c, "start", json_get_num(c, start_v, &SPEC_TIME, &start));
    json_num_spec end_spec = {start, SPEC_TIME.hi, 0, NULL};
    char expect[64];
    snprintf(expect, sizeof expect, "a time >= start (%.15g) and <= %g", start, SPEC_TIME.hi);
    end_spec.expect = expect;
    AT_KEY(c, "end", json_get_num(c, end_v, &end_spec, &end));
    /* The 1e-9 keeps (end - start) * fps that should be integral but rounds
     * to just below it from losing the last frame. The comparison is done in
     * double before any cast, so a huge span cannot overflow a size_t. */
    double span = (end - start) * fps + 1e-9;
    if (!(span < (double)MR_MAX_FRAMES)) {
        if (isfinite(span))
            return json_fail(c, MR_ERR_LIMIT, "expected at most %d frames, got %.15g", MR_MAX_FRAMES,
                        floor(span) + 1);
        return json_fail(c, MR_ERR_LIMIT, "expected at most %d frames, got too many to count",
                    MR_MAX_FRAMES);
    }
    size_t n = (size_t)floor(span) + 1;
    job->frame_times = malloc(n * sizeof *job->frame_times);
    if (!job->frame_times)
        return json_fail_nomem(c);
    job->frame_count = n;
    for (size_t i = 0; i < n; i++)
        job->frame_times[i] = start + (double)i / fps;
    return MR_OK;
}

static const char *const POSE_FIELDS[] = {"clip", "time", "speed", "offset", "loop", "joints"};

static int parse_joints(mr_json_ctx *c, const cJSON *v, mr_pose_desc *p)
{
    TRY(json_want_object(c, v, "an object mapping node names to transforms"));
    size_t n = (size_t)cJSON_GetArraySize(v);
    if (n == 0)
        return json_fail(c, MR_ERR_INVALID, "expected 1..%d joints, got none", MR_MAX_JOINT_OVERRIDES);
    if (n > MR_MAX_JOINT_OVERRIDES)
        return json_fail(c, MR_ERR_LIMIT, "expected at most %d joints, got %zu",
                    MR_MAX_JOINT_OVERRIDES, n);
    TRY(json_check_unique_keys(c, v, n));
    p->joints = calloc(n, sizeof *p->joints);
    if (!p->joints)
        return json_fail_nomem(c);
    p->joint_count = n;
    size_t i = 0;
    for (const cJSON *j = v->child; j; j = j->next, i++) {
        const char *name = j->string ? j->string : "";
        size_t mark = json_push_key(c, name);
        TRY(json_check_text(c, name, MR_MAX_NAME));
        TRY(json_dup_string(c, name, &p->joints[i].joint));
        TRY(get_transform(c, j, &p->joints[i].local));
        json_pop(c, mark);
    }
    return MR_OK;
}

static int parse_pose(mr_json_ctx *c, const cJSON *v, mr_pose_desc *p)
{
    TRY(json_want_object(c, v, "a pose object"));
    TRY(json_check_fields(c, v, POSE_FIELDS, COUNT_OF(POSE_FIELDS)));
    const cJSON *clip = json_field(v, "clip"), *time = json_field(v, "time"), *speed = json_field(v, "speed"),
                *offset = json_field(v, "offset"), *loop = json_field(v, "loop"),
                *joints = json_field(v, "joints");
    p->clip_index = -1;
    p->speed = 1;
    p->offset = 0;
    p->loop = true;
    if (!clip && !joints)
        return json_fail(c, MR_ERR_INVALID, "expected a pose with \"clip\" or \"joints\", got neither");
    if (!clip) {
        const char *const needs_clip[] = {"time", "speed", "offset", "loop"};
        for (size_t i = 0; i < COUNT_OF(needs_clip); i++)
            if (json_field(v, needs_clip[i])) {
                json_push_key(c, needs_clip[i]);
                return json_fail(c, MR_ERR_INVALID, "\"%s\" requires \"clip\"", needs_clip[i]);
            }
    }
    if (time && (speed || offset)) {
        json_push_key(c, speed ? "speed" : "offset");
        return json_fail(c, MR_ERR_INVALID, "\"%s\" cannot be combined with \"time\"",
                    speed ? "speed" : "offset");
    }
    if (clip) {
        size_t mark = json_push_key(c, "clip");
        if (cJSON_IsString(clip)) {
            TRY(json_get_string(c, clip, MR_MAX_NAME, &p->clip_name));
        } else {
            static const json_num_spec clip_index = {0, INT_MAX, JSON_NUM_INT,
                                                "a clip name (string) or index (integer >= 0)"};
            double d;
            TRY(json_get_num(c, clip, &clip_index, &d));
            p->clip_index = (int)d;
        }
        json_pop(c, mark);
        p->has_clip = true;
    }
    if (time) {
        AT_KEY(c, "time", json_get_num(c, time, &SPEC_TIME, &p->time));
        p->has_time = true;
    }
    if (speed)
        AT_KEY(c, "speed", json_get_num(c, speed, &SPEC_SPEED, &p->speed));
    if (offset)
        AT_KEY(c, "offset", json_get_num(c, offset, &SPEC_TIME, &p->offset));
    if (loop)
        AT_KEY(c, "loop", json_get_bool(c, loop, &p->loop));
    if (joints)
        AT_KEY(c, "joints", parse_joints(c, joints, p));
    return MR_OK;
}

static int parse_object_pose(mr_json_ctx *c, const cJSON *v, mr_object_desc *o, size_t frame_count)
{
    if (cJSON_IsObject(v)) {
        o->poses = calloc(1, sizeof *o->poses);
        if (!o->poses)
            return json_fail_nomem(c);
        o->pose_count = 1;
        return parse_pose(c, v, &o->poses[0]);
    }
    if (!cJSON_IsArray(v))
        return json_fail_expected(c, "a pose object or an array of pose objects (one per frame)", v);
    size_t n = (size_t)cJSON_GetArraySize(v);
    /* frame_count 0: "frames" failed (collecting every problem), so the
     * count is unknown and not compared */
    if (n != frame_count && frame_count > 0)
        return json_fail(c, MR_ERR_INVALID,
                    "expected one pose per frame (%zu frame%s), got an array of %zu pose%s",
                    frame_count, frame_count == 1 ? "" : "s", n, n == 1 ? "" : "s");
    o->poses = calloc(n, sizeof *o->poses);
    if (!o->poses)
        return json_fail_nomem(c);
    o->pose_count = n;
    size_t i = 0;
    for (const cJSON *p = v->child; p; p = p->next, i++)
        GO_ON_AT_INDEX(c, i, parse_pose(c, p, &o->poses[i]));
    return MR_OK;
}

/* ------------------------------------------------------------------------ */
/* A kind's parameter block, read from its table (microray.h).     */

#define PARAM_AT(values, off, type) ((type *)((char *)(values) + (off)))

static json_num_spec param_spec(const mr_param *p)
{
    unsigned flags = (p->type == MR_PARAM_INT ? JSON_NUM_INT : 0u) |
                     (p->type == MR_PARAM_NUMBER ? JSON_NUM_FLOAT : 0u) |
                     ((p->flags & MR_PARAM_LO_OPEN) ? JSON_NUM_LO_OPEN : 0u) |
                     ((p->flags & MR_PARAM_HI_OPEN) ? JSON_NUM_HI_OPEN : 0u);
    return (json_num_spec){p->lo, p->hi, flags, p->expect};
}

static int parse_params(mr_json_ctx *c, const cJSON *v, const mr_param_table *t,
                        const mr_job *job, void *values);

/* Fails at the hook's field with its message. */
static int fail_param(mr_json_ctx *c, const mr_param_error *pe)
{
    if (pe->field[0])
        json_push_key(c, pe->field);
    return json_fail(c, pe->code ? pe->code : MR_ERR_INVALID, "%s", pe->message);
}

static int parse_param_array(mr_json_ctx *c, const cJSON *v, const mr_param *p, const mr_job *job,
                             void *values)
{
    char expect[128];
    snprintf(expect, sizeof expect, "an array of 1..%zu %s", p->max_items, p->sub->plural);
    if (!cJSON_IsArray(v) || cJSON_GetArraySize(v) == 0)
        return json_fail_expected(c, expect, v);
    size_t n = (size_t)cJSON_GetArraySize(v);
    if (n > p->max_items)
        return json_fail(c, MR_ERR_LIMIT, "expected at most %zu %s, got %zu", p->max_items, p->field, n);
    char *items = calloc(n, p->sub->size);
    if (!items)
        return json_fail_nomem(c);
    *PARAM_AT(values, p->offset, char *) = items;
    *PARAM_AT(values, p->count_offset, size_t) = n;
    size_t i = 0;
    for (const cJSON *e = v->child; e; e = e->next, i++) {
        void *item = items + i * p->sub->size;
        mr_params_defaults(p->sub, item);
        GO_ON_AT_INDEX(c, i, parse_params(c, e, p->sub, job, item));
    }
    return MR_OK;
}

#define MR_PARAM_MAX_NUMBERS 16

static int parse_param(mr_json_ctx *c, const cJSON *v, const mr_param *p, const mr_job *job,
                       void *values)
{
    double x;
    int choice;
    json_num_spec spec = param_spec(p);
    switch (p->type) {
    case MR_PARAM_INT:
        TRY(json_get_num(c, v, &spec, &x));
        *PARAM_AT(values, p->offset, uint32_t) = (uint32_t)x;
        return MR_OK;
    case MR_PARAM_NUMBER:
        TRY(json_get_num(c, v, &spec, &x));
        *PARAM_AT(values, p->offset, float) = (float)x;
        return MR_OK;
    case MR_PARAM_BOOL:
        return json_get_bool(c, v, PARAM_AT(values, p->offset, bool));
    case MR_PARAM_ENUM: {
        char expect[256];
        if (p->expect)
            snprintf(expect, sizeof expect, "%s", p->expect);
        else
            json_choices_text(p->choices, p->choice_count, expect, sizeof expect);
        TRY(json_get_choice(c, v, p->choices, p->choice_count, expect, &choice));
        *PARAM_AT(values, p->offset, int) = choice;
        return MR_OK;
    }
    case MR_PARAM_FLAG_OBJECT:
        if (cJSON_IsBool(v)) {
            *PARAM_AT(values, p->offset, bool) = cJSON_IsTrue(v);
            return MR_OK;
        }
        TRY(parse_params(c, v, p->sub, job, values));
        *PARAM_AT(values, p->offset, bool) = true;
        return MR_OK;
    case MR_PARAM_ARRAY:
        return parse_param_array(c, v, p, job, values);
    case MR_PARAM_ASSET: {
        size_t index = 0;
        TRY(find_asset(c, v, job, &index));
        *PARAM_AT(values, p->offset, uint32_t) = (uint32_t)index + 1;
        return MR_OK;
    }
    case MR_PARAM_NUMBERS: {
        double xs[MR_PARAM_MAX_NUMBERS];
        char expect[64];
        size_t n = p->max_items < MR_PARAM_MAX_NUMBERS ? p->max_items : MR_PARAM_MAX_NUMBERS;
        snprintf(expect, sizeof expect, "an array of %zu numbers", n);
        TRY(json_get_numbers(c, v, n, &spec, expect, xs));
        for (size_t k = 0; k < n; k++)
            PARAM_AT(values, p->offset, float)[k] = (float)xs[k];
        return MR_OK;
    }
    case MR_PARAM_TRANSFORM:
        return get_transform(c, v, PARAM_AT(values, p->offset, mr_mat4));
    case MR_PARAM_POSE:
        TRY(parse_pose(c, v, PARAM_AT(values, p->offset, mr_pose_desc)));
        *PARAM_AT(values, p->present_offset, bool) = true;
        return MR_OK;
    case MR_PARAM_VEC3: {
        double d[3]; /* each number in the field's range, reported at its index */
        TRY(json_get_numbers(c, v, 3, &spec, "an array of 3 numbers", d));
        *PARAM_AT(values, p->offset, mr_vec3) = mr_v3((float)d[0], (float)d[1], (float)d[2]);
        return MR_OK;
    }
    case MR_PARAM_QUAT:
        return json_get_quat(c, v, PARAM_AT(values, p->offset, mr_quat));
    }
    return json_fail(c, MR_ERR_INVALID, "unsupported parameter type");
}

/* Reads object v into values (already holding the table's defaults):
 * known and unique keys, then every field in table order, each followed by
 * its after hook. */
static int parse_params(mr_json_ctx *c, const cJSON *v, const mr_param_table *t,
                        const mr_job *job, void *values)
{
    const char *names[MR_PARAM_MAX_FIELDS];
    const cJSON *fields[MR_PARAM_MAX_FIELDS];
    bool given[MR_PARAM_MAX_FIELDS];
    TRY(json_want_object(c, v, t->expect));
    for (size_t i = 0; i < t->count; i++)
        names[i] = t->params[i].field;
    GO_ON(c, json_check_fields(c, v, names, t->count));
    for (size_t i = 0; i < t->count; i++)
        given[i] = (fields[i] = json_field(v, names[i])) != NULL;
    for (size_t i = 0; i < t->count; i++) {
        const mr_param *p = &t->params[i];
        const cJSON *fv = fields[i];
        if (fv && p->conflicts) {
            int k = mr_param_index(t, p->conflicts);
            if (k >= 0 && given[k]) {
                GO_ON_AT_KEY(c, p->conflicts,
                             json_fail(c, MR_ERR_INVALID, "give either \"%s\" or \"%s\", not both",
                                       p->field, p->conflicts));
                continue;
            }
        }
        if (fv) {
            GO_ON_AT_KEY(c, p->field, parse_param(c, fv, p, job, values));
            if (c->failed) /* its checks would only repeat the problem */
                continue;
        }
        if (p->after) {
            mr_param_error pe = {0};
            if (p->after(values, given, &pe) < 0)
                GO_ON(c, fail_param(c, &pe));
        }
    }
    return MR_OK;
}

/* A kind's rules hold when its block is absent too: its after hooks run
 * over the defaults (nothing given), so a kind that needs a field (a
 * height source) says so at validation, pointing at the missing block. */
static int check_absent_block(mr_json_ctx *c, const mr_param_table *t, void *values)
{
    bool given[MR_PARAM_MAX_FIELDS] = {false};
    for (size_t i = 0; i < t->count; i++) {
        mr_param_error pe = {0};
        if (t->params[i].after && t->params[i].after(values, given, &pe) < 0)
            return fail_param(c, &pe);
    }
    return MR_OK;
}

static const char *const OBJECT_FIELDS_HEAD[] = {"name", "asset", "kind"};
static const char *const OBJECT_FIELDS_TAIL[] = {"transform", "color", "pose", "reference",
                                                  "tolerance_px"};

/* The keys an object may have: its own, and after "kind" each registered
 * kind's parameter block, in registry order. */
static size_t object_fields(const char **names, size_t cap)
{
    size_t n = 0;
    for (size_t i = 0; i < COUNT_OF(OBJECT_FIELDS_HEAD) && n < cap; i++)
        names[n++] = OBJECT_FIELDS_HEAD[i];
    for (size_t i = 0; i < mr_kind_count() && n < cap; i++)
        if (mr_kind_params(mr_kind_at(i)))
            names[n++] = mr_kind_name(mr_kind_at(i));
    for (size_t i = 0; i < COUNT_OF(OBJECT_FIELDS_TAIL) && n < cap; i++)
        names[n++] = OBJECT_FIELDS_TAIL[i];
    return n;
}

static int parse_kind(mr_json_ctx *c, const cJSON *v, const mr_kind **out)
{
    const char *names[32];
    size_t n = 0;
    for (size_t i = 0; i < mr_kind_count() && n < COUNT_OF(names); i++)
        names[n++] = mr_kind_name(mr_kind_at(i));
    char expect[512];
    json_choices_text(names, n, expect, sizeof expect);
    int choice = 0;
    TRY(json_get_choice(c, v, names, n, expect, &choice));
    *out = mr_kind_at((size_t)choice);
    return MR_OK;
}

/* "tolerance_px": a number of pixels, or null (off: the finest level). */
static int parse_tolerance(mr_json_ctx *c, const cJSON *v, double *out)
{
    static const json_num_spec spec = {0, MR_MAX_TOLERANCE_PX, JSON_NUM_LO_OPEN,
                                       "null or a number of pixels in (0, 1000]"};
    if (cJSON_IsNull(v)) {
        *out = 0;
        return MR_OK;
    }
    return json_get_num(c, v, &spec, out);
}

static int parse_object(mr_json_ctx *c, const cJSON *v, mr_job *job, size_t index, mr_object_desc *o)
{
    const char *fields[MR_PARAM_MAX_FIELDS];
    size_t field_count = object_fields(fields, COUNT_OF(fields));
    TRY(json_want_object(c, v, "an object description"));
    GO_ON(c, json_check_fields(c, v, fields, field_count));
    GO_ON(c, json_require(c, v, "asset"));
    const cJSON *name = json_field(v, "name"), *kind = json_field(v, "kind"), *xf = json_field(v, "transform"),
                *color = json_field(v, "color"), *pose = json_field(v, "pose"),
                *asset = json_field(v, "asset"), *reference = json_field(v, "reference"),
                *tolerance = json_field(v, "tolerance_px");
    if (name) {
        GO_ON_AT_KEY(c, "name", json_get_string(c, name, MR_MAX_NAME, &o->name));
    } else {
        char buf[32];
        snprintf(buf, sizeof buf, "object%zu", index);
        TRY(json_dup_string(c, buf, &o->name));
    }
    if (asset)
        GO_ON_AT_KEY(c, "asset", find_asset(c, asset, job, &o->asset));
    o->kind = mr_kind_at(0); /* the default kind: triangle meshes */
    bool kind_ok = true;
    if (kind) {
        GO_ON_AT_KEY(c, "kind", parse_kind(c, kind, &o->kind));
        kind_ok = !c->failed; /* else its block is not read: which kind's would it be? */
    }
    const mr_param_table *table = mr_kind_params(o->kind);
    if (table) {
        if (!(o->params = calloc(1, table->size)))
            return json_fail_nomem(c);
        mr_params_defaults(table, o->params);
    }
    for (size_t i = 0; i < mr_kind_count(); i++) {
        const mr_kind *k = mr_kind_at(i);
        const char *kname = mr_kind_name(k);
        const cJSON *block = mr_kind_params(k) ? json_field(v, kname) : NULL;
        if (!block || !kind_ok)
            continue;
        if (k != o->kind) {
            GO_ON_AT_KEY(c, kname,
                         json_fail(c, MR_ERR_INVALID, "\"%s\" parameters need \"kind\": \"%s\"", kname,
                                   kname));
            continue;
        }
        GO_ON_AT_KEY(c, kname, parse_params(c, block, mr_kind_params(k), job, o->params));
    }
    if (table && !json_field(v, mr_kind_name(o->kind)))
        AT_KEY(c, mr_kind_name(o->kind), check_absent_block(c, table, o->params));
    o->transform = mr_mat4_identity();
    if (xf)
        GO_ON_AT_KEY(c, "transform", get_transform(c, xf, &o->transform));
    o->color = mr_v3(0.8f, 0.8f, 0.8f);
    if (color)
        GO_ON_AT_KEY(c, "color", json_get_vec3(c, color, &SPEC_COLOR, &o->color));
    if (pose && kind_ok && !mr_kind_takes_pose(o->kind))
        GO_ON_AT_KEY(c, "pose",
                     json_fail(c, MR_ERR_INVALID, "expected no pose: a \"%s\" object moves by itself",
                               mr_kind_name(o->kind)));
    else if (pose)
        GO_ON_AT_KEY(c, "pose", parse_object_pose(c, pose, o, job->frame_count));
    o->reference = job->reference; /* parsed before "objects" */
    if (reference)
        GO_ON_AT_KEY(c, "reference", json_get_bool(c, reference, &o->reference));
    o->tolerance_px = job->tolerance_px; /* parsed before "objects" */
    if (tolerance)
        GO_ON_AT_KEY(c, "tolerance_px", parse_tolerance(c, tolerance, &o->tolerance_px));
    return MR_OK;
}

static int parse_objects(mr_json_ctx *c, const cJSON *v, mr_job *job)
{
    if (!cJSON_IsArray(v) || cJSON_GetArraySize(v) == 0)
        return json_fail_expected(c, "an array of 1..1024 objects", v);
    size_t n = (size_t)cJSON_GetArraySize(v);
    if (n > MR_MAX_OBJECTS)
        return json_fail(c, MR_ERR_LIMIT, "expected at most %d objects, got %zu", MR_MAX_OBJECTS, n);
    job->objects = calloc(n, sizeof *job->objects);
    if (!job->objects)
        return json_fail_nomem(c);
    job->object_count = n;
    size_t i = 0;
    for (const cJSON *o = v->child; o; o = o->next, i++)
        GO_ON_AT_INDEX(c, i, parse_object(c, o, job, i, &job->objects[i]));
    return MR_OK;
}

static const char *const LIGHT_FIELDS[] = {"direction", "color", "intensity"};

static int parse_light(mr_json_ctx *c, const cJSON *v, mr_light_desc *l)
{
    TRY(json_want_object(c, v, "a light object"));
    TRY(json_check_fields(c, v, LIGHT_FIELDS, COUNT_OF(LIGHT_FIELDS)));
    TRY(json_require(c, v, "direction"));
    double col[3] = {1, 1, 1}, intensity = 1;
    const cJSON *color = json_field(v, "color"), *inten = json_field(v, "intensity");
    AT_KEY(c, "direction", json_get_unit_vec3(c, json_field(v, "direction"), &l->direction));
    if (color)
        AT_KEY(c, "color", json_get_numbers(c, color, 3, &SPEC_COLOR, "an array of 3 numbers", col));
    if (inten)
        AT_KEY(c, "intensity", json_get_num(c, inten, &SPEC_COLOR, &intensity));
    l->color = mr_v3((float)(col[0] * intensity), (float)(col[1] * intensity),
                     (float)(col[2] * intensity));
    return MR_OK;
}

static int parse_lights(mr_json_ctx *c, const cJSON *v, mr_job *job)
{
    if (!v) {
        /* No "lights": one sun from above, front left, so a job without
         * lighting still shows shape. */
        double d[3] = {-0.4, -1.0, -0.6};
        mr_normalize_d(d, 3);
        job->lights = malloc(sizeof *job->lights);
        if (!job->lights)
            return json_fail_nomem(c);
        job->light_count = 1;
        job->lights[0].direction = mr_v3((float)d[0], (float)d[1], (float)d[2]);
        job->lights[0].color = mr_v3(1, 1, 1);
        return MR_OK;
    }
    if (!cJSON_IsArray(v))
        return json_fail_expected(c, "an array of 0..64 lights", v);
    size_t n = (size_t)cJSON_GetArraySize(v);
    if (n > MR_MAX_LIGHTS)
        return json_fail(c, MR_ERR_LIMIT, "expected at most %d lights, got %zu", MR_MAX_LIGHTS, n);
    if (n == 0)
        return MR_OK;
    job->lights = calloc(n, sizeof *job->lights);
    if (!job->lights)
        return json_fail_nomem(c);
    job->light_count = n;
    size_t i = 0;
    for (const cJSON *l = v->child; l; l = l->next, i++)
        GO_ON_AT_INDEX(c, i, parse_light(c, l, &job->lights[i]));
    return MR_OK;
}

static const char *const BACKGROUND_FIELDS[] = {"color", "alpha"};

static int parse_background(mr_json_ctx *c, const cJSON *v, mr_job *job)
{
    TRY(json_want_object(c, v, "a background object"));
    TRY(json_check_fields(c, v, BACKGROUND_FIELDS, COUNT_OF(BACKGROUND_FIELDS)));
    const cJSON *color = json_field(v, "color"), *alpha = json_field(v, "alpha");
    if (color)
        AT_KEY(c, "color", json_get_vec3(c, color, &SPEC_COLOR, &job->background));
    if (alpha) {
        double a;
        AT_KEY(c, "alpha", json_get_num(c, alpha, &SPEC_ALPHA, &a));
        job->background_alpha = (float)a;
    }
    return MR_OK;
}

static const char *const KEY_FIELDS[] = {"t", "position", "target", "rotation", "yfov"};

static int parse_camera_key(mr_json_ctx *c, const cJSON *v, mr_camera_key *k, float default_yfov,
                            const mr_camera_key *prev)
{
    TRY(json_want_object(c, v, "a camera key object"));
    TRY(json_check_fields(c, v, KEY_FIELDS, COUNT_OF(KEY_FIELDS)));
    TRY(json_require(c, v, "t"));
    TRY(json_require(c, v, "position"));
    const cJSON *target = json_field(v, "target"), *rot = json_field(v, "rotation"), *yfov = json_field(v, "yfov");
    if (target && rot)
        return json_fail(c, MR_ERR_INVALID,
                    "expected exactly one of \"target\" or \"rotation\", got both");
    if (!target && !rot)
        return json_fail(c, MR_ERR_INVALID, "missing required field: \"target\" or \"rotation\"");
    /* Every key's time is under the time cap, not only the first one's: a
     * later key at 1e300 would make the differences of key times overflow. */
    AT_KEY(c, "t", json_get_num(c, json_field(v, "t"), &SPEC_TIME, &k->t));
    if (prev && !(k->t > prev->t)) {
        char expect[96];
        snprintf(expect, sizeof expect, "a time greater than the previous key's (%.15g)", prev->t);
        json_push_key(c, "t");
        return json_fail_expected(c, expect, json_field(v, "t"));
    }
    AT_KEY(c, "position", json_get_vec3(c, json_field(v, "position"), &SPEC_COORD, &k->position));
    k->rotation = mr_quat_identity();
    if (target) {
        AT_KEY(c, "target", json_get_vec3(c, target, &SPEC_COORD, &k->target));
        /* Compared as stored (float): that is what the look-at will see. */
        if (k->target.x == k->position.x && k->target.y == k->position.y &&
            k->target.z == k->position.z) {
            json_push_key(c, "target");
            return json_fail(c, MR_ERR_INVALID,
                        "expected a target different from \"position\", got the same point");
        }
        k->has_target = true;
    } else {
        AT_KEY(c, "rotation", json_get_quat(c, rot, &k->rotation));
    }
    k->yfov = default_yfov;
    if (yfov) {
        double deg;
        AT_KEY(c, "yfov", json_get_num(c, yfov, &SPEC_YFOV, &deg));
        k->yfov = (float)(deg * DEG_TO_RAD);
    }
    return MR_OK;
}

static const char *const NODE_FIELDS[] = {"asset", "name"};

static int parse_camera_node(mr_json_ctx *c, const cJSON *v, mr_job *job)
{
    TRY(json_want_object(c, v, "a camera node object {\"asset\", \"name\"}"));
    TRY(json_check_fields(c, v, NODE_FIELDS, COUNT_OF(NODE_FIELDS)));
    TRY(json_require(c, v, "asset"));
    TRY(json_require(c, v, "name"));
    AT_KEY(c, "asset", find_asset(c, json_field(v, "asset"), job, &job->camera.node_asset));
    AT_KEY(c, "name", json_get_string(c, json_field(v, "name"), MR_MAX_NAME, &job->camera.node_name));
    job->camera.source = MR_CAMERA_SOURCE_NODE;
    return MR_OK;
}

static const char *const CAMERA_FIELDS[] = {"path", "interpolation", "up", "yfov", "node"};

static int parse_camera(mr_json_ctx *c, const cJSON *v, mr_job *job)
{
    TRY(json_want_object(c, v, "a camera object"));
    TRY(json_check_fields(c, v, CAMERA_FIELDS, COUNT_OF(CAMERA_FIELDS)));
    const cJSON *path = json_field(v, "path"), *node = json_field(v, "node"),
                *interp = json_field(v, "interpolation"), *up = json_field(v, "up"),
                *yfov = json_field(v, "yfov");
    if (path && node)
        return json_fail(c, MR_ERR_INVALID, "expected exactly one of \"path\" or \"node\", got both");
    if (!path && !node)
        return json_fail(c, MR_ERR_INVALID, "missing required field: \"path\" or \"node\"");
    if (node) {
        const char *path_only[] = {"interpolation", "up", "yfov"};
        for (size_t i = 0; i < COUNT_OF(path_only); i++)
            if (json_field(v, path_only[i])) {
                json_push_key(c, path_only[i]);
                return json_fail(c, MR_ERR_INVALID, "\"%s\" only applies to \"path\" cameras",
                            path_only[i]);
            }
        AT_KEY(c, "node", parse_camera_node(c, node, job));
        return MR_OK;
    }
    mr_camera_path *cp = &job->camera.path;
    job->camera.source = MR_CAMERA_SOURCE_PATH;
    cp->interp = MR_INTERP_CATMULL_ROM;
    cp->up = mr_v3(0, 1, 0);
    double deg = MR_DEFAULT_YFOV_DEG;
    if (interp) {
        if (cJSON_IsString(interp) && strcmp(interp->valuestring, "linear") == 0)
            cp->interp = MR_INTERP_LINEAR;
        else if (!(cJSON_IsString(interp) && strcmp(interp->valuestring, "catmull-rom") == 0)) {
            json_push_key(c, "interpolation");
            return json_fail_expected(c, "one of: \"linear\", \"catmull-rom\"", interp);
        }
    }
    if (up)
        GO_ON_AT_KEY(c, "up", json_get_unit_vec3(c, up, &cp->up));
    if (yfov)
        GO_ON_AT_KEY(c, "yfov", json_get_num(c, yfov, &SPEC_YFOV, &deg));
    float default_yfov = (float)(deg * DEG_TO_RAD);
    if (!cJSON_IsArray(path) || cJSON_GetArraySize(path) == 0) {
        json_push_key(c, "path");
        return json_fail_expected(c, "an array of 1..10000 camera keys", path);
    }
    size_t n = (size_t)cJSON_GetArraySize(path);
    if (n > MR_MAX_CAMERA_KEYS) {
        json_push_key(c, "path");
        return json_fail(c, MR_ERR_LIMIT, "expected at most %d camera keys, got %zu", MR_MAX_CAMERA_KEYS,
                    n);
    }
    cp->keys = calloc(n, sizeof *cp->keys);
    if (!cp->keys)
        return json_fail_nomem(c);
    cp->key_count = n;
    size_t mark = json_push_key(c, "path"), i = 0;
    bool prev_ok = false; /* a key that failed is no reference for the next one's time */
    for (const cJSON *k = path->child; k; k = k->next, i++) {
        GO_ON_AT_INDEX(c, i,
                       parse_camera_key(c, k, &cp->keys[i], default_yfov,
                                        i && prev_ok ? &cp->keys[i - 1] : NULL));
        prev_ok = !c->failed;
    }
    json_pop(c, mark);
    return MR_OK;
}

static const char *const OUTPUT_FIELDS[] = {"width",       "height",    "samples", "shadows",
                                            "seed",        "compression", "zip_level", "aovs",
                                            "normals"};

/* "aovs": a non-empty array of distinct pass names. */
static int parse_aovs(mr_json_ctx *c, const cJSON *v, unsigned *aovs)
{
    static const char expect[] =
        "an array of 1..7 distinct passes: \"rgba\", \"z\", \"n\", \"p\", \"id\", \"cryptomatte\", \"t\"";
    if (!cJSON_IsArray(v) || cJSON_GetArraySize(v) == 0)
        return json_fail_expected(c, expect, v);
    unsigned set = 0;
    size_t i = 0;
    for (const cJSON *e = v->child; e; e = e->next, i++) {
        mr_aov aov;
        if (!cJSON_IsString(e) || !mr_aov_parse(e->valuestring, &aov)) {
            json_push_index(c, i);
            return json_fail_expected(c, "one of: \"rgba\", \"z\", \"n\", \"p\", \"id\", \"cryptomatte\", \"t\"", e);
        }
        if (set & aov) {
            json_push_index(c, i);
            return json_fail(c, MR_ERR_INVALID, "expected each pass once, got \"%s\" again",
                             e->valuestring);
        }
        set |= aov;
    }
    *aovs = set;
    return MR_OK;
}

static int parse_output(mr_json_ctx *c, const cJSON *v, mr_job *job)
{
    TRY(json_want_object(c, v, "an output object"));
    GO_ON(c, json_check_fields(c, v, OUTPUT_FIELDS, COUNT_OF(OUTPUT_FIELDS)));
    mr_output_desc *o = &job->output;
    const cJSON *w = json_field(v, "width"), *h = json_field(v, "height"), *spp = json_field(v, "samples"),
                *shadows = json_field(v, "shadows"), *seed = json_field(v, "seed"),
                *comp = json_field(v, "compression"), *zip = json_field(v, "zip_level"),
                *aovs = json_field(v, "aovs"), *normals = json_field(v, "normals");
    double d;
    bool size_ok = true;
    if (w) {
        GO_ON_AT_KEY(c, "width", json_get_num(c, w, &SPEC_SIZE, &d));
        if (!c->failed)
            o->width = (int)d;
        else
            size_ok = false;
    }
    if (h) {
        GO_ON_AT_KEY(c, "height", json_get_num(c, h, &SPEC_SIZE, &d));
        if (!c->failed)
            o->height = (int)d;
        else
            size_ok = false;
    }
    uint64_t pixels = (uint64_t)o->width * (uint64_t)o->height;
    if (size_ok && pixels > MR_MAX_PIXELS)
        GO_ON(c, json_fail(c, MR_ERR_LIMIT,
                           "expected at most %u pixels (width * height), got %d x %d = %llu",
                           (unsigned)MR_MAX_PIXELS, o->width, o->height, (unsigned long long)pixels));
    if (spp) {
        GO_ON_AT_KEY(c, "samples", json_get_num(c, spp, &SPEC_SPP, &d));
        if (!c->failed)
            o->spp = (int)d;
    }
    if (shadows)
        GO_ON_AT_KEY(c, "shadows", json_get_bool(c, shadows, &o->shadows));
    if (seed) {
        GO_ON_AT_KEY(c, "seed", json_get_num(c, seed, &SPEC_SEED, &d));
        if (!c->failed)
            o->seed = (uint32_t)d;
    }
    if (comp &&
        !(cJSON_IsString(comp) && mr_compression_parse(comp->valuestring, &o->exr.compression)))
        GO_ON_AT_KEY(c, "compression",
                     json_fail_expected(c, "one of: \"none\", \"zip\", \"zips\", \"piz\"", comp));
    if (zip) {
        GO_ON_AT_KEY(c, "zip_level", json_get_num(c, zip, &SPEC_ZIP, &d));
        if (!c->failed)
            o->exr.zip_level = (int)d;
    }
    if (aovs)
        GO_ON_AT_KEY(c, "aovs", parse_aovs(c, aovs, &o->aovs));
    if (normals) {
        if (cJSON_IsString(normals) && strcmp(normals->valuestring, "half") == 0)
            o->exr.half_normals = true;
        else if (!(cJSON_IsString(normals) && strcmp(normals->valuestring, "float") == 0))
            GO_ON_AT_KEY(c, "normals", json_fail_expected(c, "one of: \"float\", \"half\"", normals));
    }
    return MR_OK;
}

static const char *const ROOT_FIELDS[] = {"name",   "priority", "max_retries", "assets",
                                          "objects", "lights", "ambient",     "background",
                                          "camera",  "frames",   "output",      "notify",
                                          "reference", "tolerance_px"};

/* Reference passes compare colour, depth, normals and ids (mr_film_compare):
 * a job that asks for them keeps those passes (at "output", whose "aovs"
 * left them out). */
static int check_reference_passes(mr_json_ctx *c, const mr_job *job)
{
    if (!mr_job_has_reference(job) || (job->output.aovs & MR_AOV_REFERENCE) == MR_AOV_REFERENCE)
        return MR_OK;
    return json_fail(c, MR_ERR_INVALID,
                     "the job's reference passes compare colour, depth, normals and ids: expected "
                     "\"aovs\" holding \"rgba\", \"z\", \"n\" and \"id\"");
}

/* A job asking for reference passes must get one: some asking object's
 * kind has a reference for it (at "/reference", or the first asking
 * object's when the job does not ask). */
static int check_references_exist(mr_json_ctx *c, const mr_job *job)
{
    unsigned passes = 0;
    mr_error err = {0};
    if (!mr_job_has_reference(job))
        return MR_OK;
    if (mr_job_reference_passes(job, &passes, &err) < 0)
        return json_fail(c, err.code, "%s", err.msg);
    if (passes)
        return MR_OK;
    size_t first = 0;
    while (!job->objects[first].reference)
        first++;
    size_t mark = json_push_key(c, job->reference ? "reference" : "objects");
    if (!job->reference) {
        json_push_index(c, first);
        json_push_key(c, "reference");
    }
    int rc = json_fail(c, MR_ERR_INVALID,
                       "no object asking for reference passes has a reference (each kind's are "
                       "in docs/job-format.md)");
    json_pop(c, mark);
    return rc;
}

/* Longest notify URL. */
#define MAX_NOTIFY_URL 2048

/* "notify": an http:// or https:// URL with a host, of printable ASCII
 * without spaces (what goes into the daemon's request line). */
static int parse_notify(mr_json_ctx *c, const cJSON *v, char **out)
{
    static const char expect[] = "an http:// or https:// URL of printable ASCII without spaces";
    if (!cJSON_IsString(v))
        return json_fail_expected(c, expect, v);
    const char *u = v->valuestring;
    size_t n = strlen(u), scheme = !strncmp(u, "http://", 7) ? 7 : !strncmp(u, "https://", 8) ? 8 : 0;
    bool ok = scheme && n > scheme && n <= MAX_NOTIFY_URL && u[scheme] != '/';
    for (size_t i = 0; ok && i < n; i++)
        ok = u[i] > 0x20 && u[i] < 0x7f;
    if (!ok)
        return json_fail_expected(c, expect, v);
    return json_dup_string(c, u, out);
}

static void set_defaults(mr_job *job)
{
    job->ambient = mr_v3(0.15f, 0.15f, 0.15f);
    job->background = mr_v3(0.1f, 0.1f, 0.12f);
    /* Transparent: premultiplied colour over nothing, as renderers hand
     * frames to a compositor (it was 1, opaque, before issue 13). */
    job->background_alpha = 0.0f;
    job->fps = 24;
    job->max_retries = 2;
    job->output.width = 640;
    job->output.height = 360;
    job->output.spp = 1;
    job->output.shadows = true;
    job->output.seed = 0;
    job->output.exr.compression = MR_COMPRESSION_ZIP;
    job->output.exr.zip_level = MR_ZIP_LEVEL_DEFAULT;
    job->output.aovs = MR_AOV_DEFAULT;
}

static int parse_root(mr_json_ctx *c, const cJSON *root, mr_job *job)
{
    TRY(json_want_object(c, root, "a JSON object"));
    GO_ON(c, json_check_fields(c, root, ROOT_FIELDS, COUNT_OF(ROOT_FIELDS)));
    static const char *const required[] = {"assets", "objects", "camera", "frames"};
    for (size_t i = 0; i < COUNT_OF(required); i++)
        GO_ON(c, json_require(c, root, required[i]));
    set_defaults(job);
    const cJSON *name = json_field(root, "name"), *lights = json_field(root, "lights"),
                *ambient = json_field(root, "ambient"), *background = json_field(root, "background"),
                *output = json_field(root, "output"), *assets = json_field(root, "assets"),
                *frames = json_field(root, "frames"), *objects = json_field(root, "objects"),
                *camera = json_field(root, "camera");
    if (name)
        GO_ON_AT_KEY(c, "name", json_get_string(c, name, MR_MAX_NAME, &job->name));
    else
        TRY(json_dup_string(c, "job", &job->name));
    const cJSON *priority = json_field(root, "priority"), *retries = json_field(root, "max_retries");
    double d;
    if (priority) {
        static const json_num_spec spec = {-MR_MAX_PRIORITY, MR_MAX_PRIORITY, JSON_NUM_INT, NULL};
        GO_ON_AT_KEY(c, "priority", json_get_num(c, priority, &spec, &d));
        if (!c->failed)
            job->priority = (int)d;
    }
    if (retries) {
        static const json_num_spec spec = {0, MR_MAX_RETRIES, JSON_NUM_INT, NULL};
        GO_ON_AT_KEY(c, "max_retries", json_get_num(c, retries, &spec, &d));
        if (!c->failed)
            job->max_retries = (int)d;
    }
    const cJSON *notify = json_field(root, "notify");
    if (notify)
        GO_ON_AT_KEY(c, "notify", parse_notify(c, notify, &job->notify));
    const cJSON *reference = json_field(root, "reference");
    if (reference) /* before "objects": their default */
        GO_ON_AT_KEY(c, "reference", json_get_bool(c, reference, &job->reference));
    const cJSON *tolerance = json_field(root, "tolerance_px");
    if (tolerance) /* before "objects": their default */
        GO_ON_AT_KEY(c, "tolerance_px", parse_tolerance(c, tolerance, &job->tolerance_px));
    if (assets)
        GO_ON_AT_KEY(c, "assets", parse_assets(c, assets, job));
    /* Before "objects": per-frame pose arrays are checked against the count. */
    if (frames) {
        GO_ON_AT_KEY(c, "frames", parse_frames(c, frames, job));
        if (c->failed)
            job->frame_count = 0; /* unknown: not compared (parse_object_pose) */
    }
    if (objects) {
        GO_ON_AT_KEY(c, "objects", parse_objects(c, objects, job));
        if (!c->failed)
            GO_ON(c, check_references_exist(c, job));
    }
    if (camera)
        GO_ON_AT_KEY(c, "camera", parse_camera(c, camera, job));
    GO_ON_AT_KEY(c, "lights", parse_lights(c, lights, job));
    if (ambient)
        GO_ON_AT_KEY(c, "ambient", json_get_vec3(c, ambient, &SPEC_COLOR, &job->ambient));
    if (background)
        GO_ON_AT_KEY(c, "background", parse_background(c, background, job));
    if (output)
        GO_ON_AT_KEY(c, "output", parse_output(c, output, job));
    if (output && json_field(output, "aovs") && !c->failed) {
        size_t mark = json_push_key(c, "output");
        json_push_key(c, "aovs");
        GO_ON_PART(c, mark, check_reference_passes(c, job));
    }
    return MR_OK;
}

/* ------------------------------------------------------------------------ */
/* Entry point.                                                             */

/* mr_job_parse, collecting every problem into all when it is not NULL. */
static int parse_job(const char *json, size_t len, mr_job **out, mr_job_error *err,
                     mr_job_problems *all)
{
    mr_job_error scratch;
    mr_json_ctx c;
    char *text = NULL;
    cJSON *root = NULL;
    mr_job *job = NULL;
    int rc;

    memset(&c, 0, sizeof c);
    c.err = err ? err : &scratch;
    memset(c.err, 0, sizeof *c.err);
    c.all = all;
    if (all)
        memset(all, 0, sizeof *all);
    if (out)
        *out = NULL;
    if (!out) {
        rc = json_fail(&c, MR_ERR_INVALID, "no job given");
        goto cleanup;
    }
    if ((rc = json_parse_document(&c, json, len, MR_JOB_MAX_BYTES, "job", &text, &root)) < 0)
        goto cleanup;
    job = calloc(1, sizeof *job);
    if (!job) {
        rc = json_fail_nomem(&c);
        goto cleanup;
    }
    rc = parse_root(&c, root, job);
    if (rc == MR_OK && c.first_rc < 0) /* problems gone on from */
        rc = c.first_rc;
    if (rc < 0)
        goto cleanup;
    *out = job;
    job = NULL;
    rc = MR_OK;

cleanup:
    mr_job_free(job);
    cJSON_Delete(root);
    free(text);
    return rc;
}

int mr_job_parse(const char *json, size_t len, mr_job **out, mr_job_error *err)
{
    return parse_job(json, len, out, err, NULL);
}

int mr_job_check(const char *json, size_t len, mr_job **out, mr_job_problems *all)
{
    return parse_job(json, len, out, NULL, all);
}
