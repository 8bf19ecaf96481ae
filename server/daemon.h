/*
 * daemon.h - microrayd serve: the render service around the store.
 *
 * A daemon owns the store, the Embree device, the scene cache, a pool of
 * render workers and the HTTP front end (http.h). Jobs arrive through HTTP,
 * are validated and stored as queued; workers claim them by priority and
 * render frame by frame (never on an HTTP thread), writing each finished
 * frame through the store. Events (frame done, state changes) are published
 * to subscribers (the SSE endpoint). SIGTERM: stop accepting work (/readyz
 * and submissions answer 503 with Retry-After, reads go on), let the frame
 * in progress finish, leave the job queued so the next start resumes it,
 * and only then close the port.
 */
#ifndef MR_DAEMON_H
#define MR_DAEMON_H

#include "job_json.h"
#include "microray.h"
#include "store.h"

typedef struct mr_daemon_config {
    const char *listen_host;      /* default "127.0.0.1" */
    unsigned port;                /* 0 = pick a free port (tests); default 8470 */
    const char *data_dir;         /* required */
    const char *const *asset_roots; /* server-side paths must resolve below one of these */
    size_t asset_root_count;
    unsigned workers;             /* jobs rendered at once; default 1 */
    unsigned render_threads;      /* threads per render; 0 = all cores */
    size_t cache_bytes;           /* scene cache cap; default 1 GiB */
    size_t max_job_bytes;         /* POST /v1/jobs body cap; default 1 MiB */
    size_t max_asset_bytes;       /* POST /v1/assets body cap; default 512 MiB */
    unsigned http_threads;        /* libmicrohttpd thread pool; default one per core */
    unsigned connection_timeout_s;/* idle connection timeout; default 30 */
    unsigned per_ip_connections;  /* default 128 */
    size_t import_memory;         /* an import's own memory; default a quarter of RAM, >= 1 GiB */
    double import_timeout_s;      /* an import's wall clock; default 300 */
    const char *worker_exe;       /* the microrayd binary render workers run (render_proc.h;
                                     they exec it again for each import, import_worker.h);
                                     default /proc/self/exe, this very binary */
    size_t job_memory;            /* a job's geometry (mr_renderer_options.memory_budget);
                                     default half of RAM */
    size_t worker_memory;         /* a render worker's resident memory, beyond which it is
                                     killed; default job_memory + cache_bytes + 1 GiB */
    double frame_timeout_s;       /* a frame's (and a job's preparation's) wall clock in a
                                     render worker; 0: none (the default) */
    size_t disk_reserve;          /* bytes kept free for a full disk (space_guard.h); default 64 MiB */
    unsigned max_connections;     /* connection budget; default 1024 */
    unsigned request_timeout_s;   /* request head deadline, body grace; default 10 */
    const char *token;            /* bearer token every request but /healthz, /readyz needs; NULL: none */
    bool insecure;                /* allow a non-loopback listen address without a token */
    const char *tls_cert_pem;     /* TLS certificate chain and key (PEM text); NULL: plain HTTP */
    const char *tls_key_pem;
    bool quiet;                   /* no request/frame log lines */
} mr_daemon_config;

typedef struct mr_daemon mr_daemon;

/* Opens the store, recovers after a crash, starts workers and HTTP. */
int mr_daemon_start(const mr_daemon_config *cfg, mr_daemon **out, mr_error *err);
/* The port actually listened on (useful with port 0). */
unsigned mr_daemon_port(const mr_daemon *d);
/* Graceful stop: the queue stops and every frame in progress finishes
 * while HTTP keeps serving reads (draining: mr_daemon_stopping), then HTTP
 * stops and everything is freed. */
void mr_daemon_stop(mr_daemon *d);

/* ---- for the HTTP handlers (http_handlers.c, http_events.c) ----------- */

mr_store *mr_daemon_store(mr_daemon *d);
const mr_daemon_config *mr_daemon_config_of(const mr_daemon *d);
bool mr_daemon_ready(const mr_daemon *d);
/* A stop has begun: the frames in progress are finishing (new work is
 * refused with 503, reads are served). */
bool mr_daemon_stopping(mr_daemon *d);

