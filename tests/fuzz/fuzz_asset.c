/*
 * fuzz_asset.c - libFuzzer harness of asset import: mr_asset_load
 * (core/asset/asset.c: the size and count prechecks, the confined file
 * system that keeps a model's references inside its folder, assimp, and the
 * conversion of its scene into our arrays) on a file holding the input, as
 * the daemon's import worker (server/import_worker.c) runs it in its child
 * process. An imported asset then goes through the worker's hand-back,
 * mr_asset_blob_write and mr_asset_blob_read, which must give the same
 * counts back.
 *
 * Input: the first byte picks the file's extension (assimp chooses its
 * reader by it, then by content), the rest is the file. Files that start
 * with a PNG, JPEG or EXR signature are images (asset/image.c: libpng,
 * libjpeg, OpenEXR) whatever the extension; the seed corpus holds one of
 * each. Each input is
 * written to a fresh file in a private folder (on /dev/shm when there is
 * one) that holds nothing else, so a model naming other files (.mtl, glTF
 * buffers) finds none or is refused.
 *
 * assimp is neither instrumented nor leak-free, and allocates what a header
 * claims: tests/fuzz/fuzz_asset.options caps input size, memory and time,
 * and turns libFuzzer's leak check after each input off (docs/fuzzing.md).
 * LeakSanitizer's check at exit still runs, and reports only our leaks: see
 * __lsan_default_suppressions below.
 */
#define _GNU_SOURCE /* nftw (fuzz_tmp.h) */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "fuzz_tmp.h"
#include "microray.h"

static const char *const EXTS[] = {"obj", "ply", "off", "x",   "gltf", "glb", "stl",
                                   "smd", "dae", "fbx", "png", "jpg", "exr"};
#define EXT_COUNT (sizeof EXTS / sizeof EXTS[0])

static char dir[128];
static unsigned long serial;

/* LeakSanitizer's suppressions, read at start-up: a leaked block allocated
 * with a frame in assimp, or by C++'s operator new (libstdc++; our code is C,
 * so only a C++ library such as assimp allocates that way), is assimp's own
 * leak (its X reader loses nodes on broken files). The stacks are cut short
 * at libstdc++, which has no frame pointers, so both names are needed; a
 * block our code allocates with malloc and loses is still reported.
 * tests/fuzz/crashers/fuzz_asset/leak-4cf61549... is such a file. */
const char *__lsan_default_suppressions(void);
const char *__lsan_default_suppressions(void)
{
    return "leak:libassimp.so\n"
           "leak:libstdc++.so\n";
}

static void die(const char *what)
{
    fprintf(stderr, "fuzz_asset: %s\n", what);
    abort();
}

static void cleanup(void)
{
    fuzz_tmp_remove(dir);
}

int LLVMFuzzerInitialize(int *argc, char ***argv)
{
    (void)argc, (void)argv;
    if (fuzz_tmp_make("fuzz-asset", dir, sizeof dir) != 0)
        die("mkdtemp");
    atexit(cleanup);
    return 0;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    if (size < 1)
        return 0;
    char path[128];
    /* A new name each time: nothing (assimp included) can keep state keyed
     * by the path. */
    snprintf(path, sizeof path, "%s/m%lu.%s", dir, serial++, EXTS[data[0] % EXT_COUNT]);
    FILE *f = fopen(path, "wb");
    if (!f || (size > 1 && fwrite(data + 1, 1, size - 1, f) != size - 1) || fclose(f) != 0)
        die("cannot write the model file");

    mr_asset *a = NULL;
    mr_error err;
    int rc = mr_asset_load(path, &a, &err);
    unlink(path);
    if (rc != MR_OK) {
        if (a)
            die("an error with an asset");
        if (!err.msg[0])
            die("an error without a message");
        return 0;
    }
    /* a model has triangles; an image (a file with an image signature:
     * PNG, JPEG, EXR) has pixels and none */
    uint32_t w = 0, h = 0;
    bool image = mr_asset_image_size(a, &w, &h);
    if (!a || (!image && mr_asset_triangle_count(a) == 0))
        die("MR_OK without triangles");
    if (image && (w == 0 || h == 0 || w > MR_MAX_IMAGE_SIDE || h > MR_MAX_IMAGE_SIDE ||
                  (uint64_t)w * h > MR_MAX_IMAGE_PIXELS || mr_asset_triangle_count(a) != 0))
        die("an image asset outside the caps or with triangles");

    uint8_t *blob = NULL;
    size_t blob_size = 0;
    if (mr_asset_blob_write(a, &blob, &blob_size, &err) == MR_OK) {
        mr_asset *b = NULL;
        if (mr_asset_blob_read(blob, blob_size, &b, &err) != MR_OK)
            die("a blob we wrote does not read back");
        if (mr_asset_triangle_count(b) != mr_asset_triangle_count(a) ||
            mr_asset_memory(b) != mr_asset_memory(a))
            die("a blob read back differs");
        mr_asset_free(b);
        /* A blob cut short anywhere must be refused, never overread. */
        if (blob_size > 1 && mr_asset_blob_read(blob, blob_size / 2, &b, &err) == MR_OK)
            die("half a blob was accepted");
        free(blob);
    }
    mr_asset_free(a);
    return 0;
}
