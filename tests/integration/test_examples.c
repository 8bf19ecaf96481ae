/*
 * test_examples.c - every job in examples/ renders through the one-shot
 * renderer (`microrayd render`, as a user runs it), scaled down to at most
 * 160 pixels wide: all its frames on 1 thread and its frame 0 on 2. Both
 * runs succeed, frame 0 is the same on both (colour, depth and normals bit
 * for bit: `microrayd compare` reports 999 dB and zero depth and normal
 * differences), and the first or the last frame (a fly-through may start
 * far away) shows the scene: at least as many pixels hit as 1000 of the
 * example's own frame size, scaled to the small one. Each example runs
 * with its own kinds and settings (shadows, samples, passes, its whole
 * clip), so a kind or a renderer change that breaks one of them, hangs in
 * it (each render runs under `timeout 600`, exit 124), loses the scene or
 * makes it depend on the thread count fails here. Stop 31: 16-wide shadow
 * packets never returned on the crowd example, which no test rendered.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <math.h>

#include "daemon_fixture.h"
#include "../support/json_fixture.h"

/* The example at path, its asset paths made absolute and its frame at most
 * 160 pixels wide (aspect kept), written to out; *scale: the small frame's
 * pixels over the example's. */
static void shrink_job(const char *path, const char *examples, const char *out, double *scale)
{
    char *text = fx_slurp(path, NULL);
    assert_non_null(text);
    cJSON *j = cJSON_Parse(text);
    free(text);
    if (!j)
        fail_msg("%s: not JSON", path);
    cJSON *asset;
    cJSON_ArrayForEach(asset, cJSON_GetObjectItem(j, "assets"))
    {
        cJSON *p = cJSON_GetObjectItem(asset, "path");
        if (cJSON_IsString(p) && p->valuestring[0] != '/') {
            char abs[4200];
            snprintf(abs, sizeof abs, "%s/%s", examples, p->valuestring);
            cJSON_SetValuestring(p, abs);
        }
    }
    cJSON *o = cJSON_GetObjectItem(j, "output");
    assert_non_null(o);
    cJSON *w = cJSON_GetObjectItem(o, "width"), *h = cJSON_GetObjectItem(o, "height");
    double width = cJSON_IsNumber(w) ? w->valuedouble : 640, height = cJSON_IsNumber(h) ? h->valuedouble : 360;
    const double full = width * height;
    if (width > 160) {
        height = round(height * 160 / width);
        width = 160;
    }
    cJSON_DeleteItemFromObject(o, "width");
    cJSON_DeleteItemFromObject(o, "height");
    cJSON_AddNumberToObject(o, "width", width);
    cJSON_AddNumberToObject(o, "height", height < 8 ? 8 : height);
    *scale = width * (height < 8 ? 8 : height) / full;
    char *s = cJSON_Print(j);
    FILE *f = fopen(out, "w");
    assert_non_null(f);
    fputs(s, f);
    fclose(f);
    free(s);
    cJSON_Delete(j);
}

/* `microrayd compare a b` of two frames: its report, parsed. */
static cJSON *compare(const char *a, const char *b)
{
    char cmd[3200];
    snprintf(cmd, sizeof cmd, "'%s/microrayd' compare '%s' '%s'", fx_build_dir, a, b);
    char *report = NULL;
    assert_int_equal(fx_run(cmd, &report), 0);
    cJSON *c = cJSON_Parse(report);
    if (!c)
        fail_msg("compare %s %s printed %s", a, b, report ? report : "nothing");
    free(report);
    return c;
}

static void test_every_example(void **state)
{
    (void)state;
    char examples[2100];
    snprintf(examples, sizeof examples, "%s/examples", fx_src_dir);
    DIR *d = opendir(examples);
    assert_non_null(d);
    struct dirent *e;
    size_t count = 0;
    while ((e = readdir(d))) {
        size_t n = strlen(e->d_name);
        if (n < 6 || strcmp(e->d_name + n - 5, ".json") != 0)
            continue;
        char name[256], src[2400], job[600], out[2][700], cmd[8192];
        snprintf(name, sizeof name, "%.*s", (int)(n - 5), e->d_name);
        snprintf(src, sizeof src, "%s/%s", examples, e->d_name);
        snprintf(job, sizeof job, "%s/%s.json", fx_tmp, name);
        double scale;
        shrink_job(src, examples, job, &scale);
        for (int t = 0; t < 2; t++) {
            snprintf(out[t], sizeof out[t], "%s/%s-%d", fx_tmp, name, t + 1);
            /* a hang guard, not a time limit: each render takes seconds
             * here, set-up included */
            snprintf(cmd, sizeof cmd,
                     "(exec 2>&1; timeout 600 '%s/microrayd' render '%s' --out '%s' %s "
                     "--threads %d --quiet --cache '%s/cache')",
                     fx_build_dir, job, out[t], t == 0 ? "" : "--frames 0", t + 1, fx_tmp);
            char *log = NULL;
            int rc = fx_run(cmd, &log);
            if (rc != 0)
                fail_msg("%s on %d thread(s): exit %d: %s", name, t + 1, rc, log ? log : "");
            free(log);
        }
        char first[2][1420], last[1420];
        for (int t = 0; t < 2; t++)
            snprintf(first[t], sizeof first[t], "%s/0000.exr", out[t]);
        cJSON *c = compare(first[0], first[1]);
        const double psnr = fx_json_number(c, "psnr_rgb_db"), depth = fx_json_number(c, "depth_max"),
                     normal = fx_json_number(c, "normal_max_deg");
        double hit = fx_json_number(c, "pixels_hit_either");
        cJSON_Delete(c);
        if (psnr != 999 || depth != 0 || normal != 0)
            fail_msg("%s: 1 and 2 threads differ (%g dB, depth %g, normals %g deg)", name, psnr,
                     depth, normal);
        size_t frames = 0;
        DIR *fd = opendir(out[0]);
        assert_non_null(fd);
        for (struct dirent *fe; (fe = readdir(fd));)
            frames += strstr(fe->d_name, ".exr") != NULL;
        closedir(fd);
        if (frames > 1) {
            snprintf(last, sizeof last, "%s/%04zu.exr", out[0], frames - 1);
            c = compare(last, last);
            const double hit_last = fx_json_number(c, "pixels_hit_either");
            hit = hit_last > hit ? hit_last : hit;
            cJSON_Delete(c);
        }
        print_message("%-24s %3zu frames, %4.0f pixels hit (first or last), 1 vs 2 threads: %g dB\n", name,
                      frames, hit, psnr);
        if (!(hit >= 1000 * scale))
            fail_msg("%s: only %.0f pixels show the scene (%.1f of a full-size frame's 1000)", name, hit,
                     1000 * scale);
        count++;
    }
    closedir(d);
    /* the examples the README lists: a glob that found none must not pass */
    assert_true(count >= 16);
}

int main(void)
{
    const struct CMUnitTest tests[] = {cmocka_unit_test(test_every_example)};
    return cmocka_run_group_tests(tests, fx_dirs_setup, fx_dirs_teardown);
}
