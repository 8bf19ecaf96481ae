/* json_reader.c - reading untrusted JSON with pointers and messages (json_reader.h). */
#include "json_reader.h"

#include <float.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* ------------------------------------------------------------------------ */
/* The JSON pointer of the value being read.                                */

/* Appends "/key" (escaped per RFC 6901) and returns the length to pop back
 * to. An absurdly long key is cut at a UTF-8 boundary rather than overflow. */
size_t json_push_key(mr_json_ctx *c, const char *key)
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

size_t json_push_index(mr_json_ctx *c, size_t i)
{
    char buf[32];
    snprintf(buf, sizeof buf, "%zu", i);
    return json_push_key(c, buf);
}

void json_pop(mr_json_ctx *c, size_t mark)
{
    c->len = mark;
    c->ptr[mark] = '\0';
}

int json_fail(mr_json_ctx *c, int code, const char *fmt, ...)
{
    va_list ap;
    bool first = !c->all || (c->all->count == 0 && c->all->more == 0);
    mr_json_error *e = NULL;
    if (c->all && c->all->count < MR_JSON_ERRORS_MAX)
        e = &c->all->items[c->all->count++];
    else if (c->all)
        c->all->more++;
    if (first)
        memset(c->err, 0, sizeof *c->err);
    if (first)
        memcpy(c->err->pointer, c->ptr, c->len + 1);
    if (e) {
        memset(e, 0, sizeof *e);
        memcpy(e->pointer, c->ptr, c->len + 1);
    }
    va_start(ap, fmt);
    char message[sizeof c->err->message];
    vsnprintf(message, sizeof message, fmt, ap);
    va_end(ap);
    if (first)
        memcpy(c->err->message, message, sizeof message);
    if (e)
        memcpy(e->message, message, sizeof message);
    return code;
}

void json_errors_add(mr_json_errors *all, const char *pointer, const char *message)
{
    if (all->count >= MR_JSON_ERRORS_MAX) {
        all->more++;
        return;
    }
    mr_json_error *e = &all->items[all->count++];
    memset(e, 0, sizeof *e);
    snprintf(e->pointer, sizeof e->pointer, "%s", pointer ? pointer : "");
    snprintf(e->message, sizeof e->message, "%s", message ? message : "");
}

bool json_go_on(mr_json_ctx *c, int rc)
{
    if (!c->all || rc == MR_ERR_NOMEM)
        return false;
    if (c->first_rc == 0)
        c->first_rc = rc;
    return true;
}

/* The problem just recorded (the first, and the last of the list) is one
 * of syntax. */
static int mark_syntax(mr_json_ctx *c, int rc)
{
    if (rc == MR_ERR_NOMEM || rc == MR_ERR_LIMIT)
        return rc;
    c->err->syntax = true;
    if (c->all && c->all->count > 0)
        c->all->items[c->all->count - 1].syntax = true;
    return rc;
}

int json_fail_nomem(mr_json_ctx *c) { return json_fail(c, MR_ERR_NOMEM, "out of memory"); }




/* ------------------------------------------------------------------------ */
/* Describing what was found, for "expected X, got Y" messages.             */

/* Writes s as a short quoted JSON-ish string, cut at a UTF-8 boundary. */
void json_quote(const char *s, char *buf, size_t n)
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

const char *json_describe(const cJSON *v, char *buf, size_t n)
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
        json_quote(v->valuestring, buf, n);
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

int json_fail_expected(mr_json_ctx *c, const char *expect, const cJSON *v)
{
    char got[256];
    return json_fail(c, MR_ERR_INVALID, "expected %s, got %s", expect, json_describe(v, got, sizeof got));
}

/* ------------------------------------------------------------------------ */
/* Scalars.                                                                 */


const json_num_spec JSON_SPEC_FLOAT = {-FLT_MAX, FLT_MAX, 0,
                                    "a number within the 32-bit float range (|x| <= 3.4e38)"};

