/* grid.c - the node grid filling a mesh (grid.h). */
#include "kinds/springmass/grid.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

const int8_t sm_neighbour_dir[18][3] = {
    {1, 0, 0},  {-1, 0, 0}, {0, 1, 0},  {0, -1, 0}, {0, 0, 1},  {0, 0, -1},
    {1, 1, 0},  {-1, -1, 0}, {1, -1, 0}, {-1, 1, 0},
    {1, 0, 1},  {-1, 0, -1}, {1, 0, -1}, {-1, 0, 1},
    {0, 1, 1},  {0, -1, -1}, {0, 1, -1}, {0, -1, 1},
};

void sm_grid_free(sm_grid *g)
{
    if (!g)
        return;
    free(g->active);
    free(g->flags);
    memset(g, 0, sizeof *g);
}

/* The lattice for spacing h around the box lo..hi; false if beyond max_cells. */
static bool lattice_for(const double lo[3], const double hi[3], double h, size_t max_cells,
                        sm_lattice *lat)
{
    double cells = 1;
    for (int a = 0; a < 3; a++) {
        double span = (hi[a] - lo[a]) / h;
        if (!(span < 1e7))
            return false;
        uint32_t m = (uint32_t)ceil(span) + 1;
        if (m < 3)
            m = 3; /* a box thinner than 2 h: its middle is a lattice point */
        lat->n[a] = m + 2 * SM_GRID_PAD;
        lat->origin[a] = 0.5 * (lo[a] + hi[a]) - (0.5 * (m - 1) + SM_GRID_PAD) * h;
        cells *= lat->n[a];
    }
    lat->h = h;
    return cells <= (double)max_cells;
}

static int classify(const double *pos, const uint32_t *tris, uint32_t tri_count, const sm_lattice *lat,
                    unsigned threads, sm_grid *g, mr_error *err)
{
    sm_grid_free(g);
    memcpy(g->n, lat->n, sizeof g->n);
    memcpy(g->origin, lat->origin, sizeof g->origin);
    g->h = lat->h;
    g->cells = (size_t)lat->n[0] * lat->n[1] * lat->n[2];
    g->active = calloc(g->cells, 1);
    g->flags = calloc(g->cells, 1);
    if (!g->active || !g->flags)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory for a grid of %zu cells", g->cells);
    int rc = sm_inside_lattice(pos, tris, tri_count, lat, threads, g->active, &g->inside, err);
    if (rc < 0)
        return rc;
    g->nodes = g->inside.inside;
    return MR_OK;
}

/* Drops the nodes of components (linked by springs: 18-neighbours) that
 * have fewer than SM_GRID_MIN_PART nodes and less than 1 % of all: bits
 * of a thin part (a tail, a horn) the lattice caught without the part
 * around them, which would float free of the body. */
static int drop_specks(sm_grid *g, mr_error *err)
{
    uint32_t *label = calloc(g->cells, sizeof *label);
    size_t *queue = malloc((g->nodes + 1) * sizeof *queue), *sizes = NULL;
    size_t parts = 0, cap = 0;
    int rc = MR_OK;
    if (!label || !queue) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory for %zu nodes", g->nodes);
        goto done;
    }
    for (size_t c = 0; c < g->cells; c++) {
        if (!g->active[c] || label[c])
            continue;
        if (parts == cap) {
            cap = cap ? cap * 2 : 64;
            size_t *n = realloc(sizes, cap * sizeof *n);
            if (!n) {
                rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory for %zu nodes", g->nodes);
                goto done;
            }
            sizes = n;
        }
        uint32_t id = (uint32_t)++parts;
        size_t head = 0, tail = 0;
        label[c] = id;
        queue[tail++] = c;
        while (head < tail) {
            size_t q = queue[head++];
            for (int d = 0; d < 18; d++) {
                size_t n = (size_t)((ptrdiff_t)q + sm_grid_offset(g, sm_neighbour_dir[d]));
                if (g->active[n] && !label[n]) {
                    label[n] = id;
                    queue[tail++] = n;
                }
            }
        }
        sizes[id - 1] = tail;
    }
    size_t keep_at = (size_t)fmax(1, fmin(SM_GRID_MIN_PART, 0.01 * (double)g->nodes));
    for (size_t c = 0; c < g->cells; c++)
        if (g->active[c] && sizes[label[c] - 1] < keep_at) {
            g->active[c] = 0;
            g->nodes--;
            g->dropped++;
        }
done:
    free(label);
    free(queue);
    free(sizes);
    return rc;
}

