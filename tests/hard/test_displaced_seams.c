/*
 * test_displaced_seams.c - no cracks between displaced base triangles
 * (issue 14, part 5), proved with rays along every shared edge.
 *
 * Two base triangles that share an edge (the same two vertices) compute the
 * micro-vertices along it from the edge alone (dsurf.h), so their
 * micro-triangles meet in bit-identical points. For every shared edge of a
 * mesh, the points where the displaced surface runs along it (the edge's
 * corners and grid crossings, in order) are taken from one side, and rays
 * are shot from random directions at points on every micro-segment between
 * them (its middle and four other fractions): a ray through a point of the
 * surface hits it, at that point or before, unless there is a crack. Every
 * ray is traced through the kind (Embree and the traversal, from both
 * triangles' boxes) and through the tessellation by brute force.
 *
 * Meshes: the UV sphere of 960 triangles (examples/models), a bumpy grid
 * whose middle vertices share one texture point (flat triangles, which close
 * up by their boundary fans), and the skinned bar of assimp-testmodels in a
 * bent pose. A UV seam (the sphere's meridian where u jumps from 1 to 0:
 * the same positions, other vertices and texture coordinates) is not a
 * shared edge and is not tested here: the two sides compute their points
 * from other texture coordinates, so they meet only as far as their
 * heights and roundings agree (README, "Seams").
 * Each case reports its cracks and edges whose two sides hold other points
 * for `make hard` (hard_report.h).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <float.h>
#include <math.h>

#include "../support/displaced_fixture.h"
#include "kinds/displaced/dsurf.h"

#define HARD_KIND "displaced"
#include "../support/hard_report.h"

#define BAR "/usr/share/assimp/models/FBX/animation_with_skeleton.fbx"
#define MAX_BOUNDARY 4096

typedef struct edge_key {
    uint32_t a, b;  /* vertex indices, a < b */
    uint32_t t, e;  /* triangle and its edge (corner e -> e + 1) */
} edge_key;

static int edge_cmp(const void *x, const void *y)
{
    const edge_key *p = x, *q = y;
    return p->a != q->a ? (p->a < q->a ? -1 : 1) : p->b != q->b ? (p->b < q->b ? -1 : 1) : 0;
}

/* The base mesh as the kind sees it (one mesh). */
typedef struct base {
    const float *p, *n, *uv;
    const uint32_t *idx;
    uint32_t nt;
    uint32_t gw, gh; /* grid size (texture samples per period) */
} base;

static void base_tri(const base *m, uint32_t t, mr_dbase *b, const mr_dheights *hs)
{
    double g[3][2];
    const float *p[3], *n[3];
    for (int k = 0; k < 3; k++) {
        uint32_t v = m->idx[t * 3 + k];
        g[k][0] = (double)m->uv[v * 2] * m->gw;
        g[k][1] = (double)m->uv[v * 2 + 1] * m->gh;
        p[k] = m->p + (size_t)v * 3;
        n[k] = m->n + (size_t)v * 3;
    }
    mr_dbase_init(b, g, p, n, hs);
}

static double grid_h(const void *src, int64_t i, int64_t j)
{
    const mr_image *img = src;
    int64_t x = i % img->width, y = j % img->height;
    x += x < 0 ? img->width : 0;
    y += y < 0 ? img->height : 0;
    /* the kind's formula with its float parameters (dgrid.h) */
    return 0.0 + (double)0.1f * (mr_image_sample(img, (uint32_t)x, img->height - 1 - (uint32_t)y) / 255.0);
}

/* The tessellation's micro-edges by their end points' float bits, so the
 * two micro-triangles along a micro-segment are found by binary search. */
typedef struct micro_edge {
    uint32_t key[6]; /* lower end point first */
    mr_vec3 n;       /* its triangle's normal (unnormalised) */
    mr_vec3 third;   /* its triangle's vertex off the edge */
} micro_edge;

static void point_bits(mr_vec3 p, uint32_t out[3])
{
    memcpy(&out[0], &p.x, 4), memcpy(&out[1], &p.y, 4), memcpy(&out[2], &p.z, 4);
}

