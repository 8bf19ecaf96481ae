/*
 * job_json.c - validates job JSON and turns it into the structs of core/job.h.
 *
 * Hand-written rather than driven by a JSON Schema library because the
 * daemon must answer with one precise JSON pointer and a short message, and
 * must refuse what a schema cannot express (strictly increasing key times,
 * pose arrays matching the frame count, invertible matrices, references to
 * asset names, caps with their own error code). schemas/job.schema.json
 * describes the same format for clients: change both together.
 *
 * cJSON quirks handled here:
 *  - it keeps duplicate keys: every object's keys are checked;
 *  - overflowing literals (1e999) become inf: every number must be finite;
 *  - "\u0000" decodes to a NUL that silently truncates the string: a private
 *    copy of the input has it rewritten to "\u0001" first, so the
 *    control-character check catches it with the right pointer;
 *  - it skips any byte <= 0x20 as whitespace (NUL included) and stops at the
 *    end of the first value: raw NUL bytes are refused up front and the tail
 *    after the value is checked here, by length (the input need not be
 *    NUL-terminated).
 *
 * Every value is stored into the (zeroed) job as soon as it is allocated, so
 * an error anywhere is cleaned up by the single mr_job_free() in
 * mr_job_parse().
 */
#include "job_json.h"

#include "kinds/kind.h"

#include <cJSON.h>
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

/* ------------------------------------------------------------------------ */
/* Context: the JSON pointer of the value being read, and where errors go.  */

typedef struct jctx {
    mr_job_error *err;
    char ptr[sizeof(((mr_job_error *)0)->pointer)];
    size_t len;
    bool nul_escapes; /* prescan() rewrote some "\u0000" to "\u0001" */
} jctx;

/* Appends "/key" (escaped per RFC 6901) and returns the length to pop back
 * to. An absurdly long key is cut at a UTF-8 boundary rather than overflow. */
static size_t push_key(jctx *c, const char *key)
{
    size_t mark = c->len, cap = sizeof c->ptr - 1, n = c->len;
    bool cut = false;
    if (n < cap)
        c->ptr[n++] = '/';
    for (const char *s = key; *s; s++) {
        const char *esc = *s == '~' ? "~0" : *s == '/' ? "~1" : NULL;
        size_t need = esc ? 2 : 1;
        if (n + need > cap) {
            cut = true;
            break;
        }
        if (esc) {
            c->ptr[n++] = esc[0];
            c->ptr[n++] = esc[1];
        } else {
            c->ptr[n++] = *s;
        }
    }
    if (cut) {
        while (n > mark + 1 && ((unsigned char)c->ptr[n - 1] & 0xC0) == 0x80)
            n--;
        if (n > mark + 1 && (unsigned char)c->ptr[n - 1] >= 0xC0)
            n--;
    }
    c->ptr[n] = '\0';
    c->len = n;
    return mark;
}

static size_t push_index(jctx *c, size_t i)
{
    char buf[32];
    snprintf(buf, sizeof buf, "%zu", i);
    return push_key(c, buf);
}

static void pop(jctx *c, size_t mark)
{
    c->len = mark;
    c->ptr[mark] = '\0';
}

static int fail(jctx *c, int code, const char *fmt, ...) __attribute__((format(printf, 3, 4)));
static int fail(jctx *c, int code, const char *fmt, ...)
{
    va_list ap;
    memcpy(c->err->pointer, c->ptr, c->len + 1);
    va_start(ap, fmt);
    vsnprintf(c->err->message, sizeof c->err->message, fmt, ap);
    va_end(ap);
    return code;
}

static int fail_nomem(jctx *c) { return fail(c, MR_ERR_NOMEM, "out of memory"); }

#define TRY(expr)                                                                            \
    do {                                                                                     \
        int rc_ = (expr);                                                                    \
        if (rc_ < 0)                                                                         \
            return rc_;                                                                      \
    } while (0)

/* Runs expr with /key appended to the pointer; on failure the pointer stays,
 * since the error has already copied it. */
#define AT_KEY(c, key, expr)                                                                 \
    do {                                                                                     \
        size_t mark_ = push_key((c), (key));                                                 \
        TRY(expr);                                                                           \
        pop((c), mark_);                                                                     \
    } while (0)

#define AT_INDEX(c, i, expr)                                                                 \
    do {                                                                                     \
        size_t mark_ = push_index((c), (i));                                                 \
        TRY(expr);                                                                           \
        pop((c), mark_);                                                                     \
    } while (0)

/* ------------------------------------------------------------------------ */
/* Describing what was found, for "expected X, got Y" messages.             */

/* Writes s as a short quoted JSON-ish string, cut at a UTF-8 boundary. */
static void quote(const char *s, char *buf, size_t n)
{
    const size_t shown = 40;
    size_t o = 0, i = 0;
    buf[0] = '\0';
    if (n < 16)
        return;
    buf[o++] = '"';
    /* Each byte takes at most 6 ("\u001f"); keep 5 for "...", '"' and NUL. */
    for (; s[i] && i < shown && o + 6 + 5 <= n; i++) {
        unsigned char b = (unsigned char)s[i];
        if (b == '"' || b == '\\') {
            buf[o++] = '\\';
            buf[o++] = (char)b;
        } else if (b < 0x20 || b == 0x7F) {
            o += (size_t)snprintf(buf + o, n - o, "\\u%04x", b);
        } else {
            buf[o++] = (char)b;
        }
    }
    if (s[i]) {
        while (o > 1 && ((unsigned char)buf[o - 1] & 0xC0) == 0x80)
            o--;
        if (o > 1 && (unsigned char)buf[o - 1] >= 0xC0)
            o--;
        memcpy(buf + o, "...", 3);
        o += 3;
    }
    buf[o++] = '"';
    buf[o] = '\0';
}

static const char *describe(const cJSON *v, char *buf, size_t n)
{
    if (!v) {
        snprintf(buf, n, "nothing");
    } else if (cJSON_IsNull(v)) {
        snprintf(buf, n, "null");
    } else if (cJSON_IsTrue(v)) {
        snprintf(buf, n, "true");
    } else if (cJSON_IsFalse(v)) {
        snprintf(buf, n, "false");
    } else if (cJSON_IsNumber(v)) {
        if (isfinite(v->valuedouble))
            snprintf(buf, n, "%.15g", v->valuedouble);
        else
            snprintf(buf, n, "a number too large to represent (it overflows to infinity)");
    } else if (cJSON_IsString(v)) {
        quote(v->valuestring, buf, n);
    } else if (cJSON_IsArray(v)) {
        int k = cJSON_GetArraySize(v);
        if (k == 0)
            snprintf(buf, n, "an empty array");
        else
            snprintf(buf, n, "an array of %d element%s", k, k == 1 ? "" : "s");
    } else if (cJSON_IsObject(v)) {
        snprintf(buf, n, "an object");
    } else {
        snprintf(buf, n, "an invalid value");
    }
    return buf;
}

static int fail_expected(jctx *c, const char *expect, const cJSON *v)
{
    char got[256];
    return fail(c, MR_ERR_INVALID, "expected %s, got %s", expect, describe(v, got, sizeof got));
}

/* ------------------------------------------------------------------------ */
/* Scalars.                                                                 */

enum { NUM_INT = 1u, NUM_LO_OPEN = 2u, NUM_HI_OPEN = 4u };

typedef struct num_spec {
    double lo, hi;
    unsigned flags;
    const char *expect; /* NULL: derived from lo, hi and flags */
} num_spec;

/* Values stored as float must fit one, or they silently become inf. */
static const num_spec SPEC_FLOAT = {-FLT_MAX, FLT_MAX, 0,
                                    "a number within the 32-bit float range (|x| <= 3.4e38)"};
/* Positions, translations, scales and matrix entries. Far beyond any scene,
 * but well inside what Embree accepts for ray origins (about 1.8e19), so a
 * valid job can never trip Embree's ray validity checks. */
static const num_spec SPEC_COORD = {-1e9, 1e9, 0, "a number with |x| <= 1e9"};
/* Times on the job's timeline and clip times, seconds: differences of two
 * stay finite, so interpolation can never divide inf by inf. */
