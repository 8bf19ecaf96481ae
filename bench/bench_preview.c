/*
 * bench_preview.c - what a PNG preview costs (make bench; issue 13 part 5).
 * Not a test: it prints figures, it never fails on a time.
 *
 * A mid frame of examples/skinned-walk.json is rendered at 640x360 and
 * 1920x1080; then, interleaved and repeated (medians), the steps of a
 * preview are timed side by side with the EXR encode of the same film:
 * tone mapping (mr_preview_from_film), PNG encoding (mr_png_encode), the
 * contact-sheet thumbnail (mr_preview_thumbnail), the EXR the daemon writes
 * (the job's ZIP) and the EXR read a preview of a stored frame starts with.
 *
 * usage: bench_preview [--repeats N] [--threads N]   (run from the repository root)
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "files.h"
#include "job_json.h"
#include "microray.h"
#include "bench_util.h"

static int repeats = 9;
static unsigned threads = 0;

static void die(const char *what, const char *msg)
{
    fprintf(stderr, "bench_preview: %s: %s\n", what, msg);
    exit(1);
}

static void bench_size(mr_device *dev, mr_job *job, mr_asset **assets, int w, int h)
{
    mr_error err = {0};
    job->output.width = w;
    job->output.height = h;
    mr_renderer *r = NULL;
    mr_film *film = NULL, *back = NULL;
    if (mr_renderer_new(dev, job, assets, NULL, &r, &err) < 0 || mr_film_new(w, h, &film, &err) < 0)
        die("renderer", err.msg);
    mr_frame_stats st;
    if (mr_renderer_render(r, job->frame_count / 2, film, &st, &err) < 0)
        die("render", err.msg);

    char path[] = "/tmp/bench_preview_XXXXXX.exr";
    int fd = mkstemps(path, 4);
    if (fd < 0)
        die("temporary file", "mkstemps failed");
    close(fd);
    mr_exr_meta meta = {.frame = 0, .scene_diagonal = st.scene_diagonal};
    if (mr_exr_write_file(path, film, &job->output.exr, &meta, &err) < 0)
        die(path, err.msg);

    double tone[64], png[64], thumb[64], exr[64], read[64];
    size_t png_bytes = 0, exr_bytes = 0;
    for (int i = 0; i < repeats; i++) {
        mr_image8 img, small;
        uint8_t *data = NULL;
        double t0 = mr_now();
        if (mr_preview_from_film(film, &img, &err) < 0)
            die("preview", err.msg);
        double t1 = mr_now();
        if (mr_png_encode(&img, &data, &png_bytes, &err) < 0)
            die("png", err.msg);
        double t2 = mr_now();
        if (mr_preview_thumbnail(film, &small, &err) < 0)
            die("thumbnail", err.msg);
        double t3 = mr_now();
        free(data);
        mr_image8_free(&img);
        mr_image8_free(&small);
        if (mr_exr_write_memory(&data, &exr_bytes, film, &job->output.exr, &meta, &err) < 0)
            die("exr", err.msg);
        double t4 = mr_now();
        free(data);
        if (mr_exr_read_file(path, &back, NULL, &err) < 0)
            die(path, err.msg);
        double t5 = mr_now();
        mr_film_free(back);
        tone[i] = t1 - t0;
        png[i] = t2 - t1;
        thumb[i] = t3 - t2;
        exr[i] = t4 - t3;
        read[i] = t5 - t4;
    }
    unlink(path);
    double mt = median(tone, repeats), mp = median(png, repeats), me = median(exr, repeats);
    printf("| %4dx%-4d | %8.1f | %7.1f | %7.0f | %9.1f | %7.1f | %8.1f | %15.2f | %7.0f |\n", w, h,
           mt * 1e3, mp * 1e3, (double)png_bytes / 1024.0, median(thumb, repeats) * 1e3,
           me * 1e3, median(read, repeats) * 1e3, (mt + mp) / me, (double)exr_bytes / 1024.0);
    mr_film_free(film);
    mr_renderer_free(r);
}

int main(int argc, char **argv)
{
    for (int i = 1; i < argc; i++)
        if (!strcmp(argv[i], "--repeats") && i + 1 < argc)
            repeats = atoi(argv[++i]);
        else if (!strcmp(argv[i], "--threads") && i + 1 < argc)
            threads = (unsigned)atoi(argv[++i]);
    if (repeats < 1 || repeats > 64)
        repeats = 9;
    const char *job_path = "examples/skinned-walk.json";
    char *text = NULL;
    size_t len = 0;
    mr_job *job = NULL;
    mr_error err = {0};
    mr_job_error jerr = {0};
    if (mr_file_read(job_path, MR_JOB_MAX_BYTES, &text, &len, &err) < 0)
        die(job_path, err.msg);
    if (mr_job_parse(text, len, &job, &jerr) < 0)
        die(job_path, jerr.message);
    free(text);
    mr_asset **assets = calloc(job->asset_count, sizeof *assets);
    for (size_t i = 0; i < job->asset_count; i++)
        if (mr_asset_load(job->assets[i].path, &assets[i], &err) < 0)
            die(job->assets[i].path, err.msg);
    mr_device *dev = NULL;
    if (mr_device_new(threads, &dev, &err) < 0)
        die("device", err.msg);

    printf("\nPNG previews (ms, one thread; medians of %d; skinned example, mid frame; EXR: the job's "
           "%s on %u threads)\n\n", repeats, mr_compression_name(job->output.exr.compression),
           mr_device_threads(dev));
    printf("| size      | tone map | PNG enc | PNG KiB | thumbnail | EXR enc | EXR read | preview/EXR enc | EXR KiB |\n");
    printf("|-----------|----------|---------|---------|-----------|---------|----------|-----------------|---------|\n");
    bench_size(dev, job, assets, 640, 360);
    bench_size(dev, job, assets, 1920, 1080);

    mr_device_free(dev);
    for (size_t i = 0; i < job->asset_count; i++)
        mr_asset_free(assets[i]);
    free(assets);
    mr_job_free(job);
    return 0;
}
