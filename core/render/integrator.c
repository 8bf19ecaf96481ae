/* integrator.c - tiled primary-ray integrator (integrator.h). */
#include "render/integrator.h"

#include <float.h>
#include <limits.h>
#include <math.h>
#include <stdlib.h>
#include <emmintrin.h>
#include <stdatomic.h>
#include <string.h>

#include "util/parallel.h"

/* Two uniform floats in [0,1) for one sample. */
static inline void sample_jitter(const mr_trace_setup *s, uint32_t x, uint32_t y, uint32_t k, float *jx,
                                 float *jy)
{
    /* stateless, which per-pixel determinism needs */
    uint64_t h = mr_mix64(((uint64_t)s->seed << 32 | s->frame) ^ mr_mix64((uint64_t)y << 32 | x) ^
                          mr_mix64((uint64_t)k + 0x9e3779b97f4a7c15ull));
    *jx = (float)(h >> 40) * (1.0f / 16777216.0f);
    *jy = (float)((h >> 16) & 0xffffff) * (1.0f / 16777216.0f);
}

/* The film's float and id planes (film_planes), Cryptomatte aside. */
#define PLANES 16
/* The depth plane's place among them (film_planes, tile_planes). */
#define PLANE_Z 4

/* What a packet block of the film holds, by the film's record
 * (film_record): nothing known; the frame's miss values in every plane;
 * what mr_film_clear left, untouched since. */
enum block_state { BLOCK_UNKNOWN = 0, BLOCK_MISS = 1, BLOCK_CLEARED = 2 };

typedef struct {
    const mr_trace_setup *s;
    mr_camera_rays rays_setup;
    mr_vec3 forward;   /* the camera's viewing direction (unit): depth = t dir . forward */
    /* the film rectangle [x0, x1] x [y0, y1] (pixel coordinates) outside
     * which a primary ray misses the whole scene (scene_rect) */
    double x0, x1, y0, y1;
    uint32_t miss[PLANES]; /* a missed pixel's bits in each film plane (miss_values) */
    uint32_t miss_crypto[MR_CRYPTO_LAYERS][2 * MR_CRYPTO_MAX_RANKS];
    /* trace_pixels writes a packet that hits nothing into the tile too:
     * for miss_values, which makes c->miss from it, and in a frame
     * without c->miss (no memory for miss_values) */
    bool misses_to_tile;
    mr_film *film;
    /* per packet block of the film (film_record): what it holds
     * (block_state); NULL: nothing known, every block is written */
    uint8_t *held;
    int tiles_x, tiles_y, blocks_x;
    atomic_ullong rays;
    atomic_bool cancelled;
} trace_ctx;

/* What one sample of a lane that hit gives (trace_packet's hit mask says
 * which lanes did). */
typedef struct {
    float t;
    mr_vec3 normal; /* shading normal, unit, facing the ray origin */
    mr_vec3 tangent; /* shading tangent, unit and orthogonal to normal; 0: none (MR_AOV_T) */
    uint32_t object, prim;
    mr_vec3 rgb;
    float depth;    /* camera-space depth of the hit */
    mr_vec3 pos;    /* world-space position of the hit */
} sample_result;

/* Moves a point off the surface along its (unit, geometric) normal so a ray
 * leaving it cannot hit the surface it starts on. The intersection point
 * carries a rounding error proportional to the magnitude of its
 * coordinates, so a fixed offset fails far from the origin (at 1e5 one
 * float step is 0.008): each coordinate moves by `scene_bias` (relative to
 * the scene size) or by 64 float steps of its own magnitude, whichever is
 * larger. */
static mr_vec3 offset_from_surface(mr_vec3 p, mr_vec3 n, float scene_bias)
{
    float c[3] = {p.x, p.y, p.z}, d[3] = {n.x, n.y, n.z};
    for (int i = 0; i < 3; i++) {
        float ulps = 64.0f * FLT_EPSILON * fabsf(c[i]);
        c[i] += d[i] * (scene_bias > ulps ? scene_bias : ulps);
    }
    return mr_v3(c[0], c[1], c[2]);
}

/* One lane of a hit record: what shading needs, whatever the packet width. */
typedef struct hit_view {
    unsigned geom, prim;
    float u, v, t;
    mr_vec3 ng;
} hit_view;

/* Primary rays go to Embree as packets of MR_PACKET neighbouring pixels,
 * MR_PACKET_W columns of MR_PACKET_ROWS rows (lane i: column i %
 * MR_PACKET_W of row i / MR_PACKET_W): they are coherent, so Embree
 * traverses the BVH for all of them at once with SIMD, which is what lets
 * the renderer keep up with (and pass) a plain one-ray-at-a-time loop.
 * Each lane's result is the closest hit of its ray, so the packet's shape
 * changes no image, as long as no kind reports a hit nearer than its
 * primitive's bounds (then which hit is nearest depends on Embree's order:
 * one pixel in some frames of a level-of-detail example changed with 4x4
 * packets, docs/performance.md, stop 61). The squarest bundle of sixteen: bare loops
 * over static-human at 1280x720 took 6.9 ms a frame in 8x1 packets, 6.1 in
 * 16x1 and 5.6 in 8x2 (2026-12-03); 4x4 instead of 8x2 (stop 61) traced static-human and skinned-walk at 1.01-1.02 and
 * 1.10-1.13 of the bare 8-packet loop's rate against 0.97-0.99 and
 * 1.06-1.08, and the kinds whose callbacks walk a packet's rays together
 * traced in 0.93-0.96 of the time (docs/performance.md, primary rays). */
#define MR_PACKET_W 4
#define MR_PACKET_ROWS 4
#define MR_PACKET (MR_PACKET_W * MR_PACKET_ROWS)
_Static_assert((MR_PACKET_W & (MR_PACKET_W - 1)) == 0, "a lane's column and row are a mask and a shift");
_Static_assert(MR_PACKET % 8 == 0, "a packet's directions are made eight at a time (mr_camera_rays_dir8)");
_Static_assert(MR_PACKET == 16, "packets go to Embree as RTCRayHit16");
_Static_assert(MR_TILE_H % MR_PACKET_ROWS == 0, "a tile holds whole packet rows");

/* The pixels of one packet: lane i is pixel (x0 + i % MR_PACKET_W, y + i /
 * MR_PACKET_W); live: the lanes that are pixels of the tile (a tile's right
 * and bottom edges cut packets short). Lane 0 is always live. */
typedef struct packet_px {
    int x0, y;
    unsigned live;
} packet_px;

