/*
 * test_hostile_assets.c - hostile model files against the real daemon
 * (issue 12, "a hostile-input suite"): every file of Debian's
 * /usr/share/assimp/models/invalid, crafted huge-count files for the
 * formats assimp believes (PLY, OFF, X, STL, OBJ, glTF), and a glTF bomb
 * set (deep nesting, a huge byteLength, a huge accessor count, a buffer
 * URI out of the asset's folder), each uploaded and rendered by a job.
 *
 * Each must end with the job failed (or, for a file that is merely odd,
 * succeeded) and a message that names no server path and leaks no bytes of
 * a file outside the asset; and after all of them the daemon answers
 * /healthz at once and its database passes sqlite's integrity check. The
 * daemon imports in a child with --import-memory-mb 512, so a file that
 * makes assimp allocate without end costs a few seconds, not the machine.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <cJSON.h>
#include <dirent.h>
#include <stdbool.h>

#include "daemon_fixture.h"
#include "microray.h"

static daemon_proc D;

static int setup(void **state)
{
    (void)state;
    curl_global_init(CURL_GLOBAL_DEFAULT);
    fx_init_dirs();
    const char *const args[] = {"--import-memory-mb", "512", "--import-timeout", "60", NULL};
    daemon_start_args(&D, "hostile", args);
    return 0;
}

static int teardown(void **state)
{
    (void)state;
    int rc = daemon_stop(&D, SIGTERM);
    fx_cleanup_dirs();
    return rc == 0 ? 0 : -1;
}

/* Uploads bytes, renders them in a one-frame job and returns the job's
 * final state ("failed", "succeeded"); 0-byte files are refused (400) at
 * the upload and return "refused". */
static const char *render_upload(const char *name, const void *bytes, size_t len, char *why,
                                 size_t why_size)
{
    static char state_buf[32];
    why[0] = '\0';
    http_result r = http(&D, "POST", "/v1/assets", bytes, len, "Content-Type: application/octet-stream");
    if (len == 0) {
        assert_int_equal(r.status, 400);
        http_free(&r);
        return "refused";
    }
    if (r.status != 201 && r.status != 200)
        fail_msg("%s: upload answered %ld %s", name, r.status, r.body);
    cJSON *j = cJSON_Parse(r.body);
    char asset[80], job[1024];
    snprintf(asset, sizeof asset, "%s", cJSON_GetObjectItem(j, "id")->valuestring);
    cJSON_Delete(j);
    http_free(&r);
    snprintf(job, sizeof job,
             "{\"name\":\"%s\",\"max_retries\":0,\"assets\":{\"m\":{\"id\":\"%s\"}},"
             "\"objects\":[{\"asset\":\"m\"}],"
             "\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0,5],\"target\":[0,0,0]}]},"
             "\"frames\":{\"times\":[0]},\"output\":{\"width\":32,\"height\":18}}",
             name, asset);
    r = http(&D, "POST", "/v1/jobs", job, strlen(job), NULL);
    if (r.status != 202)
        fail_msg("%s: submit answered %ld %s", name, r.status, r.body);
    j = cJSON_Parse(r.body);
    char path[128];
    snprintf(path, sizeof path, "/v1/jobs/%s", cJSON_GetObjectItem(j, "id")->valuestring);
    cJSON_Delete(j);
    http_free(&r);
    double t0 = mr_now();
    for (int i = 0; i < 1800; i++) {
        r = http(&D, "GET", path, NULL, 0, NULL);
        assert_int_equal(r.status, 200);
        j = cJSON_Parse(r.body);
        http_free(&r);
        const char *s = cJSON_GetObjectItem(j, "state")->valuestring;
        if (!strcmp(s, "failed") || !strcmp(s, "succeeded") || !strcmp(s, "canceled")) {
            snprintf(state_buf, sizeof state_buf, "%s", s);
            const cJSON *e = cJSON_GetObjectItem(j, "error");
            snprintf(why, why_size, "%s", cJSON_IsString(e) ? e->valuestring : "");
            cJSON_Delete(j);
            print_message("[ hostile  ] %-22s %-9s %5.2f s  %.160s\n", name, state_buf,
                          mr_now() - t0, why);
            return state_buf;
        }
        cJSON_Delete(j);
        fx_sleep_ms(100);
    }
    fail_msg("%s: the job did not finish within 180 s", name);
    return NULL;
}

/* may_succeed: the file is odd rather than broken (assimp reads
 * invalid/malformed2.obj, say); a bomb must fail. */
static void expect_no_harm(const char *name, const void *bytes, size_t len, bool may_succeed)
{
    char why[1024];
    const char *state = render_upload(name, bytes, len, why, sizeof why);
    if (!strcmp(state, "refused") || (may_succeed && !strcmp(state, "succeeded")))
        return;
    assert_string_equal(state, "failed");
    assert_true(why[0] != '\0');
    if (strstr(why, D.data) || strstr(why, fx_tmp))
        fail_msg("%s: the error shows a server path: %s", name, why);
    if (strstr(why, "root:") || strstr(why, "7.58801e+31"))
        fail_msg("%s: the error leaks another file's bytes: %s", name, why);
}

static void expect_clean_failure(const char *name, const void *bytes, size_t len)
{
    expect_no_harm(name, bytes, len, false);
}

