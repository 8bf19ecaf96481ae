/*
 * film.c - allocation of the per-AOV frame buffer (film.h).
 *
 * Every plane is its own calloc'ed block so a fresh film is already "all
 * miss" (zero) and so the EXR encoder and the comparison can walk planes
 * independently. The caps are checked before any size arithmetic, which
 * keeps width * height * sizeof(float) far from overflowing size_t.
 */
#include "render/film.h"

#include <stdlib.h>
#include <string.h>

static size_t film_pixels(const mr_film *film)
{
    return (size_t)film->width * (size_t)film->height;
}

int mr_film_new(int width, int height, mr_film **out, mr_error *err)
{
    mr_film *film = NULL;
    size_t n;

    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "mr_film_new: out is NULL");
    *out = NULL;
    if (width <= 0 || height <= 0)
        return mr_error_set(err, MR_ERR_INVALID,
                            "film size %dx%d: width and height must be positive",
                            width, height);
    if (width > MR_MAX_RESOLUTION || height > MR_MAX_RESOLUTION)
        return mr_error_set(err, MR_ERR_LIMIT,
                            "film size %dx%d: width and height must be at most %d",
                            width, height, MR_MAX_RESOLUTION);
    /* Both sides are <= 8192 here, so the product fits in size_t (and uint64). */
    n = (size_t)width * (size_t)height;
    if (n > (size_t)MR_MAX_PIXELS)
        return mr_error_set(err, MR_ERR_LIMIT,
                            "film size %dx%d: %zu pixels exceed the cap of %u "
                            "(width * height)",
                            width, height, n, (unsigned)MR_MAX_PIXELS);

    film = calloc(1, sizeof *film);
    if (!film)
        goto nomem;
    film->width = width;
    film->height = height;
    /* calloc checks n * size for overflow itself; the caps above make it moot. */
    film->r = calloc(n, sizeof(float));
    film->g = calloc(n, sizeof(float));
    film->b = calloc(n, sizeof(float));
    film->a = calloc(n, sizeof(float));
    film->z = calloc(n, sizeof(float));
    film->nx = calloc(n, sizeof(float));
    film->ny = calloc(n, sizeof(float));
    film->nz = calloc(n, sizeof(float));
    film->object_id = calloc(n, sizeof(uint32_t));
    film->prim_id = calloc(n, sizeof(uint32_t));
    if (!film->r || !film->g || !film->b || !film->a || !film->z || !film->nx ||
        !film->ny || !film->nz || !film->object_id || !film->prim_id)
        goto nomem;

    *out = film;
    return MR_OK;

nomem:
    mr_film_free(film);
    return mr_error_set(err, MR_ERR_NOMEM, "film size %dx%d: out of memory", width,
                        height);
}

void mr_film_free(mr_film *film)
{
    if (!film)
        return;
    free(film->r);
    free(film->g);
    free(film->b);
    free(film->a);
    free(film->z);
    free(film->nx);
    free(film->ny);
    free(film->nz);
    free(film->object_id);
    free(film->prim_id);
    free(film);
}

void mr_film_clear(mr_film *film)
{
    size_t n;

    if (!film || film->width <= 0 || film->height <= 0)
        return;
    n = film_pixels(film);
    /* All-zero bits are 0.0f in IEEE 754, i.e. "miss" for every plane. */
    if (film->r) memset(film->r, 0, n * sizeof(float));
    if (film->g) memset(film->g, 0, n * sizeof(float));
    if (film->b) memset(film->b, 0, n * sizeof(float));
    if (film->a) memset(film->a, 0, n * sizeof(float));
    if (film->z) memset(film->z, 0, n * sizeof(float));
    if (film->nx) memset(film->nx, 0, n * sizeof(float));
    if (film->ny) memset(film->ny, 0, n * sizeof(float));
    if (film->nz) memset(film->nz, 0, n * sizeof(float));
    if (film->object_id) memset(film->object_id, 0, n * sizeof(uint32_t));
    if (film->prim_id) memset(film->prim_id, 0, n * sizeof(uint32_t));
}