static void segment_key(mr_vec3 a, mr_vec3 b, uint32_t key[6])
{
    uint32_t ka[3], kb[3];
    point_bits(a, ka), point_bits(b, kb);
    bool swap = memcmp(kb, ka, sizeof ka) < 0;
    memcpy(key, swap ? kb : ka, 12);
    memcpy(key + 3, swap ? ka : kb, 12);
}

static int micro_cmp(const void *x, const void *y)
{
    return memcmp(((const micro_edge *)x)->key, ((const micro_edge *)y)->key, 24);
}

static micro_edge *micro_edges(const dfx *f, size_t *count)
{
    size_t n = (size_t)f->tess.triangle_count * 3;
    micro_edge *m = malloc(n * sizeof *m);
    assert_non_null(m);
    for (uint32_t t = 0; t < f->tess.triangle_count; t++) {
        mr_vec3 v[3];
        for (int c = 0; c < 3; c++)
            v[c] = dfx_vertex(&f->tess, f->tess.indices[t * 3 + c]);
        mr_vec3 nn = mr_v3_cross(mr_v3_sub(v[1], v[0]), mr_v3_sub(v[2], v[0]));
        for (int c = 0; c < 3; c++) {
            segment_key(v[c], v[(c + 1) % 3], m[t * 3 + c].key);
            m[t * 3 + c].n = nn;
            m[t * 3 + c].third = v[(c + 2) % 3];
        }
    }
    qsort(m, n, sizeof *m, micro_cmp);
    *count = n;
    return m;
}

/* Shoots rays at every micro-segment of every shared edge; returns cracks,
 * the shared edges whose two sides hold other points in *mismatched_out.
 * The two micro-triangles along a segment are two half-planes (pages) on
 * its line, splitting space into two wedges; a ray through a point of the
 * segment that comes out of the narrower wedge crosses a page there, so it
 * must hit one of them at that point or something before it. Directions
 * are drawn so (the reverse direction a positive mix of the two pages'
 * in-page directions); a ray along a crease's outer side may miss both
 * pages without any hole, which is why not any direction will do. Flat
 * pairs (pages opposite) get directions against their normal instead. */
