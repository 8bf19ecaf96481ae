/*
 * api.c - HTTP for the microray client on libcurl (see api.h).
 *
 * Every transfer resets its handle and sets all options again, so no
 * setting of one request (a custom method, an upload callback) can leak
 * into the next, while the connection cache survives the reset and keeps
 * consecutive requests on one keep-alive connection.
 */
#include "api.h"

#include <ctype.h>
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>
#include <sys/stat.h>
#include <unistd.h>

#include <curl/curl.h>

#define JSON_BODY_LIMIT ((size_t)64 << 20)  /* job lists with 100k-frame jobs stay far below */
#define ERROR_BODY_LIMIT ((size_t)64 << 10) /* enough for any problem document */
#define API_TIMEOUT_S 120L
#define CONNECT_TIMEOUT_MS 5000L
/* Below 1 byte/s for this long counts as a dead connection. The stream gets
 * longer because a daemon may legitimately say nothing while a slow frame
 * renders (and the client falls back to polling when it gives up). */
#define TRANSFER_STALL_S 60L
#define STREAM_STALL_S 120L

struct mrc_http {
    char *base;
    char *token; /* bearer token sent with every request; NULL: none */
    CURL *easy;
    CURL *stream;
    char errbuf[CURL_ERROR_SIZE];
    char stream_errbuf[CURL_ERROR_SIZE];
};

typedef enum { KIND_API, KIND_TRANSFER, KIND_STREAM } transfer_kind;

/* ---- buffers and responses ------------------------------------------------ */

/* Appends what fits under the limit; returns false when something was dropped. */
static bool buf_append(mrc_buf *b, const char *p, size_t n)
{
    if (b->overflow)
        return false;
    size_t room = b->limit > b->len ? b->limit - b->len : 0;
    size_t take = n < room ? n : room;
    if (b->len + take + 1 > b->cap) {
        size_t ncap = b->cap ? b->cap : 4096;
        while (ncap < b->len + take + 1)
            ncap *= 2;
        char *d = realloc(b->data, ncap);
        if (!d) {
            b->overflow = true;
            return false;
        }
        b->data = d;
        b->cap = ncap;
    }
    memcpy(b->data + b->len, p, take);
    b->len += take;
    b->data[b->len] = '\0';
    if (take < n)
        b->overflow = true;
    return take == n;
}

void mrc_response_free(mrc_response *r)
{
    if (!r)
        return;
    free(r->body.data);
    memset(r, 0, sizeof *r);
}

static void response_reset(mrc_response *r, size_t limit)
{
    free(r->body.data);
    memset(r, 0, sizeof *r);
    r->body.limit = limit;
}

/* ---- handle setup --------------------------------------------------------- */

int mrc_http_open(const char *base, mrc_http **out, mrc_error *err)
{
    int rc = 0;
    mrc_http *h = NULL;
    *out = NULL;

    const char *scheme_end = strstr(base, "://");
    if (scheme_end) {
        size_t sl = (size_t)(scheme_end - base);
        if (!((sl == 4 && strncasecmp(base, "http", 4) == 0) ||
              (sl == 5 && strncasecmp(base, "https", 5) == 0))) {
            rc = mrc_fail(err, MRC_EXIT_USAGE, "server URL '%s': only http:// and https:// are supported",
                          base);
            goto cleanup;
        }
    }
    if (base[0] == '\0' || (scheme_end && scheme_end[3] == '\0')) {
        rc = mrc_fail(err, MRC_EXIT_USAGE, "server URL '%s' names no host", base);
        goto cleanup;
    }
    for (const char *p = base; *p; p++) {
        if ((unsigned char)*p <= ' ' || *p == 0x7f) {
            rc = mrc_fail(err, MRC_EXIT_USAGE, "server URL contains a space or control character");
            goto cleanup;
        }
    }
    h = calloc(1, sizeof *h);
    if (!h) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
        goto cleanup;
    }
    size_t n = strlen(base);
    while (n > 0 && base[n - 1] == '/')
        n--;
    const char *prefix = scheme_end ? "" : "http://";
    h->base = malloc(strlen(prefix) + n + 1);
    if (!h->base) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
        goto cleanup;
    }
    strcpy(h->base, prefix);
    strncat(h->base, base, n);
    h->easy = curl_easy_init();
    h->stream = curl_easy_init();
    if (!h->easy || !h->stream) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "cannot initialise libcurl");
        goto cleanup;
    }
    *out = h;
    h = NULL;
