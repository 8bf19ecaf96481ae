/* schema_gen.c - kind blocks of the job schema from parameter tables (schema_gen.h). */
#include "schema_gen.h"
#include "usage.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "files.h"

#define KIND_DEF_PREFIX "kind_"

static cJSON *table_schema(const mr_param_table *t, const char *comment, const char *description,
                           mr_error *err);

static bool add(cJSON *obj, const char *key, cJSON *item)
{
    return item && cJSON_AddItemToObject(obj, key, item);
}

static cJSON *ref_to(const char *def)
{
    char buf[128];
    snprintf(buf, sizeof buf, "#/$defs/%s", def);
    cJSON *o = cJSON_CreateObject();
    if (o && !add(o, "$ref", cJSON_CreateString(buf))) {
        cJSON_Delete(o);
        return NULL;
    }
    return o;
}

/* A default the schema may state: one the parser would accept if given. */
static bool default_in_range(const mr_param *p)
{
    double d = p->def;
    if (p->flags & MR_PARAM_NO_DEFAULT)
        return false;
    if (d < p->lo || d > p->hi)
        return false;
    if ((p->flags & MR_PARAM_LO_OPEN) && d <= p->lo)
        return false;
    if ((p->flags & MR_PARAM_HI_OPEN) && d >= p->hi)
        return false;
    return true;
}

static cJSON *param_schema(const mr_param *p, mr_error *err)
{
    cJSON *s = NULL;
    bool ok = true;
    switch (p->type) {
    case MR_PARAM_INT:
    case MR_PARAM_NUMBER:
        s = cJSON_CreateObject();
        ok = s && add(s, "type", cJSON_CreateString(p->type == MR_PARAM_INT ? "integer" : "number"));
        ok = ok && add(s, (p->flags & MR_PARAM_LO_OPEN) ? "exclusiveMinimum" : "minimum",
                       cJSON_CreateNumber(p->lo));
        ok = ok && add(s, (p->flags & MR_PARAM_HI_OPEN) ? "exclusiveMaximum" : "maximum",
                       cJSON_CreateNumber(p->hi));
        if (ok && default_in_range(p))
            ok = add(s, "default", cJSON_CreateNumber(p->def));
        break;
    case MR_PARAM_BOOL:
        s = cJSON_CreateObject();
        ok = s && add(s, "type", cJSON_CreateString("boolean")) &&
             add(s, "default", cJSON_CreateBool(p->def != 0));
        break;
    case MR_PARAM_ENUM: {
        s = cJSON_CreateObject();
        cJSON *e = cJSON_CreateStringArray(p->choices, (int)p->choice_count);
        ok = s && add(s, "enum", e);
        size_t d = (size_t)p->def;
        if (ok && d < p->choice_count)
            ok = add(s, "default", cJSON_CreateString(p->choices[d]));
        break;
    }
    case MR_PARAM_FLAG_OBJECT: {
        s = cJSON_CreateObject();
        cJSON *one = cJSON_CreateArray(), *b = cJSON_CreateObject();
        ok = s && one && b && add(b, "type", cJSON_CreateString("boolean"));
        ok = ok && cJSON_AddItemToArray(one, b);
        if (!ok)
            cJSON_Delete(b);
        ok = ok && cJSON_AddItemToArray(one, table_schema(p->sub, NULL, NULL, err));
        ok = ok && add(s, "oneOf", one);
        if (!ok)
            cJSON_Delete(one);
        ok = ok && add(s, "default", cJSON_CreateBool(p->def != 0));
        break;
    }
    case MR_PARAM_ARRAY:
        s = cJSON_CreateObject();
        ok = s && add(s, "type", cJSON_CreateString("array")) &&
             add(s, "minItems", cJSON_CreateNumber(1)) &&
             add(s, "maxItems", cJSON_CreateNumber((double)p->max_items)) &&
             add(s, "items", table_schema(p->sub, NULL, NULL, err));
        break;
    case MR_PARAM_TRANSFORM: s = ref_to("transform"); break;
    case MR_PARAM_POSE: s = ref_to("pose"); break;
    case MR_PARAM_ASSET:
        s = cJSON_CreateObject();
        ok = s && add(s, "type", cJSON_CreateString("string"));
        break;
    case MR_PARAM_QUAT: s = ref_to("quat"); break;
    case MR_PARAM_NUMBERS:
    case MR_PARAM_VEC3: { /* an array of exactly n numbers in lo..hi */
        size_t n = p->type == MR_PARAM_VEC3 ? 3 : p->max_items;
        s = cJSON_CreateObject();
        cJSON *item = cJSON_CreateObject();
        ok = s && item && add(item, "type", cJSON_CreateString("number")) &&
             add(item, (p->flags & MR_PARAM_LO_OPEN) ? "exclusiveMinimum" : "minimum",
                 cJSON_CreateNumber(p->lo)) &&
             add(item, (p->flags & MR_PARAM_HI_OPEN) ? "exclusiveMaximum" : "maximum",
                 cJSON_CreateNumber(p->hi));
        ok = ok && add(s, "type", cJSON_CreateString("array")) &&
             add(s, "minItems", cJSON_CreateNumber((double)n)) &&
             add(s, "maxItems", cJSON_CreateNumber((double)n)) && add(s, "items", item);
        if (!ok && item && !cJSON_GetObjectItem(s, "items"))
            cJSON_Delete(item);
        if (ok && p->type == MR_PARAM_VEC3 && !(p->flags & MR_PARAM_NO_DEFAULT))
            ok = add(s, "default", cJSON_CreateDoubleArray(p->def3, 3));
        break;
    }
    }
    if (ok && s && p->description)
        ok = add(s, "description", cJSON_CreateString(p->description));
    if (!ok || !s) {
        cJSON_Delete(s);
        if (err && err->code == 0)
            mr_error_set(err, MR_ERR_NOMEM, "out of memory building the schema of \"%s\"", p->field);
        return NULL;
    }
    return s;
}

