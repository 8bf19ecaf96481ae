/*
 * test_previews.c - PNG previews through the real microrayd on loopback
 * (issue 13 part 5): jobs rendered by the daemon, each frame's EXR fetched
 * from it and read with mr_exr_read_file, its PNG preview fetched by
 * Accept: image/png and by the .png route, decoded with libpng's own reader
 * and checked pixel by pixel against the documented operator (to 1 code:
 * tests/support/png_fixture.h says why); content negotiation (q-values,
 * 406); the contact sheet of a canceled 401-frame job (64 cells, finished
 * cells against thumbnails computed from the EXRs, unfinished cells drawn
 * as such, ETag and 304); missing frames and jobs, a damaged EXR on disk
 * (500 naming the frame, the daemon still up); `microray fetch --png` and
 * `microrayd render --png`.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <cJSON.h>
#include <dirent.h>

#include "daemon_fixture.h"
#include "microray.h"
#include "../support/png_fixture.h"

static daemon_proc D;

/* A small job of the skinned dancer: a half-transparent background and 4
 * samples, so edges and background have 0 < alpha < 1 (un-premultiplied
 * by the preview). */
static char *job_text(int frames_end_q, int width, const char *name)
{
    char *s = malloc(4096);
    snprintf(s, 4096,
             "{\"name\":\"%s\",\"assets\":{\"d\":{\"path\":\"/usr/share/assimp/models/X/BCN_Epileptic.X\"}},"
             "\"objects\":[{\"asset\":\"d\",\"pose\":{\"clip\":0}}],"
             "\"background\":{\"color\":[0.3,0.5,0.9],\"alpha\":0.4},"
             "\"lights\":[{\"direction\":[-0.4,-0.8,-0.6],\"intensity\":1.6}],"
             "\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0.2,3.3],\"target\":[0,0,-0.1]}]},"
             "\"frames\":{\"fps\":4,\"start\":0,\"end\":%g},"
             "\"output\":{\"width\":%d,\"height\":%d,\"samples\":4}}",
             name, frames_end_q / 4.0, width, width * 9 / 16);
    return s;
}

static void render_job(const char *job, char id[64])
{
    fx_submit(&D, job, id);
    cJSON *j = fx_wait_job(&D, id, 120);
    if (strcmp(cJSON_GetObjectItem(j, "state")->valuestring, "succeeded"))
        fail_msg("job %s ended %s (daemon log %s)", id, cJSON_GetObjectItem(j, "state")->valuestring, D.log);
    cJSON_Delete(j);
}

