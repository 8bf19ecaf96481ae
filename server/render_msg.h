/*
 * render_msg.h - the messages between the daemon and a render worker
 * process (render_proc.h), on a local stream socket.
 *
 * A message is a fixed header (type, frame index, an mr_err code, flags,
 * the lengths of up to four byte strings) followed by those strings. The
 * conversation is strictly request and answer, so neither side ever waits
 * on a message the other is not about to send:
 *
 *   worker -> daemon  HELLO    (index: MR_RENDER_PROTOCOL) once, at start
 *   daemon -> worker  JOB      parts: job id, job JSON as submitted, the
 *                              resolved asset paths (each NUL-terminated),
 *                              the wanted frames (one byte per frame, 1 = render)
 *   worker -> daemon  STARTED  (index) a frame is being rendered
 *                    FRAME    (index) parts: stats JSON, EXR file bytes
 *   daemon -> worker  ACK      (code: how storing it went; flags: the
 *                              decision when it failed, STOP)
 *   worker -> daemon  FAILED   (index, code) part: the error message
 *   daemon -> worker  DECISION (flags: RETRY/SKIP/ABORT, STOP)
 *   worker -> daemon  END      (code) parts: the error message, the
 *                              worker's scene-cache figures (mr_cache_stats)
 *
 * A cancel does not travel as a message: the daemon kills the worker.
 */
#ifndef MR_RENDER_MSG_H
#define MR_RENDER_MSG_H

#include <stddef.h>
#include <stdint.h>

#include "microray.h"

/* Raised whenever a message changes meaning. */
#define MR_RENDER_PROTOCOL 1

typedef enum mr_msg_type {
    MR_MSG_HELLO = 1,
    MR_MSG_JOB,
    MR_MSG_STARTED,
    MR_MSG_FRAME,
    MR_MSG_ACK,
    MR_MSG_FAILED,
    MR_MSG_DECISION,
    MR_MSG_END
} mr_msg_type;

/* flags of ACK and DECISION: the low two bits are an mr_frame_decision
 * (worker.h) when the frame failed; STOP asks the worker to end the job
 * after this frame (the daemon is stopping, or the disk is full). */
#define MR_MSG_DECISION_MASK 3u
#define MR_MSG_STOP 4u

#define MR_MSG_PARTS 4

typedef struct mr_msg {
    uint32_t type;   /* mr_msg_type */
    uint32_t index;  /* frame index */
    int32_t code;    /* an mr_err */
    uint32_t flags;
    size_t len[MR_MSG_PARTS];
    /* Sending: borrowed. Received: each part is NUL-terminated (one byte
     * past len) and owned by the message (mr_msg_free). */
    const uint8_t *part[MR_MSG_PARTS];
    uint8_t *buf;
} mr_msg;

/* Writes the whole message (MR_ERR_IO if the peer is gone: no SIGPIPE). */
int mr_msg_send(int fd, const mr_msg *m, mr_error *err);
/* Reads one message, blocking until it is complete. A message longer than
 * max_bytes in all, or a malformed header, is MR_ERR_FORMAT; the end of the
 * stream is MR_ERR_IO ("closed"). */
int mr_msg_recv(int fd, size_t max_bytes, mr_msg *m, mr_error *err);
void mr_msg_free(mr_msg *m);

#endif
