/*
 * test_cli.c - the command lines and their packaging (issue 19):
 *   - `microrayd --help` lists every flag the commands' parsers know (the
 *     flags are read from the server's sources), each command's --help prints to
 *     standard output and exits 0, and the same for `microray`;
 *   - the manual pages both programs print (make man) pass groff's
 *     warnings and hold every flag of --help; the bash completions parse
 *     and complete;
 *   - `make install DESTDIR=... PREFIX=/usr`: binaries that run, man pages,
 *     completions, the example jobs and a sandboxed systemd unit that
 *     systemd-analyze verifies;
 *   - `--json` on every client command gives JSON on standard output;
 *   - Ctrl-C during `submit --wait` says how to follow the job again, which
 *     goes on on the server.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <cJSON.h>

#include "daemon_fixture.h"

static daemon_proc D;

/* Every "--flag" string literal of a source file (after prefix, when it
 * is not ""), into flags (space separated). */
static void source_flags_after(const char *rel, const char *prefix, char *flags, size_t size)
{
    char path[2200], needle[64];
    snprintf(path, sizeof path, "%s/%s", fx_src_dir, rel);
    snprintf(needle, sizeof needle, "%s\"--", prefix);
    char *src = fx_slurp(path, NULL);
    assert_non_null(src);
    size_t skip = strlen(prefix);
    for (const char *q = src; (q = strstr(q, needle)); q++) {
        const char *p = q + skip;
        size_t n = strspn(p + 1, "-abcdefghijklmnopqrstuvwxyz");
        if (n > 2 && p[1 + n] == '"') {
            char flag[64];
            snprintf(flag, sizeof flag, " %.*s ", (int)n, p + 1);
            if (!strstr(flags, flag) && strlen(flags) + strlen(flag) + 1 < size)
                strcat(flags, flag + 1);
        }
    }
    free(src);
}

static void source_flags(const char *rel, char *flags, size_t size)
{
    source_flags_after(rel, "", flags, size);
}

/* Each flag of the space-separated list occurs in text as a word. */
static void flags_in(const char *flags, const char *text, const char *where)
{
    char copy[4096];
    snprintf(copy, sizeof copy, "%s", flags);
    for (char *f = strtok(copy, " "); f; f = strtok(NULL, " ")) {
        bool found = false;
        for (const char *p = text; !found && (p = strstr(p, f)); p++) {
            char after = p[strlen(f)];
            found = !(after == '-' || (after >= 'a' && after <= 'z'));
        }
        if (!found)
            fail_msg("%s does not mention %s", where, f);
    }
}

static void test_help_lists_every_flag(void **state)
{
    (void)state;
    char cmd[3000], *all = NULL, *out = NULL;
    snprintf(cmd, sizeof cmd, "'%s/microrayd' --help", fx_build_dir);
    assert_int_equal(fx_run(cmd, &all), 0);
    char flags[4096] = "";
    source_flags("server/serve_cmd.c", flags, sizeof flags);
    source_flags("server/render_cmd.c", flags, sizeof flags);
    source_flags("server/schema_gen.c", flags, sizeof flags);
    assert_non_null(strstr(flags, "--per-ip-connections"));
    flags_in(flags, all, "microrayd --help");
    static const char *const commands[] = {"render", "plan", "stats-merge", "compare", "serve", "schema",
                                           "version", "help"};
    for (size_t i = 0; i < sizeof commands / sizeof *commands; i++) {
        snprintf(cmd, sizeof cmd, "'%s/microrayd' %s --help 2>/dev/null", fx_build_dir, commands[i]);
        int st = fx_run(cmd, &out);
        if (st != 0 || !strstr(out, "usage:") || !strstr(out, commands[i]))
            fail_msg("microrayd %s --help: exit %d, '%s'", commands[i], st, out);
        free(out);
    }
    snprintf(cmd, sizeof cmd, "'%s/microrayd' serve --help", fx_build_dir);
    assert_int_equal(fx_run(cmd, &out), 0);
    char serve_flags[4096] = "";
    source_flags("server/serve_cmd.c", serve_flags, sizeof serve_flags);
    flags_in(serve_flags, out, "microrayd serve --help");
    free(out);
    free(all);

    /* the client: every option its sources know, in --help; each command's --help */
    snprintf(cmd, sizeof cmd, "'%s/microray' --help", fx_build_dir);
    assert_int_equal(fx_run(cmd, &all), 0);
    char cflags[4096] = "";
    source_flags("client/usage.c", cflags, sizeof cflags);
    source_flags("client/main.c", cflags, sizeof cflags);
    /* cluster.c passes flags to Slurm too: only those it compares with */
    source_flags_after("client/cluster.c", "strcmp(opt, ", cflags, sizeof cflags);
    assert_non_null(strstr(cflags, "--partition"));
    flags_in(cflags, all, "microray --help");
    static const char *const ccommands[] = {"submit", "status", "list", "wait", "fetch", "cancel", "retry",
                                            "delete", "upload", "health", "cluster submit",
                                            "cluster status", "cluster wait"};
    for (size_t i = 0; i < sizeof ccommands / sizeof *ccommands; i++) {
        snprintf(cmd, sizeof cmd, "'%s/microray' %s --help 2>/dev/null", fx_build_dir, ccommands[i]);
        int st = fx_run(cmd, &out);
        if (st != 0 || !strstr(out, "usage:") || !strstr(out, ccommands[i]))
            fail_msg("microray %s --help: exit %d, '%s'", ccommands[i], st, out);
        free(out);
    }
    free(all);
}