/* GET of a frame's EXR from the daemon, read back with OpenEXR. */
static mr_film *fetch_exr(const char *id, int n)
{
    char path[128], file[700];
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/%d", id, n);
    http_result r = http(&D, "GET", path, NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    assert_string_equal(r.content_type, "image/x-exr");
    assert_string_equal(r.vary, "Accept");
    snprintf(file, sizeof file, "%s/fetched-%s-%d.exr", fx_tmp, id, n);
    FILE *f = fopen(file, "wb");
    assert_non_null(f);
    assert_int_equal(fwrite(r.body, 1, r.len, f), r.len);
    fclose(f);
    http_free(&r);
    mr_film *film = NULL;
    mr_error err = {0};
    if (mr_exr_read_file(file, &film, NULL, &err) < 0)
        fail_msg("%s", err.msg);
    return film;
}

/* Pixels with 0 < alpha < 1 (the un-premultiplied ones). */
static size_t partial_pixels(const mr_film *f)
{
    size_t n = 0;
    for (size_t i = 0; i < (size_t)f->width * (size_t)f->height; i++)
        n += f->a[i] > 0 && f->a[i] < 1;
    return n;
}

static void test_frame_png_matches_exr(void **state)
{
    (void)state;
    char id[64], path[160];
    char *job = job_text(2, 192, "png-frames");
    render_job(job, id);
    free(job);
    for (int n = 0; n < 3; n++) {
        mr_film *film = fetch_exr(id, n);
        assert_true(partial_pixels(film) > 100);
        snprintf(path, sizeof path, "/v1/jobs/%s/frames/%d", id, n);
        http_result a = http(&D, "GET", path, NULL, 0, "Accept: image/png");
        assert_int_equal(a.status, 200);
        assert_string_equal(a.content_type, "image/png");
        assert_string_equal(a.vary, "Accept");
        char want[64];
        snprintf(want, sizeof want, "inline; filename=\"%04d.png\"", n);
        assert_string_equal(a.disposition, want);
        fx_png png = fx_png_read(a.body, a.len);
        assert_true(png.srgb);
        size_t off = fx_check_preview(&png, film);
        print_message("frame %d: %dx%d, %zu partly covered pixels, %zu values off by one\n", n,
                      png.width, png.height, partial_pixels(film), off);
        /* the .png route answers the same bytes (whatever Accept says) */
        snprintf(path, sizeof path, "/v1/jobs/%s/frames/%d.png", id, n);
        http_result b = http(&D, "GET", path, NULL, 0, "Accept: text/html");
        assert_int_equal(b.status, 200);
        assert_string_equal(b.content_type, "image/png");
        assert_string_equal(b.vary, "");
        assert_int_equal(b.len, a.len);
        assert_memory_equal(b.body, a.body, a.len);
        /* leading zeros name the same frame */
        snprintf(path, sizeof path, "/v1/jobs/%s/frames/000%d.png", id, n);
        http_result c = http(&D, "GET", path, NULL, 0, NULL);
        assert_int_equal(c.status, 200);
        assert_int_equal(c.len, a.len);
        http_free(&a);
        http_free(&b);
        http_free(&c);
        fx_png_free(&png);
        mr_film_free(film);
    }
    /* cached beside the EXR */
    char cached[900];
    snprintf(cached, sizeof cached, "%s/frames/%s/0001.png", D.data, id);
    struct stat st;
    assert_int_equal(stat(cached, &st), 0);
}

/* Accept header(s) -> the type answered ("406" for Not Acceptable). */
static void expect_negotiated(const char *id, const char *const *headers, const char *want)
{
    char path[128];
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/0", id);
    http_result r = http_headers(&D, "GET", path, NULL, 0, headers);
    const char *got = r.status == 406 ? "406" : r.content_type;
    if (strcmp(got, want))
        fail_msg("Accept '%s'%s%s: got %ld %s, want %s", headers[0] ? headers[0] : "(none)",
                 headers[0] && headers[1] ? " + " : "", headers[0] && headers[1] ? headers[1] : "",
                 r.status, r.content_type, want);
    assert_string_equal(r.vary, "Accept");
    if (r.status == 406) {
        assert_string_equal(r.content_type, "application/problem+json");
        cJSON *j = cJSON_Parse(r.body);
        assert_non_null(j);
        assert_int_equal(cJSON_GetObjectItem(j, "status")->valueint, 406);
        assert_non_null(strstr(cJSON_GetObjectItem(j, "detail")->valuestring, "image/png"));
        cJSON_Delete(j);
    }
    http_free(&r);
}

static void test_content_negotiation(void **state)
{
    (void)state;
    char id[64];
    char *job = job_text(0, 64, "png-negotiation");
    render_job(job, id);
    free(job);
    static const struct {
        const char *accept, *want;
    } cases[] = {
        {NULL, "image/x-exr"},
        {"Accept: */*", "image/x-exr"},
        {"Accept: image/*", "image/x-exr"},           /* a tie: the server prefers EXR */
        {"Accept: image/png", "image/png"},
        {"Accept: IMAGE/PNG", "image/png"},
        {"Accept: image/x-exr", "image/x-exr"},
        {"Accept: image/png, image/x-exr;q=0.9", "image/png"},
        {"Accept: image/png;q=0.5, image/x-exr;q=0.6", "image/x-exr"},
        {"Accept: image/png;q=0.6, image/x-exr;q=0.5", "image/png"},
        {"Accept: image/x-exr;q=0, */*", "image/png"},
        {"Accept: */*;q=0.1, image/png", "image/png"},
        {"Accept: image/*;q=0.2, image/png;q=0.1", "image/x-exr"}, /* most specific range rules */
        {"Accept: text/html, image/png;q=0.001", "image/png"},
        {"Accept: image/png;level=1;q=0.9, image/x-exr;q=0.8", "image/png"},
        {"Accept: image/png ; q=1.000", "image/png"},
        {"Accept: text/html", "406"},
        {"Accept: text/html, application/json;q=0.9", "406"},
        {"Accept: image/png;q=0, image/x-exr;q=0", "406"},
        {"Accept: */*;q=0", "406"},
        {"Accept: image/*;q=0", "406"},
        /* elements that do not parse are ignored; none left: no preference */
        {"Accept: garbage", "image/x-exr"},
        {"Accept: image/png;q=1.5", "image/x-exr"},
        {"Accept: image/png;q=0.0001", "image/x-exr"},
        {"Accept: image/png;q=0.5, bogus;;", "image/png"},
        {"Accept: ", "image/x-exr"},
    };
    for (size_t i = 0; i < sizeof cases / sizeof *cases; i++) {
        const char *h[] = {cases[i].accept, NULL};
        expect_negotiated(id, h, cases[i].want);
    }
    /* two Accept header lines are one list */
    const char *two[] = {"Accept: text/html", "Accept: image/png;q=0.3", NULL};
    expect_negotiated(id, two, "image/png");
}

static const uint8_t *sheet_px(const fx_png *s, int x, int y)
{
    return s->px + ((size_t)y * (size_t)s->width + (size_t)x) * 3;
}

/* A cell drawn as "not finished": grey 56 crossed by its diagonals in 128. */
static void check_pending_cell(const fx_png *s, int cx, int cy, int tw, int th)
{
    int n = tw > th ? tw : th;
    unsigned char *cross = calloc((size_t)tw * (size_t)th, 1);
    for (int k = 0; k < n; k++) {
        int x = (int)((long long)k * (tw - 1) / (n - 1)), y = (int)((long long)k * (th - 1) / (n - 1));
        cross[(size_t)y * (size_t)tw + (size_t)x] = 1;
        cross[(size_t)y * (size_t)tw + (size_t)(tw - 1 - x)] = 1;
    }
    for (int y = 0; y < th; y++)
        for (int x = 0; x < tw; x++) {
            const uint8_t *p = sheet_px(s, cx + x, cy + y);
            int want = cross[(size_t)y * (size_t)tw + (size_t)x] ? 128 : 56;
            if (p[0] != want || p[1] != want || p[2] != want)
                fail_msg("pending cell at (%d, %d): pixel (%d, %d) is %d %d %d, want %d", cx, cy, x, y,
                         p[0], p[1], p[2], want);
        }
    free(cross);
}

/* Distinct colours in a cell (at most 64 counted). */
static int cell_colours(const fx_png *s, int cx, int cy, int tw, int th)
{
    uint32_t seen[64];
    int n = 0;
    for (int y = 0; y < th; y++)
        for (int x = 0; x < tw && n < 64; x++) {
            const uint8_t *p = sheet_px(s, cx + x, cy + y);
            uint32_t c = (uint32_t)p[0] << 16 | (uint32_t)p[1] << 8 | p[2];
            int k = 0;
            while (k < n && seen[k] != c)
                k++;
            if (k == n)
                seen[n++] = c;
        }
    return n;
}

static void test_contact_sheet(void **state)
{
    (void)state;
    /* 401 frames, canceled once frames 0..6 are done: frames 0 and 6 are
     * the first two cells, the last frames are not rendered */
    char id[64], path[160];
    char *job = job_text(400, 96, "png-sheet");
    fx_submit(&D, job, id);
    free(job);
    fx_wait_frames_done(&D, id, 7);
    snprintf(path, sizeof path, "/v1/jobs/%s/cancel", id);
    http_result cr = http(&D, "POST", path, NULL, 0, NULL);
    assert_int_equal(cr.status, 202);
    http_free(&cr);
    cJSON *j = fx_wait_job(&D, id, 120);
    assert_string_equal(cJSON_GetObjectItem(j, "state")->valuestring, "canceled");
    cJSON *states = cJSON_GetObjectItem(j, "frame_states");
    assert_int_equal(cJSON_GetArraySize(states), 401);

    snprintf(path, sizeof path, "/v1/jobs/%s/contact-sheet.png", id);
    http_result r = http(&D, "GET", path, NULL, 0, NULL);
    assert_int_equal(r.status, 200);
    assert_string_equal(r.content_type, "image/png");
    assert_true(strlen(r.etag) == 18);
    fx_png sheet = fx_png_read(r.body, r.len);
    int tw, th;
    mr_preview_thumb_size(96, 54, &tw, &th);
    assert_true(tw == 96 && th == 54); /* smaller than 160: never enlarged */
    /* 64 cells in 8 columns, 4 pixels apart */
    assert_int_equal(sheet.width, 4 + 8 * (96 + 4));
    assert_int_equal(sheet.height, 4 + 8 * (54 + 4));
    size_t done_cells = 0, pending_cells = 0;
    for (int i = 0; i < 64; i++) {
        int index = i * 400 / 63, cx = 4 + (i % 8) * 100, cy = 4 + (i / 8) * 58;
        const char *st = cJSON_GetObjectItem(cJSON_GetArrayItem(states, index), "state")->valuestring;
        if (strcmp(st, "done")) {
            check_pending_cell(&sheet, cx, cy, tw, th);
            pending_cells++;
            continue;
        }
        mr_film *film = fetch_exr(id, index);
        fx_check_thumb(&sheet, cx, cy, film, tw, th);
        /* not empty: an empty frame (its background over the checkerboard)
         * has two colours; the dancer brings many more */
        assert_true(cell_colours(&sheet, cx, cy, tw, th) > 10);
        mr_film_free(film);
        done_cells++;
    }
    print_message("contact sheet %dx%d: %zu finished cells, %zu pending\n", sheet.width, sheet.height,
                  done_cells, pending_cells);
    assert_true(done_cells >= 2 && pending_cells >= 1);
    /* gutters */
    assert_int_equal(sheet_px(&sheet, 0, 0)[0], 16);
    assert_int_equal(sheet_px(&sheet, 100, 30)[1], 16);

    /* revalidation: 304 for the same ETag, cached on disk */
    char inm[160];
    snprintf(inm, sizeof inm, "If-None-Match: %s", r.etag);
    http_result nm = http(&D, "GET", path, NULL, 0, inm);
    assert_int_equal(nm.status, 304);
    assert_string_equal(nm.etag, r.etag);
    http_free(&nm);
    http_result again = http(&D, "GET", path, NULL, 0, "If-None-Match: \"0000000000000000\"");
    assert_int_equal(again.status, 200);
    assert_int_equal(again.len, r.len);
    assert_memory_equal(again.body, r.body, r.len);
    http_free(&again);
    char file[900];
    snprintf(file, sizeof file, "%s/frames/%s/contact-sheet-%.16s.png", D.data, id, r.etag + 1);
    struct stat sb;
    assert_int_equal(stat(file, &sb), 0);
    /* HEAD: the headers alone */
    http_result head = http(&D, "HEAD", path, NULL, 0, NULL);
    assert_int_equal(head.status, 200);
    assert_int_equal(head.len, 0);
    http_free(&head);

    fx_png_free(&sheet);
    http_free(&r);
    cJSON_Delete(j);
}

static void expect_problem(const char *path, const char *header, long status, const char *detail)
{
    http_result r = http(&D, "GET", path, NULL, 0, header);
    if (r.status != status)
        fail_msg("GET %s: %ld, want %ld: %s", path, r.status, status, r.body);
    assert_string_equal(r.content_type, "application/problem+json");
    cJSON *j = cJSON_Parse(r.body);
    assert_non_null(j);
    const char *d = cJSON_GetObjectItem(j, "detail")->valuestring;
    if (detail && !strstr(d, detail))
        fail_msg("GET %s: detail '%s' lacks '%s'", path, d, detail);
    assert_null(strstr(d, D.data)); /* no server paths */
    cJSON_Delete(j);
    http_free(&r);
}

static void test_bad_cases(void **state)
{
    (void)state;
    char path[200], id[64];
    const char *ghost = "0123456789abcdef0123456789abcdef";
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/0.png", ghost);
    expect_problem(path, NULL, 404, "no job");
    snprintf(path, sizeof path, "/v1/jobs/%s/contact-sheet.png", ghost);
    expect_problem(path, NULL, 404, "no job");
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/0", ghost);
    expect_problem(path, "Accept: image/png", 404, "no job");

    char *job = job_text(1, 64, "png-bad");
    render_job(job, id);
    free(job);
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/2.png", id);
    expect_problem(path, NULL, 404, "has 2 frames");
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/x.png", id);
    expect_problem(path, NULL, 404, "not a frame number");
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/.png", id);
    expect_problem(path, NULL, 404, "not a frame number");
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/2", id);
    expect_problem(path, "Accept: image/png", 404, "has 2 frames");
    snprintf(path, sizeof path, "/v1/jobs/%s/contact-sheet.png", id);
    http_result m = http(&D, "POST", path, "", 0, NULL);
    assert_int_equal(m.status, 405);
    http_free(&m);

    /* not rendered: a job held in the queue behind a long one */
    char *blocker = job_text(400, 64, "png-blocker"), *queued = job_text(0, 64, "png-queued");
    char bid[64], qid[64];
    fx_submit(&D, blocker, bid);
    fx_submit(&D, queued, qid);
    free(blocker);
    free(queued);
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/0.png", qid);
    expect_problem(path, NULL, 404, "not rendered");
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/0", qid);
    expect_problem(path, "Accept: image/png", 404, "not rendered");
    /* a sheet of nothing finished is all pending cells */
    snprintf(path, sizeof path, "/v1/jobs/%s/contact-sheet.png", qid);
    http_result s = http(&D, "GET", path, NULL, 0, NULL);
    assert_int_equal(s.status, 200);
    fx_png sheet = fx_png_read(s.body, s.len);
    assert_true(sheet.width == 4 + 64 + 4 && sheet.height == 4 + 36 + 4);
    check_pending_cell(&sheet, 4, 4, 64, 36);
    fx_png_free(&sheet);
    http_free(&s);
    snprintf(path, sizeof path, "/v1/jobs/%s", bid);
    http_result del = http(&D, "DELETE", path, NULL, 0, NULL);
    assert_int_equal(del.status, 204);
    http_free(&del);
    snprintf(path, sizeof path, "/v1/jobs/%s", qid);
    del = http(&D, "DELETE", path, NULL, 0, NULL);
    http_free(&del);

    /* a damaged EXR on disk: garbage for frame 0, a truncated frame 1 */
    char exr[900];
    snprintf(exr, sizeof exr, "%s/frames/%s/0000.exr", D.data, id);
    FILE *f = fopen(exr, "wb");
    fputs("this is not an OpenEXR file at all, but long enough to be read", f);
    fclose(f);
    snprintf(exr, sizeof exr, "%s/frames/%s/0001.exr", D.data, id);
    assert_int_equal(truncate(exr, 300), 0);
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/0.png", id);
    expect_problem(path, NULL, 500, "frame 0 of job");
    snprintf(path, sizeof path, "/v1/jobs/%s/frames/1", id);
    expect_problem(path, "Accept: image/png", 500, "frame 1 of job");
    snprintf(path, sizeof path, "/v1/jobs/%s/contact-sheet.png", id);
    expect_problem(path, NULL, 500, "frame 0 of job");
    /* still serving */
    http_result h = http(&D, "GET", "/healthz", NULL, 0, NULL);
    assert_int_equal(h.status, 200);
    http_free(&h);
}

static int run(const char *cmd)
{
    int st = system(cmd);
    return WIFEXITED(st) ? WEXITSTATUS(st) : -1;
}

static fx_png read_png_file(const char *path)
{
    size_t n = 0;
    char *bytes = fx_slurp(path, &n);
    if (!bytes)
        fail_msg("%s is missing", path);
    fx_png p = fx_png_read(bytes, n);
    free(bytes);
    return p;
}

static void test_client_fetch_png(void **state)
{
    (void)state;
    char id[64], out[600], cmd[6000], log[700];
    char *job = job_text(2, 128, "png-fetch");
    render_job(job, id);
    free(job);
    snprintf(out, sizeof out, "%s/fetch-png", fx_tmp);
    snprintf(log, sizeof log, "%s/fetch-png.log", fx_tmp);
    snprintf(cmd, sizeof cmd, "'%s/microray' --server %s fetch %s --out '%s' --png >'%s' 2>&1",
             fx_build_dir, D.base, id, out, log);
    if (run(cmd) != 0) {
        char *text = fx_slurp(log, NULL);
        fail_msg("microray fetch --png failed: %s", text ? text : "");
    }
    for (int n = 0; n < 3; n++) {
        char p[700];
        snprintf(p, sizeof p, "%s/%04d.exr", out, n);
        struct stat st;
        assert_int_not_equal(stat(p, &st), 0); /* previews instead of EXRs */
        snprintf(p, sizeof p, "%s/%04d.png", out, n);
        fx_png png = read_png_file(p);
        mr_film *film = fetch_exr(id, n);
        fx_check_preview(&png, film);
        mr_film_free(film);
        fx_png_free(&png);
    }
    char p[700];
    snprintf(p, sizeof p, "%s/contact-sheet.png", out);
    fx_png sheet = read_png_file(p);
    assert_true(sheet.width == 4 + 2 * (128 + 4) && sheet.height == 4 + 2 * (72 + 4));
    fx_png_free(&sheet);
    snprintf(p, sizeof p, "%s/stats.json", out);
    char *stats = fx_slurp(p, NULL);
    assert_non_null(stats);
    free(stats);
    /* --png wants --out */
    snprintf(cmd, sizeof cmd, "'%s/microray' --server %s fetch %s --png >/dev/null 2>&1", fx_build_dir,
             D.base, id);
    assert_int_equal(run(cmd), 2);
}

static void test_render_png(void **state)
{
    (void)state;
    char job_path[600], out[600], cmd[6000];
    snprintf(job_path, sizeof job_path, "%s/render-png.json", fx_tmp);
    snprintf(out, sizeof out, "%s/render-png", fx_tmp);
    char *job = job_text(2, 112, "png-render");
    FILE *f = fopen(job_path, "w");
    fputs(job, f);
    fclose(f);
    free(job);
    snprintf(cmd, sizeof cmd, "'%s/microrayd' render '%s' --out '%s' --png --threads 2 --quiet",
             fx_build_dir, job_path, out);
    assert_int_equal(run(cmd), 0);
    char p[700];
    snprintf(p, sizeof p, "%s/contact-sheet.png", out);
    fx_png sheet = read_png_file(p);
    int tw = 112, th = 63;
    assert_true(sheet.width == 4 + 2 * (tw + 4) && sheet.height == 4 + 2 * (th + 4));
    for (int n = 0; n < 3; n++) {
        snprintf(p, sizeof p, "%s/%04d.exr", out, n);
        mr_film *film = NULL;
        mr_error err = {0};
        if (mr_exr_read_file(p, &film, NULL, &err) < 0)
            fail_msg("%s", err.msg);
        snprintf(p, sizeof p, "%s/%04d.png", out, n);
        fx_png png = read_png_file(p);
        /* the preview was made from the film, the EXR holds its halves:
         * within the one code of the tolerance all the same */
        fx_check_preview(&png, film);
        fx_check_thumb(&sheet, 4 + (n % 2) * (tw + 4), 4 + (n / 2) * (th + 4), film, tw, th);
        fx_png_free(&png);
        mr_film_free(film);
    }
    /* three cells in a 2 x 2 grid: the fourth place is background */
    for (int y = 0; y < th; y++)
        for (int x = 0; x < tw; x++)
            assert_int_equal(sheet_px(&sheet, 4 + tw + 4 + x, 4 + th + 4 + y)[0], 16);
    fx_png_free(&sheet);
    snprintf(p, sizeof p, "%s/stats.json", out);
    char *stats = fx_slurp(p, NULL);
    assert_non_null(stats);
    assert_non_null(strstr(stats, "\"png_s\""));
    free(stats);
}

static int setup(void **state)
{
    (void)state;
    curl_global_init(CURL_GLOBAL_DEFAULT);
    fx_init_dirs();
    daemon_start(&D, "data");
    return 0;
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
        cmocka_unit_test(test_frame_png_matches_exr),
        cmocka_unit_test(test_content_negotiation),
        cmocka_unit_test(test_contact_sheet),
        cmocka_unit_test(test_bad_cases),
        cmocka_unit_test(test_client_fetch_png),
        cmocka_unit_test(test_render_png),
    };
    return cmocka_run_group_tests_name("previews", tests, setup, teardown);
}