static cJSON *table_schema(const mr_param_table *t, const char *comment, const char *description,
                           mr_error *err)
{
    cJSON *s = cJSON_CreateObject(), *props = cJSON_CreateObject();
    bool ok = s && props;
    if (ok && comment)
        ok = add(s, "$comment", cJSON_CreateString(comment));
    if (ok && description)
        ok = add(s, "description", cJSON_CreateString(description));
    ok = ok && add(s, "type", cJSON_CreateString("object")) &&
         add(s, "additionalProperties", cJSON_CreateFalse());
    for (size_t i = 0; ok && i < t->count; i++)
        ok = add(props, t->params[i].field, param_schema(&t->params[i], err));
    ok = ok && add(s, "properties", props);
    if (!ok)
        cJSON_Delete(props);
    /* "conflicts": the two fields are alternatives */
    for (size_t i = 0; ok && i < t->count; i++) {
        const mr_param *p = &t->params[i];
        if (!p->conflicts)
            continue;
        const char *pair[2] = {p->field, p->conflicts};
        cJSON *no = cJSON_CreateObject();
        ok = no && add(no, "required", cJSON_CreateStringArray(pair, 2)) && add(s, "not", no);
        if (!ok)
            cJSON_Delete(no);
    }
    if (ok && t->schema_rules) {
        cJSON *rules = cJSON_Parse(t->schema_rules);
        if (!cJSON_IsObject(rules)) {
            cJSON_Delete(rules);
            cJSON_Delete(s);
            mr_error_set(err, MR_ERR_INVALID, "a parameter table's schema_rules is not a JSON object");
            return NULL;
        }
        while (ok && rules->child) {
            cJSON *r = cJSON_DetachItemViaPointer(rules, rules->child);
            ok = add(s, r->string, r);
            if (!ok)
                cJSON_Delete(r);
        }
        cJSON_Delete(rules);
    }
    if (!ok) {
        cJSON_Delete(s);
        if (err && err->code == 0)
            mr_error_set(err, MR_ERR_NOMEM, "out of memory building a schema");
        return NULL;
    }
    return s;
}

