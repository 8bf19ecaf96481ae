/*
 * dsurf.h - the displaced surface over one base triangle, exactly: the one
 * definition the tessellation-free traversal, the tessellated reference and
 * the ray marcher share (issue 14).
 *
 * Heights live on the integer points of a "grid space" (dgrid.h: texel
 * corners of the height texture, or the procedural lattice subdivided
 * `range` times). Every cell [i, i+1] x [j, j+1] is split by its
 * anti-diagonal x + y = i + j + 1 into a lower triangle (i, j) (i+1, j)
 * (i, j+1) and an upper one, and heights are linear on each: two triangles
 * per texel. A base triangle T maps to grid space through its vertices'
 * texture coordinates (g_k); the surface over T is T cut by those lines:
 * every piece T n (cell half) is a convex polygon, fanned into
 * micro-triangles whose vertices are displaced along the unit interpolated
 * normal:  S(q) = P(q) + h(q) N(q) / |N(q)|  (thesis eq. 2.1), with P and
 * N interpolated over T, h linear over the cell half. A piece's vertices are
 * of three sorts, each evaluated by one function of data both neighbours
 * of a shared edge hold identically:
 *  - BASE k: a corner of T (p_k, n_k, h at g_k by the canonical cell-half
 *    formula);
 *  - EDGE: where a base edge crosses a grid line x = i, y = j or x + y = k:
 *    computed from the edge's two endpoints in a canonical order (the one
 *    with the smaller grid coordinates first), so both triangles sharing
 *    the edge compute bit-identical points, P, N and h (linear along the
 *    grid line);
 *  - GRID (i, j): a grid point inside T (barycentric P and N, h = H(i, j)).
 * Pieces are cut from T by Sutherland-Hodgman against the cell's lines in a
 * fixed order (x >= i, x <= i+1, y >= j, y <= j+1, then the diagonal),
 * every crossing of a base edge computed from that edge alone and every
 * other crossing being an exact grid point: both sides of a shared edge
 * then make the same decisions about it and hold the same vertices along
 * it, so the micro-triangles meet without cracks (tested with rays along
 * every shared edge: tests/hard/test_displaced_seams.c). Two triangles that
 * share an edge in space but not its texture coordinates (a UV seam) meet
 * only where their heights agree: a seam in the texture is a seam in the
 * surface, as in any displacement by texture.
 *
 * Zero-area triangles in grid space ("flat": collinear or equal texture
 * coordinates) have no interior to cut: their surface is a fan over their
 * boundary points (corners and edge crossings, the same points their
 * neighbours use), so neighbours still close up against them.
 *
 * Precision: grid coordinates, P, N and h are doubles; micro-vertices are
 * rounded to float once, at the end. Results do not depend on the order in
 * which cells are visited or on threads.
 */
#ifndef MR_DSURF_H
#define MR_DSURF_H

#include <stdbool.h>
#include <stdint.h>

#include "math/mr_math.h"

/* A source of heights on the grid's integer points. */
typedef struct mr_dheights {
    double (*at)(const void *src, int64_t i, int64_t j);
    const void *src;
} mr_dheights;

/* One base triangle as the surface is defined over it. */
typedef struct mr_dbase {
    double g[3][2];   /* grid coordinates of the corners */
    double p[3][3];   /* positions */
    double n[3][3];   /* normals (unit, or zero) */
    double h[3];      /* heights at the corners */
    double m[4];      /* (b1, b2) = [m0 m2; m1 m3] (q - g0): grid -> barycentric */
    bool flat;        /* no area in grid space: a boundary fan */
    int orient;       /* +1: corners counter-clockwise in grid space, -1: clockwise */
    double edge[3][3];/* edge e's line: a x + b y + c, positive inside T (orient applied) */
    double margin;    /* grid-space distance taken as "clearly inside" (dsurf.c) */
    uint8_t canon[3]; /* edge e (corner e -> e+1) starts at corner e (0) or e+1 (1) canonically */
} mr_dbase;