cleanup:
    mrc_http_close(h);
    return rc;
}

void mrc_http_close(mrc_http *h)
{
    if (!h)
        return;
    if (h->easy)
        curl_easy_cleanup(h->easy);
    if (h->stream)
        curl_easy_cleanup(h->stream);
    free(h->base);
    free(h->token);
    free(h);
}

int mrc_http_set_token(mrc_http *h, const char *token, mrc_error *err)
{
    free(h->token);
    h->token = NULL;
    if (!token || !token[0])
        return 0;
    if (!(h->token = strdup(token)))
        return mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
    return 0;
}

const char *mrc_http_base(const mrc_http *h)
{
    return h->base;
}

/* Captures the headers the client uses; a new status line (after a
 * "100 Continue") starts over. */
static size_t on_header(char *line, size_t size, size_t nmemb, void *user)
{
    mrc_response *r = user;
    size_t len = size * nmemb;
    if (len >= 5 && memcmp(line, "HTTP/", 5) == 0) {
        r->content_type[0] = '\0';
        r->location[0] = '\0';
        return len;
    }
    char *target = NULL;
    size_t target_size = 0, skip = 0;
    if (len > 12 && strncasecmp(line, "retry-after:", 12) == 0) {
        char *end = NULL;
        long v = strtol(line + 12, &end, 10);
        r->retry_after = end != line + 12 && v > 0 && v < 86400 ? (int)v : 0;
        return len;
    }
    if (len > 13 && strncasecmp(line, "content-type:", 13) == 0) {
        target = r->content_type;
        target_size = sizeof r->content_type;
        skip = 13;
    } else if (len > 9 && strncasecmp(line, "location:", 9) == 0) {
        target = r->location;
        target_size = sizeof r->location;
        skip = 9;
    }
    if (target) {
        const char *v = line + skip, *end = line + len;
        while (v < end && (*v == ' ' || *v == '\t'))
            v++;
        while (end > v && isspace((unsigned char)end[-1]))
            end--;
        size_t vl = (size_t)(end - v);
        if (vl >= target_size)
            vl = target_size - 1;
        memcpy(target, v, vl);
        target[vl] = '\0';
    }
    return len;
}

/* Where a response body goes: the file (2xx downloads) or the buffer. */
typedef struct sink {
    CURL *curl;
    mrc_response *resp;
    int fd;             /* download target, -1 for none */
    bool decided, to_file;
    int write_errno;    /* the file write that failed */
    int64_t written;
} sink;

static size_t on_body(char *p, size_t size, size_t nmemb, void *user)
{
    sink *s = user;
    size_t len = size * nmemb;
    if (!s->decided) {
        long code = 0;
        curl_easy_getinfo(s->curl, CURLINFO_RESPONSE_CODE, &code);
        s->to_file = s->fd >= 0 && code >= 200 && code < 300;
        /* an error document is small; a success body may be a job list */
        s->resp->body.limit = (code >= 200 && code < 300) ? JSON_BODY_LIMIT : ERROR_BODY_LIMIT;
        s->decided = true;
    }
    if (s->to_file) {
        size_t done = 0;
        while (done < len) {
            ssize_t w = write(s->fd, p + done, len - done);
            if (w < 0 && errno == EINTR)
                continue;
            if (w <= 0) {
                s->write_errno = w < 0 ? errno : EIO;
                return 0; /* aborts the transfer */
            }
            done += (size_t)w;
        }
        s->written += (int64_t)len;
        return len;
    }
    if (!buf_append(&s->resp->body, p, len)) {
        long code = 0;
        curl_easy_getinfo(s->curl, CURLINFO_RESPONSE_CODE, &code);
        /* keep reading a long error page (the start is enough to report it),
         * but stop a success body that exceeds the cap */
        return (code >= 200 && code < 300) ? 0 : len;
    }
    return len;
}