/* The packet of columns x0 .. x0 + cols - 1 of rows y .. y + rows - 1
 * (cols <= MR_PACKET_W, rows <= MR_PACKET_ROWS, both >= 1). */
static packet_px packet_at(int x0, int y, int cols, int rows)
{
    unsigned row = (1u << cols) - 1u, live = 0;
    for (int r = 0; r < rows; r++)
        live |= row << (r * MR_PACKET_W);
    return (packet_px){x0, y, live};
}

static bool lane_live(unsigned live, int i) { return live >> i & 1u; }

/* How many pixels packet row `row` of pk has (its live lanes). */
static int row_pixels(const packet_px *pk, int row)
{
    return mr_popcount32(pk->live >> (row * MR_PACKET_W) & ((1u << MR_PACKET_W) - 1u));
}

/* Lane i's pixel in a tile whose packet starts at index i0. */
static size_t lane_at(size_t i0, int i)
{
    return i0 + (size_t)(i / MR_PACKET_W) * MR_TILE_W + (size_t)(i % MR_PACKET_W);
}

/* A lane's light so far and the shadow rays it still waits for: one per
 * light that faces the hit (cosine > 0), all from org. */
typedef struct light_wait {
    bool waits;
    mr_vec3 org, albedo, light;
    float cosine[MR_MAX_LIGHTS]; /* 0: no shadow ray (the light does not reach) */
} light_wait;

/* Shades a hit but for its shadows: *lw gets the lights that face it and
 * the ambient light, and waits when they need shadow rays (shadows).
 * normal: the kind's normal at the hit (kind.h normal), asked for before. */
static void shade(const mr_trace_setup *s, const hit_view *h, mr_vec3 normal, mr_vec3 org,
                  mr_vec3 dir, sample_result *out, light_wait *lw)
{
    lw->waits = false;
    const mr_shade_object *obj = &s->objects[h->geom];
    mr_vec3 ng = mr_v3_normalize_or(h->ng, mr_v3(0, 0, 1));
    if (mr_v3_dot(ng, dir) > 0)
        ng = mr_v3_scale(ng, -1.0f);
    mr_vec3 n = mr_v3_normalize_or(normal, ng);
    float step = obj->kind->surface_step ? obj->kind->surface_step(obj->geom, h->prim, h->u, h->v) : 0.0f;
    /* A shading normal facing away from the viewer: a smooth surface seen
     * from behind its interpolated normals is turned round. A voxel whose
     * surface faces away is seen only because it sticks out past the
     * silhouette of the surface it stands for (boxes hold the surface and
     * more); there that surface is seen edge-on, its normal at right
     * angles to the ray: the normal's part across the ray. Turned round
     * instead, it lit silhouettes as if they faced the other way (dark
     * pixels along creases and arms). */
    float facing = mr_v3_dot(n, dir);
    if (facing > 0 && step > 0)
        n = mr_v3_normalize_or(mr_v3_sub(n, mr_v3_scale(dir, facing)), ng);
    else if (facing > 0)
        n = mr_v3_scale(n, -1.0f);
    out->t = h->t;
    out->normal = n;
    /* the tangent along increasing u, fitted to the shading normal (its
     * direction does not turn with the normal's side) */
    mr_vec3 t;
    out->tangent = (s->aovs & MR_AOV_T) && obj->kind->tangent &&
                           obj->kind->tangent(obj->geom, h->prim, h->u, h->v, &t)
                       ? mr_v3_tangent_to(t, n, false)
                       : mr_v3(0, 0, 0);
    out->object = h->geom + 1;
    out->prim = obj->kind->id_primitive ? obj->kind->id_primitive(obj->geom, h->prim) : h->prim;
    out->rgb = mr_v3(0, 0, 0);
    if (!(s->aovs & MR_AOV_RGBA))
        return; /* nothing asks for light */

    mr_vec3 light = s->ambient;
    mr_vec3 p = mr_v3_add(org, mr_v3_scale(dir, h->t));
    bool stepped = step > 0;
    /* A surface shaded by smooth normals stands for the curved surface
     * they describe: shadow rays start on it (kind.h shading_point), when
     * it lies on the viewer's side of the hit triangle, and the shading
     * normal alone says which lights face it (the shadow terminator).
     * Without shadow rays the point itself goes nowhere: it is looked up
     * only when some light faces the shading normal but not the hit
     * triangle, the one case where being smooth changes the light (the
     * same image, without the lookup on most hits). */
    bool smooth = false, need_point = s->shadows;
    for (size_t i = 0; i < s->light_count && !need_point && !stepped; i++) {
        mr_vec3 l = mr_v3_scale(s->lights[i].direction, -1.0f);
        need_point = mr_v3_dot(n, l) > 0 && mr_v3_dot(ng, l) <= 0;
    }
    mr_vec3 q;
    if (need_point && obj->kind->shading_point &&
        obj->kind->shading_point(obj->geom, h->prim, h->u, h->v, p, &q) &&
        mr_v3_dot(mr_v3_sub(q, p), ng) >= 0) {
        p = q;
        smooth = true;
    }
    mr_vec3 shadow_org = s->shadows ? offset_from_surface(p, ng, s->shadow_bias) : p;
    /* A surface of steps (voxels) stands for the smooth one its shading
     * normals describe: lit by those alone, its shadow rays start 3 steps
     * along them, so the staircase does not shadow itself (kind.h
     * surface_step: the edge of the voxel hit, coarser than the finest
     * one where voxels were selected for a distant view, stretched at
     * bends). Past one voxel's diagonal (1.73 edges) is the least; measured
     * with per-hit steps, 1.5 / 3 / 6 of them gave the skinned dancers 2.03
     * / 2.12 / 2.14 % isolated dark pixels, the rigid crowd 5.19 / 5.26 /
     * 5.37 % and the skeleton 1.86 / 1.11 / 1.10 %: 3 keeps contact shadows
     * within 3 voxels (README, "Error metrics"). */
    if (stepped)
        shadow_org = mr_v3_add(shadow_org, mr_v3_scale(n, 3.0f * step));
    lw->org = shadow_org;
    lw->albedo = obj->albedo;
    for (size_t i = 0; i < s->light_count; i++) {
        mr_vec3 l = mr_v3_scale(s->lights[i].direction, -1.0f); /* towards the light */
        float cosine = mr_v3_dot(n, l);
        lw->cosine[i] = 0.0f;
        if (cosine <= 0 || (!stepped && !smooth && mr_v3_dot(ng, l) <= 0))
            continue;
        if (s->shadows) {
            lw->cosine[i] = cosine;
            lw->waits = true;
            continue;
        }
        light = mr_v3_add(light, mr_v3_scale(s->lights[i].color, cosine));
    }
    lw->light = light;
    out->rgb = mr_v3_mul(obj->albedo, light);
}

