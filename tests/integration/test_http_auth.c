/*
 * test_http_auth.c - authentication and TLS of the real microrayd (issue
 * 12, the design part): a non-loopback --listen without --token-file or
 * --insecure is refused at start; with --token-file every request but
 * /healthz and /readyz needs Authorization: Bearer <token> (401
 * problem+json with WWW-Authenticate otherwise), also for the microray
 * client (MICRORAY_TOKEN, --token-file); with --tls-cert/--tls-key the
 * daemon speaks HTTPS (a self-signed certificate made here with openssl,
 * checked by libcurl against it).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <stdbool.h>

#include "daemon_fixture.h"

#define TOKEN "t0k3n-for-the-tests-0123456789abcdef"

static daemon_proc A; /* --token-file, plain HTTP */
static char token_file[400], cert[400], key[400];

static int setup(void **state)
{
    (void)state;
    curl_global_init(CURL_GLOBAL_DEFAULT);
    fx_init_dirs();
    snprintf(token_file, sizeof token_file, "%s/token", fx_tmp);
    FILE *f = fopen(token_file, "w");
    if (!f)
        return -1;
    fprintf(f, "%s\n", TOKEN);
    fclose(f);
    const char *const args[] = {"--token-file", token_file, NULL};
    daemon_start_args(&A, "auth", args);
    return 0;
}

static int teardown(void **state)
{
    (void)state;
    int rc = daemon_stop(&A, SIGTERM);
    fx_cleanup_dirs();
    return rc == 0 ? 0 : -1;
}

/* Runs microrayd serve with args (a shell fragment) and returns its exit
 * status; its stderr lands in out. */
static int serve_status(const char *args, char *out, size_t size)
{
    char cmd[3000], log[400];
    snprintf(log, sizeof log, "%s/refused.log", fx_tmp);
    snprintf(cmd, sizeof cmd, "timeout 20 '%s/microrayd' serve --data '%s/refused' --quiet %s 2>'%s'",
             fx_build_dir, fx_tmp, args, log);
    int st = system(cmd);
    char *text = fx_slurp(log, NULL);
    snprintf(out, size, "%s", text ? text : "");
    free(text);
    return WIFEXITED(st) ? WEXITSTATUS(st) : -1;
}

static void test_non_loopback_needs_token(void **state)
{
    (void)state;
    char err[2048];
    int st = serve_status("--listen 0.0.0.0:0", err, sizeof err);
    if (st != 1 || !strstr(err, "--token-file") || !strstr(err, "--insecure"))
        fail_msg("--listen 0.0.0.0:0 without a token: exit %d, %s", st, err);
    st = serve_status("--listen '[::]:0'", err, sizeof err);
    if (st != 1 || !strstr(err, "not a loopback address"))
        fail_msg("--listen [::]:0 without a token: exit %d, %s", st, err);
    /* a token too short to be a secret */
    char args[600], shortf[400];
    snprintf(shortf, sizeof shortf, "%s/short", fx_tmp);
    FILE *f = fopen(shortf, "w");
    fputs("abc\n", f);
    fclose(f);
    snprintf(args, sizeof args, "--token-file '%s'", shortf);
    st = serve_status(args, err, sizeof err);
    if (st != 2 || !strstr(err, "at least 16"))
        fail_msg("a 3-character token: exit %d, %s", st, err);
}

static void expect_401(const char *path, const char *header, bool invalid)
{
    http_result r = http(&A, "GET", path, NULL, 0, header);
    if (r.status != 401 || !strstr(r.content_type, "application/problem+json"))
        fail_msg("GET %s (%s): %ld %s %s", path, header ? header : "no token", r.status, r.content_type,
                 r.body);
    http_free(&r);
    /* the challenge, by hand: the fixture does not keep other headers */
    char url[512], challenge[256] = "";
    snprintf(url, sizeof url, "%s%s", A.base, path);
    CURL *c = curl_easy_init();
    struct curl_slist *h = header ? curl_slist_append(NULL, header) : NULL;
    curl_easy_setopt(c, CURLOPT_URL, url);
    curl_easy_setopt(c, CURLOPT_HTTPHEADER, h);
    curl_easy_setopt(c, CURLOPT_NOBODY, 0L);
    curl_easy_setopt(c, CURLOPT_WRITEFUNCTION, fx_collect);
    http_result sink = {0};
    curl_easy_setopt(c, CURLOPT_WRITEDATA, &sink);
    assert_int_equal(curl_easy_perform(c), CURLE_OK);
    struct curl_header *w = NULL;
    if (curl_easy_header(c, "WWW-Authenticate", 0, CURLH_HEADER, -1, &w) == CURLHE_OK)
        snprintf(challenge, sizeof challenge, "%s", w->value);
    curl_slist_free_all(h);
    curl_easy_cleanup(c);
    free(sink.body);
    if (strncmp(challenge, "Bearer ", 7) != 0 || (invalid != (strstr(challenge, "invalid_token") != NULL)))
        fail_msg("GET %s: WWW-Authenticate '%s'", path, challenge);
}