static const num_spec SPEC_TIME = {-1e9, 1e9, 0, "a time in seconds with |t| <= 1e9"};
static const num_spec SPEC_SPEED = {-1e6, 1e6, 0, NULL};
static const num_spec SPEC_COLOR = {0, 1000, 0, NULL};
static const num_spec SPEC_ALPHA = {0, 1, 0, NULL};
static const num_spec SPEC_FPS = {0, 1000, NUM_LO_OPEN, NULL};
static const num_spec SPEC_YFOV = {0.001, 179.9, 0, "a field of view in degrees in [0.001, 179.9]"};
static const num_spec SPEC_SIZE = {1, MR_MAX_RESOLUTION, NUM_INT, NULL};
static const num_spec SPEC_SPP = {1, MR_MAX_SPP, NUM_INT, NULL};
static const num_spec SPEC_SEED = {0, 4294967295.0, NUM_INT, NULL};
static const num_spec SPEC_ZIP = {1, 9, NUM_INT, NULL};

static void spec_text(const num_spec *s, char *buf, size_t n)
{
    if (s->expect)
        snprintf(buf, n, "%s", s->expect);
    else if (s->flags & NUM_INT)
        snprintf(buf, n, "an integer in %.15g..%.15g", s->lo, s->hi);
    else if (s->flags & (NUM_LO_OPEN | NUM_HI_OPEN))
        snprintf(buf, n, "a number in %c%.15g, %.15g%c", (s->flags & NUM_LO_OPEN) ? '(' : '[',
                 s->lo, s->hi, (s->flags & NUM_HI_OPEN) ? ')' : ']');
    else
        snprintf(buf, n, "a number in %.15g..%.15g", s->lo, s->hi);
}

static int get_num(jctx *c, const cJSON *v, const num_spec *s, double *out)
{
    double x = cJSON_IsNumber(v) ? v->valuedouble : NAN;
    /* Every test below is false for NaN/inf, so the cast to integers later
     * only ever sees finite, integral, in-range doubles. */
    bool ok = isfinite(x) && x >= s->lo && x <= s->hi;
    if (ok && (s->flags & NUM_INT))
        ok = x == floor(x);
    if (ok && (s->flags & NUM_LO_OPEN))
        ok = x > s->lo;
    if (ok && (s->flags & NUM_HI_OPEN))
        ok = x < s->hi;
    if (!ok) {
        char expect[128];
        spec_text(s, expect, sizeof expect);
        return fail_expected(c, expect, v);
    }
    *out = x;
    return MR_OK;
}

static int get_bool(jctx *c, const cJSON *v, bool *out)
{
    if (!cJSON_IsBool(v))
        return fail_expected(c, "a boolean (true or false)", v);
    *out = cJSON_IsTrue(v);
    return MR_OK;
}

/* Offset of the first byte that is not valid UTF-8 (RFC 3629: no overlongs,
 * no surrogates, nothing above U+10FFFF), or SIZE_MAX if all are valid. */
static size_t utf8_invalid_at(const char *str)
{
    const unsigned char *s = (const unsigned char *)str;
    size_t i = 0;
    while (s[i]) {
        unsigned b = s[i], need, cp;
        if (b < 0x80) {
            i++;
            continue;
        }
        if (b >= 0xC2 && b <= 0xDF) {
            need = 1;
            cp = b & 0x1F;
        } else if (b >= 0xE0 && b <= 0xEF) {
            need = 2;
            cp = b & 0x0F;
        } else if (b >= 0xF0 && b <= 0xF4) {
            need = 3;
            cp = b & 0x07;
        } else {
            return i;
        }
        /* A NUL terminator fails the continuation test, so this never reads
         * past the end of the string. */
        for (unsigned k = 1; k <= need; k++) {
            if ((s[i + k] & 0xC0) != 0x80)
                return i;
            cp = (cp << 6) | (s[i + k] & 0x3F);
        }
        if ((need == 2 && (cp < 0x800 || (cp >= 0xD800 && cp <= 0xDFFF))) ||
            (need == 3 && (cp < 0x10000 || cp > 0x10FFFF)))
            return i;
        i += need + 1;
    }
    return SIZE_MAX;
}

/* Checks a string the job keeps (name, path, key): 1..max bytes, valid
 * UTF-8, no control characters (which also catches "\u0000", see top). */
static int check_text(jctx *c, const char *s, size_t max)
{
    size_t n = strlen(s), bad;
    if (n == 0 || n > max) {
        char got[128];
        if (n == 0)
            snprintf(got, sizeof got, "an empty string");
        else
            snprintf(got, sizeof got, "%zu bytes", n);
        return fail(c, MR_ERR_INVALID, "expected a string of 1..%zu bytes, got %s", max, got);
    }
    for (size_t i = 0; i < n; i++) {
        unsigned ch = (unsigned char)s[i];
        if (ch < 0x20 || ch == 0x7F) {
            /* Most likely the rewritten NUL: name what the user wrote. */
            if (ch == 0x01 && c->nul_escapes)
                ch = 0;
            return fail(c, MR_ERR_INVALID,
                        "expected a string without control characters, found U+%04X at byte %zu",
                        ch, i);
        }
    }
    bad = utf8_invalid_at(s);
    if (bad != SIZE_MAX)
        return fail(c, MR_ERR_INVALID, "expected valid UTF-8, found an invalid byte at byte %zu",
                    bad);
    return MR_OK;
}

static int dup_string(jctx *c, const char *s, char **out)
{
    size_t n = strlen(s) + 1;
    char *d = malloc(n);
    if (!d)
        return fail_nomem(c);
    memcpy(d, s, n);
    *out = d;
    return MR_OK;
}

/* Type, length and content checks, then a copy into *out. */
static int get_string(jctx *c, const cJSON *v, size_t max, char **out)
{
    if (!cJSON_IsString(v) || !v->valuestring) {
        char expect[64];
        snprintf(expect, sizeof expect, "a string of 1..%zu bytes", max);
        return fail_expected(c, expect, v);
    }
    TRY(check_text(c, v->valuestring, max));
    return dup_string(c, v->valuestring, out);
}

/* ------------------------------------------------------------------------ */
/* Objects: allowed keys, duplicates, required keys.                        */

static const cJSON *field(const cJSON *obj, const char *key)
{
    return cJSON_GetObjectItemCaseSensitive(obj, key);
}

static int want_object(jctx *c, const cJSON *v, const char *expect)
{
    return cJSON_IsObject(v) ? MR_OK : fail_expected(c, expect, v);
}

/* Refuses unknown and repeated keys. A repeated key is caught at its second
 * occurrence, so even an object with millions of copies of one allowed key
 * costs O(keys * allowed). */
static int check_fields(jctx *c, const cJSON *obj, const char *const *allowed, size_t n)
{
    uint32_t seen = 0;
    for (const cJSON *f = obj->child; f; f = f->next) {
        const char *key = f->string ? f->string : "";
        size_t i = 0;
        while (i < n && strcmp(key, allowed[i]) != 0)
            i++;
        if (i == n) {
            char list[400];
            size_t o = 0;
            list[0] = '\0';
            for (size_t k = 0; k < n && o < sizeof list; k++)
                o += (size_t)snprintf(list + o, sizeof list - o, "%s%s", k ? ", " : "", allowed[k]);
            push_key(c, key);
            return fail(c, MR_ERR_INVALID, "unknown field; expected one of: %s", list);
        }
        if (seen & (1u << i)) {
            push_key(c, key);
            return fail(c, MR_ERR_INVALID, "duplicate field \"%s\"", key);
        }
        seen |= 1u << i;
    }
    return MR_OK;
}

typedef struct key_ref {
    const char *key;
    size_t index; /* position in the object */
} key_ref;

static int key_ref_cmp(const void *a, const void *b)
{
    const key_ref *x = a, *y = b;
    int d = strcmp(x->key, y->key);
    return d ? d : (x->index > y->index) - (x->index < y->index);
}

/* For maps with user-chosen keys (assets, joints), n entries. Sorting keeps
 * this O(n log n): a pairwise scan of 1024 joints in each of thousands of
 * per-frame poses took seconds. Reports the entry, first in document order,
 * that repeats an earlier key, as a pairwise scan would. */
static int check_unique_keys(jctx *c, const cJSON *obj, size_t n)
{
    key_ref *refs = malloc((n ? n : 1) * sizeof *refs);
    size_t i = 0, first_repeat = SIZE_MAX;
    const char *repeated = NULL;
    if (!refs)
        return fail_nomem(c);
    for (const cJSON *f = obj->child; f && i < n; f = f->next, i++)
        refs[i] = (key_ref){f->string ? f->string : "", i};
    qsort(refs, i, sizeof *refs, key_ref_cmp);
    for (size_t k = 1; k < i; k++) {
        bool opens_group = k == 1 || strcmp(refs[k - 2].key, refs[k - 1].key) != 0;
        if (opens_group && strcmp(refs[k - 1].key, refs[k].key) == 0 &&
            refs[k].index < first_repeat) {
            first_repeat = refs[k].index;
            repeated = refs[k].key;
        }
    }
    free(refs);
    if (repeated) {
        char q[128];
        push_key(c, repeated);
        quote(repeated, q, sizeof q);
        return fail(c, MR_ERR_INVALID, "duplicate field %s", q);
    }
    return MR_OK;
}