#define SHADOW_LANES 8 /* rtcOccluded8 */
_Static_assert(MR_PACKET % SHADOW_LANES == 0, "a packet is whole shadow packets");

/* The shadow rays the lanes of a packet wait for, light by light, as
 * packets too, one per eight lanes (rtcOccluded8: the lanes' rays to one
 * light start at neighbouring points and run parallel); each lane adds the
 * lights nothing blocks in the lights' order, as one ray at a time did.
 * Eight wide, not sixteen: rtcOccluded16 never returned on the crowd
 * example's instanced user geometries (Embree 3.13.5 kept calling the
 * kind's occlusion callback; 16-wide primary rays are fine there). */
static void shadow_packet(const mr_trace_setup *s, light_wait *lw, sample_result *out,
                          unsigned lanes, uint64_t *rays)
{
    for (size_t i = 0; i < s->light_count; i++) {
        mr_vec3 l = mr_v3_scale(s->lights[i].direction, -1.0f);
        for (int row = 0; row < MR_PACKET; row += SHADOW_LANES) {
            RTC_ALIGN(32) int valid[SHADOW_LANES];
            struct RTCRay8 ray;
            int live = 0;
            for (int j = 0; j < SHADOW_LANES; j++) {
                int k = row + j;
                bool on = lane_live(lanes, k) && lw[k].waits && lw[k].cosine[i] > 0;
                valid[j] = on ? -1 : 0;
                live += on;
                mr_vec3 o = on ? lw[k].org : mr_v3(0, 0, 0); /* idle lanes: any valid ray */
                ray.org_x[j] = o.x, ray.org_y[j] = o.y, ray.org_z[j] = o.z;
                ray.dir_x[j] = l.x, ray.dir_y[j] = l.y, ray.dir_z[j] = l.z;
                ray.tnear[j] = 0.0f;
                ray.tfar[j] = FLT_MAX;
                ray.time[j] = 0.0f;
                ray.mask[j] = 0xffffffffu;
                ray.id[j] = (unsigned)j;
                ray.flags[j] = 0;
            }
            if (!live)
                continue;
            struct RTCIntersectContext ctx;
            rtcInitIntersectContext(&ctx);
            ctx.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
            rtcOccluded8(valid, s->scene, &ctx, &ray);
            *rays += (uint64_t)live;
            for (int j = 0; j < SHADOW_LANES; j++)
                if (valid[j] && !(ray.tfar[j] < 0)) /* Embree sets tfar = -inf when occluded */
                    lw[row + j].light = mr_v3_add(
                        lw[row + j].light, mr_v3_scale(s->lights[i].color, lw[row + j].cosine[i]));
        }
    }
    for (int k = 0; k < MR_PACKET; k++)
        if (lane_live(lanes, k) && lw[k].waits)
            out[k].rgb = mr_v3_mul(lw[k].albedo, lw[k].light);
}

/* The packet's lanes for Embree, four at a time: valid (-1: a pixel of the
 * tile, 0: idle) and the film points of sample 0, the pixels' centres (x +
 * 0.5, y + 0.5); an idle lane takes lane 0's pixel (always a valid ray). */
static inline void packet_lanes(const packet_px *pk, int valid[MR_PACKET], float px[MR_PACKET],
                                float py[MR_PACKET])
{
    const __m128i live = _mm_set1_epi32((int)pk->live);
    const __m128 h = _mm_set1_ps(0.5f);
    for (int i = 0; i < MR_PACKET; i += 4) {
        const __m128i lane = _mm_setr_epi32(i, i + 1, i + 2, i + 3);
        const __m128i bit = _mm_setr_epi32(1 << i, 1 << (i + 1), 1 << (i + 2), 1 << (i + 3));
        const __m128i on = _mm_cmpeq_epi32(_mm_and_si128(live, bit), bit);
        const __m128i l = _mm_and_si128(lane, on);
        /* l % MR_PACKET_W and l / MR_PACKET_W (a power of 2, asserted above) */
        const __m128i x = _mm_add_epi32(_mm_set1_epi32(pk->x0), _mm_and_si128(l, _mm_set1_epi32(MR_PACKET_W - 1)));
        const __m128i y = _mm_add_epi32(_mm_set1_epi32(pk->y), _mm_srli_epi32(l, __builtin_ctz(MR_PACKET_W)));
        _mm_store_si128((__m128i *)(valid + i), on);
        _mm_store_ps(px + i, _mm_add_ps(_mm_cvtepi32_ps(x), h));
        _mm_store_ps(py + i, _mm_add_ps(_mm_cvtepi32_ps(y), h));
    }
}

/* Traces sample k of the packet's pixels; returns the mask of lanes that
 * hit (only their out[] is written). */
