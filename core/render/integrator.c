/* integrator.c - tiled primary-ray integrator (integrator.h). */
#include "render/integrator.h"

#include <float.h>
#include <stdatomic.h>
#include <string.h>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#include "util/parallel.h"

/* splitmix64 finaliser: a good 64-bit mix, cheap, and stateless, which is
 * what per-pixel determinism needs. */
static inline uint64_t mix64(uint64_t z)
{
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
}

/* Two uniform floats in [0,1) for one sample. */
static inline void sample_jitter(const mr_trace_setup *s, uint32_t x, uint32_t y, uint32_t k, float *jx,
                                 float *jy)
{
    uint64_t h = mix64(((uint64_t)s->seed << 32 | s->frame) ^ mix64((uint64_t)y << 32 | x) ^
                       mix64((uint64_t)k + 0x9e3779b97f4a7c15ull));
    *jx = (float)(h >> 40) * (1.0f / 16777216.0f);
    *jy = (float)((h >> 16) & 0xffffff) * (1.0f / 16777216.0f);
}

typedef struct {
    const mr_trace_setup *s;
    mr_camera_rays rays_setup;
    mr_film *film;
    int tiles_x;
    atomic_ullong rays;
} trace_ctx;

typedef struct {
    bool hit;
    float t;
    mr_vec3 normal; /* shading normal, unit, facing the ray origin */
    uint32_t object, prim;
    mr_vec3 rgb;
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

static void shade(const mr_trace_setup *s, const struct RTCRayHit *rh, mr_vec3 org, mr_vec3 dir,
                  sample_result *out, uint64_t *rays)
{
    const mr_shade_object *obj = &s->objects[rh->hit.geomID];
    mr_vec3 ng = mr_v3_normalize_or(mr_v3(rh->hit.Ng_x, rh->hit.Ng_y, rh->hit.Ng_z), mr_v3(0, 0, 1));
    if (mr_v3_dot(ng, dir) > 0)
        ng = mr_v3_scale(ng, -1.0f);
    mr_vec3 n = obj->ops->normal(obj->geom, rh->hit.primID, rh->hit.u, rh->hit.v);
    n = mr_v3_normalize_or(n, ng);
    if (mr_v3_dot(n, dir) > 0)
        n = mr_v3_scale(n, -1.0f);
    out->hit = true;
    out->t = rh->ray.tfar;
    out->normal = n;
    out->object = rh->hit.geomID + 1;
    out->prim = rh->hit.primID;

    mr_vec3 light = s->ambient;
    mr_vec3 p = mr_v3_add(org, mr_v3_scale(dir, rh->ray.tfar));
    mr_vec3 shadow_org = offset_from_surface(p, ng, s->shadow_bias);
    for (size_t i = 0; i < s->light_count; i++) {
        mr_vec3 l = mr_v3_scale(s->lights[i].direction, -1.0f); /* towards the light */
        float cosine = mr_v3_dot(n, l);
        if (cosine <= 0 || mr_v3_dot(ng, l) <= 0)
            continue;
        if (s->shadows) {
            struct RTCIntersectContext ctx;
            rtcInitIntersectContext(&ctx);
            struct RTCRay ray = {.org_x = shadow_org.x, .org_y = shadow_org.y, .org_z = shadow_org.z,
                          .dir_x = l.x, .dir_y = l.y, .dir_z = l.z,
                          .tnear = 0.0f, .tfar = FLT_MAX, .mask = 0xffffffffu, .flags = 0};
            rtcOccluded1(s->scene, &ctx, &ray);
            (*rays)++;
            if (ray.tfar < 0) /* Embree sets tfar = -inf when occluded */
                continue;
        }
        light = mr_v3_add(light, mr_v3_scale(s->lights[i].color, cosine));
    }
    out->rgb = mr_v3_mul(obj->albedo, light);
}

static void trace_sample(const mr_trace_setup *s, mr_vec3 org, mr_vec3 dir, sample_result *out,
                         uint64_t *rays)
{
    struct RTCIntersectContext ctx;
    rtcInitIntersectContext(&ctx);
    struct RTCRayHit rh;
    rh.ray = (struct RTCRay){.org_x = org.x, .org_y = org.y, .org_z = org.z,
                      .dir_x = dir.x, .dir_y = dir.y, .dir_z = dir.z,
                      .tnear = 0.0f, .tfar = FLT_MAX, .mask = 0xffffffffu, .flags = 0};
    rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
    rtcIntersect1(s->scene, &ctx, &rh);
    (*rays)++;
    if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID || rh.hit.geomID >= s->object_count) {
        *out = (sample_result){.hit = false};
        return;
    }
    shade(s, &rh, org, dir, out, rays);
}

/* One tile's worth of every film plane. Tiles are traced into this private
 * buffer and copied out row by row when done: neighbouring tiles go to
 * different workers, and writing the shared film pixel by pixel made them
 * fight over the cache lines at tile edges (false sharing halved the ray rate
 * on 2 cores). */
