/*
 * film.h - the frame buffer a render writes into: one plane per AOV.
 *
 * Planes are row-major, row 0 at the top of the image (EXR's increasing-y
 * order). Colour is linear and premultiplied by alpha.
 *
 * The data AOVs (z, n*, object_id, prim_id) describe the pixel-centre ray
 * (sample 0), so two renders of the same camera compare pixel by pixel
 * whatever their sample counts; colour and alpha average all samples.
 *  - z: distance along the (unit-length) ray to the hit; 0 where it missed.
 *  - nx, ny, nz: world-space shading normal, unit length, facing the camera;
 *    0 where it missed.
 *  - object_id: 1-based index of the job object hit, 0 = miss.
 *  - prim_id: index of the primitive (triangle) within that object.
 */
#ifndef MR_FILM_H
#define MR_FILM_H

#include "microray.h"

/* Caps shared by the job parser and the film allocator (documented in README). */
#define MR_MAX_RESOLUTION 8192                 /* per side, pixels */
#define MR_MAX_PIXELS (4096u * 4096u)          /* width * height */

typedef struct mr_film {
    int width, height;
    float *r, *g, *b, *a;
    float *z;
    float *nx, *ny, *nz;
    uint32_t *object_id, *prim_id;
} mr_film;

/* Allocates a zeroed film. Fails with MR_ERR_LIMIT beyond the caps above. */
int mr_film_new(int width, int height, mr_film **out, mr_error *err);
void mr_film_free(mr_film *film);
/* Resets every plane to zero (miss). */
void mr_film_clear(mr_film *film);

#endif
