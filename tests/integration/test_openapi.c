/*
 * test_openapi.c - schemas/openapi.yaml against the running daemon, route
 * by route, read from the document itself (converted to JSON by the schema
 * test tools' js-yaml), and linted with Redocly's OpenAPI linter
 * (tests/schema/lint-openapi.js: @redocly/openapi-core, the engine of
 * `redocly lint`, pinned in tests/schema/package-lock.json).
 *
 *   - the document's paths and methods are the route table's
 *     (server/http_routes.c), both ways;
 *   - every operation is exercised (a request per operationId, plus the
 *     error statuses a test can cause: 400, 404, 406, 409, 416, 422, 304,
 *     206): each status answered is documented for the operation, its
 *     Content-Type is one the document gives for it (an empty body when it
 *     gives none), its required headers are there, and every JSON body
 *     validates against the documented schema (ajv, JSON Schema 2020-12,
 *     tests/schema/validate-responses.js);
 *   - every path answers OPTIONS with 204 and an Allow listing exactly the
 *     document's methods (with HEAD and OPTIONS), another method with 405
 *     and the same Allow, and 405 is documented for each of its operations;
 *   - every operation answers a Content-Length past any cap with 413, and
 *     documents it; every GET answers HEAD like GET, without a body.
 * An operation in the document without a request here fails the test, so
 * a new route cannot go unchecked.
 */
#define _GNU_SOURCE /* strcasestr */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <arpa/inet.h>
#include <cJSON.h>
#include <netinet/in.h>
#include <sys/socket.h>

#include "daemon_fixture.h"

static daemon_proc D;
static cJSON *API;   /* the document */
static cJSON *CASES; /* JSON bodies to validate: [{what, pointer, body}] */
static cJSON *SEEN;  /* operationIds exercised */
static char JOB[64], GONE_JOB[64], ASSET[80];
static size_t failures;

#define CHECK(cond, ...)                                                                           \
    do {                                                                                           \
        if (!(cond)) {                                                                             \
            failures++;                                                                            \
            print_error(__VA_ARGS__);                                                              \
            print_error("\n");                                                                     \
        }                                                                                          \
    } while (0)

/* ---- the document ------------------------------------------------------ */

/* RFC 6901: the member of o named by one pointer segment. */
static void pointer_escape(const char *in, char *out, size_t size)
{
    size_t o = 0;
    for (; *in && o + 3 < size; in++) {
        if (*in == '~' || *in == '/') {
            out[o++] = '~';
            out[o++] = *in == '~' ? '0' : '1';
        } else {
            out[o++] = *in;
        }
    }
    out[o] = '\0';
}

/* The node at an absolute pointer "/a/b~1c" of the document. */
static const cJSON *at_pointer(const char *pointer)
{
    const cJSON *n = API;
    char seg[512];
    for (const char *p = pointer; n && *p == '/';) {
        p++;
        size_t k = 0;
        while (*p && *p != '/' && k + 1 < sizeof seg) {
            if (p[0] == '~' && (p[1] == '0' || p[1] == '1')) {
                seg[k++] = p[1] == '0' ? '~' : '/';
                p += 2;
            } else {
                seg[k++] = *p++;
            }
        }
        seg[k] = '\0';
        n = cJSON_GetObjectItemCaseSensitive(n, seg);
    }
    return n;
}

/* o, or what its "$ref" (local) names; *pointer follows along. */
static const cJSON *deref(const cJSON *o, char *pointer, size_t size)
{
    for (int hops = 0; o && hops < 8; hops++) {
        const cJSON *ref = cJSON_GetObjectItemCaseSensitive(o, "$ref");
        if (!cJSON_IsString(ref) || ref->valuestring[0] != '#')
            return o;
        snprintf(pointer, size, "%s", ref->valuestring + 1);
        o = at_pointer(pointer);
    }
    return o;
}