/* Man pages and completions, as make man / make install builds them. */
static void test_man_pages_and_completion(void **state)
{
    (void)state;
    static const char *const progs[] = {"microrayd", "microray"};
    for (size_t i = 0; i < 2; i++) {
        char cmd[6000], *man = NULL, *help = NULL, *warn = NULL;
        snprintf(cmd, sizeof cmd, "'%s/%s' man", fx_build_dir, progs[i]);
        assert_int_equal(fx_run(cmd, &man), 0);
        /* groff's warnings of every kind: none */
        snprintf(cmd, sizeof cmd, "'%s/%s' man | groff -man -ww -z 2>&1", fx_build_dir, progs[i]);
        assert_int_equal(fx_run(cmd, &warn), 0);
        if (warn[0])
            fail_msg("groff warns about %s.1: %s", progs[i], warn);
        /* every flag of --help is in the page (written \-\- in roff) */
        snprintf(cmd, sizeof cmd, "'%s/%s' man | groff -man -Tascii -P-cbou 2>/dev/null", fx_build_dir,
                 progs[i]);
        char *page = NULL;
        assert_int_equal(fx_run(cmd, &page), 0);
        snprintf(cmd, sizeof cmd, "'%s/%s' --help", fx_build_dir, progs[i]);
        assert_int_equal(fx_run(cmd, &help), 0);
        char flags[4096] = "";
        for (const char *p = help; (p = strstr(p, "--")); p += 2) {
            size_t n = strspn(p + 2, "-abcdefghijklmnopqrstuvwxyz");
            char flag[64];
            snprintf(flag, sizeof flag, " --%.*s ", (int)n, p + 2);
            if (n > 1 && !strstr(flags, flag) && strlen(flags) + strlen(flag) < sizeof flags)
                strcat(flags, flag + 1);
        }
        char where[64];
        snprintf(where, sizeof where, "the manual page %s.1", progs[i]);
        flags_in(flags, page, where);
        free(page);
        free(man);
        free(help);
        free(warn);
        /* the completion parses and completes a command's options */
        char comp[600];
        snprintf(comp, sizeof comp, "%s/%s.bash", fx_tmp, progs[i]);
        snprintf(cmd, sizeof cmd, "'%s/%s' completion > '%s' && bash -n '%s'", fx_build_dir, progs[i], comp,
                 comp);
        assert_int_equal(fx_run(cmd, NULL), 0);
    }
    char cmd[6000], *out = NULL;
    snprintf(cmd, sizeof cmd,
             "bash -c 'source \"%s/microray.bash\"; COMP_WORDS=(microray list --st); COMP_CWORD=2; "
             "_microray; echo \"${COMPREPLY[@]}\"'",
             fx_tmp);
    assert_int_equal(fx_run(cmd, &out), 0);
    assert_non_null(strstr(out, "--state"));
    free(out);
    snprintf(cmd, sizeof cmd,
             "bash -c 'source \"%s/microrayd.bash\"; COMP_WORDS=(microrayd serve --asset); COMP_CWORD=2; "
             "_microrayd; echo \"${COMPREPLY[@]}\"'",
             fx_tmp);
    assert_int_equal(fx_run(cmd, &out), 0);
    assert_non_null(strstr(out, "--asset-root"));
    free(out);
}

