/* previews.c - PNG previews of stored frames and their disk cache (previews.h). */
#include "previews.h"

#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

/* Part of every sheet's key: bump it when the drawing of a sheet changes,
 * so sheets cached by an older daemon are not served. Thumbnails are
 * checked by size only; bump SHEET_VERSION and rename THUMB_SUFFIX if their
 * drawing changes. */
#define SHEET_VERSION "microray contact sheet 1"
#define THUMB_SUFFIX ".thumb.png"
#define SHEET_PREFIX "contact-sheet-"
/* A thumbnail is at most 160 x 160 RGB; its PNG is far below this. */
#define THUMB_MAX_BYTES (1u << 20)

void mr_preview_body_free(mr_preview_body *b)
{
    if (!b)
        return;
    if (b->fd >= 0)
        close(b->fd);
    free(b->data);
    b->fd = -1;
    b->data = NULL;
    b->size = 0;
}

static void body_init(mr_preview_body *b)
{
    b->fd = -1;
    b->data = NULL;
    b->size = 0;
}

/* exr_path with its ".exr" replaced by suffix; NULL when out of memory or
 * when the path does not end in ".exr". */
static char *sibling(const char *exr_path, const char *suffix)
{
    size_t n = strlen(exr_path);
    if (n < 4 || strcmp(exr_path + n - 4, ".exr") != 0)
        return NULL;
    char *p = malloc(n - 4 + strlen(suffix) + 1);
    if (p) {
        memcpy(p, exr_path, n - 4);
        strcpy(p + n - 4, suffix);
    }
    return p;
}

static bool not_older(const struct stat *a, const struct stat *b)
{
    return a->st_mtim.tv_sec > b->st_mtim.tv_sec ||
           (a->st_mtim.tv_sec == b->st_mtim.tv_sec && a->st_mtim.tv_nsec >= b->st_mtim.tv_nsec);
}

/* Opens cache_path when it is a regular file not older than exr_path. */
static int open_fresh(const char *cache_path, const char *exr_path, size_t *size)
{
    struct stat se, sc;
    if (stat(exr_path, &se) != 0)
        return -1;
    int fd = open(cache_path, O_RDONLY | O_CLOEXEC | O_NOFOLLOW | O_NONBLOCK);
    if (fd < 0)
        return -1;
    if (fstat(fd, &sc) != 0 || !S_ISREG(sc.st_mode) || sc.st_size <= 0 || !not_older(&sc, &se)) {
        close(fd);
        return -1;
    }
    *size = (size_t)sc.st_size;
    return fd;
}

/* The EXR's film; MR_ERR_NOT_FOUND when the file is gone. */
static int read_exr(const char *exr_path, mr_film **film, mr_error *err)
{
    struct stat st;
    if (stat(exr_path, &st) != 0 && errno == ENOENT)
        return mr_error_set(err, MR_ERR_NOT_FOUND, "%s is gone", exr_path);
    return mr_exr_read_file(exr_path, film, NULL, err);
}

/* Best effort: a cache that cannot be written is made again next time. */
static void cache_write(const char *path, const uint8_t *data, size_t size)
{
    mr_error ignored = {0};
    (void)mr_fs_write_atomic(path, data, size, "preview cache", &ignored);
}

/* ---- a frame's preview ---------------------------------------------------- */

bool mr_preview_frame_cached(const char *exr_path, mr_preview_body *out)
{
    body_init(out);
    char *png = sibling(exr_path, ".png");
    if (!png)
        return false;
    out->fd = open_fresh(png, exr_path, &out->size);
    free(png);
    return out->fd >= 0;
}

int mr_preview_frame_build(const char *exr_path, bool may_cache, mr_preview_body *out,
                           mr_error *err)
{
    body_init(out);
    mr_film *film = NULL;
    mr_image8 img = {0};
    char *png = sibling(exr_path, ".png");
    if (!png)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    int rc = read_exr(exr_path, &film, err);
    if (rc == MR_OK)
        rc = mr_preview_from_film(film, &img, err);
    if (rc == MR_OK)
        rc = mr_png_encode(&img, &out->data, &out->size, err);
    if (rc == MR_OK && may_cache)
        cache_write(png, out->data, out->size);
    mr_image8_free(&img);
    mr_film_free(film);
    free(png);
    return rc;
}

/* ---- contact sheets ------------------------------------------------------- */

void mr_sheet_plan_key(mr_sheet_plan *plan)
{
    mr_sha256 s;
    mr_sha256_init(&s);
    mr_sha256_update(&s, SHEET_VERSION, sizeof SHEET_VERSION);
    uint64_t v = plan->frame_count;
    mr_sha256_update(&s, &v, sizeof v);
    for (size_t i = 0; i < plan->count; i++) {
        uint64_t cell[2] = {plan->index[i], plan->exr[i] != NULL};
        mr_sha256_update(&s, cell, sizeof cell);
    }
    uint8_t digest[32];
    mr_sha256_final(&s, digest);
    mr_hex_encode(digest, 8, plan->key);
}