typedef struct tile_buffer {
    float r[MR_TILE_PIXELS], g[MR_TILE_PIXELS], b[MR_TILE_PIXELS];
    float a[MR_TILE_PIXELS], z[MR_TILE_PIXELS];
    float nx[MR_TILE_PIXELS], ny[MR_TILE_PIXELS], nz[MR_TILE_PIXELS];
    uint32_t object_id[MR_TILE_PIXELS], prim_id[MR_TILE_PIXELS];
} tile_buffer;

static void trace_pixel(const trace_ctx *c, int x, int y, tile_buffer *t, size_t i, uint64_t *rays)
{
    const mr_trace_setup *s = c->s;
    mr_vec3 rgb = mr_v3(0, 0, 0);
    float alpha = 0;
    for (int k = 0; k < s->spp; k++) {
        float jx = 0.5f, jy = 0.5f;
        if (k > 0)
            sample_jitter(s, (uint32_t)x, (uint32_t)y, (uint32_t)k, &jx, &jy);
        mr_vec3 dir = mr_camera_rays_dir(&c->rays_setup, (float)x + jx, (float)y + jy);
        sample_result r;
        trace_sample(s, c->rays_setup.origin, dir, &r, rays);
        if (r.hit) {
            rgb = mr_v3_add(rgb, r.rgb);
            alpha += 1.0f;
        } else {
            rgb = mr_v3_add(rgb, mr_v3_scale(s->background, s->background_alpha));
            alpha += s->background_alpha;
        }
        if (k == 0) {
            t->z[i] = r.hit ? r.t : 0.0f;
            t->nx[i] = r.hit ? r.normal.x : 0.0f;
            t->ny[i] = r.hit ? r.normal.y : 0.0f;
            t->nz[i] = r.hit ? r.normal.z : 0.0f;
            t->object_id[i] = r.hit ? r.object : 0;
            t->prim_id[i] = r.hit ? r.prim : 0;
        }
    }
    float inv_spp = 1.0f / (float)s->spp;
    t->r[i] = rgb.x * inv_spp;
    t->g[i] = rgb.y * inv_spp;
    t->b[i] = rgb.z * inv_spp;
    t->a[i] = alpha * inv_spp;
}

/* Copies n 4-byte values from a tile row into the film. The film is far
 * larger than the caches and is not read again until encoding, so where the
 * destination is 16-byte aligned the copy uses streaming stores, which skip
 * reading each line in before overwriting it. Bit-identical either way. */
static void copy_out(void *dst, const void *src, int n)
{
#if defined(__SSE2__)
    if (((uintptr_t)dst & 15) == 0 && (n & 3) == 0) {
        float *d = dst;
        const float *sp = src;
        for (int i = 0; i < n; i += 4)
            _mm_stream_ps(d + i, _mm_loadu_ps(sp + i));
        return;
    }
#endif
    memcpy(dst, src, (size_t)n * 4);
}

static void trace_tiles(void *p, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    trace_ctx *c = p;
    mr_film *f = c->film;
    uint64_t rays = 0;
    tile_buffer t;
    for (size_t tile = begin; tile < end; tile++) {
        int x0 = (int)(tile % (size_t)c->tiles_x) * MR_TILE_W;
        int y0 = (int)(tile / (size_t)c->tiles_x) * MR_TILE_H;
        int tw = f->width - x0 < MR_TILE_W ? f->width - x0 : MR_TILE_W;
        int th = f->height - y0 < MR_TILE_H ? f->height - y0 : MR_TILE_H;
        for (int y = 0; y < th; y++)
            for (int x = 0; x < tw; x++)
                trace_pixel(c, x0 + x, y0 + y, &t, (size_t)y * MR_TILE_W + x, &rays);
        for (int y = 0; y < th; y++) {
            size_t src = (size_t)y * MR_TILE_W, dst = (size_t)(y0 + y) * f->width + x0;
            copy_out(f->r + dst, t.r + src, tw);
            copy_out(f->g + dst, t.g + src, tw);
            copy_out(f->b + dst, t.b + src, tw);
            copy_out(f->a + dst, t.a + src, tw);
            copy_out(f->z + dst, t.z + src, tw);
            copy_out(f->nx + dst, t.nx + src, tw);
            copy_out(f->ny + dst, t.ny + src, tw);
            copy_out(f->nz + dst, t.nz + src, tw);
            copy_out(f->object_id + dst, t.object_id + src, tw);
            copy_out(f->prim_id + dst, t.prim_id + src, tw);
        }
    }
#if defined(__SSE2__)
    _mm_sfence(); /* streaming stores are weakly ordered: publish them before the join */
#endif
    atomic_fetch_add(&c->rays, rays);
}

uint64_t mr_trace_frame(const mr_trace_setup *setup, mr_film *film)
{
    trace_ctx c = {.s = setup, .film = film};
    c.rays_setup = mr_camera_rays_setup(&setup->camera, film->width, film->height);
    c.tiles_x = (film->width + MR_TILE_W - 1) / MR_TILE_W;
    int tiles_y = (film->height + MR_TILE_H - 1) / MR_TILE_H;
    atomic_init(&c.rays, 0);
    mr_parallel_for(setup->threads, (size_t)c.tiles_x * tiles_y, 1, trace_tiles, &c);
    return atomic_load(&c.rays);
}
