/* inside.c - lattice points inside a triangle mesh by voting rays (inside.h). */
#include "kinds/springmass/inside.h"

#include <math.h>
#include <stdbool.h>
#include <stdlib.h>
#include <string.h>

#include "util/parallel.h"

/* Crossings of one axis family before they are sorted by line. */
#define MAX_CROSSINGS (1ull << 28)

typedef struct crossing {
    uint32_t line;
    int32_t sign;    /* +1: the triangle normal points along +axis, -1 against */
    double at;       /* coordinate along the axis */
    uint32_t tri;    /* for a total order (deterministic sort) */
} crossing;

static int crossing_cmp(const void *pa, const void *pb)
{
    const crossing *a = pa, *b = pb;
    if (a->line != b->line)
        return a->line < b->line ? -1 : 1;
    if (a->at != b->at)
        return a->at < b->at ? -1 : 1;
    if (a->tri != b->tri)
        return a->tri < b->tri ? -1 : 1;
    return (a->sign > b->sign) - (a->sign < b->sign);
}

/* Sign of the edge function of (a -> b) at p in the (u, v) projection,
 * evaluated in a canonical endpoint order so two triangles sharing an edge
 * get exactly opposite values; zero is resolved by perturbing p by
 * (eps, eps^2), the same for every triangle, so a line through a shared
 * edge or vertex crosses a watertight surface exactly once. */
static int edge_sign(const double a[2], const double b[2], double pu, double pv, double *val)
{
    bool swap = a[0] > b[0] || (a[0] == b[0] && a[1] > b[1]);
    if (swap) {
        const double *t = a;
        a = b;
        b = t;
    }
    double du = b[0] - a[0], dv = b[1] - a[1];
    double e = du * (pv - a[1]) - dv * (pu - a[0]);
    int s = e > 0 ? 1 : e < 0 ? -1 : 0;
    if (s == 0)
        s = dv != 0 ? (dv > 0 ? -1 : 1) : (du > 0 ? 1 : du < 0 ? -1 : 0);
    *val = swap ? -e : e;
    return swap ? -s : s;
}

typedef struct crossing_list {
    crossing *items;
    size_t count, cap;
} crossing_list;

static int push_crossing(crossing_list *l, crossing c, mr_error *err)
{
    if (l->count == l->cap) {
        if (l->cap >= MAX_CROSSINGS)
            return mr_error_set(err, MR_ERR_LIMIT,
                                "the node grid's inside test: more than %llu ray crossings (spacing "
                                "too small for the mesh)",
                                (unsigned long long)MAX_CROSSINGS);
        size_t cap = l->cap ? l->cap * 2 : 4096;
        crossing *n = realloc(l->items, cap * sizeof *n);
        if (!n)
            return mr_error_set(err, MR_ERR_NOMEM, "out of memory for ray crossings");
        l->items = n;
        l->cap = cap;
    }
    l->items[l->count++] = c;
    return MR_OK;
}