static void setup(mrc_http *h, CURL *c, char *errbuf, const char *url, transfer_kind kind)
{
    curl_easy_reset(c);
    errbuf[0] = '\0';
    curl_easy_setopt(c, CURLOPT_URL, url);
    curl_easy_setopt(c, CURLOPT_ERRORBUFFER, errbuf);
    curl_easy_setopt(c, CURLOPT_NOSIGNAL, 1L);
    curl_easy_setopt(c, CURLOPT_PROTOCOLS_STR, "http,https");
    curl_easy_setopt(c, CURLOPT_USERAGENT, "microray/" MRC_VERSION);
    curl_easy_setopt(c, CURLOPT_CONNECTTIMEOUT_MS, CONNECT_TIMEOUT_MS);
    curl_easy_setopt(c, CURLOPT_LOW_SPEED_LIMIT, 1L);
    curl_easy_setopt(c, CURLOPT_TCP_KEEPALIVE, 1L);
    switch (kind) {
    case KIND_API:
        curl_easy_setopt(c, CURLOPT_TIMEOUT, API_TIMEOUT_S);
        curl_easy_setopt(c, CURLOPT_LOW_SPEED_TIME, TRANSFER_STALL_S);
        break;
    case KIND_TRANSFER:
        curl_easy_setopt(c, CURLOPT_LOW_SPEED_TIME, TRANSFER_STALL_S);
        break;
    case KIND_STREAM:
        curl_easy_setopt(c, CURLOPT_LOW_SPEED_TIME, STREAM_STALL_S);
        break;
    }
    if (h->token) { /* Authorization: Bearer <token>, on every request */
        curl_easy_setopt(c, CURLOPT_HTTPAUTH, CURLAUTH_BEARER);
        curl_easy_setopt(c, CURLOPT_XOAUTH2_BEARER, h->token);
    }
}

static char *make_url(const mrc_http *h, const char *path, mrc_error *err)
{
    size_t n = strlen(h->base) + strlen(path) + 1;
    char *url = malloc(n);
    if (!url) {
        mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
        return NULL;
    }
    snprintf(url, n, "%s%s", h->base, path);
    return url;
}

static int transport_error(const char *method, const char *url, CURLcode cc, const char *errbuf,
                           mrc_error *err)
{
    return mrc_fail(err, MRC_EXIT_SERVER, "%s %s: %s", method, url,
                    errbuf[0] ? errbuf : curl_easy_strerror(cc));
}

/* ---- requests ------------------------------------------------------------- */