cJSON *mr_schema_kind_block(const mr_kind *kind, mr_error *err)
{
    if (!mr_kind_params(kind)) {
        mr_error_set(err, MR_ERR_INVALID, "kind \"%s\" takes no parameters", mr_kind_name(kind));
        return NULL;
    }
    char note[256];
    snprintf(note, sizeof note,
             "Generated from the \"%s\" kind's parameter table by `make schema`; edit the "
             "table, not this block.",
             mr_kind_name(kind));
    return table_schema(mr_kind_params(kind), note, mr_kind_summary(kind), err);
}

/* {"properties": {"kind": {"const": name}}, "required": ["kind"]}: a
 * kind's block needs its "kind". */
static cJSON *needs_kind(const char *name)
{
    const char *req[1] = {"kind"};
    cJSON *dep = cJSON_CreateObject(), *props = cJSON_CreateObject(), *kc = cJSON_CreateObject();
    bool ok = dep && props && kc && add(kc, "const", cJSON_CreateString(name));
    ok = ok && add(props, "kind", kc);
    if (!ok)
        cJSON_Delete(kc);
    ok = ok && add(dep, "properties", props);
    if (!ok && props && !props->string)
        cJSON_Delete(props);
    if (!ok || !add(dep, "required", cJSON_CreateStringArray(req, 1))) {
        cJSON_Delete(dep);
        return NULL;
    }
    return dep;
}

/* Adds obj[key] = item just before obj[before] (at the end without it). */
static bool add_before(cJSON *obj, const char *before, const char *key, cJSON *item)
{
    cJSON *moved = cJSON_CreateArray();
    if (!item || !moved) {
        cJSON_Delete(item);
        cJSON_Delete(moved);
        return false;
    }
    cJSON *c = obj->child;
    while (c && strcmp(c->string, before) != 0)
        c = c->next;
    while (c) {
        cJSON *next = c->next;
        cJSON_AddItemToArray(moved, cJSON_DetachItemViaPointer(obj, c));
        c = next;
    }
    bool ok = cJSON_AddItemToObject(obj, key, item);
    if (!ok)
        cJSON_Delete(item);
    while (moved->child) {
        cJSON *m = cJSON_DetachItemViaPointer(moved, moved->child);
        char *name = m->string;
        m->string = NULL;
        if (!cJSON_AddItemToObject(obj, name, m)) {
            cJSON_Delete(m);
            ok = false;
        }
        free(name);
    }
    cJSON_Delete(moved);
    return ok;
}

/* obj[key] = item, in place when it exists (keeps the key's position). */
static bool put(cJSON *obj, const char *key, cJSON *item)
{
    if (!item)
        return false;
    if (cJSON_GetObjectItemCaseSensitive(obj, key))
        return cJSON_ReplaceItemInObjectCaseSensitive(obj, key, item);
    return cJSON_AddItemToObject(obj, key, item);
}

static cJSON *object_member(cJSON *parent, const char *key, mr_error *err)
{
    cJSON *o = cJSON_GetObjectItemCaseSensitive(parent, key);
    if (!o) {
        o = cJSON_CreateObject();
        if (!o || !cJSON_AddItemToObject(parent, key, o)) {
            cJSON_Delete(o);
            mr_error_set(err, MR_ERR_NOMEM, "out of memory");
            return NULL;
        }
    }
    if (!cJSON_IsObject(o)) {
        mr_error_set(err, MR_ERR_FORMAT, "schema: \"%s\" is not an object", key);
        return NULL;
    }
    return o;
}