static long shoot_edges(dfx *f, const base *m, const mr_dheights *hs, uint64_t *seed, long *rays,
                        long *mismatched_out)
{
    size_t ne = (size_t)m->nt * 3, nm;
    edge_key *ek = malloc(ne * sizeof *ek);
    assert_non_null(ek);
    for (uint32_t t = 0; t < m->nt; t++)
        for (uint32_t e = 0; e < 3; e++) {
            uint32_t a = m->idx[t * 3 + e], b = m->idx[t * 3 + (e + 1) % 3];
            ek[t * 3 + e] = (edge_key){a < b ? a : b, a < b ? b : a, t, e};
        }
    qsort(ek, ne, sizeof *ek, edge_cmp);
    micro_edge *me = micro_edges(f, &nm);
    static mr_dvert pts[MAX_BOUNDARY];
    static mr_vec3 along[MAX_BOUNDARY];
    long cracks = 0, shared = 0, segments = 0, mismatched = 0;
    for (size_t k = 0; k + 1 < ne; k++) {
        if (edge_cmp(&ek[k], &ek[k + 1]) != 0 || ek[k].a == ek[k].b)
            continue;
        shared++;
        mr_dbase b;
        base_tri(m, ek[k].t, &b, hs);
        int n = mr_dsurf_flat_boundary(&b, pts, MAX_BOUNDARY);
        assert_true(n < MAX_BOUNDARY);
        /* the points on edge e, in boundary order, and its end corner */
        int na = 0;
        uint32_t e = ek[k].e;
        for (int i = 0; i < n; i++)
            if ((pts[i].kind == MR_DV_BASE || pts[i].kind == MR_DV_EDGE) && pts[i].idx == e)
                along[na++] = mr_dsurf_vertex(&b, hs, &pts[i]);
        mr_dvert end = {.kind = MR_DV_BASE, .idx = (uint8_t)((e + 1) % 3)};
        along[na++] = mr_dsurf_vertex(&b, hs, &end);
        /* the other side's points along the same edge: the same floats, in
         * the opposite order (the proof that nothing can pass between) */
        {
            mr_dbase b2;
            base_tri(m, ek[k + 1].t, &b2, hs);
            static mr_dvert pts2[MAX_BOUNDARY];
            int n2 = mr_dsurf_flat_boundary(&b2, pts2, MAX_BOUNDARY), nb = 0;
            uint32_t e2 = ek[k + 1].e;
            static mr_vec3 other[MAX_BOUNDARY];
            for (int i = 0; i < n2; i++)
                if ((pts2[i].kind == MR_DV_BASE || pts2[i].kind == MR_DV_EDGE) && pts2[i].idx == e2)
                    other[nb++] = mr_dsurf_vertex(&b2, hs, &pts2[i]);
            mr_dvert end2 = {.kind = MR_DV_BASE, .idx = (uint8_t)((e2 + 1) % 3)};
            other[nb++] = mr_dsurf_vertex(&b2, hs, &end2);
            bool same = nb == na;
            for (int i = 0; same && i < na; i++)
                same = !memcmp(&along[i], &other[na - 1 - i], sizeof along[i]);
            if (!same) {
                mismatched++;
                if (mismatched <= 3)
                    print_error("edge %u-%u: %d points on one side, %d on the other, or other "
                                "floats\n", ek[k].a, ek[k].b, na, nb);
            }
        }
        for (int sg = 0; sg + 1 < na; sg++) {
            micro_edge probe;
            segment_key(along[sg], along[sg + 1], probe.key);
            micro_edge *hit = bsearch(&probe, me, nm, sizeof *me, micro_cmp);
            if (!hit)
                continue; /* no area on this piece (a degenerate segment) */
            /* both micro-triangles of the segment */
            micro_edge *lo = hit, *hi = hit;
            while (lo > me && !micro_cmp(lo - 1, &probe))
                lo--;
            while (hi + 1 < me + nm && !micro_cmp(hi + 1, &probe))
                hi++;
            if (hi - lo != 1)
                continue; /* a boundary or a folded fan: not two pages */
            segments++;
            mr_vec3 l = mr_v3_normalize_or(mr_v3_sub(along[sg + 1], along[sg]), mr_v3(0, 0, 0));
            mr_vec3 u[2];
            for (int pg = 0; pg < 2; pg++) {
                mr_vec3 w = mr_v3_sub(pg ? hi->third : lo->third, along[sg]);
                u[pg] = mr_v3_normalize_or(mr_v3_sub(w, mr_v3_scale(l, mr_v3_dot(w, l))), mr_v3(0, 0, 0));
            }
            bool flat = mr_v3_dot(u[0], u[1]) < -0.98f;
            mr_vec3 nf = mr_v3_normalize_or(lo->n, mr_v3(0, 0, 0));
            float len = mr_v3_len(mr_v3_sub(along[sg + 1], along[sg]));
            float mag = fmaxf(fmaxf(fabsf(along[sg].x), fabsf(along[sg].y)), fabsf(along[sg].z));
            /* a point between the ends is computed in float: on a segment
             * shorter than ~1000 roundings of its coordinates it lands
             * beside the segment rather than on it */
            if (len < 1000 * mag * FLT_EPSILON)
                continue;
            static const float FR[] = {0.5f, 0.17f, 0.83f};
            for (int q = 0; q < 3; q++) {
                mr_vec3 w;
                if (flat)
                    w = mr_v3_sub(mr_v3_scale(rnd_unit(seed), 0.4f), nf);
                else
                    w = mr_v3_scale(mr_v3_add(mr_v3_scale(u[0], rndf(seed, 0.2f, 1)),
                                              mr_v3_scale(u[1], rndf(seed, 0.2f, 1))), -1);
                w = mr_v3_add(w, mr_v3_scale(l, rndf(seed, -0.5f, 0.5f) * mr_v3_len(w)));
                mr_vec3 d = mr_v3_normalize_or(w, mr_v3(0, 0, 0));
                if (mr_v3_len(d) == 0)
                    continue;
                mr_vec3 x = mr_v3_lerp(along[sg], along[sg + 1], FR[q]);
                /* start a couple of segment lengths back; the target is a
                 * float point, a few roundings of its coordinates off the
                 * segment, which a ray at a shallow angle turns into up to
                 * 20x as much along it */
                float back = 2 * len + 1e-3f * (1 + mag), tt, tb = 0;
                mr_vec3 o = mr_v3_sub(x, mr_v3_scale(d, back));
                bool ht = dfx_trace(f, o, d, 0, INFINITY, &tt, NULL);
                /* the brute force on every tenth ray (it is the slow part) */
                bool check = (*rays % 10) == 0, hb = check ? dfx_brute(f, o, d, 0, INFINITY, &tb) : true;
                float lim = back * (1 + 1e-5f) + 20 * 8 * mag * FLT_EPSILON;
                bool crack = !ht || tt > lim || !hb || tb > lim;
                if (crack && !check) /* confirm with the brute force */
                    hb = dfx_brute(f, o, d, 0, INFINITY, &tb);
                if (crack && cracks < 5) {
                    print_error("edge %u-%u segment %d: traced %d t %.9g, brute %d t %.9g (lim %g)\n",
                                ek[k].a, ek[k].b, sg, ht, tt, hb, tb, lim);
                    if (getenv("DFX_DEBUG"))
                        print_message("  seg (%.9g %.9g %.9g)-(%.9g %.9g %.9g) d (%.9g %.9g %.9g) "
                                      "u1.u2 %g third1 (%g %g %g) third2 (%g %g %g)\n", along[sg].x, along[sg].y, along[sg].z,
                                      along[sg + 1].x, along[sg + 1].y, along[sg + 1].z, d.x, d.y,
                                      d.z, mr_v3_dot(u[0], u[1]), lo->third.x, lo->third.y, lo->third.z, hi->third.x, hi->third.y, hi->third.z);
                }
                cracks += crack;
                (*rays)++;
            }
        }
    }
    free(me);
    free(ek);
    assert_true(shared > 0 && segments > 0);
    print_message("%ld shared edges, %ld with other points on the two sides\n", shared, mismatched);
    *mismatched_out = mismatched;
    return cracks;
}