void json_spec_text(const json_num_spec *s, char *buf, size_t n)
{
    if (s->expect)
        snprintf(buf, n, "%s", s->expect);
    else if (s->flags & JSON_NUM_INT)
        snprintf(buf, n, "an integer in %.15g..%.15g", s->lo, s->hi);
    else if (s->flags & (JSON_NUM_LO_OPEN | JSON_NUM_HI_OPEN))
        snprintf(buf, n, "a number in %c%.15g, %.15g%c", (s->flags & JSON_NUM_LO_OPEN) ? '(' : '[',
                 s->lo, s->hi, (s->flags & JSON_NUM_HI_OPEN) ? ')' : ']');
    else
        snprintf(buf, n, "a number in %.15g..%.15g", s->lo, s->hi);
}

/* Whether x is within s's range. Every test is false for NaN/inf, so the
 * cast to integers later only ever sees finite, integral, in-range
 * doubles. */
static bool in_spec(const json_num_spec *s, double x)
{
    bool ok = isfinite(x) && x >= s->lo && x <= s->hi;
    if (ok && (s->flags & JSON_NUM_INT))
        ok = x == floor(x);
    if (ok && (s->flags & JSON_NUM_LO_OPEN))
        ok = x > s->lo;
    if (ok && (s->flags & JSON_NUM_HI_OPEN))
        ok = x < s->hi;
    return ok;
}

int json_get_num(mr_json_ctx *c, const cJSON *v, const json_num_spec *s, double *out)
{
    double x = cJSON_IsNumber(v) ? v->valuedouble : NAN;
    const bool ok = in_spec(s, x);
    if (!ok || ((s->flags & JSON_NUM_FLOAT) && !in_spec(s, (double)(float)x))) {
        char expect[160];
        json_spec_text(s, expect, sizeof expect);
        if (ok) /* only its float is out */
            snprintf(expect + strlen(expect), sizeof expect - strlen(expect), " (as a 32-bit float)");
        return json_fail_expected(c, expect, v);
    }
    *out = x;
    return MR_OK;
}

