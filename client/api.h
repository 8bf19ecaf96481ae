/*
 * api.h - the client's HTTP layer over libcurl: JSON requests, streamed
 * downloads into files (atomically renamed into place), streamed uploads,
 * the server-sent event stream, and RFC 9457 problem+json error messages.
 *
 * One mrc_http holds two curl handles: one for ordinary requests and
 * downloads (reused, so consecutive requests share a keep-alive
 * connection) and one for the event stream, so frames can be downloaded
 * while the stream stays open. Timeouts: 5 s to connect; ordinary requests
 * at most 120 s; downloads, uploads and the stream have no total limit but
 * are abandoned when fewer than 1 byte/s arrives for a while.
 * curl_global_init() is the caller's business (main, once).
 */
#ifndef MRC_API_H
#define MRC_API_H

#include "client.h"

typedef struct mrc_http mrc_http;

/* A growable byte buffer with a cap; always NUL-terminated when non-NULL. */
typedef struct mrc_buf {
    char *data;
    size_t len, cap, limit;
    bool overflow; /* more arrived than `limit`; the rest was dropped */
} mrc_buf;

typedef struct mrc_response {
    long status;            /* HTTP status, 0 when no response arrived */
    char content_type[128];
    char location[512];     /* Location header, "" when absent */
    int retry_after;        /* Retry-After in seconds (delta form), 0 when absent */
    mrc_buf body;
} mrc_response;

void mrc_response_free(mrc_response *r);

/* base: "http://host:port" (a missing scheme means http://; trailing
 * slashes are dropped). Only http and https are ever spoken. */
int mrc_http_open(const char *base, mrc_http **out, mrc_error *err);
void mrc_http_close(mrc_http *h);
/* The bearer token (Authorization: Bearer) every later request sends; NULL
 * or "" sends none. */
int mrc_http_set_token(mrc_http *h, const char *token, mrc_error *err);
const char *mrc_http_base(const mrc_http *h);

/* One request; method "GET", "POST" or "DELETE". body may be NULL (POST
 * then sends an empty body). idempotency_key may be NULL. Succeeds (0)
 * whenever any HTTP answer arrived, whatever its status; fails with
 * MRC_EXIT_SERVER when the server could not be reached or the answer broke
 * off or exceeded the body cap. */
int mrc_http_request(mrc_http *h, const char *method, const char *path, const void *body,
                     size_t len, const char *content_type, const char *idempotency_key,
                     mrc_response *resp, mrc_error *err);

/* Turns a non-2xx response into an error: "<status> <title>: <detail>
 * (at <pointer>)" from problem+json, or the status and the start of the
 * body otherwise. 4xx -> MRC_EXIT_REJECTED, anything else ->
 * MRC_EXIT_SERVER. Returns 0 for 2xx. */
int mrc_http_check(const mrc_response *resp, mrc_error *err);

/* mrc_http_request + mrc_http_check + parsing the body as a JSON object.
 * *json is NULL when the answer had no body (204). */
int mrc_http_json(mrc_http *h, const char *method, const char *path, const void *body,
                  size_t len, const char *content_type, const char *idempotency_key,
                  mrc_response *resp, cJSON **json, mrc_error *err);

/* GET path as a JSON object; an answer without a body is an error
 * (MRC_EXIT_SERVER) here. */
int mrc_http_get_json(mrc_http *h, const char *path, cJSON **json, mrc_error *err);

/* GET path into file dest, streamed (never held in memory): written to a
 * temporary name in dest's directory, fsync'ed and renamed over dest only
 * after the whole body arrived with a 2xx status. *bytes (may be NULL)
 * receives the size. A 503 with a Retry-After of 1 to 5 seconds (the
 * daemon busy making previews) is tried again after that wait, for up to
 * a minute in all. */
int mrc_http_download(mrc_http *h, const char *path, const char *dest, int64_t *bytes,
                      mrc_error *err);

/* POST the file's bytes (application/octet-stream), streamed from disk. */
int mrc_http_upload(mrc_http *h, const char *path, const char *file, mrc_response *resp,
                    mrc_error *err);

/* GET path as text/event-stream (resuming after last_event_id when it is
 * not NULL or "": Last-Event-ID) and hand the raw bytes to on_data as they
 * arrive; on_tick is called about once a second while waiting (may be
 * NULL), for redrawing progress. Either callback may stop the stream by
 * returning nonzero.
 * Returns 0 when the server ended the stream, 1 when a callback stopped it,
 * negative (with err filled) when it could not be opened or broke. */
typedef int (*mrc_stream_data_fn)(const char *data, size_t len, void *user);
typedef int (*mrc_stream_tick_fn)(void *user);
int mrc_http_stream(mrc_http *h, const char *path, const char *last_event_id,
                    mrc_stream_data_fn on_data, mrc_stream_tick_fn on_tick, void *user,
                    mrc_error *err);

#endif
