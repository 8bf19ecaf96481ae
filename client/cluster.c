/*
 * cluster.c - `microray cluster submit|status|wait` on Slurm (cluster.h).
 */
#define _GNU_SOURCE
#include "cluster.h"
#include "usage.h"

#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <poll.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "client.h"
#include "progress.h"

#define STATE_VERSION 1
#define MAX_TASKS 100000
#define OUTPUT_CAP ((size_t)4 << 20) /* of a scheduler command */

/* ---- running the scheduler's commands -------------------------------------- */

/* Runs argv (searched in PATH); its stdout into *out and its stderr into
 * *errout (malloc'ed, NUL-terminated, at most OUTPUT_CAP each; either may
 * be NULL). Returns its exit status, or -1 (errno set) if it did not run. */
static int run(char *const argv[], char **out, char **errout)
{
    int po[2], pe[2];
    if (pipe2(po, O_CLOEXEC) != 0)
        return -1;
    if (pipe2(pe, O_CLOEXEC) != 0) {
        close(po[0]);
        close(po[1]);
        return -1;
    }
    fflush(NULL);
    pid_t pid = fork();
    if (pid < 0) {
        int e = errno;
        close(po[0]), close(po[1]), close(pe[0]), close(pe[1]);
        errno = e;
        return -1;
    }
    if (pid == 0) {
        dup2(po[1], STDOUT_FILENO);
        dup2(pe[1], STDERR_FILENO);
        execvp(argv[0], argv);
        fprintf(stderr, "%s: %s\n", argv[0], strerror(errno));
        _exit(127);
    }
    close(po[1]);
    close(pe[1]);
    char *buf[2] = {calloc(1, 1), calloc(1, 1)};
    size_t len[2] = {0, 0};
    struct pollfd pf[2] = {{.fd = po[0], .events = POLLIN}, {.fd = pe[0], .events = POLLIN}};
    int open_fds = 2;
    while (open_fds > 0) {
        if (poll(pf, 2, -1) < 0) {
            if (errno == EINTR)
                continue;
            break;
        }
        for (int k = 0; k < 2; k++) {
            if (pf[k].fd < 0 || !(pf[k].revents & (POLLIN | POLLHUP | POLLERR)))
                continue;
            char chunk[4096];
            ssize_t n = read(pf[k].fd, chunk, sizeof chunk);
            if (n < 0 && errno == EINTR)
                continue;
            if (n <= 0) {
                close(pf[k].fd);
                pf[k].fd = -1;
                open_fds--;
                continue;
            }
            if (buf[k] && len[k] + (size_t)n <= OUTPUT_CAP) {
                char *grown = realloc(buf[k], len[k] + (size_t)n + 1);
                if (grown) {
                    memcpy(grown + len[k], chunk, (size_t)n);
                    len[k] += (size_t)n;
                    grown[len[k]] = '\0';
                }
                buf[k] = grown;
            }
        }
    }
    int status = 0;
    while (waitpid(pid, &status, 0) < 0 && errno == EINTR)
        ;
    if (out)
        *out = buf[0];
    else
        free(buf[0]);
    if (errout)
        *errout = buf[1];
    else
        free(buf[1]);
    return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + (WIFSIGNALED(status) ? WTERMSIG(status) : 0);
}

/* Runs a command that must succeed; its stdout in *out (may be NULL). */
static int run_ok(char *const argv[], char **out, mrc_error *err)
{
    char *o = NULL, *e = NULL;
    int st = run(argv, &o, &e);
    int rc = 0;
    if (st < 0) {
        rc = mrc_fail(err, MRC_EXIT_SERVER, "cannot run %s: %s", argv[0], strerror(errno));
    } else if (st != 0) {
        char msg[600];
        mrc_sanitize(msg, sizeof msg, e && e[0] ? e : o ? o : "");
        msg[strcspn(msg, "\n")] = '\0';
        rc = mrc_fail(err, MRC_EXIT_SERVER, "%s failed (exit %d): %s", argv[0], st,
                      msg[0] ? msg : "no message");
    }
    if (rc == 0 && out)
        *out = o;
    else
        free(o);
    free(e);
    return rc;
}

/* ---- the state file ------------------------------------------------------- */

typedef struct cluster_state {
    char dir[PATH_MAX];       /* the output folder, absolute */
    char job[PATH_MAX];       /* the job file, absolute */
    char microrayd[PATH_MAX]; /* the renderer the tasks run */
    long frames, chunk, tasks, max_retries;
    char prepare[32], array[32], merge[32]; /* Slurm job ids */
    long merges;              /* merge jobs submitted so far */
    int *requeues;            /* per task */
} cluster_state;

static void state_free(cluster_state *s)
{
    free(s->requeues);
    s->requeues = NULL;
}

static int write_file_atomic(const char *path, const char *text, mrc_error *err)
{
    char tmp[PATH_MAX + 32];
    snprintf(tmp, sizeof tmp, "%s.tmp.%d", path, (int)getpid());
    FILE *f = fopen(tmp, "w");
    if (!f)
        return mrc_fail(err, MRC_EXIT_LOCAL, "%s: %s", tmp, strerror(errno));
    bool ok = fputs(text, f) >= 0 && fflush(f) == 0 && fsync(fileno(f)) == 0;
    ok &= fclose(f) == 0;
    if (!ok || rename(tmp, path) != 0) {
        int e = errno;
        unlink(tmp);
        return mrc_fail(err, MRC_EXIT_LOCAL, "%s: %s", path, strerror(e));
    }
    return 0;
}