int json_get_bool(mr_json_ctx *c, const cJSON *v, bool *out)
{
    if (!cJSON_IsBool(v))
        return json_fail_expected(c, "a boolean (true or false)", v);
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

void json_utf8_text(const char *in, char *out, size_t size)
{
    size_t o = 0;
    while (*in && o + 1 < size) {
        const size_t bad = utf8_invalid_at(in);
        const size_t good = bad == SIZE_MAX ? strlen(in) : bad;
        const size_t n = good < size - 1 - o ? good : size - 1 - o;
        memcpy(out + o, in, n);
        o += n, in += n;
        if (n < good) { /* out is full: no character cut in two */
            out[o] = '\0';
            while (o > 0 && utf8_invalid_at(out) != SIZE_MAX)
                out[--o] = '\0';
            return;
        }
        if (!*in)
            break;
        if (o + 5 > size)
            break;
        snprintf(out + o, 5, "\\x%02X", (unsigned char)*in++);
        o += 4;
    }
    if (size)
        out[o < size ? o : size - 1] = '\0';
}

/* Checks a string the job keeps (name, path, key): 1..max bytes, valid
 * UTF-8, no control characters (which also catches "\u0000", see top). */
int json_check_text(mr_json_ctx *c, const char *s, size_t max)
{
    size_t n = strlen(s), bad;
    if (n == 0 || n > max) {
        char got[128];
        if (n == 0)
            snprintf(got, sizeof got, "an empty string");
        else
            snprintf(got, sizeof got, "%zu bytes", n);
        return json_fail(c, MR_ERR_INVALID, "expected a string of 1..%zu bytes, got %s", max, got);
    }
    for (size_t i = 0; i < n; i++) {
        unsigned ch = (unsigned char)s[i];
        if (ch < 0x20 || ch == 0x7F) {
            /* Most likely the rewritten NUL: name what the user wrote. */
            if (ch == 0x01 && c->nul_escapes)
                ch = 0;
            return json_fail(c, MR_ERR_INVALID,
                        "expected a string without control characters, found U+%04X at byte %zu",
                        ch, i);
        }
    }
    bad = utf8_invalid_at(s);
    if (bad != SIZE_MAX)
        return json_fail(c, MR_ERR_INVALID, "expected valid UTF-8, found an invalid byte at byte %zu",
                    bad);
    return MR_OK;
}

int json_dup_string(mr_json_ctx *c, const char *s, char **out)
{
    size_t n = strlen(s) + 1;
    char *d = malloc(n);
    if (!d)
        return json_fail_nomem(c);
    memcpy(d, s, n);
    *out = d;
    return MR_OK;
}

/* Type, length and content checks, then a copy into *out. */
int json_get_string(mr_json_ctx *c, const cJSON *v, size_t max, char **out)
{
    if (!cJSON_IsString(v) || !v->valuestring) {
        char expect[64];
        snprintf(expect, sizeof expect, "a string of 1..%zu bytes", max);
        return json_fail_expected(c, expect, v);
    }
    TRY(json_check_text(c, v->valuestring, max));
    return json_dup_string(c, v->valuestring, out);
}

/* ------------------------------------------------------------------------ */
/* Objects: allowed keys, duplicates, required keys.                        */

const cJSON *json_field(const cJSON *obj, const char *key)
{
    return cJSON_GetObjectItemCaseSensitive(obj, key);
}

int json_want_object(mr_json_ctx *c, const cJSON *v, const char *expect)
{
    return cJSON_IsObject(v) ? MR_OK : json_fail_expected(c, expect, v);
}

/* Refuses unknown and repeated keys. A repeated key is caught at its second
 * occurrence, so even an object with millions of copies of one allowed key
 * costs O(keys * allowed). */
int json_check_fields(mr_json_ctx *c, const cJSON *obj, const char *const *allowed, size_t n)
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
            json_push_key(c, key);
            return json_fail(c, MR_ERR_INVALID, "unknown field; expected one of: %s", list);
        }
        if (seen & (1u << i)) {
            json_push_key(c, key);
            return json_fail(c, MR_ERR_INVALID, "duplicate field \"%s\"", key);
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
int json_check_unique_keys(mr_json_ctx *c, const cJSON *obj, size_t n)
{
    key_ref *refs = malloc((n ? n : 1) * sizeof *refs);
    size_t i = 0, first_repeat = SIZE_MAX;
    const char *repeated = NULL;
    if (!refs)
        return json_fail_nomem(c);
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
        json_push_key(c, repeated);
        json_quote(repeated, q, sizeof q);
        return json_fail(c, MR_ERR_INVALID, "duplicate field %s", q);
    }
    return MR_OK;
}

int json_require(mr_json_ctx *c, const cJSON *obj, const char *key)
{
    if (json_field(obj, key))
        return MR_OK;
    return json_fail(c, MR_ERR_INVALID, "missing required field \"%s\"", key);
}

/* ------------------------------------------------------------------------ */
/* Vectors, quaternions, transforms.                                        */

int json_get_numbers(mr_json_ctx *c, const cJSON *v, size_t n, const json_num_spec *s, const char *expect,
                       double *out)
{
    if (!cJSON_IsArray(v) || (size_t)cJSON_GetArraySize(v) != n)
        return json_fail_expected(c, expect, v);
    size_t i = 0;
    for (const cJSON *e = v->child; e; e = e->next, i++)
        AT_INDEX(c, i, json_get_num(c, e, s, &out[i]));
    return MR_OK;
}

int json_get_vec3(mr_json_ctx *c, const cJSON *v, const json_num_spec *s, mr_vec3 *out)
{
    double d[3];
    TRY(json_get_numbers(c, v, 3, s, "an array of 3 numbers", d));
    *out = mr_v3((float)d[0], (float)d[1], (float)d[2]);
    return MR_OK;
}

int json_get_unit_vec3(mr_json_ctx *c, const cJSON *v, mr_vec3 *out)
{
    double d[3];
    TRY(json_get_numbers(c, v, 3, &JSON_SPEC_FLOAT, "an array of 3 numbers", d));
    if (!mr_normalize_d(d, 3))
        return json_fail(c, MR_ERR_INVALID, "expected a non-zero vector, got [0, 0, 0]");
    *out = mr_v3((float)d[0], (float)d[1], (float)d[2]);
    return MR_OK;
}

