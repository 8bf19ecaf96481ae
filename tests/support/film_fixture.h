/*
 * film_fixture.h - bit-for-bit comparison of two films, for tests that
 * claim two renders are the same frame (thread counts, frame ranges,
 * resumed and retried jobs). Include after cmocka.h.
 */
#ifndef MR_TEST_FILM_FIXTURE_H
#define MR_TEST_FILM_FIXTURE_H

#include <string.h>

#include "microray.h"

/* Every plane of a and b holds the same bits; what names the frame in the
 * failure message. */
static inline void fx_assert_same_pixels(const mr_film *a, const mr_film *b, const char *what)
{
    assert_int_equal(a->width, b->width);
    assert_int_equal(a->height, b->height);
    size_t n = (size_t)a->width * (size_t)a->height;
    const float *fa[] = {a->r, a->g, a->b, a->a, a->z, a->nx, a->ny, a->nz};
    const float *fb[] = {b->r, b->g, b->b, b->a, b->z, b->nx, b->ny, b->nz};
    static const char *const name[] = {"R", "G", "B", "A", "Z", "N.X", "N.Y", "N.Z"};
    for (size_t p = 0; p < sizeof fa / sizeof *fa; p++)
        if (memcmp(fa[p], fb[p], n * sizeof(float)) != 0)
            fail_msg("%s: plane %s differs", what, name[p]);
    if (memcmp(a->object_id, b->object_id, n * sizeof(uint32_t)) != 0 ||
        memcmp(a->prim_id, b->prim_id, n * sizeof(uint32_t)) != 0)
        fail_msg("%s: the id planes differ", what);
}

#endif
