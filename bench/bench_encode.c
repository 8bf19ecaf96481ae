/*
 * bench_encode.c - EXR encoding as a share of frame time (make bench).
 * Not a test: it prints figures, it never fails on a time.
 *
 * The example job (examples/skinned-walk.json, as parsed: its passes, 2
 * samples, shadows) is rendered at 640x360, 960x540 (the example's own
 * size), 1280x720, 1920x1080 and 3840x2160; each frame is then encoded
 * with every codec, all interleaved and repeated, and the table gives
 * medians: encode ms, render ms (the frame's total: pose, BVH and trace),
 * the share encode / (render + encode) and the file size; beside the wall
 * times the CPU times of encode and render (all threads) and the share of
 * those, which other load on the machine moves much less (a busy machine
 * stretches wall times, not the work done). Encoding uses all cores, as
 * the renderer does. A second table does the same at the example's size
 * with the default codec for other choices of passes.
 *
 * Written against the public API only (core/microray.h) plus the server's
 * job parser.
 *
 * usage: bench_encode [--repeats N] [--threads N] [--job FILE]   (from the repository root)
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

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

static const int k_sizes[][2] = {{640, 360}, {960, 540}, {1280, 720}, {1920, 1080}, {3840, 2160}};
#define SIZES (sizeof k_sizes / sizeof k_sizes[0])

/* Renders frame 0 of job at width x height `repeats` times and encodes each
 * render with the codecs; prints one row per codec (label: the first
 * column, or the codec's name). */
static void bench_size(mr_device *dev, mr_job *job, mr_asset **assets, int width, int height,
                       const mr_compression *codecs, size_t ncodecs, const char *label)
{
    mr_error err = {0};
    mr_renderer *r = NULL;
    mr_film *film = NULL;
    job->output.width = width;
    job->output.height = height;
    if (mr_renderer_new(dev, job, assets, NULL, &r, &err) < 0 ||
        mr_job_film_new(job, &film, &err) < 0)
        die("setup", err.msg);

    double render[64], render_cpu[64], enc[CODECS][64], cpu[CODECS][64];
    size_t bytes[CODECS] = {0};
    mr_frame_stats st;
    for (int i = 0; i < repeats; i++) {
        double rc0 = bench_cpu_now();
        if (mr_renderer_render(r, 0, film, &st, &err) < 0)
            die("render", err.msg);
        render_cpu[i] = bench_cpu_now() - rc0;
        render[i] = st.total_s;
        mr_exr_meta meta;
        mr_exr_meta_for_frame(&meta, job, &st);
        for (size_t c = 0; c < ncodecs; c++) {
            mr_exr_options opt = job->output.exr;
            opt.compression = codecs[c];
            opt.threads = threads;
            uint8_t *data = NULL;
            double t0 = mr_now(), c0 = bench_cpu_now();
            if (mr_exr_write_memory(&data, &bytes[c], film, &opt, &meta, &err) < 0)
                die("encode", err.msg);
            enc[c][i] = mr_now() - t0;
            cpu[c][i] = bench_cpu_now() - c0;
            free(data);
        }
    }
    double rs = median(render, repeats), rcs = median(render_cpu, repeats);
    for (size_t c = 0; c < ncodecs; c++) {
        double e = median(enc[c], repeats), ec = median(cpu[c], repeats);
        printf("| %-24s | %4dx%-4d | %9.1f | %13.1f | %9.1f | %13.1f | %5.1f %% | %9.1f %% "
               "| %8.3f |\n",
               label ? label : mr_compression_name(codecs[c]), width, height, e * 1e3, ec * 1e3,
               rs * 1e3, rcs * 1e3, 100.0 * e / (e + rs), 100.0 * ec / (ec + rcs),
               (double)bytes[c] / (1024.0 * 1024.0));
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
    printf("%s frame 0, %d samples, %s; share = encode / (render + encode), CPU share the same "
           "of CPU times\n\n", job->name,
           job->output.spp, job->output.shadows ? "shadows" : "no shadows");
    printf("| codec                    | size      | encode ms | encode CPU ms | render ms | render CPU ms | share   | CPU share   | MiB      |\n");
    printf("|--------------------------|-----------|-----------|---------------|-----------|---------------|---------|-------------|----------|\n");
    for (size_t s = 0; s < SIZES; s++)
        bench_size(dev, job, assets, k_sizes[s][0], k_sizes[s][1], k_codecs, CODECS, NULL);

    /* Passes at the example's size, default codec. */
    static const struct {
        const char *label;
        unsigned aovs;
        bool half_normals;
    } passes[] = {
        {"rgba z n id (default)", MR_AOV_DEFAULT, false},
        {"rgba z n id, half n", MR_AOV_DEFAULT, true},
        {"rgba z id", MR_AOV_RGBA | MR_AOV_Z | MR_AOV_ID, false},
        {"rgba z", MR_AOV_RGBA | MR_AOV_Z, false},
        /* the six passes of the README's table (measured before "t" came) */
        {"all six", MR_AOV_ALL & ~MR_AOV_T, false},
    };
    unsigned aovs = job->output.aovs;
    bool half = job->output.exr.half_normals;
    printf("\nPasses, %s, %dx%d (render ms includes what each choice traces)\n\n",
           mr_compression_name(job->output.exr.compression), 960, 540);
    printf("| passes                   | size      | encode ms | encode CPU ms | render ms | render CPU ms | share   | CPU share   | MiB      |\n");
    printf("|--------------------------|-----------|-----------|---------------|-----------|---------------|---------|-------------|----------|\n");
    for (size_t p = 0; p < sizeof passes / sizeof passes[0]; p++) {
        job->output.aovs = passes[p].aovs;
        job->output.exr.half_normals = passes[p].half_normals;
        bench_size(dev, job, assets, 960, 540, &job->output.exr.compression, 1, passes[p].label);
    }
    job->output.aovs = aovs;
    job->output.exr.half_normals = half;

    mr_device_free(dev);
    for (size_t i = 0; i < job->asset_count; i++)
        mr_asset_free(assets[i]);
    free(assets);
    mr_job_free(job);
    return 0;
}