static void load_api(void)
{
    char out[600], cmd[3000];
    snprintf(out, sizeof out, "%s/openapi.json", fx_tmp);
    snprintf(cmd, sizeof cmd,
             "cd '%s' && node -e \"const y = require('./tests/schema/node_modules/js-yaml'); "
             "process.stdout.write(JSON.stringify(y.load(require('fs').readFileSync("
             "'schemas/openapi.yaml', 'utf8'))))\" > '%s'",
             fx_src_dir, out);
    if (system(cmd) != 0)
        fail_msg("cannot read schemas/openapi.yaml with js-yaml (scripts/setup.sh installs it)");
    char *text = fx_slurp(out, NULL);
    API = cJSON_Parse(text);
    free(text);
    assert_non_null(API);
}

static const char *const METHODS[] = {"get", "post", "put", "delete", "patch"};

/* ---- checking one answer ------------------------------------------------ */

/* Media type without parameters, lower case: "text/plain". */
static void media_base(const char *ct, char *out, size_t size)
{
    size_t n = strcspn(ct, ";");
    while (n && ct[n - 1] == ' ')
        n--;
    snprintf(out, size, "%.*s", (int)n, ct);
    for (char *p = out; *p; p++)
        *p = (char)(*p >= 'A' && *p <= 'Z' ? *p + 32 : *p);
}

/* Checks a response r to method on the path template against the
 * document's operation; what names it in messages. */
static void check_answer(const char *tmpl, const char *method, const http_result *r, const char *what)
{
    char lower[8], esc[300], pointer[1024];
    snprintf(lower, sizeof lower, "%s", method);
    for (char *p = lower; *p; p++)
        *p = (char)(*p + (*p >= 'A' && *p <= 'Z' ? 32 : 0));
    if (!strcmp(lower, "head"))
        snprintf(lower, sizeof lower, "get");
    pointer_escape(tmpl, esc, sizeof esc);
    snprintf(pointer, sizeof pointer, "/paths/%s/%s", esc, lower);
    const cJSON *op = at_pointer(pointer);
    if (!op) {
        CHECK(false, "%s: no operation %s %s in the document", what, method, tmpl);
        return;
    }
    const cJSON *id = cJSON_GetObjectItemCaseSensitive(op, "operationId");
    if (cJSON_IsString(id) && strcmp(method, "HEAD") != 0)
        cJSON_AddItemToArray(SEEN, cJSON_CreateString(id->valuestring));
    char status[8];
    snprintf(status, sizeof status, "%ld", r->status);
    size_t base_len = strlen(pointer);
    snprintf(pointer + base_len, sizeof pointer - base_len, "/responses/%s", status);
    const cJSON *resp = deref(at_pointer(pointer), pointer, sizeof pointer);
    if (!resp) {
        CHECK(false, "%s: %s %s answered %ld, which the document does not list (%s)", what, method,
              tmpl, r->status, r->body ? r->body : "");
        return;
    }
    /* content types */
    const cJSON *content = cJSON_GetObjectItemCaseSensitive(resp, "content");
    char got[128];
    media_base(r->content_type, got, sizeof got);
    bool head = !strcmp(method, "HEAD");
    if (!content) {
        CHECK(r->len == 0, "%s: %s %s %ld has a body of %zu bytes, the document gives none", what,
              method, tmpl, r->status, r->len);
    } else {
        const cJSON *m, *match = NULL;
        cJSON_ArrayForEach(m, content) {
            char want[128];
            media_base(m->string, want, sizeof want);
            /* parameters the document names must be there too (metrics' version) */
            const char *params = strchr(m->string, ';');
            if (!strcmp(want, got) && (!params || strstr(r->content_type, params + 1)))
                match = m;
        }
        CHECK(match != NULL, "%s: %s %s %ld has Content-Type '%s', not one the document gives", what,
              method, tmpl, r->status, r->content_type);
        if (match && !head && (!strcmp(got, "application/json") || !strcmp(got, "application/problem+json"))) {
            cJSON *body = cJSON_Parse(r->body);
            CHECK(body != NULL, "%s: %s %s %ld: the body is not JSON", what, method, tmpl, r->status);
            char media_esc[128], schema_ptr[1300];
            pointer_escape(match->string, media_esc, sizeof media_esc);
            snprintf(schema_ptr, sizeof schema_ptr, "%s/content/%s/schema", pointer, media_esc);
            if (body) {
                cJSON *c = cJSON_CreateObject();
                char label[400];
                snprintf(label, sizeof label, "%s (%s %s %ld)", what, method, tmpl, r->status);
                cJSON_AddStringToObject(c, "what", label);
                cJSON_AddStringToObject(c, "pointer", schema_ptr);
                cJSON_AddItemToObject(c, "body", body);
                cJSON_AddItemToArray(CASES, c);
            }
        }
    }
    /* required headers */
    const cJSON *headers = cJSON_GetObjectItemCaseSensitive(resp, "headers"), *h;
    cJSON_ArrayForEach(h, headers) {
        char hp[1024] = "";
        const cJSON *hd = deref(h, hp, sizeof hp);
        char value[512];
        if (cJSON_IsTrue(cJSON_GetObjectItemCaseSensitive(hd, "required")))
            CHECK(fx_header_get(r, h->string, value, sizeof value), "%s: %s %s %ld lacks the header %s",
                  what, method, tmpl, r->status, h->string);
    }
}