static unsigned trace_packet(const trace_ctx *c, const packet_px *pk, int k, sample_result *out,
                             uint64_t *rays)
{
    const mr_trace_setup *s = c->s;
    mr_vec3 org = c->rays_setup.origin;
    RTC_ALIGN(64) int valid[MR_PACKET];
    struct RTCRayHit16 rh;
    RTC_ALIGN(16) float px[MR_PACKET], py[MR_PACKET];
    packet_lanes(pk, valid, px, py);
    if (k > 0)
        for (int i = 0; i < MR_PACKET; i++) {
            int l = lane_live(pk->live, i) ? i : 0; /* idle lanes repeat lane 0: a valid ray */
            int x = pk->x0 + l % MR_PACKET_W, y = pk->y + l / MR_PACKET_W;
            float jx, jy;
            sample_jitter(s, (uint32_t)x, (uint32_t)y, (uint32_t)k, &jx, &jy);
            px[i] = (float)x + jx;
            py[i] = (float)y + jy;
        }
    for (int h = 0; h < MR_PACKET; h += 8)
        mr_camera_rays_dir8(&c->rays_setup, px + h, py + h, rh.ray.dir_x + h, rh.ray.dir_y + h,
                            rh.ray.dir_z + h);
    for (int i = 0; i < MR_PACKET; i++) /* (loops of one field each: filled as vectors) */
        rh.ray.id[i] = (unsigned)i;
    for (int i = 0; i < MR_PACKET; i++) {
        rh.ray.org_x[i] = org.x;
        rh.ray.org_y[i] = org.y;
        rh.ray.org_z[i] = org.z;
        rh.ray.tnear[i] = 0.0f;
        rh.ray.tfar[i] = FLT_MAX;
        rh.ray.time[i] = 0.0f;
    }
    for (int i = 0; i < MR_PACKET; i++) {
        rh.ray.mask[i] = 0xffffffffu;
        rh.ray.flags[i] = 0;
        rh.hit.geomID[i] = RTC_INVALID_GEOMETRY_ID;
        rh.hit.instID[0][i] = RTC_INVALID_GEOMETRY_ID;
    }
    struct RTCIntersectContext ctx;
    rtcInitIntersectContext(&ctx);
    ctx.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
    rtcIntersect16(valid, s->scene, &ctx, &rh);
    *rays += (uint64_t)mr_popcount32(pk->live);
    light_wait lw[MR_PACKET];
    bool waits = false;
    unsigned hits = 0, reached = 0;
    _Static_assert(RTC_INVALID_GEOMETRY_ID == 0xffffffffu, "a miss's geomID is all ones");
    for (int h = 0; h < MR_PACKET; h += 4) /* the lanes whose geomID is not all ones */
        reached |= (unsigned)(~_mm_movemask_ps(_mm_castsi128_ps(_mm_cmpeq_epi32(
                                  _mm_loadu_si128((const __m128i *)(rh.hit.geomID + h)),
                                  _mm_set1_epi32(-1)))) & 15) << h;
    /* The hits and their kinds' normals first, in a loop of their own: the
     * normals' loads (a mesh's indices and vertex normals, often not in
     * cache) of all the lanes under way at once, not one lane's at a time
     * between the shading of the others. */
    hit_view hv[MR_PACKET];
    mr_vec3 normal[MR_PACKET];
    for (unsigned m = pk->live & reached; m; m &= m - 1) {
        int i = __builtin_ctz(m);
        /* An instance hit names the instance's top-level id; the kind
         * learns which instance as prim (kind.h geometry_ids). */
        bool instanced = rh.hit.instID[0][i] != RTC_INVALID_GEOMETRY_ID;
        unsigned id = instanced ? rh.hit.instID[0][i] : rh.hit.geomID[i];
        unsigned geom = s->id_object ? (id < s->id_count ? s->id_object[id] : UINT_MAX) : id;
        if (geom >= s->object_count) {
            reached &= ~(1u << i);
            continue;
        }
        unsigned prim = instanced ? id - s->objects[geom].first_id : rh.hit.primID[i];
        hv[i] = (hit_view){geom, prim, rh.hit.u[i], rh.hit.v[i], rh.ray.tfar[i],
                           mr_v3(rh.hit.Ng_x[i], rh.hit.Ng_y[i], rh.hit.Ng_z[i])};
        const mr_shade_object *obj = &s->objects[geom];
        normal[i] = obj->kind->normal(obj->geom, prim, hv[i].u, hv[i].v, hv[i].ng);
    }
    for (unsigned m = pk->live & reached; m; m &= m - 1) {
        int i = __builtin_ctz(m);
        mr_vec3 dir = mr_v3(rh.ray.dir_x[i], rh.ray.dir_y[i], rh.ray.dir_z[i]);
        shade(s, &hv[i], normal[i], org, dir, &out[i], &lw[i]);
        hits |= 1u << i;
        waits |= lw[i].waits;
        out[i].depth = hv[i].t * mr_v3_dot(dir, c->forward);
        out[i].pos = mr_v3_add(org, mr_v3_scale(dir, hv[i].t));
    }
    if (waits)
        shadow_packet(s, lw, out, hits, rays);
    return hits;
}

/* One tile's worth of every film plane. Tiles are traced into this private
 * buffer and copied out row by row when done: neighbouring tiles go to
 * different workers, and writing the shared film pixel by pixel made them
 * fight over the cache lines at tile edges (false sharing halved the ray rate
 * on 2 cores). Only the film's planes are filled and copied. */
typedef struct tile_buffer {
    float r[MR_TILE_PIXELS], g[MR_TILE_PIXELS], b[MR_TILE_PIXELS];
    float a[MR_TILE_PIXELS], z[MR_TILE_PIXELS];
    float nx[MR_TILE_PIXELS], ny[MR_TILE_PIXELS], nz[MR_TILE_PIXELS];
    float px[MR_TILE_PIXELS], py[MR_TILE_PIXELS], pz[MR_TILE_PIXELS];
    float tx[MR_TILE_PIXELS], ty[MR_TILE_PIXELS], tz[MR_TILE_PIXELS];
    uint32_t object_id[MR_TILE_PIXELS], prim_id[MR_TILE_PIXELS];
    float crypto[MR_CRYPTO_LAYERS][2 * MR_CRYPTO_MAX_RANKS][MR_TILE_PIXELS];
} tile_buffer;

/* Cryptomatte: the ids one pixel's samples hit and how many samples hit
 * each. A pixel sees at most spp ids; beyond the first CRYPTO_DISTINCT
 * distinct ones (more objects than that in one pixel) later ones are not
 * counted, which can only matter past the 6 ranks kept. */
#define CRYPTO_DISTINCT 16
typedef struct crypto_tally {
    int count;
    uint32_t id[CRYPTO_DISTINCT];   /* float bits */
    uint32_t hits[CRYPTO_DISTINCT];
} crypto_tally;

static void tally_add(crypto_tally *t, float id)
{
    uint32_t bits;
    memcpy(&bits, &id, sizeof bits);
    for (int i = 0; i < t->count; i++)
        if (t->id[i] == bits) {
            t->hits[i]++;
            return;
        }
    if (t->count < CRYPTO_DISTINCT) {
        t->id[t->count] = bits;
        t->hits[t->count++] = 1;
    }
}

/* Writes the tally's ranks into the tile: by falling coverage (hits /
 * samples), ties by the smaller id bits so the order never depends on the
 * order samples came in; unused ranks 0, 0. */
static void tally_write(crypto_tally *t, int ranks, int samples, float (*planes)[MR_TILE_PIXELS],
                        size_t p)
{
    for (int k = 0; k < ranks; k++) {
        int best = -1;
        for (int i = 0; i < t->count; i++)
            if (t->hits[i] && (best < 0 || t->hits[i] > t->hits[best] ||
                               (t->hits[i] == t->hits[best] && t->id[i] < t->id[best])))
                best = i;
        float id = 0.0f, coverage = 0.0f;
        if (best >= 0) {
            memcpy(&id, &t->id[best], sizeof id);
            coverage = (float)t->hits[best] / (float)samples;
            t->hits[best] = 0;
        }
        planes[2 * k][p] = id;
        planes[2 * k + 1][p] = coverage;
    }
}

