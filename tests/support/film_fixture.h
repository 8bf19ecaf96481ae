/*
 * film_fixture.h - bit-for-bit comparison of two films, for tests that
 * claim two renders are the same frame (thread counts, frame ranges,
 * resumed and retried jobs), and a rendered frame's own stats fields by
 * name. Include after cmocka.h.
 */
#ifndef MR_TEST_FILM_FIXTURE_H
#define MR_TEST_FILM_FIXTURE_H

#include <string.h>

#include "microray.h"

/* a and b have the same passes and every plane holds the same bits; what
 * names the frame in the failure message. */
static inline void fx_assert_same_pixels(const mr_film *a, const mr_film *b, const char *what)
{
    assert_int_equal(a->width, b->width);
    assert_int_equal(a->height, b->height);
    if (a->aovs != b->aovs || a->crypto_ranks != b->crypto_ranks)
        fail_msg("%s: the passes differ (0x%x against 0x%x)", what, a->aovs, b->aovs);
    size_t n = (size_t)a->width * (size_t)a->height;
    const void *pa[] = {a->r, a->g, a->b, a->a, a->z, a->nx, a->ny, a->nz,
                        a->px, a->py, a->pz, a->tx, a->ty, a->tz, a->object_id, a->prim_id};
    const void *pb[] = {b->r, b->g, b->b, b->a, b->z, b->nx, b->ny, b->nz,
                        b->px, b->py, b->pz, b->tx, b->ty, b->tz, b->object_id, b->prim_id};
    static const char *const name[] = {"R", "G", "B", "A", "Z", "N.X", "N.Y", "N.Z",
                                       "P.X", "P.Y", "P.Z", "T.X", "T.Y", "T.Z", "id.object", "id.primitive"};
    for (size_t p = 0; p < sizeof pa / sizeof *pa; p++)
        if (pa[p] && memcmp(pa[p], pb[p], n * 4) != 0) /* every plane: 4-byte values */
            fail_msg("%s: plane %s differs", what, name[p]);
    for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
        for (int k = 0; k < 2 * a->crypto_ranks; k++)
            if (a->crypto[l][k] && memcmp(a->crypto[l][k], b->crypto[l][k], n * sizeof(float)) != 0)
                fail_msg("%s: Cryptomatte layer %d plane %d differs", what, l, k);
}

/* The kind's stats field `name` of a rendered frame (its extras); fails the
 * test naming the field when the frame does not carry it, so a renamed
 * field cannot read as 0. */
static inline double fx_frame_extra(const mr_frame_stats *st, const char *name)
{
    for (uint32_t i = 0; i < st->extra_count; i++)
        if (strcmp(st->extras[i].name, name) == 0)
            return st->extras[i].value;
    fail_msg("frame %d has no stats field %s", st->frame, name);
    return 0;
}

#endif
