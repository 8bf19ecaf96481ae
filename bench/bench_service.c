/*
 * bench_service.c - the render service under load (make bench). Not a
 * test: it prints figures and never fails on a time.
 *  1. Status requests per second and p50/p99 latency with 64 concurrent
 *     keep-alive clients (wrk, loopback only, 5 s) while a job renders.
 *  2. Submission-to-first-frame: POST /v1/jobs until the first frame event
 *     arrives, against the one-shot renderer's start-to-first-frame on the
 *     same job (median of 5 each, interleaved, fresh asset import each time
 *     for the one-shot; the daemon's figure is shown with a cold and a warm
 *     scene cache).
 * usage: bench_service [--repeats N]   (from the repository root; the
 * daemon binary is $MR_BUILD_DIR/microrayd, default build/microrayd)
 */
#include <curl/curl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "microray.h"
#include "bench_util.h"

static char tmp[64] = "/tmp/microray-bench-XXXXXX";
static char microrayd[512] = "build/microrayd"; /* $MR_BUILD_DIR/microrayd */
static char base[64];
static pid_t daemon_pid;

static void start_daemon(void)
{
    char data[128], port_file[128];
    snprintf(data, sizeof data, "%s/data", tmp);
    snprintf(port_file, sizeof port_file, "%s/port", tmp);
    daemon_pid = fork();
    if (daemon_pid == 0) {
        execl(microrayd, "microrayd", "serve", "--listen", "127.0.0.1:0", "--data", data,
              "--asset-root", "/usr/share/assimp/models", "--port-file", port_file, "--quiet", (char *)NULL);
        _exit(127);
    }
    for (int i = 0; i < 300; i++) {
        FILE *f = fopen(port_file, "r");
        unsigned port = 0;
        if (f) {
            if (fscanf(f, "%u", &port) != 1)
                port = 0;
            fclose(f);
        }
        if (port) {
            snprintf(base, sizeof base, "http://127.0.0.1:%u", port);
            return;
        }
        usleep(100000);
    }
    fprintf(stderr, "bench_service: microrayd did not start\n");
    exit(1);
}

typedef struct buf {
    char *p;
    size_t n;
    double first_frame; /* mr_now() when "event: frame" first arrived */
} buf;

static size_t collect(char *p, size_t size, size_t n, void *user)
{
    buf *b = user;
    char *q = realloc(b->p, b->n + size * n + 1);
    if (!q)
        return 0;
    memcpy(q + b->n, p, size * n);
    b->p = q;
    b->n += size * n;
    b->p[b->n] = '\0';
    if (!b->first_frame && strstr(b->p, "event: frame\n")) {
        b->first_frame = mr_now();
        return 0; /* enough: abort the stream */
    }
    return size * n;
}

/* POSTs a job, returns its id (static buffer). */
static const char *post_job(const char *job)
{
    static char id[64];
    char url[128];
    snprintf(url, sizeof url, "%s/v1/jobs", base);
    buf b = {0};
    CURL *c = curl_easy_init();
    curl_easy_setopt(c, CURLOPT_URL, url);
    curl_easy_setopt(c, CURLOPT_POSTFIELDS, job);
    curl_easy_setopt(c, CURLOPT_WRITEFUNCTION, collect);
    curl_easy_setopt(c, CURLOPT_WRITEDATA, &b);
    curl_easy_perform(c);
    curl_easy_cleanup(c);
    const char *k = b.p ? strstr(b.p, "\"id\":\"") : NULL;
    if (!k) {
        fprintf(stderr, "bench_service: submit failed: %s\n", b.p ? b.p : "(no answer)");
        exit(1);
    }
    snprintf(id, sizeof id, "%.32s", k + 6);
    free(b.p);
    return id;
}

/* Seconds from POST to the first frame event. */
static double daemon_first_frame(const char *job)
{
    double t0 = mr_now();
    const char *id = post_job(job);
    char url[160];
    snprintf(url, sizeof url, "%s/v1/jobs/%s/events", base, id);
    buf b = {0};
    CURL *c = curl_easy_init();
    curl_easy_setopt(c, CURLOPT_URL, url);
    curl_easy_setopt(c, CURLOPT_WRITEFUNCTION, collect);
    curl_easy_setopt(c, CURLOPT_WRITEDATA, &b);
    curl_easy_setopt(c, CURLOPT_TIMEOUT, 120L);
    curl_easy_perform(c);
    curl_easy_cleanup(c);
    free(b.p);
    return b.first_frame ? b.first_frame - t0 : -1;
}