int mrc_http_request(mrc_http *h, const char *method, const char *path, const void *body,
                     size_t len, const char *content_type, const char *idempotency_key,
                     mrc_response *resp, mrc_error *err)
{
    int rc = 0;
    char *url = NULL;
    struct curl_slist *hdrs = NULL, *tmp;
    char line[600];
    sink s = {.curl = h->easy, .resp = resp, .fd = -1};

    response_reset(resp, JSON_BODY_LIMIT);
    url = make_url(h, path, err);
    if (!url) {
        rc = -MRC_EXIT_LOCAL;
        goto cleanup;
    }
    setup(h, h->easy, h->errbuf, url, KIND_API);

#define ADD_HEADER(text)                                                                   \
    do {                                                                                   \
        tmp = curl_slist_append(hdrs, (text));                                             \
        if (!tmp) {                                                                        \
            rc = mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");                           \
            goto cleanup;                                                                  \
        }                                                                                  \
        hdrs = tmp;                                                                        \
    } while (0)

    ADD_HEADER("Accept: application/json, application/problem+json");
    if (strcmp(method, "POST") == 0) {
        curl_easy_setopt(h->easy, CURLOPT_POST, 1L);
        curl_easy_setopt(h->easy, CURLOPT_POSTFIELDS, body ? (const char *)body : "");
        curl_easy_setopt(h->easy, CURLOPT_POSTFIELDSIZE_LARGE, (curl_off_t)(body ? len : 0));
        if (content_type) {
            snprintf(line, sizeof line, "Content-Type: %s", content_type);
            ADD_HEADER(line);
        } else {
            /* libcurl would claim a form otherwise */
            ADD_HEADER("Content-Type:");
        }
    } else if (strcmp(method, "GET") != 0) {
        curl_easy_setopt(h->easy, CURLOPT_CUSTOMREQUEST, method);
    }
    if (idempotency_key) {
        snprintf(line, sizeof line, "Idempotency-Key: %s", idempotency_key);
        ADD_HEADER(line);
    }
#undef ADD_HEADER
    curl_easy_setopt(h->easy, CURLOPT_HTTPHEADER, hdrs);
    curl_easy_setopt(h->easy, CURLOPT_HEADERFUNCTION, on_header);
    curl_easy_setopt(h->easy, CURLOPT_HEADERDATA, resp);
    curl_easy_setopt(h->easy, CURLOPT_WRITEFUNCTION, on_body);
    curl_easy_setopt(h->easy, CURLOPT_WRITEDATA, &s);

    CURLcode cc = curl_easy_perform(h->easy);
    curl_easy_getinfo(h->easy, CURLINFO_RESPONSE_CODE, &resp->status);
    bool ok_status = resp->status >= 200 && resp->status < 300;
    if (cc != CURLE_OK) {
        if (resp->body.overflow && ok_status)
            rc = mrc_fail(err, MRC_EXIT_SERVER, "%s %s: the answer is larger than %zu bytes", method,
                          url, (size_t)JSON_BODY_LIMIT);
        else if (resp->status >= 300 && resp->body.len > 0)
            rc = 0; /* an error page that broke off: its start still says what went wrong */
        else
            rc = transport_error(method, url, cc, h->errbuf, err);
        goto cleanup;
    }
cleanup:
    curl_slist_free_all(hdrs);
    free(url);
    return rc;
}

static const char *reason_phrase(long status)
{
    switch (status) {
    case 400: return "Bad Request";
    case 401: return "Unauthorized";
    case 403: return "Forbidden";
    case 404: return "Not Found";
    case 405: return "Method Not Allowed";
    case 406: return "Not Acceptable";
    case 408: return "Request Timeout";
    case 409: return "Conflict";
    case 410: return "Gone";
    case 411: return "Length Required";
    case 413: return "Content Too Large";
    case 415: return "Unsupported Media Type";
    case 422: return "Unprocessable Content";
    case 429: return "Too Many Requests";
    case 500: return "Internal Server Error";
    case 501: return "Not Implemented";
    case 502: return "Bad Gateway";
    case 503: return "Service Unavailable";
    case 504: return "Gateway Timeout";
    default: return status >= 300 && status < 400 ? "Redirect" : "Unexpected Status";
    }
}

int mrc_http_check(const mrc_response *resp, mrc_error *err)
{
    long st = resp->status;
    if (st >= 200 && st < 300)
        return 0;
    int code = (st >= 400 && st < 500) ? MRC_EXIT_REJECTED : MRC_EXIT_SERVER;
    char title[200], detail[600], pointer[160];
    title[0] = detail[0] = pointer[0] = '\0';

    cJSON *doc = NULL;
    if (resp->body.data && resp->body.len > 0)
        doc = cJSON_ParseWithLength(resp->body.data, resp->body.len);
    if (cJSON_IsObject(doc)) {
        mrc_sanitize(title, sizeof title, mrc_json_str(doc, "title"));
        mrc_sanitize(detail, sizeof detail, mrc_json_str(doc, "detail"));
        mrc_sanitize(pointer, sizeof pointer, mrc_json_str(doc, "pointer"));
    } else if (resp->body.data && resp->body.len > 0) {
        /* not a problem document (a proxy's page, a crash): show its first line */
        const char *p = resp->body.data;
        while (*p && isspace((unsigned char)*p))
            p++;
        size_t n = strcspn(p, "\r\n");
        if (n > 160)
            n = 160;
        char first[161];
        memcpy(first, p, n);
        first[n] = '\0';
        mrc_sanitize(detail, sizeof detail, first);
    }
    cJSON_Delete(doc);
    if (!title[0])
        snprintf(title, sizeof title, "%s", reason_phrase(st));
    if (st == 0)
        return mrc_fail(err, MRC_EXIT_SERVER, "no HTTP answer");
    if (detail[0] && pointer[0])
        return mrc_fail(err, code, "%ld %s: %s (at %s)", st, title, detail, pointer);
    if (detail[0])
        return mrc_fail(err, code, "%ld %s: %s", st, title, detail);
    if (pointer[0])
        return mrc_fail(err, code, "%ld %s (at %s)", st, title, pointer);
    return mrc_fail(err, code, "%ld %s", st, title);
}

int mrc_http_json(mrc_http *h, const char *method, const char *path, const void *body,
                  size_t len, const char *content_type, const char *idempotency_key,
                  mrc_response *resp, cJSON **json, mrc_error *err)
{
    *json = NULL;
    int rc = mrc_http_request(h, method, path, body, len, content_type, idempotency_key, resp, err);
    if (rc < 0)
        return rc;
    rc = mrc_http_check(resp, err);
    if (rc < 0)
        return rc;
    if (resp->body.len == 0)
        return 0;
    cJSON *doc = cJSON_ParseWithLength(resp->body.data, resp->body.len);
    if (!cJSON_IsObject(doc)) {
        cJSON_Delete(doc);
        return mrc_fail(err, MRC_EXIT_SERVER, "%s %s%s: the answer (%ld) is not a JSON object",
                        method, h->base, path, resp->status);
    }
    *json = doc;
    return 0;
}

int mrc_http_get_json(mrc_http *h, const char *path, cJSON **json, mrc_error *err)
{
    mrc_response resp = {0};
    int rc = mrc_http_json(h, "GET", path, NULL, 0, NULL, NULL, &resp, json, err);
    if (rc == 0 && !*json)
        rc = mrc_fail(err, MRC_EXIT_SERVER, "GET %s: empty answer", path);
    mrc_response_free(&resp);
    return rc;
}

/* ---- downloads and uploads ------------------------------------------------ */

int mrc_http_download(mrc_http *h, const char *path, const char *dest, int64_t *bytes,
                      mrc_error *err)
{
    int rc = 0, fd = -1;
    char *url = NULL, *tmp = NULL;
    struct curl_slist *hdrs = NULL;
    mrc_response resp = {0};
    sink s = {.curl = h->easy, .resp = &resp, .fd = -1};

    if (bytes)
        *bytes = 0;
    url = make_url(h, path, err);
    /* ".NAME.PID.tmp" next to the target: same file system, so rename is
     * atomic, and hidden from globs like *.exr */
    size_t tn = strlen(dest) + 48;
    tmp = malloc(tn);
    if (!url || !tmp) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
        goto cleanup;
    }
    const char *slash = strrchr(dest, '/');
    int dir_len = slash ? (int)(slash - dest + 1) : 0;
    snprintf(tmp, tn, "%.*s.%s.%ld.tmp", dir_len, dest, dest + dir_len, (long)getpid());
    for (int attempt = 0; attempt < 2 && fd < 0; attempt++) {
        fd = open(tmp, O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC | O_NOFOLLOW, 0666);
        if (fd < 0 && errno == EEXIST && attempt == 0)
            unlink(tmp); /* left behind by an earlier process with our pid */
        else if (fd < 0)
            break;
    }
    if (fd < 0) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "cannot create %s: %s", tmp, strerror(errno));
        goto cleanup;
    }

    hdrs = curl_slist_append(NULL, "Accept: */*");
    CURLcode cc;
    for (int waited = 0;;) {
        response_reset(&resp, ERROR_BODY_LIMIT);
        s = (sink){.curl = h->easy, .resp = &resp, .fd = fd};
        setup(h, h->easy, h->errbuf, url, KIND_TRANSFER);
        curl_easy_setopt(h->easy, CURLOPT_HTTPHEADER, hdrs);
        curl_easy_setopt(h->easy, CURLOPT_HEADERFUNCTION, on_header);
        curl_easy_setopt(h->easy, CURLOPT_HEADERDATA, &resp);
        curl_easy_setopt(h->easy, CURLOPT_WRITEFUNCTION, on_body);
        curl_easy_setopt(h->easy, CURLOPT_WRITEDATA, &s);
        cc = curl_easy_perform(h->easy);
        curl_easy_getinfo(h->easy, CURLINFO_RESPONSE_CODE, &resp.status);
        /* busy for a moment (an error body is never written to the file) */
        if (resp.status != 503 || resp.retry_after < 1 || resp.retry_after > 5 ||
            waited + resp.retry_after > 60)
            break;
        sleep((unsigned)resp.retry_after);
        waited += resp.retry_after;
    }
    if (s.write_errno) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "cannot write %s: %s", tmp, strerror(s.write_errno));
        goto cleanup;
    }
    if (cc != CURLE_OK && !(resp.status >= 300 && resp.body.len > 0)) {
        rc = transport_error("GET", url, cc, h->errbuf, err);
        goto cleanup;
    }
    rc = mrc_http_check(&resp, err);
    if (rc < 0)
        goto cleanup;
    /* the file must be complete on disk before its final name appears */
    if (fsync(fd) != 0 && errno != EINVAL) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "cannot write %s: %s", tmp, strerror(errno));
        goto cleanup;
    }
    int cfd = fd;
    fd = -1;
    if (close(cfd) != 0) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "cannot write %s: %s", tmp, strerror(errno));
        goto cleanup;
    }
    if (rename(tmp, dest) != 0) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "cannot rename %s to %s: %s", tmp, dest, strerror(errno));
        goto cleanup;
    }
    free(tmp);
    tmp = NULL; /* renamed: nothing to remove */
    if (bytes)
        *bytes = s.written;
