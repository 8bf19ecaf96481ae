/*
 * render_msg.c - framing of the daemon's render-worker messages (render_msg.h).
 * Both ends are the same binary, so the header is written in the host's
 * byte order; a magic number catches a stream out of step.
 */
#include "render_msg.h"

#include <errno.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/uio.h>
#include <unistd.h>

#define MSG_MAGIC 0x4d524d53u /* "MRMS" */

typedef struct wire_header {
    uint32_t magic, type, index;
    int32_t code;
    uint32_t flags, pad;
    uint64_t len[MR_MSG_PARTS];
} wire_header;

int mr_msg_send(int fd, const mr_msg *m, mr_error *err)
{
    wire_header h = {.magic = MSG_MAGIC, .type = m->type, .index = m->index, .code = m->code,
                     .flags = m->flags};
    struct iovec iov[1 + MR_MSG_PARTS];
    int n = 0;
    iov[n++] = (struct iovec){.iov_base = &h, .iov_len = sizeof h};
    for (int i = 0; i < MR_MSG_PARTS; i++) {
        h.len[i] = m->len[i];
        if (m->len[i])
            iov[n++] = (struct iovec){.iov_base = (void *)m->part[i], .iov_len = m->len[i]};
    }
    struct msghdr mh = {.msg_iov = iov, .msg_iovlen = (size_t)n};
    while (mh.msg_iovlen > 0) {
        ssize_t w = sendmsg(fd, &mh, MSG_NOSIGNAL);
        if (w < 0 && errno == EINTR)
            continue;
        if (w < 0)
            return mr_error_set(err, MR_ERR_IO, "render worker channel: %s", strerror(errno));
        size_t done = (size_t)w;
        while (mh.msg_iovlen > 0 && done >= mh.msg_iov[0].iov_len) {
            done -= mh.msg_iov[0].iov_len;
            mh.msg_iov++;
            mh.msg_iovlen--;
        }
        if (mh.msg_iovlen > 0) {
            mh.msg_iov[0].iov_base = (uint8_t *)mh.msg_iov[0].iov_base + done;
            mh.msg_iov[0].iov_len -= done;
        }
    }
    return MR_OK;
}

/* 1: all n bytes read; 0: the stream ended before the first byte; -1: error
 * or an end in the middle (errno EPIPE then). */
static int read_full(int fd, void *p, size_t n)
{
    uint8_t *b = p;
    size_t got = 0;
    while (got < n) {
        ssize_t r = read(fd, b + got, n - got);
        if (r < 0 && errno == EINTR)
            continue;
        if (r < 0)
            return -1;
        if (r == 0) {
            if (got == 0)
                return 0;
            errno = EPIPE;
            return -1;
        }
        got += (size_t)r;
    }
    return 1;
}

int mr_msg_recv(int fd, size_t max_bytes, mr_msg *m, mr_error *err)
{
    memset(m, 0, sizeof *m);
    wire_header h;
    int r = read_full(fd, &h, sizeof h);
    if (r == 0)
        return mr_error_set(err, MR_ERR_IO, "render worker channel closed");
    if (r < 0)
        return mr_error_set(err, MR_ERR_IO, "render worker channel: %s", strerror(errno));
    if (h.magic != MSG_MAGIC || h.type < MR_MSG_HELLO || h.type > MR_MSG_END)
        return mr_error_set(err, MR_ERR_FORMAT, "render worker channel: not a message header");
    uint64_t total = 0;
    for (int i = 0; i < MR_MSG_PARTS; i++) {
        if (h.len[i] > max_bytes || total + h.len[i] + 1 > max_bytes)
            return mr_error_set(err, MR_ERR_FORMAT, "render worker channel: a message of more "
                                "than %zu bytes", max_bytes);
        total += h.len[i] + 1; /* each part NUL-terminated */
    }
    m->type = h.type;
    m->index = h.index;
    m->code = h.code;
    m->flags = h.flags;
    m->buf = malloc(total ? (size_t)total : 1);
    if (!m->buf)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory reading a %llu-byte message",
                            (unsigned long long)total);
    uint8_t *p = m->buf;
    for (int i = 0; i < MR_MSG_PARTS; i++) {
        if (h.len[i] && read_full(fd, p, (size_t)h.len[i]) != 1) {
            int e = errno;
            mr_msg_free(m);
            return mr_error_set(err, MR_ERR_IO, "render worker channel: %s", strerror(e));
        }
        p[h.len[i]] = '\0';
        m->part[i] = p;
        m->len[i] = (size_t)h.len[i];
        p += h.len[i] + 1;
    }
    return MR_OK;
}

void mr_msg_free(mr_msg *m)
{
    free(m->buf);
    memset(m, 0, sizeof *m);
}
