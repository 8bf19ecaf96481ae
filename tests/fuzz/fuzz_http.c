/*
 * fuzz_http.c - libFuzzer harness of the HTTP request path: the real
 * daemon (mr_daemon_start: store, workers, libmicrohttpd front end with its
 * guard, routes, handlers and replies) is started once, on a loopback port
 * chosen by the kernel with a temporary data directory, and each input is
 * written as raw bytes to a new connection; the answer is read until the
 * daemon closes the connection. So every input goes through libmicrohttpd's
 * parsing into our callbacks (the unescape callback, begin_request's
 * framing and size checks, http_route_find, the token check is off), the
 * handlers (job submission into mr_job_parse, asset uploads into the store,
 * job queries against sqlite) and the problem+json replies.
 *
 * The write side is shut down after the input. libmicrohttpd 0.9.75 (epoll,
 * edge-triggered) often misses that end of stream when it arrives with the
 * last bytes of a request (an unfinished head or body, or a keep-alive
 * connection after its answers), and the connection then waits for the
 * guard's request deadline (10 s) to cut it. Waiting for that would make a
 * few executions a minute, so the harness ends an input when the daemon is
 * idle on it instead: the daemon's end of the connection (found among this
 * process's descriptors by its peer address) has no unread bytes and
 * nothing has come back for QUIET_MS. The socket is then closed with
 * SO_LINGER 0 (a reset: no TIME_WAIT pile-up over a long run). A
 * connection neither closed nor idle after ANSWER_TIMEOUT_MS, or an answer
 * that is not HTTP, is a failure (abort, so libFuzzer keeps the input).
 * The data directory is on /dev/shm when there is one (sqlite's fsyncs).
 *
 * libmicrohttpd, sqlite and cJSON are not instrumented: coverage counts our
 * code only.
 */
#define _GNU_SOURCE
#include <arpa/inet.h>
#include <errno.h>
#include <ftw.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "daemon.h"
#include "import_worker.h"
#include "render_proc.h"
#include "fuzz_tmp.h"

#define ANSWER_TIMEOUT_MS 20000
#define QUIET_MS 3

static mr_daemon *daemon_;
static unsigned port;
static char data_dir[128];

static void die(const char *what)
{
    fprintf(stderr, "fuzz_http: %s\n", what);
    abort();
}

static void cleanup(void)
{
    if (daemon_)
        mr_daemon_stop(daemon_);
    daemon_ = NULL;
    fuzz_tmp_remove(data_dir);
}

int LLVMFuzzerInitialize(int *argc, char ***argv)
{
    /* The daemon's render worker (and its import children) exec this very
     * program (/proc/self/exe): run as that, not as the fuzzer. */
    if (*argc >= 2 && !strcmp((*argv)[1], "render-worker"))
        exit(mr_cmd_render_worker(*argc - 2, *argv + 2));
    if (*argc >= 2 && !strcmp((*argv)[1], "import-worker"))
        exit(mr_cmd_import_worker(*argc - 2, *argv + 2));
    signal(SIGPIPE, SIG_IGN);
    if (fuzz_tmp_make("fuzz-http", data_dir, sizeof data_dir) != 0)
        die("mkdtemp");
    mr_daemon_config cfg = {
        .listen_host = "127.0.0.1",
        .port = 0,
        .data_dir = data_dir,
        .workers = 1,
        .render_threads = 1,
        .http_threads = 1,
        .cache_bytes = (size_t)64 << 20,
        .max_asset_bytes = (size_t)1 << 20,
        .import_memory = (size_t)1 << 30,
        .import_timeout_s = 10,
        .quiet = true,
    };
    mr_error err;
    if (mr_daemon_start(&cfg, &daemon_, &err) < 0) {
        fprintf(stderr, "fuzz_http: mr_daemon_start: %s\n", err.msg);
        abort();
    }
    port = mr_daemon_port(daemon_);
    atexit(cleanup);
    return 0;
}