cleanup:
    if (fd >= 0)
        close(fd);
    if (tmp && s.fd >= 0)
        unlink(tmp);
    curl_slist_free_all(hdrs);
    mrc_response_free(&resp);
    free(tmp);
    free(url);
    return rc;
}

typedef struct upload_src {
    FILE *f;
    int read_errno;
} upload_src;

static size_t on_read(char *p, size_t size, size_t nmemb, void *user)
{
    upload_src *u = user;
    size_t n = fread(p, 1, size * nmemb, u->f);
    if (n == 0 && ferror(u->f)) {
        u->read_errno = errno ? errno : EIO;
        return CURL_READFUNC_ABORT;
    }
    return n;
}

int mrc_http_upload(mrc_http *h, const char *path, const char *file, mrc_response *resp,
                    mrc_error *err)
{
    int rc = 0;
    char *url = NULL;
    struct curl_slist *hdrs = NULL, *tmp = NULL;
    upload_src src = {0};
    sink s = {.curl = h->easy, .resp = resp, .fd = -1};
    struct stat st;

    response_reset(resp, JSON_BODY_LIMIT);
    src.f = fopen(file, "rb");
    if (!src.f) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "%s: %s", file, strerror(errno));
        goto cleanup;
    }
    if (fstat(fileno(src.f), &st) != 0 || !S_ISREG(st.st_mode)) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "%s: not a regular file", file);
        goto cleanup;
    }
    url = make_url(h, path, err);
    hdrs = curl_slist_append(NULL, "Content-Type: application/octet-stream");
    tmp = hdrs ? curl_slist_append(hdrs, "Accept: application/json, application/problem+json") : NULL;
    if (!url || !tmp) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
        goto cleanup;
    }
    hdrs = tmp;
    setup(h, h->easy, h->errbuf, url, KIND_TRANSFER);
    curl_easy_setopt(h->easy, CURLOPT_POST, 1L);
    curl_easy_setopt(h->easy, CURLOPT_READFUNCTION, on_read);
    curl_easy_setopt(h->easy, CURLOPT_READDATA, &src);
    curl_easy_setopt(h->easy, CURLOPT_POSTFIELDSIZE_LARGE, (curl_off_t)st.st_size);
    curl_easy_setopt(h->easy, CURLOPT_HTTPHEADER, hdrs);
    curl_easy_setopt(h->easy, CURLOPT_HEADERFUNCTION, on_header);
    curl_easy_setopt(h->easy, CURLOPT_HEADERDATA, resp);
    curl_easy_setopt(h->easy, CURLOPT_WRITEFUNCTION, on_body);
    curl_easy_setopt(h->easy, CURLOPT_WRITEDATA, &s);
    CURLcode cc = curl_easy_perform(h->easy);
    curl_easy_getinfo(h->easy, CURLINFO_RESPONSE_CODE, &resp->status);
    if (src.read_errno) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "%s: %s", file, strerror(src.read_errno));
        goto cleanup;
    }
    if (cc != CURLE_OK && !(resp->status >= 300 && resp->body.len > 0)) {
        if (resp->body.overflow && resp->status >= 200 && resp->status < 300)
            rc = mrc_fail(err, MRC_EXIT_SERVER, "POST %s: the answer is too large", url);
        else
            rc = transport_error("POST", url, cc, h->errbuf, err);
        goto cleanup;
    }