/* A request to the concrete path, checked against the template's
 * operation; want > 0: the status it must get. */
static http_result exercise(const char *tmpl, const char *method, const char *path, const void *body,
                            size_t len, const char *const *headers, long want, const char *what)
{
    http_result r = http_headers(&D, method, path, body, len, headers);
    CHECK(want <= 0 || r.status == want, "%s: %s %s answered %ld, the test expects %ld: %s", what,
          method, path, r.status, want, r.body);
    check_answer(tmpl, method, &r, what);
    return r;
}

static void exercise_free(const char *tmpl, const char *method, const char *path, const void *body,
                          size_t len, const char *header, long want, const char *what)
{
    const char *headers[] = {header, NULL};
    http_result r = exercise(tmpl, method, path, body, len, headers, want, what);
    http_free(&r);
}

/* The concrete path of a template: the test's job, frame 0, asset, a slug. */
static void concrete(const char *tmpl, char *out, size_t size)
{
    size_t o = 0;
    for (const char *p = tmpl; *p && o + 1 < size;) {
        if (*p == '{') {
            const char *e = strchr(p, '}');
            const char *v = !strncmp(p, "{n}", 3)      ? "0"
                            : !strncmp(p, "{slug}", 6) ? "invalid-job"
                            : !strncmp(tmpl, "/v1/assets", 10) ? ASSET
                                                               : JOB;
            o += (size_t)snprintf(out + o, size - o, "%s", v);
            p = e ? e + 1 : p + strlen(p);
        } else {
            out[o++] = *p++;
        }
    }
    out[o < size ? o : size - 1] = '\0';
}

/* ---- the tests ---------------------------------------------------------- */

/* The document's paths and methods are exactly the route table's. */
static void test_routes_match_the_table(void **state)
{
    (void)state;
    failures = 0;
    char path[2200];
    snprintf(path, sizeof path, "%s/server/http_routes.c", fx_src_dir);
    char *src = fx_slurp(path, NULL);
    assert_non_null(src);
    size_t routes = 0;
    const cJSON *paths = cJSON_GetObjectItemCaseSensitive(API, "paths");
    for (const char *p = src; (p = strstr(p, "    {\"")); p++) {
        char method[16], pattern[256];
        if (sscanf(p, " {\"%15[A-Z]\", \"%255[^\"]\"", method, pattern) != 2)
            continue;
        routes++;
        char lower[16];
        for (size_t i = 0; i <= strlen(method); i++)
            lower[i] = (char)(method[i] + (method[i] >= 'A' && method[i] <= 'Z' ? 32 : 0));
        const cJSON *item = cJSON_GetObjectItemCaseSensitive(paths, pattern);
        CHECK(item && cJSON_GetObjectItemCaseSensitive(item, lower),
              "the route %s %s is not in schemas/openapi.yaml", method, pattern);
    }
    free(src);
    assert_true(routes >= 20);
    size_t ops = 0;
    const cJSON *item;
    cJSON_ArrayForEach(item, paths) {
        for (size_t m = 0; m < sizeof METHODS / sizeof *METHODS; m++) {
            if (!cJSON_GetObjectItemCaseSensitive(item, METHODS[m]))
                continue;
            ops++;
            char upper[16], needle[400];
            for (size_t i = 0; i <= strlen(METHODS[m]); i++)
                upper[i] = (char)(METHODS[m][i] - (METHODS[m][i] >= 'a' && METHODS[m][i] <= 'z' ? 32 : 0));
            snprintf(needle, sizeof needle, "{\"%s\", \"%s\"", upper, item->string);
            src = fx_slurp(path, NULL);
            CHECK(strstr(src, needle) != NULL, "%s %s is documented but not in the route table", upper,
                  item->string);
            free(src);
        }
    }
    assert_int_equal(ops, routes);
    assert_int_equal(failures, 0);
}

