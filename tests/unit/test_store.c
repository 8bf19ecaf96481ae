/*
 * test_store.c - the durable store (server/store.c) and SHA-256
 * (core/util/sha256.c).
 *
 * SHA-256 is checked against the FIPS 180-4 / NIST example vectors ("",
 * "abc", the 448- and 896-bit messages, one million 'a'), against lengths
 * around the padding boundaries, and with one message fed in pieces split
 * at every position and at block-straddling sizes: the digest must not
 * depend on how the bytes arrive.
 *
 * The store tests use a real sqlite file in a fresh mkdtemp directory per
 * test (removed afterwards): job life cycle, claim order, frame files that
 * exist before their rows say done, retries, retry of failed jobs, recovery
 * after a process killed with SIGKILL in the middle of a job, idempotency
 * keys, deletion of rows and files, content-addressed assets and the ids
 * their paths accept, counts, a 100,000-frame job (its timings are printed,
 * never asserted: machines differ) and four threads claiming at once.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <pthread.h>
#include <signal.h>
#include <sqlite3.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "util/clock.h"
#include "util/hex.h"
#include "util/sha256.h"
#include "store.h"

/* ---- helpers ---------------------------------------------------------------- */

/* Removes a directory tree (the test directories are at most three deep). */
static void rm_rf(const char *path)
{
    struct stat sb;
    if (lstat(path, &sb) != 0)
        return;
    if (S_ISDIR(sb.st_mode)) {
        DIR *d = opendir(path);
        struct dirent *e;
        while (d && (e = readdir(d)) != NULL) {
            if (strcmp(e->d_name, ".") == 0 || strcmp(e->d_name, "..") == 0)
                continue;
            char sub[4096];
            snprintf(sub, sizeof sub, "%s/%s", path, e->d_name);
            rm_rf(sub);
        }
        if (d)
            closedir(d);
        rmdir(path);
    } else {
        unlink(path);
    }
}

static bool exists(const char *path)
{
    struct stat sb;
    return stat(path, &sb) == 0;
}

static size_t count_entries(const char *dir, const char *containing)
{
    DIR *d = opendir(dir);
    if (!d)
        return 0;
    size_t n = 0;
    struct dirent *e;
    while ((e = readdir(d)) != NULL) {
        if (strcmp(e->d_name, ".") == 0 || strcmp(e->d_name, "..") == 0)
            continue;
        if (!containing || strstr(e->d_name, containing))
            n++;
    }
    closedir(d);
    return n;
}

static char *read_whole(const char *path, size_t *size)
{
    FILE *f = fopen(path, "rb");
    if (!f)
        return NULL;
    fseek(f, 0, SEEK_END);
    long n = ftell(f);
    fseek(f, 0, SEEK_SET);
    char *buf = malloc((size_t)n + 1);
    assert_non_null(buf);
    size_t got = fread(buf, 1, (size_t)n, f);
    fclose(f);
    buf[got] = '\0';
    *size = got;
    return buf;
}

typedef struct fixture {
    char dir[256];
    mr_store *st;
} fixture;

static int setup(void **state)
{
    fixture *fx = calloc(1, sizeof *fx);
    if (!fx)
        return -1;
    const char *tmp = getenv("TMPDIR");
    snprintf(fx->dir, sizeof fx->dir, "%s/test_store.XXXXXX", tmp && *tmp ? tmp : "/tmp");
    if (!mkdtemp(fx->dir)) {
        free(fx);
        return -1;
    }
    mr_error err = {0};
    if (mr_store_open(fx->dir, &fx->st, &err) != MR_OK) {
        fprintf(stderr, "open: %s\n", err.msg);
        rm_rf(fx->dir);
        free(fx);
        return -1;
    }
    *state = fx;
    return 0;
}

static int teardown(void **state)
{
    fixture *fx = *state;
    mr_store_close(fx->st);
    rm_rf(fx->dir);
    free(fx);
    return 0;
}

static void create_job(mr_store *st, const char *name, size_t frames, int priority,
                       int max_retries, char id[MR_JOB_ID_LEN + 1])
{
    char json[128];
    snprintf(json, sizeof json, "{\"name\":\"%s\"}", name);
    bool existing = true;
    mr_error err = {0};
    int rc = mr_store_job_create(st, json, strlen(json), name, frames, priority, max_retries,
                                 NULL, NULL, id, &existing, &err);
    if (rc != MR_OK)
        fail_msg("create %s: %s", name, err.msg);
    assert_false(existing);
}

static mr_job_record get_job(mr_store *st, const char *id)
{
    mr_job_record r;
    mr_error err = {0};
    int rc = mr_store_job_get(st, id, &r, &err);
    if (rc != MR_OK)
        fail_msg("get %s: %s", id, err.msg);
    return r;
}

static void ok(int rc, const mr_error *err)
{
    if (rc < 0)
        fail_msg("%s: %s", mr_err_name(rc), err->msg);
}

/* ---- SHA-256 ---------------------------------------------------------------- */

static void check_hex(const char *msg, size_t len, const char *expect)
{
    char hex[65];
    mr_sha256_hex(msg, len, hex);
    assert_string_equal(hex, expect);
}

