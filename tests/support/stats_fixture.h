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

static inline mr_frame_stats frame_fixture(int i)
{
    mr_frame_stats f;
    memset(&f, 0, sizeof f);
    f.frame = i;
    switch (i) {
    case 0:
        f.time = 0.5;
        f.load_s = 0.25;
        f.assets_cached = 1;
        f.assets_loaded = 2;
        f.load_saved_s = 0.125;
        f.pose_s = 0.001;
        f.bvh_s = 0.003;
        f.bvh = MR_BVH_BUILD;
        f.trace_s = 0.11;
        f.encode_s = 0.2;
        f.total_s = 0.36;
        f.rays = 1586211;
        f.mrays_per_s = 14.4;
        f.triangles = 5126;
        f.geometry_bytes = 159188;
        f.bvh_bytes = 622592;
        f.peak_rss_bytes = 52428800;
        f.scene_diagonal = 1.94f;
        break;
    case 1:
        f.time = 0.75;
        f.pose_s = 1.0 / 3.0;
        f.bvh_s = 0.1;
        f.bvh = MR_BVH_REFIT;
        f.trace_s = 2.5e-7;
        f.encode_s = 12345.678;
        f.total_s = 1e-3;
        f.rays = ((uint64_t)1 << 40) + 1;
        f.mrays_per_s = 0.0;
        f.triangles = 4294967296ull;
        f.geometry_bytes = 1;
        f.bvh_bytes = 0;
        f.peak_rss_bytes = 123456789012ull;
        f.scene_diagonal = 0.1f;
        break;
    default:
        f.time = 1.0 * i;
        f.bvh = MR_BVH_NONE;
        f.assets_cached = 3; /* a cache hit: "hit" */
        f.load_saved_s = 2.0;
        break;
    }
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

/* What mr_frame_stats_json gives for frame_fixture(0), (1) and (2). */
static const char FRAME0[] =
    "{\"frame\":0,\"time\":0.5,\"file\":\"0000.exr\",\"seconds\":{\"load\":0.25,\"pose\":0.001,"
    "\"bvh\":0.003,\"trace\":0.11,\"encode\":0.2,\"total\":0.36},\"bvh\":\"build\",\"rays\":1586211,"
    "\"mrays_per_s\":14.4,\"triangles\":5126,\"bytes\":{\"geometry\":159188,\"bvh\":622592,"
    "\"peak_rss\":52428800},\"scene_diagonal\":1.940000057220459,\"cache\":{\"result\":\"partial\","
    "\"assets_cached\":1,\"assets_loaded\":2,\"saved_s\":0.125}}";

static const char FRAME1[] =
    "{\"frame\":1,\"time\":0.75,\"file\":\"0001.exr\",\"seconds\":{\"load\":0,"
    "\"pose\":0.33333333333333331,\"bvh\":0.1,\"trace\":2.5e-07,\"encode\":12345.678,\"total\":0.001},"
    "\"bvh\":\"refit\",\"rays\":1099511627777,\"mrays_per_s\":0,\"triangles\":4294967296,"
    "\"bytes\":{\"geometry\":1,\"bvh\":0,\"peak_rss\":123456789012},"
    "\"scene_diagonal\":0.10000000149011612}";

static const char FRAME2[] =
    "{\"frame\":2,\"time\":2,\"file\":\"0002.exr\",\"seconds\":{\"load\":0,\"pose\":0,\"bvh\":0,"
    "\"trace\":0,\"encode\":0,\"total\":0},\"bvh\":\"none\",\"rays\":0,\"mrays_per_s\":0,"
    "\"triangles\":0,\"bytes\":{\"geometry\":0,\"bvh\":0,\"peak_rss\":0},\"scene_diagonal\":0,"
    "\"cache\":{\"result\":\"hit\",\"assets_cached\":3,\"assets_loaded\":0,\"saved_s\":2}}";

#endif
