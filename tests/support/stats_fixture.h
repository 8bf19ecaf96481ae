/*
 * stats_fixture.h - frame statistics with values that print differently
 * under any careless conversion (0.1, 1/3, 2^40 + 1 rays, a float diagonal),
 * the job they belong to, and the recorded documents the stats writer
 * (server/stats_json.c) gives for them, for the unit test of the writer and
 * the HTTP test of the daemon's stats. Include after <cmocka.h>.
 */
#ifndef MR_TEST_STATS_FIXTURE_H
#define MR_TEST_STATS_FIXTURE_H

#include <stdio.h>
#include <string.h>

#include "render/renderer.h"

/* Frame 0: a first frame with a partial scene-cache result; 1: awkward
 * numbers; any other: a cache hit, all else 0. */
static inline mr_frame_stats frame_fixture(int i)
{
    static const mr_frame_stats first = {
        .time = 0.5, .load_s = 0.25, .derive_s = 0.0625, .assets_cached = 1, .assets_loaded = 2,
        .load_saved_s = 0.125,
        .pose_s = 0.001, .bvh_s = 0.003, .bvh = MR_BVH_BUILD, .trace_s = 0.11, .encode_s = 0.2,
        .total_s = 0.36, .rays = 1586211, .mrays_per_s = 14.4, .triangles = 5126,
        .geometry_bytes = 159188, .bvh_bytes = 622592, .peak_rss_bytes = 52428800,
        .scene_diagonal = 1.94f, .speckle_pct = 0.25};
    static const mr_frame_stats awkward = {
        .time = 0.75, .pose_s = 1.0 / 3.0, .bvh_s = 0.1, .bvh = MR_BVH_REFIT, .trace_s = 2.5e-7,
        .encode_s = 12345.678, .total_s = 1e-3, .rays = ((uint64_t)1 << 40) + 1,
        .triangles = 4294967296ull, .geometry_bytes = 1, .peak_rss_bytes = 123456789012ull,
        .scene_diagonal = 0.1f, .speckle_pct = 100.0 / 3.0};
    mr_frame_stats f = i == 0 ? first : i == 1 ? awkward : (mr_frame_stats){.time = 1.0 * i};
    if (i > 1) {
        f.assets_cached = 3;
        f.load_saved_s = 2.0;
    }
    f.frame = i;
    return f;
}

static inline mr_job job_fixture(void)
{
    mr_job j;
    memset(&j, 0, sizeof j);
    j.name = "golden \"walk\"";
    j.output.width = 192;
    j.output.height = 108;
    j.output.spp = 3;
    j.frame_count = 4;
    return j;
}

static inline void expect_text(const char *got, const char *want)
{
    assert_non_null(got);
    if (strcmp(got, want) != 0) {
        fprintf(stderr, "got:\n%s\nwanted:\n%s\n", got, want);
        fail();
    }
}

/* What mr_frame_stats_json gives for frame_fixture(0), (1) and (2) (as
 * macros too, for documents that hold them). */
#define FRAME0_TEXT \
    "{\"frame\":0,\"time\":0.5,\"file\":\"0000.exr\",\"seconds\":{\"load\":0.25,\"derive\":0.0625,\"pose\":0.001," \
    "\"bvh\":0.003,\"trace\":0.11,\"encode\":0.2,\"total\":0.36},\"bvh\":\"build\",\"rays\":1586211," \
    "\"mrays_per_s\":14.4,\"triangles\":5126,\"bytes\":{\"geometry\":159188,\"bvh\":622592," \
    "\"peak_rss\":52428800},\"scene_diagonal\":1.940000057220459,\"speckle_pct\":0.25,\"cache\":{\"result\":\"partial\"," \
    "\"assets_cached\":1,\"assets_loaded\":2,\"saved_s\":0.125}}"

#define FRAME1_TEXT \
    "{\"frame\":1,\"time\":0.75,\"file\":\"0001.exr\",\"seconds\":{\"load\":0,\"derive\":0," \
    "\"pose\":0.33333333333333331,\"bvh\":0.1,\"trace\":2.5e-07,\"encode\":12345.678,\"total\":0.001}," \
    "\"bvh\":\"refit\",\"rays\":1099511627777,\"mrays_per_s\":0,\"triangles\":4294967296," \
    "\"bytes\":{\"geometry\":1,\"bvh\":0,\"peak_rss\":123456789012}," \
    "\"scene_diagonal\":0.10000000149011612,\"speckle_pct\":33.333333333333336}"

#define FRAME2_TEXT \
    "{\"frame\":2,\"time\":2,\"file\":\"0002.exr\",\"seconds\":{\"load\":0,\"derive\":0,\"pose\":0,\"bvh\":0," \
    "\"trace\":0,\"encode\":0,\"total\":0},\"bvh\":\"none\",\"rays\":0,\"mrays_per_s\":0," \
    "\"triangles\":0,\"bytes\":{\"geometry\":0,\"bvh\":0,\"peak_rss\":0},\"scene_diagonal\":0,\"speckle_pct\":0," \
    "\"cache\":{\"result\":\"hit\",\"assets_cached\":3,\"assets_loaded\":0,\"saved_s\":2}}"

static const char FRAME0[] = FRAME0_TEXT, FRAME1[] = FRAME1_TEXT, FRAME2[] = FRAME2_TEXT;

#endif
