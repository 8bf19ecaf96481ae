/*
 * integrator.h - the primary-ray integrator: tiles of pixels traced on all
 * workers, Lambert shading from directional lights plus ambient, optional
 * shadow rays, jittered supersampling.
 *
 * Determinism: each pixel's samples depend only on (seed, frame, x, y,
 * sample), never on which worker traced it, so frames are bit-identical for
 * any thread count. Sample 0 goes through the pixel centre and feeds the data
 * AOVs (film.h); samples 1..spp-1 are uniformly jittered within the pixel.
 * Only the film's passes are computed and written (mr_trace_setup.aovs).
 */
#ifndef MR_INTEGRATOR_H
#define MR_INTEGRATOR_H

#include <embree3/rtcore.h>
#include <stdatomic.h>

#include "kinds/kind.h"
#include "render/camera.h"
#include "render/film.h"

/* Tiles are wide and short: rays of a tile stay coherent, and each tile row
 * is a long contiguous run in every film plane (row-major), which keeps the
 * copy-out from touching a new page per 64 bytes (measured: square 16x16
 * tiles spent a third of the trace time writing the film). */
#ifndef MR_TILE_W
#define MR_TILE_W 64
#endif
#ifndef MR_TILE_H
#define MR_TILE_H 4
#endif
#define MR_TILE_PIXELS (MR_TILE_W * MR_TILE_H)

/* What the integrator needs to know about one object to shade its hits. */
typedef struct mr_shade_object {
    const mr_kind *kind;
    const mr_geom *geom;
    mr_vec3 albedo;
    unsigned first_id;  /* its first Embree geometry id (kind.h geometry_ids) */
} mr_shade_object;

typedef struct mr_trace_setup {
    RTCScene scene;
    const mr_shade_object *objects; /* indexed by object */
    size_t object_count;
    const unsigned *id_object;      /* Embree geometry id (instID for instances, else
                                       geomID) -> object; NULL: the id is the object */
    unsigned id_count;
    mr_camera camera;
    const mr_light_desc *lights;
    size_t light_count;
    mr_vec3 ambient, background;
    float background_alpha;
    int spp;
    bool shadows;
    uint32_t seed;
    uint32_t frame;
    /* The passes to compute (the film's, mr_aov bits): without rgba no
     * pixel is shaded (no light loop, no shadow rays) and only sample 0
     * (the data passes) is traced, unless cryptomatte needs every sample. */
    unsigned aovs;
    /* Cryptomatte: each object's id (mr_cryptomatte_id of its name, and of
     * its asset's name), indexed by object. NULL without the pass. */
    const float *crypto_ids[MR_CRYPTO_LAYERS];
    float shadow_bias;              /* world units, ~1e-4 of the scene diagonal */
    unsigned threads;
    const atomic_bool *cancel;      /* may be NULL; checked before every tile */
    bool trace_every_pixel;         /* no scene-rectangle cull (mr_renderer_options) */
} mr_trace_setup;

/* Traces the whole film; returns the number of rays traced. When *cancel
 * becomes true the remaining tiles are skipped (the film is then incomplete
 * and *cancelled is set). */
uint64_t mr_trace_frame(const mr_trace_setup *setup, mr_film *film, bool *cancelled);

#endif