int json_get_quat(mr_json_ctx *c, const cJSON *v, mr_quat *out)
{
    double d[4];
    TRY(json_get_numbers(c, v, 4, &JSON_SPEC_FLOAT, "an array of 4 numbers [x, y, z, w]", d));
    if (!mr_normalize_d(d, 4))
        return json_fail(c, MR_ERR_INVALID,
                    "expected a non-zero quaternion [x, y, z, w], got one of length 0");
    *out = (mr_quat){(float)d[0], (float)d[1], (float)d[2], (float)d[3]};
    return MR_OK;
}


/* Index of v's string in names, or a failure naming the choices. */
int json_get_choice(mr_json_ctx *c, const cJSON *v, const char *const *names, size_t count,
                      const char *expected, int *out)
{
    if (cJSON_IsString(v))
        for (size_t i = 0; i < count; i++)
            if (strcmp(v->valuestring, names[i]) == 0) {
                *out = (int)i;
                return MR_OK;
            }
    return json_fail_expected(c, expected, v);
}

/* "one of: \"a\", \"b\"" for a choice list. */
void json_choices_text(const char *const *names, size_t count, char *buf, size_t n)
{
    size_t o = (size_t)snprintf(buf, n, "one of: ");
    for (size_t i = 0; i < count && o < n; i++)
        o += (size_t)snprintf(buf + o, n - o, "%s\"%s\"", i ? ", " : "", names[i]);
}

static bool is_hex(char ch)
{
    return (ch >= '0' && ch <= '9') || (ch >= 'a' && ch <= 'f') || (ch >= 'A' && ch <= 'F');
}

static bool is_digit(char ch) { return ch >= '0' && ch <= '9'; }

/* Length of the RFC 8259 number at t[0..len) (-? int frac? exp?, int
 * without leading zeros), or 0 if none starts there. cJSON would also take
 * 064, 64., 1.e1, +1 and read them as some other number. */
static size_t number_length(const char *t, size_t len)
{
    size_t i = 0;
    if (i < len && t[i] == '-')
        i++;
    if (i < len && t[i] == '0') {
        i++;
    } else if (i < len && t[i] >= '1' && t[i] <= '9') {
        while (i < len && is_digit(t[i]))
            i++;
    } else {
        return 0;
    }
    if (i < len && t[i] == '.') {
        if (!(i + 1 < len && is_digit(t[i + 1])))
            return 0;
        i++;
        while (i < len && is_digit(t[i]))
            i++;
    }
    if (i < len && (t[i] == 'e' || t[i] == 'E')) {
        i++;
        if (i < len && (t[i] == '+' || t[i] == '-'))
            i++;
        if (!(i < len && is_digit(t[i])))
            return 0;
        while (i < len && is_digit(t[i]))
            i++;
    }
    return i;
}

static int fail_syntax(mr_json_ctx *c, const char *text, size_t len, size_t off, const char *what);

/* Refuses what RFC 8259 forbids but cJSON lets through, before cJSON sees
 * it: raw NUL bytes, control characters between tokens (cJSON skips every
 * byte <= 0x20 as whitespace; inside strings json_check_text refuses them,
 * naming the field), \u escapes without four
 * hex digits (cJSON decodes "\uZZZZ" as U+0000 and silently cuts the
 * string there), numbers outside the JSON grammar, and invalid UTF-8. It
 * also rewrites "\u0000" escapes to "\u0001" in the private copy (same
 * length, so byte offsets in later messages still match the caller's
 * input), for the control-character check to name them. Structure (braces,
 * commas, literals) is left for cJSON to report. */