/* Every operation, its success and the errors a test can cause. */
static void test_operations(void **state)
{
    (void)state;
    failures = 0;
    char p[512];
    /* with reference passes: its stats carry error entries and the job's
     * error summary, held to their schemas like the rest */
    char *job = fx_small_job(1, 48, "\"reference\":true,");
    /* jobs */
    exercise_free("/v1/jobs", "POST", "/v1/jobs", job, strlen(job), NULL, 202, "submit");
    exercise_free("/v1/jobs", "POST", "/v1/jobs?dry_run=1", job, strlen(job), NULL, 200, "dry run");
    exercise_free("/v1/jobs", "POST", "/v1/jobs", "{", 1, NULL, 400, "malformed job");
    char *bad = fx_small_job(1, 0, NULL);
    exercise_free("/v1/jobs", "POST", "/v1/jobs", bad, strlen(bad), NULL, 422, "invalid job");
    free(bad);
    free(job);
    exercise_free("/v1/jobs", "GET", "/v1/jobs?limit=1", NULL, 0, NULL, 200, "list");
    exercise_free("/v1/jobs", "GET", "/v1/jobs?limit=0", NULL, 0, NULL, 400, "list, bad limit");
    snprintf(p, sizeof p, "/v1/jobs/%s", JOB);
    exercise_free("/v1/jobs/{id}", "GET", p, NULL, 0, NULL, 200, "job");
    snprintf(p, sizeof p, "/v1/jobs/%s/cancel", JOB);
    exercise_free("/v1/jobs/{id}/cancel", "POST", p, "", 0, NULL, 409, "cancel a finished job");
    snprintf(p, sizeof p, "/v1/jobs/%s/retry", JOB);
    exercise_free("/v1/jobs/{id}/retry", "POST", p, "", 0, NULL, 409, "retry a finished job");
    /* frames */
    snprintf(p, sizeof p, "/v1/jobs/%s/frames", JOB);
    exercise_free("/v1/jobs/{id}/frames", "GET", p, NULL, 0, NULL, 200, "frames");
    snprintf(p, sizeof p, "/v1/jobs/%s/frames?state=lost", JOB);
    exercise_free("/v1/jobs/{id}/frames", "GET", p, NULL, 0, NULL, 400, "frames, bad state");
    snprintf(p, sizeof p, "/v1/jobs/%s/frames.tar", JOB);
    exercise_free("/v1/jobs/{id}/frames.tar", "GET", p, NULL, 0, NULL, 200, "tar");
    snprintf(p, sizeof p, "/v1/jobs/%s/frames/0", JOB);
    const char *none[] = {NULL};
    http_result f = exercise("/v1/jobs/{id}/frames/{n}", "GET", p, NULL, 0, none, 200, "frame");
    char etag[128], inm[160];
    fx_header_get(&f, "ETag", etag, sizeof etag);
    snprintf(inm, sizeof inm, "If-None-Match: %s", etag);
    exercise_free("/v1/jobs/{id}/frames/{n}", "GET", p, NULL, 0, inm, 304, "frame, not modified");
    exercise_free("/v1/jobs/{id}/frames/{n}", "GET", p, NULL, 0, "Range: bytes=0-9", 206, "frame range");
    exercise_free("/v1/jobs/{id}/frames/{n}", "GET", p, NULL, 0, "Accept: image/png", 200, "frame as PNG");
    exercise_free("/v1/jobs/{id}/frames/{n}", "GET", p, NULL, 0, "Accept: text/html", 406, "frame, nothing acceptable");
    char range[96];
    snprintf(range, sizeof range, "Range: bytes=%zu-", f.len);
    exercise_free("/v1/jobs/{id}/frames/{n}", "GET", p, NULL, 0, range, 416, "frame, range outside");
    http_free(&f);
    snprintf(p, sizeof p, "/v1/jobs/%s/frames/7", JOB);
    exercise_free("/v1/jobs/{id}/frames/{n}", "GET", p, NULL, 0, NULL, 404, "frame outside the job");
    snprintf(p, sizeof p, "/v1/jobs/%s/frames/0.png", JOB);
    f = exercise("/v1/jobs/{id}/frames/{n}.png", "GET", p, NULL, 0, none, 200, "preview");
    fx_header_get(&f, "ETag", etag, sizeof etag);
    snprintf(inm, sizeof inm, "If-None-Match: %s", etag);
    exercise_free("/v1/jobs/{id}/frames/{n}.png", "GET", p, NULL, 0, inm, 304, "preview, not modified");
    http_free(&f);
    snprintf(p, sizeof p, "/v1/jobs/%s/frames/0/stats", JOB);
    exercise_free("/v1/jobs/{id}/frames/{n}/stats", "GET", p, NULL, 0, NULL, 200, "frame stats");
    snprintf(p, sizeof p, "/v1/jobs/%s/stats", JOB);
    exercise_free("/v1/jobs/{id}/stats", "GET", p, NULL, 0, NULL, 200, "job stats");
    snprintf(p, sizeof p, "/v1/jobs/%s/contact-sheet.png", JOB);
    f = exercise("/v1/jobs/{id}/contact-sheet.png", "GET", p, NULL, 0, none, 200, "contact sheet");
    fx_header_get(&f, "ETag", etag, sizeof etag);
    snprintf(inm, sizeof inm, "If-None-Match: %s", etag);
    exercise_free("/v1/jobs/{id}/contact-sheet.png", "GET", p, NULL, 0, inm, 304, "sheet, not modified");
    http_free(&f);
    snprintf(p, sizeof p, "/v1/jobs/%s/events", JOB);
    exercise_free("/v1/jobs/{id}/events", "GET", p, NULL, 0, NULL, 200, "events");
    exercise_free("/v1/jobs/{id}/events", "GET", p, NULL, 0, "Last-Event-ID: x", 400, "events, bad id");
    /* assets */
    exercise_free("/v1/assets", "POST", "/v1/assets", "other bytes", 11, NULL, 201, "upload");
    exercise_free("/v1/assets", "POST", "/v1/assets", "other bytes", 11, NULL, 200, "upload again");
    exercise_free("/v1/assets", "POST", "/v1/assets", "", 0, NULL, 400, "empty upload");
    exercise_free("/v1/assets", "GET", "/v1/assets", NULL, 0, NULL, 200, "assets");
    exercise_free("/v1/assets", "GET", "/v1/assets?limit=0", NULL, 0, NULL, 400, "assets, bad limit");
    snprintf(p, sizeof p, "/v1/assets/%s", ASSET);
    exercise_free("/v1/assets/{id}", "GET", p, NULL, 0, NULL, 200, "asset");
    /* service */
    exercise_free("/healthz", "GET", "/healthz", NULL, 0, NULL, 200, "health");
    exercise_free("/readyz", "GET", "/readyz", NULL, 0, NULL, 200, "ready");
    exercise_free("/metrics", "GET", "/metrics", NULL, 0, NULL, 200, "metrics");
    exercise_free("/problems/{slug}", "GET", "/problems/invalid-job", NULL, 0, NULL, 200, "problem page");
    exercise_free("/problems/{slug}", "GET", "/problems/nothing", NULL, 0, NULL, 404, "no problem page");
    /* unknown ids: 404, documented wherever there is an id */
    const cJSON *item;
    cJSON_ArrayForEach(item, cJSON_GetObjectItemCaseSensitive(API, "paths")) {
        if (!strstr(item->string, "{id}"))
            continue;
        char saved_job[64], saved_asset[80], path[512];
        memcpy(saved_job, JOB, sizeof JOB);
        memcpy(saved_asset, ASSET, sizeof ASSET);
        snprintf(JOB, sizeof JOB, "0123456789abcdef0123456789abcdef");
        snprintf(ASSET, sizeof ASSET, "%064d", 0);
        concrete(item->string, path, sizeof path);
        memcpy(JOB, saved_job, sizeof JOB);
        memcpy(ASSET, saved_asset, sizeof ASSET);
        for (size_t m = 0; m < sizeof METHODS / sizeof *METHODS; m++) {
            if (!cJSON_GetObjectItemCaseSensitive(item, METHODS[m]))
                continue;
            char upper[16];
            for (size_t i = 0; i <= strlen(METHODS[m]); i++)
                upper[i] = (char)(METHODS[m][i] - (METHODS[m][i] >= 'a' && METHODS[m][i] <= 'z' ? 32 : 0));
            exercise_free(item->string, upper, path, !strcmp(upper, "POST") ? "" : NULL, 0, NULL, 404,
                          "unknown id");
        }
    }
    /* last: the deletions */
    snprintf(p, sizeof p, "/v1/assets/%s", ASSET);
    exercise_free("/v1/assets/{id}", "DELETE", p, NULL, 0, NULL, 204, "delete asset");
    snprintf(p, sizeof p, "/v1/jobs/%s", GONE_JOB);
    exercise_free("/v1/jobs/{id}", "DELETE", p, NULL, 0, NULL, 204, "delete job");
    /* every operation of the document was exercised */
    cJSON_ArrayForEach(item, cJSON_GetObjectItemCaseSensitive(API, "paths")) {
        for (size_t m = 0; m < sizeof METHODS / sizeof *METHODS; m++) {
            const cJSON *op = cJSON_GetObjectItemCaseSensitive(item, METHODS[m]);
            const cJSON *id = cJSON_GetObjectItemCaseSensitive(op, "operationId");
            if (!op)
                continue;
            bool seen = false;
            const cJSON *s;
            cJSON_ArrayForEach(s, SEEN) seen = seen || (cJSON_IsString(id) && !strcmp(s->valuestring, id->valuestring));
            CHECK(seen, "operation %s (%s %s) has no request in this test", cJSON_IsString(id) ? id->valuestring : "?",
                  METHODS[m], item->string);
        }
    }
    assert_int_equal(failures, 0);
}

