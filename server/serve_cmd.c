/*
 * serve_cmd.c - `microrayd serve`: runs the daemon until SIGTERM or SIGINT.
 *
 *   microrayd serve [--listen HOST:PORT] [--data DIR] [--asset-root DIR]...
 *                   [--workers N] [--threads N] [--http-threads N] [--cache-mb N]
 *                   [--job-memory-mb N] [--worker-memory-mb N] [--frame-timeout S]
 *                   [--import-memory-mb N] [--import-timeout S]
 *                   [--disk-reserve-mb N]
 *                   [--max-connections N] [--per-ip-connections N] [--request-timeout S]
 *                   [--token-file F] [--insecure] [--tls-cert F --tls-key F]
 *                   [--port-file F] [--quiet]
 *
 * Signals are blocked in every thread and taken synchronously here with
 * sigwait, so the stop runs in ordinary code (no async-signal-safety games):
 * HTTP stops, workers finish the frame in progress, the store closes.
 */
#include <errno.h>
#include <pthread.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "daemon.h"
#include "render_cmd.h"
#include "usage.h"
#include "microray.h"

#define MR_DEFAULT_PORT 8470
#define MR_MAX_ROOTS 64

static void usage(void)
{
    mr_usage_command_print(stderr, "serve");
}

static bool parse_uint(const char *s, unsigned long lo, unsigned long hi, unsigned long *out)
{
    char *end;
    errno = 0;
    unsigned long v = strtoul(s, &end, 10);
    if (errno || *end || s[0] == '-' || s[0] == '\0' || v < lo || v > hi)
        return false;
    *out = v;
    return true;
}

/* The default data directory: $MICRORAY_DATA, else $XDG_DATA_HOME/microray,
 * else $HOME/.local/share/microray, else ./microray-data. */
static void default_data_dir(char *out, size_t n)
{
    const char *env = getenv("MICRORAY_DATA"), *xdg = getenv("XDG_DATA_HOME"), *home = getenv("HOME");
    if (env && env[0])
        snprintf(out, n, "%s", env);
    else if (xdg && xdg[0])
        snprintf(out, n, "%s/microray", xdg);
    else if (home && home[0])
        snprintf(out, n, "%s/.local/share/microray", home);
    else
        snprintf(out, n, "microray-data");
}

/* A PEM file or the token file, NUL-terminated; NULL after printing why. */
static char *read_text(const char *path, uint64_t max, const char *what)
{
    uint8_t *buf = NULL;
    size_t size = 0;
    mr_error err = {0};
    if (mr_fs_read_capped(path, max, &buf, &size, what, &err) < 0) {
        fprintf(stderr, "microrayd: %s\n", err.msg);
        return NULL;
    }
    char *text = realloc(buf, size + 1);
    if (!text) {
        free(buf);
        fprintf(stderr, "microrayd: out of memory\n");
        return NULL;
    }
    text[size] = '\0';
    return text;
}

/* The bearer token of --token-file: its first line, which must be an RFC
 * 6750 b64token of at least MIN_TOKEN characters (guessing it must not be
 * an option). NULL after printing why. */
#define MIN_TOKEN 16
static char *read_token(const char *path)
{
    char *t = read_text(path, 4096, "token file");
    if (!t)
        return NULL;
    t[strcspn(t, "\r\n")] = '\0';
    size_t n = strlen(t);
    while (n && (t[n - 1] == ' ' || t[n - 1] == '\t'))
        t[--n] = '\0';
    size_t bad = strspn(t, "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-._~+/");
    while (t[bad] == '=')
        bad++;
    if (n < MIN_TOKEN || bad != n) {
        fprintf(stderr,
                "microrayd: token file %s: the first line must be a token of at least %d characters "
                "A-Z a-z 0-9 - . _ ~ + / (e.g. from: openssl rand -hex 32)\n",
                path, MIN_TOKEN);
        free(t);
        return NULL;
    }
    return t;
}