static int prescan(mr_json_ctx *c, char *text, size_t len)
{
    bool in_str = false, esc = false;
    for (size_t i = 0; i < len; i++) {
        char ch = text[i];
        unsigned char u = (unsigned char)ch;
        if (ch == '\0')
            return json_fail(c, MR_ERR_INVALID, "malformed JSON: NUL byte at byte offset %zu", i);
        if (esc) {
            esc = false;
            if (ch == 'u') {
                if (!(len - i > 4 && is_hex(text[i + 1]) && is_hex(text[i + 2]) &&
                      is_hex(text[i + 3]) && is_hex(text[i + 4])))
                    return fail_syntax(c, text, len, i - 1,
                                       "malformed JSON: a \\u escape needs four hex digits");
                if (memcmp(text + i + 1, "0000", 4) == 0) {
                    text[i + 4] = '1';
                    c->nul_escapes = true;
                }
            }
        } else if (in_str) {
            if (ch == '\\')
                esc = true;
            else if (ch == '"')
                in_str = false;
            /* raw control characters inside strings are left to
             * json_check_text, which names the field and the byte */
        } else if (ch == '"') {
            in_str = true;
        } else if (u < 0x20 && ch != ' ' && ch != '\t' && ch != '\n' && ch != '\r') {
            return fail_syntax(c, text, len, i,
                               "malformed JSON: control character outside a string");
        } else if (ch == '-' || is_digit(ch)) {
            size_t n = number_length(text + i, len - i);
            /* the number must end where the grammar says: no 064, 64., 1.e1 */
            char next = i + n < len ? text[i + n] : ' ';
            if (n == 0 || is_digit(next) || next == '.' || next == 'e' || next == 'E' ||
                next == '+' || next == '-')
                return fail_syntax(c, text, len, i,
                                   "malformed JSON: not a number by RFC 8259 (no leading zeros, "
                                   "digits on both sides of '.', digits in the exponent)");
            i += n - 1;
        } else if (ch == '+' || ch == '.') {
            return fail_syntax(c, text, len, i,
                               "malformed JSON: not a number by RFC 8259 (no leading '+' or '.')");
        }
    }
    /* RFC 8259 requires UTF-8. Checking the whole text (which now has no
     * NUL before text[len]) also keeps unknown keys and quoted values valid
     * UTF-8 when they are echoed in pointers and messages. */
    size_t bad = utf8_invalid_at(text);
    if (bad != SIZE_MAX)
        return json_fail(c, MR_ERR_INVALID, "malformed JSON: invalid UTF-8 at byte offset %zu", bad);
    return MR_OK;
}

static int fail_syntax(mr_json_ctx *c, const char *text, size_t len, size_t off, const char *what)
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
    return json_fail(c, MR_ERR_INVALID, "%s at byte offset %zu (line %zu, column %zu), near %s", what,
                off, line, col, near);
}

int json_parse_document(mr_json_ctx *c, const char *json, size_t len, size_t max, const char *noun,
                        char **text_out, cJSON **root_out)
{
    const char *end = NULL;
    size_t off;
    int rc;
    *text_out = NULL;
    *root_out = NULL;
    if (!json && len > 0)
        return mark_syntax(c, json_fail(c, MR_ERR_INVALID, "no %s given", noun));
    if (len > max)
        return json_fail(c, MR_ERR_LIMIT, "expected a %s of at most %zu bytes, got %zu bytes", noun,
                         max, len);
    char *text = malloc(len + 1);
    if (!text)
        return json_fail_nomem(c);
    if (len > 0)
        memcpy(text, json, len);
    text[len] = '\0';
    if ((rc = prescan(c, text, len)) < 0) {
        free(text);
        return mark_syntax(c, rc);
    }
    cJSON *root = cJSON_ParseWithLengthOpts(text, len, &end, 0);
    if (!root) {
        off = end && end >= text ? (size_t)(end - text) : 0;
        rc = fail_syntax(c, text, len, off, "malformed JSON");
        free(text);
        return mark_syntax(c, rc);
    }
    off = end && end >= text ? (size_t)(end - text) : len;
    while (off < len && (text[off] == ' ' || text[off] == '\t' || text[off] == '\n' ||
                         text[off] == '\r'))
        off++;
    if (off < len) {
        char what[96];
        snprintf(what, sizeof what, "malformed JSON: unexpected data after the %s", noun);
        rc = fail_syntax(c, text, len, off, what);
        cJSON_Delete(root);
        free(text);
        return mark_syntax(c, rc);
    }
    *text_out = text;
    *root_out = root;
    return MR_OK;
}