/* Where on the film the scene can be seen: its bounding box (Embree's, of
 * everything committed) projected, every corner in front of the camera (a
 * convex box in front projects inside its corners' hull), grown by a pixel
 * for the rounding of ray directions. A primary ray through a film point
 * outside misses the box and so everything in it: such pixels are misses
 * without a ray (a distant object leaves most of the film empty; its rays
 * were the floor of a frame's time however few triangles it had). The
 * whole film when a corner is behind or near the camera's plane (or the
 * caller asks for every pixel); nothing when the scene is empty. */
static void scene_rect(trace_ctx *c, const mr_trace_setup *s, int width, int height)
{
    c->x0 = 0, c->x1 = width, c->y0 = 0, c->y1 = height;
    if (s->trace_every_pixel)
        return;
    struct RTCBounds b;
    rtcGetSceneBounds(s->scene, &b);
    if (!(b.lower_x <= b.upper_x && b.lower_y <= b.upper_y && b.lower_z <= b.upper_z)) {
        c->x0 = c->y0 = 1, c->x1 = c->y1 = -1; /* empty: every ray misses */
        return;
    }
    const double th = tan(0.5 * (double)s->camera.yfov), aspect = (double)width / height;
    mr_vec3 right = mr_quat_rotate(s->camera.rotation, mr_v3(1, 0, 0));
    mr_vec3 up = mr_quat_rotate(s->camera.rotation, mr_v3(0, 1, 0));
    double x0 = INFINITY, x1 = -INFINITY, y0 = INFINITY, y1 = -INFINITY;
    for (int k = 0; k < 8; k++) {
        mr_vec3 p = mr_v3(k & 1 ? b.upper_x : b.lower_x, k & 2 ? b.upper_y : b.lower_y,
                          k & 4 ? b.upper_z : b.lower_z);
        mr_vec3 d = mr_v3_sub(p, s->camera.position);
        double z = (double)d.x * c->forward.x + (double)d.y * c->forward.y + (double)d.z * c->forward.z;
        double len = sqrt((double)d.x * d.x + (double)d.y * d.y + (double)d.z * d.z);
        if (!(z > 1e-4 * len) || !isfinite(z))
            return; /* near or behind the camera's plane: the whole film */
        double X = (double)d.x * right.x + (double)d.y * right.y + (double)d.z * right.z;
        double Y = (double)d.x * up.x + (double)d.y * up.y + (double)d.z * up.z;
        /* film point (px, py) looks along camera-space x = (2 px / w - 1) th aspect,
         * y = (1 - 2 py / h) th (mr_camera_rays_setup) */
        double px = (X / z / (th * aspect) + 1) * 0.5 * width, py = (1 - Y / z / th) * 0.5 * height;
        x0 = fmin(x0, px), x1 = fmax(x1, px), y0 = fmin(y0, py), y1 = fmax(y1, py);
    }
    c->x0 = x0 - 1, c->x1 = x1 + 1, c->y0 = y0 - 1, c->y1 = y1 + 1;
}

/* Whether a primary ray through the film rectangle [x0, x1] x [y0, y1]
 * can hit the scene (scene_rect). */
static bool rect_seen(const trace_ctx *c, double x0, double x1, double y0, double y1)
{
    return x1 >= c->x0 && x0 <= c->x1 && y1 >= c->y0 && y0 <= c->y1;
}

/* The data planes (depth, normal, position, tangent, ids) of n pixels of
 * a tile row from index p as a miss leaves them: depth MR_DEPTH_MISS,
 * every other 0. A packet row at a time (n = MR_PACKET_W but at the
 * tile's right edge): a few wide stores, where writing each missed lane's
 * planes one by one took a tenth of the trace (static-human). */
static inline void fill_miss_row(tile_buffer *t, size_t p, size_t n)
{
    void *zero[] = {t->nx + p, t->ny + p, t->nz + p, t->px + p, t->py + p, t->pz + p,
                    t->tx + p, t->ty + p, t->tz + p, t->object_id + p, t->prim_id + p};
    for (size_t k = 0; k < sizeof zero / sizeof zero[0]; k++)
        memset(zero[k], 0, n * 4);
    for (size_t i = 0; i < n; i++)
        t->z[p + i] = MR_DEPTH_MISS;
}

static void store_miss_row(tile_buffer *t, size_t p, int n)
{
    if (n == MR_PACKET_W)
        fill_miss_row(t, p, MR_PACKET_W); /* a size the compiler knows: inline stores */
    else
        fill_miss_row(t, p, (size_t)n);
}

/* The data planes of packet pk's pixels (tile index i0 on) as misses. */
static void store_miss_rows(tile_buffer *t, const packet_px *pk, size_t i0)
{
    for (int row = 0; row < MR_PACKET_ROWS && lane_live(pk->live, row * MR_PACKET_W); row++)
        store_miss_row(t, i0 + (size_t)row * MR_TILE_W, row_pixels(pk, row));
}

/* The colour and alpha sums of n missed samples, from zero, added in
 * order: what every lane holds after them. */
static void miss_sums(int n, mr_vec3 miss_rgb, float miss_alpha, mr_vec3 *rgb, float *alpha)
{
    *rgb = mr_v3(0, 0, 0);
    *alpha = 0;
    for (int j = 0; j < n; j++) {
        *rgb = mr_v3_add(*rgb, miss_rgb);
        *alpha += miss_alpha;
    }
}

/* All samples of the packet's pixels; results go to the tile from index i0
 * (the packet's first pixel); seen: false when none of their rays can hit
 * the scene (rect_seen): misses, untraced. Returns whether any sample hit;
 * if none did, every pixel is the miss values (c->miss), which go to the
 * tile only for c->misses_to_tile. */