/* A raw request announcing a body past every cap: the status line's code. */
static long announce_huge_body(const char *method, const char *path, char *ctype, size_t ctype_size)
{
    int fd = socket(AF_INET, SOCK_STREAM, 0);
    struct sockaddr_in a = {.sin_family = AF_INET, .sin_port = htons((uint16_t)D.port),
                            .sin_addr.s_addr = htonl(INADDR_LOOPBACK)};
    assert_int_equal(connect(fd, (struct sockaddr *)&a, sizeof a), 0);
    char req[1024];
    int n = snprintf(req, sizeof req,
                     "%s %s HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 1000000000000\r\n"
                     "Connection: close\r\n\r\n",
                     method, path);
    assert_int_equal(write(fd, req, (size_t)n), n);
    char buf[4096];
    size_t len = 0;
    for (ssize_t got; len < sizeof buf - 1 && (got = read(fd, buf + len, sizeof buf - 1 - len)) > 0;)
        len += (size_t)got;
    buf[len] = '\0';
    close(fd);
    long status = 0;
    sscanf(buf, "HTTP/1.1 %ld", &status);
    const char *ct = strcasestr(buf, "\r\nContent-Type:");
    ctype[0] = '\0';
    if (ct)
        sscanf(ct + 15, " %127[^\r]", ctype);
    (void)ctype_size;
    return status;
}