static void flag_nodes(sm_grid *g)
{
    g->surface_nodes = g->thin_nodes = 0;
    for (uint32_t k = 1; k + 1 < g->n[2]; k++)
        for (uint32_t j = 1; j + 1 < g->n[1]; j++)
            for (uint32_t i = 1; i + 1 < g->n[0]; i++) {
                size_t c = sm_grid_cell(g, i, j, k);
                if (!g->active[c])
                    continue;
                uint8_t f = 0;
                for (int a = 0; a < 3; a++) {
                    ptrdiff_t o = sm_grid_offset(g, sm_neighbour_dir[2 * a]);
                    bool plus = g->active[c + o], minus = g->active[c - o];
                    if (!plus || !minus)
                        f |= SM_NODE_SURFACE;
                    if (!plus && !minus)
                        f |= SM_NODE_THIN;
                }
                g->flags[c] = f;
                g->surface_nodes += (f & SM_NODE_SURFACE) != 0;
                g->thin_nodes += (f & SM_NODE_THIN) != 0;
            }
}

int sm_grid_build(const double *pos, uint32_t vertex_count, const uint32_t *tris, uint32_t tri_count,
                  double spacing, uint32_t target_nodes, size_t max_cells, unsigned threads,
                  sm_grid *out, mr_error *err)
{
    memset(out, 0, sizeof *out);
    if (max_cells == 0 || max_cells > SM_GRID_MAX_CELLS)
        max_cells = SM_GRID_MAX_CELLS;
    if (vertex_count == 0 || tri_count == 0)
        return mr_error_set(err, MR_ERR_INVALID, "the mesh has no triangles to fill with nodes");
    double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (uint32_t v = 0; v < vertex_count; v++)
        for (int a = 0; a < 3; a++) {
            lo[a] = fmin(lo[a], pos[(size_t)v * 3 + a]);
            hi[a] = fmax(hi[a], pos[(size_t)v * 3 + a]);
        }
    double ext[3] = {hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]};
    double diag = sqrt(ext[0] * ext[0] + ext[1] * ext[1] + ext[2] * ext[2]);
    if (!(diag > 0) || !isfinite(diag))
        return mr_error_set(err, MR_ERR_INVALID, "the mesh has no extent to fill with nodes");
    sm_lattice lat;
    int rc;
    if (spacing > 0) {
        if (!lattice_for(lo, hi, spacing, max_cells, &lat))
            return mr_error_set(err, MR_ERR_LIMIT,
                                "a spacing of %g makes a grid of more than %zu cells around a mesh "
                                "of %g x %g x %g",
                                spacing, max_cells, ext[0], ext[1], ext[2]);
        if ((rc = classify(pos, tris, tri_count, &lat, threads, out, err)) < 0)
            goto fail;
    } else {
        /* start from the box volume (thin boxes: their largest two sides) */
        double vol = fmax(ext[0], diag * 1e-3) * fmax(ext[1], diag * 1e-3) * fmax(ext[2], diag * 1e-3);
        double h = cbrt(0.5 * vol / target_nodes);
        for (int round = 0; round < 6; round++) {
            if (!lattice_for(lo, hi, h, max_cells, &lat))
                return mr_error_set(err, MR_ERR_LIMIT,
                                    "%u nodes need a grid of more than %zu cells around a mesh of "
                                    "%g x %g x %g",
                                    target_nodes, max_cells, ext[0], ext[1], ext[2]);
            if ((rc = classify(pos, tris, tri_count, &lat, threads, out, err)) < 0)
                goto fail;
            double ratio = (double)(out->nodes ? out->nodes : 1) / target_nodes;
            if (fabs(ratio - 1) <= 0.05)
                break;
            if (out->nodes == 0)
                ratio = 1.0 / 8; /* nothing inside yet: halve the spacing */
            h *= cbrt(ratio);
        }
    }
    if (out->nodes && (rc = drop_specks(out, err)) < 0)
        goto fail;
    if (out->nodes == 0) {
        rc = mr_error_set(err, MR_ERR_INVALID,
                          "no grid node lies inside the mesh at a spacing of %g (is it closed? "
                          "thinner than the spacing?)",
                          out->h);
        goto fail;
    }
    if (out->nodes > SM_GRID_MAX_NODES) {
        rc = mr_error_set(err, MR_ERR_LIMIT, "%zu nodes, more than the %u an object may have",
                          out->nodes, SM_GRID_MAX_NODES);
        goto fail;
    }
    flag_nodes(out);
    return MR_OK;
fail:
    sm_grid_free(out);
    return rc;
}