/* Seconds from starting `microrayd render` to its first frame file. */
static double oneshot_first_frame(const char *job_path, int run)
{
    char out[128], first[160];
    snprintf(out, sizeof out, "%s/oneshot%d", tmp, run);
    snprintf(first, sizeof first, "%s/0000.exr", out);
    double t0 = mr_now();
    pid_t pid = fork();
    if (pid == 0) {
        execl(microrayd, "microrayd", "render", job_path, "--out", out, "--quiet", (char *)NULL);
        _exit(127);
    }
    struct stat st;
    double t = -1;
    while (t < 0) {
        if (stat(first, &st) == 0)
            t = mr_now() - t0;
        else
            usleep(500);
    }
    kill(pid, SIGTERM);
    waitpid(pid, NULL, 0);
    return t;
}

static const char *JOB_FMT =
    "{\"name\":\"bench\",\"assets\":{\"d\":{\"path\":\"/usr/share/assimp/models/X/BCN_Epileptic.X\"}},"
    "\"objects\":[{\"asset\":\"d\",\"pose\":{\"clip\":0}}],"
    "\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0.2,4.3],\"target\":[0,0,-0.1]}]},"
    "\"frames\":{\"fps\":24,\"start\":0,\"end\":%g},\"output\":{\"width\":%d,\"height\":%d,\"samples\":%d}}";

int main(int argc, char **argv)
{
    int repeats = 5;
    for (int i = 1; i < argc; i++)
        if (!strcmp(argv[i], "--repeats") && i + 1 < argc)
            repeats = atoi(argv[++i]);
    if (repeats < 1 || repeats > 50)
        repeats = 5;
    if (getenv("MR_BUILD_DIR"))
        snprintf(microrayd, sizeof microrayd, "%s/microrayd", getenv("MR_BUILD_DIR"));
    if (!mkdtemp(tmp))
        return 1;
    curl_global_init(CURL_GLOBAL_DEFAULT);
    start_daemon();
    printf("\nmicroray service benchmarks: medians of %d runs\n", repeats);

    /* 2. submission to first frame */
    char job[2048], job_path[128];
    /* one frame: each measurement finds the queue empty */
    snprintf(job, sizeof job, JOB_FMT, 0.0, 640, 360, 1);
    snprintf(job_path, sizeof job_path, "%s/job.json", tmp);
    FILE *f = fopen(job_path, "w");
    fputs(job, f);
    fclose(f);
    double cold = daemon_first_frame(job); /* first job on this daemon: cache miss */
    double warm[50], shot[50];
    for (int i = 0; i < repeats; i++) {
        warm[i] = daemon_first_frame(job);
        shot[i] = oneshot_first_frame(job_path, i);
    }
    double mw = median(warm, repeats), ms = median(shot, repeats);
    printf("\nSubmission to first frame, 640x360, skinned example (ms)\n\n");
    printf("| path | first frame ms |\n|------|----------------|\n");
    printf("| one-shot `microrayd render` (process start, import, render, write) | %.1f |\n", ms * 1e3);
    printf("| daemon, cold cache (POST, import, render, store, event) | %.1f |\n", cold * 1e3);
    printf("| daemon, warm cache | %.1f |\n", mw * 1e3);
    printf("| daemon warm / one-shot | %.2f |\n", mw / ms);

    /* 1. status requests under load, while a long job renders */
    /* the example's 49 frames, big enough to keep both cores busy for the 5 s */
    snprintf(job, sizeof job, JOB_FMT, 2.0, 1920, 1080, 4);
    const char *id = post_job(job);
    char cmd[512], out[160];
    snprintf(out, sizeof out, "%s/wrk.txt", tmp);
    snprintf(cmd, sizeof cmd, "wrk -t2 -c64 -d5s --latency %s/v1/jobs/%s > %s 2>&1", base, id, out);
    if (system(cmd) != 0) {
        printf("\n(wrk not available: status load figures skipped)\n");
    } else {
        FILE *w = fopen(out, "r");
        char line[256], p50[32] = "?", p99[32] = "?", rps[32] = "?";
        while (w && fgets(line, sizeof line, w)) {
            sscanf(line, " 50%% %31s", p50);
            sscanf(line, " 99%% %31s", p99);
            sscanf(line, "Requests/sec: %31s", rps);
        }
        if (w)
            fclose(w);
        printf("\nStatus requests (GET /v1/jobs/{id}) with 64 keep-alive clients while a job renders (wrk, 5 s)\n\n");
        printf("| requests/s | p50 | p99 (goal < 5 ms) |\n|------------|-----|-----|\n| %s | %s | %s |\n", rps, p50, p99);
    }
    kill(daemon_pid, SIGTERM);
    waitpid(daemon_pid, NULL, 0);
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", tmp);
    if (system(cmd) != 0)
        return 1;
    curl_global_cleanup();
    return 0;
}