typedef struct seam_figures {
    long rays, cracks, mismatched;
} seam_figures;

static seam_figures check_mesh(const mr_asset *mesh_asset, mr_asset *tex, const mr_pose_desc *pose,
                               uint64_t *seed, const char *name)
{
    dfx f = {0};
    dfx_params(&f, 0.1f, 0);
    dfx_open(&f, (mr_asset *)mesh_asset, tex, pose, NULL, 0.4);
    /* the posed base mesh: from the kind's tessellation we cannot read it,
     * so the same posing here (rest pose, or the skinned pose) */
    const mr_mesh *mm = &mesh_asset->meshes[0];
    float *p = malloc((size_t)mm->vertex_count * 3 * sizeof(float) + 4);
    float *n = malloc((size_t)mm->vertex_count * 3 * sizeof(float) + 4);
    mr_mat4 id = mr_mat4_identity();
    mr_skin_mesh(mesh_asset, 0, f.pose, &id, p, n, 1);
    base m = {p, n, mm->uvs, mm->indices, mm->triangle_count, tex->image->width, tex->image->height};
    mr_dheights hs = {grid_h, tex->image};
    seam_figures sf = {0};
    sf.cracks = shoot_edges(&f, &m, &hs, seed, &sf.rays, &sf.mismatched);
    print_message("%s: %ld rays at the micro-segments of shared edges, %ld cracks\n", name, sf.rays, sf.cracks);
    free(p);
    free(n);
    dfx_close(&f);
    mr_device_free(f.dev);
    return sf;
}

/* The figures of check_mesh under the case test: cracks and mismatched
 * edges together held to allowed, as the case always has. */
static void report_seams(const char *test, const seam_figures *sf, long allowed)
{
    hard_check(test, "leaks", (double)(sf->cracks + sf->mismatched), "<=", (double)allowed,
               "rays through cracks at shared edges, plus edges whose sides hold other points (%ld of them; "
               "%ld rays)", sf->mismatched, sf->rays);
    hard_check(test, "other", (double)sf->rays, ">", 1000, "rays at the micro-segments of shared edges");
}

