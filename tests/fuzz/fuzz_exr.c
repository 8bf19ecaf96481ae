/*
 * fuzz_exr.c - libFuzzer harness of the EXR reader: each input is the
 * content of an EXR file, read back with mr_exr_read_file
 * (core/render/exr.c on OpenEXRCore), as `microrayd compare` reads the two
 * frames it compares. The file is a memfd reached through /proc/self/fd, so
 * the reader gets a regular file (it refuses anything else) without disk
 * I/O. A film that was read is also compared with itself (compare.c walks
 * every plane, with whatever NaN or huge values the file held), when small.
 *
 * Seeds (tests/fuzz/corpus/fuzz_exr/): tiny frames in every compression we
 * write, made by mr_exr_write_memory (`fuzz_exr -seeds DIR` writes them).
 */
#define _GNU_SOURCE
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <unistd.h>

#include "microray.h"
#include "fuzz_seeds.h"

static int fd = -1;
static char path[64];

static void die(const char *what)
{
    fprintf(stderr, "fuzz_exr: %s\n", what);
    abort();
}

/* A small film with every AOV filled, for the seed files. */
static mr_film *seed_film(int w, int h)
{
    mr_film *f = NULL;
    if (mr_film_new(w, h, &f, NULL) < 0)
        die("mr_film_new");
    for (int i = 0; i < w * h; i++) {
        f->r[i] = 0.1f * (float)i;
        f->g[i] = 0.5f;
        f->b[i] = i % 3 ? 1.0f : -2.0f;
        f->a[i] = 1.0f;
        f->z[i] = 3.0f + (float)i;
        f->nx[i] = 0.0f, f->ny[i] = 1.0f, f->nz[i] = 0.0f;
        f->object_id[i] = (uint32_t)(i % 2);
        f->prim_id[i] = (uint32_t)i * 7u;
    }
    return f;
}

static void write_seeds(const char *dir)
{
    static const mr_compression comps[] = {MR_COMPRESSION_NONE, MR_COMPRESSION_ZIP,
                                           MR_COMPRESSION_ZIPS, MR_COMPRESSION_PIZ};
    mr_exr_meta meta = {.frame = 3, .time = 0.125, .render_seconds = 1.5, .scene_diagonal = 2.0f};
    snprintf(meta.job, sizeof meta.job, "seed");
    for (size_t i = 0; i < sizeof comps / sizeof comps[0]; i++) {
        mr_film *f = seed_film(5, 3 + (int)i);
        mr_exr_options opt = {.compression = comps[i], .threads = 1};
        uint8_t *data = NULL;
        size_t size = 0;
        if (mr_exr_write_memory(&data, &size, f, &opt, &meta, NULL) < 0)
            die("mr_exr_write_memory");
        char name[1024];
        snprintf(name, sizeof name, "%s/%s.exr", dir, mr_compression_name(comps[i]));
        FILE *out = fopen(name, "wb");
        if (!out || fwrite(data, 1, size, out) != size || fclose(out) != 0)
            die("cannot write a seed");
        free(data);
        mr_film_free(f);
    }
}

int LLVMFuzzerInitialize(int *argc, char ***argv)
{
    fuzz_seeds_option(*argc, *argv, write_seeds);
    fd = memfd_create("fuzz_exr", MFD_CLOEXEC);
    if (fd < 0)
        die("memfd_create");
    snprintf(path, sizeof path, "/proc/self/fd/%d", fd);
    return 0;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    if (ftruncate(fd, 0) != 0 || (size && pwrite(fd, data, size, 0) != (ssize_t)size))
        die("cannot fill the memfd");

    mr_film *film = NULL;
    mr_exr_meta meta;
    mr_error err;
    int rc = mr_exr_read_file(path, &film, &meta, &err);
    if (rc == MR_OK) {
        if (!film || film->width < 1 || film->height < 1 || film->width > MR_MAX_RESOLUTION ||
            film->height > MR_MAX_RESOLUTION)
            die("MR_OK without a film in the caps");
        if (!memchr(meta.job, '\0', sizeof meta.job))
            die("meta.job not terminated");
        if ((size_t)film->width * (size_t)film->height <= 256u * 256u) {
            mr_compare_result res;
            double diag = isfinite(meta.scene_diagonal) && meta.scene_diagonal > 0 ? meta.scene_diagonal : 1.0;
            if (mr_film_compare(film, film, diag, &res, NULL) != MR_OK)
                die("a film does not compare with itself");
        }
        mr_film_free(film);
    } else if (film) {
        die("an error with a film");
    }
    return 0;
}