/* Every crossing of the lines along axis a with the mesh, sorted. */
static int axis_crossings(const double *pos, const uint32_t *tris, uint32_t tri_count,
                          const sm_lattice *lat, int a, crossing_list *out, mr_error *err)
{
    int b = (a + 1) % 3, c = (a + 2) % 3;
    const double h = lat->h;
    const uint32_t nb = lat->n[b], nc = lat->n[c];
    for (uint32_t t = 0; t < tri_count; t++) {
        const double *v[3];
        double uv[3][2];
        for (int q = 0; q < 3; q++) {
            v[q] = pos + (size_t)tris[(size_t)t * 3 + q] * 3;
            /* lattice units in the projection plane */
            uv[q][0] = (v[q][b] - lat->origin[b]) / h;
            uv[q][1] = (v[q][c] - lat->origin[c]) / h;
        }
        double umin = fmin(uv[0][0], fmin(uv[1][0], uv[2][0])), umax = fmax(uv[0][0], fmax(uv[1][0], uv[2][0]));
        double vmin = fmin(uv[0][1], fmin(uv[1][1], uv[2][1])), vmax = fmax(uv[0][1], fmax(uv[1][1], uv[2][1]));
        if (!(umax >= 0 && vmax >= 0 && umin <= nb - 1 && vmin <= nc - 1))
            continue;
        double u0 = fmax(0, ceil(umin)), u1 = fmin(nb - 1, floor(umax));
        double w0 = fmax(0, ceil(vmin)), w1 = fmin(nc - 1, floor(vmax));
        for (double pv = w0; pv <= w1; pv++)
            for (double pu = u0; pu <= u1; pu++) {
                double e0, e1, e2;
                int s0 = edge_sign(uv[1], uv[2], pu, pv, &e0);
                int s1 = edge_sign(uv[2], uv[0], pu, pv, &e1);
                int s2 = edge_sign(uv[0], uv[1], pu, pv, &e2);
                if (s0 == 0 || s0 != s1 || s1 != s2)
                    continue;
                double sum = e0 + e1 + e2, at;
                if (sum != 0 && isfinite(sum))
                    at = (e0 * v[0][a] + e1 * v[1][a] + e2 * v[2][a]) / sum;
                else
                    at = (v[0][a] + v[1][a] + v[2][a]) / 3.0;
                crossing cr = {(uint32_t)pu + nb * (uint32_t)pv, s0, at, t};
                int rc = push_crossing(out, cr, err);
                if (rc < 0)
                    return rc;
            }
    }
    if (out->count)
        qsort(out->items, out->count, sizeof *out->items, crossing_cmp);
    return MR_OK;
}

/* Index of lattice point with coordinate `along` on axis a on line `line`. */
static size_t point_index(const sm_lattice *lat, int a, uint32_t line, uint32_t along)
{
    int b = (a + 1) % 3;
    uint32_t ijk[3];
    ijk[a] = along;
    ijk[b] = line % lat->n[b];
    ijk[(a + 2) % 3] = line / lat->n[b];
    return ijk[0] + (size_t)lat->n[0] * (ijk[1] + (size_t)lat->n[1] * ijk[2]);
}

/* Votes of the lines along axis a: votes_in / votes_out per point. */
static void axis_votes(const sm_lattice *lat, int a, const crossing_list *cl, uint8_t *votes_in,
                       uint8_t *votes_out, sm_inside_info *info)
{
    int b = (a + 1) % 3, c = (a + 2) % 3;
    size_t lines = (size_t)lat->n[b] * lat->n[c];
    info->lines += lines;
    size_t k = 0;
    for (size_t line = 0; line < lines; line++) {
        size_t first = k;
        while (k < cl->count && cl->items[k].line == line)
            k++;
        size_t count = k - first;
        long total = 0;
        for (size_t q = first; q < k; q++)
            total += cl->items[q].sign;
        bool winding = total == 0, parity = !winding && count % 2 == 0;
        if (!winding && !parity) {
            info->abstained++;
            continue;
        }
        /* walk the points of the line, consuming crossings before each */
        size_t q = first;
        long wind = 0, crossed = 0;
        for (uint32_t p = 0; p < lat->n[a]; p++) {
            double at = lat->origin[a] + lat->h * p;
            while (q < k && cl->items[q].at < at) {
                wind -= cl->items[q].sign; /* entering (normal against the ray) counts +1 */
                crossed++;
                q++;
            }
            bool in = winding ? wind != 0 : (crossed & 1) != 0;
            size_t idx = point_index(lat, a, (uint32_t)line, p);
            if (in)
                votes_in[idx]++;
            else
                votes_out[idx]++;
        }
    }
}