static bool trace_pixels(const trace_ctx *c, const packet_px *pk, bool seen, tile_buffer *t,
                         size_t i0, uint64_t *rays)
{
    const mr_trace_setup *s = c->s;
    const bool colour = s->aovs & MR_AOV_RGBA, crypto = s->aovs & MR_AOV_CRYPTOMATTE;
    /* sample 0 alone feeds the data passes */
    const int samples = colour || crypto ? s->spp : 1;
    /* the lanes' sums, set when a sample first hits (a packet no sample
     * hits, most of a frame's, never reads them) */
    mr_vec3 rgb[MR_PACKET];
    float alpha[MR_PACKET];
    crypto_tally tally[MR_PACKET][MR_CRYPTO_LAYERS];
    if (crypto)
        for (int i = 0; i < MR_PACKET; i++)
            for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
                tally[i][l].count = 0;
    mr_vec3 miss_rgb = mr_v3_scale(s->background, s->background_alpha);
    /* Samples that hit nothing before any sample hit: every lane's sums
     * are the same, made once (miss_sums) and handed to the lanes when a
     * later sample hits; a packet no sample hits keeps them as its one
     * colour. */
    int lead = 0;
    unsigned any = 0;
    bool data = false; /* the data planes written */
    mr_vec3 lead_rgb = mr_v3(0, 0, 0);
    float lead_alpha = 0;
    for (int k = 0; k < samples; k++) {
        sample_result r[MR_PACKET];
        unsigned hits = seen ? trace_packet(c, pk, k, r, rays) : 0;
        if (!(any | hits)) {
            lead++;
        } else {
            if (!any) {
                miss_sums(lead, miss_rgb, s->background_alpha, &lead_rgb, &lead_alpha);
                for (int i = 0; i < MR_PACKET; i++)
                    rgb[i] = lead_rgb, alpha[i] = lead_alpha;
            }
            any |= hits;
            for (int i = 0; i < MR_PACKET; i++) {
                bool hit = hits >> i & 1u;
                rgb[i] = mr_v3_add(rgb[i], hit ? r[i].rgb : miss_rgb);
                alpha[i] += hit ? 1.0f : s->background_alpha;
            }
        }
        /* the data planes: the misses' values, then the hits' (sample 0
         * alone; a packet it misses whole is written below, if at all) */
        if (k == 0 && hits)
            store_miss_rows(t, pk, i0), data = true;
        for (unsigned m = hits; m; m &= m - 1) {
            int i = __builtin_ctz(m);
            if (crypto)
                for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
                    tally_add(&tally[i][l], s->crypto_ids[l][r[i].object - 1]);
            if (k == 0) {
                size_t p = lane_at(i0, i);
                t->z[p] = r[i].depth;
                t->nx[p] = r[i].normal.x;
                t->ny[p] = r[i].normal.y;
                t->nz[p] = r[i].normal.z;
                t->px[p] = r[i].pos.x;
                t->py[p] = r[i].pos.y;
                t->pz[p] = r[i].pos.z;
                t->tx[p] = r[i].tangent.x;
                t->ty[p] = r[i].tangent.y;
                t->tz[p] = r[i].tangent.z;
                t->object_id[p] = r[i].object;
                t->prim_id[p] = r[i].prim;
            }
        }
    }
    if (!any && !c->misses_to_tile)
        return false;
    if (!data) /* sample 0 hit nothing */
        store_miss_rows(t, pk, i0);
    float inv_spp = 1.0f / (float)s->spp;
    if (!any)
        miss_sums(lead, miss_rgb, s->background_alpha, &lead_rgb, &lead_alpha);
    if (!any && crypto)
        for (int i = 0; i < MR_PACKET; i++)
            rgb[i] = lead_rgb, alpha[i] = lead_alpha;
    if (!any && !crypto) {
        /* no sample hit: one colour for the packet, a row at a time (most
         * packets of a frame; lane by lane it cost skinned-walk ~3 % of
         * its 1280x720 trace) */
        const float v[4] = {lead_rgb.x * inv_spp, lead_rgb.y * inv_spp, lead_rgb.z * inv_spp,
                            lead_alpha * inv_spp};
        float *plane[4] = {t->r, t->g, t->b, t->a};
        for (int row = 0; row < MR_PACKET_ROWS && lane_live(pk->live, row * MR_PACKET_W); row++) {
            const int n = row_pixels(pk, row);
            const size_t p = i0 + (size_t)row * MR_TILE_W;
            for (int q = 0; q < 4; q++)
                for (int i = 0; i < n; i++)
                    plane[q][p + (size_t)i] = v[q];
        }
        return false;
    }
    for (unsigned m = pk->live; m; m &= m - 1) {
        int i = __builtin_ctz(m);
        size_t p = lane_at(i0, i);
        t->r[p] = rgb[i].x * inv_spp;
        t->g[p] = rgb[i].y * inv_spp;
        t->b[p] = rgb[i].z * inv_spp;
        t->a[p] = alpha[i] * inv_spp;
        if (crypto)
            for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
                tally_write(&tally[i][l], c->film->crypto_ranks, samples, t->crypto[l], p);
    }
    return any != 0;
}

/* Copies n 4-byte values from a tile row into the film, inline: most runs
 * are one packet row (32 bytes), and a call to memcpy for each of a
 * block's 20 or so plane rows took 4-6 % of static-human's trace.
 * (Streaming stores cut the trace but cost the EXR encoder, which reads
 * the film next, as much: README, Benchmarks.) */
static inline void copy_out(void *dst, const void *src, int n)
{
    uint32_t *d = dst;
    const uint32_t *s = src;
    int i = 0;
    for (; i + 4 <= n; i += 4)
        _mm_storeu_si128((__m128i *)(d + i), _mm_loadu_si128((const __m128i *)(s + i)));
    for (; i < n; i++)
        d[i] = s[i];
}

/* The film's planes and a tile buffer's, in one order (PLANES). */
static void film_planes(mr_film *f, void *out[PLANES])
{
    void *o[PLANES] = {f->r, f->g, f->b, f->a, f->z /* PLANE_Z */, f->nx, f->ny, f->nz,
                       f->px, f->py, f->pz, f->tx, f->ty, f->tz, f->object_id, f->prim_id};
    memcpy(out, o, sizeof o);
}

static void tile_planes(tile_buffer *t, void *in[PLANES])
{
    void *i[PLANES] = {t->r, t->g, t->b, t->a, t->z /* PLANE_Z */, t->nx, t->ny, t->nz,
                       t->px, t->py, t->pz, t->tx, t->ty, t->tz, t->object_id, t->prim_id};
    memcpy(in, i, sizeof i);
}

/* Fills n 4-byte values of a film row with v: streaming stores where the
 * row is 16-byte aligned (the film is only written here, so its lines need
 * not be read in first). */
static void fill_out(void *dst, uint32_t v, int n)
{
    uint32_t *d = dst;
    int i = 0;
    while (i < n && ((uintptr_t)(d + i) & 15))
        d[i++] = v;
    const __m128i q = _mm_set1_epi32((int)v);
    for (; i + 4 <= n; i += 4)
        _mm_stream_si128((__m128i *)(d + i), q);
    for (; i < n; i++)
        d[i] = v;
}

