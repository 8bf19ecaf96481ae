/*
 * inside.h - which points of a regular lattice lie inside a triangle mesh
 * (the node grid of paper 001 fills the inside of the detailed mesh).
 *
 * Votes of three ray families, then an exact fallback:
 *  1. Rows of lattice points along each axis a are lines; each line is
 *     crossed with every triangle in the projection onto the other two axes
 *     (exact-sign edge functions in a canonical endpoint order with one
 *     symbolic perturbation for every triangle, so a line through a shared
 *     edge or vertex of a watertight mesh crosses exactly once). A crossing
 *     carries the sign of the triangle normal's a component.
 *  2. Along a line whose signed crossings sum to zero (a closed, consistently
 *     oriented surface) a point votes inside when the signed sum before it
 *     is non-zero: the winding number along the ray, so nested and
 *     overlapping shells count as their union. A line whose signs do not
 *     cancel but whose crossings are even in number (closed, some triangles
 *     flipped) votes by parity. A line with an odd count passed through a
 *     hole and does not vote at all: a small hole costs the lines through
 *     it their vote, never a streak of wrong points.
 *  3. Points with more inside than outside votes are inside and vice versa;
 *     ties (every line through the point passed a hole, or the families
 *     disagree) get the generalised winding number (the solid angle of the
 *     whole mesh seen from the point over 4 pi, inside when |w| >= 1/2),
 *     which is robust to holes but costs a pass over all triangles. More
 *     than SM_WINDING_BUDGET point-triangle pairs is refused (a mesh that
 *     is open almost everywhere has no inside to fill).
 * Results are the same for any thread count.
 */
#ifndef SM_INSIDE_H
#define SM_INSIDE_H

#include <stddef.h>
#include <stdint.h>

#include "microray.h"

/* Point-triangle solid angles the fallback may evaluate for one lattice. */
#define SM_WINDING_BUDGET 400000000ull

typedef struct sm_lattice {
    double origin[3]; /* position of point (0, 0, 0) */
    double h;         /* spacing */
    uint32_t n[3];    /* points per axis; point (i, j, k) is at i + n0 (j + n1 k) */
} sm_lattice;

typedef struct sm_inside_info {
    size_t inside;        /* points found inside */
    size_t abstained;     /* lines that did not vote (an odd crossing count: a hole) */
    size_t lines;         /* lines cast, over the three axes */
    size_t winding;       /* points decided by the generalised winding number */
} sm_inside_info;

/* Fills inside[point] with 1 (inside) or 0 for every point of the lattice.
 * positions: 3 doubles per vertex; triangles: 3 indices each (all <
 * vertex_count, checked by the caller). MR_ERR_LIMIT when the fallback
 * would exceed SM_WINDING_BUDGET (the message says how many points the
 * rays could not decide), MR_ERR_NOMEM. */
int sm_inside_lattice(const double *positions, const uint32_t *triangles, uint32_t triangle_count,
                      const sm_lattice *lat, unsigned threads, uint8_t *inside,
                      sm_inside_info *info, mr_error *err);

/* The generalised winding number of the mesh at p (1 inside a closed
 * outward-oriented surface, 0 outside, about 1/2 on it). */
double sm_winding_number(const double *positions, const uint32_t *triangles,
                         uint32_t triangle_count, const double p[3]);

#endif