static int state_path(const char *dir, char *out, size_t size)
{
    return snprintf(out, size, "%s/cluster/state.json", dir) < (int)size ? 0 : -1;
}

static int state_save(const cluster_state *s, mrc_error *err)
{
    cJSON *o = cJSON_CreateObject();
    cJSON_AddNumberToObject(o, "version", STATE_VERSION);
    cJSON_AddStringToObject(o, "scheduler", "slurm");
    cJSON_AddStringToObject(o, "job", s->job);
    cJSON_AddStringToObject(o, "microrayd", s->microrayd);
    cJSON_AddNumberToObject(o, "frames", (double)s->frames);
    cJSON_AddNumberToObject(o, "chunk", (double)s->chunk);
    cJSON_AddNumberToObject(o, "tasks", (double)s->tasks);
    cJSON_AddNumberToObject(o, "max_retries", (double)s->max_retries);
    cJSON_AddStringToObject(o, "prepare", s->prepare);
    cJSON_AddStringToObject(o, "array", s->array);
    cJSON_AddStringToObject(o, "merge", s->merge);
    cJSON_AddNumberToObject(o, "merges", (double)s->merges);
    cJSON *rq = cJSON_AddArrayToObject(o, "requeues");
    for (long t = 0; t < s->tasks; t++)
        cJSON_AddItemToArray(rq, cJSON_CreateNumber(s->requeues[t]));
    char *text = cJSON_Print(o);
    cJSON_Delete(o);
    if (!text)
        return mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
    char path[PATH_MAX + 32];
    state_path(s->dir, path, sizeof path);
    int rc = write_file_atomic(path, text, err);
    free(text);
    return rc;
}

static int copy_str(char *dst, size_t size, const cJSON *o, const char *key)
{
    const char *v = mrc_json_str(o, key);
    if (!v || strlen(v) >= size)
        return -1;
    snprintf(dst, size, "%s", v);
    return 0;
}

static int state_load(const char *dir, cluster_state *s, mrc_error *err)
{
    memset(s, 0, sizeof *s);
    char path[PATH_MAX + 32], *text = NULL;
    size_t len;
    if (!realpath(dir, s->dir))
        return mrc_fail(err, MRC_EXIT_LOCAL, "%s: %s", dir, strerror(errno));
    state_path(s->dir, path, sizeof path);
    int rc = mrc_read_file(path, 1 << 22, &text, &len, err);
    if (rc)
        return rc;
    cJSON *o = cJSON_Parse(text);
    free(text);
    const cJSON *rq = cJSON_GetObjectItemCaseSensitive(o, "requeues");
    s->frames = (long)mrc_json_int(o, "frames", -1, 1, 1 << 30);
    s->chunk = (long)mrc_json_int(o, "chunk", -1, 1, 1 << 30);
    s->tasks = (long)mrc_json_int(o, "tasks", -1, 1, MAX_TASKS);
    s->max_retries = (long)mrc_json_int(o, "max_retries", 0, 0, 1000);
    s->merges = (long)mrc_json_int(o, "merges", 1, 0, 1 << 30);
    bool ok = o && mrc_json_int(o, "version", 0, 0, 1000) == STATE_VERSION && s->frames > 0 &&
              s->chunk > 0 && s->tasks > 0 && cJSON_GetArraySize(rq) == s->tasks &&
              copy_str(s->job, sizeof s->job, o, "job") == 0 &&
              copy_str(s->microrayd, sizeof s->microrayd, o, "microrayd") == 0 &&
              copy_str(s->prepare, sizeof s->prepare, o, "prepare") == 0 &&
              copy_str(s->array, sizeof s->array, o, "array") == 0 &&
              copy_str(s->merge, sizeof s->merge, o, "merge") == 0;
    if (ok && !(s->requeues = calloc((size_t)s->tasks, sizeof *s->requeues)))
        ok = false;
    for (long t = 0; ok && t < s->tasks; t++) {
        const cJSON *it = cJSON_GetArrayItem(rq, (int)t);
        s->requeues[t] = cJSON_IsNumber(it) && it->valuedouble >= 0 && it->valuedouble <= 1000
                             ? (int)it->valuedouble
                             : 0;
    }
    cJSON_Delete(o);
    if (!ok) {
        state_free(s);
        return mrc_fail(err, MRC_EXIT_LOCAL, "%s: not a microray cluster state file (made by "
                        "`microray cluster submit`)", path);
    }
    return 0;
}

/* ---- submit --------------------------------------------------------------- */

/* s with every ' made safe inside a single-quoted shell word. */
static void shell_quote(char *dst, size_t size, const char *s)
{
    size_t o = 0;
    if (o + 1 < size)
        dst[o++] = '\'';
    for (; *s && o + 5 < size; s++) {
        if (*s == '\'') {
            memcpy(dst + o, "'\\''", 4);
            o += 4;
        } else {
            dst[o++] = *s;
        }
    }
    if (o + 1 < size)
        dst[o++] = '\'';
    dst[o] = '\0';
}

/* The microrayd the tasks run: --microrayd, else the one beside this
 * program, else the first in PATH; absolute, so compute nodes find it on
 * the shared file system. */