/* make install into a DESTDIR: what it installs works. */
static void test_make_install(void **state)
{
    (void)state;
    char dest[600], cmd[6000], *out = NULL;
    snprintf(dest, sizeof dest, "%s/destdir", fx_tmp);
    /* make install builds what is out of date, with the flags of its own
     * command line: in build/check (sanitizers) that would relink the
     * binaries the other tests run without them. Sources edited since this
     * tree was built are not what this test is about. */
    char query[8400];
    snprintf(query, sizeof query, "make -s -q -C '%s' BUILD='%s' '%s/microrayd' '%s/microray'",
             fx_src_dir, fx_build_dir, fx_build_dir, fx_build_dir);
    if (fx_run(query, NULL) != 0) {
        print_message("skipped: %s is older than the sources (make install would rebuild it)\n",
                      fx_build_dir);
        skip();
    }
    snprintf(cmd, sizeof cmd, "make -s -C '%s' install BUILD='%s' DESTDIR='%s' PREFIX=/usr 2>&1", fx_src_dir,
             fx_build_dir, dest);
    if (fx_run(cmd, &out) != 0)
        fail_msg("make install: %s", out);
    free(out);
    static const char *const files[] = {
        "usr/bin/microrayd", "usr/bin/microray", "usr/share/man/man1/microrayd.1",
        "usr/share/man/man1/microray.1", "usr/share/bash-completion/completions/microrayd",
        "usr/share/bash-completion/completions/microray", "usr/lib/systemd/system/microrayd.service",
        "usr/share/microray/microrayd.default", "usr/share/microray/examples/skinned-walk.json"};
    for (size_t i = 0; i < sizeof files / sizeof *files; i++) {
        char path[1200];
        snprintf(path, sizeof path, "%s/%s", dest, files[i]);
        struct stat sb;
        if (stat(path, &sb) != 0)
            fail_msg("make install left no %s", files[i]);
    }
    snprintf(cmd, sizeof cmd, "'%s/usr/bin/microrayd' version && '%s/usr/bin/microray' --version", dest, dest);
    assert_int_equal(fx_run(cmd, &out), 0);
    free(out);
    /* an installed example that names a model beside it (models/...,
     * relative to the job) finds it */
    snprintf(cmd, sizeof cmd,
             "'%s/usr/bin/microrayd' render --prepare '%s/usr/share/microray/examples/displaced-sphere.json' "
             "--out '%s/installed-out' --cache '%s/installed-cache' --quiet 2>&1",
             dest, dest, fx_tmp, fx_tmp);
    if (fx_run(cmd, &out) != 0)
        fail_msg("the installed displaced-sphere.json: %s", out);
    free(out);
    /* the unit: sandboxed, the installed binary, and systemd finds nothing
     * wrong with it (its ExecStart pointed into the DESTDIR for the check) */
    char unit[1200];
    snprintf(unit, sizeof unit, "%s/usr/lib/systemd/system/microrayd.service", dest);
    char *text = fx_slurp(unit, NULL);
    static const char *const wanted[] = {"DynamicUser=yes", "StateDirectory=microray", "ProtectSystem=strict",
                                         "NoNewPrivileges=yes", "ExecStart=/usr/bin/microrayd serve --data ${STATE_DIRECTORY}",
                                         "KillSignal=SIGTERM"};
    for (size_t i = 0; i < sizeof wanted / sizeof *wanted; i++)
        if (!strstr(text, wanted[i]))
            fail_msg("microrayd.service lacks %s", wanted[i]);
    assert_null(strstr(text, "@BINDIR@"));
    free(text);
    snprintf(cmd, sizeof cmd,
             "mkdir -p '%s/verify' && sed 's|ExecStart=/usr/bin/microrayd|ExecStart=%s/usr/bin/microrayd|' "
             "'%s' > '%s/verify/microrayd.service' && cd '%s/verify' && "
             "systemd-analyze verify --man=no ./microrayd.service 2>&1",
             fx_tmp, dest, unit, fx_tmp, fx_tmp);
    if (fx_run(cmd, &out) != 0)
        fail_msg("systemd-analyze verify: %s", out);
    free(out);
    /* every flag the unit's example options give, serve knows */
    snprintf(cmd, sizeof cmd, "'%s/usr/bin/microrayd' serve --asset-root /usr/share/assimp/models "
             "--listen 127.0.0.1:70000 2>&1", dest);
    assert_int_equal(fx_run(cmd, &out), 2); /* a bad port: usage error, so the flag before was taken */
    free(out);
    snprintf(cmd, sizeof cmd, "make -s -C '%s' uninstall BUILD='%s' DESTDIR='%s' PREFIX=/usr && "
             "test -z \"$(find '%s' -type f)\"", fx_src_dir, fx_build_dir, dest, dest);
    assert_int_equal(fx_run(cmd, NULL), 0);
}

