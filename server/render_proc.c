/*
 * render_proc.c - the daemon's side of its render worker processes
 * (render_proc.h): start one, hold one job's conversation with it, watch
 * it, and say how it died when it does.
 */
#define _GNU_SOURCE
#include "render_proc.h"

#include <errno.h>
#include <poll.h>
#include <pthread.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

#include "child.h"
#include "render_msg.h"

#define POLL_MS 50
/* A fresh worker has this long to say hello (a sanitizer build starts
 * slowly, and the Embree device starts its threads). */
#define HELLO_TIMEOUT_S 60.0
/* After its channel closes, a worker has this long to exit on its own. */
#define EXIT_GRACE_S 5.0
/* The largest message a worker may send: an uncompressed EXR of the
 * largest film with every pass, and then some. */
#define MAX_MESSAGE ((size_t)4 << 30)
/* Deaths of a worker between two frames (neither preparing the job nor in
 * a frame: an outside kill) tolerated in one job before it fails. */
#define MAX_DEATHS_BETWEEN_FRAMES 2

struct mr_render_proc {
    mr_render_proc_config cfg;
    pthread_mutex_t lock; /* pid and the cache figures, read by other threads */
    pid_t pid;            /* 0: no worker */
    int fd;
    mr_cache_stats retired; /* summed counters of workers that ended */
    mr_cache_stats current; /* the live worker's, as of its last job */
};

size_t mr_render_proc_memory_limit(size_t job_memory, size_t cache_bytes)
{
    return job_memory + cache_bytes + ((size_t)1 << 30);
}

/* Ends the worker: killed, or (graceful) told by closing its channel and
 * given EXIT_GRACE_S. Returns its wait status. Its cache counters retire. */
static int end_worker(mr_render_proc *p, bool graceful)
{
    if (!p->pid)
        return 0;
    if (!graceful)
        kill(p->pid, SIGKILL);
    close(p->fd);
    p->fd = -1;
    if (graceful) {
        double until = mr_now() + EXIT_GRACE_S;
        while (mr_now() < until && kill(p->pid, 0) == 0 && mr_child_memory(p->pid, false) > 0) {
            struct timespec ts = {0, 20 * 1000000L};
            nanosleep(&ts, NULL);
        }
        kill(p->pid, SIGKILL); /* a zombie ignores it; a worker that hangs does not */
    }
    int status = mr_child_reap(p->pid);
    pthread_mutex_lock(&p->lock);
    p->pid = 0;
    p->retired.hits += p->current.hits;
    p->retired.misses += p->current.misses;
    p->retired.evictions += p->current.evictions;
    p->retired.saved_s += p->current.saved_s;
    memset(&p->current, 0, sizeof p->current);
    pthread_mutex_unlock(&p->lock);
    return status;
}