int mr_schema_update(cJSON *schema, mr_error *err)
{
    cJSON *defs = object_member(schema, "$defs", err);
    cJSON *object = defs ? object_member(defs, "object", err) : NULL;
    cJSON *props = object ? object_member(object, "properties", err) : NULL;
    cJSON *deps = object ? object_member(object, "dependentSchemas", err) : NULL;
    if (!props || !deps)
        return err->code ? err->code : MR_ERR_FORMAT;

    /* drop blocks of kinds no longer registered, and their references */
    for (cJSON *d = defs->child, *next; d; d = next) {
        next = d->next;
        const char *name = d->string + strlen(KIND_DEF_PREFIX);
        if (strncmp(d->string, KIND_DEF_PREFIX, strlen(KIND_DEF_PREFIX)) == 0 &&
            !mr_kind_find(name)) {
            cJSON_DeleteItemFromObjectCaseSensitive(props, name);
            cJSON_DeleteItemFromObjectCaseSensitive(deps, name);
            cJSON_Delete(cJSON_DetachItemViaPointer(defs, d));
        }
    }

    const char *names[64];
    size_t n = 0;
    for (size_t i = 0; i < mr_kind_count() && n < 64; i++)
        names[n++] = mr_kind_name(mr_kind_at(i));
    cJSON *kind = cJSON_CreateObject();
    bool ok = kind && add(kind, "enum", cJSON_CreateStringArray(names, (int)n)) &&
              add(kind, "default", cJSON_CreateString(names[0])) &&
              add(kind, "description", cJSON_CreateString("The geometry kind; its parameters, "
                                                          "if it takes any, go in the member "
                                                          "of the same name."));
    if (!ok || !put(props, "kind", kind)) {
        cJSON_Delete(kind);
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    }
    for (size_t i = 0; i < mr_kind_count(); i++) {
        const mr_kind *k = mr_kind_at(i);
        const char *kname = mr_kind_name(k);
        if (!mr_kind_params(k))
            continue;
        char def[96];
        snprintf(def, sizeof def, KIND_DEF_PREFIX "%s", kname);
        cJSON *block = mr_schema_kind_block(k, err);
        if (!block)
            return err->code ? err->code : MR_ERR_NOMEM;
        if (!put(defs, def, block)) {
            cJSON_Delete(block);
            return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
        }
        /* the block's property sits before "transform" (the parser's order) */
        if (!cJSON_GetObjectItemCaseSensitive(props, kname)) {
            if (!add_before(props, "transform", kname, ref_to(def)))
                return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
        } else if (!put(props, kname, ref_to(def))) {
            return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
        }
        if (!put(deps, kname, needs_kind(kname)))
            return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    }
    return MR_OK;
}

/* ------------------------------------------------------------------------ */
/* Printing in the committed file's style.                                  */

typedef struct out {
    char *buf;
    size_t len, cap;
    bool failed;
} out;

static void put_raw(out *o, const char *s, size_t n)
{
    if (o->failed)
        return;
    if (o->len + n + 1 > o->cap) {
        size_t cap = o->cap ? o->cap * 2 : 4096;
        while (cap < o->len + n + 1)
            cap *= 2;
        char *b = realloc(o->buf, cap);
        if (!b) {
            o->failed = true;
            return;
        }
        o->buf = b;
        o->cap = cap;
    }
    memcpy(o->buf + o->len, s, n);
    o->len += n;
    o->buf[o->len] = '\0';
}

static void put_str(out *o, const char *s) { put_raw(o, s, strlen(s)); }

static void put_quoted(out *o, const char *s)
{
    put_str(o, "\"");
    for (; *s; s++) {
        unsigned char ch = (unsigned char)*s;
        char esc[8];
        if (ch == '"' || ch == '\\') {
            esc[0] = '\\';
            esc[1] = (char)ch;
            put_raw(o, esc, 2);
        } else if (ch < 0x20) {
            snprintf(esc, sizeof esc, "\\u%04x", ch);
            put_str(o, esc);
        } else {
            put_raw(o, s, 1);
        }
    }
    put_str(o, "\"");
}