static void test_invalid_models(void **state)
{
    (void)state;
    const char *dir = "/usr/share/assimp/models/invalid";
    DIR *d = opendir(dir);
    assert_non_null(d);
    struct dirent *e;
    int files = 0;
    while ((e = readdir(d)) != NULL) {
        if (e->d_name[0] == '.' || !strcmp(e->d_name, "readme.txt"))
            continue;
        char path[600];
        snprintf(path, sizeof path, "%s/%s", dir, e->d_name);
        size_t len = 0;
        char *bytes = fx_slurp(path, &len);
        assert_non_null(bytes);
        expect_no_harm(e->d_name, bytes, len, true);
        free(bytes);
        files++;
    }
    closedir(d);
    assert_true(files >= 14);
}

static void test_huge_counts(void **state)
{
    (void)state;
    static const char ply_vertices[] =
        "ply\nformat ascii 1.0\nelement vertex 1500000000\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n0 0 0\n";
    expect_clean_failure("ply-vertex-count", ply_vertices, sizeof ply_vertices - 1);

    static const char ply_head[] =
        "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uint int vertex_indices\nend_header\n";
    unsigned char ply[sizeof ply_head - 1 + 36 + 4 + 12] = {0};
    memcpy(ply, ply_head, sizeof ply_head - 1);
    const float v[9] = {0, 0, 0, 1, 0, 0, 0, 1, 0};
    const uint32_t list = 2000000000u;
    memcpy(ply + sizeof ply_head - 1, v, sizeof v);
    memcpy(ply + sizeof ply_head - 1 + 36, &list, 4);
    expect_clean_failure("ply-face-list", ply, sizeof ply);

    static const char off[] = "OFF\n353535235358 1 0\n0 0 0\n";
    expect_clean_failure("off-vertex-count", off, sizeof off - 1);

    static const char x[] = "xof 0303txt 0032\nMesh {\n2000000000;\n0;0;0;;\n}\n";
    expect_clean_failure("x-vertex-count", x, sizeof x - 1);

    unsigned char stl[80 + 4 + 50] = {0};
    memcpy(stl, "binary stl", 10);
    const uint32_t tris = 0xffffffffu;
    memcpy(stl + 80, &tris, 4);
    expect_clean_failure("stl-triangle-count", stl, sizeof stl);

    static const char obj[] = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 2000000000\n";
    expect_clean_failure("obj-index", obj, sizeof obj - 1);
}

static void test_gltf_bombs(void **state)
{
    (void)state;
    /* 30,000 nodes nested one in the other (crashed assimp's recursion on
     * an 8 MiB stack) */
    enum { DEPTH = 30000 };
    size_t cap = (size_t)DEPTH * 40 + 512, n = 0;
    char *deep = malloc(cap);
    n += (size_t)snprintf(deep + n, cap - n, "{\"asset\":{\"version\":\"2.0\"},\"scene\":0,"
                                             "\"scenes\":[{\"nodes\":[0]}],\"nodes\":[");
    for (int i = 0; i < DEPTH; i++)
        n += (size_t)snprintf(deep + n, cap - n, i + 1 < DEPTH ? "{\"children\":[%d]}," : "{}",
                              i + 1);
    n += (size_t)snprintf(deep + n, cap - n, "]}");
    expect_clean_failure("gltf-deep", deep, n);
    free(deep);

    /* one triangle's accessors over a buffer that claims a terabyte, then
     * one whose accessor claims 2e9 vertices, then one read from /etc */
    static const char *const variants[][2] = {
        {"gltf-bytelength", "\"buffers\":[{\"uri\":\"data:application/octet-stream;base64,AAAA\","
                            "\"byteLength\":1000000000000}]"},
        {"gltf-count", "\"buffers\":[{\"uri\":\"data:application/octet-stream;base64,"
                       "AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA\",\"byteLength\":36}]"},
        {"gltf-uri-escape", "\"buffers\":[{\"uri\":\"../../../../../../../../etc/passwd\","
                            "\"byteLength\":36}]"},
    };
    for (size_t k = 0; k < sizeof variants / sizeof *variants; k++) {
        char doc[2048];
        unsigned count = k == 1 ? 2000000000u : 3u;
        int len = snprintf(doc, sizeof doc,
                           "{\"asset\":{\"version\":\"2.0\"},\"scene\":0,\"scenes\":[{\"nodes\":[0]}],"
                           "\"nodes\":[{\"mesh\":0}],\"meshes\":[{\"primitives\":[{\"attributes\":"
                           "{\"POSITION\":0}}]}],\"accessors\":[{\"bufferView\":0,"
                           "\"componentType\":5126,\"count\":%u,\"type\":\"VEC3\","
                           "\"min\":[0,0,0],\"max\":[1,1,0]}],\"bufferViews\":[{\"buffer\":0,"
                           "\"byteOffset\":0,\"byteLength\":36}],%s}",
                           count, variants[k][1]);
        expect_clean_failure(variants[k][0], doc, (size_t)len);
    }
}

/* After everything: serving at once, nothing corrupt. */
static void test_still_healthy(void **state)
{
    (void)state;
    double t0 = mr_now();
    http_result r = http(&D, "GET", "/healthz", NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    http_free(&r);
    assert_true(mr_now() - t0 < 1.0);
    fx_assert_store_intact(D.data);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_invalid_models),
        cmocka_unit_test(test_huge_counts),
        cmocka_unit_test(test_gltf_bombs),
        cmocka_unit_test(test_still_healthy),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
