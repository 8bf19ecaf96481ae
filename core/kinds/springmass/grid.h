/*
 * grid.h - the node grid of paper 001 (3.1): nodes on a regular lattice
 * filling the inside of the detailed mesh, each connected to its 18 nearest
 * neighbours (6 along the axes at distance h, 12 along face diagonals at
 * h sqrt 2), in world space.
 *
 * Lattice: axis-aligned, spacing h; along each axis the points covering
 * the mesh's bounding box, centred on it (three at least, so a box thinner
 * than 2 h still gets its middle layer of nodes), plus SM_GRID_PAD empty
 * layers on every side, so every neighbour offset of a node, and of the cells the
 * mappings read around the surface, stays inside the arrays.
 * Nodes: the lattice points inside the mesh (inside.h), less the specks:
 * parts linked by springs to no more than SM_GRID_MIN_PART - 1 other nodes
 * (and under 1 % of all), a few lattice points that caught a thin feature
 * (a tail's tip) and would float free of the body; the mappings bind the
 * surface there to the nearest nodes that remain. Flags per node:
 *  - surface: a node with an empty axis neighbour (its 18-neighbourhood
 *    reaches outside); the mappings bind vertices to surface nodes;
 *  - thin: a node with both axis neighbours empty along some axis, in a
 *    part one node thin there: its approximate normal (eq. 3) has no
 *    neighbour across the sheet (3.5), so the curvature-corrected mapping
 *    falls back to the constant basis around it.
 * Spacing: given, or found for a target node count: h from the box volume,
 * then scaled by the cube root of found / target until within 5 % (at most
 * six classifications).
 */
#ifndef SM_GRID_H
#define SM_GRID_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "kinds/springmass/inside.h"
#include "microray.h"

#define SM_GRID_PAD 2u
/* Largest grid (cells, padding included) and node count one object may
 * have; the parameters are refused beyond them. */
#define SM_GRID_MAX_CELLS (1u << 23)
#define SM_GRID_MAX_NODES (1u << 21)
/* Parts (nodes linked by springs) smaller than this, and than 1 % of the
 * nodes, are dropped: specks of a thin feature the lattice caught alone. */
#define SM_GRID_MIN_PART 8u

enum { SM_NODE_SURFACE = 1u, SM_NODE_THIN = 2u };

typedef struct sm_grid {
    uint32_t n[3];       /* cells per axis, padding included */
    size_t cells;        /* n0 n1 n2; cell (i, j, k) is i + n0 (j + n1 k) */
    double origin[3];    /* world position of cell (0, 0, 0) */
    double h;            /* spacing, world units */
    uint8_t *active;     /* per cell: 1 = a node */
    uint8_t *flags;      /* per cell: SM_NODE_* */
    size_t nodes, surface_nodes, thin_nodes;
    size_t dropped;      /* nodes of specks dropped (below) */
    sm_inside_info inside;
} sm_grid;

/* The 18 neighbour offsets (di, dj, dk): 6 axis ones first (rest length
 * h), then 12 face diagonals (h sqrt 2), in a fixed order every loop uses
 * (the order of summation, and so the bits, depend on it). */
extern const int8_t sm_neighbour_dir[18][3];

/* Builds the grid for the world-space mesh (positions: 3 doubles per
 * vertex). spacing > 0 uses it; else target_nodes (> 0) picks one.
 * max_cells caps the grid below SM_GRID_MAX_CELLS (a memory budget); a
 * grid beyond it, or with more than SM_GRID_MAX_NODES nodes, is
 * MR_ERR_LIMIT; a mesh holding no node is MR_ERR_INVALID. Messages do not
 * name the parameter: the caller prefixes it. */
int sm_grid_build(const double *positions, uint32_t vertex_count, const uint32_t *triangles,
                  uint32_t triangle_count, double spacing, uint32_t target_nodes, size_t max_cells,
                  unsigned threads, sm_grid *out, mr_error *err);
void sm_grid_free(sm_grid *g);

/* Cell index of (i, j, k). */
static inline size_t sm_grid_cell(const sm_grid *g, uint32_t i, uint32_t j, uint32_t k)
{
    return i + (size_t)g->n[0] * (j + (size_t)g->n[1] * k);
}
/* Signed offset between neighbouring cells along d. */
static inline ptrdiff_t sm_grid_offset(const sm_grid *g, const int8_t d[3])
{
    return d[0] + (ptrdiff_t)g->n[0] * (d[1] + (ptrdiff_t)g->n[1] * d[2]);
}

#endif