/* The shortest text that reads back as the same double. */
static void put_number(out *o, double x)
{
    char buf[40];
    if (x == floor(x) && fabs(x) < 1e15) {
        snprintf(buf, sizeof buf, "%.0f", x);
    } else {
        for (int prec = 1; prec <= 17; prec++) {
            snprintf(buf, sizeof buf, "%.*g", prec, x);
            if (strtod(buf, NULL) == x)
                break;
        }
    }
    put_str(o, buf);
}

static bool scalar(const cJSON *v) { return !cJSON_IsArray(v) && !cJSON_IsObject(v); }

static void put_value(out *o, const cJSON *v, int depth)
{
    if (cJSON_IsObject(v) || cJSON_IsArray(v)) {
        bool arr = cJSON_IsArray(v), inline_arr = arr;
        for (const cJSON *c = v->child; c && inline_arr; c = c->next)
            inline_arr = scalar(c);
        if (!v->child) {
            put_str(o, arr ? "[]" : "{}");
            return;
        }
        put_str(o, arr ? "[" : "{");
        for (const cJSON *c = v->child; c; c = c->next) {
            if (!inline_arr) {
                put_str(o, "\n");
                for (int i = 0; i <= depth; i++)
                    put_str(o, "  ");
            }
            if (!arr) {
                put_quoted(o, c->string);
                put_str(o, ": ");
            }
            put_value(o, c, depth + 1);
            if (c->next)
                put_str(o, inline_arr ? ", " : ",");
        }
        if (!inline_arr) {
            put_str(o, "\n");
            for (int i = 0; i < depth; i++)
                put_str(o, "  ");
        }
        put_str(o, arr ? "]" : "}");
    } else if (cJSON_IsString(v)) {
        put_quoted(o, v->valuestring);
    } else if (cJSON_IsNumber(v)) {
        put_number(o, v->valuedouble);
    } else if (cJSON_IsTrue(v)) {
        put_str(o, "true");
    } else if (cJSON_IsFalse(v)) {
        put_str(o, "false");
    } else {
        put_str(o, "null");
    }
}

char *mr_schema_print(const cJSON *doc)
{
    out o = {0};
    put_value(&o, doc, 0);
    put_str(&o, "\n");
    if (o.failed) {
        free(o.buf);
        return NULL;
    }
    return o.buf;
}

int mr_cmd_schema(int argc, char **argv)
{
    const char *path = NULL;
    bool check = false, usage = false;
    for (int i = 0; i < argc && !usage; i++) {
        if (!strcmp(argv[i], "--check"))
            check = true;
        else if (argv[i][0] != '-' && !path)
            path = argv[i];
        else
            usage = true;
    }
    if (usage || !path) {
        mr_usage_command_print(stderr, "schema");
        return 2;
    }
    char *text = NULL, *fresh = NULL;
    size_t len = 0;
    mr_error err = {0};
    cJSON *doc = NULL;
    int status = 1;
    if (mr_file_read(path, 16u << 20, &text, &len, &err) < 0) {
        fprintf(stderr, "microrayd: %s\n", err.msg);
        goto done;
    }
    if (!(doc = cJSON_ParseWithLength(text, len)) || !cJSON_IsObject(doc)) {
        fprintf(stderr, "microrayd: %s: not a JSON object\n", path);
        goto done;
    }
    if (mr_schema_update(doc, &err) < 0 || !(fresh = mr_schema_print(doc))) {
        fprintf(stderr, "microrayd: %s: %s\n", path, err.code ? err.msg : "out of memory");
        goto done;
    }
    if (check) {
        status = strcmp(fresh, text) == 0 ? 0 : 1;
        if (status)
            fprintf(stderr, "microrayd: %s is stale: run `make schema`\n", path);
    } else {
        fputs(fresh, stdout);
        status = 0;
    }
done:
    cJSON_Delete(doc);
    free(fresh);
    free(text);
    return status;
}