/* OPTIONS, 405 with Allow, 413 and HEAD on every path of the document. */
static void test_methods_and_caps(void **state)
{
    (void)state;
    failures = 0;
    const cJSON *item;
    cJSON_ArrayForEach(item, cJSON_GetObjectItemCaseSensitive(API, "paths")) {
        char path[512], want[128] = "", allow[128];
        concrete(item->string, path, sizeof path);
        /* the document's methods, in the order the server lists them:
         * route table order, HEAD after GET, OPTIONS last; compared as sets */
        bool has[5] = {false};
        for (size_t m = 0; m < 5; m++)
            has[m] = cJSON_GetObjectItemCaseSensitive(item, METHODS[m]) != NULL;
        http_result r = http(&D, "OPTIONS", path, NULL, 0, NULL);
        CHECK(r.status == 204, "OPTIONS %s: %ld", path, r.status);
        fx_header_get(&r, "Allow", allow, sizeof allow);
        http_free(&r);
        for (size_t m = 0; m < 5; m++) {
            char upper[16];
            for (size_t i = 0; i <= strlen(METHODS[m]); i++)
                upper[i] = (char)(METHODS[m][i] - (METHODS[m][i] >= 'a' && METHODS[m][i] <= 'z' ? 32 : 0));
            bool listed = strstr(allow, upper) != NULL;
            CHECK(listed == has[m], "OPTIONS %s: Allow '%s' %s %s, the document %s", path, allow,
                  listed ? "lists" : "lacks", upper, has[m] ? "has it" : "has not");
            if (has[m])
                snprintf(want + strlen(want), sizeof want - strlen(want), "%s ", upper);
        }
        CHECK(strstr(allow, "OPTIONS") && (!has[0] || strstr(allow, "HEAD")),
              "OPTIONS %s: Allow '%s' lacks HEAD or OPTIONS", path, allow);
        /* another method: 405 with the same Allow, documented by each operation */
        r = http(&D, "PATCH", path, NULL, 0, NULL);
        char allow405[128];
        fx_header_get(&r, "Allow", allow405, sizeof allow405);
        CHECK(r.status == 405 && !strcmp(allow405, allow), "PATCH %s: %ld, Allow '%s' (OPTIONS said '%s')",
              path, r.status, allow405, allow);
        for (size_t m = 0; m < 5; m++) {
            if (!has[m])
                continue;
            char upper[16];
            for (size_t i = 0; i <= strlen(METHODS[m]); i++)
                upper[i] = (char)(METHODS[m][i] - (METHODS[m][i] >= 'a' && METHODS[m][i] <= 'z' ? 32 : 0));
            check_answer(item->string, upper, &r, "405");
            /* a body past every cap: 413, documented */
            char ctype[128];
            http_result big = {0};
            big.status = announce_huge_body(upper, path, ctype, sizeof ctype);
            snprintf(big.content_type, sizeof big.content_type, "%s", ctype);
            CHECK(big.status == 413, "%s %s with a huge Content-Length: %ld", upper, path, big.status);
            char ptr[1024], esc[300];
            pointer_escape(item->string, esc, sizeof esc);
            snprintf(ptr, sizeof ptr, "/paths/%s/%s/responses/413", esc, METHODS[m]);
            CHECK(at_pointer(ptr) != NULL, "%s %s does not document 413", upper, item->string);
            snprintf(ptr, sizeof ptr, "/paths/%s/%s/responses/405", esc, METHODS[m]);
            CHECK(at_pointer(ptr) != NULL, "%s %s does not document 405", upper, item->string);
        }
        http_free(&r);
        /* HEAD answers as GET does, without a body */
        if (has[0] && !strstr(item->string, "/events")) {
            http_result g = http(&D, "GET", path, NULL, 0, NULL);
            http_result h = http(&D, "HEAD", path, NULL, 0, NULL);
            CHECK(h.status == g.status && h.len == 0 && !strcmp(h.content_type, g.content_type),
                  "HEAD %s: %ld '%s' %zu bytes, GET: %ld '%s'", path, h.status, h.content_type, h.len,
                  g.status, g.content_type);
            check_answer(item->string, "HEAD", &h, "HEAD");
            http_free(&g);
            http_free(&h);
        }
    }
    assert_int_equal(failures, 0);
}