static void test_sha256_nist_vectors(void **state)
{
    (void)state;
    check_hex("", 0, "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
    check_hex(NULL, 0, "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
    check_hex("abc", 3, "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
    const char *m448 = "abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq";
    assert_int_equal(strlen(m448) * 8, 448);
    check_hex(m448, strlen(m448),
              "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1");
    const char *m896 = "abcdefghbcdefghicdefghijdefghijkefghijklfghijklmghijklmnhijklmno"
                       "ijklmnopjklmnopqklmnopqrlmnopqrsmnopqrstnopqrstu";
    assert_int_equal(strlen(m896) * 8, 896);
    check_hex(m896, strlen(m896),
              "cf5b16a778af8380036ce59e7b0492370b249b11e8f07a51afac45037afee9d1");

    /* One million 'a', once in one call and once in 1000-byte updates. */
    const char *million = "cdc76e5c9914fb9281a1c7e284d73e67f1809a48a497200e046d39ccc7112cd0";
    char *a = malloc(1000000);
    assert_non_null(a);
    memset(a, 'a', 1000000);
    check_hex(a, 1000000, million);
    mr_sha256 s;
    uint8_t d[32];
    char hex[65];
    mr_sha256_init(&s);
    for (int i = 0; i < 1000; i++)
        mr_sha256_update(&s, a, 1000);
    mr_sha256_final(&s, d);
    mr_hex_encode(d, 32, hex);
    assert_string_equal(hex, million);
    free(a);
}

/* Lengths around the padding boundaries: 55 bytes is the longest message
 * whose length field fits in its last block, 56 the first that needs an
 * extra block. Expected digests from coreutils sha256sum. */
static void test_sha256_padding_boundaries(void **state)
{
    (void)state;
    static const struct {
        size_t n;
        const char *hex;
    } cases[] = {
        {55, "9f4390f8d30c2dd92ec9f095b65e2b9ae9b0a925a5258e241c9f1e910f734318"},
        {56, "b35439a4ac6f0948b6d6f9e3c6af0f5f590ce20f1bde7090ef7970686ec6738a"},
        {63, "7d3e74a05d7db15bce4ad9ec0658ea98e3f06eeecf16b4c6fff2da457ddc2f34"},
        {64, "ffe054fe7ae0cb6dc65c3af9b61d5209f439851db43d0ba5997337df154668eb"},
        {65, "635361c48bb9eab14198e76ea8ab7f1a41685d6ad62aa9146d301d4f17eb0ae0"},
        {119, "31eba51c313a5c08226adf18d4a359cfdfd8d2e816b13f4af952f7ea6584dcfb"},
        {120, "2f3d335432c70b580af0e8e1b3674a7c020d683aa5f73aaaedfdc55af904c21c"},
        {127, "c57e9278af78fa3cab38667bef4ce29d783787a2f731d4e12200270f0c32320a"},
        {128, "6836cf13bac400e9105071cd6af47084dfacad4e5e302c94bfed24e013afb73e"},
    };
    char a[128];
    memset(a, 'a', sizeof a);
    for (size_t i = 0; i < sizeof cases / sizeof *cases; i++)
        check_hex(a, cases[i].n, cases[i].hex);
}

/* A 1000-byte pseudo-random message fed in pieces. Expected digest from
 * coreutils sha256sum over the same bytes. */
static void test_sha256_split_updates(void **state)
{
    (void)state;
    const char *expect = "3fec874244848bfca7c32ea872a9449045e958ee839d5b32f9cbfe3e855e1739";
    uint8_t msg[1000];
    for (int i = 0; i < 1000; i++)
        msg[i] = (uint8_t)(((i * 131 + 7) ^ (i >> 3)) & 255);
    check_hex((const char *)msg, sizeof msg, expect);

    mr_sha256 s;
    uint8_t d[32];
    char hex[65];
    /* Every two-way split, including empty first and last pieces. */
    for (size_t cut = 0; cut <= sizeof msg; cut++) {
        mr_sha256_init(&s);
        mr_sha256_update(&s, msg, cut);
        mr_sha256_update(&s, msg + cut, sizeof msg - cut);
        mr_sha256_final(&s, d);
        mr_hex_encode(d, 32, hex);
        if (strcmp(hex, expect) != 0)
            fail_msg("split at %zu: %s", cut, hex);
    }
    /* Repeating piece sizes that straddle block edges in every phase, with
     * empty updates in between. */
    static const size_t pieces[] = {1, 3, 7, 55, 56, 63, 64, 65, 127, 128, 129, 200};
    for (size_t p = 0; p < sizeof pieces / sizeof *pieces; p++) {
        mr_sha256_init(&s);
        for (size_t off = 0; off < sizeof msg;) {
            size_t n = pieces[p] < sizeof msg - off ? pieces[p] : sizeof msg - off;
            mr_sha256_update(&s, msg + off, n);
            mr_sha256_update(&s, msg + off, 0);
            off += n;
        }
        mr_sha256_final(&s, d);
        mr_hex_encode(d, 32, hex);
        if (strcmp(hex, expect) != 0)
            fail_msg("pieces of %zu: %s", pieces[p], hex);
    }
    /* Mixed sizes: 1, 62, 1, 64, 65, ... */
    static const size_t mix[] = {1, 62, 1, 64, 65, 0, 63, 2, 130, 55, 9, 64};
    mr_sha256_init(&s);
    size_t off = 0;
    for (size_t i = 0; off < sizeof msg; i = (i + 1) % (sizeof mix / sizeof *mix)) {
        size_t n = mix[i] < sizeof msg - off ? mix[i] : sizeof msg - off;
        mr_sha256_update(&s, msg + off, n);
        off += n;
    }
    mr_sha256_final(&s, d);
    mr_hex_encode(d, 32, hex);
    assert_string_equal(hex, expect);
}

/* ---- store: basics ---------------------------------------------------------- */

static void test_state_names(void **state)
{
    (void)state;
    for (int s = MR_JOB_QUEUED; s <= MR_JOB_CANCELED; s++) {
        mr_job_state back;
        assert_true(mr_job_state_parse(mr_job_state_name((mr_job_state)s), &back));
        assert_int_equal(back, s);
    }
    assert_string_equal(mr_job_state_name(MR_JOB_CANCELED), "canceled");
    assert_string_equal(mr_frame_state_name(MR_FRAME_DONE), "done");
    mr_job_state x;
    assert_false(mr_job_state_parse("Queued", &x));
    assert_false(mr_job_state_parse("", &x));
    assert_false(mr_job_state_parse(NULL, &x));
    assert_string_equal(mr_job_state_name((mr_job_state)42), "unknown");
}

static void test_open_schema(void **state)
{
    fixture *fx = *state;
    assert_string_equal(mr_store_dir(fx->st), fx->dir);
    char path[512];
    snprintf(path, sizeof path, "%s/assets", fx->dir);
    assert_true(exists(path));
    snprintf(path, sizeof path, "%s/frames", fx->dir);
    assert_true(exists(path));

    /* A second connection sees WAL mode and the schema version. */
    snprintf(path, sizeof path, "%s/microray.sqlite", fx->dir);
    sqlite3 *db = NULL;
    assert_int_equal(sqlite3_open_v2(path, &db, SQLITE_OPEN_READWRITE, NULL), SQLITE_OK);
    sqlite3_stmt *s = NULL;
    assert_int_equal(sqlite3_prepare_v2(db, "PRAGMA journal_mode", -1, &s, NULL), SQLITE_OK);
    assert_int_equal(sqlite3_step(s), SQLITE_ROW);
    assert_string_equal((const char *)sqlite3_column_text(s, 0), "wal");
    sqlite3_finalize(s);
    assert_int_equal(sqlite3_prepare_v2(db, "PRAGMA user_version", -1, &s, NULL), SQLITE_OK);
    assert_int_equal(sqlite3_step(s), SQLITE_ROW);
    assert_int_equal(sqlite3_column_int(s, 0), 4);
    sqlite3_finalize(s);

    /* A newer schema is refused instead of being misread. */
    mr_store_close(fx->st);
    fx->st = NULL;
    assert_int_equal(sqlite3_exec(db, "PRAGMA user_version = 99", NULL, NULL, NULL), SQLITE_OK);
    sqlite3_close(db);
    mr_error err = {0};
    mr_store *st = NULL;
    assert_int_equal(mr_store_open(fx->dir, &st, &err), MR_ERR_FORMAT);
    assert_null(st);
    assert_non_null(strstr(err.msg, "99"));

    /* Not a database at all. */
    char dir2[300];
    snprintf(dir2, sizeof dir2, "%s/other", fx->dir);
    assert_int_equal(mkdir(dir2, 0755), 0);
    snprintf(path, sizeof path, "%s/microray.sqlite", dir2);
    FILE *f = fopen(path, "wb");
    assert_non_null(f);
    for (int i = 0; i < 4096; i++)
        fputc("garbage!"[i % 8], f);
    fclose(f);
    assert_int_equal(mr_store_open(dir2, &st, &err), MR_ERR_FORMAT);
    assert_non_null(strstr(err.msg, "not a database"));

    /* The data directory is a regular file. */
    assert_int_equal(mr_store_open(path, &st, &err), MR_ERR_IO);
    assert_non_null(strstr(err.msg, path));
    assert_int_equal(mr_store_open("", &st, &err), MR_ERR_INVALID);

    /* Reopen the fixture's directory for teardown, with the version put back. */
    snprintf(path, sizeof path, "%s/microray.sqlite", fx->dir);
    assert_int_equal(sqlite3_open_v2(path, &db, SQLITE_OPEN_READWRITE, NULL), SQLITE_OK);
    assert_int_equal(sqlite3_exec(db, "PRAGMA user_version = 4", NULL, NULL, NULL), SQLITE_OK);
    sqlite3_close(db);
    ok(mr_store_open(fx->dir, &fx->st, &err), &err);
}

/* How many jobs the fixture's database lists as deleted with their
 * folders maybe still on disk (deleted_jobs). */
static int deleted_listed(const fixture *fx)
{
    char path[512];
    snprintf(path, sizeof path, "%s/microray.sqlite", fx->dir);
    sqlite3 *db = NULL;
    sqlite3_stmt *s = NULL;
    int n = -1;
    if (sqlite3_open_v2(path, &db, SQLITE_OPEN_READONLY, NULL) == SQLITE_OK &&
        sqlite3_prepare_v2(db, "SELECT count(*) FROM deleted_jobs", -1, &s, NULL) == SQLITE_OK &&
        sqlite3_step(s) == SQLITE_ROW)
        n = sqlite3_column_int(s, 0);
    sqlite3_finalize(s);
    sqlite3_close(db);
    return n;
}

/* The fixture's database as an older version wrote it: the store closed,
 * sql (what later versions added, taken away, and the old version number)
 * run on the file, the store opened again (which upgrades it). */
static void reopen_as(fixture *fx, const char *sql)
{
    mr_store_close(fx->st);
    fx->st = NULL;
    char path[512];
    snprintf(path, sizeof path, "%s/microray.sqlite", fx->dir);
    sqlite3 *db = NULL;
    assert_int_equal(sqlite3_open_v2(path, &db, SQLITE_OPEN_READWRITE, NULL), SQLITE_OK);
    assert_int_equal(sqlite3_exec(db, sql, NULL, NULL, NULL), SQLITE_OK);
    sqlite3_close(db);
    mr_error err = {0};
    ok(mr_store_open(fx->dir, &fx->st, &err), &err);
}

/* What version 4 added, taken away again: a file as version 3 wrote it. */
#define UNDO_V4 "DROP TABLE deleted_jobs; "
/* What versions 3 and 4 added: a file as version 2 wrote it. */
#define UNDO_V3                                                                                    \
    UNDO_V4 "DROP TABLE job_assets; ALTER TABLE assets DROP COLUMN last_used; "                    \
            "ALTER TABLE jobs DROP COLUMN done_seq; ALTER TABLE frames DROP COLUMN done_seq; "

/* A version-3 file (before deleted jobs were listed) is upgraded in place:
 * its jobs stay, and a delete lists and forgets as in a new file. */
static void test_schema_upgrade_from_v3(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    char job[MR_JOB_ID_LEN + 1];
    create_job(fx->st, "old", 2, 0, 0, job);
    ok(mr_store_frame_done(fx->st, job, 0, "exr", 3, "{}", &err), &err);
    reopen_as(fx, UNDO_V4 "PRAGMA user_version = 3");
    assert_int_equal(get_job(fx->st, job).frames_done, 1);
    ok(mr_store_job_delete(fx->st, job, &err), &err);
    char dir[512];
    snprintf(dir, sizeof dir, "%s/frames/%s", fx->dir, job);
    assert_false(exists(dir));
    assert_int_equal(deleted_listed(fx), 0); /* forgotten once its folder is gone */
}

/* A version-1 file (before crash-loop protection) is upgraded in place:
 * its jobs stay, and the new count works on them. */
static void test_schema_upgrade_from_v1(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    char job[MR_JOB_ID_LEN + 1];
    create_job(fx->st, "old", 2, 0, 0, job);
    reopen_as(fx, UNDO_V3 "ALTER TABLE jobs DROP COLUMN interrupted; PRAGMA user_version = 1");
    assert_string_equal(get_job(fx->st, job).name, "old");
    char id[MR_JOB_ID_LEN + 1];
    ok(mr_store_job_claim(fx->st, id, &err), &err);
    ok(mr_store_recover(fx->st, &err), &err); /* max_retries 0: one interrupted start fails it */
    assert_int_equal(get_job(fx->st, job).state, MR_JOB_FAILED);
}

/* A version-2 file is upgraded in place: its jobs and done frames stay,
 * frames done from then on are numbered in order, and its assets can be
 * used and deleted. */
static void test_schema_upgrade_from_v2(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    char job[MR_JOB_ID_LEN + 1], asset[MR_ASSET_ID_LEN + 1];
    bool existed;
    create_job(fx->st, "old", 3, 0, 0, job);
    ok(mr_store_frame_done(fx->st, job, 0, "exr", 3, "{}", &err), &err);
    ok(mr_store_asset_put(fx->st, "bytes", 5, asset, &existed, &err), &err);
    reopen_as(fx, UNDO_V3 "PRAGMA user_version = 2");
    mr_job_record r = get_job(fx->st, job);
    assert_int_equal(r.frames_done, 1);
    assert_true(r.done_seq == 0); /* frames done before the upgrade have no number */
    ok(mr_store_frame_done(fx->st, job, 2, "exr", 3, "{}", &err), &err);
    assert_true(get_job(fx->st, job).done_seq == 1);
    mr_frame_done_record *after = NULL;
    size_t n = 0;
    ok(mr_store_frames_after(fx->st, job, 0, 0, &after, &n, &err), &err);
    assert_int_equal(n, 1);
    assert_int_equal(after[0].index, 2);
    mr_frame_done_records_free(after, n);
    mr_asset_record a;
    ok(mr_store_asset_get(fx->st, asset, &a, &err), &err);
    assert_true(a.size == 5 && a.last_used == 0 && a.jobs_active == 0);
    ok(mr_store_asset_delete(fx->st, asset, &err), &err);
}

/* Uploaded assets used by jobs: in use while a job that names them is
 * queued or running (not deleted then), free again once it ended; the list
 * pages newest first. */
static void test_asset_use_list_delete(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    char a[MR_ASSET_ID_LEN + 1], b[MR_ASSET_ID_LEN + 1], job[MR_JOB_ID_LEN + 1];
    bool existed, existing;
    ok(mr_store_asset_put(fx->st, "first", 5, a, &existed, &err), &err);
    ok(mr_store_asset_put(fx->st, "second", 6, b, &existed, &err), &err);
    const char *ids[] = {a, a}; /* one asset under two names */
    ok(mr_store_job_create_using(fx->st, "{}", 2, "uses", 1, 0, 0, NULL, NULL, ids, 2, job, &existing,
                                 &err), &err);
    mr_asset_record r;
    ok(mr_store_asset_get(fx->st, a, &r, &err), &err);
    assert_int_equal(r.jobs_active, 1);
    assert_true(r.last_used > 0);
    assert_int_equal(mr_store_asset_delete(fx->st, a, &err), MR_ERR_CONFLICT);
    assert_non_null(strstr(err.msg, "used by 1 queued or running job"));
    mr_asset_record *list = NULL;
    size_t n = 0;
    int64_t next = 0;
    ok(mr_store_asset_list(fx->st, 0, 1, &list, &n, &next, &err), &err);
    assert_int_equal(n, 1);
    assert_string_equal(list[0].id, b);
    assert_true(next > 0);
    free(list);
    ok(mr_store_asset_list(fx->st, next, 1, &list, &n, &next, &err), &err);
    assert_int_equal(n, 1);
    assert_string_equal(list[0].id, a);
    assert_true(next == 0);
    free(list);
    /* the job ends: the asset is free */
    ok(mr_store_job_set_state(fx->st, job, MR_JOB_CANCELED, NULL, &err), &err);
    ok(mr_store_asset_delete(fx->st, a, &err), &err);
    assert_int_equal(mr_store_asset_get(fx->st, a, &r, &err), MR_ERR_NOT_FOUND);
    assert_int_equal(mr_store_asset_delete(fx->st, a, &err), MR_ERR_NOT_FOUND);
    /* a job naming an asset that is gone is refused, and nothing is stored */
    const char *gone[] = {a};
    assert_int_equal(mr_store_job_create_using(fx->st, "{}", 2, "late", 1, 0, 0, NULL, NULL, gone, 1,
                                               job, &existing, &err),
                     MR_ERR_NOT_FOUND);
    mr_job_record *jobs = NULL;
    ok(mr_store_job_list(fx->st, &(mr_job_query){.name = "late"}, &jobs, &n, NULL, &err), &err);
    assert_int_equal(n, 0);
    free(jobs);
}

static void test_create_get_list_filter(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    char a[MR_JOB_ID_LEN + 1], b[MR_JOB_ID_LEN + 1], c[MR_JOB_ID_LEN + 1];
    create_job(fx->st, "alpha", 3, 0, 2, a);
    create_job(fx->st, "beta", 1, 7, 0, b);
    create_job(fx->st, "gamma", 5, -3, 4, c);

    /* 32 lowercase hex digits, all different. */
    assert_int_equal(strlen(a), MR_JOB_ID_LEN);
    assert_int_equal(strspn(a, "0123456789abcdef"), MR_JOB_ID_LEN);
    assert_string_not_equal(a, b);
    assert_string_not_equal(b, c);

    mr_job_record r = get_job(fx->st, a);
    assert_string_equal(r.id, a);
    assert_string_equal(r.name, "alpha");
    assert_int_equal(r.state, MR_JOB_QUEUED);
    assert_int_equal(r.priority, 0);
    assert_int_equal(r.max_retries, 2);
    assert_int_equal(r.frame_count, 3);
    assert_int_equal(r.frames_done, 0);
    assert_int_equal(r.frames_failed, 0);
    assert_true(r.created > 1.6e9);
    assert_true(r.started == 0.0 && r.finished == 0.0);
    assert_string_equal(r.error, "");

    char *json = NULL;
    ok(mr_store_job_json(fx->st, c, &json, &err), &err);
    assert_string_equal(json, "{\"name\":\"gamma\"}");
    free(json);

    mr_job_record *list = NULL;
    size_t n = 0;
    ok(mr_store_job_list(fx->st, &(mr_job_query){0}, &list, &n, NULL, &err), &err);
    assert_int_equal(n, 3);
    /* newest first */
    assert_string_equal(list[0].id, c);
    assert_string_equal(list[1].id, b);
    assert_string_equal(list[2].id, a);
    assert_int_equal(list[0].frame_count, 5);
    free(list);

    ok(mr_store_job_set_state(fx->st, b, MR_JOB_RUNNING, NULL, &err), &err);
    ok(mr_store_job_list(fx->st, &(mr_job_query){.by_state = true, .state = MR_JOB_QUEUED}, &list, &n, NULL, &err), &err);
    assert_int_equal(n, 2);
    assert_string_equal(list[0].id, c);
    assert_string_equal(list[1].id, a);
    free(list);
    ok(mr_store_job_list(fx->st, &(mr_job_query){.by_state = true, .state = MR_JOB_RUNNING}, &list, &n, NULL, &err), &err);
    assert_int_equal(n, 1);
    assert_string_equal(list[0].id, b);
    free(list);
    ok(mr_store_job_list(fx->st, &(mr_job_query){.by_state = true, .state = MR_JOB_FAILED}, &list, &n, NULL, &err), &err);
    assert_int_equal(n, 0);
    free(list);

    /* pages: limit, the cursor of the next page, and the last page's 0 */
    int64_t next = -1;
    ok(mr_store_job_list(fx->st, &(mr_job_query){.limit = 2}, &list, &n, &next, &err), &err);
    assert_int_equal(n, 2);
    assert_string_equal(list[0].id, c);
    assert_string_equal(list[1].id, b);
    assert_true(next == list[1].seq && next > 0);
    free(list);
    ok(mr_store_job_list(fx->st, &(mr_job_query){.limit = 2, .before = next}, &list, &n, &next, &err),
       &err);
    assert_int_equal(n, 1);
    assert_string_equal(list[0].id, a);
    assert_true(next == 0);
    free(list);
    /* exactly a page's worth: no next page */
    ok(mr_store_job_list(fx->st, &(mr_job_query){.limit = 3}, &list, &n, &next, &err), &err);
    assert_int_equal(n, 3);
    assert_true(next == 0);
    free(list);
    /* by name, with the state */
    ok(mr_store_job_list(fx->st, &(mr_job_query){.name = "beta"}, &list, &n, NULL, &err), &err);
    assert_int_equal(n, 1);
    assert_string_equal(list[0].id, b);
    free(list);
    ok(mr_store_job_list(fx->st, &(mr_job_query){.name = "beta", .by_state = true, .state = MR_JOB_QUEUED},
                         &list, &n, NULL, &err), &err);
    assert_int_equal(n, 0);
    free(list);

    /* Unknown and malformed ids: NOT_FOUND naming the id. */
    const char *unknown = "0123456789abcdef0123456789abcdef";
    assert_int_equal(mr_store_job_get(fx->st, unknown, &r, &err), MR_ERR_NOT_FOUND);
    assert_int_equal(err.code, MR_ERR_NOT_FOUND);
    assert_non_null(strstr(err.msg, unknown));
    assert_int_equal(mr_store_job_get(fx->st, "../../etc/passwd", &r, &err), MR_ERR_NOT_FOUND);
    assert_non_null(strstr(err.msg, "../../etc/passwd"));
    assert_int_equal(mr_store_job_get(fx->st, NULL, &r, &err), MR_ERR_NOT_FOUND);
    char upper[MR_JOB_ID_LEN + 1];
    for (int i = 0; i <= MR_JOB_ID_LEN; i++)
        upper[i] = (char)(a[i] >= 'a' && a[i] <= 'f' ? a[i] - 32 : a[i]);
    if (strcmp(upper, a) != 0)
        assert_int_equal(mr_store_job_get(fx->st, upper, &r, &err), MR_ERR_NOT_FOUND);
    assert_int_equal(mr_store_job_json(fx->st, unknown, &json, &err), MR_ERR_NOT_FOUND);
    assert_null(json);
    assert_int_equal(mr_store_job_set_state(fx->st, unknown, MR_JOB_FAILED, "x", &err),
                     MR_ERR_NOT_FOUND);
    assert_non_null(strstr(err.msg, unknown));
    mr_frame_record *frames = NULL;
    assert_int_equal(mr_store_frames(fx->st, unknown, &frames, &n, &err), MR_ERR_NOT_FOUND);

    /* Long names are cut at 256 bytes, not inside a UTF-8 character. */
    char longname[400];
    memset(longname, 'x', 255);
    strcpy(longname + 255, "\xc3\xa9tail"); /* 'é' straddles byte 256 */
    char d[MR_JOB_ID_LEN + 1];
    bool existing;
    ok(mr_store_job_create(fx->st, "{}", 2, longname, 1, 0, 0, NULL, NULL, d, &existing, &err),
       &err);
    r = get_job(fx->st, d);
    assert_int_equal(strlen(r.name), 255);

    /* Bad arguments. */
    assert_int_equal(mr_store_job_create(fx->st, "{}", 2, "n", 1, 0, -1, NULL, NULL, d, &existing,
                                         &err),
                     MR_ERR_INVALID);
    assert_int_equal(mr_store_job_create(fx->st, "{}", 2, "n", (size_t)-1, 0, 0, NULL, NULL, d,
                                         &existing, &err),
                     MR_ERR_LIMIT);
    assert_int_equal(mr_store_job_set_state(fx->st, a, (mr_job_state)9, NULL, &err),
                     MR_ERR_INVALID);
}

static void test_set_state_times(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    char id[MR_JOB_ID_LEN + 1];
    create_job(fx->st, "t", 1, 0, 0, id);
    ok(mr_store_job_set_state(fx->st, id, MR_JOB_RUNNING, NULL, &err), &err);
    mr_job_record r = get_job(fx->st, id);
    assert_int_equal(r.state, MR_JOB_RUNNING);
    double started = r.started;
    assert_true(started >= r.created);
    assert_true(r.finished == 0.0);

    /* Back to queued and running again: started keeps the first time. */
    struct timespec pause = {0, 20 * 1000 * 1000};
    nanosleep(&pause, NULL);
    ok(mr_store_job_set_state(fx->st, id, MR_JOB_QUEUED, NULL, &err), &err);
    ok(mr_store_job_set_state(fx->st, id, MR_JOB_RUNNING, NULL, &err), &err);
    r = get_job(fx->st, id);
    assert_true(r.started == started);

    ok(mr_store_job_set_state(fx->st, id, MR_JOB_FAILED, "frame 0: out of memory", &err), &err);
    r = get_job(fx->st, id);
    assert_int_equal(r.state, MR_JOB_FAILED);
    assert_true(r.finished >= started);
    assert_string_equal(r.error, "frame 0: out of memory");
    /* NULL keeps the error; a string replaces it. */
    ok(mr_store_job_set_state(fx->st, id, MR_JOB_CANCELED, NULL, &err), &err);
    r = get_job(fx->st, id);
    assert_int_equal(r.state, MR_JOB_CANCELED);
    assert_string_equal(r.error, "frame 0: out of memory");
    ok(mr_store_job_set_state(fx->st, id, MR_JOB_SUCCEEDED, "", &err), &err);
    r = get_job(fx->st, id);
    assert_string_equal(r.error, "");
    assert_true(r.finished > 0.0);
}

static void test_claim_order(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    char id[MR_JOB_ID_LEN + 1];
    assert_int_equal(mr_store_job_claim(fx->st, id, &err), MR_ERR_NOT_FOUND);
    assert_string_equal(id, "");

    char a[33], b[33], c[33], d[33], e[33], running[33];
    create_job(fx->st, "a", 1, 0, 0, a);
    create_job(fx->st, "b", 1, 5, 0, b);
    create_job(fx->st, "running", 1, 100, 0, running);
    create_job(fx->st, "c", 1, 5, 0, c);
    create_job(fx->st, "d", 1, 0, 0, d);
    create_job(fx->st, "e", 1, -1, 0, e);
    /* Not queued: never claimed even with the highest priority. */
    ok(mr_store_job_set_state(fx->st, running, MR_JOB_RUNNING, NULL, &err), &err);

    const char *expect[] = {b, c, a, d, e};
    for (int i = 0; i < 5; i++) {
        ok(mr_store_job_claim(fx->st, id, &err), &err);
        assert_string_equal(id, expect[i]);
        mr_job_record r = get_job(fx->st, id);
        assert_int_equal(r.state, MR_JOB_RUNNING);
        assert_true(r.started > 0.0);
    }
    assert_int_equal(mr_store_job_claim(fx->st, id, &err), MR_ERR_NOT_FOUND);
}

/* ---- store: frames ---------------------------------------------------------- */

static void frame_file_path(const fixture *fx, const char *id, int index, char *out, size_t n)
{
    snprintf(out, n, "%s/frames/%s/%04d.exr", fx->dir, id, index);
}

static void test_frame_done(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    char id[33], path[512], got[512];
    create_job(fx->st, "f", 3, 0, 1, id);

    assert_int_equal(mr_store_frame_path(fx->st, id, 1, got, sizeof got, &err), MR_ERR_NOT_FOUND);
    ok(mr_store_frame_set_running(fx->st, id, 1, &err), &err);

    static const char exr[] = "v/1\001\0binary\377EXR bytes";
    const char *stats = "{\"frame\":1,\"seconds\":{\"total\":0.5}}";
    ok(mr_store_frame_done(fx->st, id, 1, exr, sizeof exr, stats, &err), &err);

    frame_file_path(fx, id, 1, path, sizeof path);
    size_t size = 0;
    char *bytes = read_whole(path, &size);
    assert_non_null(bytes);
    assert_int_equal(size, sizeof exr);
    assert_memory_equal(bytes, exr, sizeof exr);
    free(bytes);
    char dir[512];
    snprintf(dir, sizeof dir, "%s/frames/%s", fx->dir, id);
    assert_int_equal(count_entries(dir, ".tmp"), 0);

    ok(mr_store_frame_path(fx->st, id, 1, got, sizeof got, &err), &err);
    assert_string_equal(got, path);
    char tiny[8];
    assert_int_equal(mr_store_frame_path(fx->st, id, 1, tiny, sizeof tiny, &err), MR_ERR_INVALID);

    mr_frame_record *frames = NULL;
    size_t n = 0;
    ok(mr_store_frames(fx->st, id, &frames, &n, &err), &err);
    assert_int_equal(n, 3);
    for (size_t i = 0; i < n; i++)
        assert_int_equal(frames[i].index, i);
    assert_int_equal(frames[0].state, MR_FRAME_PENDING);
    assert_int_equal(frames[1].state, MR_FRAME_DONE);
    assert_string_equal(frames[1].stats_json, stats);
    assert_null(frames[0].stats_json);
    mr_frame_records_free(frames, n);
    mr_job_record r = get_job(fx->st, id);
    assert_int_equal(r.frames_done, 1);

    /* Unknown frame: refused before any file is written. */
    assert_int_equal(mr_store_frame_done(fx->st, id, 3, exr, sizeof exr, NULL, &err),
                     MR_ERR_NOT_FOUND);
    assert_non_null(strstr(err.msg, "frame 3"));
    frame_file_path(fx, id, 3, path, sizeof path);
    assert_false(exists(path));
    assert_int_equal(mr_store_frame_set_running(fx->st, id, 3, &err), MR_ERR_NOT_FOUND);

    /* A file that cannot be written leaves the row as it was: here the
     * frame's target name is taken by a directory, so the rename fails. */
    frame_file_path(fx, id, 2, path, sizeof path);
    assert_int_equal(mkdir(path, 0755), 0);
    char inner[600];
    snprintf(inner, sizeof inner, "%s/keep", path);
    FILE *f = fopen(inner, "w");
    assert_non_null(f);
    fclose(f);
    ok(mr_store_frame_set_running(fx->st, id, 2, &err), &err);
    assert_int_equal(mr_store_frame_done(fx->st, id, 2, exr, sizeof exr, stats, &err), MR_ERR_IO);
    assert_int_equal(err.code, MR_ERR_IO);
    assert_non_null(strstr(err.msg, path));
    ok(mr_store_frames(fx->st, id, &frames, &n, &err), &err);
    assert_int_equal(frames[2].state, MR_FRAME_RUNNING);
    assert_null(frames[2].stats_json);
    mr_frame_records_free(frames, n);
    assert_int_equal(count_entries(dir, ".tmp"), 0);
    assert_int_equal(mr_store_frame_path(fx->st, id, 2, got, sizeof got, &err), MR_ERR_NOT_FOUND);
    rm_rf(path);

    /* Zero bytes are a valid (if useless) file. */
    ok(mr_store_frame_done(fx->st, id, 0, NULL, 0, NULL, &err), &err);
    frame_file_path(fx, id, 0, path, sizeof path);
    assert_true(exists(path));
}

/* Two writers of one frame (a retry while a stuck attempt still writes, a
 * second daemon on the same data directory) must not share a temporary:
 * here the other writer holds the name the store used to write through
 * ("NNNN.exr.tmp") and keeps writing after this frame is done. The frame
 * file must hold exactly this write's bytes. */
static void test_frame_done_own_temporary(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    char id[33], dir[512], held[600], path[512];
    create_job(fx->st, "t", 2, 0, 0, id);
    snprintf(dir, sizeof dir, "%s/frames/%s", fx->dir, id);
    assert_int_equal(mkdir(dir, 0755), 0);
    snprintf(held, sizeof held, "%s/0001.exr.tmp", dir);
    FILE *other = fopen(held, "w");
    assert_non_null(other);
    static const char exr[] = "the complete frame";
    ok(mr_store_frame_set_running(fx->st, id, 1, &err), &err);
    ok(mr_store_frame_done(fx->st, id, 1, exr, sizeof exr, "{}", &err), &err);
    fputs("the other writer's bytes", other);
    fclose(other);
    frame_file_path(fx, id, 1, path, sizeof path);
    size_t size = 0;
    char *bytes = read_whole(path, &size);
    assert_non_null(bytes);
    assert_int_equal(size, sizeof exr);
    assert_memory_equal(bytes, exr, sizeof exr);
    free(bytes);
    /* its own temporary is gone; the other writer's is its business */
    assert_int_equal(count_entries(dir, ".tmp"), 1);
}

static void test_frame_failed_retries(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    char id[33];
    create_job(fx->st, "r", 2, 0, 2, id);
    bool gave_up = true;
    mr_frame_record *frames = NULL;
    size_t n = 0;
    /* max_retries 2: attempts 1 and 2 fail and go back to pending, the
     * third failure gives up. */
    for (int attempt = 1; attempt <= 3; attempt++) {
        ok(mr_store_frame_set_running(fx->st, id, 1, &err), &err);
        char msg[64];
        snprintf(msg, sizeof msg, "attempt %d failed", attempt);
        ok(mr_store_frame_failed(fx->st, id, 1, msg, false, &gave_up, &err), &err);
        ok(mr_store_frames(fx->st, id, &frames, &n, &err), &err);
        assert_int_equal(frames[1].retries, attempt);
        assert_string_equal(frames[1].error, msg);
        if (attempt < 3) {
            assert_false(gave_up);
            assert_int_equal(frames[1].state, MR_FRAME_PENDING);
        } else {
            assert_true(gave_up);
            assert_int_equal(frames[1].state, MR_FRAME_FAILED);
        }
        assert_int_equal(frames[0].state, MR_FRAME_PENDING);
        mr_frame_records_free(frames, n);
    }
    mr_job_record r = get_job(fx->st, id);
    assert_int_equal(r.frames_failed, 1);
    assert_int_equal(r.frames_done, 0);

    /* max_retries 0: the first failure is final. */
    char z[33];
    create_job(fx->st, "zero", 1, 0, 0, z);
    ok(mr_store_frame_failed(fx->st, z, 0, NULL, false, &gave_up, &err), &err);
    assert_true(gave_up);
    assert_int_equal(mr_store_frame_failed(fx->st, z, 5, "x", false, &gave_up, &err), MR_ERR_NOT_FOUND);
    assert_int_equal(mr_store_frame_failed(fx->st, "nope", 0, "x", false, &gave_up, &err),
                     MR_ERR_NOT_FOUND);

    /* A final failure (the same frame would fail the same way: over a
     * budget) gives up at once, retries left or not. */
    char f[33];
    create_job(fx->st, "final", 1, 0, 2, f);
    ok(mr_store_frame_failed(fx->st, f, 0, "over budget", true, &gave_up, &err), &err);
    assert_true(gave_up);
    mr_frame_record rec;
    ok(mr_store_frame_get(fx->st, f, 0, &rec, &err), &err);
    free(rec.stats_json);
    assert_int_equal(rec.state, MR_FRAME_FAILED);
    assert_int_equal(rec.retries, 1);
}

static void test_retry(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    char id[33];
    bool gave_up;
    create_job(fx->st, "retry", 4, 0, 0, id);
    ok(mr_store_job_claim(fx->st, id, &err), &err);
    /* Running: not retryable. */
    assert_int_equal(mr_store_job_retry(fx->st, id, &err), MR_ERR_CONFLICT);
    ok(mr_store_frame_done(fx->st, id, 0, "x", 1, NULL, &err), &err);
    ok(mr_store_frame_done(fx->st, id, 3, "x", 1, NULL, &err), &err);
    ok(mr_store_frame_failed(fx->st, id, 1, "boom", false, &gave_up, &err), &err);
    assert_true(gave_up);
    ok(mr_store_job_set_state(fx->st, id, MR_JOB_FAILED, "frame 1: boom", &err), &err);
    mr_job_record r = get_job(fx->st, id);
    assert_int_equal(r.frames_failed, 1);
    assert_int_equal(r.frames_done, 2);

    /* Frame 1 failed and frame 2 was never rendered: both go again. */
    int n = mr_store_job_retry(fx->st, id, &err);
    ok(n, &err);
    assert_int_equal(n, 2);
    r = get_job(fx->st, id);
    assert_int_equal(r.state, MR_JOB_QUEUED);
    assert_string_equal(r.error, "");
    assert_true(r.finished == 0.0);
    assert_int_equal(r.frames_failed, 0);
    assert_int_equal(r.frames_done, 2);
    mr_frame_record *frames = NULL;
    size_t count = 0;
    ok(mr_store_frames(fx->st, id, &frames, &count, &err), &err);
    assert_int_equal(frames[1].state, MR_FRAME_PENDING);
    assert_int_equal(frames[1].retries, 0);
    assert_string_equal(frames[1].error, "");
    assert_int_equal(frames[0].state, MR_FRAME_DONE);
    mr_frame_records_free(frames, count);

    /* Queued: conflict. */
    assert_int_equal(mr_store_job_retry(fx->st, id, &err), MR_ERR_CONFLICT);
    assert_non_null(strstr(err.msg, "queued"));

    /* Canceled with unfinished frames: allowed. */
    ok(mr_store_job_set_state(fx->st, id, MR_JOB_CANCELED, NULL, &err), &err);
    n = mr_store_job_retry(fx->st, id, &err);
    assert_int_equal(n, 2);

    /* Everything done: nothing to retry, and the job stays as it was. */
    ok(mr_store_frame_done(fx->st, id, 1, "x", 1, NULL, &err), &err);
    ok(mr_store_frame_done(fx->st, id, 2, "x", 1, NULL, &err), &err);
    ok(mr_store_job_set_state(fx->st, id, MR_JOB_FAILED, "odd", &err), &err);
    assert_int_equal(mr_store_job_retry(fx->st, id, &err), MR_ERR_CONFLICT);
    r = get_job(fx->st, id);
    assert_int_equal(r.state, MR_JOB_FAILED);
    assert_string_equal(r.error, "odd");
    ok(mr_store_job_set_state(fx->st, id, MR_JOB_SUCCEEDED, NULL, &err), &err);
    assert_int_equal(mr_store_job_retry(fx->st, id, &err), MR_ERR_CONFLICT);

    assert_int_equal(mr_store_job_retry(fx->st, "ffffffffffffffffffffffffffffffff", &err),
                     MR_ERR_NOT_FOUND);
}

/* ---- store: crash recovery -------------------------------------------------- */

/* The child renders half a job and is killed; it reports failures through
 * its exit status because cmocka's asserts belong to the parent. */
static void crash_child(const char *dir, const char *expect_id)
{
    mr_error err = {0};
    mr_store *st = NULL;
    if (mr_store_open(dir, &st, &err) != MR_OK)
        _exit(10);
    char id[33];
    if (mr_store_job_claim(st, id, &err) != MR_OK || strcmp(id, expect_id) != 0)
        _exit(11);
    for (size_t i = 0; i < 2; i++) {
        char bytes[16];
        snprintf(bytes, sizeof bytes, "frame %zu", i);
        if (mr_store_frame_set_running(st, id, i, &err) != MR_OK ||
            mr_store_frame_done(st, id, i, bytes, strlen(bytes), "{}", &err) != MR_OK)
            _exit(12);
    }
    if (mr_store_frame_set_running(st, id, 2, &err) != MR_OK)
        _exit(13);
    /* Half a frame file, as a crash mid-write leaves it (mr_fs_atomic's
     * temporary) */
    char tmp[512];
    snprintf(tmp, sizeof tmp, "%s/frames/%s/0002.exr.tmpQ1w2E3", dir, id);
    FILE *f = fopen(tmp, "w");
    if (f) {
        fputs("half", f);
        fclose(f);
    }
    raise(SIGKILL);
    _exit(14);
}

static void test_recover_after_crash(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    char job[33], waiting[33];
    create_job(fx->st, "crashy", 4, 1, 2, job);
    create_job(fx->st, "waiting", 2, 0, 2, waiting);
    /* An orphaned frame directory from a delete that never finished. */
    char orphan[512];
    snprintf(orphan, sizeof orphan, "%s/frames/00000000000000000000000000000abc", fx->dir);
    assert_int_equal(mkdir(orphan, 0755), 0);
    char orphan_file[600];
    snprintf(orphan_file, sizeof orphan_file, "%s/0000.exr", orphan);
    FILE *f = fopen(orphan_file, "w");
    assert_non_null(f);
    fclose(f);
    /* ... and a folder of a job this database never had (a database lost
     * or replaced): its frames must not be removed */
    char unknown[512], unknown_file[600];
    snprintf(unknown, sizeof unknown, "%s/frames/00000000000000000000000000000def", fx->dir);
    assert_int_equal(mkdir(unknown, 0755), 0);
    snprintf(unknown_file, sizeof unknown_file, "%s/0000.exr", unknown);
    assert_non_null(f = fopen(unknown_file, "w"));
    fclose(f);
    mr_store_close(fx->st);
    fx->st = NULL;
    /* the delete's commit listed the orphan's job (deleted_jobs) */
    char db_path[600];
    snprintf(db_path, sizeof db_path, "%s/microray.sqlite", fx->dir);
    sqlite3 *db = NULL;
    assert_int_equal(sqlite3_open(db_path, &db), SQLITE_OK);
    assert_int_equal(sqlite3_exec(db, "INSERT INTO deleted_jobs(id) VALUES ('00000000000000000000000000000abc')",
                                  NULL, NULL, NULL),
                     SQLITE_OK);
    sqlite3_close(db);

    fflush(NULL);
    pid_t pid = fork();
    assert_true(pid >= 0);
    if (pid == 0)
        crash_child(fx->dir, job);
    int status = 0;
    assert_int_equal(waitpid(pid, &status, 0), pid);
    if (!WIFSIGNALED(status))
        fail_msg("child exited with %d instead of being killed", WEXITSTATUS(status));
    assert_int_equal(WTERMSIG(status), SIGKILL);

    ok(mr_store_open(fx->dir, &fx->st, &err), &err);
    /* Before recovery the store shows what the dead process left. */
    mr_job_record r = get_job(fx->st, job);
    assert_int_equal(r.state, MR_JOB_RUNNING);
    assert_int_equal(r.frames_done, 2);

    int n = mr_store_recover(fx->st, &err);
    ok(n, &err);
    assert_int_equal(n, 1);
    r = get_job(fx->st, job);
    assert_int_equal(r.state, MR_JOB_QUEUED);
    assert_int_equal(r.frames_done, 2);
    assert_true(r.started > 0.0);
    r = get_job(fx->st, waiting);
    assert_int_equal(r.state, MR_JOB_QUEUED);

    mr_frame_record *frames = NULL;
    size_t count = 0;
    ok(mr_store_frames(fx->st, job, &frames, &count, &err), &err);
    assert_int_equal(count, 4);
    assert_int_equal(frames[0].state, MR_FRAME_DONE);
    assert_int_equal(frames[1].state, MR_FRAME_DONE);
    assert_int_equal(frames[2].state, MR_FRAME_PENDING);
    assert_int_equal(frames[3].state, MR_FRAME_PENDING);
    mr_frame_records_free(frames, count);
    /* Frames marked done have their complete files. */
    for (int i = 0; i < 2; i++) {
        char path[512], expect[32];
        ok(mr_store_frame_path(fx->st, job, (size_t)i, path, sizeof path, &err), &err);
        size_t size = 0;
        char *bytes = read_whole(path, &size);
        assert_non_null(bytes);
        snprintf(expect, sizeof expect, "frame %d", i);
        assert_string_equal(bytes, expect);
        free(bytes);
    }
    assert_false(exists(orphan));
    assert_true(exists(unknown_file));
    assert_int_equal(mr_store_unknown_frame_dirs(fx->st), 1);
    char stale[600];
    snprintf(stale, sizeof stale, "%s/frames/%s/0002.exr.tmpQ1w2E3", fx->dir, job);
    assert_false(exists(stale));

    /* The resumed job is claimed first again (priority 1), and the stale
     * temporary does not get in the way of the next attempt. */
    char id[33];
    ok(mr_store_job_claim(fx->st, id, &err), &err);
    assert_string_equal(id, job);
    ok(mr_store_frame_done(fx->st, job, 2, "whole", 5, NULL, &err), &err);
    char path[512];
    frame_file_path(fx, job, 2, path, sizeof path);
    size_t size = 0;
    char *bytes = read_whole(path, &size);
    assert_string_equal(bytes, "whole");
    free(bytes);

    /* A clean close without finishing behaves the same. */
    mr_store_close(fx->st);
    fx->st = NULL;
    ok(mr_store_open(fx->dir, &fx->st, &err), &err);
    n = mr_store_recover(fx->st, &err);
    assert_int_equal(n, 1);
    assert_int_equal(get_job(fx->st, job).state, MR_JOB_QUEUED);
    assert_int_equal(get_job(fx->st, job).frames_done, 3);
    /* Nothing left to recover. */
    assert_int_equal(mr_store_recover(fx->st, &err), 0);
}

/* Crash-loop protection: starts that died count, progress forgives them.
 * A close without finishing stands for the death (recovery cannot tell the
 * two apart, and test_recover_after_crash shows a real kill reads the same). */
static void reopen(fixture *fx)
{
    mr_error err = {0};
    mr_store_close(fx->st);
    fx->st = NULL;
    ok(mr_store_open(fx->dir, &fx->st, &err), &err);
    ok(mr_store_recover(fx->st, &err), &err);
}

static void test_recover_crash_loop(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    char id[MR_JOB_ID_LEN + 1];

    /* A frame that kills the process each time: max_retries 1 allows two
     * attempts; the second death fails the frame and the job. */
    char poison[MR_JOB_ID_LEN + 1];
    create_job(fx->st, "poison", 3, 0, 1, poison);
    for (int attempt = 1; attempt <= 2; attempt++) {
        ok(mr_store_job_claim(fx->st, id, &err), &err);
        assert_string_equal(id, poison);
        ok(mr_store_frame_set_running(fx->st, poison, 0, &err), &err);
        reopen(fx);
        mr_frame_record f;
        ok(mr_store_frame_get(fx->st, poison, 0, &f, &err), &err);
        free(f.stats_json);
        assert_int_equal(f.retries, attempt);
        assert_non_null(strstr(f.error, "the daemon stopped during this frame"));
        mr_job_record r = get_job(fx->st, poison);
        if (attempt == 1) {
            assert_int_equal(f.state, MR_FRAME_PENDING);
            assert_int_equal(r.state, MR_JOB_QUEUED);
        } else {
            assert_int_equal(f.state, MR_FRAME_FAILED);
            assert_int_equal(r.state, MR_JOB_FAILED);
            assert_non_null(strstr(r.error, "stopped 2 times in a row"));
            assert_true(r.finished > 0);
        }
    }
    assert_int_equal(mr_store_job_claim(fx->st, id, &err), MR_ERR_NOT_FOUND);

    /* Dying before any frame started (an import that kills the process)
     * counts too: max_retries 0 means the first death is final. */
    char setup_death[MR_JOB_ID_LEN + 1];
    create_job(fx->st, "import-crash", 2, 0, 0, setup_death);
    ok(mr_store_job_claim(fx->st, id, &err), &err);
    reopen(fx);
    mr_job_record r = get_job(fx->st, setup_death);
    assert_int_equal(r.state, MR_JOB_FAILED);
    assert_non_null(strstr(r.error, "stopped 1 times in a row"));
    /* a user's retry gives it a fresh count */
    assert_int_equal(mr_store_job_retry(fx->st, setup_death, &err), 2);
    assert_int_equal(get_job(fx->st, setup_death).state, MR_JOB_QUEUED);
    ok(mr_store_job_claim(fx->st, id, &err), &err);
    ok(mr_store_frame_done(fx->st, setup_death, 0, "x", 1, "{}", &err), &err);
    ok(mr_store_frame_done(fx->st, setup_death, 1, "x", 1, "{}", &err), &err);
    ok(mr_store_job_set_state(fx->st, setup_death, MR_JOB_SUCCEEDED, NULL, &err), &err);

    /* A job killed again and again but finishing a frame each time is
     * making progress and is never given up. */
    char slow[MR_JOB_ID_LEN + 1];
    create_job(fx->st, "progress", 6, 0, 0, slow);
    for (size_t i = 0; i < 5; i++) {
        ok(mr_store_job_claim(fx->st, id, &err), &err);
        assert_string_equal(id, slow);
        ok(mr_store_frame_set_running(fx->st, slow, i, &err), &err);
        ok(mr_store_frame_done(fx->st, slow, i, "x", 1, "{}", &err), &err);
        reopen(fx);
        r = get_job(fx->st, slow);
        assert_int_equal(r.state, MR_JOB_QUEUED);
        assert_int_equal(r.frames_done, i + 1);
        assert_int_equal(r.frames_failed, 0);
    }
    /* A graceful stop (the job put back to queued) counts nothing. */
    for (int k = 0; k < 3; k++) {
        ok(mr_store_job_claim(fx->st, id, &err), &err);
        ok(mr_store_job_set_state(fx->st, slow, MR_JOB_QUEUED, NULL, &err), &err);
        reopen(fx);
        assert_int_equal(get_job(fx->st, slow).state, MR_JOB_QUEUED);
    }
}

/* ---- store: idempotency, delete, assets, counts ------------------------------ */

static void test_idempotency(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    const char *body = "{\"job\":1}", *body2 = "{\"job\":2}";
    char h1[65], h2[65];
    mr_sha256_hex(body, strlen(body), h1);
    mr_sha256_hex(body2, strlen(body2), h2);
    char id1[33], id2[33], id3[33];
    bool existing = true;
    ok(mr_store_job_create(fx->st, body, strlen(body), "i", 2, 0, 1, "key-1", h1, id1, &existing,
                           &err),
       &err);
    assert_false(existing);
    ok(mr_store_job_create(fx->st, body, strlen(body), "i", 2, 0, 1, "key-1", h1, id2, &existing,
                           &err),
       &err);
    assert_true(existing);
    assert_string_equal(id1, id2);

    assert_int_equal(mr_store_job_create(fx->st, body2, strlen(body2), "i", 2, 0, 1, "key-1", h2,
                                         id3, &existing, &err),
                     MR_ERR_CONFLICT);
    assert_false(existing);
    assert_non_null(strstr(err.msg, "key-1"));

    uint64_t counts[5];
    ok(mr_store_job_counts(fx->st, counts, &err), &err);
    assert_int_equal(counts[MR_JOB_QUEUED], 1);

    /* Another key, or none, makes a new job. */
    ok(mr_store_job_create(fx->st, body, strlen(body), "i", 2, 0, 1, "key-2", h1, id3, &existing,
                           &err),
       &err);
    assert_false(existing);
    assert_string_not_equal(id3, id1);
    ok(mr_store_job_create(fx->st, body, strlen(body), "i", 2, 0, 1, NULL, NULL, id3, &existing,
                           &err),
       &err);
    assert_false(existing);

    /* Deleting the job frees its key. */
    ok(mr_store_job_delete(fx->st, id1, &err), &err);
    ok(mr_store_job_create(fx->st, body2, strlen(body2), "i", 2, 0, 1, "key-1", h2, id2,
                           &existing, &err),
       &err);
    assert_false(existing);
    assert_string_not_equal(id2, id1);
    assert_int_equal(mr_store_job_create(fx->st, body, strlen(body), "i", 2, 0, 1, "key-1", NULL,
                                         id2, &existing, &err),
                     MR_ERR_INVALID);
}

static void test_delete(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    char id[33], keep[33];
    create_job(fx->st, "del", 3, 0, 0, id);
    create_job(fx->st, "keep", 1, 0, 0, keep);
    ok(mr_store_frame_done(fx->st, id, 0, "zero", 4, "{}", &err), &err);
    ok(mr_store_frame_done(fx->st, id, 2, "two", 3, "{}", &err), &err);
    ok(mr_store_frame_done(fx->st, keep, 0, "k", 1, "{}", &err), &err);
    char dir[512], keep_file[512];
    snprintf(dir, sizeof dir, "%s/frames/%s", fx->dir, id);
    assert_int_equal(count_entries(dir, NULL), 2);
    /* A stray temporary is removed along with the frames. */
    char stray[600];
    snprintf(stray, sizeof stray, "%s/0001.exr.tmp", dir);
    FILE *f = fopen(stray, "w");
    assert_non_null(f);
    fclose(f);

    ok(mr_store_job_delete(fx->st, id, &err), &err);
    mr_job_record r;
    assert_int_equal(mr_store_job_get(fx->st, id, &r, &err), MR_ERR_NOT_FOUND);
    mr_frame_record *frames = NULL;
    size_t n = 99;
    assert_int_equal(mr_store_frames(fx->st, id, &frames, &n, &err), MR_ERR_NOT_FOUND);
    assert_null(frames);
    assert_int_equal(n, 0);
    assert_false(exists(dir));
    assert_int_equal(deleted_listed(fx), 0);
    assert_int_equal(mr_store_job_delete(fx->st, id, &err), MR_ERR_NOT_FOUND);
    assert_int_equal(mr_store_frame_done(fx->st, id, 0, "x", 1, NULL, &err), MR_ERR_NOT_FOUND);
    assert_false(exists(dir));

    /* No row of it is left behind in any table. */
    char path[512];
    snprintf(path, sizeof path, "%s/microray.sqlite", fx->dir);
    sqlite3 *db = NULL;
    assert_int_equal(sqlite3_open_v2(path, &db, SQLITE_OPEN_READONLY, NULL), SQLITE_OK);
    sqlite3_stmt *s = NULL;
    assert_int_equal(sqlite3_prepare_v2(db, "SELECT (SELECT COUNT(*) FROM frames WHERE job_id = ?1)"
                                            " + (SELECT COUNT(*) FROM jobs WHERE id = ?1)",
                                        -1, &s, NULL),
                     SQLITE_OK);
    sqlite3_bind_text(s, 1, id, -1, SQLITE_STATIC);
    assert_int_equal(sqlite3_step(s), SQLITE_ROW);
    assert_int_equal(sqlite3_column_int(s, 0), 0);
    sqlite3_finalize(s);
    sqlite3_close(db);

    /* The other job is untouched; a job without frame files deletes too. */
    frame_file_path(fx, keep, 0, keep_file, sizeof keep_file);
    assert_true(exists(keep_file));
    assert_int_equal(get_job(fx->st, keep).frames_done, 1);
    char bare[33];
    create_job(fx->st, "bare", 2, 0, 0, bare);
    ok(mr_store_job_delete(fx->st, bare, &err), &err);
    assert_int_equal(mr_store_job_delete(fx->st, "../frames", &err), MR_ERR_NOT_FOUND);
    snprintf(path, sizeof path, "%s/frames", fx->dir);
    assert_true(exists(path));
}

static void test_assets(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    const char data[] = "solid 4 bytes of mesh\0with a NUL";
    char id[MR_ASSET_ID_LEN + 1], expect[65], path[512];
    mr_sha256_hex(data, sizeof data, expect);
    bool existed = true;
    ok(mr_store_asset_put(fx->st, data, sizeof data, id, &existed, &err), &err);
    assert_false(existed);
    assert_string_equal(id, expect);

    ok(mr_store_asset_path(fx->st, id, path, sizeof path, &err), &err);
    char want[512];
    snprintf(want, sizeof want, "%s/assets/%s", fx->dir, id);
    assert_string_equal(path, want);
    size_t size = 0;
    char *bytes = read_whole(path, &size);
    assert_int_equal(size, sizeof data);
    assert_memory_equal(bytes, data, sizeof data);
    free(bytes);

    /* Same bytes: same id, reported as existing, still one file. */
    char id2[MR_ASSET_ID_LEN + 1];
    ok(mr_store_asset_put(fx->st, data, sizeof data, id2, &existed, &err), &err);
    assert_true(existed);
    assert_string_equal(id2, id);
    char adir[512];
    snprintf(adir, sizeof adir, "%s/assets", fx->dir);
    assert_int_equal(count_entries(adir, NULL), 1);

    /* Different bytes, and the empty asset. */
    ok(mr_store_asset_put(fx->st, "other", 5, id2, &existed, &err), &err);
    assert_false(existed);
    assert_string_not_equal(id2, id);
    ok(mr_store_asset_put(fx->st, NULL, 0, id2, &existed, &err), &err);
    assert_string_equal(id2, "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
    assert_int_equal(count_entries(adir, NULL), 3);
    assert_int_equal(count_entries(adir, "tmp"), 0);

    /* Only exact 64-digit lowercase hex ids are accepted. */
    char upper[65];
    for (int i = 0; i <= 64; i++)
        upper[i] = (char)(id[i] >= 'a' && id[i] <= 'f' ? id[i] - 32 : id[i]);
    char shorter[65];
    memcpy(shorter, id, 63);
    shorter[63] = '\0';
    char longer[67];
    snprintf(longer, sizeof longer, "%s0", id);
    char traversal[70];
    snprintf(traversal, sizeof traversal, "../../%.58s", id);
    const char *bad[] = {"../x", "..", "", "/etc/passwd", upper, shorter, longer, traversal,
                         "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b85g"};
    for (size_t i = 0; i < sizeof bad / sizeof *bad; i++) {
        strcpy(path, "unchanged");
        if (mr_store_asset_path(fx->st, bad[i], path, sizeof path, &err) != MR_ERR_NOT_FOUND)
            fail_msg("asset id '%s' was accepted", bad[i]);
        assert_int_equal(err.code, MR_ERR_NOT_FOUND);
        assert_string_equal(path, "");
    }
    assert_int_equal(mr_store_asset_path(fx->st, NULL, path, sizeof path, &err), MR_ERR_NOT_FOUND);
    /* Well-formed but unknown. */
    assert_int_equal(mr_store_asset_path(fx->st,
                                         "0000000000000000000000000000000000000000000000000000000000000000",
                                         path, sizeof path, &err),
                     MR_ERR_NOT_FOUND);

    /* A recorded asset whose file vanished is unknown until uploaded again. */
    unlink(want);
    assert_int_equal(mr_store_asset_path(fx->st, id, path, sizeof path, &err), MR_ERR_NOT_FOUND);
    ok(mr_store_asset_put(fx->st, data, sizeof data, id2, &existed, &err), &err);
    assert_true(existed);
    ok(mr_store_asset_path(fx->st, id, path, sizeof path, &err), &err);
    assert_true(exists(want));
}

static void test_job_counts(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    uint64_t counts[5] = {9, 9, 9, 9, 9};
    ok(mr_store_job_counts(fx->st, counts, &err), &err);
    for (int i = 0; i < 5; i++)
        assert_int_equal(counts[i], 0);
    char ids[7][33];
    for (int i = 0; i < 7; i++)
        create_job(fx->st, "c", 1, 0, 0, ids[i]);
    ok(mr_store_job_set_state(fx->st, ids[0], MR_JOB_RUNNING, NULL, &err), &err);
    ok(mr_store_job_set_state(fx->st, ids[1], MR_JOB_SUCCEEDED, NULL, &err), &err);
    ok(mr_store_job_set_state(fx->st, ids[2], MR_JOB_SUCCEEDED, NULL, &err), &err);
    ok(mr_store_job_set_state(fx->st, ids[3], MR_JOB_FAILED, "x", &err), &err);
    ok(mr_store_job_set_state(fx->st, ids[4], MR_JOB_CANCELED, NULL, &err), &err);
    ok(mr_store_job_counts(fx->st, counts, &err), &err);
    assert_int_equal(counts[MR_JOB_QUEUED], 2);
    assert_int_equal(counts[MR_JOB_RUNNING], 1);
    assert_int_equal(counts[MR_JOB_SUCCEEDED], 2);
    assert_int_equal(counts[MR_JOB_FAILED], 1);
    assert_int_equal(counts[MR_JOB_CANCELED], 1);
}

/* ---- store: scale and threads ------------------------------------------------ */

/* Timings are printed for the report, never asserted. */
static void test_large_job(void **state)
{
    fixture *fx = *state;
    mr_error err = {0};
    const size_t frames = 100000;
    char id[33];
    bool existing;
    double t0 = mr_now();
    ok(mr_store_job_create(fx->st, "{}", 2, "big", frames, 0, 2, NULL, NULL, id, &existing, &err),
       &err);
    double t_create = mr_now() - t0;

    mr_job_record r = get_job(fx->st, id);
    assert_int_equal(r.frame_count, frames);

    /* Frame writes: a small EXR-sized buffer, fsync and all. */
    enum { DONE = 50 };
    static char exr[64 * 1024];
    for (size_t i = 0; i < sizeof exr; i++)
        exr[i] = (char)(i * 7);
    t0 = mr_now();
    for (size_t i = 0; i < DONE; i++)
        ok(mr_store_frame_done(fx->st, id, i * 1999, exr, sizeof exr, "{\"x\":1}", &err), &err);
    double t_done = (mr_now() - t0) / DONE;

    t0 = mr_now();
    for (int i = 0; i < 20; i++)
        r = get_job(fx->st, id);
    double t_get = (mr_now() - t0) / 20;
    assert_int_equal(r.frames_done, DONE);

    mr_frame_record *list = NULL;
    size_t n = 0;
    t0 = mr_now();
    ok(mr_store_frames(fx->st, id, &list, &n, &err), &err);
    double t_frames = mr_now() - t0;
    assert_int_equal(n, frames);
    assert_int_equal(list[frames - 1].index, frames - 1);
    assert_int_equal(list[1999].state, MR_FRAME_DONE);
    mr_frame_records_free(list, n);

    /* The status of a finished job counts 100,000 done frames; mark them
     * done behind the store's back (a second connection, as WAL allows). */
    char path[512];
    snprintf(path, sizeof path, "%s/microray.sqlite", fx->dir);
    sqlite3 *db = NULL;
    assert_int_equal(sqlite3_open_v2(path, &db, SQLITE_OPEN_READWRITE, NULL), SQLITE_OK);
    assert_int_equal(sqlite3_exec(db, "UPDATE frames SET state = 2", NULL, NULL, NULL), SQLITE_OK);
    sqlite3_close(db);
    t0 = mr_now();
    for (int i = 0; i < 20; i++)
        r = get_job(fx->st, id);
    double t_get_all = (mr_now() - t0) / 20;
    assert_int_equal(r.frames_done, frames);

    t0 = mr_now();
    ok(mr_store_job_delete(fx->st, id, &err), &err);
    double t_delete = mr_now() - t0;

    printf("[ timing   ] create 100000-frame job %.1f ms; frame_done (64 KiB) %.2f ms each; "
           "job_get %.3f ms (%.2f ms with 100000 frames done); frames list %.1f ms; "
           "delete %.1f ms\n",
           t_create * 1e3, t_done * 1e3, t_get * 1e3, t_get_all * 1e3, t_frames * 1e3,
           t_delete * 1e3);
}

enum { THREADS = 4, JOBS_PER_THREAD = 40 };

typedef struct worker_arg {
    mr_store *st;
    int n;
    char claimed[THREADS * JOBS_PER_THREAD][33];
    int failures;
    char msg[600];
} worker_arg;

/* Each thread submits its share of jobs, then claims and "renders" until
 * the queue is empty, reading status in between like the HTTP threads do. */
static void *worker(void *p)
{
    worker_arg *w = p;
    mr_error err = {0};
    for (int i = 0; i < JOBS_PER_THREAD; i++) {
        char id[33];
        bool existing;
        if (mr_store_job_create(w->st, "{}", 2, "t", 2, i % 3, 1, NULL, NULL, id, &existing,
                                &err) != MR_OK)
            goto fail;
    }
    for (;;) {
        char id[33];
        int rc = mr_store_job_claim(w->st, id, &err);
        if (rc == MR_ERR_NOT_FOUND)
            break;
        if (rc != MR_OK)
            goto fail;
        memcpy(w->claimed[w->n++], id, 33);
        mr_job_record r;
        mr_job_record *list = NULL;
        size_t n;
        uint64_t counts[5];
        bool gave_up;
        if (mr_store_frame_set_running(w->st, id, 0, &err) != MR_OK ||
            mr_store_frame_done(w->st, id, 0, id, 32, "{}", &err) != MR_OK ||
            mr_store_frame_failed(w->st, id, 1, "x", false, &gave_up, &err) != MR_OK ||
            mr_store_job_get(w->st, id, &r, &err) != MR_OK ||
            mr_store_job_list(w->st, &(mr_job_query){0}, &list, &n, NULL, &err) != MR_OK ||
            mr_store_job_counts(w->st, counts, &err) != MR_OK ||
            mr_store_job_set_state(w->st, id, MR_JOB_SUCCEEDED, NULL, &err) != MR_OK) {
            free(list);
            goto fail;
        }
        free(list);
        if (r.state != MR_JOB_RUNNING || r.frames_done != 1) {
            snprintf(w->msg, sizeof w->msg, "job %s: state %d, %zu frames done", id, r.state,
                     r.frames_done);
            w->failures++;
            return NULL;
        }
    }
    return NULL;
fail:
    snprintf(w->msg, sizeof w->msg, "%s", err.msg);
    w->failures++;
    return NULL;
}

static int cmp_id(const void *a, const void *b) { return strcmp(a, b); }

static void test_concurrent_claims(void **state)
{
    fixture *fx = *state;
    worker_arg *args = calloc(THREADS, sizeof *args);
    assert_non_null(args);
    pthread_t th[THREADS];
    for (int i = 0; i < THREADS; i++) {
        args[i].st = fx->st;
        assert_int_equal(pthread_create(&th[i], NULL, worker, &args[i]), 0);
    }
    for (int i = 0; i < THREADS; i++)
        pthread_join(th[i], NULL);

    char(*all)[33] = calloc(THREADS * JOBS_PER_THREAD, 33);
    assert_non_null(all);
    int total = 0;
    for (int i = 0; i < THREADS; i++) {
        if (args[i].failures)
            fail_msg("thread %d: %s", i, args[i].msg);
        for (int j = 0; j < args[i].n; j++)
            memcpy(all[total++], args[i].claimed[j], 33);
    }
    /* A thread that finished submitting early may claim the rest while the
     * others still submit, so every job is claimed exactly once overall. */
    assert_int_equal(total, THREADS * JOBS_PER_THREAD);
    qsort(all, (size_t)total, 33, cmp_id);
    for (int i = 1; i < total; i++)
        if (strcmp(all[i - 1], all[i]) == 0)
            fail_msg("job %s was claimed twice", all[i]);

    mr_error err = {0};
    uint64_t counts[5];
    ok(mr_store_job_counts(fx->st, counts, &err), &err);
    assert_int_equal(counts[MR_JOB_SUCCEEDED], THREADS * JOBS_PER_THREAD);
    assert_int_equal(counts[MR_JOB_QUEUED] + counts[MR_JOB_RUNNING], 0);
    free(all);
    free(args);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_sha256_nist_vectors),
        cmocka_unit_test(test_sha256_padding_boundaries),
        cmocka_unit_test(test_sha256_split_updates),
        cmocka_unit_test(test_state_names),
        cmocka_unit_test_setup_teardown(test_open_schema, setup, teardown),
        cmocka_unit_test_setup_teardown(test_schema_upgrade_from_v1, setup, teardown),
        cmocka_unit_test_setup_teardown(test_schema_upgrade_from_v2, setup, teardown),
        cmocka_unit_test_setup_teardown(test_asset_use_list_delete, setup, teardown),
        cmocka_unit_test_setup_teardown(test_create_get_list_filter, setup, teardown),
        cmocka_unit_test_setup_teardown(test_set_state_times, setup, teardown),
        cmocka_unit_test_setup_teardown(test_claim_order, setup, teardown),
        cmocka_unit_test_setup_teardown(test_frame_done, setup, teardown),
        cmocka_unit_test_setup_teardown(test_frame_done_own_temporary, setup, teardown),
        cmocka_unit_test_setup_teardown(test_frame_failed_retries, setup, teardown),
        cmocka_unit_test_setup_teardown(test_retry, setup, teardown),
        cmocka_unit_test_setup_teardown(test_recover_after_crash, setup, teardown),
        cmocka_unit_test_setup_teardown(test_recover_crash_loop, setup, teardown),
        cmocka_unit_test_setup_teardown(test_idempotency, setup, teardown),
        cmocka_unit_test_setup_teardown(test_delete, setup, teardown),
        cmocka_unit_test_setup_teardown(test_schema_upgrade_from_v3, setup, teardown),
        cmocka_unit_test_setup_teardown(test_assets, setup, teardown),
        cmocka_unit_test_setup_teardown(test_job_counts, setup, teardown),
        cmocka_unit_test_setup_teardown(test_large_job, setup, teardown),
        cmocka_unit_test_setup_teardown(test_concurrent_claims, setup, teardown),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