/* --json on every client command: one JSON document on standard output. */
static void test_client_json(void **state)
{
    (void)state;
    char job_path[600], model[600], out_dir[600], cmd[8192];
    snprintf(job_path, sizeof job_path, "%s/cli-job.json", fx_tmp);
    snprintf(model, sizeof model, "%s/model.bin", fx_tmp);
    snprintf(out_dir, sizeof out_dir, "%s/cli-out", fx_tmp);
    char *job = fx_small_job(1, 40, NULL);
    FILE *f = fopen(job_path, "w");
    fputs(job, f);
    fclose(f);
    free(job);
    f = fopen(model, "w");
    fputs("not a model, only bytes", f);
    fclose(f);
    char id[64] = "";
    struct {
        const char *args;
        int exit;
        const char *key; /* a member the JSON must have */
    } cases[] = {
        {"submit '%s' --json", 0, "location"},
        {"submit '%s' --wait --json", 0, "frame_states"},
        {"status %s --json", 0, "state"},
        {"list --limit 1 --json", 0, "jobs"},
        {"wait %s --json", 0, "finished_at"},
        {"fetch %s --out '%s' --json", 0, "frames_fetched"},
        {"retry %s --json", 3, NULL}, /* a succeeded job: 409, no JSON */
        {"upload '%s' --json", 0, "id"},
        {"health --json", 0, "readyz"},
        {"status 123 --json", 3, NULL}, /* an id of the right characters the server does not know: 404 */
        {"delete %s --json", 0, "deleted"},
    };
    for (size_t i = 0; i < sizeof cases / sizeof *cases; i++) {
        char args[2000];
        if (i < 2)
            snprintf(args, sizeof args, cases[i].args, job_path);
        else if (strstr(cases[i].args, "--out"))
            snprintf(args, sizeof args, cases[i].args, id, out_dir);
        else if (strstr(cases[i].args, "upload"))
            snprintf(args, sizeof args, cases[i].args, model);
        else
            snprintf(args, sizeof args, cases[i].args, id);
        snprintf(cmd, sizeof cmd, "'%s/microray' --server %s --quiet %s 2>/dev/null", fx_build_dir, D.base, args);
        char *out = NULL;
        int st = fx_run(cmd, &out);
        if (st != cases[i].exit)
            fail_msg("microray %s: exit %d, want %d: %s", args, st, cases[i].exit, out);
        if (cases[i].key) {
            cJSON *doc = cJSON_Parse(out);
            if (!doc || !cJSON_GetObjectItem(doc, cases[i].key))
                fail_msg("microray %s: not JSON with \"%s\": %s", args, cases[i].key, out);
            if (i == 1)
                snprintf(id, sizeof id, "%s", cJSON_GetObjectItem(doc, "id")->valuestring);
            cJSON_Delete(doc);
        } else {
            assert_string_equal(out, "");
        }
        free(out);
    }
}

/* Ctrl-C while following: exit 130, the job goes on, and the message says
 * how to follow it again. */