static mr_asset *load(const char *path)
{
    mr_asset *a = NULL;
    mr_error err;
    if (mr_asset_load(path, &a, &err) != MR_OK)
        fail_msg("%s", err.msg);
    return a;
}

static void test_sphere_edges(void **state)
{
    (void)state;
    const char *dir = getenv("MR_SOURCE_DIR");
    char path[1024];
    snprintf(path, sizeof path, "%s/examples/models/sphere960.obj", dir ? dir : ".");
    mr_asset *sphere = load(path);
    uint64_t seed = 1;
    mr_asset *tex = dfx_texture(37, 29, MR_SAMPLE_U8, dfx_noise, &seed);
    seam_figures sf = check_mesh(sphere, tex, NULL, &seed, "sphere960");
    report_seams(__func__, &sf, 0);
    mr_asset_free(sphere);
    mr_asset_free(tex);
}

static void test_flat_triangles_close_up(void **state)
{
    (void)state;
    /* a 4 x 4 grid whose middle four vertices share one texture point */
    enum { N = 4 };
    float P[N * N * 3], NR[N * N * 3], UV[N * N * 2];
    uint32_t I[(N - 1) * (N - 1) * 6];
    uint64_t seed = 2;
    for (int z = 0; z < N; z++)
        for (int x = 0; x < N; x++) {
            int v = z * N + x;
            bool mid = (x == 1 || x == 2) && (z == 1 || z == 2);
            P[v * 3] = -1 + 2.0f * x / 3, P[v * 3 + 1] = rndf(&seed, -0.1f, 0.1f), P[v * 3 + 2] = -1 + 2.0f * z / 3;
            NR[v * 3] = 0, NR[v * 3 + 1] = 1, NR[v * 3 + 2] = 0;
            UV[v * 2] = mid ? 0.5f : x / 3.0f;
            UV[v * 2 + 1] = mid ? 0.5f : z / 3.0f;
        }
    int k = 0;
    for (int z = 0; z + 1 < N; z++)
        for (int x = 0; x + 1 < N; x++) {
            uint32_t a = (uint32_t)(z * N + x), b = a + 1, c = a + N, d = c + 1;
            uint32_t q[6] = {a, c, d, a, d, b};
            memcpy(I + k, q, sizeof q);
            k += 6;
        }
    mr_asset *mesh = dfx_mesh(P, NR, UV, N * N, I, (N - 1) * (N - 1) * 2);
    mr_asset *tex = dfx_texture(23, 19, MR_SAMPLE_U8, dfx_noise, &seed);
    seam_figures sf = check_mesh(mesh, tex, NULL, &seed, "grid with flat triangles");
    report_seams(__func__, &sf, 0);
    mr_asset_free(mesh);
    mr_asset_free(tex);
}

static void test_skinned_bar_edges(void **state)
{
    (void)state;
    mr_asset *bar = load(BAR);
    uint64_t seed = 3;
    mr_asset *tex = dfx_texture(64, 64, MR_SAMPLE_U8, dfx_noise, &seed);
    mr_pose_desc clip = {.has_clip = true, .clip_index = 0, .speed = 1, .loop = true};
    /* The bar's coordinates reach 3,500 (float steps of 2.4e-4): 8 of its
     * 44,463 rays pass through pieces so thin that two of their
     * micro-vertices (crossings of different grid lines) round to the same
     * float, leaving a micro-triangle without area. The brute force over
     * the tessellation passes through them too (the traversal misses
     * nothing the reference has), and both sides of every edge hold the
     * same points; what is left is float rounding of the surface itself,
     * counted here so that it cannot grow unnoticed. */
    seam_figures sf = check_mesh(bar, tex, &clip, &seed, "skinned bar");
    report_seams(__func__, &sf, 8);
    mr_asset_free(bar);
    mr_asset_free(tex);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_sphere_edges),
        cmocka_unit_test(test_flat_triangles_close_up),
        cmocka_unit_test(test_skinned_bar_edges),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