static void test_token_required(void **state)
{
    (void)state;
    expect_401("/v1/jobs", NULL, false);
    expect_401("/metrics", NULL, false);
    expect_401("/v2/no-such-path", NULL, false); /* not even a 404 without the token */
    expect_401("/v1/jobs", "Authorization: Bearer wrong-token-wrong-token-wrong", true);
    expect_401("/v1/jobs", "Authorization: Bearer " TOKEN "x", true);
    expect_401("/v1/jobs", "Authorization: Basic dXNlcjpwYXNz", false);
    http_result r = http(&A, "GET", "/v1/jobs", NULL, 0, "Authorization: Bearer " TOKEN);
    assert_int_equal(r.status, 200);
    http_free(&r);
    r = http(&A, "GET", "/v2/no-such-path", NULL, 0, "Authorization: bearer " TOKEN);
    assert_int_equal(r.status, 404);
    http_free(&r);
    const char *open[] = {"/healthz", "/readyz"};
    for (int i = 0; i < 2; i++) {
        r = http(&A, "GET", open[i], NULL, 0, NULL);
        assert_int_equal(r.status, 200);
        http_free(&r);
    }
}

static void test_client_sends_token(void **state)
{
    (void)state;
    char cmd[3000];
    const char *client_fmt = "'%s/microray' --server %s --quiet %s list >/dev/null 2>&1";
    snprintf(cmd, sizeof cmd, client_fmt, fx_build_dir, A.base, "");
    int st = system(cmd);
    assert_int_equal(WEXITSTATUS(st), 3); /* rejected: 401 */
    char with_env[3100];
    snprintf(with_env, sizeof with_env, "MICRORAY_TOKEN=%s %s", TOKEN, cmd);
    st = system(with_env);
    assert_int_equal(WEXITSTATUS(st), 0);
    char flag[600];
    snprintf(flag, sizeof flag, "--token-file '%s'", token_file);
    snprintf(cmd, sizeof cmd, client_fmt, fx_build_dir, A.base, flag);
    st = system(cmd);
    assert_int_equal(WEXITSTATUS(st), 0);
}

/* GET url over HTTPS trusting only ca; returns the status (0: no answer). */
static long https_get(const char *url, const char *ca, const char *header)
{
    CURL *c = curl_easy_init();
    struct curl_slist *h = header ? curl_slist_append(NULL, header) : NULL;
    http_result sink = {0};
    curl_easy_setopt(c, CURLOPT_URL, url);
    curl_easy_setopt(c, CURLOPT_CAINFO, ca);
    curl_easy_setopt(c, CURLOPT_HTTPHEADER, h);
    curl_easy_setopt(c, CURLOPT_WRITEFUNCTION, fx_collect);
    curl_easy_setopt(c, CURLOPT_WRITEDATA, &sink);
    curl_easy_setopt(c, CURLOPT_TIMEOUT, 20L);
    long status = 0;
    if (curl_easy_perform(c) == CURLE_OK)
        curl_easy_getinfo(c, CURLINFO_RESPONSE_CODE, &status);
    curl_slist_free_all(h);
    curl_easy_cleanup(c);
    free(sink.body);
    return status;
}

static void test_tls(void **state)
{
    (void)state;
    snprintf(cert, sizeof cert, "%s/cert.pem", fx_tmp);
    snprintf(key, sizeof key, "%s/key.pem", fx_tmp);
    char cmd[2000];
    snprintf(cmd, sizeof cmd,
             "openssl req -x509 -newkey rsa:2048 -nodes -keyout '%s' -out '%s' -days 2 "
             "-subj /CN=127.0.0.1 -addext subjectAltName=IP:127.0.0.1 >/dev/null 2>&1",
             key, cert);
    if (system(cmd) != 0)
        fail_msg("openssl could not make a self-signed certificate (scripts/setup.sh installs openssl)");
    daemon_proc T;
    const char *const args[] = {"--tls-cert", cert, "--tls-key", key, "--token-file", token_file, NULL};
    daemon_start_args(&T, "tls", args);
    char url[256];
    snprintf(url, sizeof url, "https://127.0.0.1:%u/healthz", T.port);
    assert_int_equal(https_get(url, cert, NULL), 200);
    snprintf(url, sizeof url, "https://127.0.0.1:%u/v1/jobs", T.port);
    assert_int_equal(https_get(url, cert, NULL), 401);
    assert_int_equal(https_get(url, cert, "Authorization: Bearer " TOKEN), 200);
    /* plain HTTP on the TLS port gets no HTTP answer */
    http_result sink = {0};
    CURL *c = curl_easy_init();
    snprintf(url, sizeof url, "http://127.0.0.1:%u/healthz", T.port);
    curl_easy_setopt(c, CURLOPT_URL, url);
    curl_easy_setopt(c, CURLOPT_TIMEOUT, 10L);
    curl_easy_setopt(c, CURLOPT_WRITEFUNCTION, fx_collect);
    curl_easy_setopt(c, CURLOPT_WRITEDATA, &sink);
    CURLcode rc = curl_easy_perform(c);
    long status = 0;
    curl_easy_getinfo(c, CURLINFO_RESPONSE_CODE, &status);
    curl_easy_cleanup(c);
    free(sink.body);
    assert_true(rc != CURLE_OK || status != 200);
    char *log = fx_slurp(T.log, NULL);
    assert_non_null(log);
    assert_non_null(strstr(log, "listening on https://"));
    free(log);
    assert_int_equal(daemon_stop(&T, SIGTERM), 0);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_non_loopback_needs_token),
        cmocka_unit_test(test_token_required),
        cmocka_unit_test(test_client_sends_token),
        cmocka_unit_test(test_tls),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