int mr_cmd_serve(int argc, char **argv)
{
    mr_daemon_config cfg = {.port = MR_DEFAULT_PORT};
    const char *roots[MR_MAX_ROOTS];
    const char *port_file = NULL, *token_file = NULL, *cert_file = NULL, *key_file = NULL;
    char host[256] = "127.0.0.1", data[4096];
    default_data_dir(data, sizeof data);
    for (int i = 0; i < argc; i++) {
        const char *a = argv[i], *v = i + 1 < argc ? argv[i + 1] : NULL;
        unsigned long n;
        if (!strcmp(a, "--quiet")) {
            cfg.quiet = true;
            continue;
        }
        if (!strcmp(a, "--insecure")) {
            cfg.insecure = true;
            continue;
        }
        if (!v) {
            usage();
            return 2;
        }
        i++;
        if (!strcmp(a, "--listen")) {
            const char *colon = strrchr(v, ':');
            if (!colon || colon == v || (size_t)(colon - v) >= sizeof host || !parse_uint(colon + 1, 0, 65535, &n)) {
                fprintf(stderr, "microrayd: --listen wants HOST:PORT, e.g. 127.0.0.1:8470\n");
                return 2;
            }
            snprintf(host, sizeof host, "%.*s", (int)(colon - v), v);
            cfg.port = (unsigned)n;
        } else if (!strcmp(a, "--data")) {
            snprintf(data, sizeof data, "%s", v);
        } else if (!strcmp(a, "--asset-root")) {
            if (cfg.asset_root_count == MR_MAX_ROOTS) {
                fprintf(stderr, "microrayd: at most %d asset roots\n", MR_MAX_ROOTS);
                return 2;
            }
            roots[cfg.asset_root_count++] = v;
        } else if (!strcmp(a, "--workers") && parse_uint(v, 1, 64, &n)) {
            cfg.workers = (unsigned)n;
        } else if (!strcmp(a, "--threads") && parse_uint(v, 1, MR_MAX_THREADS, &n)) {
            cfg.render_threads = (unsigned)n;
        } else if (!strcmp(a, "--http-threads") && parse_uint(v, 1, 64, &n)) {
            cfg.http_threads = (unsigned)n;
        } else if (!strcmp(a, "--cache-mb") && parse_uint(v, 1, 1u << 20, &n)) {
            cfg.cache_bytes = (size_t)n << 20;
        } else if (!strcmp(a, "--disk-reserve-mb") && parse_uint(v, 1, 1u << 16, &n)) {
            cfg.disk_reserve = (size_t)n << 20;
        } else if (!strcmp(a, "--job-memory-mb") && parse_uint(v, 16, 1u << 24, &n)) {
            cfg.job_memory = (size_t)n << 20;
        } else if (!strcmp(a, "--worker-memory-mb") && parse_uint(v, 64, 1u << 24, &n)) {
            cfg.worker_memory = (size_t)n << 20;
        } else if (!strcmp(a, "--import-memory-mb") && parse_uint(v, 16, 1u << 24, &n)) {
            cfg.import_memory = (size_t)n << 20;
        } else if (!strcmp(a, "--frame-timeout") && parse_uint(v, 1, 7 * 86400, &n)) {
            cfg.frame_timeout_s = (double)n;
        } else if (!strcmp(a, "--import-timeout") && parse_uint(v, 1, 86400, &n)) {
            cfg.import_timeout_s = (double)n;
        } else if (!strcmp(a, "--max-connections") && parse_uint(v, 16, 1u << 20, &n)) {
            cfg.max_connections = (unsigned)n;
        } else if (!strcmp(a, "--per-ip-connections") && parse_uint(v, 1, 1u << 20, &n)) {
            cfg.per_ip_connections = (unsigned)n;
        } else if (!strcmp(a, "--request-timeout") && parse_uint(v, 1, 3600, &n)) {
            cfg.request_timeout_s = (unsigned)n;
        } else if (!strcmp(a, "--token-file")) {
            token_file = v;
        } else if (!strcmp(a, "--tls-cert")) {
            cert_file = v;
        } else if (!strcmp(a, "--tls-key")) {
            key_file = v;
        } else if (!strcmp(a, "--port-file")) {
            port_file = v;
        } else {
            usage();
            return 2;
        }
    }
    cfg.listen_host = host;
    cfg.data_dir = data;
    cfg.asset_roots = roots;
    /* Read once here; they live (like cfg) until the process ends. */
    char *token = NULL, *cert = NULL, *key = NULL;
    if (token_file && !(token = read_token(token_file)))
        return 2;
    if ((cert_file || key_file) && !(cert_file && key_file)) {
        fprintf(stderr, "microrayd: TLS needs both --tls-cert FILE and --tls-key FILE\n");
        return 2;
    }
    if (cert_file && (!(cert = read_text(cert_file, 1u << 20, "TLS certificate")) ||
                      !(key = read_text(key_file, 1u << 20, "TLS key")))) {
        free(token);
        free(cert);
        return 2;
    }
    cfg.token = token;
    cfg.tls_cert_pem = cert;
    cfg.tls_key_pem = key;

    /* Block the stop signals before any thread starts, so all inherit it. */
    sigset_t set;
    sigemptyset(&set);
    sigaddset(&set, SIGTERM);
    sigaddset(&set, SIGINT);
    pthread_sigmask(SIG_BLOCK, &set, NULL);
    signal(SIGPIPE, SIG_IGN);

    mr_daemon *d = NULL;
    mr_error err = {0};
    if (mr_daemon_start(&cfg, &d, &err) < 0) {
        fprintf(stderr, "microrayd: %s\n", err.msg);
        free(token);
        free(cert);
        free(key);
        return err.code == MR_ERR_IO ? 4 : 1;
    }
    if (port_file) {
        char text[32];
        int len = snprintf(text, sizeof text, "%u\n", mr_daemon_port(d));
        if (mr_fs_write_atomic(port_file, text, (size_t)len, "port file", &err) < 0)
            fprintf(stderr, "microrayd: warning: %s\n", err.msg);
    }
    int sig = 0;
    sigwait(&set, &sig);
    if (!cfg.quiet)
        fprintf(stderr, "microrayd: %s: stopping (the frame in progress finishes)\n", sig == SIGINT ? "SIGINT" : "SIGTERM");
    mr_daemon_stop(d);
    free(token);
    free(cert);
    free(key);
    return 0;
}