/* Packet blocks of a tile per row and per column. */
enum { TILE_BLOCKS_X = MR_TILE_W / MR_PACKET_W, TILE_BLOCKS_Y = MR_TILE_H / MR_PACKET_ROWS };
_Static_assert(MR_TILE_W % MR_PACKET_W == 0 && TILE_BLOCKS_X <= 16,
               "a tile row holds whole packets, a 16-bit mask of them");

/* The bits plane k (film_planes' order) holds where mr_film_clear left it;
 * 0 in every Cryptomatte plane. */
static uint32_t cleared_bits(size_t k)
{
    const float depth_miss = MR_DEPTH_MISS;
    uint32_t z;
    memcpy(&z, &depth_miss, sizeof z);
    return k == PLANE_Z ? z : 0u;
}

/* Pixels [x, x + n) of film row y (from the tile's left edge x0): from
 * tile row ty of t (its planes in), or, t NULL, the miss values (streaming
 * stores: lines the film does not read in first), but for the planes
 * where a cleared film holds them already when `cleared`. */
static void put_pixels(const trace_ctx *c, void *const out[PLANES], const tile_buffer *t,
                       void *const in[PLANES], bool cleared, int ty, int x0, int y, int x,
                       int n)
{
    mr_film *f = c->film;
    const size_t dst = (size_t)y * f->width + x0 + x, src = (size_t)ty * MR_TILE_W + x;
    for (size_t k = 0; k < PLANES; k++)
        if (out[k]) { /* the film's passes only */
            if (t)
                copy_out((uint32_t *)out[k] + dst, (const uint32_t *)in[k] + src, n);
            else if (!(cleared && c->miss[k] == cleared_bits(k)))
                fill_out((uint32_t *)out[k] + dst, c->miss[k], n);
        }
    for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
        for (int k = 0; k < 2 * f->crypto_ranks; k++) {
            if (t)
                copy_out(f->crypto[l][k] + dst, t->crypto[l][k] + src, n);
            else if (!(cleared && c->miss_crypto[l][k] == 0u))
                fill_out(f->crypto[l][k] + dst, c->miss_crypto[l][k], n);
        }
}

/* Writes the tile's blocks of mask (bit i: block column i) over film rows
 * [y, y + rows), tile rows from ty, runs of neighbouring blocks at once
 * (t NULL: the miss values; cleared: blocks that hold a cleared film's). */
static void put_blocks(const trace_ctx *c, void *const out[PLANES], const tile_buffer *t,
                       void *const in[PLANES], bool cleared, unsigned mask, int ty, int x0,
                       int y, int rows, int tw)
{
    while (mask) {
        const int a = __builtin_ctz(mask), b = a + __builtin_ctz(~(mask >> a));
        mask &= ~((1u << b) - 1u);
        const int px = a * MR_PACKET_W, pe = b * MR_PACKET_W < tw ? b * MR_PACKET_W : tw;
        for (int r = 0; r < rows; r++)
            put_pixels(c, out, t, in, cleared, ty + r, x0, y + r, px, pe - px);
    }
}

/* Tiles go down bands of TILE_BAND rows of them (64 x 16 pixels), a band
 * at a time: a tile's neighbour below is traced next, so the packets of
 * pixels over the same surface follow one another closely, on the same
 * worker, and the kinds' per-thread caches keep what they made for it
 * (row by row, the next row of a 640-pixel film came 160 packets later and
 * often went to the other worker). A sphere with a height texture at 200
 * texels per unit: cells made a frame 24,369 -> 21,114, trace 0.98 of the
 * time; a procedural plane at range 64 0.96; triangles 1.00
 * (docs/performance.md, stop 63). */
#define TILE_BAND 4

/* Tile `tile`'s first pixel (the tiles in that order). */
static void tile_origin(const trace_ctx *c, size_t tile, int *x0, int *y0)
{
    const size_t per_band = (size_t)c->tiles_x * TILE_BAND, band = tile / per_band;
    const size_t rows = (size_t)c->tiles_y - band * TILE_BAND < TILE_BAND
                            ? (size_t)c->tiles_y - band * TILE_BAND
                            : TILE_BAND; /* (the last band may be shorter) */
    const size_t at = tile - band * per_band;
    *x0 = (int)(at / rows) * MR_TILE_W;
    *y0 = (int)(band * TILE_BAND + at % rows) * MR_TILE_H;
}

static void trace_tiles(void *p, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    trace_ctx *c = p;
    mr_film *f = c->film;
    uint64_t rays = 0;
    tile_buffer t;
    void *out[PLANES], *in[PLANES];
    film_planes(f, out);
    tile_planes(&t, in);
    for (size_t tile = begin; tile < end; tile++) {
        if (c->s->cancel && atomic_load_explicit(c->s->cancel, memory_order_relaxed)) {
            atomic_store(&c->cancelled, true);
            break;
        }
        int x0, y0;
        tile_origin(c, tile, &x0, &y0);
        int tw = f->width - x0 < MR_TILE_W ? f->width - x0 : MR_TILE_W;
        int th = f->height - y0 < MR_TILE_H ? f->height - y0 : MR_TILE_H;
        const unsigned blocks = (1u << ((tw + MR_PACKET_W - 1) / MR_PACKET_W)) - 1u;
        /* the tile's blocks in the film's record (c->held), a row of them
         * at a time: which hold the miss values already, which a cleared
         * film's */
        uint8_t *held[TILE_BLOCKS_Y] = {0};
        unsigned kept[TILE_BLOCKS_Y] = {0}, cleared[TILE_BLOCKS_Y] = {0};
        for (int by = 0; c->held && by * MR_PACKET_ROWS < th; by++) {
            held[by] = c->held + (size_t)(y0 / MR_PACKET_ROWS + by) * c->blocks_x + x0 / MR_PACKET_W;
            for (unsigned m = blocks; m; m &= m - 1) {
                const uint8_t h = held[by][__builtin_ctz(m)];
                kept[by] |= (unsigned)(h == BLOCK_MISS) << __builtin_ctz(m);
                cleared[by] |= (unsigned)(h == BLOCK_CLEARED) << __builtin_ctz(m);
            }
        }
        const bool seen_tile = rect_seen(c, x0, x0 + tw, y0, y0 + th);
        for (int by = 0; by * MR_PACKET_ROWS < th; by++) {
            const int y = by * MR_PACKET_ROWS;
            const int rows = th - y < MR_PACKET_ROWS ? th - y : MR_PACKET_ROWS;
            unsigned hit = 0;
            if (seen_tile)
                for (int x = 0; x < tw; x += MR_PACKET_W) {
                    int cols = tw - x < MR_PACKET_W ? tw - x : MR_PACKET_W;
                    packet_px pk = packet_at(x0 + x, y0 + y, cols, rows);
                    /* the pixels' samples lie in [x, x + cols] x [y, y + rows] */
                    bool seen = rect_seen(c, x0 + x, x0 + x + cols, y0 + y, y0 + y + rows);
                    if (trace_pixels(c, &pk, seen, &t, (size_t)y * MR_TILE_W + x, &rays))
                        hit |= 1u << (x / MR_PACKET_W);
                }
            /* blocks that hit something, from the tile, and misses the
             * film does not hold yet, from c->miss */
            const unsigned put = (hit | ~kept[by]) & blocks;
            const unsigned from_tile = (c->misses_to_tile ? ~0u : hit) & blocks;
            const unsigned miss_blocks = put & ~from_tile;
            put_blocks(c, out, &t, in, false, from_tile, y, x0, y0 + y, rows, tw);
            put_blocks(c, out, NULL, in, false, miss_blocks & ~cleared[by], y, x0, y0 + y, rows,
                       tw);
            put_blocks(c, out, NULL, in, true, miss_blocks & cleared[by], y, x0, y0 + y, rows, tw);
            if (held[by])
                for (unsigned m = put; m; m &= m - 1)
                    held[by][__builtin_ctz(m)] =
                        hit >> __builtin_ctz(m) & 1u ? BLOCK_UNKNOWN : BLOCK_MISS;
        }
    }
    _mm_sfence(); /* the streaming stores (fill_out) before the join says the tiles are done */
    atomic_fetch_add(&c->rays, rays);
}

