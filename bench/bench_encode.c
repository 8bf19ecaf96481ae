/*
 * bench_encode.c - EXR encoding as a share of frame time (make bench).
 * Not a test: it prints figures, it never fails on a time.
 *
 * The example job (examples/skinned-walk.json, as parsed: its passes, 2
 * samples, shadows) is rendered at 640x360, 1280x720, 1920x1080 and
 * 3840x2160; each frame is then encoded with every codec, all interleaved
 * and repeated, and the table gives medians: encode ms, render ms (the
 * frame's total: pose, BVH and trace), the share encode / (render +
 * encode) and the file size. Encoding uses all cores, as the renderer does.
 *
 * Written against the public API only (core/microray.h) plus the server's
 * job parser.
 *
 * usage: bench_encode [--repeats N] [--threads N] [--job FILE]   (from the repository root)
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "microray.h"
#include "files.h"
#include "job_json.h"
#include "bench_util.h"

static int repeats = 5;
static unsigned threads = 0;

static void die(const char *what, const char *msg)
{
    fprintf(stderr, "bench_encode: %s: %s\n", what, msg);
    exit(1);
}

static const mr_compression k_codecs[] = {MR_COMPRESSION_NONE, MR_COMPRESSION_ZIP,
                                          MR_COMPRESSION_ZIPS, MR_COMPRESSION_PIZ};
#define CODECS (sizeof k_codecs / sizeof k_codecs[0])

static const int k_sizes[][2] = {{640, 360}, {1280, 720}, {1920, 1080}, {3840, 2160}};
#define SIZES (sizeof k_sizes / sizeof k_sizes[0])

static void bench_size(mr_device *dev, mr_job *job, mr_asset **assets, int width, int height)
{
    mr_error err = {0};
    mr_renderer *r = NULL;
    mr_film *film = NULL;
    job->output.width = width;
    job->output.height = height;
    if (mr_renderer_new(dev, job, assets, NULL, &r, &err) < 0 ||
        mr_film_new(width, height, &film, &err) < 0)
        die("setup", err.msg);

    double render[64], enc[CODECS][64];
    size_t bytes[CODECS] = {0};
    mr_frame_stats st;
    for (int i = 0; i < repeats; i++) {
        if (mr_renderer_render(r, 0, film, &st, &err) < 0)
            die("render", err.msg);
        render[i] = st.total_s;
        mr_exr_meta meta = {.frame = 0, .time = st.time, .render_seconds = st.total_s,
                            .scene_diagonal = st.scene_diagonal};
        snprintf(meta.job, sizeof meta.job, "%s", job->name);
        for (size_t c = 0; c < CODECS; c++) {
            mr_exr_options opt = job->output.exr;
            opt.compression = k_codecs[c];
            opt.threads = threads;
            uint8_t *data = NULL;
            double t0 = mr_now();
            if (mr_exr_write_memory(&data, &bytes[c], film, &opt, &meta, &err) < 0)
                die("encode", err.msg);
            enc[c][i] = mr_now() - t0;
            free(data);
        }
    }
    double rs = median(render, repeats);
    for (size_t c = 0; c < CODECS; c++) {
        double e = median(enc[c], repeats);
        printf("| %-5s | %4dx%-4d | %9.1f | %9.1f | %5.1f %% | %8.2f |\n",
               mr_compression_name(k_codecs[c]), width, height, e * 1e3, rs * 1e3,
               100.0 * e / (e + rs), (double)bytes[c] / (1024.0 * 1024.0));
    }
    mr_film_free(film);
    mr_renderer_free(r);
}

int main(int argc, char **argv)
{
    const char *job_path = "examples/skinned-walk.json";
    for (int i = 1; i < argc; i++)
        if (!strcmp(argv[i], "--repeats") && i + 1 < argc)
            repeats = atoi(argv[++i]);
        else if (!strcmp(argv[i], "--threads") && i + 1 < argc)
            threads = (unsigned)atoi(argv[++i]);
        else if (!strcmp(argv[i], "--job") && i + 1 < argc)
            job_path = argv[++i];
    if (repeats < 1 || repeats > 64)
        repeats = 5;

    mr_error err = {0};
    mr_job_error jerr = {0};
    char *text = NULL;
    size_t len = 0;
    mr_job *job = NULL;
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

    printf("microray %s EXR encode: %u threads, medians of %d runs\n\n", MR_VERSION_STRING,
           mr_device_threads(dev), repeats);
    printf("%s frame 0, %d samples, %s; share = encode / (render + encode)\n\n", job->name,
           job->output.spp, job->output.shadows ? "shadows" : "no shadows");
    printf("| codec | size      | encode ms | render ms | share   | MiB      |\n");
    printf("|-------|-----------|-----------|-----------|---------|----------|\n");
    for (size_t s = 0; s < SIZES; s++)
        bench_size(dev, job, assets, k_sizes[s][0], k_sizes[s][1]);

    mr_device_free(dev);
    for (size_t i = 0; i < job->asset_count; i++)
        mr_asset_free(assets[i]);
    free(assets);
    mr_job_free(job);
    return 0;
}
