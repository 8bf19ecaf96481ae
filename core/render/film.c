/*
 * film.c - allocation of the per-AOV frame buffer (film.h).
 *
 * Every plane is its own block so the EXR encoder and the comparison can
 * walk planes independently, and only the planes of the passes asked for
 * exist (a NULL plane is a pass the film does not have). The caps are
 * checked before any size arithmetic, which keeps width * height *
 * sizeof(float) far from overflowing size_t.
 */
#include "render/film.h"
#include "util/large_alloc.h"

#include <stdlib.h>
#include <string.h>

static const char *const k_aov_names[MR_AOV_COUNT] = {"rgba", "z", "n", "p", "id", "cryptomatte", "t"};

const char *mr_aov_name(mr_aov aov)
{
    for (int i = 0; i < MR_AOV_COUNT; i++)
        if ((unsigned)aov == 1u << i)
            return k_aov_names[i];
    return NULL;
}

bool mr_aov_parse(const char *name, mr_aov *out)
{
    if (!name)
        return false;
    for (int i = 0; i < MR_AOV_COUNT; i++)
        if (strcmp(name, k_aov_names[i]) == 0) {
            if (out)
                *out = (mr_aov)(1u << i);
            return true;
        }
    return false;
}

static size_t film_pixels(const mr_film *film)
{
    return (size_t)film->width * (size_t)film->height;
}

#define FILM_SLOTS (16 + MR_CRYPTO_LAYERS * 2 * MR_CRYPTO_MAX_RANKS)

/* Where every plane pointer of the film lives (NULL or not), for
 * freeing and clearing them alike. Returns how many (FILM_SLOTS). */
static size_t film_slots(mr_film *f, void **slot[FILM_SLOTS])
{
    void **fixed[] = {(void **)&f->r,  (void **)&f->g,  (void **)&f->b,  (void **)&f->a,
                      (void **)&f->z,  (void **)&f->nx, (void **)&f->ny, (void **)&f->nz,
                      (void **)&f->px, (void **)&f->py, (void **)&f->pz,
                      (void **)&f->tx, (void **)&f->ty, (void **)&f->tz,
                      (void **)&f->object_id, (void **)&f->prim_id};
    size_t n = 0;
    for (size_t i = 0; i < sizeof fixed / sizeof fixed[0]; i++)
        slot[n++] = fixed[i];
    for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
        for (int k = 0; k < 2 * MR_CRYPTO_MAX_RANKS; k++)
            slot[n++] = (void **)&f->crypto[l][k];
    return n;
}

/* Ranks per Cryptomatte layer a film gets for crypto_ranks asked. */
static int film_crypto_ranks(int crypto_ranks)
{
    int ranks = crypto_ranks < 2 ? 2 : crypto_ranks > MR_CRYPTO_MAX_RANKS ? MR_CRYPTO_MAX_RANKS
                                                                          : crypto_ranks;
    return ranks + (ranks & 1);
}

size_t mr_film_bytes(int width, int height, unsigned aovs, int crypto_ranks)
{
    if (width <= 0 || height <= 0)
        return 0;
    size_t planes = ((aovs & MR_AOV_RGBA) ? 4u : 0u) + ((aovs & MR_AOV_Z) ? 1u : 0u) +
                    ((aovs & MR_AOV_N) ? 3u : 0u) + ((aovs & MR_AOV_P) ? 3u : 0u) +
                    ((aovs & MR_AOV_ID) ? 2u : 0u) + ((aovs & MR_AOV_T) ? 3u : 0u);
    if (aovs & MR_AOV_CRYPTOMATTE)
        planes += (size_t)MR_CRYPTO_LAYERS * 2u * (size_t)film_crypto_ranks(crypto_ranks);
    return (size_t)width * (size_t)height * planes * 4u;
}

int mr_film_new_aovs(int width, int height, unsigned aovs, int crypto_ranks, mr_film **out,
                     mr_error *err)
{
    mr_film *film = NULL;
    size_t n;

    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "mr_film_new: out is NULL");
    *out = NULL;
    if (aovs == 0 || (aovs & ~MR_AOV_ALL))
        return mr_error_set(err, MR_ERR_INVALID, "film passes 0x%x: expected a non-empty set of "
                            "rgba, z, n, p, id, cryptomatte, t", aovs);
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
    film->aovs = aovs;
    /* malloc checks nothing for overflow, but the caps above make it moot. */
#define PLANE(p) ((p) = mr_large_alloc(n * 4u), (p) != NULL)
    if ((aovs & MR_AOV_RGBA) &&
        !(PLANE(film->r) && PLANE(film->g) && PLANE(film->b) && PLANE(film->a)))
        goto nomem;
    if ((aovs & MR_AOV_Z) && !PLANE(film->z))
        goto nomem;
    if ((aovs & MR_AOV_N) && !(PLANE(film->nx) && PLANE(film->ny) && PLANE(film->nz)))
        goto nomem;
    if ((aovs & MR_AOV_P) && !(PLANE(film->px) && PLANE(film->py) && PLANE(film->pz)))
        goto nomem;
    if ((aovs & MR_AOV_ID) && !(PLANE(film->object_id) && PLANE(film->prim_id)))
        goto nomem;
    if ((aovs & MR_AOV_T) && !(PLANE(film->tx) && PLANE(film->ty) && PLANE(film->tz)))
        goto nomem;
    if (aovs & MR_AOV_CRYPTOMATTE) {
        film->crypto_ranks = film_crypto_ranks(crypto_ranks);
        for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
            for (int k = 0; k < 2 * film->crypto_ranks; k++)
                if (!PLANE(film->crypto[l][k]))
                    goto nomem;
    }
#undef PLANE
    mr_film_clear(film);
    *out = film;
    return MR_OK;

nomem:
    mr_film_free(film);
    return mr_error_set(err, MR_ERR_NOMEM, "film size %dx%d: out of memory", width,
                        height);
}

int mr_film_new(int width, int height, mr_film **out, mr_error *err)
{
    return mr_film_new_aovs(width, height, MR_AOV_DEFAULT, 0, out, err);
}

void mr_film_free(mr_film *film)
{
    void **slot[FILM_SLOTS];
    size_t count;

    if (!film)
        return;
    count = film_slots(film, slot);
    for (size_t i = 0; i < count; i++)
        free(*slot[i]);
    free(film->misses); /* one block (integrator.c) */
    free(film);
}

void mr_film_clear(mr_film *film)
{
    void **slot[FILM_SLOTS];
    size_t n, count;

    if (!film || film->width <= 0 || film->height <= 0)
        return;
    free(film->misses);
    film->misses = NULL;
    n = film_pixels(film);
    /* All-zero bits are 0.0f in IEEE 754, i.e. "miss" for every plane but
     * depth. */
    count = film_slots(film, slot);
    for (size_t i = 0; i < count; i++)
        if (*slot[i])
            memset(*slot[i], 0, n * 4u);
    if (film->z)
        for (size_t i = 0; i < n; i++)
            film->z[i] = MR_DEPTH_MISS;
    film->cleared = true;
}