/* What a pixel no ray of which can hit the scene holds in every plane:
 * the untraced path's own output for one such pixel, bit for bit. */
static bool miss_values(trace_ctx *c)
{
    tile_buffer *t = malloc(sizeof *t);
    if (!t) { /* no template: cull nothing */
        c->x0 = -INFINITY, c->x1 = INFINITY, c->y0 = -INFINITY, c->y1 = INFINITY;
        return false;
    }
    uint64_t rays = 0;
    packet_px one = packet_at(0, 0, 1, 1);
    c->misses_to_tile = true;
    trace_pixels(c, &one, false, t, 0, &rays);
    c->misses_to_tile = false;
    void *in[PLANES];
    tile_planes(t, in);
    for (size_t k = 0; k < PLANES; k++)
        memcpy(&c->miss[k], in[k], 4);
    /* (the film's Cryptomatte ranks only: the tile holds nothing else) */
    const int ranks = c->s->aovs & MR_AOV_CRYPTOMATTE ? 2 * c->film->crypto_ranks : 0;
    for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
        for (int k = 0; k < 2 * MR_CRYPTO_MAX_RANKS; k++) {
            c->miss_crypto[l][k] = 0;
            if (k < ranks)
                memcpy(&c->miss_crypto[l][k], &t->crypto[l][k][0], 4);
        }
    free(t);
    return true;
}

/* The film's record of what its blocks hold (mr_film's misses): a miss's
 * values or a cleared film's (block_state), blocks of MR_PACKET_W x
 * MR_PACKET_ROWS pixels, row-major. */
struct mr_film_misses {
    uint32_t miss[PLANES]; /* the values they hold (trace_ctx's) */
    uint32_t miss_crypto[MR_CRYPTO_LAYERS][2 * MR_CRYPTO_MAX_RANKS];
    uint8_t held[];        /* per block: its block_state */
};

/* The film's record for this frame's miss values (c->miss): its own when
 * it was made for the same values, else a new one that knows nothing (a
 * new background, say) but what a cleared film holds (mr_film.cleared);
 * NULL when out of memory. */
static uint8_t *film_record(trace_ctx *c, int blocks_y)
{
    mr_film *f = c->film;
    struct mr_film_misses *m = f->misses;
    if (m && !memcmp(m->miss, c->miss, sizeof m->miss) &&
        !memcmp(m->miss_crypto, c->miss_crypto, sizeof m->miss_crypto))
        return m->held;
    free(m);
    const size_t blocks = (size_t)c->blocks_x * (size_t)blocks_y;
    f->misses = m = malloc(sizeof *m + blocks);
    if (!m)
        return NULL;
    memcpy(m->miss, c->miss, sizeof m->miss);
    memcpy(m->miss_crypto, c->miss_crypto, sizeof m->miss_crypto);
    memset(m->held, f->cleared ? BLOCK_CLEARED : BLOCK_UNKNOWN, blocks);
    return m->held;
}

uint64_t mr_trace_frame(const mr_trace_setup *setup, mr_film *film, bool *cancelled)
{
    trace_ctx c = {.s = setup, .film = film};
    c.rays_setup = mr_camera_rays_setup(&setup->camera, film->width, film->height);
    c.forward = mr_quat_rotate(setup->camera.rotation, mr_v3(0, 0, -1));
    scene_rect(&c, setup, film->width, film->height);
    c.tiles_x = (film->width + MR_TILE_W - 1) / MR_TILE_W;
    c.blocks_x = (film->width + MR_PACKET_W - 1) / MR_PACKET_W;
    if (miss_values(&c)) {
        c.held = film_record(&c, (film->height + MR_PACKET_ROWS - 1) / MR_PACKET_ROWS);
    } else { /* every block written, and no record kept of this frame's */
        c.misses_to_tile = true;
        free(film->misses);
        film->misses = NULL;
    }
    film->cleared = false; /* (written from here on) */
    c.tiles_y = (film->height + MR_TILE_H - 1) / MR_TILE_H;
    atomic_init(&c.rays, 0);
    atomic_init(&c.cancelled, false);
    /* Workers take runs of tiles, up to a film row's count: every run taken is
     * an atomic add on a counter both cores write (and one on c.rays), and
     * one per 64x4 tile cost a tenth of the trace (static-human, 1280x720,
     * 1 sample: 15.8 -> 14.4 ms a frame with rows; skinned-walk, mostly
     * background, 12.9 -> 10.6). At least 32 runs a thread keep the load
     * balanced. Which worker traces a tile changes no pixel. */
    size_t tiles = (size_t)c.tiles_x * c.tiles_y,
           threads = setup->threads ? setup->threads : mr_cpu_count();
    size_t run = tiles / (threads * 32);
    run = run < 1 ? 1 : run > (size_t)c.tiles_x ? (size_t)c.tiles_x : run;
    mr_parallel_for(setup->threads, tiles, run, trace_tiles, &c);
    if (cancelled)
        *cancelled = atomic_load(&c.cancelled);
    return atomic_load(&c.rays);
}