cleanup:
    if (src.f)
        fclose(src.f);
    curl_slist_free_all(hdrs);
    free(url);
    return rc;
}

/* ---- the event stream ----------------------------------------------------- */

typedef struct stream_ctx {
    CURL *curl;
    mrc_response *resp;
    mrc_stream_data_fn on_data;
    mrc_stream_tick_fn on_tick;
    void *user;
    bool checked, is_stream, stopped;
} stream_ctx;

static size_t on_stream_body(char *p, size_t size, size_t nmemb, void *user)
{
    stream_ctx *c = user;
    size_t len = size * nmemb;
    if (!c->checked) {
        long code = 0;
        curl_easy_getinfo(c->curl, CURLINFO_RESPONSE_CODE, &code);
        c->is_stream = code == 200 && strncasecmp(c->resp->content_type, "text/event-stream", 17) == 0;
        c->checked = true;
    }
    if (!c->is_stream) {
        buf_append(&c->resp->body, p, len); /* an error document, reported afterwards */
        return len;
    }
    if (c->on_data(p, len, c->user) != 0) {
        c->stopped = true;
        return 0;
    }
    return len;
}

static int on_stream_progress(void *user, curl_off_t dltotal, curl_off_t dlnow, curl_off_t ultotal,
                              curl_off_t ulnow)
{
    (void)dltotal, (void)dlnow, (void)ultotal, (void)ulnow;
    stream_ctx *c = user;
    if (c->on_tick && c->on_tick(c->user) != 0) {
        c->stopped = true;
        return 1;
    }
    return 0;
}