/* Validates a job body as a submission does, without storing anything:
 * every problem the job parser finds (server/job_json.c, mr_job_check),
 * then the job memory budget and each asset's resolution (ids to stored
 * files, server-side paths to real paths below an asset root: "..",
 * symlinks out of the roots and absolute paths elsewhere are refused),
 * each asset that does not resolve one more problem. problems (required)
 * receives them, with their JSON pointers; the result is the first one's
 * code: MR_ERR_INVALID, MR_ERR_LIMIT (a cap, the budget, or a document
 * over MR_JOB_MAX_BYTES), MR_ERR_NOT_FOUND (a missing asset), and err
 * holds its message. On success *job_out (may be NULL) is the job with
 * its assets resolved (mr_job_free). */
int mr_daemon_check_job(mr_daemon *d, const char *body, size_t len, mr_job **job_out,
                        mr_job_problems *problems, mr_error *err);
/* mr_daemon_check_job, then stores the job as queued. MR_ERR_CONFLICT
 * for an idempotency key reused with another body; *existing tells an
 * idempotent replay. */
int mr_daemon_submit(mr_daemon *d, const char *body, size_t len, const char *idempotency_key,
                     char id[MR_JOB_ID_LEN + 1], bool *existing, mr_job_problems *problems,
                     mr_error *err);
/* Cancels a queued or running job (a running render stops within one tile).
 * MR_ERR_CONFLICT if it already finished; MR_ERR_NOT_FOUND if unknown. */
int mr_daemon_cancel(mr_daemon *d, const char *id, mr_error *err);
/* Re-queues the unfinished frames (failed ones with their retry counts
 * reset) of a failed or canceled job and returns how many; MR_ERR_CONFLICT
 * for queued, running and succeeded jobs. */
int mr_daemon_retry(mr_daemon *d, const char *id, mr_error *err);
/* Cancels if needed, waits until no worker uses the job, removes it and
 * its frames from disk. */
int mr_daemon_delete(mr_daemon *d, const char *id, mr_error *err);

/* A write failed for want of space (MR_ERR_NO_SPACE; why says which): the
 * queue pauses, the running job stops after its frame and goes back to
 * queued, reads and deletes go on; it resumes by itself once space is
 * back (space_guard.h). */
void mr_daemon_no_space(mr_daemon *d, const char *why);
/* Whether the queue is paused for disk space (why: the first failure). */
bool mr_daemon_disk_full(mr_daemon *d, char *why, size_t size);

/* in with the data directory's own paths made relative to it, for what a
 * client reads ("assets/<sha256>: ...", not the server's absolute paths). */
void mr_daemon_redact(const mr_daemon *d, const char *in, char *out, size_t size);

/* Prometheus text exposition (malloc'ed); NULL when out of memory. */
char *mr_daemon_metrics(mr_daemon *d);

/* Events for one job, as ready-to-send server-sent-event text blocks
 * ("id: 7\nevent: frame\ndata: {...}\n\n"). A subscriber first receives a
 * "state" event with the job's current state, then every event published
 * after it; after the job reaches a terminal state the stream ends. Event
 * ids count the job's frames done, in the order they were: a frame event
 * carries its own number, the others the last frame's before them. */
typedef struct mr_event_sub mr_event_sub;
/* NULL for an unknown job, or when MR_MAX_SUBSCRIBERS (64) streams are
 * already open. A subscriber that lets 1024 events pile up unread has its
 * stream ended. last_event_id >= 0 resumes a stream (the client's
 * Last-Event-ID): the frame events after that id come first, from the
 * store (at most about 1000; with more the stream ends after them and the
 * client resumes again from the last), then the state. */
mr_event_sub *mr_events_subscribe(mr_daemon *d, const char *job_id, int64_t last_event_id);
/* Copies the next pending event into buf (NUL-terminated; a block that does
 * not fit is truncated) and returns its length; 0 when none is pending; -1
 * when the stream has ended (and nothing is pending). Never blocks. */
int mr_events_next(mr_event_sub *sub, char *buf, size_t size);
/* Calls fn(user) once whenever an event becomes pending for this subscriber
 * (from the publishing thread; fn must not block): the HTTP layer uses it
 * to resume a suspended connection. */
void mr_events_set_notify(mr_event_sub *sub, void (*fn)(void *user), void *user);
/* After it returns the notify function is never called again and no call of
 * it is in progress (publishers call it under the lock this takes). */
void mr_events_unsubscribe(mr_event_sub *sub);

#endif