/* What a micro-vertex is (the kinds above). */
enum { MR_DV_BASE = 0, MR_DV_EDGE, MR_DV_GRID };
/* Grid line families. */
enum { MR_DLINE_X = 0, MR_DLINE_Y, MR_DLINE_D };

typedef struct mr_dvert {
    double x, y;       /* grid coordinates */
    uint8_t kind;      /* MR_DV_* */
    uint8_t idx;       /* BASE: corner; EDGE: base edge */
    uint8_t fam;       /* EDGE: family of the grid line crossed */
    int64_t a, b;      /* GRID: (i, j); EDGE: the line's value in a */
    double t;          /* EDGE: parameter from the canonical start */
} mr_dvert;

/* The pieces of one cell half, fanned: at most this many micro-triangles. */
#define MR_DSURF_MAX_POLY 12
#define MR_DSURF_MAX_TRIS (2 * (MR_DSURF_MAX_POLY - 2))

/* The micro-triangles of one cell (both halves, or one: half = 0 lower,
 * 1 upper, 2 both): vertex records (deduplicated within the cell) and
 * triangles as index triples into them. */
typedef struct mr_dcell {
    int nv, nt;
    mr_dvert v[2 * MR_DSURF_MAX_POLY];
    uint8_t tri[MR_DSURF_MAX_TRIS][3];
    uint8_t half[MR_DSURF_MAX_TRIS]; /* which cell half each triangle lies in */
} mr_dcell;

/* Sets up b from the corners' grid coordinates, positions and normals
 * (normals are normalised here; a zero normal stays zero) and the heights
 * at the corners from hs. */
void mr_dbase_init(mr_dbase *b, const double g[3][2], const float *p[3], const float *n[3],
                   const mr_dheights *hs);
/* Only the parts that depend on position and normal (a new pose). */
void mr_dbase_pose(mr_dbase *b, const float *p[3], const float *n[3]);

/* The grid cells whose closed squares T's bounding box touches: i in
 * [i0, i1], j in [j0, j1] (empty when i1 < i0). */
void mr_dbase_cells(const mr_dbase *b, int64_t *i0, int64_t *i1, int64_t *j0, int64_t *j1);

/* Whether cell (i, j) lies clearly inside T (it is then not cut). */
bool mr_dsurf_cell_inside(const mr_dbase *b, int64_t i, int64_t j);

/* The micro-triangles of T in cell (i, j), half 0, 1 or 2 (both): a cell
 * clearly inside T directly, a cell clearly crossed by one edge of T alone
 * as its square cut by that edge (most of the cut cells of small
 * triangles: the sphere of 960 faces at 50 texels per unit), others by
 * cutting T. The same triangles of the same vertex records as
 * mr_dsurf_cell_cut makes (tested). */
void mr_dsurf_cell(const mr_dbase *b, int64_t i, int64_t j, int half, mr_dcell *out);
/* Always by cutting (the definition; tests). */
void mr_dsurf_cell_cut(const mr_dbase *b, int64_t i, int64_t j, int half, mr_dcell *out);

/* The displaced position of a micro-vertex (the one evaluation). */
mr_vec3 mr_dsurf_vertex(const mr_dbase *b, const mr_dheights *hs, const mr_dvert *v);

/* Boundary fan of a flat triangle: at most max vertices (in order around
 * the boundary; triangle k is (0, k+1, k+2)); returns how many were
 * collected (0 when nothing). */
int mr_dsurf_flat_boundary(const mr_dbase *b, mr_dvert *out, int max);

/* Height at a grid point q by the cell-half rule (h of a BASE corner). */
double mr_dsurf_height_at(const mr_dheights *hs, double x, double y);

/* Barycentric coordinates (b1, b2) of grid point (x, y) in T. */
static inline void mr_dbase_bary(const mr_dbase *b, double x, double y, double *b1, double *b2)
{
    double dx = x - b->g[0][0], dy = y - b->g[0][1];
    *b1 = b->m[0] * dx + b->m[2] * dy;
    *b2 = b->m[1] * dx + b->m[3] * dy;
}

#endif