/* Every JSON body seen is valid against the schema documented for it. */
static void test_bodies_match_schemas(void **state)
{
    (void)state;
    char cases_path[600], cmd[3000];
    snprintf(cases_path, sizeof cases_path, "%s/bodies.json", fx_tmp);
    char *text = cJSON_Print(CASES);
    FILE *f = fopen(cases_path, "w");
    fputs(text, f);
    fclose(f);
    free(text);
    assert_true(cJSON_GetArraySize(CASES) >= 30);
    snprintf(cmd, sizeof cmd,
             "cd '%s' && NODE_PATH=tests/schema/node_modules node tests/schema/validate-responses.js "
             "schemas/openapi.yaml '%s'",
             fx_src_dir, cases_path);
    assert_int_equal(system(cmd), 0);
}

/* The document passes Redocly's linter (its recommended rules, every
 * warning a failure), and the linter is real: a copy with an operation
 * that documents no error response fails. */
static void test_lint(void **state)
{
    (void)state;
    char cmd[16384], copy_dir[600];
    snprintf(cmd, sizeof cmd, "cd '%s' && node tests/schema/lint-openapi.js schemas/openapi.yaml",
             fx_src_dir);
    assert_int_equal(system(cmd), 0);
    snprintf(copy_dir, sizeof copy_dir, "%s/lint", fx_tmp);
    snprintf(cmd, sizeof cmd,
             "mkdir -p '%s' && cp '%s/schemas/job.schema.json' '%s/' && "
             "node -e \"const fs = require('fs'); let t = fs.readFileSync('%s/schemas/openapi.yaml', 'utf8'); "
             "t = t.replace(/(operationId: health[\\s\\S]*?)\\\"405\\\": [^\\n]*\\n[^\\n]*\\\"413\\\": [^\\n]*\\n/, '\\$1'); "
             "fs.writeFileSync('%s/openapi.yaml', t)\" && "
             "cd '%s' && ! node tests/schema/lint-openapi.js '%s/openapi.yaml' > '%s/lint.log' 2>&1 && "
             "grep -q operation-4xx-response '%s/lint.log'",
             copy_dir, fx_src_dir, copy_dir, fx_src_dir, copy_dir, fx_src_dir, copy_dir, copy_dir, copy_dir);
    assert_int_equal(system(cmd), 0);
}