static int start_worker(mr_render_proc *p, mr_error *err)
{
    const mr_render_proc_config *c = &p->cfg;
    char threads[24], cache[32], job_mem[32], imp_mem[32], imp_time[48];
    snprintf(threads, sizeof threads, "%u", c->threads);
    snprintf(cache, sizeof cache, "%zu", c->cache_bytes);
    snprintf(job_mem, sizeof job_mem, "%zu", c->job_memory);
    snprintf(imp_mem, sizeof imp_mem, "%zu", c->import_memory);
    snprintf(imp_time, sizeof imp_time, "%a", c->import_timeout_s);
    char *fixed[] = {"microrayd", "render-worker", "--threads", threads, "--cache-bytes", cache,
                     "--data", (char *)c->data_dir, "--job-memory", job_mem, "--import-memory",
                     imp_mem, "--import-timeout", imp_time, "--import-exe", (char *)c->exe};
    size_t nf = sizeof fixed / sizeof *fixed;
    char **argv = calloc(nf + 2 * c->root_count + 1, sizeof *argv);
    if (!argv)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    memcpy(argv, fixed, sizeof fixed);
    for (size_t i = 0; i < c->root_count; i++) {
        argv[nf + 2 * i] = "--asset-root";
        argv[nf + 2 * i + 1] = (char *)c->asset_roots[i];
    }
    int sv[2];
    if (socketpair(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0, sv) != 0) {
        free(argv);
        return mr_error_set(err, MR_ERR_IO, "cannot start a render worker: socketpair: %s",
                            strerror(errno));
    }
    mr_child_limits lim = {.nice = c->nice};
    pid_t pid = mr_child_spawn(c->exe, argv, sv[1], &lim, NULL, NULL);
    int spawn_errno = errno;
    free(argv);
    close(sv[1]);
    if (pid < 0) {
        close(sv[0]);
        return mr_error_set(err, MR_ERR_IO, "cannot start a render worker: fork: %s",
                            strerror(spawn_errno));
    }
    pthread_mutex_lock(&p->lock);
    p->pid = pid;
    p->fd = sv[0];
    pthread_mutex_unlock(&p->lock);
    struct pollfd pf = {.fd = p->fd, .events = POLLIN};
    int n;
    while ((n = poll(&pf, 1, (int)(HELLO_TIMEOUT_S * 1000))) < 0 && errno == EINTR)
        ;
    mr_msg m;
    mr_error e = {0};
    if (n <= 0 || mr_msg_recv(p->fd, 64, &m, &e) < 0) {
        int status = end_worker(p, false);
        char how[64];
        mr_child_describe_exit(status, how, sizeof how);
        return mr_error_set(err, MR_ERR_CRASHED, "cannot start a render worker (%s): %s", c->exe,
                            n == 0 ? "it did not answer within a minute" : how);
    }
    bool ok = m.type == MR_MSG_HELLO && m.index == MR_RENDER_PROTOCOL;
    mr_msg_free(&m);
    if (!ok) {
        end_worker(p, false);
        return mr_error_set(err, MR_ERR_CRASHED, "cannot start a render worker: %s speaks "
                            "another protocol (not the daemon's own binary?)", c->exe);
    }
    return MR_OK;
}

int mr_render_proc_new(const mr_render_proc_config *cfg, mr_render_proc **out, mr_error *err)
{
    *out = NULL;
    mr_render_proc *p = calloc(1, sizeof *p);
    if (!p)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    p->cfg = *cfg;
    p->fd = -1;
    pthread_mutex_init(&p->lock, NULL);
    *out = p;
    return MR_OK;
}

/* Whether the idle worker is gone (killed while it waited for a job: the
 * kernel's OOM killer picks a big idle worker too). An idle worker sends
 * nothing, so its channel readable, hung up or broken means it is gone. */
static bool idle_worker_gone(const mr_render_proc *p)
{
    struct pollfd pf = {.fd = p->fd, .events = POLLIN};
    int n;
    while ((n = poll(&pf, 1, 0)) < 0 && errno == EINTR)
        ;
    return n != 0;
}

int mr_render_proc_start(mr_render_proc *p, mr_error *err)
{
    if (p->pid && idle_worker_gone(p))
        end_worker(p, false); /* reaped; the job goes to a new worker, not to the dead one */
    return p->pid ? MR_OK : start_worker(p, err);
}

void mr_render_proc_free(mr_render_proc *p)
{
    if (!p)
        return;
    end_worker(p, true);
    pthread_mutex_destroy(&p->lock);
    free(p);
}

void mr_render_proc_cache_stats(mr_render_proc *p, mr_cache_stats *out)
{
    pthread_mutex_lock(&p->lock);
    *out = p->current;
    out->hits += p->retired.hits;
    out->misses += p->retired.misses;
    out->evictions += p->retired.evictions;
    out->saved_s += p->retired.saved_s;
    pthread_mutex_unlock(&p->lock);
}

int mr_render_proc_pid(mr_render_proc *p)
{
    pthread_mutex_lock(&p->lock);
    int pid = p->pid;
    pthread_mutex_unlock(&p->lock);
    return pid;
}

/* Where the worker is in the job: what its death means. */
typedef enum phase { PREPARING, IN_FRAME, BETWEEN } phase;

typedef enum wait_result { GOT_MESSAGE, CANCELLED, STOPPED, DIED, TOO_BIG, TOO_LONG } wait_result;

/* Waits for the worker's next message, watching the session's cancel and
 * stop, the worker's memory and the deadline (mr_now(); 0: none). */