static int require(jctx *c, const cJSON *obj, const char *key)
{
    if (field(obj, key))
        return MR_OK;
    return fail(c, MR_ERR_INVALID, "missing required field \"%s\"", key);
}

/* ------------------------------------------------------------------------ */
/* Vectors, quaternions, transforms.                                        */

static int get_numbers(jctx *c, const cJSON *v, size_t n, const num_spec *s, const char *expect,
                       double *out)
{
    if (!cJSON_IsArray(v) || (size_t)cJSON_GetArraySize(v) != n)
        return fail_expected(c, expect, v);
    size_t i = 0;
    for (const cJSON *e = v->child; e; e = e->next, i++)
        AT_INDEX(c, i, get_num(c, e, s, &out[i]));
    return MR_OK;
}

static int get_vec3(jctx *c, const cJSON *v, const num_spec *s, mr_vec3 *out)
{
    double d[3];
    TRY(get_numbers(c, v, 3, s, "an array of 3 numbers", d));
    *out = mr_v3((float)d[0], (float)d[1], (float)d[2]);
    return MR_OK;
}

/* Scales by the largest component before squaring so tiny but non-zero
 * inputs (1e-200) normalise instead of underflowing to a zero length.
 * Returns false for the zero vector. */
static bool normalize_d(double *d, size_t n)
{
    double m = 0, l = 0;
    for (size_t i = 0; i < n; i++)
        m = fmax(m, fabs(d[i]));
    if (!(m > 0))
        return false;
    for (size_t i = 0; i < n; i++) {
        d[i] /= m;
        l += d[i] * d[i];
    }
    l = sqrt(l);
    for (size_t i = 0; i < n; i++)
        d[i] /= l;
    return true;
}

static int get_unit_vec3(jctx *c, const cJSON *v, mr_vec3 *out)
{
    double d[3];
    TRY(get_numbers(c, v, 3, &SPEC_FLOAT, "an array of 3 numbers", d));
    if (!normalize_d(d, 3))
        return fail(c, MR_ERR_INVALID, "expected a non-zero vector, got [0, 0, 0]");
    *out = mr_v3((float)d[0], (float)d[1], (float)d[2]);
    return MR_OK;
}

static int get_quat(jctx *c, const cJSON *v, mr_quat *out)
{
    double d[4];
    TRY(get_numbers(c, v, 4, &SPEC_FLOAT, "an array of 4 numbers [x, y, z, w]", d));
    if (!normalize_d(d, 4))
        return fail(c, MR_ERR_INVALID,
                    "expected a non-zero quaternion [x, y, z, w], got one of length 0");
    *out = (mr_quat){(float)d[0], (float)d[1], (float)d[2], (float)d[3]};
    return MR_OK;
}

/* mr_mat4_inverse judges affine matrices by their 3x3 part alone, so large
 * translations are fine; a finite inverse guards against overflow. */
static bool affine_invertible(const mr_mat4 *m)
{
    mr_mat4 inv;
    return mr_mat4_inverse(m, &inv) && mr_mat4_is_finite(&inv);
}

static const char *const TRANSFORM_FIELDS[] = {"translation", "rotation", "scale", "matrix"};

/* {"translation","rotation","scale"} (any subset) or {"matrix": [16]}. */
static int get_transform(jctx *c, const cJSON *v, mr_mat4 *out)
{
    TRY(want_object(c, v,
                    "a transform object ({\"translation\", \"rotation\", \"scale\"} or "
                    "{\"matrix\"})"));
    TRY(check_fields(c, v, TRANSFORM_FIELDS, COUNT_OF(TRANSFORM_FIELDS)));
    const cJSON *t = field(v, "translation"), *r = field(v, "rotation"), *s = field(v, "scale"),
                *m = field(v, "matrix");
    if (m && (t || r || s))
        return fail(c, MR_ERR_INVALID, "expected either \"matrix\" or "
                                       "\"translation\"/\"rotation\"/\"scale\", got both forms");
    if (m) {
        double d[16];
        AT_KEY(c, "matrix",
               get_numbers(c, m, 16, &SPEC_COORD, "an array of 16 numbers (row-major 4x4)", d));
        /* mr_mat4_point() ignores w, so a projective last row would be
         * silently dropped: refuse it. 1e-6 forgives exporters' rounding. */
        if (fabs(d[12]) > 1e-6 || fabs(d[13]) > 1e-6 || fabs(d[14]) > 1e-6 ||
            fabs(d[15] - 1) > 1e-6) {
            push_key(c, "matrix");
            return fail(c, MR_ERR_INVALID,
                        "expected an affine matrix with last row [0, 0, 0, 1], got [%.9g, %.9g, "
                        "%.9g, %.9g]",
                        d[12], d[13], d[14], d[15]);
        }
        for (int i = 0; i < 12; i++)
            out->m[i] = (float)d[i];
        out->m[12] = out->m[13] = out->m[14] = 0.0f;
        out->m[15] = 1.0f;
        if (!affine_invertible(out)) {
            push_key(c, "matrix");
            return fail(c, MR_ERR_INVALID, "expected an invertible matrix, got a singular one");
        }
        return MR_OK;
    }
    mr_vec3 tv = mr_v3(0, 0, 0), sv = mr_v3(1, 1, 1);
    mr_quat q = mr_quat_identity();
    if (t)
        AT_KEY(c, "translation", get_vec3(c, t, &SPEC_COORD, &tv));
    if (r)
        AT_KEY(c, "rotation", get_quat(c, r, &q));
    if (s) {
        double d[3];
        AT_KEY(c, "scale", get_numbers(c, s, 3, &SPEC_COORD, "an array of 3 numbers", d));
        for (size_t i = 0; i < 3; i++)
            if (d[i] == 0) {
                push_key(c, "scale");
                push_index(c, i);
                return fail(c, MR_ERR_INVALID, "expected a non-zero scale, got 0");
            }
        sv = mr_v3((float)d[0], (float)d[1], (float)d[2]);
    }
    *out = mr_mat4_from_trs(tv, q, sv);
    if (!mr_mat4_is_finite(out) || !affine_invertible(out))
        return fail(c, MR_ERR_INVALID,
                    "expected an invertible transform, got a numerically singular one "
                    "(scales too far apart or below float precision)");
    return MR_OK;
}

/* ------------------------------------------------------------------------ */
/* Top-level sections.                                                      */