int mrc_http_stream(mrc_http *h, const char *path, const char *last_event_id,
                    mrc_stream_data_fn on_data, mrc_stream_tick_fn on_tick, void *user,
                    mrc_error *err)
{
    int rc = 0;
    char *url = NULL;
    struct curl_slist *hdrs = NULL, *tmp = NULL;
    mrc_response resp = {0};
    stream_ctx c = {.curl = h->stream, .resp = &resp, .on_data = on_data, .on_tick = on_tick,
                    .user = user};

    response_reset(&resp, ERROR_BODY_LIMIT);
    url = make_url(h, path, err);
    hdrs = curl_slist_append(NULL, "Accept: text/event-stream");
    tmp = hdrs ? curl_slist_append(hdrs, "Cache-Control: no-cache") : NULL;
    if (tmp && last_event_id && last_event_id[0]) {
        char line[96];
        /* the id came from the server's stream: printable, no line breaks */
        snprintf(line, sizeof line, "Last-Event-ID: %.64s", last_event_id);
        hdrs = tmp;
        tmp = strpbrk(last_event_id, "\r\n") ? NULL : curl_slist_append(hdrs, line);
    }
    if (!url || !tmp) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
        goto cleanup;
    }
    hdrs = tmp;
    setup(h, h->stream, h->stream_errbuf, url, KIND_STREAM);
    curl_easy_setopt(h->stream, CURLOPT_HTTPHEADER, hdrs);
    curl_easy_setopt(h->stream, CURLOPT_HEADERFUNCTION, on_header);
    curl_easy_setopt(h->stream, CURLOPT_HEADERDATA, &resp);
    curl_easy_setopt(h->stream, CURLOPT_WRITEFUNCTION, on_stream_body);
    curl_easy_setopt(h->stream, CURLOPT_WRITEDATA, &c);
    curl_easy_setopt(h->stream, CURLOPT_NOPROGRESS, 0L);
    curl_easy_setopt(h->stream, CURLOPT_XFERINFOFUNCTION, on_stream_progress);
    curl_easy_setopt(h->stream, CURLOPT_XFERINFODATA, &c);
    CURLcode cc = curl_easy_perform(h->stream);
    curl_easy_getinfo(h->stream, CURLINFO_RESPONSE_CODE, &resp.status);
    if (c.stopped) {
        rc = 1;
    } else if (resp.status != 200 && resp.status != 0) {
        rc = mrc_http_check(&resp, err);
        if (rc == 0)
            rc = mrc_fail(err, MRC_EXIT_SERVER, "GET %s: answered %ld instead of an event stream",
                          url, resp.status);
    } else if (cc != CURLE_OK) {
        rc = transport_error("GET", url, cc, h->stream_errbuf, err);
    } else if (!c.is_stream) {
        /* 200 with another content type, or no body at all */
        rc = mrc_fail(err, MRC_EXIT_SERVER, "GET %s: not an event stream (%s)", url,
                      resp.content_type[0] ? resp.content_type : "no content type");
    }
cleanup:
    curl_slist_free_all(hdrs);
    mrc_response_free(&resp);
    free(url);
    return rc;
}
