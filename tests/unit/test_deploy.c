/*
 * test_deploy.c - the deployment files of docker/ (issue 18) agree with
 * the code they deploy. The image itself is not built by the tests (no
 * image registry to pull debian:bookworm from, and building takes minutes:
 * docs/scale.md says how it was built by hand here); what can drift is
 * checked:
 *   - every file the Dockerfile COPYs from the repository exists, the
 *     setup script takes the --build it is run with, and the local build
 *     tree is kept out of the image's context (.dockerignore);
 *   - every library microrayd and microray load directly (readelf NEEDED)
 *     is in a package the runtime stage installs (or in the base system);
 *   - every flag the Dockerfile, the compose file and the Kubernetes Jobs
 *     give microrayd or microray is one their usage text lists;
 *   - the YAML files parse (js-yaml, the schema test tools' copy), the
 *     compose service builds this Dockerfile, and the frames Job is an
 *     Indexed Job whose pods render --frames.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

static char src[2048], build[2048];

static char *slurp(const char *path)
{
    FILE *f = fopen(path, "rb");
    if (!f)
        fail_msg("%s: cannot read", path);
    fseek(f, 0, SEEK_END);
    long n = ftell(f);
    fseek(f, 0, SEEK_SET);
    char *s = malloc((size_t)n + 1);
    size_t got = fread(s, 1, (size_t)n, f);
    s[got] = '\0';
    fclose(f);
    return s;
}

/* A command's stdout and stderr together (malloc'ed); its exit status in *status. */
static char *capture(int *status, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
static char *capture(int *status, const char *fmt, ...)
{
    char cmd[4096];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(cmd, sizeof cmd, fmt, ap);
    va_end(ap);
    char all[4200];
    snprintf(all, sizeof all, "{ %s; } 2>&1", cmd);
    FILE *p = popen(all, "r");
    assert_non_null(p);
    size_t cap = 1 << 16, len = 0;
    char *out = malloc(cap);
    size_t n;
    while ((n = fread(out + len, 1, cap - len - 1, p)) > 0) {
        len += n;
        if (cap - len < 1024)
            out = realloc(out, cap *= 2);
    }
    out[len] = '\0';
    int st = pclose(p);
    if (status)
        *status = WIFEXITED(st) ? WEXITSTATUS(st) : -1;
    return out;
}

static char *file_text(const char *rel)
{
    char path[4200];
    snprintf(path, sizeof path, "%s/%s", src, rel);
    return slurp(path);
}

static void test_dockerfile_copies_what_exists(void **state)
{
    (void)state;
    char *d = file_text("docker/Dockerfile");
    int copies = 0;
    for (char *line = d; line; line = strchr(line, '\n') ? strchr(line, '\n') + 1 : NULL) {
        if (strncmp(line, "COPY ", 5) != 0 || strncmp(line, "COPY --from", 11) == 0)
            continue;
        char from[512];
        assert_int_equal(sscanf(line + 5, "%511s", from), 1);
        char path[4200];
        snprintf(path, sizeof path, "%s/%s", src, from);
        struct stat st;
        if (stat(path, &st) != 0)
            fail_msg("the Dockerfile copies %s, which is not in the repository", from);
        copies++;
    }
    assert_true(copies >= 2);
    assert_non_null(strstr(d, "bash scripts/setup.sh --build"));
    /* the image builds its own binaries: a local build tree must not be
     * copied in (make would find it up to date) */
    char *ignore = file_text(".dockerignore");
    assert_non_null(strstr(ignore, "\nbuild\n"));
    free(ignore);
    int status;
    free(capture(&status, "bash '%s/scripts/setup.sh' --no-such-mode", src));
    assert_int_equal(status, 2); /* it reads its arguments: --build is one */
    char *setup = file_text("scripts/setup.sh");
    assert_non_null(strstr(setup, "--build) BUILD_ONLY=1"));
    free(setup);
    free(d);
}

/* The package a library file comes from (dpkg -S), "" if none. */
static void package_of(const char *lib, char *pkg, size_t size)
{
    int status;
    char *where = capture(&status, "ldconfig -p | awk '$1 == \"%s\" && /x86-64|x86_64/ {print $NF; exit}'", lib);
    where[strcspn(where, "\n")] = '\0';
    pkg[0] = '\0';
    if (where[0]) {
        /* dpkg knows a file by the path its package installed it at: the
         * one ldconfig names, its target, or either without a merged /usr */
        char *owner = capture(&status, "p='%s'; r=$(readlink -f \"$p\"); dpkg -S \"$p\" || "
                                       "dpkg -S \"$r\" || dpkg -S \"${p#/usr}\" || dpkg -S \"${r#/usr}\"",
                              where);
        /* the first line that names a package ("libc6:amd64: /path") */
        for (char *l = owner; status == 0 && l && *l; l = strchr(l, '\n') ? strchr(l, '\n') + 1 : NULL)
            if (strstr(l, ": /") && strncmp(l, "dpkg-query", 10) != 0) {
                snprintf(pkg, size, "%.*s", (int)strcspn(l, ":"), l);
                break;
            }
        free(owner);
    }
    free(where);
}

static void test_runtime_stage_has_every_library(void **state)
{
    (void)state;
    char *d = file_text("docker/Dockerfile");
    const char *runtime = strstr(d, "FROM debian:bookworm\n");
    assert_non_null(runtime); /* the second stage */
    static const char *const base[] = {"libc6", "libgcc-s1", "libstdc++6", "zlib1g", NULL};
    const char *bins[] = {"microrayd", "microray"};
    int libs = 0;
    for (int b = 0; b < 2; b++) {
        int status;
        char *needed = capture(&status, "readelf -d '%s/%s' | sed -n 's/.*Shared library: \\[\\(.*\\)\\]/\\1/p'",
                               build, bins[b]);
        assert_int_equal(status, 0);
        for (char *lib = strtok(needed, "\n"); lib; lib = strtok(NULL, "\n")) {
            /* a sanitizer build's runtimes (make check) are not the image's */
            if (!strncmp(lib, "libasan", 7) || !strncmp(lib, "libubsan", 8))
                continue;
            char pkg[256];
            package_of(lib, pkg, sizeof pkg);
            if (!pkg[0])
                fail_msg("%s needs %s, which no Debian package here provides", bins[b], lib);
            bool in_base = false;
            for (const char *const *p = base; *p; p++)
                in_base |= strcmp(pkg, *p) == 0;
            char word[300];
            snprintf(word, sizeof word, " %s ", pkg);
            /* the runtime stage's apt-get line lists it (space-separated) */
            char *list = strstr(runtime, "apt-get install");
            char *end = list ? strstr(list, "&& rm") : NULL;
            assert_non_null(end);
            char *copy = strndup(list, (size_t)(end - list));
            for (char *c = copy; *c; c++)
                if (*c == '\n' || *c == '\\')
                    *c = ' ';
            bool listed = strstr(copy, word) != NULL;
            free(copy);
            if (!in_base && !listed)
                fail_msg("%s loads %s from %s, which the Dockerfile's runtime stage does not install",
                         bins[b], lib, pkg);
            libs++;
        }
        free(needed);
    }
    print_message("[ deploy   ] %d direct libraries of microrayd and microray, each installed\n", libs);
    free(d);
}

/* Every "--flag" of text after a mention of a microrayd command word must
 * be in that command's usage. */
static void check_flags(const char *file, const char *text)
{
    int status;
    char *usage = capture(&status, "'%s/microrayd' serve --no-such-flag; '%s/microrayd' render; "
                                   "'%s/microrayd' stats-merge; '%s/microray' --help",
                          build, build, build, build);
    int checked = 0;
    for (const char *p = text; (p = strstr(p, "--")) != NULL; p += 2) {
        if (p > text && (p[-1] != ' ' && p[-1] != '"' && p[-1] != '[' && p[-1] != '\n'))
            continue;
        /* lines that run other programs: the setup script, apt-get */
        const char *line = p;
        while (line > text && line[-1] != '\n')
            line--;
        size_t line_len = strcspn(line, "\n");
        char *l = strndup(line, line_len);
        bool other = strstr(l, "setup.sh") || strstr(l, "apt-get");
        free(l);
        if (other)
            continue;
        char flag[64];
        size_t n = strspn(p + 2, "abcdefghijklmnopqrstuvwxyz-");
        if (n == 0 || n > 40 || p[2] < 'a' || p[2] > 'z') /* not a flag: "---", "-- " */
            continue;
        snprintf(flag, sizeof flag, "--%.*s", (int)n, p + 2);
        /* docker's own flags in the comments and HEALTHCHECK options */
        static const char *const docker[] = {"--from", "--interval", "--timeout", "--start-period",
                                             "--retries", "--system", "--uid", "--home-dir",
                                             "--shell", NULL};
        bool skip = false;
        for (const char *const *d = docker; *d; d++)
            skip |= strcmp(flag, *d) == 0;
        if (skip)
            continue;
        /* the whole flag, not a longer one it begins */
        bool listed = false;
        size_t fl = strlen(flag);
        for (const char *u = usage; !listed && (u = strstr(u, flag)) != NULL; u += fl)
            listed = !strchr("abcdefghijklmnopqrstuvwxyz-", u[fl]) || u[fl] == '\0';
        if (!listed)
            fail_msg("%s gives %s, which no microrayd or microray usage lists", file, flag);
        checked++;
    }
    assert_true(checked > 0);
    free(usage);
}

static void test_flags_are_real(void **state)
{
    (void)state;
    const char *files[] = {"docker/Dockerfile", "docker/compose.yaml", "docker/render-frames-job.yaml"};
    for (size_t i = 0; i < 3; i++) {
        char *t = file_text(files[i]);
        /* only the lines that run microray's programs, and the flags around them */
        check_flags(files[i], strstr(t, "microrayd") ? t : "");
        free(t);
    }
}

static void test_yaml_files(void **state)
{
    (void)state;
    int status;
    char *out = capture(
        &status,
        "cd '%s' && node -e \"\n"
        "const yaml = require('./tests/schema/node_modules/js-yaml');\n"
        "const fs = require('fs');\n"
        "const compose = yaml.safeLoad(fs.readFileSync('docker/compose.yaml', 'utf8'));\n"
        "const s = compose.services.microrayd;\n"
        "if (!s || s.build.dockerfile !== 'docker/Dockerfile' || s.build.context !== '..') throw 'compose: build';\n"
        "if (!fs.existsSync(require('path').join('docker', s.build.context, s.build.dockerfile))) throw 'compose: no Dockerfile';\n"
        "if (!s.command.includes('--listen') || !s.ports[0].startsWith('127.0.0.1:')) throw 'compose: listen';\n"
        "const jobs = yaml.safeLoadAll(fs.readFileSync('docker/render-frames-job.yaml', 'utf8'));\n"
        "const byName = Object.fromEntries(jobs.map(j => [j.metadata.name, j]));\n"
        "const frames = byName['microray-frames'];\n"
        "if (!frames || frames.kind !== 'Job' || frames.spec.completionMode !== 'Indexed') throw 'frames job';\n"
        "if (!frames.spec.template.spec.containers[0].args[0].includes('--frames')) throw 'frames args';\n"
        "if (!byName['microray-prepare'].spec.template.spec.containers[0].args.includes('--prepare')) throw 'prepare';\n"
        "if (byName['microray-merge'].spec.template.spec.containers[0].args[0] !== 'stats-merge') throw 'merge';\n"
        "console.log('yaml ok', jobs.length);\"",
        src);
    if (status != 0 || !strstr(out, "yaml ok 3"))
        fail_msg("the YAML files: %s", out);
    free(out);
}

static int setup(void **state)
{
    (void)state;
    const char *s = getenv("MR_SOURCE_DIR"), *b = getenv("MR_BUILD_DIR");
    snprintf(src, sizeof src, "%s", s ? s : ".");
    snprintf(build, sizeof build, "%s", b ? b : "build");
    return 0;
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_dockerfile_copies_what_exists),
        cmocka_unit_test(test_runtime_stage_has_every_library),
        cmocka_unit_test(test_flags_are_real),
        cmocka_unit_test(test_yaml_files),
    };
    return cmocka_run_group_tests(tests, setup, NULL);
}