static const char *const ASSET_FIELDS[] = {"path", "id", "refine"};
static const char *const REFINE_FIELDS[] = {"rounds", "amplitude", "frequency", "octaves", "seed"};
static const num_spec SPEC_REFINE_ROUNDS = {0, MR_ASSET_REFINE_MAX_ROUNDS, NUM_INT, NULL};
static const num_spec SPEC_REFINE_OCTAVES = {0, MR_ASSET_REFINE_MAX_OCTAVES, NUM_INT, NULL};
/* Mesh units, like coordinates (SPEC_COORD): |displacement| <= amplitude. */
static const num_spec SPEC_REFINE_AMPLITUDE = {0, 1e9, 0, "a number in 0..1e9 (mesh units)"};
static const num_spec SPEC_REFINE_FREQUENCY = {0, 1e9, NUM_LO_OPEN,
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

/* An asset's "refine" parameters (core/asset/refine.h), every field
 * optional. The frequency is stored as float and must stay positive there:
 * refine.h refuses a zero frequency with a non-zero amplitude, which would
 * otherwise only surface when the job runs. */
static int parse_refine(jctx *c, const cJSON *v, mr_refine_params *p)
{
    TRY(want_object(c, v, "an object of refine parameters"));
    TRY(check_fields(c, v, REFINE_FIELDS, COUNT_OF(REFINE_FIELDS)));
    const cJSON *rounds = field(v, "rounds"), *amp = field(v, "amplitude"),
                *freq = field(v, "frequency"), *oct = field(v, "octaves"), *seed = field(v, "seed");
    double x;
    *p = (mr_refine_params){.rounds = MR_ASSET_REFINE_DEFAULT_ROUNDS,
                            .amplitude = 0.0f,
                            .frequency = MR_ASSET_REFINE_DEFAULT_FREQUENCY,
                            .octaves = MR_ASSET_REFINE_DEFAULT_OCTAVES,
                            .seed = MR_ASSET_REFINE_DEFAULT_SEED};
    if (rounds) {
        AT_KEY(c, "rounds", get_num(c, rounds, &SPEC_REFINE_ROUNDS, &x));
        p->rounds = (unsigned)x;
    }
    if (amp) {
        AT_KEY(c, "amplitude", get_num(c, amp, &SPEC_REFINE_AMPLITUDE, &x));
        p->amplitude = (float)x;
    }
    if (freq) {
        AT_KEY(c, "frequency", get_num(c, freq, &SPEC_REFINE_FREQUENCY, &x));
        if (!((float)x > 0.0f)) {
            push_key(c, "frequency");
            return fail(c, MR_ERR_INVALID,
                        "expected a number in (0, 1e9] that stays above 0 as a 32-bit float, "
                        "got %.15g",
                        x);
        }
        p->frequency = (float)x;
    }
    if (oct) {
        AT_KEY(c, "octaves", get_num(c, oct, &SPEC_REFINE_OCTAVES, &x));
        p->octaves = (unsigned)x;
    }
    if (seed) {
        AT_KEY(c, "seed", get_num(c, seed, &SPEC_SEED, &x));
        p->seed = (uint32_t)x;
    }
    return MR_OK;
}

/* One asset's description: a server-side {"path"} or the content hash of an
 * uploaded asset, {"id"} (exactly one of the two), optionally "refine"d. */
static int parse_asset(jctx *c, const cJSON *v, mr_asset_desc *a)
{
    TRY(want_object(c, v, "an asset object {\"path\": ...} or {\"id\": ...}"));
    TRY(check_fields(c, v, ASSET_FIELDS, COUNT_OF(ASSET_FIELDS)));
    const cJSON *path = field(v, "path"), *id = field(v, "id"), *refine = field(v, "refine");
    if (!path == !id)
        return fail(c, MR_ERR_INVALID, "expected exactly one of \"path\" (a file on the server) or "
                                       "\"id\" (an uploaded asset's SHA-256)");
    if (path) {
        AT_KEY(c, "path", get_string(c, path, MR_MAX_PATH, &a->path));
    } else {
        AT_KEY(c, "id", get_string(c, id, 64, &a->id));
        if (!hex64(a->id)) {
            push_key(c, "id");
            return fail(c, MR_ERR_INVALID, "expected 64 lowercase hex digits (the SHA-256 POST /v1/assets returned)");
        }
    }
    if (refine) {
        AT_KEY(c, "refine", parse_refine(c, refine, &a->refine_params));
        a->refine = true;
    }
    return MR_OK;
}

static int parse_assets(jctx *c, const cJSON *v, mr_job *job)
{
    TRY(want_object(c, v, "an object mapping asset names to assets"));
    size_t n = (size_t)cJSON_GetArraySize(v);
    if (n == 0)
        return fail(c, MR_ERR_INVALID, "expected 1..%d assets, got none", MR_MAX_ASSETS);
    if (n > MR_MAX_ASSETS)
        return fail(c, MR_ERR_LIMIT, "expected at most %d assets, got %zu", MR_MAX_ASSETS, n);
    TRY(check_unique_keys(c, v, n));
    job->assets = calloc(n, sizeof *job->assets);
    if (!job->assets)
        return fail_nomem(c);
    job->asset_count = n;
    size_t i = 0;
    for (const cJSON *a = v->child; a; a = a->next, i++) {
        const char *name = a->string ? a->string : "";
        size_t mark = push_key(c, name);
        if (!asset_name_ok(name)) {
            char q[128];
            quote(name, q, sizeof q);
            return fail(c, MR_ERR_INVALID,
                        "expected an asset name matching [A-Za-z0-9_.-]{1,%d}, got %s",
                        MAX_ASSET_NAME, q);
        }
        TRY(dup_string(c, name, &job->assets[i].name));
        TRY(parse_asset(c, a, &job->assets[i]));
        pop(c, mark);
    }
    return MR_OK;
}

static int find_asset(jctx *c, const cJSON *v, const mr_job *job, size_t *out)
{
    if (!cJSON_IsString(v) || !v->valuestring)
        return fail_expected(c, "the name of an asset (a string)", v);
    for (size_t i = 0; i < job->asset_count; i++)
        if (strcmp(job->assets[i].name, v->valuestring) == 0) {
            *out = i;
            return MR_OK;
        }
    return fail_expected(c, "the name of an entry in \"assets\"", v);
}

static const char *const FRAMES_FIELDS[] = {"fps", "start", "end", "times"};

static int parse_frames(jctx *c, const cJSON *v, mr_job *job)
{
    TRY(want_object(c, v, "a frames object"));
    TRY(check_fields(c, v, FRAMES_FIELDS, COUNT_OF(FRAMES_FIELDS)));
    const cJSON *fps_v = field(v, "fps"), *start_v = field(v, "start"), *end_v = field(v, "end"),
                *times_v = field(v, "times");
    double fps = 24, start = 0, end = 0;
    if (fps_v)
        AT_KEY(c, "fps", get_num(c, fps_v, &SPEC_FPS, &fps));
    job->fps = fps;
    if (end_v && times_v) {
        push_key(c, "times");
        return fail(c, MR_ERR_INVALID, "\"times\" cannot be combined with \"end\"");
    }
    if (!end_v && !times_v)
        return fail(c, MR_ERR_INVALID, "missing required field: \"end\" or \"times\"");
    if (times_v) {
        if (start_v) {
            push_key(c, "start");
            return fail(c, MR_ERR_INVALID,
                        "\"start\" cannot be combined with \"times\" (list the times instead)");
        }
        if (!cJSON_IsArray(times_v) || cJSON_GetArraySize(times_v) == 0) {
            char expect[64];
            push_key(c, "times");
            snprintf(expect, sizeof expect, "an array of 1..%d times in seconds", MR_MAX_FRAMES);
            return fail_expected(c, expect, times_v);
        }
        size_t n = (size_t)cJSON_GetArraySize(times_v);
        if (n > MR_MAX_FRAMES)
            return fail(c, MR_ERR_LIMIT, "expected at most %d frames, got %zu", MR_MAX_FRAMES, n);
        job->frame_times = malloc(n * sizeof *job->frame_times);
        if (!job->frame_times)
            return fail_nomem(c);
        job->frame_count = n;
        size_t mark = push_key(c, "times"), i = 0;
        for (const cJSON *t = times_v->child; t; t = t->next, i++)
            AT_INDEX(c, i, get_num(c, t, &SPEC_TIME, &job->frame_times[i]));
        pop(c, mark);
        return MR_OK;
    }
    if (start_v)
        AT_KEY(c, "start", get_num(c, start_v, &SPEC_TIME, &start));
    num_spec end_spec = {start, SPEC_TIME.hi, 0, NULL};
    char expect[64];
    snprintf(expect, sizeof expect, "a time >= start (%.15g) and <= %g", start, SPEC_TIME.hi);
    end_spec.expect = expect;
    AT_KEY(c, "end", get_num(c, end_v, &end_spec, &end));
    /* The 1e-9 keeps (end - start) * fps that should be integral but rounds
     * to just below it from losing the last frame. The comparison is done in
     * double before any cast, so a huge span cannot overflow a size_t. */
    double span = (end - start) * fps + 1e-9;
    if (!(span < (double)MR_MAX_FRAMES)) {
        if (isfinite(span))
            return fail(c, MR_ERR_LIMIT, "expected at most %d frames, got %.15g", MR_MAX_FRAMES,
                        floor(span) + 1);
        return fail(c, MR_ERR_LIMIT, "expected at most %d frames, got too many to count",
                    MR_MAX_FRAMES);
    }
    size_t n = (size_t)floor(span) + 1;
    job->frame_times = malloc(n * sizeof *job->frame_times);
    if (!job->frame_times)
        return fail_nomem(c);
    job->frame_count = n;
    for (size_t i = 0; i < n; i++)
        job->frame_times[i] = start + (double)i / fps;
    return MR_OK;
}

static const char *const POSE_FIELDS[] = {"clip", "time", "speed", "offset", "loop", "joints"};

static int parse_joints(jctx *c, const cJSON *v, mr_pose_desc *p)
{
    TRY(want_object(c, v, "an object mapping node names to transforms"));
    size_t n = (size_t)cJSON_GetArraySize(v);
    if (n == 0)
        return fail(c, MR_ERR_INVALID, "expected 1..%d joints, got none", MR_MAX_JOINT_OVERRIDES);
    if (n > MR_MAX_JOINT_OVERRIDES)
        return fail(c, MR_ERR_LIMIT, "expected at most %d joints, got %zu",
                    MR_MAX_JOINT_OVERRIDES, n);
    TRY(check_unique_keys(c, v, n));
    p->joints = calloc(n, sizeof *p->joints);
    if (!p->joints)
        return fail_nomem(c);
    p->joint_count = n;
    size_t i = 0;
    for (const cJSON *j = v->child; j; j = j->next, i++) {
        const char *name = j->string ? j->string : "";
        size_t mark = push_key(c, name);
        TRY(check_text(c, name, MR_MAX_NAME));
        TRY(dup_string(c, name, &p->joints[i].joint));
        TRY(get_transform(c, j, &p->joints[i].local));
        pop(c, mark);
    }
    return MR_OK;
}

static int parse_pose(jctx *c, const cJSON *v, mr_pose_desc *p)
{
    TRY(want_object(c, v, "a pose object"));
    TRY(check_fields(c, v, POSE_FIELDS, COUNT_OF(POSE_FIELDS)));
    const cJSON *clip = field(v, "clip"), *time = field(v, "time"), *speed = field(v, "speed"),
                *offset = field(v, "offset"), *loop = field(v, "loop"),
                *joints = field(v, "joints");
    p->clip_index = -1;
    p->speed = 1;
    p->offset = 0;
    p->loop = true;
    if (!clip && !joints)
        return fail(c, MR_ERR_INVALID, "expected a pose with \"clip\" or \"joints\", got neither");
    if (!clip) {
        const char *const needs_clip[] = {"time", "speed", "offset", "loop"};
        for (size_t i = 0; i < COUNT_OF(needs_clip); i++)
            if (field(v, needs_clip[i])) {
                push_key(c, needs_clip[i]);
                return fail(c, MR_ERR_INVALID, "\"%s\" requires \"clip\"", needs_clip[i]);
            }
    }
    if (time && (speed || offset)) {
        push_key(c, speed ? "speed" : "offset");
        return fail(c, MR_ERR_INVALID, "\"%s\" cannot be combined with \"time\"",
                    speed ? "speed" : "offset");
    }
    if (clip) {
        size_t mark = push_key(c, "clip");
        if (cJSON_IsString(clip)) {
            TRY(get_string(c, clip, MR_MAX_NAME, &p->clip_name));
        } else {
            static const num_spec clip_index = {0, INT_MAX, NUM_INT,
                                                "a clip name (string) or index (integer >= 0)"};
            double d;
            TRY(get_num(c, clip, &clip_index, &d));
            p->clip_index = (int)d;
        }
        pop(c, mark);
        p->has_clip = true;
    }
    if (time) {
        AT_KEY(c, "time", get_num(c, time, &SPEC_TIME, &p->time));
        p->has_time = true;
    }
    if (speed)
        AT_KEY(c, "speed", get_num(c, speed, &SPEC_SPEED, &p->speed));
    if (offset)
        AT_KEY(c, "offset", get_num(c, offset, &SPEC_TIME, &p->offset));
    if (loop)
        AT_KEY(c, "loop", get_bool(c, loop, &p->loop));
    if (joints)
        AT_KEY(c, "joints", parse_joints(c, joints, p));
    return MR_OK;
}

static int parse_object_pose(jctx *c, const cJSON *v, mr_object_desc *o, size_t frame_count)
{
    if (cJSON_IsObject(v)) {
        o->poses = calloc(1, sizeof *o->poses);
        if (!o->poses)
            return fail_nomem(c);
        o->pose_count = 1;
        return parse_pose(c, v, &o->poses[0]);
    }
    if (!cJSON_IsArray(v))
        return fail_expected(c, "a pose object or an array of pose objects (one per frame)", v);
    size_t n = (size_t)cJSON_GetArraySize(v);
    if (n != frame_count)
        return fail(c, MR_ERR_INVALID,
                    "expected one pose per frame (%zu frame%s), got an array of %zu pose%s",
                    frame_count, frame_count == 1 ? "" : "s", n, n == 1 ? "" : "s");
    o->poses = calloc(n, sizeof *o->poses);
    if (!o->poses)
        return fail_nomem(c);
    o->pose_count = n;
    size_t i = 0;
    for (const cJSON *p = v->child; p; p = p->next, i++)
        AT_INDEX(c, i, parse_pose(c, p, &o->poses[i]));
    return MR_OK;
}

/* Index of v's string in names, or a failure naming the choices. */
static int get_choice(jctx *c, const cJSON *v, const char *const *names, size_t count,
                      const char *expected, int *out)
{
    if (cJSON_IsString(v))
        for (size_t i = 0; i < count; i++)
            if (strcmp(v->valuestring, names[i]) == 0) {
                *out = (int)i;
                return MR_OK;
            }
    return fail_expected(c, expected, v);
}

/* "one of: \"a\", \"b\"" for a choice list. */
static void choices_text(const char *const *names, size_t count, char *buf, size_t n)
{
    size_t o = (size_t)snprintf(buf, n, "one of: ");
    for (size_t i = 0; i < count && o < n; i++)
        o += (size_t)snprintf(buf + o, n - o, "%s\"%s\"", i ? ", " : "", names[i]);
}

/* ------------------------------------------------------------------------ */
/* A kind's parameter block, read from its table (core/kinds/params.h).     */

#define PARAM_AT(values, off, type) ((type *)((char *)(values) + (off)))

static num_spec param_spec(const mr_param *p)
{
    unsigned flags = (p->type == MR_PARAM_INT ? NUM_INT : 0u) |
                     ((p->flags & MR_PARAM_LO_OPEN) ? NUM_LO_OPEN : 0u) |
                     ((p->flags & MR_PARAM_HI_OPEN) ? NUM_HI_OPEN : 0u);
    return (num_spec){p->lo, p->hi, flags, p->expect};
}

static int parse_params(jctx *c, const cJSON *v, const mr_param_table *t, void *values,
                        bool flag_object);

/* Fails at the hook's field with its message. */
static int fail_param(jctx *c, const mr_param_error *pe)
{
    if (pe->field[0])
        push_key(c, pe->field);
    return fail(c, pe->code ? pe->code : MR_ERR_INVALID, "%s", pe->message);
}

static int parse_param_array(jctx *c, const cJSON *v, const mr_param *p, void *values)
{
    char expect[128];
    snprintf(expect, sizeof expect, "an array of 1..%zu %s", p->max_items, p->sub->plural);
    if (!cJSON_IsArray(v) || cJSON_GetArraySize(v) == 0)
        return fail_expected(c, expect, v);
    size_t n = (size_t)cJSON_GetArraySize(v);
    if (n > p->max_items)
        return fail(c, MR_ERR_LIMIT, "expected at most %zu %s, got %zu", p->max_items, p->field, n);
    char *items = calloc(n, p->sub->size);
    if (!items)
        return fail_nomem(c);
    *PARAM_AT(values, p->offset, char *) = items;
    *PARAM_AT(values, p->count_offset, size_t) = n;
    size_t i = 0;
    for (const cJSON *e = v->child; e; e = e->next, i++) {
        void *item = items + i * p->sub->size;
        mr_params_defaults(p->sub, item);
        AT_INDEX(c, i, parse_params(c, e, p->sub, item, false));
    }
    return MR_OK;
}

static int parse_param(jctx *c, const cJSON *v, const mr_param *p, void *values)
{
    double x;
    int choice;
    num_spec spec = param_spec(p);
    switch (p->type) {
    case MR_PARAM_INT:
        TRY(get_num(c, v, &spec, &x));
        *PARAM_AT(values, p->offset, uint32_t) = (uint32_t)x;
        return MR_OK;
    case MR_PARAM_NUMBER:
        TRY(get_num(c, v, &spec, &x));
        *PARAM_AT(values, p->offset, float) = (float)x;
        return MR_OK;
    case MR_PARAM_BOOL:
        return get_bool(c, v, PARAM_AT(values, p->offset, bool));
    case MR_PARAM_ENUM: {
        char expect[256];
        if (p->expect)
            snprintf(expect, sizeof expect, "%s", p->expect);
        else
            choices_text(p->choices, p->choice_count, expect, sizeof expect);
        TRY(get_choice(c, v, p->choices, p->choice_count, expect, &choice));
        *PARAM_AT(values, p->offset, int) = choice;
        return MR_OK;
    }
    case MR_PARAM_FLAG_OBJECT:
        if (cJSON_IsBool(v)) {
            *PARAM_AT(values, p->offset, bool) = cJSON_IsTrue(v);
            return MR_OK;
        }
        TRY(parse_params(c, v, p->sub, values, true));
        *PARAM_AT(values, p->offset, bool) = true;
        return MR_OK;
    case MR_PARAM_ARRAY:
        return parse_param_array(c, v, p, values);
    case MR_PARAM_TRANSFORM:
        return get_transform(c, v, PARAM_AT(values, p->offset, mr_mat4));
    case MR_PARAM_POSE:
        TRY(parse_pose(c, v, PARAM_AT(values, p->offset, mr_pose_desc)));
        *PARAM_AT(values, p->present_offset, bool) = true;
        return MR_OK;
    }
    return fail(c, MR_ERR_INVALID, "unsupported parameter type");
}

/* Reads object v into values (already holding the table's defaults):
 * known and unique keys, then every field in table order, each followed by
 * its after hook. flag_object: v is a FLAG_OBJECT's object form. */
static int parse_params(jctx *c, const cJSON *v, const mr_param_table *t, void *values,
                        bool flag_object)
{
    const char *names[MR_PARAM_MAX_FIELDS];
    bool given[MR_PARAM_MAX_FIELDS] = {false};
    (void)flag_object;
    TRY(want_object(c, v, t->expect));
    for (size_t i = 0; i < t->count; i++)
        names[i] = t->params[i].field;
    TRY(check_fields(c, v, names, t->count));
    for (size_t i = 0; i < t->count; i++)
        given[i] = field(v, names[i]) != NULL;
    for (size_t i = 0; i < t->count; i++) {
        const mr_param *p = &t->params[i];
        const cJSON *fv = field(v, p->field);
        if (fv && p->conflicts) {
            int k = mr_param_index(t, p->conflicts);
            if (k >= 0 && given[k]) {
                push_key(c, p->conflicts);
                return fail(c, MR_ERR_INVALID, "give either \"%s\" or \"%s\", not both", p->field,
                            p->conflicts);
            }
        }
        if (fv)
            AT_KEY(c, p->field, parse_param(c, fv, p, values));
        if (p->after) {
            mr_param_error pe = {0};
            if (p->after(values, given, &pe) < 0)
                return fail_param(c, &pe);
        }
    }
    return MR_OK;
}

static const char *const OBJECT_FIELDS_HEAD[] = {"name", "asset", "kind"};
static const char *const OBJECT_FIELDS_TAIL[] = {"transform", "color", "pose"};

/* The keys an object may have: its own, and after "kind" each registered
 * kind's parameter block, in registry order. */
static size_t object_fields(const char **names, size_t cap)
{
    size_t n = 0;
    for (size_t i = 0; i < COUNT_OF(OBJECT_FIELDS_HEAD) && n < cap; i++)
        names[n++] = OBJECT_FIELDS_HEAD[i];
    for (size_t i = 0; i < mr_kind_count() && n < cap; i++)
        if (mr_kind_at(i)->params)
            names[n++] = mr_kind_at(i)->name;
    for (size_t i = 0; i < COUNT_OF(OBJECT_FIELDS_TAIL) && n < cap; i++)
        names[n++] = OBJECT_FIELDS_TAIL[i];
    return n;
}

static int parse_kind(jctx *c, const cJSON *v, const mr_kind **out)
{
    const char *names[32];
    size_t n = 0;
    for (size_t i = 0; i < mr_kind_count() && n < COUNT_OF(names); i++)
        names[n++] = mr_kind_at(i)->name;
    char expect[512];
    choices_text(names, n, expect, sizeof expect);
    int choice = 0;
    TRY(get_choice(c, v, names, n, expect, &choice));
    *out = mr_kind_at((size_t)choice);
    return MR_OK;
}

static int parse_object(jctx *c, const cJSON *v, mr_job *job, size_t index, mr_object_desc *o)
{
    const char *fields[MR_PARAM_MAX_FIELDS];
    size_t field_count = object_fields(fields, COUNT_OF(fields));
    TRY(want_object(c, v, "an object description"));
    TRY(check_fields(c, v, fields, field_count));
    TRY(require(c, v, "asset"));
    const cJSON *name = field(v, "name"), *kind = field(v, "kind"), *xf = field(v, "transform"),
                *color = field(v, "color"), *pose = field(v, "pose");
    if (name) {
        AT_KEY(c, "name", get_string(c, name, MR_MAX_NAME, &o->name));
    } else {
        char buf[32];
        snprintf(buf, sizeof buf, "object%zu", index);
        TRY(dup_string(c, buf, &o->name));
    }
    AT_KEY(c, "asset", find_asset(c, field(v, "asset"), job, &o->asset));
    o->kind = mr_kind_at(0); /* the default kind: triangle meshes */
    if (kind)
        AT_KEY(c, "kind", parse_kind(c, kind, &o->kind));
    if (o->kind->params) {
        if (!(o->params = calloc(1, o->kind->params->size)))
            return fail_nomem(c);
        mr_params_defaults(o->kind->params, o->params);
    }
    for (size_t i = 0; i < mr_kind_count(); i++) {
        const mr_kind *k = mr_kind_at(i);
        const cJSON *block = k->params ? field(v, k->name) : NULL;
        if (!block)
            continue;
        if (k != o->kind) {
            push_key(c, k->name);
            return fail(c, MR_ERR_INVALID, "\"%s\" parameters need \"kind\": \"%s\"", k->name,
                        k->name);
        }
        AT_KEY(c, k->name, parse_params(c, block, k->params, o->params, false));
    }
    o->transform = mr_mat4_identity();
    if (xf)
        AT_KEY(c, "transform", get_transform(c, xf, &o->transform));
    o->color = mr_v3(0.8f, 0.8f, 0.8f);
    if (color)
        AT_KEY(c, "color", get_vec3(c, color, &SPEC_COLOR, &o->color));
    if (pose)
        AT_KEY(c, "pose", parse_object_pose(c, pose, o, job->frame_count));
    return MR_OK;
}

static int parse_objects(jctx *c, const cJSON *v, mr_job *job)
{
    if (!cJSON_IsArray(v) || cJSON_GetArraySize(v) == 0)
        return fail_expected(c, "an array of 1..1024 objects", v);
    size_t n = (size_t)cJSON_GetArraySize(v);
    if (n > MR_MAX_OBJECTS)
        return fail(c, MR_ERR_LIMIT, "expected at most %d objects, got %zu", MR_MAX_OBJECTS, n);
    job->objects = calloc(n, sizeof *job->objects);
    if (!job->objects)
        return fail_nomem(c);
    job->object_count = n;
    size_t i = 0;
    for (const cJSON *o = v->child; o; o = o->next, i++)
        AT_INDEX(c, i, parse_object(c, o, job, i, &job->objects[i]));
    return MR_OK;
}

static const char *const LIGHT_FIELDS[] = {"direction", "color", "intensity"};

static int parse_light(jctx *c, const cJSON *v, mr_light_desc *l)
{
    TRY(want_object(c, v, "a light object"));
    TRY(check_fields(c, v, LIGHT_FIELDS, COUNT_OF(LIGHT_FIELDS)));
    TRY(require(c, v, "direction"));
    double col[3] = {1, 1, 1}, intensity = 1;
    const cJSON *color = field(v, "color"), *inten = field(v, "intensity");
    AT_KEY(c, "direction", get_unit_vec3(c, field(v, "direction"), &l->direction));
    if (color)
        AT_KEY(c, "color", get_numbers(c, color, 3, &SPEC_COLOR, "an array of 3 numbers", col));
    if (inten)
        AT_KEY(c, "intensity", get_num(c, inten, &SPEC_COLOR, &intensity));
    l->color = mr_v3((float)(col[0] * intensity), (float)(col[1] * intensity),
                     (float)(col[2] * intensity));
    return MR_OK;
}

static int parse_lights(jctx *c, const cJSON *v, mr_job *job)
{
    if (!v) {
        /* No "lights": one sun from above, front left, so a job without
         * lighting still shows shape. */
        double d[3] = {-0.4, -1.0, -0.6};
        normalize_d(d, 3);
        job->lights = malloc(sizeof *job->lights);
        if (!job->lights)
            return fail_nomem(c);
        job->light_count = 1;
        job->lights[0].direction = mr_v3((float)d[0], (float)d[1], (float)d[2]);
        job->lights[0].color = mr_v3(1, 1, 1);
        return MR_OK;
    }
    if (!cJSON_IsArray(v))
        return fail_expected(c, "an array of 0..64 lights", v);
    size_t n = (size_t)cJSON_GetArraySize(v);
    if (n > MR_MAX_LIGHTS)
        return fail(c, MR_ERR_LIMIT, "expected at most %d lights, got %zu", MR_MAX_LIGHTS, n);
    if (n == 0)
        return MR_OK;
    job->lights = calloc(n, sizeof *job->lights);
    if (!job->lights)
        return fail_nomem(c);
    job->light_count = n;
    size_t i = 0;
    for (const cJSON *l = v->child; l; l = l->next, i++)
        AT_INDEX(c, i, parse_light(c, l, &job->lights[i]));
    return MR_OK;
}

static const char *const BACKGROUND_FIELDS[] = {"color", "alpha"};

static int parse_background(jctx *c, const cJSON *v, mr_job *job)
{
    TRY(want_object(c, v, "a background object"));
    TRY(check_fields(c, v, BACKGROUND_FIELDS, COUNT_OF(BACKGROUND_FIELDS)));
    const cJSON *color = field(v, "color"), *alpha = field(v, "alpha");
    if (color)
        AT_KEY(c, "color", get_vec3(c, color, &SPEC_COLOR, &job->background));
    if (alpha) {
        double a;
        AT_KEY(c, "alpha", get_num(c, alpha, &SPEC_ALPHA, &a));
        job->background_alpha = (float)a;
    }
    return MR_OK;
}

static const char *const KEY_FIELDS[] = {"t", "position", "target", "rotation", "yfov"};

static int parse_camera_key(jctx *c, const cJSON *v, mr_camera_key *k, float default_yfov,
                            const mr_camera_key *prev)
{
    TRY(want_object(c, v, "a camera key object"));
    TRY(check_fields(c, v, KEY_FIELDS, COUNT_OF(KEY_FIELDS)));
    TRY(require(c, v, "t"));
    TRY(require(c, v, "position"));
    const cJSON *target = field(v, "target"), *rot = field(v, "rotation"), *yfov = field(v, "yfov");
    if (target && rot)
        return fail(c, MR_ERR_INVALID,
                    "expected exactly one of \"target\" or \"rotation\", got both");
    if (!target && !rot)
        return fail(c, MR_ERR_INVALID, "missing required field: \"target\" or \"rotation\"");
    /* Every key's time is under the time cap, not only the first one's: a
     * later key at 1e300 would make the differences of key times overflow. */
    AT_KEY(c, "t", get_num(c, field(v, "t"), &SPEC_TIME, &k->t));
    if (prev && !(k->t > prev->t)) {
        char expect[96];
        snprintf(expect, sizeof expect, "a time greater than the previous key's (%.15g)", prev->t);
        push_key(c, "t");
        return fail_expected(c, expect, field(v, "t"));
    }
    AT_KEY(c, "position", get_vec3(c, field(v, "position"), &SPEC_COORD, &k->position));
    k->rotation = mr_quat_identity();
    if (target) {
        AT_KEY(c, "target", get_vec3(c, target, &SPEC_COORD, &k->target));
        /* Compared as stored (float): that is what the look-at will see. */
        if (k->target.x == k->position.x && k->target.y == k->position.y &&
            k->target.z == k->position.z) {
            push_key(c, "target");
            return fail(c, MR_ERR_INVALID,
                        "expected a target different from \"position\", got the same point");
        }
        k->has_target = true;
    } else {
        AT_KEY(c, "rotation", get_quat(c, rot, &k->rotation));
    }
    k->yfov = default_yfov;
    if (yfov) {
        double deg;
        AT_KEY(c, "yfov", get_num(c, yfov, &SPEC_YFOV, &deg));
        k->yfov = (float)(deg * DEG_TO_RAD);
    }
    return MR_OK;
}

static const char *const NODE_FIELDS[] = {"asset", "name"};

static int parse_camera_node(jctx *c, const cJSON *v, mr_job *job)
{
    TRY(want_object(c, v, "a camera node object {\"asset\", \"name\"}"));
    TRY(check_fields(c, v, NODE_FIELDS, COUNT_OF(NODE_FIELDS)));
    TRY(require(c, v, "asset"));
    TRY(require(c, v, "name"));
    AT_KEY(c, "asset", find_asset(c, field(v, "asset"), job, &job->camera.node_asset));
    AT_KEY(c, "name", get_string(c, field(v, "name"), MR_MAX_NAME, &job->camera.node_name));
    job->camera.source = MR_CAMERA_SOURCE_NODE;
    return MR_OK;
}

static const char *const CAMERA_FIELDS[] = {"path", "interpolation", "up", "yfov", "node"};

static int parse_camera(jctx *c, const cJSON *v, mr_job *job)
{
    TRY(want_object(c, v, "a camera object"));
    TRY(check_fields(c, v, CAMERA_FIELDS, COUNT_OF(CAMERA_FIELDS)));
    const cJSON *path = field(v, "path"), *node = field(v, "node"),
                *interp = field(v, "interpolation"), *up = field(v, "up"),
                *yfov = field(v, "yfov");
    if (path && node)
        return fail(c, MR_ERR_INVALID, "expected exactly one of \"path\" or \"node\", got both");
    if (!path && !node)
        return fail(c, MR_ERR_INVALID, "missing required field: \"path\" or \"node\"");
    if (node) {
        const char *path_only[] = {"interpolation", "up", "yfov"};
        for (size_t i = 0; i < COUNT_OF(path_only); i++)
            if (field(v, path_only[i])) {
                push_key(c, path_only[i]);
                return fail(c, MR_ERR_INVALID, "\"%s\" only applies to \"path\" cameras",
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
            push_key(c, "interpolation");
            return fail_expected(c, "one of: \"linear\", \"catmull-rom\"", interp);
        }
    }
    if (up)
        AT_KEY(c, "up", get_unit_vec3(c, up, &cp->up));
    if (yfov)
        AT_KEY(c, "yfov", get_num(c, yfov, &SPEC_YFOV, &deg));
    float default_yfov = (float)(deg * DEG_TO_RAD);
    if (!cJSON_IsArray(path) || cJSON_GetArraySize(path) == 0) {
        push_key(c, "path");
        return fail_expected(c, "an array of 1..10000 camera keys", path);
    }
    size_t n = (size_t)cJSON_GetArraySize(path);
    if (n > MR_MAX_CAMERA_KEYS) {
        push_key(c, "path");
        return fail(c, MR_ERR_LIMIT, "expected at most %d camera keys, got %zu", MR_MAX_CAMERA_KEYS,
                    n);
    }
    cp->keys = calloc(n, sizeof *cp->keys);
    if (!cp->keys)
        return fail_nomem(c);
    cp->key_count = n;
    size_t mark = push_key(c, "path"), i = 0;
    for (const cJSON *k = path->child; k; k = k->next, i++)
        AT_INDEX(c, i,
                 parse_camera_key(c, k, &cp->keys[i], default_yfov, i ? &cp->keys[i - 1] : NULL));
    pop(c, mark);
    return MR_OK;
}

static const char *const OUTPUT_FIELDS[] = {"width",       "height", "samples",  "shadows",
                                            "seed",        "compression", "zip_level"};

static int parse_output(jctx *c, const cJSON *v, mr_job *job)
{
    TRY(want_object(c, v, "an output object"));
    TRY(check_fields(c, v, OUTPUT_FIELDS, COUNT_OF(OUTPUT_FIELDS)));
    mr_output_desc *o = &job->output;
    const cJSON *w = field(v, "width"), *h = field(v, "height"), *spp = field(v, "samples"),
                *shadows = field(v, "shadows"), *seed = field(v, "seed"),
                *comp = field(v, "compression"), *zip = field(v, "zip_level");
    double d;
    if (w) {
        AT_KEY(c, "width", get_num(c, w, &SPEC_SIZE, &d));
        o->width = (int)d;
    }
    if (h) {
        AT_KEY(c, "height", get_num(c, h, &SPEC_SIZE, &d));
        o->height = (int)d;
    }
    uint64_t pixels = (uint64_t)o->width * (uint64_t)o->height;
    if (pixels > MR_MAX_PIXELS)
        return fail(c, MR_ERR_LIMIT,
                    "expected at most %u pixels (width * height), got %d x %d = %llu",
                    (unsigned)MR_MAX_PIXELS, o->width, o->height, (unsigned long long)pixels);
    if (spp) {
        AT_KEY(c, "samples", get_num(c, spp, &SPEC_SPP, &d));
        o->spp = (int)d;
    }
    if (shadows)
        AT_KEY(c, "shadows", get_bool(c, shadows, &o->shadows));
    if (seed) {
        AT_KEY(c, "seed", get_num(c, seed, &SPEC_SEED, &d));
        o->seed = (uint32_t)d;
    }
    if (comp &&
        !(cJSON_IsString(comp) && mr_compression_parse(comp->valuestring, &o->exr.compression))) {
        push_key(c, "compression");
        return fail_expected(c, "one of: \"none\", \"zip\", \"zips\", \"piz\"", comp);
    }
    if (zip) {
        AT_KEY(c, "zip_level", get_num(c, zip, &SPEC_ZIP, &d));
        o->exr.zip_level = (int)d;
    }
    return MR_OK;
}

static const char *const ROOT_FIELDS[] = {"name",   "priority", "max_retries", "assets",
                                          "objects", "lights", "ambient",     "background",
                                          "camera",  "frames",   "output"};

static void set_defaults(mr_job *job)
{
    job->ambient = mr_v3(0.15f, 0.15f, 0.15f);
    job->background = mr_v3(0.1f, 0.1f, 0.12f);
    job->background_alpha = 1.0f;
    job->fps = 24;
    job->max_retries = 2;
    job->output.width = 640;
    job->output.height = 360;
    job->output.spp = 1;
    job->output.shadows = true;
    job->output.seed = 0;
    job->output.exr.compression = MR_COMPRESSION_ZIP;
    job->output.exr.zip_level = MR_ZIP_LEVEL_DEFAULT;
}

static int parse_root(jctx *c, const cJSON *root, mr_job *job)
{
    TRY(want_object(c, root, "a JSON object"));
    TRY(check_fields(c, root, ROOT_FIELDS, COUNT_OF(ROOT_FIELDS)));
    TRY(require(c, root, "assets"));
    TRY(require(c, root, "objects"));
    TRY(require(c, root, "camera"));
    TRY(require(c, root, "frames"));
    set_defaults(job);
    const cJSON *name = field(root, "name"), *lights = field(root, "lights"),
                *ambient = field(root, "ambient"), *background = field(root, "background"),
                *output = field(root, "output");
    if (name)
        AT_KEY(c, "name", get_string(c, name, MR_MAX_NAME, &job->name));
    else
        TRY(dup_string(c, "job", &job->name));
    const cJSON *priority = field(root, "priority"), *retries = field(root, "max_retries");
    double d;
    if (priority) {
        static const num_spec spec = {-MR_MAX_PRIORITY, MR_MAX_PRIORITY, NUM_INT, NULL};
        AT_KEY(c, "priority", get_num(c, priority, &spec, &d));
        job->priority = (int)d;
    }
    if (retries) {
        static const num_spec spec = {0, MR_MAX_RETRIES, NUM_INT, NULL};
        AT_KEY(c, "max_retries", get_num(c, retries, &spec, &d));
        job->max_retries = (int)d;
    }
    AT_KEY(c, "assets", parse_assets(c, field(root, "assets"), job));
    /* Before "objects": per-frame pose arrays are checked against the count. */
    AT_KEY(c, "frames", parse_frames(c, field(root, "frames"), job));
    AT_KEY(c, "objects", parse_objects(c, field(root, "objects"), job));
    AT_KEY(c, "camera", parse_camera(c, field(root, "camera"), job));
    AT_KEY(c, "lights", parse_lights(c, lights, job));
    if (ambient)
        AT_KEY(c, "ambient", get_vec3(c, ambient, &SPEC_COLOR, &job->ambient));
    if (background)
        AT_KEY(c, "background", parse_background(c, background, job));
    if (output)
        AT_KEY(c, "output", parse_output(c, output, job));
    return MR_OK;
}

/* ------------------------------------------------------------------------ */
/* Entry point.                                                             */

/* Refuses raw NUL bytes and invalid UTF-8, and rewrites "\u0000" escapes
 * to "\u0001" in the private copy (same length, so byte offsets in later
 * messages still match the caller's input). Only escapes inside strings are
 * touched; malformed input is left for cJSON to report. */
static int prescan(jctx *c, char *text, size_t len)
{
    bool in_str = false, esc = false;
    for (size_t i = 0; i < len; i++) {
        char ch = text[i];
        if (ch == '\0')
            return fail(c, MR_ERR_INVALID, "malformed JSON: NUL byte at byte offset %zu", i);
        if (esc) {
            esc = false;
            if (ch == 'u' && len - i > 4 && memcmp(text + i + 1, "0000", 4) == 0) {
                text[i + 4] = '1';
                c->nul_escapes = true;
            }
        } else if (in_str) {
            if (ch == '\\')
                esc = true;
            else if (ch == '"')
                in_str = false;
        } else if (ch == '"') {
            in_str = true;
        }
    }
    /* RFC 8259 requires UTF-8. Checking the whole text (which now has no
     * NUL before text[len]) also keeps unknown keys and quoted values valid
     * UTF-8 when they are echoed in pointers and messages. */
    size_t bad = utf8_invalid_at(text);
    if (bad != SIZE_MAX)
        return fail(c, MR_ERR_INVALID, "malformed JSON: invalid UTF-8 at byte offset %zu", bad);
    return MR_OK;
}

static int fail_syntax(jctx *c, const char *text, size_t len, size_t off, const char *what)
{
    size_t line = 1, col = 1;
    char near[32];
    for (size_t i = 0; i < off && i < len; i++) {
        if (text[i] == '\n') {
            line++;
            col = 1;
        } else {
            col++;
        }
    }
    if (off >= len)
        snprintf(near, sizeof near, "the end of the input");
    else if ((unsigned char)text[off] >= 0x20 && (unsigned char)text[off] < 0x7F)
        snprintf(near, sizeof near, "'%c'", text[off]);
    else
        snprintf(near, sizeof near, "byte 0x%02x", (unsigned)(unsigned char)text[off]);
    return fail(c, MR_ERR_INVALID, "%s at byte offset %zu (line %zu, column %zu), near %s", what,
                off, line, col, near);
}

int mr_job_parse(const char *json, size_t len, mr_job **out, mr_job_error *err)
{
    mr_job_error scratch;
    jctx c;
    char *text = NULL;
    cJSON *root = NULL;
    mr_job *job = NULL;
    const char *end = NULL;
    size_t off;
    int rc;

    memset(&c, 0, sizeof c);
    c.err = err ? err : &scratch;
    c.err->pointer[0] = '\0';
    c.err->message[0] = '\0';
    if (out)
        *out = NULL;
    if (!out || (!json && len > 0)) {
        rc = fail(&c, MR_ERR_INVALID, "no job given");
        goto cleanup;
    }
    if (len > MR_JOB_MAX_BYTES) {
        rc = fail(&c, MR_ERR_LIMIT, "expected a job of at most %u bytes, got %zu bytes",
                  (unsigned)MR_JOB_MAX_BYTES, len);
        goto cleanup;
    }
    text = malloc(len + 1);
    if (!text) {
        rc = fail_nomem(&c);
        goto cleanup;
    }
    if (len > 0)
        memcpy(text, json, len);
    text[len] = '\0';
    rc = prescan(&c, text, len);
    if (rc < 0)
        goto cleanup;
    root = cJSON_ParseWithLengthOpts(text, len, &end, 0);
    if (!root) {
        off = end && end >= text ? (size_t)(end - text) : 0;
        rc = fail_syntax(&c, text, len, off, "malformed JSON");
        goto cleanup;
    }
    off = end && end >= text ? (size_t)(end - text) : len;
    while (off < len && (text[off] == ' ' || text[off] == '\t' || text[off] == '\n' ||
                         text[off] == '\r'))
        off++;
    if (off < len) {
        rc = fail_syntax(&c, text, len, off, "malformed JSON: unexpected data after the job");
        goto cleanup;
    }
    job = calloc(1, sizeof *job);
    if (!job) {
        rc = fail_nomem(&c);
        goto cleanup;
    }
    rc = parse_root(&c, root, job);
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