double sm_winding_number(const double *pos, const uint32_t *tris, uint32_t tri_count, const double p[3])
{
    double sum = 0;
    for (uint32_t t = 0; t < tri_count; t++) {
        double a[3], b[3], c[3];
        const double *va = pos + (size_t)tris[(size_t)t * 3] * 3, *vb = pos + (size_t)tris[(size_t)t * 3 + 1] * 3,
                     *vc = pos + (size_t)tris[(size_t)t * 3 + 2] * 3;
        for (int d = 0; d < 3; d++) {
            a[d] = va[d] - p[d];
            b[d] = vb[d] - p[d];
            c[d] = vc[d] - p[d];
        }
        double la = sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
        double lb = sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2]);
        double lc = sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
        double det = a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0]) +
                     a[2] * (b[0] * c[1] - b[1] * c[0]);
        double ab = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        double ac = a[0] * c[0] + a[1] * c[1] + a[2] * c[2];
        double bc = b[0] * c[0] + b[1] * c[1] + b[2] * c[2];
        double den = la * lb * lc + ab * lc + ac * lb + bc * la;
        /* Van Oosterom and Strackee: the solid angle is 2 atan2(det, den) */
        sum += 2.0 * atan2(det, den);
    }
    return sum / (4.0 * M_PI);
}

typedef struct winding_job {
    const double *pos;
    const uint32_t *tris;
    uint32_t tri_count;
    const sm_lattice *lat;
    const size_t *points;
    uint8_t *inside;
} winding_job;

static void winding_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    winding_job *j = ctx;
    const sm_lattice *lat = j->lat;
    for (size_t q = begin; q < end; q++) {
        size_t idx = j->points[q];
        size_t i = idx % lat->n[0], r = idx / lat->n[0];
        size_t jj = r % lat->n[1], kk = r / lat->n[1];
        double p[3] = {lat->origin[0] + lat->h * (double)i, lat->origin[1] + lat->h * (double)jj,
                       lat->origin[2] + lat->h * (double)kk};
        double w = sm_winding_number(j->pos, j->tris, j->tri_count, p);
        j->inside[idx] = fabs(w) >= 0.5;
    }
}

int sm_inside_lattice(const double *positions, const uint32_t *triangles, uint32_t triangle_count,
                      const sm_lattice *lat, unsigned threads, uint8_t *inside,
                      sm_inside_info *info, mr_error *err)
{
    sm_inside_info local = {0};
    size_t points = (size_t)lat->n[0] * lat->n[1] * lat->n[2];
    uint8_t *vin = calloc(points ? points : 1, 1), *vout = calloc(points ? points : 1, 1);
    size_t *ties = NULL;
    crossing_list cl = {0};
    int rc = MR_OK;
    if (!vin || !vout) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory for %zu grid points", points);
        goto done;
    }
    for (int a = 0; a < 3; a++) {
        cl.count = 0;
        if ((rc = axis_crossings(positions, triangles, triangle_count, lat, a, &cl, err)) < 0)
            goto done;
        axis_votes(lat, a, &cl, vin, vout, &local);
    }
    size_t tie_count = 0;
    for (size_t i = 0; i < points; i++) {
        inside[i] = vin[i] > vout[i];
        tie_count += vin[i] == vout[i];
    }
    if (tie_count) {
        if ((unsigned long long)tie_count * triangle_count > SM_WINDING_BUDGET) {
            rc = mr_error_set(err, MR_ERR_LIMIT,
                              "the mesh is too open to fill with nodes: rays through %zu grid points "
                              "passed holes, and their winding numbers would take %llu point-triangle "
                              "solid angles (at most %llu)",
                              tie_count, (unsigned long long)tie_count * triangle_count,
                              SM_WINDING_BUDGET);
            goto done;
        }
        if (!(ties = malloc(tie_count * sizeof *ties))) {
            rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory for %zu grid points", tie_count);
            goto done;
        }
        size_t n = 0;
        for (size_t i = 0; i < points; i++)
            if (vin[i] == vout[i])
                ties[n++] = i;
        winding_job wj = {positions, triangles, triangle_count, lat, ties, inside};
        mr_parallel_for(threads, tie_count, 16, winding_range, &wj);
        local.winding = tie_count;
    }
    for (size_t i = 0; i < points; i++)
        local.inside += inside[i];
done:
    free(cl.items);
    free(vin);
    free(vout);
    free(ties);
    if (info)
        *info = local;
    return rc;
}