static wait_result wait_message(mr_render_proc *p, const mr_render_session *s, bool let_finish,
                                double deadline, mr_msg *m, mr_error *err)
{
    for (;;) {
        if (deadline > 0 && mr_now() > deadline)
            return TOO_LONG;
        if (s->cancelled && s->cancelled(s->user))
            return CANCELLED;
        /* a frame in progress finishes (and a worker told to stop ends the
         * job on its own); a job being prepared (an import, a bake) stops
         * at once and is prepared again later */
        if (!let_finish && s->stop_requested && s->stop_requested(s->user))
            return STOPPED;
        if (p->cfg.memory_limit && mr_child_memory(p->pid, true) > p->cfg.memory_limit)
            return TOO_BIG;
        struct pollfd pf = {.fd = p->fd, .events = POLLIN};
        int n = poll(&pf, 1, POLL_MS);
        if (n < 0 && errno != EINTR)
            return DIED;
        if (n > 0)
            return mr_msg_recv(p->fd, MAX_MESSAGE, m, err) == MR_OK ? GOT_MESSAGE : DIED;
    }
}

/* What preparing a job is, for messages. */
#define PREPARING_WHAT "importing assets, deriving data or building the scene"

/* The worker is gone (or broken): kill, reap and say how it ended. */
static int worker_died(mr_render_proc *p, wait_result w, phase ph, long frame, mr_error *err)
{
    int status = end_worker(p, false);
    char where[160];
    if (ph == IN_FRAME)
        snprintf(where, sizeof where, "while rendering frame %ld", frame);
    else if (ph == PREPARING)
        snprintf(where, sizeof where, "while preparing the job (" PREPARING_WHAT ")");
    else
        snprintf(where, sizeof where, "between frames");
    if (w == TOO_LONG) {
        if (ph == IN_FRAME)
            return mr_error_set(err, MR_ERR_LIMIT, "frame %ld took longer than %g s (the daemon's "
                                "--frame-timeout)", frame, p->cfg.frame_timeout_s);
        return mr_error_set(err, MR_ERR_LIMIT, "preparing the job (" PREPARING_WHAT ") took "
                            "longer than %g s (the daemon's --frame-timeout)",
                            p->cfg.frame_timeout_s);
    }
    if (w == TOO_BIG) {
        char limit[MR_BYTES_TEXT];
        mr_format_bytes(p->cfg.memory_limit, limit, sizeof limit);
        return mr_error_set(err, MR_ERR_LIMIT, "the render worker used more than %s of memory %s "
                            "(the daemon's --worker-memory-mb)", limit, where);
    }
    char how[64];
    mr_child_describe_exit(status, how, sizeof how);
    if (WIFSIGNALED(status))
        return mr_error_set(err, MR_ERR_CRASHED, "the render worker was %s%s %s", how,
                            WTERMSIG(status) == SIGKILL ? " (out of memory?)" : "", where);
    return mr_error_set(err, MR_ERR_CRASHED, "the render worker ended unexpectedly (%s) %s", how,
                        where);
}

static int send_job(mr_render_proc *p, const mr_render_session *s, mr_error *err)
{
    size_t paths_len = 0;
    for (size_t i = 0; i < s->path_count; i++)
        paths_len += strlen(s->paths[i]) + 1;
    char *paths = malloc(paths_len ? paths_len : 1);
    if (!paths)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    char *w = paths;
    for (size_t i = 0; i < s->path_count; i++) {
        size_t n = strlen(s->paths[i]) + 1;
        memcpy(w, s->paths[i], n);
        w += n;
    }
    mr_msg m = {.type = MR_MSG_JOB,
                .len = {strlen(s->job_id), s->job_json_len, paths_len, s->frame_count},
                .part = {(const uint8_t *)s->job_id, (const uint8_t *)s->job_json,
                         (const uint8_t *)paths, s->wanted}};
    int rc = mr_msg_send(p->fd, &m, err);
    free(paths);
    return rc;
}

static bool any_wanted(const mr_render_session *s)
{
    for (size_t i = 0; i < s->frame_count; i++)
        if (s->wanted[i])
            return true;
    return false;
}

static int reply(mr_render_proc *p, uint32_t type, int code, uint32_t flags, const char *msg,
                 mr_error *err)
{
    mr_msg m = {.type = type, .code = code, .flags = flags,
                .len = {msg ? strlen(msg) : 0}, .part = {(const uint8_t *)msg}};
    return mr_msg_send(p->fd, &m, err);
}