static void test_interrupt_says_how_to_resume(void **state)
{
    (void)state;
    char job_path[600], log[600];
    snprintf(job_path, sizeof job_path, "%s/long.json", fx_tmp);
    snprintf(log, sizeof log, "%s/interrupt.log", fx_tmp);
    char *job = fx_small_job(400, 160, NULL);
    FILE *f = fopen(job_path, "w");
    fputs(job, f);
    fclose(f);
    free(job);
    pid_t pid = fork();
    if (pid == 0) {
        setpgid(0, 0);
        FILE *o = freopen(log, "w", stdout);
        FILE *e = freopen(log, "a", stderr);
        (void)o, (void)e;
        char bin[2200];
        snprintf(bin, sizeof bin, "%s/microray", fx_build_dir);
        execl(bin, "microray", "--server", D.base, "submit", job_path, "--wait", (char *)NULL);
        _exit(127);
    }
    /* once the id is out and a frame is done, the client is following */
    char id[64] = "";
    for (int i = 0; i < 600 && !id[0]; i++) {
        char *text = fx_slurp(log, NULL);
        if (text && strspn(text, "0123456789abcdef") == 32)
            snprintf(id, sizeof id, "%.32s", text);
        free(text);
        if (!id[0])
            fx_sleep_ms(50);
    }
    assert_int_equal(strlen(id), 32);
    fx_wait_frames_done(&D, id, 1);
    kill(-pid, SIGINT);
    int st = 0;
    waitpid(pid, &st, 0);
    assert_true(WIFEXITED(st) && WEXITSTATUS(st) == 130);
    char *text = fx_slurp(log, NULL), want[128];
    snprintf(want, sizeof want, "microray wait %s", id);
    if (!strstr(text, want))
        fail_msg("no '%s' in: %s", want, text);
    free(text);
    /* the job went on */
    char path[128];
    snprintf(path, sizeof path, "/v1/jobs/%s/cancel", id);
    http_result r = http(&D, "POST", path, "", 0, NULL);
    assert_int_equal(r.status, 202);
    http_free(&r);
}

static int setup(void **state)
{
    (void)state;
    curl_global_init(CURL_GLOBAL_DEFAULT);
    fx_init_dirs();
    daemon_start(&D, "data");
    return 0;
}

/* The cluster commands read their options as every command does
 * (docs/client.md): "--name=VALUE" as "--name VALUE", "--" ends the
 * options, and an option of another command is refused. Each line stops
 * at a usage error (exit 2) that shows how far the parser got, before
 * anything reaches Slurm. */
static void test_cluster_options(void **state)
{
    (void)state;
    static const struct {
        const char *args, *says;
    } cases[] = {
        /* --chunk=0 read as --chunk with the value 0 */
        {"cluster submit --slurm job.json --out=/nonexistent --chunk=0", "--chunk wants a positive number"},
        {"cluster submit --slurm --threads=300 job.json", "--threads wants 1..256"},
        {"cluster submit --slurm=yes job.json", "takes no value"},
        {"cluster submit --slurm job.json --out", "needs a value"},
        /* after --, a name starting with - is the job, and a second one too many */
        {"cluster submit --slurm --chunk 2 -- -job.json --out", "unexpected argument '--out'"},
        {"cluster status --threads 2 /nonexistent", "unknown option '--threads' for cluster status"},
        {"cluster wait", "needs the job's output folder (DIR)"},
        {"cluster nosuch", "unknown cluster command 'nosuch'"},
    };
    for (size_t i = 0; i < sizeof cases / sizeof *cases; i++) {
        char cmd[3000], err[700];
        snprintf(err, sizeof err, "%s/cluster.err", fx_tmp);
        snprintf(cmd, sizeof cmd, "'%s/microray' %s 2>'%s'", fx_build_dir, cases[i].args, err);
        const int st = fx_run(cmd, NULL);
        char *said = fx_slurp(err, NULL);
        if (st != 2 || !said || !strstr(said, cases[i].says))
            fail_msg("microray %s: exit %d, '%s' (wanted 2 and '%s')", cases[i].args, st, said ? said : "",
                     cases[i].says);
        free(said);
    }
}

static int teardown(void **state)
{
    (void)state;
    int st = daemon_stop(&D, SIGTERM);
    if (!fx_cleanup_dirs())
        return -1;
    return st == 0 ? 0 : -1;
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_help_lists_every_flag),
        cmocka_unit_test(test_man_pages_and_completion),
        cmocka_unit_test(test_make_install),
        cmocka_unit_test(test_cluster_options),
        cmocka_unit_test(test_client_json),
        cmocka_unit_test(test_interrupt_says_how_to_resume),
    };
    return cmocka_run_group_tests_name("cli", tests, setup, teardown);
}
