/*
 * sse.h - an incremental parser for server-sent events (text/event-stream),
 * as the daemon's GET /v1/jobs/{id}/events sends them.
 *
 * Bytes arrive in arbitrary chunks from libcurl; the parser joins lines
 * across chunks (CR, LF and CRLF endings, also a CRLF split between two
 * chunks), collects "event:" and "data:" fields and calls the handler once
 * per complete event. Comments (":" lines, used as keep-alives) and
 * "retry:" are ignored; "id:" is kept as the stream's last event id (what
 * a resumed stream sends back as Last-Event-ID), as the WHATWG HTML
 * specification's event stream interpretation says. Lines and events have size caps so a misbehaving
 * server cannot make the client grow without bound.
 */
#ifndef MRC_SSE_H
#define MRC_SSE_H

#include <stdbool.h>
#include <stddef.h>

#define MRC_SSE_MAX_LINE (1u << 20)  /* one field line */
#define MRC_SSE_MAX_DATA (4u << 20)  /* the joined data of one event */

/* event is "message" when the server named none; data has its lines joined
 * with "\n" and is NUL-terminated. Returns 0 to go on, or a positive value
 * that stops parsing and is passed back by mrc_sse_feed. */
typedef int (*mrc_sse_handler)(const char *event, const char *data, size_t len, void *user);

typedef struct mrc_sse {
    mrc_sse_handler handler;
    void *user;
    char *line;          /* the line being assembled */
    size_t line_len, line_cap;
    char *data;          /* data lines of the event being assembled */
    size_t data_len, data_cap;
    char event[64];
    char id_buf[64];     /* the id field of the event being assembled */
    char last_id[64];    /* set from id_buf when an event is dispatched; "" until one had an id */
    bool have_data;
    bool after_cr;       /* the last byte was CR: an LF right after it is part of the same break */
} mrc_sse;

void mrc_sse_init(mrc_sse *s, mrc_sse_handler handler, void *user);
/* 0: consumed; > 0: the handler's stopping value; -1: a cap was exceeded or
 * memory ran out (the stream should be abandoned). */
int mrc_sse_feed(mrc_sse *s, const char *buf, size_t n);
void mrc_sse_free(mrc_sse *s);

#endif