int mr_render_proc_run(mr_render_proc *p, const mr_render_session *s, mr_error *err)
{
    int deaths_between = 0;
    for (;;) {
        int rc = mr_render_proc_start(p, err);
        if (rc < 0)
            return rc;
        if (send_job(p, s, err) < 0)
            return worker_died(p, DIED, PREPARING, -1, err);
        phase ph = PREPARING;
        bool stop_sent = false;
        /* the deadline of the preparation, then of each frame */
        double limit = p->cfg.frame_timeout_s, deadline = limit > 0 ? mr_now() + limit : 0;
        long frame = -1;
        uint32_t type = 0, index = 0; /* of the message in hand */
        wait_result w;
        mr_msg m;
        mr_error e = {0};
        while ((w = wait_message(p, s, ph == IN_FRAME || stop_sent, deadline, &m, &e)) == GOT_MESSAGE) {
            bool valid = m.index < s->frame_count;
            type = m.type;
            index = m.index;
            switch (m.type) {
            case MR_MSG_STARTED:
                if (!valid)
                    goto protocol;
                ph = IN_FRAME;
                frame = m.index;
                deadline = limit > 0 ? mr_now() + limit : 0;
                if (s->frame_started)
                    s->frame_started(s->user, m.index);
                break;
            case MR_MSG_FRAME:
            case MR_MSG_FAILED: {
                if (!valid || ph != IN_FRAME || (long)m.index != frame)
                    goto protocol;
                mr_error fe = {0};
                int frc;
                if (m.type == MR_MSG_FRAME) {
                    frc = s->frame_done(s->user, m.index, (const char *)m.part[0], m.part[1],
                                        m.len[1], &fe);
                } else {
                    frc = m.code < 0 ? m.code : MR_ERR_INVALID;
                    mr_error_set(&fe, frc, "%s", (const char *)m.part[0]);
                }
                uint32_t flags = 0;
                if (frc == MR_OK) {
                    s->wanted[m.index] = 0;
                } else if (frc != MR_ERR_CANCELLED) {
                    mr_frame_decision d = s->frame_failed(s->user, m.index, &fe);
                    if (d == MR_FRAME_SKIP)
                        s->wanted[m.index] = 0;
                    flags = (uint32_t)d;
                }
                if (s->stop_requested && s->stop_requested(s->user)) {
                    flags |= MR_MSG_STOP;
                    stop_sent = true;
                }
                ph = BETWEEN;
                deadline = 0;
                mr_msg_free(&m);
                if (reply(p, type == MR_MSG_FRAME ? MR_MSG_ACK : MR_MSG_DECISION, frc, flags,
                          frc < 0 ? fe.msg : NULL, &e) < 0) {
                    w = DIED;
                    goto dead;
                }
                continue;
            }
            case MR_MSG_END:
                if (m.len[1] == sizeof(mr_cache_stats)) {
                    pthread_mutex_lock(&p->lock);
                    memcpy(&p->current, m.part[1], sizeof p->current);
                    pthread_mutex_unlock(&p->lock);
                }
                rc = m.code;
                if (rc < 0)
                    mr_error_set(err, rc, "%s", (const char *)m.part[0]);
                mr_msg_free(&m);
                return rc;
            default:
                goto protocol;
            }
            mr_msg_free(&m);
        }
    dead:
        if (w == CANCELLED || w == STOPPED) {
            end_worker(p, false);
            return mr_error_set(err, MR_ERR_CANCELLED, "%s", w == CANCELLED ? "cancelled" : "stopped");
        }
        rc = worker_died(p, w, ph, frame, err);
        if (ph == PREPARING)
            return rc;
        if (ph == BETWEEN && ++deaths_between > MAX_DEATHS_BETWEEN_FRAMES)
            return rc;
        if (ph == IN_FRAME) {
            mr_frame_decision d = s->frame_failed(s->user, (size_t)frame, err);
            if (d == MR_FRAME_ABORT)
                return rc;
            if (d == MR_FRAME_SKIP)
                s->wanted[frame] = 0;
        }
        if (s->stop_requested && s->stop_requested(s->user))
            return mr_error_set(err, MR_ERR_CANCELLED, "stopped");
        if (!any_wanted(s))
            return MR_OK;
        continue; /* the rest of the job in a new worker */
    protocol:
        mr_msg_free(&m);
        end_worker(p, false);
        return mr_error_set(err, MR_ERR_CRASHED, "the render worker sent a message out of turn "
                            "(type %u, frame %u)", type, index);
    }
}