static int setup(void **state)
{
    (void)state;
    curl_global_init(CURL_GLOBAL_DEFAULT);
    fx_init_dirs();
    load_api();
    CASES = cJSON_CreateArray();
    SEEN = cJSON_CreateArray();
    daemon_start(&D, "data");
    char *job = fx_small_job(1, 48, NULL);
    fx_submit(&D, job, JOB);
    fx_submit(&D, job, GONE_JOB);
    free(job);
    cJSON *j = fx_wait_job(&D, JOB, 120);
    cJSON_Delete(j);
    j = fx_wait_job(&D, GONE_JOB, 120);
    cJSON_Delete(j);
    http_result r = http(&D, "POST", "/v1/assets", "asset bytes", 11, NULL);
    cJSON *a = cJSON_Parse(r.body);
    snprintf(ASSET, sizeof ASSET, "%s", cJSON_GetObjectItem(a, "id")->valuestring);
    cJSON_Delete(a);
    http_free(&r);
    return 0;
}

static int teardown(void **state)
{
    (void)state;
    cJSON_Delete(API);
    cJSON_Delete(CASES);
    cJSON_Delete(SEEN);
    int st = daemon_stop(&D, SIGTERM);
    if (!fx_cleanup_dirs())
        return -1;
    return st == 0 ? 0 : -1;
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_routes_match_the_table),
        cmocka_unit_test(test_operations),
        cmocka_unit_test(test_methods_and_caps),
        cmocka_unit_test(test_bodies_match_schemas),
        cmocka_unit_test(test_lint),
    };
    return cmocka_run_group_tests_name("openapi", tests, setup, teardown);
}
