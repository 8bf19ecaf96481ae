/*
 * grid_fixture.h - the triangles of a grid of vertices, the tests' flat and
 * bumpy meshes, and a bumpy height field as an asset. Header-only; include
 * after microray.h.
 */
#ifndef MR_TEST_GRID_FIXTURE_H
#define MR_TEST_GRID_FIXTURE_H

#include <math.h>
#include <stdint.h>
#include <stdlib.h>

/* The triangles of a grid of nx x ny vertices numbered row by row (vertex
 * y * nx + x) into idx, which holds 6 (nx - 1) (ny - 1) entries: two a
 * quad, (a, b, d) and (a, d, c), with a its corner of least x and y, b the
 * next along x, c the next along y and d across. Returns the triangle
 * count. */
static inline uint32_t grid_triangles(uint32_t nx, uint32_t ny, uint32_t *idx)
{
    uint32_t t = 0;
    for (uint32_t y = 0; y + 1 < ny; y++)
        for (uint32_t x = 0; x + 1 < nx; x++) {
            const uint32_t a = y * nx + x, b = a + 1, c = a + nx, d = c + 1;
            const uint32_t q[6] = {a, b, d, a, d, c};
            for (int k = 0; k < 6; k++)
                idx[3 * t + k] = q[k];
            t += 2;
        }
    return t;
}

/* A height field of n x n vertices over [-1, 1]^2: z = amp sin(fx x)
 * cos(fy y), as the asset "field" (grid_triangles), or NULL with err set. */
static inline mr_asset *grid_field(unsigned n, float amp, float fx, float fy, mr_error *err)
{
    float *p = malloc((size_t)n * n * 3 * sizeof(float));
    uint32_t *idx = malloc((size_t)(n - 1) * (n - 1) * 6 * sizeof(uint32_t));
    mr_asset *asset = NULL;
    if (!p || !idx) {
        mr_error_set(err, MR_ERR_NOMEM, "grid_field: out of memory");
    } else {
        for (unsigned y = 0; y < n; y++)
            for (unsigned x = 0; x < n; x++) {
                const float u = (float)x / (float)(n - 1) * 2 - 1, v = (float)y / (float)(n - 1) * 2 - 1;
                float *q = p + ((size_t)y * n + x) * 3;
                q[0] = u, q[1] = v, q[2] = amp * sinf(fx * u) * cosf(fy * v);
            }
        if (mr_asset_from_mesh("field", p, NULL, n * n, idx, grid_triangles(n, n, idx), &asset, err) < 0)
            asset = NULL;
    }
    free(p);
    free(idx);
    return asset;
}

#endif