static int find_microrayd(const char *given, char *out, size_t size, mrc_error *err)
{
    char candidate[PATH_MAX];
    if (given) {
        snprintf(candidate, sizeof candidate, "%s", given);
    } else {
        char self[PATH_MAX];
        ssize_t n = readlink("/proc/self/exe", self, sizeof self - 1);
        candidate[0] = '\0';
        if (n > 0) {
            self[n] = '\0';
            char *slash = strrchr(self, '/');
            if (slash) {
                *slash = '\0';
                snprintf(candidate, sizeof candidate, "%.*s/microrayd", PATH_MAX - 11, self);
            }
        }
        if (!candidate[0] || access(candidate, X_OK) != 0) {
            const char *path = getenv("PATH");
            candidate[0] = '\0';
            for (const char *p = path; p && *p;) {
                size_t n2 = strcspn(p, ":");
                char c[PATH_MAX];
                snprintf(c, sizeof c, "%.*s/microrayd", (int)n2, p);
                if (n2 && access(c, X_OK) == 0) {
                    snprintf(candidate, sizeof candidate, "%s", c);
                    break;
                }
                p += n2 + (p[n2] == ':');
            }
        }
    }
    if (!candidate[0] || access(candidate, X_OK) != 0 || !realpath(candidate, out) ||
        strlen(out) >= size)
        return mrc_fail(err, MRC_EXIT_USAGE, "cannot find microrayd%s%s (give --microrayd PATH)",
                        given ? " at " : "", given ? given : "");
    return 0;
}

/* DIR/cluster/NAME, executable: the shell script body (NULL: out of memory). */
static int write_script(const char *dir, const char *name, char *body, mrc_error *err)
{
    char path[PATH_MAX + 64], *text = NULL;
    snprintf(path, sizeof path, "%s/cluster/%s", dir, name);
    int rc = 0;
    if (!body || asprintf(&text,
                          "#!/bin/bash\n"
                          "# written by `microray cluster submit` (client/cluster.c); see docs/scale.md\n"
                          "set -euo pipefail\n%s",
                          body) < 0)
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
    if (rc == 0)
        rc = write_file_atomic(path, text, err);
    if (rc == 0 && chmod(path, 0755) != 0)
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "%s: %s", path, strerror(errno));
    free(text);
    free(body);
    return rc;
}