/* The folder of the job's frames (that of a done frame), or NULL when no
 * frame of the plan is done yet (then nothing is cached). */
static char *frames_dir(const mr_sheet_plan *plan)
{
    for (size_t i = 0; i < plan->count; i++)
        if (plan->exr[i])
            return mr_fs_dir_of(plan->exr[i]);
    return NULL;
}

static char *sheet_path(const char *dir, const char *key)
{
    size_t n = strlen(dir) + sizeof SHEET_PREFIX + 16 + 8;
    char *p = malloc(n);
    if (p)
        snprintf(p, n, "%s/" SHEET_PREFIX "%s.png", dir, key);
    return p;
}

bool mr_preview_sheet_cached(const mr_sheet_plan *plan, mr_preview_body *out)
{
    body_init(out);
    char *dir = frames_dir(plan), *path = dir ? sheet_path(dir, plan->key) : NULL;
    const char *exr = NULL;
    for (size_t i = 0; i < plan->count && !exr; i++)
        exr = plan->exr[i];
    /* any done frame's EXR will do as the "not older than" reference: the
     * key already says which frames the sheet shows */
    if (path && exr)
        out->fd = open_fresh(path, exr, &out->size);
    free(path);
    free(dir);
    return out->fd >= 0;
}

/* Removes the sheets of other keys (they showed fewer finished frames). */
static void remove_other_sheets(const char *dir, const char *key)
{
    DIR *d = opendir(dir);
    if (!d)
        return;
    char mine[64];
    snprintf(mine, sizeof mine, SHEET_PREFIX "%s.png", key);
    struct dirent *e;
    while ((e = readdir(d)) != NULL) {
        size_t n = strlen(e->d_name);
        if (!strncmp(e->d_name, SHEET_PREFIX, sizeof SHEET_PREFIX - 1) && n > 4 &&
            !strcmp(e->d_name + n - 4, ".png") && strcmp(e->d_name, mine) != 0)
            unlinkat(dirfd(d), e->d_name, 0);
    }
    closedir(d);
}

/* Frame exr_path's thumbnail of tw x th: the cached one when fresh and of
 * that size, else made from the EXR (and cached when may_cache). */
static int thumbnail(const char *exr_path, int tw, int th, bool may_cache, mr_image8 *out,
                     mr_error *err)
{
    memset(out, 0, sizeof *out);
    char *path = sibling(exr_path, THUMB_SUFFIX);
    if (!path)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    size_t size = 0;
    int fd = open_fresh(path, exr_path, &size);
    if (fd >= 0) {
        close(fd);
        uint8_t *bytes = NULL;
        mr_error ignored = {0};
        if (mr_fs_read_capped(path, THUMB_MAX_BYTES, &bytes, &size, "thumbnail", &ignored) == MR_OK &&
            mr_png_decode(bytes, size, path, out, &ignored) == MR_OK &&
            (out->width != tw || out->height != th || out->channels != 3))
            mr_image8_free(out);
        free(bytes);
        if (out->px) {
            free(path);
            return MR_OK;
        }
    }
    mr_film *film = NULL;
    uint8_t *png = NULL;
    int rc = read_exr(exr_path, &film, err);
    if (rc == MR_OK)
        rc = mr_preview_thumbnail(film, out, err);
    if (rc == MR_OK && may_cache && mr_png_encode(out, &png, &size, err) == MR_OK)
        cache_write(path, png, size);
    free(png);
    mr_film_free(film);
    free(path);
    return rc;
}

int mr_preview_sheet_build(const mr_sheet_plan *plan, int width, int height, bool may_cache,
                           mr_preview_body *out, size_t *bad_frame, mr_error *err)
{
    body_init(out);
    int tw, th;
    mr_preview_thumb_size(width, height, &tw, &th);
    mr_image8 sheet = {0}, thumb = {0};
    char *dir = NULL, *path = NULL;
    int rc = mr_contact_sheet_new(plan->count, tw, th, &sheet, err);
    for (size_t i = 0; i < plan->count && rc == MR_OK; i++) {
        if (!plan->exr[i])
            continue;
        rc = thumbnail(plan->exr[i], tw, th, may_cache, &thumb, err);
        if (rc == MR_OK)
            rc = mr_contact_sheet_put(&sheet, i, &thumb, err);
        mr_image8_free(&thumb);
        if (rc < 0 && bad_frame)
            *bad_frame = plan->index[i];
    }
    if (rc == MR_OK)
        rc = mr_png_encode(&sheet, &out->data, &out->size, err);
    if (rc == MR_OK && may_cache && (dir = frames_dir(plan)) && (path = sheet_path(dir, plan->key))) {
        cache_write(path, out->data, out->size);
        remove_other_sheets(dir, plan->key);
    }
    free(path);
    free(dir);
    mr_image8_free(&sheet);
    return rc;
}
