/*
 * http_routes.c - the one route table of the HTTP API (http_internal.h):
 * (method, path pattern) to handler and body kind. A path that no pattern
 * matches answers 404; a path whose patterns exist only for other methods
 * answers 405 with an Allow header (http_route_methods). Patterns match
 * segment by segment (OPTIONS on any path that exists answers 204 with the
 * same Allow header); {name} captures one non-empty segment, and
 * {name}.ext one that ends in .ext, capturing what precedes it. The first
 * route that matches wins, so a suffixed pattern comes before the plain one
 * it would otherwise lose to ("/frames/{n}" also matches "7.png").
 */
#include <stdio.h>
#include <string.h>

#include "http_internal.h"

static const route ROUTES[] = {
    {"POST", "/v1/assets", http_asset_put, BODY_ASSET},
    {"GET", "/v1/assets", http_asset_list, BODY_NONE},
    {"GET", "/v1/assets/{id}", http_asset_get, BODY_NONE},
    {"DELETE", "/v1/assets/{id}", http_asset_delete, BODY_NONE},
    {"POST", "/v1/jobs", http_job_submit, BODY_JOB},
    {"GET", "/v1/jobs", http_job_list, BODY_NONE},
    {"GET", "/v1/jobs/{id}", http_job_get, BODY_NONE},
    {"DELETE", "/v1/jobs/{id}", http_job_delete, BODY_NONE},
    {"GET", "/v1/jobs/{id}/frames", http_job_frames, BODY_NONE},
    {"GET", "/v1/jobs/{id}/frames.tar", http_frames_tar, BODY_NONE},
    {"GET", "/v1/jobs/{id}/frames/{n}.png", http_frame_png, BODY_NONE},
    {"GET", "/v1/jobs/{id}/frames/{n}", http_frame_get, BODY_NONE},
    {"GET", "/v1/jobs/{id}/frames/{n}/stats", http_frame_stats, BODY_NONE},
    {"GET", "/v1/jobs/{id}/stats", http_job_stats, BODY_NONE},
    {"GET", "/v1/jobs/{id}/contact-sheet.png", http_contact_sheet, BODY_NONE},
    {"GET", "/v1/jobs/{id}/events", http_job_events, BODY_NONE},
    {"POST", "/v1/jobs/{id}/cancel", http_job_cancel, BODY_NONE},
    {"POST", "/v1/jobs/{id}/retry", http_job_retry, BODY_NONE},
    {"GET", "/healthz", http_healthz, BODY_NONE},
    {"GET", "/readyz", http_readyz, BODY_NONE},
    {"GET", "/metrics", http_metrics, BODY_NONE},
    {"GET", "/problems/{slug}", http_problem_page, BODY_NONE},
};
#define ROUTE_COUNT (sizeof ROUTES / sizeof ROUTES[0])

static const char *segment_end(const char *s)
{
    while (*s && *s != '/')
        s++;
    return s;
}

/* Matches path against pattern segment by segment, capturing {params}. */
static bool route_match(const char *pattern, const char *path, char params[][PARAM_MAX])
{
    size_t np = 0;
    const char *p = pattern, *u = path;
    while (*p && *u) {
        if (*p != '/' || *u != '/')
            return false;
        p++;
        u++;
        const char *pe = segment_end(p), *ue = segment_end(u);
        size_t pl = (size_t)(pe - p), ul = (size_t)(ue - u);
        const char *close = pl > 2 && p[0] == '{' ? memchr(p, '}', pl) : NULL;
        if (close) {
            /* what follows the braces must end the segment: "{n}.png" */
            size_t sl = (size_t)(pe - close - 1);
            if (ul <= sl || memcmp(ue - sl, close + 1, sl) != 0)
                return false;
            ul -= sl;
            if (ul >= PARAM_MAX || np >= MAX_PARAMS)
                return false;
            if (params) {
                memcpy(params[np], u, ul);
                params[np][ul] = '\0';
            }
            np++;
        } else if (pl != ul || memcmp(p, u, pl) != 0) {
            return false;
        }
        p = pe;
        u = ue;
    }
    return *p == '\0' && *u == '\0';
}

/* HEAD is answered by the GET handler (libmicrohttpd drops the body). */
static bool method_is(const char *method, const char *route_method)
{
    return !strcmp(method, route_method) || (!strcmp(method, "HEAD") && !strcmp(route_method, "GET"));
}

static void add_allowed(char *allow, size_t size, const char *m)
{
    if (strstr(allow, m))
        return;
    size_t n = strlen(allow);
    snprintf(allow + n, size - n, "%s%s", n ? ", " : "", m);
}

const route *http_route_find(const char *method, const char *path, char params[][PARAM_MAX])
{
    for (size_t i = 0; i < ROUTE_COUNT; i++) {
        if (route_match(ROUTES[i].pattern, path, NULL) && method_is(method, ROUTES[i].method)) {
            route_match(ROUTES[i].pattern, path, params);
            return &ROUTES[i];
        }
    }
    return NULL;
}

void http_route_methods(const char *path, char *allow, size_t size)
{
    allow[0] = '\0';
    for (size_t i = 0; i < ROUTE_COUNT; i++)
        if (route_match(ROUTES[i].pattern, path, NULL)) {
            add_allowed(allow, size, ROUTES[i].method);
            if (!strcmp(ROUTES[i].method, "GET"))
                add_allowed(allow, size, "HEAD");
        }
    if (allow[0]) /* every path that exists answers OPTIONS (http.c) */
        add_allowed(allow, size, "OPTIONS");
}