/* asprintf, NULL when out of memory. */
static char *format(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
static char *format(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    char *s = NULL;
    if (vasprintf(&s, fmt, ap) < 0)
        s = NULL;
    va_end(ap);
    return s;
}

/* sbatch ... script; the job id it printed in id. */
static int sbatch(char *const *args, char *id, size_t size, mrc_error *err)
{
    char *out = NULL;
    int rc = run_ok(args, &out, err);
    if (rc == 0) {
        size_t n = strspn(out, "0123456789");
        if (n == 0 || n >= size)
            rc = mrc_fail(err, MRC_EXIT_SERVER, "sbatch printed no job id: %.200s", out);
        else
            snprintf(id, size, "%.*s", (int)n, out);
    }
    free(out);
    return rc;
}

/* The merge job: after every task of the array has ended (whatever way:
 * a task requeued later holds the new merge back again). */
static int submit_merge(cluster_state *s, const char *partition, const char *time_limit,
                        mrc_error *err)
{
    char dep[64], log[PATH_MAX + 64], script[PATH_MAX + 64];
    snprintf(dep, sizeof dep, "--dependency=afterany:%s", s->array);
    snprintf(log, sizeof log, "--output=%s/cluster/logs/merge-%%j.out", s->dir);
    snprintf(script, sizeof script, "%s/cluster/merge.sh", s->dir);
    char part[128], lim[128];
    char *args[12] = {"sbatch", "--parsable", "--job-name=microray-merge", dep, log};
    int n = 5;
    if (partition) {
        snprintf(part, sizeof part, "--partition=%s", partition);
        args[n++] = part;
    }
    if (time_limit) {
        snprintf(lim, sizeof lim, "--time=%s", time_limit);
        args[n++] = lim;
    }
    args[n++] = script;
    args[n] = NULL;
    int rc = sbatch(args, s->merge, sizeof s->merge, err);
    if (rc == 0)
        s->merges++;
    return rc;
}

typedef struct submit_opts {
    const char *job, *out, *partition, *time_limit, *microrayd;
    long chunk, threads;
    bool json; /* the status as JSON instead of the array's id */
} submit_opts;

static int cluster_submit(const submit_opts *o, bool quiet, mrc_error *err)
{
    cluster_state s = {0};
    char *plan = NULL;
    int rc = find_microrayd(o->microrayd, s.microrayd, sizeof s.microrayd, err);
    if (rc)
        return rc;
    if (!realpath(o->job, s.job))
        return mrc_fail(err, MRC_EXIT_LOCAL, "%s: %s", o->job, strerror(errno));
    /* the job validated as the renderer will read it, and its size */
    char *plan_args[] = {s.microrayd, "plan", s.job, NULL};
    if ((rc = run_ok(plan_args, &plan, err)) != 0) {
        /* the renderer's own message says what is wrong with the job */
        err->code = MRC_EXIT_REJECTED;
        return -MRC_EXIT_REJECTED;
    }
    cJSON *p = cJSON_Parse(plan);
    free(plan);
    s.frames = (long)mrc_json_int(p, "frames", -1, 1, 1 << 30);
    s.max_retries = (long)mrc_json_int(p, "max_retries", 2, 0, 1000);
    cJSON_Delete(p);
    if (s.frames < 1)
        return mrc_fail(err, MRC_EXIT_SERVER, "microrayd plan gave no frame count");
    s.chunk = o->chunk;
    s.tasks = (s.frames + s.chunk - 1) / s.chunk;
    if (s.tasks > MAX_TASKS)
        return mrc_fail(err, MRC_EXIT_USAGE, "--chunk %ld makes %ld tasks (at most %d)", s.chunk,
                        s.tasks, MAX_TASKS);
    if ((rc = mrc_mkdirs(o->out, err)) != 0)
        return rc;
    if (!realpath(o->out, s.dir))
        return mrc_fail(err, MRC_EXIT_LOCAL, "%s: %s", o->out, strerror(errno));
    char logs[PATH_MAX + 32];
    snprintf(logs, sizeof logs, "%s/cluster/logs", s.dir);
    if ((rc = mrc_mkdirs(logs, err)) != 0)
        return rc;
    if (!(s.requeues = calloc((size_t)s.tasks, sizeof *s.requeues)))
        return mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");

    char qexe[PATH_MAX * 2], qjob[PATH_MAX * 2], qdir[PATH_MAX * 2], threads[32] = "";
    shell_quote(qexe, sizeof qexe, s.microrayd);
    shell_quote(qjob, sizeof qjob, s.job);
    shell_quote(qdir, sizeof qdir, s.dir);
    if (o->threads > 0)
        snprintf(threads, sizeof threads, " --threads %ld", o->threads);
    /* 1. assets imported and data derived once, into the shared cache */
    char *body = format("%s render %s --out %s --cache %s/cache --prepare --quiet%s > "
                        "%s/cluster/prepare.json.tmp\n"
                        "mv %s/cluster/prepare.json.tmp %s/cluster/prepare.json\n",
                        qexe, qjob, qdir, qdir, threads, qdir, qdir, qdir);
    if ((rc = write_script(s.dir, "prepare.sh", body, err)) != 0)
        goto done;
    /* 2. task k: its chunk of frames, reading the cache */
    body = format("task=${SLURM_ARRAY_TASK_ID:?run as a task of the array}\n"
                  "first=$(( task * %ld ))\n"
                  "last=$(( first + %ld - 1 ))\n"
                  "if [ \"$last\" -ge %ld ]; then last=%ld; fi\n"
                  "exec %s render %s --out %s --cache %s/cache --frames \"$first-$last\" --quiet%s\n",
                  s.chunk, s.chunk, s.frames, s.frames - 1, qexe, qjob, qdir, qdir, threads);
    if ((rc = write_script(s.dir, "task.sh", body, err)) != 0)
        goto done;
    /* 3. the statistics of every part in one stats.json */
    body = format("exec %s stats-merge %s %s\n", qexe, qdir, qjob);
    if ((rc = write_script(s.dir, "merge.sh", body, err)) != 0)
        goto done;

    char part[128] = "", lim[128] = "", log[PATH_MAX + 64], script[PATH_MAX + 64], dep[64],
         array[64];
    if (o->partition)
        snprintf(part, sizeof part, "--partition=%s", o->partition);
    if (o->time_limit)
        snprintf(lim, sizeof lim, "--time=%s", o->time_limit);
    snprintf(log, sizeof log, "--output=%s/cluster/logs/prepare-%%j.out", s.dir);
    snprintf(script, sizeof script, "%s/cluster/prepare.sh", s.dir);
    char *a1[10] = {"sbatch", "--parsable", "--job-name=microray-prepare", log};
    int n = 4;
    if (part[0])
        a1[n++] = part;
    if (lim[0])
        a1[n++] = lim;
    a1[n++] = script;
    a1[n] = NULL;
    if ((rc = sbatch(a1, s.prepare, sizeof s.prepare, err)) != 0)
        goto done;
    snprintf(log, sizeof log, "--output=%s/cluster/logs/task-%%a-%%j.out", s.dir);
    snprintf(script, sizeof script, "%s/cluster/task.sh", s.dir);
    snprintf(dep, sizeof dep, "--dependency=afterok:%s", s.prepare);
    snprintf(array, sizeof array, "--array=0-%ld", s.tasks - 1);
    char *a2[12] = {"sbatch", "--parsable", "--job-name=microray-frames", "--requeue", array, dep, log};
    n = 7;
    if (part[0])
        a2[n++] = part;
    if (lim[0])
        a2[n++] = lim;
    a2[n++] = script;
    a2[n] = NULL;
    if ((rc = sbatch(a2, s.array, sizeof s.array, err)) != 0)
        goto done;
    if ((rc = submit_merge(&s, o->partition, o->time_limit, err)) != 0 ||
        (rc = state_save(&s, err)) != 0)
        goto done;
    if (!o->json)
        printf("%s\n", s.array);
    if (!quiet)
        fprintf(stderr, "submitted %ld frames as %ld task%s of %ld (Slurm jobs: prepare %s, "
                "array %s, merge %s); follow with: microray cluster wait %s\n", s.frames, s.tasks,
                s.tasks == 1 ? "" : "s", s.chunk, s.prepare, s.array, s.merge, s.dir);
done:
    state_free(&s);
    return rc;
}

/* ---- status --------------------------------------------------------------- */

typedef enum task_state { T_QUEUED, T_RUNNING, T_DONE, T_FAILED } task_state;
static const char *const TASK_STATE[] = {"queued", "running", "done", "failed"};

typedef struct snapshot {
    task_state prepare, merge;
    task_state *task;
    char (*how)[64];     /* per failed task: what sacct says, if it can */
    long frames_done, frames_running, frames_queued, frames_failed;
    bool *frame_done;
    const char *state;   /* queued, running, succeeded, failed */
} snapshot;

static void snapshot_free(snapshot *sn)
{
    free(sn->task);
    free(sn->how);
    free(sn->frame_done);
    memset(sn, 0, sizeof *sn);
}

/* squeue's view of job id, finished jobs included while slurmctld still
 * holds them (MinJobAge): one "K STATE" line per array task with -r; an id
 * it no longer knows is simply absent. */
static char *squeue(const char *id)
{
    char *args[] = {"squeue", "-h", "-r", "-t", "all", "-j", (char *)id, "-o", "%K %T", NULL};
    char *out = NULL;
    if (run(args, &out, NULL) != 0) {
        free(out);
        return calloc(1, 1);
    }
    return out;
}

/* A Slurm job state in the daemon's words; T_DONE means "ended well": the
 * files then say whether its frames are there. */
static task_state slurm_state(const char *st)
{
    static const char *const running[] = {"RUNNING", "COMPLETING", "CONFIGURING", "STAGE_OUT",
                                          "SIGNALING", NULL};
    static const char *const ended_badly[] = {"CANCELLED", "FAILED", "TIMEOUT", "NODE_FAIL",
                                              "OUT_OF_MEMORY", "BOOT_FAIL", "DEADLINE",
                                              "PREEMPTED", "REVOKED", "SPECIAL_EXIT", NULL};
    for (const char *const *r = running; *r; r++)
        if (!strcmp(st, *r))
            return T_RUNNING;
    for (const char *const *r = ended_badly; *r; r++)
        if (!strcmp(st, *r))
            return T_FAILED;
    return strcmp(st, "COMPLETED") == 0 ? T_DONE : T_QUEUED; /* PENDING, REQUEUED, ... */
}

/* A job slurmctld has forgotten: how it ended, from sacct where
 * accounting runs ("" where it does not). */
static void sacct_state(const char *id, char *how, size_t size)
{
    char *args[] = {"sacct", "-n", "-P", "-X", "-j", (char *)id, "-o", "State", NULL};
    char *out = NULL;
    how[0] = '\0';
    if (run(args, &out, NULL) == 0 && out)
        mrc_sanitize(how, size, out);
    how[strcspn(how, "\n")] = '\0';
    free(out);
}

static bool file_exists(const char *dir, const char *name)
{
    char path[PATH_MAX + 64];
    snprintf(path, sizeof path, "%s/%s", dir, name);
    struct stat st;
    return stat(path, &st) == 0 && S_ISREG(st.st_mode) && st.st_size > 0;
}

/* stats.json is there and holds every frame. */
static bool merged(const cluster_state *s)
{
    char path[PATH_MAX + 32], *text = NULL;
    size_t len;
    mrc_error e;
    snprintf(path, sizeof path, "%s/stats.json", s->dir);
    if (mrc_read_file(path, (size_t)256 << 20, &text, &len, &e) != 0)
        return false;
    cJSON *o = cJSON_Parse(text);
    free(text);
    bool all = mrc_json_int(o, "frames_done", -1, 0, 1 << 30) == s->frames;
    cJSON_Delete(o);
    return all;
}

static int gather(const cluster_state *s, snapshot *sn, mrc_error *err)
{
    memset(sn, 0, sizeof *sn);
    sn->task = calloc((size_t)s->tasks, sizeof *sn->task);
    sn->how = calloc((size_t)s->tasks, sizeof *sn->how);
    sn->frame_done = calloc((size_t)s->frames, sizeof *sn->frame_done);
    if (!sn->task || !sn->how || !sn->frame_done) {
        snapshot_free(sn);
        return mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
    }
    /* the queue first, then the files: a task that leaves the queue has
     * written its frames before */
    char *q_prep = squeue(s->prepare), *q_array = squeue(s->array), *q_merge = squeue(s->merge);
    bool *known = calloc((size_t)s->tasks, sizeof *known);
    for (char *line = q_array; known && line && *line;) {
        long k;
        char st[32];
        if (sscanf(line, "%ld %31s", &k, st) == 2 && k >= 0 && k < s->tasks) {
            known[k] = true;
            sn->task[k] = slurm_state(st);
            if (sn->task[k] == T_FAILED)
                snprintf(sn->how[k], sizeof sn->how[k], "%s", st);
        }
        line = strchr(line, '\n');
        line = line ? line + 1 : NULL;
    }
    char st[32];
    sn->prepare = sscanf(q_prep, "%*s %31s", st) == 1 ? slurm_state(st) : T_DONE;
    if (sn->prepare == T_DONE && !file_exists(s->dir, "cluster/prepare.json"))
        sn->prepare = T_FAILED;
    sn->merge = sscanf(q_merge, "%*s %31s", st) == 1 ? slurm_state(st) : T_DONE;
    if (sn->merge != T_RUNNING && sn->merge != T_QUEUED)
        sn->merge = merged(s) ? T_DONE : T_FAILED;
    for (long f = 0; f < s->frames; f++) {
        char name[32];
        snprintf(name, sizeof name, "%04ld.exr", f);
        sn->frame_done[f] = file_exists(s->dir, name);
    }
    for (long t = 0; t < s->tasks; t++) {
        long first = t * s->chunk, last = first + s->chunk > s->frames ? s->frames : first + s->chunk;
        bool all = true;
        for (long f = first; f < last; f++)
            all &= sn->frame_done[f];
        /* ended (or forgotten by slurmctld): its frames say how it went */
        if (!known || !known[t] || sn->task[t] == T_DONE) {
            sn->task[t] = all ? T_DONE : T_FAILED;
            if (!all && (!known || !known[t]) && sn->prepare == T_DONE) {
                char id[64];
                snprintf(id, sizeof id, "%s_%ld", s->array, t);
                sacct_state(id, sn->how[t], sizeof sn->how[t]);
            }
        }
        for (long f = first; f < last; f++) {
            if (sn->frame_done[f])
                sn->frames_done++;
            else if (sn->task[t] == T_RUNNING)
                sn->frames_running++;
            else if (sn->task[t] == T_FAILED)
                sn->frames_failed++;
            else
                sn->frames_queued++;
        }
    }
    free(known);
    free(q_prep);
    free(q_array);
    free(q_merge);
    bool exhausted = sn->prepare == T_FAILED;
    for (long t = 0; t < s->tasks; t++)
        exhausted |= sn->task[t] == T_FAILED && s->requeues[t] >= s->max_retries;
    sn->state = exhausted ? "failed"
                : sn->frames_done == s->frames && sn->merge == T_DONE ? "succeeded"
                : sn->frames_done == 0 && sn->frames_running == 0 ? "queued"
                                                                  : "running";
    return 0;
}

static void print_status(const cluster_state *s, const snapshot *sn, bool json)
{
    if (json) {
        cJSON *o = cJSON_CreateObject();
        cJSON_AddStringToObject(o, "state", sn->state);
        cJSON *fr = cJSON_AddObjectToObject(o, "frames");
        cJSON_AddNumberToObject(fr, "total", (double)s->frames);
        cJSON_AddNumberToObject(fr, "done", (double)sn->frames_done);
        cJSON_AddNumberToObject(fr, "running", (double)sn->frames_running);
        cJSON_AddNumberToObject(fr, "queued", (double)sn->frames_queued);
        cJSON_AddNumberToObject(fr, "failed", (double)sn->frames_failed);
        cJSON_AddStringToObject(o, "prepare", TASK_STATE[sn->prepare]);
        cJSON_AddStringToObject(o, "merge", TASK_STATE[sn->merge]);
        cJSON *tasks = cJSON_AddArrayToObject(o, "tasks");
        for (long t = 0; t < s->tasks; t++) {
            cJSON *e = cJSON_CreateObject();
            long first = t * s->chunk;
            long last = first + s->chunk - 1 < s->frames - 1 ? first + s->chunk - 1 : s->frames - 1;
            cJSON_AddNumberToObject(e, "index", (double)t);
            cJSON_AddNumberToObject(e, "first", (double)first);
            cJSON_AddNumberToObject(e, "last", (double)last);
            cJSON_AddStringToObject(e, "state", TASK_STATE[sn->task[t]]);
            cJSON_AddNumberToObject(e, "requeues", s->requeues[t]);
            if (sn->how[t][0])
                cJSON_AddStringToObject(e, "slurm", sn->how[t]);
            cJSON_AddItemToArray(tasks, e);
        }
        cJSON *slurm = cJSON_AddObjectToObject(o, "slurm");
        cJSON_AddStringToObject(slurm, "prepare", s->prepare);
        cJSON_AddStringToObject(slurm, "array", s->array);
        cJSON_AddStringToObject(slurm, "merge", s->merge);
        char *text = cJSON_Print(o);
        if (text)
            puts(text);
        free(text);
        cJSON_Delete(o);
        return;
    }
    printf("state     %s\n", sn->state);
    printf("frames    %ld/%ld done, %ld running, %ld queued, %ld failed\n", sn->frames_done,
           s->frames, sn->frames_running, sn->frames_queued, sn->frames_failed);
    printf("prepare   %s (Slurm job %s)\n", TASK_STATE[sn->prepare], s->prepare);
    printf("tasks     %ld of %ld frames (Slurm array %s)\n", s->tasks, s->chunk, s->array);
    for (long t = 0; t < s->tasks; t++)
        if (sn->task[t] != T_DONE || s->requeues[t])
            printf("  task %-5ld frames %ld-%ld  %s%s%s%s\n", t, t * s->chunk,
                   (t + 1) * s->chunk - 1 < s->frames - 1 ? (t + 1) * s->chunk - 1 : s->frames - 1,
                   TASK_STATE[sn->task[t]], sn->how[t][0] ? " (" : "", sn->how[t],
                   sn->how[t][0] ? ")" : "");
    printf("merge     %s (Slurm job %s)\n", TASK_STATE[sn->merge], s->merge);
}

/* ---- wait ----------------------------------------------------------------- */

static bool stderr_tty(void)
{
    const char *term = getenv("TERM");
    return isatty(STDERR_FILENO) && !(term && strcmp(term, "dumb") == 0);
}

/* Rounds (about a second each) a refused requeue is tried again. */
#define REQUEUE_TRIES 60
/* Seconds a requeued task is given to show up in the queue again: between
 * `scontrol requeue` and its listing as pending, squeue can miss it, and
 * a task neither listed nor done reads as failed, which requeued it a
 * second time (test_slurm saw "2 of 2" on a loaded machine). */
#define REQUEUE_GRACE_S 10.0

static int cluster_wait(cluster_state *s, bool quiet, mrc_error *err)
{
    mrc_progress p;
    mrc_progress_init(&p, stderr, stderr_tty(), quiet);
    /* per task: requeues refused in a row, and when it was last requeued (0: never) */
    struct requeue_tries {
        int refused;
        double at;
    } *tries = calloc((size_t)s->tasks, sizeof *tries);
    if (!tries)
        return mrc_fail(err, MRC_EXIT_LOCAL, "out of memory");
    for (;;) {
        snapshot sn;
        int rc = gather(s, &sn, err);
        if (rc) {
            free(tries);
            return rc;
        }
        mrc_progress_update(&p, (int)sn.frames_done, (int)sn.frames_failed, (int)s->frames,
                            sn.state, false);
        bool requeued = false;
        for (long t = 0; t < s->tasks && strcmp(sn.state, "failed") != 0; t++) {
            if (sn.task[t] != T_FAILED || sn.prepare != T_DONE ||
                (tries[t].at > 0 && mrc_now() - tries[t].at < REQUEUE_GRACE_S))
                continue;
            char id[64];
            snprintf(id, sizeof id, "%s_%ld", s->array, t);
            /* back in the queue, and eligible at once: Slurm holds a
             * requeued job back (two minutes here) unless told otherwise */
            char start[96];
            snprintf(start, sizeof start, "JobId=%s", id);
            char *args[] = {"scontrol", "requeue", id, NULL};
            char *now[] = {"scontrol", "update", start, "StartTime=now", NULL};
            if ((rc = run_ok(args, NULL, err)) != 0) {
                /* a task just killed may still be cleaning up on its node
                 * ("Unexpected message received"): try again next round,
                 * for a while */
                if (++tries[t].refused > REQUEUE_TRIES) {
                    snapshot_free(&sn);
                    free(tries);
                    return rc;
                }
                continue;
            }
            tries[t].refused = 0;
            run_ok(now, NULL, err); /* if it fails, Slurm's own delay applies */
            tries[t].at = mrc_now();
            s->requeues[t]++;
            requeued = true;
            mrc_progress_message(&p, "task %ld (frames %ld-%ld) ended without its frames%s%s%s: "
                                 "requeued (%d of %ld)", t, t * s->chunk,
                                 (t + 1) * s->chunk - 1 < s->frames - 1 ? (t + 1) * s->chunk - 1
                                                                        : s->frames - 1,
                                 sn.how[t][0] ? " (" : "", sn.how[t], sn.how[t][0] ? ")" : "",
                                 s->requeues[t], s->max_retries);
        }
        /* a merge that ran (or would run) before a requeued task is done
         * merged too little: submit it again behind the array */
        bool remerge = requeued || (sn.frames_done == s->frames && sn.merge == T_FAILED);
        if (remerge && strcmp(sn.state, "failed") != 0) {
            if (s->merges > 2 * s->tasks * (s->max_retries + 1) + 2) {
                snapshot_free(&sn);
                free(tries);
                return mrc_fail(err, MRC_EXIT_JOB_FAILED, "the merge failed %ld times (see %s/"
                                "cluster/logs/merge-*.out)", s->merges, s->dir);
            }
            char *args[] = {"scancel", s->merge, NULL};
            run(args, NULL, NULL); /* a merge that already ended: nothing to cancel */
            if ((rc = submit_merge(s, NULL, NULL, err)) != 0) {
                snapshot_free(&sn);
                free(tries);
                return rc;
            }
        }
        if ((requeued || remerge) && (rc = state_save(s, err)) != 0) {
            snapshot_free(&sn);
            free(tries);
            return rc;
        }
        const char *state = sn.state;
        snapshot_free(&sn);
        if (strcmp(state, "succeeded") == 0) {
            mrc_progress_update(&p, (int)s->frames, 0, (int)s->frames, "succeeded", true);
            mrc_progress_finish(&p);
            free(tries);
            return 0;
        }
        if (strcmp(state, "failed") == 0) {
            mrc_progress_finish(&p);
            free(tries);
            return mrc_fail(err, MRC_EXIT_JOB_FAILED, "the job cannot finish: a task failed %ld "
                            "times or the prepare job failed; `microray cluster status %s` says "
                            "which, its log is in %s/cluster/logs/", s->max_retries + 1, s->dir,
                            s->dir);
        }
        struct timespec ts = {1, 0};
        nanosleep(&ts, NULL);
    }
}

/* ---- command line ----------------------------------------------------------- */

static int usage(void)
{
    fputs("usage:\n", stderr);
    static const char *const subs[] = {"cluster submit", "cluster status", "cluster wait"};
    for (size_t i = 0; i < sizeof subs / sizeof *subs; i++)
        mrc_usage_command_print(stderr, mrc_usage_find(subs[i]));
    fputs("See docs/scale.md.\n", stderr);
    return MRC_EXIT_USAGE;
}

static bool parse_long(const char *s, long lo, long hi, long *out)
{
    char *end;
    errno = 0;
    long v = strtol(s, &end, 10);
    if (errno || *end || !s[0] || v < lo || v > hi)
        return false;
    *out = v;
    return true;
}

int mrc_cluster_main(int argc, char **argv, bool quiet)
{
    if (argc < 1)
        return usage();
    const char *cmd = argv[0];
    /* the options of this cluster command's row of the usage table, read
     * as every command reads them (client/main.c): "--name VALUE" or
     * "--name=VALUE"; after "--" everything is positional */
    char name[64];
    snprintf(name, sizeof name, "cluster %s", cmd);
    const mr_usage_command *uc = mrc_usage_find(name);
    if (!uc) {
        fprintf(stderr, "microray: unknown cluster command '%s'\n", cmd);
        return usage();
    }
    submit_opts so = {.chunk = 0};
    bool slurm = false, json = false, options_done = false;
    const char *dir = NULL;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (!options_done && !strcmp(a, "--")) {
            options_done = true;
            continue;
        }
        if (options_done || a[0] != '-' || !a[1]) {
            if (dir) {
                fprintf(stderr, "microray: unexpected argument '%s'\n", a);
                return usage();
            }
            dir = a;
            continue;
        }
        const char *eq = strchr(a, '=');
        char opt[64];
        snprintf(opt, sizeof opt, "%.*s", (int)(eq ? (size_t)(eq - a) : strlen(a)), a);
        const mr_usage_flag *f = mrc_usage_flag_find(uc, opt);
        if (!f) {
            fprintf(stderr, "microray: unknown option '%s' for cluster %s\n", a, cmd);
            return usage();
        }
        const char *v = NULL;
        if (!f->arg) {
            if (eq) {
                fprintf(stderr, "microray: option '%s' takes no value\n", a);
                return usage();
            }
        } else if (eq) {
            v = eq + 1;
        } else if (i + 1 < argc) {
            v = argv[++i];
        } else {
            fprintf(stderr, "microray: option '%s' needs a value\n", a);
            return usage();
        }
        if (!strcmp(opt, "--slurm")) {
            slurm = true;
        } else if (!strcmp(opt, "--json")) {
            json = true;
        } else if (!strcmp(opt, "--out")) {
            so.out = v;
        } else if (!strcmp(opt, "--chunk")) {
            if (!parse_long(v, 1, 1 << 30, &so.chunk)) {
                fprintf(stderr, "microray: --chunk wants a positive number of frames\n");
                return usage();
            }
        } else if (!strcmp(opt, "--threads")) {
            if (!parse_long(v, 1, 256, &so.threads)) {
                fprintf(stderr, "microray: --threads wants 1..256\n");
                return usage();
            }
        } else if (!strcmp(opt, "--partition")) {
            so.partition = v;
        } else if (!strcmp(opt, "--time")) {
            so.time_limit = v;
        } else if (!strcmp(opt, "--microrayd")) {
            so.microrayd = v;
        }
    }
    mrc_error err = {0};
    int rc;
    if (!strcmp(cmd, "submit")) {
        if (!slurm || !dir || !so.out || !so.chunk) {
            fprintf(stderr, "microray: cluster submit needs --slurm, JOB.json, --out DIR and "
                            "--chunk N\n");
            return usage();
        }
        so.job = dir;
        so.json = json;
        rc = cluster_submit(&so, quiet, &err);
        if (rc == 0 && json) { /* what was submitted, as status says it */
            cluster_state s;
            char state_dir[4096];
            snprintf(state_dir, sizeof state_dir, "%s", so.out);
            if ((rc = state_load(state_dir, &s, &err)) == 0) {
                snapshot sn;
                if ((rc = gather(&s, &sn, &err)) == 0) {
                    print_status(&s, &sn, true);
                    snapshot_free(&sn);
                }
                state_free(&s);
            }
        }
    } else if (!strcmp(cmd, "status") || !strcmp(cmd, "wait")) {
        if (!dir) {
            fprintf(stderr, "microray: cluster %s needs the job's output folder (DIR)\n", cmd);
            return usage();
        }
        cluster_state s;
        rc = state_load(dir, &s, &err);
        if (rc == 0 && !strcmp(cmd, "status")) {
            snapshot sn;
            if ((rc = gather(&s, &sn, &err)) == 0) {
                print_status(&s, &sn, json);
                rc = strcmp(sn.state, "failed") == 0 ? -MRC_EXIT_JOB_FAILED : 0;
                snapshot_free(&sn);
            }
        } else if (rc == 0) {
            rc = cluster_wait(&s, quiet, &err);
            snapshot sn;
            if (json && (rc == 0 || rc == -MRC_EXIT_JOB_FAILED) && gather(&s, &sn, &err) == 0) {
                print_status(&s, &sn, true);
                snapshot_free(&sn);
            }
        }
        state_free(&s);
    } else {
        return usage();
    }
    if (rc < 0 && err.code)
        fprintf(stderr, "microray: %s\n", err.msg);
    fflush(stdout);
    return rc < 0 ? -rc : 0;
}
