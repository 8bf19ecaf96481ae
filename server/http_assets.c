/*
 * http_assets.c - uploaded assets as resources (http_internal.h):
 *   GET    /v1/assets        the stored assets, newest first, in pages
 *                            (limit, cursor) with size, first stored, last
 *                            named by a job, jobs that use them now;
 *   GET    /v1/assets/{id}   one of them;
 *   DELETE /v1/assets/{id}   its row and file; 409 while a queued or
 *                            running job uses it.
 * The upload itself (POST /v1/assets, streamed to a file) is
 * http_handlers.c's; it answers with Location: /v1/assets/{id}.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "http_internal.h"

#define ASSET_LIMIT_DEFAULT 100
#define ASSET_LIMIT_MAX 1000

static cJSON *time_pair(cJSON *o, const char *num_key, const char *text_key, double t, bool *ok)
{
    char text[40];
    http_put(o, num_key, t > 0 ? cJSON_CreateNumber(t) : cJSON_CreateNull(), ok);
    http_put(o, text_key, t > 0 && mr_format_rfc3339(t, text, sizeof text) ? cJSON_CreateString(text)
                                                                    : cJSON_CreateNull(), ok);
    return o;
}

static cJSON *asset_json(const mr_asset_record *a, bool *ok)
{
    cJSON *o = cJSON_CreateObject();
    char href[96];
    snprintf(href, sizeof href, "/v1/assets/%s", a->id);
    http_put(o, "id", cJSON_CreateString(a->id), ok);
    http_put(o, "size", cJSON_CreateNumber((double)a->size), ok);
    time_pair(o, "created", "created_at", a->created, ok);
    time_pair(o, "last_used", "last_used_at", a->last_used, ok);
    http_put(o, "jobs_active", cJSON_CreateNumber((double)a->jobs_active), ok);
    http_put(o, "location", cJSON_CreateString(href), ok);
    if (!o)
        *ok = false;
    return o;
}

/* Decimal digits only, 1..18 of them. */
static bool parse_count(const char *s, long long *out)
{
    size_t n = strspn(s, "0123456789");
    if (n == 0 || n > 18 || s[n])
        return false;
    *out = atoll(s);
    return true;
}

enum MHD_Result http_asset_list(req *r, struct MHD_Connection *c)
{
    const char *limit_arg = MHD_lookup_connection_value(c, MHD_GET_ARGUMENT_KIND, "limit");
    const char *cursor_arg = MHD_lookup_connection_value(c, MHD_GET_ARGUMENT_KIND, "cursor");
    long long limit = ASSET_LIMIT_DEFAULT, cursor = 0;
    if (limit_arg && (!parse_count(limit_arg, &limit) || limit < 1 || limit > ASSET_LIMIT_MAX))
        return http_send_problem(r, c, P_BAD_REQUEST, NULL, "limit '%.32s': expected an integer in 1..%d",
                                 limit_arg, ASSET_LIMIT_MAX);
    if (cursor_arg && (!parse_count(cursor_arg, &cursor) || cursor < 1))
        return http_send_problem(r, c, P_BAD_REQUEST, NULL,
                                 "cursor '%.32s' is not one this daemon gave (the \"next\" of a page)",
                                 cursor_arg);
    mr_asset_record *list = NULL;
    size_t count = 0;
    int64_t next = 0;
    mr_error err = {0};
    int rc = mr_store_asset_list(mr_daemon_store(r->h->d), cursor, (size_t)limit, &list, &count, &next,
                                 &err);
    if (rc < 0)
        return http_send_error(r, c, rc, &err);
    bool ok = true;
    cJSON *doc = cJSON_CreateObject();
    cJSON *arr = http_put(doc, "assets", cJSON_CreateArray(), &ok);
    for (size_t i = 0; i < count && ok; i++) {
        cJSON *a = asset_json(&list[i], &ok);
        if (!arr || !a || !cJSON_AddItemToArray(arr, a)) {
            cJSON_Delete(a);
            ok = false;
        }
    }
    free(list);
    char cursor_text[24];
    snprintf(cursor_text, sizeof cursor_text, "%lld", (long long)next);
    http_put(doc, "next", next > 0 ? cJSON_CreateString(cursor_text) : cJSON_CreateNull(), &ok);
    return http_send_built(r, c, MHD_HTTP_OK, doc, ok);
}

enum MHD_Result http_asset_get(req *r, struct MHD_Connection *c)
{
    mr_asset_record a;
    mr_error err = {0};
    int rc = mr_store_asset_get(mr_daemon_store(r->h->d), r->params[0], &a, &err);
    if (rc < 0)
        return http_send_error(r, c, rc, &err);
    bool ok = true;
    return http_send_built(r, c, MHD_HTTP_OK, asset_json(&a, &ok), ok);
}

enum MHD_Result http_asset_delete(req *r, struct MHD_Connection *c)
{
    mr_error err = {0};
    int rc = mr_store_asset_delete(mr_daemon_store(r->h->d), r->params[0], &err);
    if (rc < 0)
        return http_send_error(r, c, rc, &err);
    struct MHD_Response *empty = MHD_create_response_from_buffer(0, (void *)"", MHD_RESPMEM_PERSISTENT);
    return http_send_response(r, c, MHD_HTTP_NO_CONTENT, empty, 0);
}