static int64_t now_ms(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000 + ts.tv_nsec / 1000000;
}

/* The daemon's descriptor of the connection whose client end is local:
 * the socket whose peer is that address; -1 while not accepted (or gone). */
static int server_fd(const struct sockaddr_in *local)
{
    for (int fd = 3; fd < 1024; fd++) {
        struct sockaddr_in peer;
        socklen_t len = sizeof peer;
        if (getpeername(fd, (struct sockaddr *)&peer, &len) == 0 && len == sizeof peer &&
            peer.sin_family == AF_INET && peer.sin_port == local->sin_port &&
            peer.sin_addr.s_addr == local->sin_addr.s_addr)
            return fd;
    }
    return -1;
}

/* A connection from a source address of its own: 127.1.0.0/16 in turn.
 * Where the daemon closes first, its side of the connection stays in
 * TIME_WAIT for a minute; at ~1,000 inputs a second from one address the
 * client's ephemeral ports then ran out after ~17 s in CI (connect failed).
 * 65,536 addresses times the port range never repeat a connection's
 * addresses within that minute. */
static int connect_daemon(void)
{
    static uint32_t next;
    for (int attempt = 0; attempt < 8; attempt++) {
        int s = socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
        if (s < 0)
            die("socket");
        struct sockaddr_in from = {.sin_family = AF_INET};
        from.sin_addr.s_addr = htonl(0x7f010000u | (next++ & 0xffffu));
        struct sockaddr_in sa = {.sin_family = AF_INET, .sin_port = htons((uint16_t)port)};
        sa.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
        if (bind(s, (struct sockaddr *)&from, sizeof from) == 0 &&
            connect(s, (struct sockaddr *)&sa, sizeof sa) == 0)
            return s;
        fprintf(stderr, "fuzz_http: connect from %s: %s\n", inet_ntoa(from.sin_addr),
                strerror(errno));
        close(s);
    }
    die("connect: the daemon is gone");
    return -1;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    int s = connect_daemon();
    struct sockaddr_in local;
    socklen_t llen = sizeof local;
    if (getsockname(s, (struct sockaddr *)&local, &llen) != 0)
        die("getsockname");

    /* Write everything; the daemon may answer (and close) before reading
     * all of it (a refused head), which ends the writing. */
    size_t off = 0;
    while (off < size) {
        ssize_t n = send(s, data + off, size - off, MSG_NOSIGNAL);
        if (n < 0 && errno == EINTR)
            continue;
        if (n <= 0)
            break;
        off += (size_t)n;
    }
    shutdown(s, SHUT_WR);

    char head[16];
    size_t got = 0;
    static char buf[65536];
    int64_t start = now_ms(), last = start;
    for (;;) {
        int64_t t = now_ms();
        if (t - start > ANSWER_TIMEOUT_MS)
            die("the daemon neither closed the connection nor went idle on it");
        struct pollfd p = {.fd = s, .events = POLLIN};
        int pr = poll(&p, 1, 1);
        if (pr < 0 && errno == EINTR)
            continue;
        if (pr > 0) {
            ssize_t n = recv(s, buf, sizeof buf, 0);
            if (n < 0 && errno == EINTR)
                continue;
            if (n <= 0)
                break; /* closed (or reset) */
            for (ssize_t i = 0; i < n && got < sizeof head; i++)
                head[got++] = buf[i];
            last = now_ms();
            continue;
        }
        if (now_ms() - last < QUIET_MS)
            continue;
        int fd = server_fd(&local);
        int unread = 0;
        if (fd >= 0 && ioctl(fd, FIONREAD, &unread) == 0 && unread == 0)
            break; /* idle: waiting for bytes that will never come */
    }
    if (got >= 5 && memcmp(head, "HTTP/", 5) != 0)
        die("the answer does not start with HTTP/");
    struct linger lg = {.l_onoff = 1, .l_linger = 0};
    setsockopt(s, SOL_SOCKET, SO_LINGER, &lg, sizeof lg);
    close(s);
    return 0;
}
