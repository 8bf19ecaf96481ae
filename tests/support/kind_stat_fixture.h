/*
 * kind_stat_fixture.h - one of a kind object's own per-frame stats fields
 * by name (kind.h frame_stats: read and cleared), for tests that drive a
 * kind's ops directly. Include after <cmocka.h>.
 */
#ifndef MR_TEST_KIND_STAT_FIXTURE_H
#define MR_TEST_KIND_STAT_FIXTURE_H

#include <string.h>

#include "kinds/kind.h"

static inline double fx_kind_stat(const mr_kind *kind, const mr_geom *g, const char *name)
{
    double v[MR_FRAME_EXTRAS_MAX] = {0};
    assert_true(kind->stat_count <= MR_FRAME_EXTRAS_MAX);
    kind->frame_stats(g, v);
    for (size_t i = 0; i < kind->stat_count; i++)
        if (!strcmp(kind->stats[i].name, name))
            return v[i];
    fail_msg("the %s kind has no stats field %s", kind->name, name);
    return 0;
}

#endif
