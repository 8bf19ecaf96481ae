/*
 * sse.c - incremental text/event-stream parser (see sse.h). Follows the
 * field rules of the HTML "server-sent events" section: a line up to the
 * first ':' is the field name, one space after the colon is dropped, "data"
 * lines accumulate, an empty line dispatches the event.
 */
#include "sse.h"

#include <stdlib.h>
#include <string.h>

void mrc_sse_init(mrc_sse *s, mrc_sse_handler handler, void *user)
{
    memset(s, 0, sizeof *s);
    s->handler = handler;
    s->user = user;
}

void mrc_sse_free(mrc_sse *s)
{
    free(s->line);
    free(s->data);
    s->line = s->data = NULL;
    s->line_len = s->line_cap = s->data_len = s->data_cap = 0;
}

/* Ensures room for `extra` more bytes plus a terminator. */
static int reserve(char **buf, size_t *cap, size_t len, size_t extra, size_t max)
{
    if (len + extra + 1 <= *cap)
        return 0;
    if (len + extra > max)
        return -1;
    size_t ncap = *cap ? *cap : 256;
    while (ncap < len + extra + 1)
        ncap *= 2;
    if (ncap > max + 1)
        ncap = max + 1;
    char *n = realloc(*buf, ncap);
    if (!n)
        return -1;
    *buf = n;
    *cap = ncap;
    return 0;
}

static int dispatch(mrc_sse *s)
{
    memcpy(s->last_id, s->id_buf, sizeof s->last_id);
    int rc = 0;
    if (s->have_data) {
        /* the data buffer holds "line\n" per data line: drop the last "\n" */
        size_t len = s->data_len ? s->data_len - 1 : 0;
        if (reserve(&s->data, &s->data_cap, len, 0, MRC_SSE_MAX_DATA) != 0)
            return -1;
        s->data[len] = '\0';
        rc = s->handler(s->event[0] ? s->event : "message", s->data, len, s->user);
    }
    s->data_len = 0;
    s->have_data = false;
    s->event[0] = '\0';
    return rc > 0 ? rc : 0;
}

static int process_line(mrc_sse *s)
{
    const char *line = s->line ? s->line : "";
    size_t len = s->line_len;
    if (len == 0)
        return dispatch(s);
    if (line[0] == ':')
        return 0; /* comment, typically a keep-alive */
    const char *colon = memchr(line, ':', len);
    size_t name_len = colon ? (size_t)(colon - line) : len;
    const char *value = colon ? colon + 1 : line + len;
    size_t value_len = (size_t)(line + len - value);
    if (value_len > 0 && value[0] == ' ') {
        value++;
        value_len--;
    }
    if (name_len == 5 && memcmp(line, "event", 5) == 0) {
        size_t n = value_len < sizeof s->event - 1 ? value_len : sizeof s->event - 1;
        memcpy(s->event, value, n);
        s->event[n] = '\0';
    } else if (name_len == 4 && memcmp(line, "data", 4) == 0) {
        if (reserve(&s->data, &s->data_cap, s->data_len, value_len + 1, MRC_SSE_MAX_DATA) != 0)
            return -1;
        memcpy(s->data + s->data_len, value, value_len);
        s->data_len += value_len;
        s->data[s->data_len++] = '\n';
        s->have_data = true;
    } else if (name_len == 2 && memcmp(line, "id", 2) == 0) {
        /* an id with a NUL is ignored (spec); one too long for us too */
        if (!memchr(value, '\0', value_len) && value_len < sizeof s->id_buf) {
            memcpy(s->id_buf, value, value_len);
            s->id_buf[value_len] = '\0';
        }
    }
    /* "retry" and unknown fields: nothing the client needs */
    return 0;
}

int mrc_sse_feed(mrc_sse *s, const char *buf, size_t n)
{
    for (size_t i = 0; i < n; i++) {
        char c = buf[i];
        if (c == '\n' && s->after_cr) {
            s->after_cr = false; /* second half of a CRLF already handled */
            continue;
        }
        s->after_cr = false;
        if (c == '\r' || c == '\n') {
            s->after_cr = c == '\r';
            int rc = process_line(s);
            s->line_len = 0;
            if (rc != 0)
                return rc;
            continue;
        }
        if (reserve(&s->line, &s->line_cap, s->line_len, 1, MRC_SSE_MAX_LINE) != 0)
            return -1;
        s->line[s->line_len++] = c;
    }
    return 0;
}
