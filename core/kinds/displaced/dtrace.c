/* dtrace.c - bounds, D-BVH traversal, local intersection and ray marching (dtrace.h). */
#include "kinds/displaced/dtrace.h"

#include <float.h>
#include <math.h>
#include <stdatomic.h>
#include <string.h>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif
#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#endif

#include "kinds/displaced/tiling.h"
#include "math/affine_arith.h"
#include "util/simd.h"
#include "util/thread_block.h"

/* NaN-free minimum and maximum: libm's fmin/fmax are calls (they must
 * handle NaN), and these run a few dozen times per node. */
static inline double dmin(double a, double b) { return a < b ? a : b; }
static inline double dmax(double a, double b) { return a > b ? a : b; }

/* The box pad: this fraction of a bound on every magnitude a micro-vertex
 * is computed from (dtrace.h). */
#define PAD_REL 0x1p-36
/* A flat triangle's boundary fan has at most this many points. */
#define FLAT_MAX 1024

mr_dray mr_dray_setup(mr_vec3 o, mr_vec3 d)
{
    /* written field by field: arrays of the converted components copied
     * whole were 16-byte loads of 8-byte stores, which stall */
    mr_dray r;
    r.o[0] = o.x, r.o[1] = o.y, r.o[2] = o.z;
    r.d[0] = d.x, r.d[1] = d.y, r.d[2] = d.z;
    for (int a = 0; a < 3; a++) {
        r.par[a] = r.d[a] == 0;
        r.inv[a] = r.d[a] != 0 ? 1.0 / r.d[a] : 0.0;
    }
    r.wt = mr_wt_ray_setup(o, d);
    return r;
}

static inline double gmax_of(const mr_dbase *b)
{
    double m = 0;
    for (int k = 0; k < 3; k++)
        m = fmax(m, fmax(fabs(b->g[k][0]), fabs(b->g[k][1])));
    return m;
}

static void tri_gbox(const mr_dbase *b, double *x0, double *x1, double *y0, double *y1);

/* Distance from the origin to triangle (a, b, c) (its closest point,
 * Ericson, Real-Time Collision Detection 5.1.5), in double. */
static double origin_distance(const double *a, const double *b, const double *c)
{
    double ab[3], ac[3], ap[3];
    for (int k = 0; k < 3; k++)
        ab[k] = b[k] - a[k], ac[k] = c[k] - a[k], ap[k] = -a[k];
    double d1 = mr_dot3d(ab, ap), d2 = mr_dot3d(ac, ap), p[3];
    if (d1 <= 0 && d2 <= 0)
        return sqrt(mr_dot3d(a, a));
    double bp[3] = {-b[0], -b[1], -b[2]}, cp[3] = {-c[0], -c[1], -c[2]};
    double d3 = mr_dot3d(ab, bp), d4 = mr_dot3d(ac, bp);
    if (d3 >= 0 && d4 <= d3)
        return sqrt(mr_dot3d(b, b));
    double vc = d1 * d4 - d3 * d2;
    if (vc <= 0 && d1 >= 0 && d3 <= 0) {
        double v = d1 / (d1 - d3);
        for (int k = 0; k < 3; k++)
            p[k] = a[k] + v * ab[k];
        return sqrt(mr_dot3d(p, p));
    }
    double d5 = mr_dot3d(ab, cp), d6 = mr_dot3d(ac, cp);
    if (d6 >= 0 && d5 <= d6)
        return sqrt(mr_dot3d(c, c));
    double vb = d5 * d2 - d1 * d6;
    if (vb <= 0 && d2 >= 0 && d6 <= 0) {
        double w = d2 / (d2 - d6);
        for (int k = 0; k < 3; k++)
            p[k] = a[k] + w * ac[k];
        return sqrt(mr_dot3d(p, p));
    }
    double va = d3 * d6 - d5 * d4;
    if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) {
        double w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        for (int k = 0; k < 3; k++)
            p[k] = b[k] + w * (c[k] - b[k]);
        return sqrt(mr_dot3d(p, p));
    }
    double den = 1 / (va + vb + vc), v = vb * den, w = vc * den;
    for (int k = 0; k < 3; k++)
        p[k] = a[k] + ab[k] * v + ac[k] * w;
    return sqrt(mr_dot3d(p, p));
}

/* Bounds of u . N / |N| over T for a linear functional u, from the least
 * and greatest of u . n_k at its corner normals (lo, hi): u . N lies
 * between them over the hull of the corner normals, and |N| in [dist, 1]
 * (dist: the hull's distance from the origin, local_frame); a hull that
 * reaches near the origin gets the bound any unit vector has, cap (u's
 * 1-norm, or 1 for a unit u). Widened by slack, within [-cap, cap]. */
static void unit_normal_bounds(double lo, double hi, double dist, double slack, double cap, double out[2])
{
    if (dist > 1e-6) {
        lo = lo >= 0 ? lo - slack : lo / dist - slack;
        hi = hi >= 0 ? hi / dist + slack : hi + slack;
    } else {
        lo = -cap, hi = cap;
    }
    out[0] = dmax(lo, -cap);
    out[1] = dmin(hi, cap);
}

/* The local frame (dtrace.h): x = P0 + Px (qx - g0x) + Py (qy - g0y) + z f
 * with f T's unit face normal; a micro-vertex of grid point q and height h
 * lies at (q + h (a, b), h c) where (a, b, c) = inv N(q) / |N(q)|. Bounds
 * of (a, b, c) over T: inv's rows are linear, so over the convex hull of
 * the corner normals they lie between their values at the corners, and
 * dividing by |N| in [dmin, 1] (dmin: the hull's distance from the origin)
 * gives the unit normal's; a hull that reaches near the origin (opposing
 * normals) gets the bound any unit vector has, which also holds the zero
 * displacement of a vanishing normal. */
static void local_frame(mr_dgrad *gr, const mr_dbase *b, double hm)
{
    double f[3] = {gr->Px[1] * gr->Py[2] - gr->Px[2] * gr->Py[1],
                   gr->Px[2] * gr->Py[0] - gr->Px[0] * gr->Py[2],
                   gr->Px[0] * gr->Py[1] - gr->Px[1] * gr->Py[0]};
    double fl = sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]);
    double px = sqrt(gr->Px[0] * gr->Px[0] + gr->Px[1] * gr->Px[1] + gr->Px[2] * gr->Px[2]);
    double py = sqrt(gr->Py[0] * gr->Py[0] + gr->Py[1] * gr->Py[1] + gr->Py[2] * gr->Py[2]);
    /* a well-shaped map only: T with area in space as well as in the grid */
    if (!(fl > 1e-6 * px * py) || !isfinite(fl))
        return;
    double M[3][3];
    for (int c = 0; c < 3; c++)
        M[c][0] = gr->Px[c], M[c][1] = gr->Py[c], M[c][2] = f[c] / fl;
    double C[3][3];
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++) {
            int r1 = (r + 1) % 3, r2 = (r + 2) % 3, c1 = (c + 1) % 3, c2 = (c + 2) % 3;
            C[r][c] = M[r1][c1] * M[r2][c2] - M[r1][c2] * M[r2][c1];
        }
    double det = M[0][0] * C[0][0] + M[0][1] * C[0][1] + M[0][2] * C[0][2];
    if (!isfinite(det) || det == 0)
        return;
    /* a micro-vertex is off its exact value by a float rounding of its
     * coordinates (2^-24 of at most the pad's basis) plus the double work
     * (far less): 2^-22 of the basis, through inv */
    double basis = gr->pad / PAD_REL, err = 0x1p-22 * basis, dist;
    dist = origin_distance(b->n[0], b->n[1], b->n[2]) * (1 - 1e-12);
    double rows[3];
    for (int r = 0; r < 3; r++) {
        double row = 0, lo = INFINITY, hi = -INFINITY;
        for (int c = 0; c < 3; c++) {
            gr->inv[r][c] = C[c][r] / det;
            row += fabs(gr->inv[r][c]);
        }
        for (int k = 0; k < 3; k++) {
            double v = gr->inv[r][0] * b->n[k][0] + gr->inv[r][1] * b->n[k][1] +
                       gr->inv[r][2] * b->n[k][2];
            lo = dmin(lo, v), hi = dmax(hi, v);
        }
        rows[r] = row;
        unit_normal_bounds(lo, hi, dist, 1e-12 * row, row, gr->nb[r]);
        gr->lpad[r] = row * err + 1e-9 * (r < 2 ? 1 + gmax_of(b) : 1 + hm);
    }
    gr->local = isfinite(gr->lpad[0]) && isfinite(gr->lpad[1]) && isfinite(gr->lpad[2]) &&
                isfinite(gr->nb[0][0] + gr->nb[0][1] + gr->nb[1][0] + gr->nb[1][1] +
                         gr->nb[2][0] + gr->nb[2][1]);
    /* a node's own normal bounds (rect_normals): worth it where the
     * normal's turn over T moves the displaced surface sideways by a
     * quarter of a cell or more (a constant normal: not at all; coarse
     * cells: seldom, and each box then costs 4 % more) */
    double sideways = hm * dmax(gr->nb[0][1] - gr->nb[0][0], gr->nb[1][1] - gr->nb[1][0]);
    gr->nrect = dist > 1e-6 && !gr->constant_normal && sideways > 0.25;
    gr->g0[0] = b->g[0][0], gr->g0[1] = b->g[0][1];
    gr->inv_ndist = dist > 1e-6 ? 1 / dist : 0;
    double dxm = dmax(fabs(gr->gx0 - gr->g0[0]), fabs(gr->gx1 - gr->g0[0]));
    double dym = dmax(fabs(gr->gy0 - gr->g0[1]), fabs(gr->gy1 - gr->g0[1]));
    for (int r = 0; r < 2; r++) {
        gr->nl[r][0] = gr->inv[r][0] * gr->N0[0] + gr->inv[r][1] * gr->N0[1] + gr->inv[r][2] * gr->N0[2];
        gr->nl[r][1] = gr->inv[r][0] * gr->Nx[0] + gr->inv[r][1] * gr->Nx[1] + gr->inv[r][2] * gr->Nx[2];
        gr->nl[r][2] = gr->inv[r][0] * gr->Ny[0] + gr->inv[r][1] * gr->Ny[1] + gr->inv[r][2] * gr->Ny[2];
        gr->nslack[r] = 1e-12 * (rows[r] + fabs(gr->nl[r][0]) + 2 * fabs(gr->nl[r][1]) * dxm +
                                 2 * fabs(gr->nl[r][2]) * dym);
        gr->nrect = gr->nrect && isfinite(gr->nl[r][0] + gr->nl[r][1] + gr->nl[r][2] + gr->nslack[r]);
    }
}

static void footprint_frame(mr_dgrad *gr, const mr_dbase *b);

/* mr_dgrad's oriented box (T without a local frame). A point of T's
 * surface is P(q) + h N(q) / |N(q)|: P(q) in the triangle of T's corners,
 * h in [hlo, hhi], and along a unit axis a the unit normal's component
 * within unit_normal_bounds, as local_frame bounds it. Padded by a micro-vertex's float rounding
 * (local_frame's 2^-22 of the basis) and 1e-9 of the coordinates for the
 * projections' own. No box (ob false) when T has no direction to take. */
static void oriented_box(mr_dgrad *gr, const mr_dbase *b, double hm)
{
    double e[3][3], len[3];
    for (int k = 0; k < 3; k++) {
        for (int c = 0; c < 3; c++)
            e[k][c] = b->p[(k + 1) % 3][c] - b->p[k][c];
        len[k] = sqrt(mr_dot3d(e[k], e[k]));
    }
    const int lk = len[0] >= len[1] && len[0] >= len[2] ? 0 : len[1] >= len[2] ? 1 : 2;
    double n[3] = {b->n[0][0] + b->n[1][0] + b->n[2][0], b->n[0][1] + b->n[1][1] + b->n[2][1],
                   b->n[0][2] + b->n[1][2] + b->n[2][2]};
    if (!(len[lk] > 0) || !isfinite(len[lk]))
        return;
    double *u = gr->ob_axis[0], *v = gr->ob_axis[1], *w = gr->ob_axis[2];
    for (int c = 0; c < 3; c++)
        u[c] = e[lk][c] / len[lk];
    const double nu = mr_dot3d(n, u);
    for (int c = 0; c < 3; c++)
        v[c] = n[c] - nu * u[c];
    const double vl = sqrt(mr_dot3d(v, v));
    if (!(vl > 1e-6 * sqrt(mr_dot3d(n, n))) || !isfinite(vl))
        return; /* the normal along the edge, or none */
    for (int c = 0; c < 3; c++)
        v[c] /= vl;
    w[0] = u[1] * v[2] - u[2] * v[1];
    w[1] = u[2] * v[0] - u[0] * v[2];
    w[2] = u[0] * v[1] - u[1] * v[0];
    const double dist = origin_distance(b->n[0], b->n[1], b->n[2]) * (1 - 1e-12);
    double pm = 0;
    for (int k = 0; k < 3; k++)
        for (int c = 0; c < 3; c++)
            pm = dmax(pm, fabs(b->p[k][c]));
    const double pad = 0x1p-22 * (gr->pad / PAD_REL) + 1e-9 * (pm + hm);
    for (int a = 0; a < 3; a++) {
        const double *x = gr->ob_axis[a];
        double plo = INFINITY, phi = -INFINITY, nlo = INFINITY, nhi = -INFINITY;
        for (int k = 0; k < 3; k++) {
            plo = dmin(plo, mr_dot3d(x, b->p[k])), phi = dmax(phi, mr_dot3d(x, b->p[k]));
            nlo = dmin(nlo, mr_dot3d(x, b->n[k])), nhi = dmax(nhi, mr_dot3d(x, b->n[k]));
        }
        double nb[2];
        unit_normal_bounds(nlo, nhi, dist, 1e-12, 1, nb);
        const double h[4] = {gr->hlo * nb[0], gr->hlo * nb[1], gr->hhi * nb[0], gr->hhi * nb[1]};
        gr->ob_lo[a] = plo + dmin(dmin(h[0], h[1]), dmin(h[2], h[3])) - pad;
        gr->ob_hi[a] = phi + dmax(dmax(h[0], h[1]), dmax(h[2], h[3])) + pad;
        if (!isfinite(gr->ob_lo[a]) || !isfinite(gr->ob_hi[a]))
            return;
    }
    gr->ob = true;
}

/* Whether ray r can meet T's oriented box at a t in [tmin, tmax]: the slab
 * test in the box's frame, its exit widened as slab widens it. */
static bool oriented_hit(const mr_dgrad *gr, const mr_dray *r, double tmin, double tmax)
{
    double t0 = tmin, t1 = tmax;
    for (int a = 0; a < 3; a++) {
        const double *x = gr->ob_axis[a];
        const double o = mr_dot3d(x, r->o), d = mr_dot3d(x, r->d);
        if (d == 0) {
            if (o < gr->ob_lo[a] || o > gr->ob_hi[a])
                return false;
            continue;
        }
        const double ta = (gr->ob_lo[a] - o) / d, tb = (gr->ob_hi[a] - o) / d;
        t0 = dmax(t0, dmin(ta, tb));
        t1 = dmin(t1, dmax(ta, tb) * (1 + 4 * DBL_EPSILON));
    }
    return t0 <= t1;
}

void mr_dgrad_init(mr_dgrad *gr, const mr_dbase *b, double hlo, double hhi)
{
    memset(gr, 0, sizeof *gr);
    gr->hlo = hlo;
    gr->hhi = hhi;
    double pm = 0, grad = 0;
    for (int c = 0; c < 3; c++) {
        double d1 = b->p[1][c] - b->p[0][c], d2 = b->p[2][c] - b->p[0][c];
        double e1 = b->n[1][c] - b->n[0][c], e2 = b->n[2][c] - b->n[0][c];
        gr->P0[c] = b->p[0][c];
        gr->N0[c] = b->n[0][c];
        if (!b->flat) {
            gr->Px[c] = b->m[0] * d1 + b->m[1] * d2;
            gr->Py[c] = b->m[2] * d1 + b->m[3] * d2;
            gr->Nx[c] = b->m[0] * e1 + b->m[1] * e2;
            gr->Ny[c] = b->m[2] * e1 + b->m[3] * e2;
        }
        for (int k = 0; k < 3; k++)
            pm = fmax(pm, fabs(b->p[k][c]));
        grad = fmax(grad, fabs(gr->Px[c]) + fabs(gr->Py[c]) + fabs(gr->Nx[c]) + fabs(gr->Ny[c]));
    }
    double hm = fmax(fabs(hlo), fabs(hhi));
    for (int k = 0; k < 3; k++)
        hm = fmax(hm, fabs(b->h[k]));
    gr->pad = PAD_REL * (pm + hm + (grad * (1 + hm)) * (gmax_of(b) + 1));
    gr->nxlen = sqrt(gr->Nx[0] * gr->Nx[0] + gr->Nx[1] * gr->Nx[1] + gr->Nx[2] * gr->Nx[2]);
    gr->nylen = sqrt(gr->Ny[0] * gr->Ny[0] + gr->Ny[1] * gr->Ny[1] + gr->Ny[2] * gr->Ny[2]);
    double n0 = sqrt(b->n[0][0] * b->n[0][0] + b->n[0][1] * b->n[0][1] + b->n[0][2] * b->n[0][2]);
    gr->constant_normal = n0 > 0.5 && !memcmp(b->n[0], b->n[1], sizeof b->n[0]) &&
                          !memcmp(b->n[0], b->n[2], sizeof b->n[0]);
    tri_gbox(b, &gr->gx0, &gr->gx1, &gr->gy0, &gr->gy1);
    gr->local = false;
    gr->ob = false;
    if (!b->flat)
        local_frame(gr, b, hm);
    if (gr->local)
        footprint_frame(gr, b);
    else if (!b->flat)
        oriented_box(gr, b, hm);
}

/* ---- boxes ----------------------------------------------------------------------- */

/* The box of S over the grid region X, Y (offsets from g0 as affine forms)
 * with heights [hlo, hhi]; dtrace.h says why it is conservative. */
static void box_of(const mr_dgrad *gr, mr_af X, mr_af Y, double hlo, double hhi, double lo[3],
                   double hi[3])
{
    mr_af P[3], N[3];
    for (int c = 0; c < 3; c++) {
        P[c] = mr_af_add(mr_af_add(mr_af_const(gr->P0[c]), mr_af_scale(X, gr->Px[c])),
                         mr_af_scale(Y, gr->Py[c]));
        N[c] = mr_af_add(mr_af_add(mr_af_const(gr->N0[c]), mr_af_scale(X, gr->Nx[c])),
                         mr_af_scale(Y, gr->Ny[c]));
    }
    mr_af len2 = mr_af_add(mr_af_add(mr_af_sqr(N[0]), mr_af_sqr(N[1])), mr_af_sqr(N[2]));
    mr_interval len = mr_interval_sqrt(mr_af_interval(len2)), inv;
    /* 2e-9: twice the length below which a micro-vertex is not displaced
     * (dsurf.c MIN_NORMAL), so no vertex the bound normalises is one the
     * evaluation left undisplaced */
    bool unit = len.lo > 2e-9 && mr_interval_recip(len, &inv);
    mr_af H = mr_af_from_interval((mr_interval){hlo, hhi});
    for (int c = 0; c < 3; c++) {
        mr_af nh;
        if (unit) {
            mr_af q = mr_af_mul(N[c], mr_af_from_interval(inv));
            mr_interval qi = mr_af_interval(q);
            nh = qi.lo >= -1 && qi.hi <= 1 ? q : mr_af_from_interval(mr_interval_clamp(qi, -1, 1));
        } else {
            nh = mr_af_from_interval((mr_interval){-1, 1});
        }
        mr_interval s = mr_af_interval(mr_af_add(P[c], mr_af_mul(H, nh)));
        lo[c] = s.lo - gr->pad;
        hi[c] = s.hi + gr->pad;
    }
}

static void to_float_box(const double lo[3], const double hi[3], float flo[3], float fhi[3])
{
    for (int c = 0; c < 3; c++) {
        flo[c] = mr_float_down(lo[c]);
        fhi[c] = mr_float_up(hi[c]);
    }
}

static void tri_gbox(const mr_dbase *b, double *x0, double *x1, double *y0, double *y1)
{
    double m = b->margin;
    *x0 = fmin(fmin(b->g[0][0], b->g[1][0]), b->g[2][0]) - m;
    *x1 = fmax(fmax(b->g[0][0], b->g[1][0]), b->g[2][0]) + m;
    *y0 = fmin(fmin(b->g[0][1], b->g[1][1]), b->g[2][1]) - m;
    *y1 = fmax(fmax(b->g[0][1], b->g[1][1]), b->g[2][1]) + m;
}

/* The traversal's node boxes: the same bound as box_of, written out for
 * speed in plain double arithmetic (P and N are affine on the rectangle, so
 * their centre-and-radius forms are exact but for rounding; the normal is
 * divided by the interval of its length; the height enters as an interval
 * product). Its few dozen roundings (each 2^-53 of a magnitude the pad's
 * basis bounds) are covered by the pad, 2^-36 of that basis. Tested to
 * contain box_of's rigorous result in tests/unit/test_displaced_trace.c. */
static bool rect_box_d(const mr_dbase *b, const mr_dgrad *gr, double x0, double x1, double y0,
                       double y1, double hlo, double hhi, double lo[3], double hi[3])
{
    x0 = dmax(x0, gr->gx0), x1 = dmin(x1, gr->gx1), y0 = dmax(y0, gr->gy0), y1 = dmin(y1, gr->gy1);
    if (x0 > x1 || y0 > y1)
        return false;
    double rx = 0.5 * (x1 - x0), ry = 0.5 * (y1 - y0);
    double dx = 0.5 * (x0 + x1) - b->g[0][0], dy = 0.5 * (y0 + y1) - b->g[0][1];
    double nlo[3], nhi[3];
    if (gr->constant_normal) {
        for (int c = 0; c < 3; c++)
            nlo[c] = nhi[c] = gr->N0[c];
    } else {
        double nc[3], nr[3], len2 = 0;
        for (int c = 0; c < 3; c++) {
            nc[c] = gr->N0[c] + gr->Nx[c] * dx + gr->Ny[c] * dy;
            nr[c] = fabs(gr->Nx[c]) * rx + fabs(gr->Ny[c]) * ry;
            len2 += nc[c] * nc[c];
        }
        double len = sqrt(len2), dev = gr->nxlen * rx + gr->nylen * ry;
        double llo = len - dev, lhi = len + dev;
        for (int c = 0; c < 3; c++) {
            if (llo > 2e-9) {
                double a = nc[c] - nr[c], z = nc[c] + nr[c];
                nlo[c] = dmax(-1.0, a / (a >= 0 ? lhi : llo));
                nhi[c] = dmin(1.0, z / (z >= 0 ? llo : lhi));
            } else {
                nlo[c] = -1, nhi[c] = 1;
            }
        }
    }
    for (int c = 0; c < 3; c++) {
        double pc = gr->P0[c] + gr->Px[c] * dx + gr->Py[c] * dy;
        double pr = fabs(gr->Px[c]) * rx + fabs(gr->Py[c]) * ry;
        double p0 = hlo * nlo[c], p1 = hlo * nhi[c], p2 = hhi * nlo[c], p3 = hhi * nhi[c];
        double mn = dmin(dmin(p0, p1), dmin(p2, p3)), mx = dmax(dmax(p0, p1), dmax(p2, p3));
        lo[c] = pc - pr + mn - gr->pad;
        hi[c] = pc + pr + mx + gr->pad;
    }
    return true;
}

bool mr_dtrace_rect_box(const mr_dbase *b, const mr_dgrad *gr, double x0, double x1, double y0,
                        double y1, double hlo, double hhi, float lo[3], float hi[3])
{
    double l[3], h[3];
    if (!rect_box_d(b, gr, x0, x1, y0, y1, hlo, hhi, l, h))
        return false;
    to_float_box(l, h, lo, hi);
    return true;
}

/* Box of the displaced micro-vertices of a flat triangle's boundary fan. */
static void flat_box(const mr_dbase *b, const mr_dheights *hs, const mr_dgrad *gr, double lo[3],
                     double hi[3])
{
    static _Thread_local mr_dvert pts[FLAT_MAX];
    int n = mr_dsurf_flat_boundary(b, pts, FLAT_MAX);
    for (int c = 0; c < 3; c++)
        lo[c] = INFINITY, hi[c] = -INFINITY;
    for (int k = 0; k < n; k++) {
        mr_vec3 v = mr_dsurf_vertex(b, hs, &pts[k]);
        double p[3] = {v.x, v.y, v.z};
        for (int c = 0; c < 3; c++)
            lo[c] = fmin(lo[c], p[c] - gr->pad), hi[c] = fmax(hi[c], p[c] + gr->pad);
    }
}

/* Embree tests our per-triangle boxes in float: they get a pad of 2^-20 of
 * the triangle's magnitude basis on top (16 float ulps: Embree's robust
 * box test rounds by a few), so a ray through a micro-vertex on a box's
 * face, or one whose hit on the next triangle is an ulp nearer than the
 * current one, still reaches the triangle's traversal. */
#define EMBREE_PAD_REL 0x1p-20

static void widen_for_embree(const mr_dgrad *gr, double l[3], double h[3])
{
    double e = EMBREE_PAD_REL * (gr->pad / PAD_REL);
    for (int c = 0; c < 3; c++)
        l[c] -= e, h[c] += e;
}

void mr_dtrace_tri_box(const mr_dbase *b, const mr_dheights *hs, const mr_dgrad *gr, float lo[3],
                       float hi[3])
{
    double l[3] = {INFINITY, INFINITY, INFINITY}, h[3] = {-INFINITY, -INFINITY, -INFINITY};
    if (b->flat) {
        flat_box(b, hs, gr, l, h);
        widen_for_embree(gr, l, h);
        to_float_box(l, h, lo, hi);
        return;
    }
    for (int k = 0; k < 3; k++) {
        const double *o = b->g[k], *n1 = b->g[(k + 1) % 3], *n2 = b->g[(k + 2) % 3];
        double ax = 0.5 * (n1[0] - o[0]), ay = 0.5 * (n1[1] - o[1]);
        double bx = 0.5 * (n2[0] - o[0]), by = 0.5 * (n2[1] - o[1]);
        /* g_k + s a + t b, s, t in [0, 1]: centre g_k + a/2 + b/2 */
        mr_af X = mr_af_uv(o[0] - b->g[0][0] + 0.5 * ax + 0.5 * bx, 0.5 * ax, 0.5 * bx);
        mr_af Y = mr_af_uv(o[1] - b->g[0][1] + 0.5 * ay + 0.5 * by, 0.5 * ay, 0.5 * by);
        double pl[3], ph[3];
        box_of(gr, X, Y, gr->hlo, gr->hhi, pl, ph);
        for (int c = 0; c < 3; c++)
            l[c] = fmin(l[c], pl[c]), h[c] = fmax(h[c], ph[c]);
    }
    widen_for_embree(gr, l, h);
    to_float_box(l, h, lo, hi);
}

/* ---- the local frame ------------------------------------------------------------- */

/* Bounds of the unit normal's local components inv N / |N| over grid
 * rectangle [x0, x1] x [y0, y1] (cut to T's grid box, which holds every
 * micro-vertex of T): inv N is affine in the grid point, so over the
 * rectangle it lies between the values its corners give, each component
 * reached at the corner its two slopes pick; then local_frame's division
 * by |N| in [least, 1], with a slack of 1e-12 of the terms' largest size
 * over T's grid box (the double evaluation is off by a few ulps of them),
 * and T's own bounds narrowed by the result. The grid components only:
 * the face component (about 1) moves a box by its heights' turn, little.
 * A curved base's boxes were as wide as the turn of its normal over all
 * of T times the height, for every node. */
static inline void rect_normals(const mr_dgrad *gr, double x0, double x1, double y0, double y1,
                                double nlo[3], double nhi[3])
{
    const double dx0 = x0 - gr->g0[0], dx1 = x1 - gr->g0[0];
    const double dy0 = y0 - gr->g0[1], dy1 = y1 - gr->g0[1];
    for (int a = 0; a < 2; a++) {
        const double *c = gr->nl[a];
        double ax0 = c[1] * dx0, ax1 = c[1] * dx1, ay0 = c[2] * dy0, ay1 = c[2] * dy1;
        double lo = c[0] + dmin(ax0, ax1) + dmin(ay0, ay1);
        double hi = c[0] + dmax(ax0, ax1) + dmax(ay0, ay1);
        lo = lo >= 0 ? lo - gr->nslack[a] : lo * gr->inv_ndist - gr->nslack[a];
        hi = hi >= 0 ? hi * gr->inv_ndist + gr->nslack[a] : hi + gr->nslack[a];
        nlo[a] = dmax(lo, gr->nb[a][0]), nhi[a] = dmin(hi, gr->nb[a][1]);
        if (!(nlo[a] <= nhi[a]))
            nlo[a] = gr->nb[a][0], nhi[a] = gr->nb[a][1];
    }
    nlo[2] = gr->nb[2][0], nhi[2] = gr->nb[2][1];
}

/* What a node's local boxes share whatever their heights: its rectangle
 * cut to T's grid box and the normal's bounds over that. */
typedef struct lrect {
    double x0, x1, y0, y1;
    double nlo[3], nhi[3];
} lrect;

static inline void local_rect(const mr_dgrad *gr, double x0, double x1, double y0, double y1,
                              lrect *r)
{
    r->x0 = dmax(x0, gr->gx0), r->x1 = dmin(x1, gr->gx1);
    r->y0 = dmax(y0, gr->gy0), r->y1 = dmin(y1, gr->gy1);
    if (gr->nrect) {
        rect_normals(gr, r->x0, r->x1, r->y0, r->y1, r->nlo, r->nhi);
    } else {
        for (int a = 0; a < 3; a++)
            r->nlo[a] = gr->nb[a][0], r->nhi[a] = gr->nb[a][1];
    }
}

/* A node's box in T's local frame (dtrace.h) over its local_rect with
 * heights [hlo, hhi]: the rectangle moved by [h] times the normal's grid
 * components, its height [h] times the normal's face component, padded. */
static inline void lrect_box(const mr_dgrad *gr, const lrect *r, double hlo, double hhi,
                             double lo[3], double hi[3])
{
    double o[3][2];
    for (int a = 0; a < 3; a++) {
        double p0 = hlo * r->nlo[a], p1 = hlo * r->nhi[a];
        double p2 = hhi * r->nlo[a], p3 = hhi * r->nhi[a];
        o[a][0] = dmin(dmin(p0, p1), dmin(p2, p3)) - gr->lpad[a];
        o[a][1] = dmax(dmax(p0, p1), dmax(p2, p3)) + gr->lpad[a];
    }
    lo[0] = r->x0 + o[0][0], hi[0] = r->x1 + o[0][1];
    lo[1] = r->y0 + o[1][0], hi[1] = r->y1 + o[1][1];
    lo[2] = o[2][0], hi[2] = o[2][1];
}

/* A node's box in T's local frame from its grid rectangle and heights. */
static inline void local_box(const mr_dgrad *gr, double x0, double x1, double y0, double y1,
                             double hlo, double hhi, double lo[3], double hi[3])
{
    lrect r;
    local_rect(gr, x0, x1, y0, y1, &r);
    lrect_box(gr, &r, hlo, hhi, lo, hi);
}

/* mr_dgrad's footprint fields (a local T's): its box, its reach, and its
 * edges' half-planes. A micro-vertex over grid point q of T (a grid point
 * inside it, a corner or an edge crossing: dsurf.h) sits at local (x, y)
 * q + h (a, b) plus the pad, within reach of q; a hit, on a micro-triangle,
 * within reach of T. So it lies on T's side of each edge's line moved out
 * by reach along that edge's normal (the normal's components times reach
 * per axis), and a margin: 1e-9 of the coordinates' size for the rounding
 * of the ray's x and y and of the products (as packet_footprint's). */
static void footprint_frame(mr_dgrad *gr, const mr_dbase *b)
{
    local_box(gr, gr->gx0, gr->gx1, gr->gy0, gr->gy1, gr->hlo, gr->hhi, gr->tlo, gr->thi);
    const double hm = dmax(fabs(gr->hlo), fabs(gr->hhi));
    for (int a = 0; a < 2; a++)
        gr->reach[a] = hm * dmax(fabs(gr->nb[a][0]), fabs(gr->nb[a][1])) + gr->lpad[a];
    const double ex[2] = {gr->reach[0] + 1e-6, gr->reach[1] + 1e-6};
    const double size =
        dmax(dmax(fabs(gr->gx0), fabs(gr->gx1)), dmax(fabs(gr->gy0), fabs(gr->gy1))) + dmax(ex[0], ex[1]);
    const double *g[3] = {b->g[0], b->g[1], b->g[2]};
    const double area =
        (g[1][0] - g[0][0]) * (g[2][1] - g[0][1]) - (g[1][1] - g[0][1]) * (g[2][0] - g[0][0]);
    const double out = area > 0 ? 1.0 : -1.0; /* (a T with a local frame is not flat) */
    for (int k = 0; k < 3; k++) {
        const double *p = g[k], *q = g[(k + 1) % 3];
        gr->en[k][0] = out * (q[1] - p[1]);
        gr->en[k][1] = -out * (q[0] - p[0]);
        const double nl = fabs(gr->en[k][0]) + fabs(gr->en[k][1]);
        gr->ec[k] = gr->en[k][0] * p[0] + gr->en[k][1] * p[1] + fabs(gr->en[k][0]) * ex[0] +
                    fabs(gr->en[k][1]) * ex[1] + 1e-9 * nl * size;
    }
}

void mr_dtrace_local_box(const mr_dgrad *gr, double x0, double x1, double y0, double y1,
                         double hlo, double hhi, double lo[3], double hi[3])
{
    local_box(gr, x0, x1, y0, y1, hlo, hhi, lo, hi);
}

void mr_dtrace_local_point(const mr_dgrad *gr, const mr_dbase *b, mr_vec3 x, double out[3])
{
    double d[3] = {(double)x.x - gr->P0[0], (double)x.y - gr->P0[1], (double)x.z - gr->P0[2]};
    for (int a = 0; a < 3; a++)
        out[a] = gr->inv[a][0] * d[0] + gr->inv[a][1] * d[1] + gr->inv[a][2] * d[2];
    out[0] += b->g[0][0];
    out[1] += b->g[0][1];
}

/* ---- the overlap test ------------------------------------------------------------ */

/* Whether the grid rectangle may overlap T, whose grid box (tri_gbox) is
 * gx0 .. gy1. */
static bool rect_overlaps(const mr_dbase *b, double gx0, double gx1, double gy0, double gy1,
                          double x0, double x1, double y0, double y1)
{
    if (x1 < gx0 || x0 > gx1 || y1 < gy0 || y0 > gy1)
        return false;
    if (b->flat)
        return true;
    /* separating axes: T's edges. The corner of the rectangle furthest
     * inside each edge decides; "outside" needs a margin (a crossing
     * computed a rounding outside T still overlaps) */
    double m = b->margin;
    for (int e = 0; e < 3; e++) {
        const double *l = b->edge[e];
        double x = l[0] > 0 ? x1 : x0, y = l[1] > 0 ? y1 : y0;
        if (l[0] * x + l[1] * y + l[2] < -m)
            return false;
    }
    return true;
}

bool mr_dtrace_overlaps(const mr_dbase *b, const mr_dgrad *gr, double x0, double x1, double y0,
                       double y1)
{
    return rect_overlaps(b, gr->gx0, gr->gx1, gr->gy0, gr->gy1, x0, x1, y0, y1);
}

/* ---- the texture's infinite quadtree ----------------------------------------------- */

typedef mr_dnode dnode;
typedef mr_dpnode pnode;

/* A node of either source. */
typedef union tnode {
    dnode d; /* texture source */
    pnode p; /* procedural source */
} tnode;

/* Index of the level-l node holding global cell c along one axis (n
 * samples per period, nl nodes at level l). */
static inline int64_t node_index(int64_t c, uint32_t n, uint32_t nl, int l, int top)
{
    int64_t tile = mr_floor_div(c, n);
    if (l <= top)
        return tile * nl + ((c - tile * n) >> l);
    int up = l - top;
    return up >= 62 ? (tile < 0 ? -1 : 0) : mr_floor_div(tile, (int64_t)1 << up);
}

static dnode node_at(const mr_dgrid *g, int l, int64_t gx, int64_t gy)
{
    dnode n = {.level = l};
    int top = (int)g->levels;
    if (l <= top) {
        n.tx = mr_floor_div(gx, g->lw[l]);
        n.ty = mr_floor_div(gy, g->lh[l]);
        n.I = (uint32_t)(gx - n.tx * g->lw[l]);
        n.J = (uint32_t)(gy - n.ty * g->lh[l]);
    } else {
        n.tx = gx;
        n.ty = gy;
    }
    return n;
}

static void node_rect(const mr_dgrid *g, const dnode *n, double *x0, double *x1, double *y0,
                      double *y1)
{
    int top = (int)g->levels;
    if (n->level <= top) {
        uint64_t s = (uint64_t)1 << n->level;
        uint64_t a = n->I * s, b = (n->I + 1) * s, c = n->J * s, d = (n->J + 1) * s;
        *x0 = (double)n->tx * g->w + (double)a;
        *x1 = (double)n->tx * g->w + (double)(b < g->w ? b : g->w);
        *y0 = (double)n->ty * g->h + (double)c;
        *y1 = (double)n->ty * g->h + (double)(d < g->h ? d : g->h);
    } else {
        double s = ldexp(1.0, n->level - top);
        *x0 = (double)n->tx * s * g->w;
        *x1 = ((double)n->tx + 1) * s * g->w;
        *y0 = (double)n->ty * s * g->h;
        *y1 = ((double)n->ty + 1) * s * g->h;
    }
}

static void node_heights(const mr_dgrid *g, const dnode *n, double *lo, double *hi)
{
    if (n->level <= (int)g->levels) {
        mr_dgrid_node_heights(g, (unsigned)n->level, n->I, n->J, lo, hi);
        return;
    }
    mr_dgrid_node_heights(g, g->levels, 0, 0, lo, hi); /* the whole texture */
}

static int children(const mr_dgrid *g, const dnode *n, dnode out[4])
{
    int top = (int)g->levels, k = 0;
    for (int b = 0; b < 2; b++)
        for (int a = 0; a < 2; a++) {
            dnode c = {.level = n->level - 1};
            if (n->level > top + 1) {
                c.tx = n->tx * 2 + a;
                c.ty = n->ty * 2 + b;
            } else if (n->level == top + 1) {
                c.tx = n->tx * 2 + a;
                c.ty = n->ty * 2 + b;
                c.I = c.J = 0;
            } else {
                c.tx = n->tx;
                c.ty = n->ty;
                c.I = n->I * 2 + (uint32_t)a;
                c.J = n->J * 2 + (uint32_t)b;
                if (c.I >= g->lw[c.level] || c.J >= g->lh[c.level])
                    continue;
            }
            out[k++] = c;
        }
    return k;
}

/* The roots of T (4.2.7): the lowest level where T's cells span at most
 * two nodes per axis. */
static int roots(const mr_dgrid *g, const mr_dbase *b, dnode out[4])
{
    int64_t i0, i1, j0, j1;
    mr_dbase_cells(b, &i0, &i1, &j0, &j1);
    if (i1 < i0 || j1 < j0)
        return 0;
    int top = (int)g->levels;
    for (int l = 0;; l++) {
        uint32_t nw = l <= top ? g->lw[l] : 1, nh = l <= top ? g->lh[l] : 1;
        int64_t x0 = node_index(i0, g->w, nw, l, top), x1 = node_index(i1, g->w, nw, l, top);
        int64_t y0 = node_index(j0, g->h, nh, l, top), y1 = node_index(j1, g->h, nh, l, top);
        if (x1 - x0 <= 1 && y1 - y0 <= 1) {
            int k = 0;
            for (int64_t y = y0; y <= y1; y++)
                for (int64_t x = x0; x <= x1; x++)
                    out[k++] = node_at(g, l, x, y);
            return k;
        }
    }
}

void mr_dtrace_roots(const mr_dgrid *g, const mr_dbase *b, mr_droots *out)
{
    out->n = roots(g, b, out->r);
}

/* Base triangle t's roots: the scene's, or found now (a scene without). */
static mr_droots tri_roots(const mr_dscene *s, uint32_t t)
{
    mr_droots rs;
    if (s->roots)
        rs = s->roots[t];
    else
        mr_dtrace_roots(s->grid, &s->bases[t], &rs);
    return rs;
}

/* ---- ray tests ----------------------------------------------------------------------- */

/* Entry distance of the ray into the box, or false. */
static bool slab(const mr_dray *r, const double lo[3], const double hi[3], double tmin,
                 double tmax, double *tnear)
{
    double t0 = tmin, t1 = tmax;
    for (int a = 0; a < 3; a++) {
        if (r->par[a]) {
            if (r->o[a] < lo[a] || r->o[a] > hi[a])
                return false;
            continue;
        }
        double n = (lo[a] - r->o[a]) * r->inv[a], f = (hi[a] - r->o[a]) * r->inv[a];
        if (n > f) {
            double s = n;
            n = f;
            f = s;
        }
        f *= 1 + 4 * DBL_EPSILON; /* Ize 2013 */
        t0 = n > t0 ? n : t0;
        t1 = f < t1 ? f : t1;
        if (t0 > t1)
            return false;
    }
    *tnear = t0;
    return true;
}

/* How far past the best hit so far a node may start and still be entered:
 * 2^-20 of the distance (16 float ulps) further. A micro-triangle that
 * touches the hit (a ray through a shared micro-vertex or edge) computes
 * the same float t, but its node's box, padded far less than a float
 * rounding of t, can start a rounding beyond that t: entered all the same,
 * its micro-triangle is tested, and the tie goes by tri_test's rule, not
 * by which was found first. */
static inline double cull_limit(float tmax)
{
    return (double)tmax + fabs((double)tmax) * 0x1p-20;
}

#if defined(__x86_64__) && defined(__GNUC__)
/* cull_limit of eight floats at once (AVX-512): its operations lane by
 * lane. */
__attribute__((target("avx512f"))) static inline __m512d cull_limit8(__m256 tmax)
{
    const __m512d t = _mm512_cvtps_pd(tmax);
    return _mm512_add_pd(t, _mm512_mul_pd(_mm512_abs_pd(t), _mm512_set1_pd(0x1p-20)));
}
#endif

/* Which micro-triangle of T: its cell (i, j), cell half and place in the
 * cell's list (flat triangles: its place in the boundary fan). */
typedef struct tri_key {
    int64_t j, i;
    int half, k;
} tri_key;

static inline bool key_less(const tri_key *a, const tri_key *b)
{
    if (a->j != b->j)
        return a->j < b->j;
    if (a->i != b->i)
        return a->i < b->i;
    return a->half != b->half ? a->half < b->half : a->k < b->k;
}

typedef struct best {
    bool hit;
    float t;
    tri_key key;
    mr_vec3 v[3];
    double q[3][2]; /* the micro-triangle's grid points */
    float u, v2;    /* its barycentrics at the hit */
} best;

/* Keeps hit h of micro-triangle (a, b, c) when it is the ray's best so
 * far. A hit at the same distance as the best so far (a ray through a
 * shared micro-edge or vertex) goes to the micro-triangle first in (j, i,
 * half, k) order, so the winner does not depend on the order cells are
 * visited in (a packet of rays visits them in another order than one ray
 * alone). The test compares t with tmax before it divides t out, so a hit
 * whose t rounds to tmax can fail it: the test is asked up to a little
 * further (cull_limit), the hit then held to tmax in its float t. */
static inline void tri_keep(const mr_wt_hit *h, mr_vec3 a, mr_vec3 b, mr_vec3 c, const mr_dvert *va,
                            const mr_dvert *vb, const mr_dvert *vc, tri_key key, float *tmax,
                            best *out)
{
    if (h->t > *tmax)
        return;
    if (out->hit && h->t == out->t && !key_less(&key, &out->key))
        return;
    *tmax = h->t;
    out->hit = true;
    out->key = key;
    out->t = h->t;
    out->v[0] = a, out->v[1] = b, out->v[2] = c;
    out->q[0][0] = va->x, out->q[0][1] = va->y;
    out->q[1][0] = vb->x, out->q[1][1] = vb->y;
    out->q[2][0] = vc->x, out->q[2][1] = vc->y;
    out->u = h->u;
    out->v2 = h->v;
}

static void tri_test(const mr_dray *r, mr_vec3 a, mr_vec3 b, mr_vec3 c, const mr_dvert *va,
                     const mr_dvert *vb, const mr_dvert *vc, tri_key key, float tmin, float *tmax,
                     best *out, mr_dstats *st)
{
    mr_wt_hit h;
    if (st)
        st->triangles++;
    if (mr_wt_intersect(&r->wt, a, b, c, tmin, (float)cull_limit(*tmax), &h))
        tri_keep(&h, a, b, c, va, vb, vc, key, tmax, out);
}

/* Ray / bilinear patch through p00 p10 p01 p11 (Reshetov, "Cool Patches",
 * Ray Tracing Gems II ch. 8): the closest (t, u, v) with u, v in [0, 1]. */
static bool bilinear_hit(const mr_dray *r, const mr_vec3 q[4], float tmin, float tmax, float *t_out,
                         double *u_out, double *v_out)
{
    double o[3] = {r->o[0], r->o[1], r->o[2]}, d[3] = {r->d[0], r->d[1], r->d[2]};
    double p00[3] = {q[0].x, q[0].y, q[0].z}, p10[3] = {q[1].x, q[1].y, q[1].z};
    double p01[3] = {q[2].x, q[2].y, q[2].z}, p11[3] = {q[3].x, q[3].y, q[3].z};
    double qn[3], e10[3], e11[3], e00[3], qo[3];
    for (int c = 0; c < 3; c++) {
        e10[c] = p10[c] - p00[c];
        e11[c] = p11[c] - p10[c];
        e00[c] = p01[c] - p00[c];
        qo[c] = p00[c] - o[c];
    }
    /* qn = cross(e10, p01 - p11) */
    double f[3] = {p01[0] - p11[0], p01[1] - p11[1], p01[2] - p11[2]};
    qn[0] = e10[1] * f[2] - e10[2] * f[1];
    qn[1] = e10[2] * f[0] - e10[0] * f[2];
    qn[2] = e10[0] * f[1] - e10[1] * f[0];
    double q10[3] = {p10[0] - o[0], p10[1] - o[1], p10[2] - o[2]};
    /* a = dot(cross(qo, d), e00), c = dot(qn, d), b = dot(cross(q10, d), e11) - a - c */
    double x[3];
    x[0] = qo[1] * d[2] - qo[2] * d[1];
    x[1] = qo[2] * d[0] - qo[0] * d[2];
    x[2] = qo[0] * d[1] - qo[1] * d[0];
    double A = x[0] * e00[0] + x[1] * e00[1] + x[2] * e00[2];
    double C = qn[0] * d[0] + qn[1] * d[1] + qn[2] * d[2];
    x[0] = q10[1] * d[2] - q10[2] * d[1];
    x[1] = q10[2] * d[0] - q10[0] * d[2];
    x[2] = q10[0] * d[1] - q10[1] * d[0];
    double B = x[0] * e11[0] + x[1] * e11[1] + x[2] * e11[2];
    B -= A + C;
    double det = B * B - 4 * A * C;
    if (det < 0)
        return false;
    det = sqrt(det);
    double u1, u2;
    if (C == 0) {
        if (B == 0)
            return false;
        u1 = -A / B;
        u2 = -1;
    } else {
        u1 = (-B - copysign(det, B)) / 2;
        u2 = A / u1;
        u1 /= C;
    }
    bool found = false;
    double bt = tmax, bu = 0, bv = 0;
    double us[2] = {u1, u2};
    for (int k = 0; k < 2; k++) {
        double u = us[k];
        if (!(u >= 0 && u <= 1))
            continue;
        double pa[3], pb[3], n[3];
        for (int c = 0; c < 3; c++) {
            pa[c] = (1 - u) * qo[c] + u * q10[c];
            pb[c] = (1 - u) * e00[c] + u * e11[c];
        }
        /* n = cross(d, pb) */
        n[0] = d[1] * pb[2] - d[2] * pb[1];
        n[1] = d[2] * pb[0] - d[0] * pb[2];
        n[2] = d[0] * pb[1] - d[1] * pb[0];
        double n2 = n[0] * n[0] + n[1] * n[1] + n[2] * n[2];
        if (!(n2 > 0))
            continue;
        /* v = det(pa, d, n) / n2, t = det(pa, pb, n) / n2 */
        double c1[3];
        c1[0] = pa[1] * d[2] - pa[2] * d[1];
        c1[1] = pa[2] * d[0] - pa[0] * d[2];
        c1[2] = pa[0] * d[1] - pa[1] * d[0];
        double v = (c1[0] * n[0] + c1[1] * n[1] + c1[2] * n[2]) / n2;
        c1[0] = pa[1] * pb[2] - pa[2] * pb[1];
        c1[1] = pa[2] * pb[0] - pa[0] * pb[2];
        c1[2] = pa[0] * pb[1] - pa[1] * pb[0];
        double t = (c1[0] * n[0] + c1[1] * n[1] + c1[2] * n[2]) / n2;
        if (v >= 0 && v <= 1 && t >= tmin && t <= bt) {
            found = true;
            bt = t, bu = u, bv = v;
        }
    }
    if (!found)
        return false;
    *t_out = (float)bt;
    *u_out = bu;
    *v_out = bv;
    return true;
}

/* The micro-triangles of T in one cell: made once, tested against each ray
 * that reaches the cell. The micro-vertices and the cell's counts and
 * triangles come first: a ray's test reads them, the vertex records (at
 * the end of mr_dcell) only for a hit. */
typedef struct cell_tris {
    mr_vec3 V[2 * MR_DSURF_MAX_POLY];
    int64_t i, j;
    mr_dcell c;
} cell_tris;

/* ---- what a thread keeps of this pose ------------------------------------------- */

/* The ways of a set of the walk caches below (walk_set, walk_find). */
#define WALK_WAYS 4

/* Cells made this pose, per thread: rays of neighbouring packets and
 * pixels meet the same cells of the same base triangle, and making one
 * (cutting it by T's edges, evaluating its micro-vertices) costs more than
 * testing a ray against it. Four-way set-associative by (triangle, cell,
 * half), the least recently used way replaced (direct-mapped, two cells
 * of neighbouring triangles that shared a slot evicted each other on every
 * ray). The keys lie apart from the cells: a set's four keys take three
 * cache lines, where with their cells they took four. 256 cells, 400 KB
 * a thread: the procedural sphere's trace at range 64 took 0.992 of the
 * time it took with 128 (the texture sphere's at 100 texels a unit
 * 0.994); 512 were no faster. */
#define CELL_SETS 64
#define CELL_CACHE (WALK_WAYS * CELL_SETS)
_Static_assert((CELL_SETS & (CELL_SETS - 1)) == 0, "walk_find picks a set by a mask");

/* The child boxes of procedural squares made this pose, per thread
 * (node_boxes): the packets of neighbouring pixels enter the same squares
 * of the same base triangle (4.8 packets a square on the procedural
 * sphere at range 64), and a square's children cost their heights' look-ups
 * and bounds besides their boxes (a texture's heights come from its
 * pyramid, where keeping the boxes bought nothing). Four-way
 * set-associative like the cells: 512 squares hit 64 % of the look-ups
 * on that sphere; 4,096 hit 79 % but missed the processor's caches,
 * 1.03-1.04 of the time. */
#define NODE_SETS 128
#define NODE_CACHE (WALK_WAYS * NODE_SETS)
_Static_assert((NODE_SETS & (NODE_SETS - 1)) == 0, "walk_find picks a set by a mask");

/* What an entry is of: base triangle t's cell (x, y) (`which`: its half)
 * or procedural square (x, y) (`which`: its level), of the pose `pose`
 * (mr_dscene.pose, unique per pose, so entries of an earlier pose or
 * another scene never match; 0: no entry). */
typedef struct walk_key {
    uint64_t pose;
    int64_t x, y;
    uint32_t t;
    int32_t which;
    bool any; /* a cell's: whether it has micro-triangles (not part of the key) */
} walk_key;

/* A square's children as proc_child_boxes_avx2 makes them without the
 * parent test: their boxes and heights, and which of them it boxed. */
typedef struct node_boxes {
    double lo[3][4], hi[3][4], hl[4], hh[4];
    unsigned boxed;
} node_boxes;

/* Grid micro-vertices made this pose, per thread, direct-mapped by
 * (triangle, grid point): a grid point is a corner of the four cells
 * around it, each made on its own. 2,048 slots held 68 % of the look-ups
 * on the procedural plane at range 64 and 71-77 % on the texture plane
 * and sphere at 200 texels per unit; trace 0.97-0.99 of the time with a
 * procedural source, 0.99-1.00 with a texture (stop 61). */
#define VERT_SLOTS 2048
_Static_assert((VERT_SLOTS & (VERT_SLOTS - 1)) == 0, "a vertex's slot is picked by a mask");

/* A grid micro-vertex of base triangle t at grid point (a, b), of the pose
 * `pose` (0: none), and its displaced position. */
typedef struct vert_entry {
    uint64_t pose;
    int64_t a, b;
    uint32_t t;
    float V[3];
} vert_entry;

/* What a look-up reads first of a set of four ways, half a cache line:
 * per way a tag of its key (walk_find: 32 bits of the key's hash with its
 * pose; 0: empty), so a key is read only where its tag matches, and the
 * thread's look-up count when the way was last used (its low 32 bits: the
 * eviction order, compared modulo 2^32), so a miss picks its way without
 * reading the set's keys (three lines: with the counts in them, a miss
 * read all three). */
typedef struct walk_set {
    uint32_t tag[WALK_WAYS];
    uint32_t used[WALK_WAYS];
} walk_set;

/* A thread's caches: entries hold exactly what is computed, so what they
 * hold changes no result. 430 KB, on the heap (thread_block.h). */
typedef struct walk_cache {
    uint32_t clock; /* look-ups made (modulo 2^32) */
    walk_set cell_sets[CELL_SETS];
    walk_set node_sets[NODE_SETS];
    walk_key cell_keys[CELL_CACHE];
    walk_key node_keys[NODE_CACHE];
    cell_tris cells[CELL_CACHE];
    node_boxes nodes[NODE_CACHE];
    vert_entry verts[VERT_SLOTS];
} walk_cache;

static mr_thread_block walk_block = MR_THREAD_BLOCK_INIT;
static _Thread_local void *my_walk;

/* This thread's caches for scene s, or NULL: a scene without a pose id
 * keeps nothing, nor a thread without the memory. */
static walk_cache *walk_cache_of(const mr_dscene *s)
{
    return s->pose ? mr_thread_block_get(&walk_block, &my_walk, sizeof(walk_cache)) : NULL;
}

/* The hash a walk cache's entry is found by (walk_find: its set and tag):
 * of base triangle t's cell or square (x, y) and `which` (walk_key). One
 * mix of the fields, each multiplied apart (three mixes, one inside the
 * other, cost the procedural plane at range 64 2.5 % of its trace). */
static inline uint64_t walk_hash(uint32_t t, int64_t x, int64_t y, int32_t which)
{
    return mr_mix64((uint64_t)x * 0x9e3779b97f4a7c15ull ^ (uint64_t)y * 0xc2b2ae3d27d4eb4full ^
                    (uint64_t)t * 0x165667b19e3779f9ull ^ (uint64_t)(uint32_t)which);
}

/* The way of key k in its set (from hash h of k's other fields: one of
 * `nsets` sets, a power of 2) of the WALK_WAYS ways in sets and keys: its
 * index in keys and true when there; else the least recently used way's,
 * given k. The set's tags are compared together and a key read only where
 * its tag matches: comparing the keys field by field, a set's three lines
 * of them, took 8 % of the procedural plane's frame at range 64 (h %
 * sets, a division since sets is no constant here, a sixth of that). */
static bool walk_find(walk_cache *wc, walk_set *sets, walk_key *keys, size_t nsets, uint64_t h,
                      const walk_key *k, size_t *at)
{
    const size_t si = (size_t)(h & (nsets - 1u));
    walk_set *ws = &sets[si];
    walk_key *set = &keys[si * WALK_WAYS];
    /* (nonzero: an empty way's tag is 0) */
    const uint32_t tag = (uint32_t)((h ^ k->pose * 0x9e3779b97f4a7c15ull) >> 32) | 1u;
    const uint32_t now = ++wc->clock;
    unsigned cand = 0;
    for (int w = 0; w < WALK_WAYS; w++)
        cand |= (unsigned)(ws->tag[w] == tag) << w;
    for (; cand; cand &= cand - 1) {
        const int w = __builtin_ctz(cand);
        const walk_key *x = &set[w];
        if (x->pose == k->pose && x->t == k->t && x->x == k->x && x->y == k->y && x->which == k->which) {
            ws->used[w] = now;
            *at = si * WALK_WAYS + (size_t)w;
            return true;
        }
    }
    int e = 0; /* the oldest: the largest age now - used */
    for (int w = 1; w < WALK_WAYS; w++)
        if (now - ws->used[w] > now - ws->used[e])
            e = w;
    ws->tag[e] = tag;
    ws->used[e] = now;
    set[e] = *k;
    *at = si * WALK_WAYS + (size_t)e;
    return false;
}

/* The displaced position of micro-vertex v of base triangle t (b): a
 * grid vertex from the thread's cache wc (NULL: none) when it holds it. */
static mr_vec3 cell_vertex(const mr_dscene *s, walk_cache *wc, uint32_t t, const mr_dbase *b,
                           const mr_dvert *v)
{
    if (!wc || v->kind != MR_DV_GRID)
        return mr_dsurf_vertex(b, &s->heights, v);
    const uint64_t h = mr_mix64((uint64_t)v->a * 0x9e3779b97f4a7c15ull ^ (uint64_t)v->b ^ (uint64_t)t << 40);
    vert_entry *e = &wc->verts[h & (VERT_SLOTS - 1u)];
    if (e->pose == s->pose && e->t == t && e->a == v->a && e->b == v->b)
        return mr_v3(e->V[0], e->V[1], e->V[2]);
    const mr_vec3 V = mr_dsurf_vertex(b, &s->heights, v);
    *e = (vert_entry){.pose = s->pose, .a = v->a, .b = v->b, .t = t, .V = {V.x, V.y, V.z}};
    return V;
}

static bool cell_make(const mr_dscene *s, walk_cache *wc, uint32_t t, const mr_dbase *b, int64_t i,
                      int64_t j, int half, cell_tris *ct, mr_dstats *st)
{
    mr_dsurf_cell(b, i, j, half, &ct->c);
    if (st)
        st->cells++;
    ct->i = i, ct->j = j;
    for (int k = 0; k < ct->c.nv; k++)
        ct->V[k] = cell_vertex(s, wc, t, b, &ct->c.v[k]);
    return ct->c.nt > 0;
}

static _Thread_local cell_tris cell_scratch; /* (a cell kept nowhere) */

/* The micro-triangles of base triangle t (b) in cell (i, j), half, or NULL
 * when it has none; valid until the thread's next cell_get. */
static const cell_tris *cell_get(const mr_dscene *s, uint32_t t, const mr_dbase *b, int64_t i, int64_t j,
                                 int half, mr_dstats *st)
{
    walk_cache *wc = walk_cache_of(s);
    if (!wc)
        return cell_make(s, NULL, t, b, i, j, half, &cell_scratch, st) ? &cell_scratch : NULL;
    const walk_key k = {.pose = s->pose, .t = t, .x = i, .y = j, .which = half};
    const uint64_t h = walk_hash(t, i, j, half);
    size_t w;
    if (!walk_find(wc, wc->cell_sets, wc->cell_keys, CELL_SETS, h, &k, &w))
        wc->cell_keys[w].any = cell_make(s, wc, t, b, i, j, half, &wc->cells[w], st);
    return wc->cell_keys[w].any ? &wc->cells[w] : NULL;
}

uint64_t mr_dscene_new_pose(void)
{
    static _Atomic uint64_t next = 1;
    return atomic_fetch_add_explicit(&next, 1, memory_order_relaxed);
}

/* The ray against the cell's micro-triangles, each micro-vertex sheared
 * into the ray's space once (the triangles share them: two per cell share
 * two of four, a cut cell's fan shares more); the same answers as
 * tri_test on each triangle (watertight.h). */
static void cell_test(const cell_tris *ct, const mr_wt_ray *wt, float tmin, float *tmax, best *out,
                      mr_dstats *st)
{
    const mr_dcell *c = &ct->c;
    mr_wt_vertex sv[2 * MR_DSURF_MAX_POLY];
    for (int k = 0; k < c->nv; k++)
        sv[k] = mr_wt_shear(wt, ct->V[k]);
    if (st)
        st->triangles += (uint64_t)c->nt;
    for (int k = 0; k < c->nt; k++) {
        const uint8_t *tr = c->tri[k];
        mr_wt_hit h;
        if (mr_wt_intersect_sheared(&sv[tr[0]], &sv[tr[1]], &sv[tr[2]], tmin,
                                    (float)cull_limit(*tmax), &h))
            tri_keep(&h, ct->V[tr[0]], ct->V[tr[1]], ct->V[tr[2]], &c->v[tr[0]], &c->v[tr[1]],
                     &c->v[tr[2]], (tri_key){ct->j, ct->i, c->half[k], k}, tmax, out);
    }
}

/* The micro-surface of T in cell (i, j). */
static void leaf(const mr_dscene *s, uint32_t t, const mr_dbase *b, int64_t i, int64_t j, int half,
                 const mr_dray *r, float tmin, float *tmax, best *out, mr_dstats *st)
{
    const cell_tris *ct = cell_get(s, t, b, i, j, half, st);
    if (!ct)
        return;
    const mr_dcell *c = &ct->c;
    const mr_vec3 *V = ct->V;
    bool full = c->nv == 4 && c->nt == 2 && half == 2;
    for (int k = 0; full && k < 4; k++)
        full = c->v[k].kind == MR_DV_GRID;
    if (s->local == MR_DLOCAL_BILINEAR && full) {
        /* corners (i,j) (i+1,j) (i,j+1) (i+1,j+1) among the four */
        mr_vec3 q[4];
        for (int k = 0; k < 4; k++)
            q[(int)(c->v[k].a - i) + 2 * (int)(c->v[k].b - j)] = V[k];
        float th;
        double u, v;
        tri_key key = {j, i, 0, 0};
        if (st)
            st->triangles++;
        if (bilinear_hit(r, q, tmin, (float)cull_limit(*tmax), &th, &u, &v) && th <= *tmax &&
            !(out->hit && th == out->t && !key_less(&key, &out->key))) {
            *tmax = th;
            out->hit = true;
            out->t = th;
            out->key = key;
            /* normal: the patch's tangents at (u, v) */
            mr_vec3 du = mr_v3_lerp(mr_v3_sub(q[1], q[0]), mr_v3_sub(q[3], q[2]), (float)v);
            mr_vec3 dv = mr_v3_lerp(mr_v3_sub(q[2], q[0]), mr_v3_sub(q[3], q[1]), (float)u);
            /* store as a degenerate triangle whose normal is du x dv */
            out->v[0] = mr_v3(0, 0, 0);
            out->v[1] = du;
            out->v[2] = dv;
            out->q[0][0] = (double)i + u, out->q[0][1] = (double)j + v;
            out->q[1][0] = out->q[0][0], out->q[1][1] = out->q[0][1];
            out->q[2][0] = out->q[0][0], out->q[2][1] = out->q[0][1];
            out->u = out->v2 = 0;
        }
        return;
    }
    cell_test(ct, &r->wt, tmin, tmax, out, st);
}

static void flat_leaf(const mr_dscene *s, const mr_dbase *b, const mr_dray *r, float tmin,
                      float *tmax, best *out, mr_dstats *st)
{
    static _Thread_local mr_dvert pts[FLAT_MAX];
    int n = mr_dsurf_flat_boundary(b, pts, FLAT_MAX);
    if (n < 3)
        return;
    mr_vec3 v0 = mr_dsurf_vertex(b, &s->heights, &pts[0]);
    mr_vec3 prev = mr_dsurf_vertex(b, &s->heights, &pts[1]);
    for (int k = 2; k < n; k++) {
        mr_vec3 cur = mr_dsurf_vertex(b, &s->heights, &pts[k]);
        tri_test(r, v0, prev, cur, &pts[0], &pts[k - 1], &pts[k], (tri_key){0, 0, 0, k}, tmin,
                 tmax, out, st);
        prev = cur;
    }
}

static void finish(const mr_dbase *b, const best *bh, mr_dhit *hit)
{
    if (!hit)
        return;
    hit->t = bh->t;
    hit->ng = mr_v3_cross(mr_v3_sub(bh->v[1], bh->v[0]), mr_v3_sub(bh->v[2], bh->v[0]));
    double w0 = 1.0 - bh->u - bh->v2;
    double x = w0 * bh->q[0][0] + bh->u * bh->q[1][0] + bh->v2 * bh->q[2][0];
    double y = w0 * bh->q[0][1] + bh->u * bh->q[1][1] + bh->v2 * bh->q[2][1];
    double b1 = 0, b2 = 0;
    if (!b->flat)
        mr_dbase_bary(b, x, y, &b1, &b2);
    hit->b1 = (float)b1;
    hit->b2 = (float)b2;
}

#define STACK_MAX 512

/* Pushes the nh children in hitc (entries with a tnear) onto the stack
 * farthest first, so the nearest is visited next (ties keep their order):
 * every traversal's entries, whatever else they hold. */
#define PUSH_NEAREST_LAST(stack, sp, hitc, nh)                                              \
    do {                                                                                    \
        for (int a_ = 1; a_ < (nh); a_++)                                                   \
            for (int m_ = a_; m_ > 0 && (hitc)[m_].tnear > (hitc)[m_ - 1].tnear; m_--) {    \
                __typeof__((hitc)[0]) t_ = (hitc)[m_];                                      \
                (hitc)[m_] = (hitc)[m_ - 1];                                                \
                (hitc)[m_ - 1] = t_;                                                        \
            }                                                                               \
        for (int k_ = 0; k_ < (nh) && (sp) < STACK_MAX; k_++)                               \
            (stack)[(sp)++] = (hitc)[k_];                                                   \
    } while (0)

/* The ray in T's local frame (grid x, grid y, face height). */
static void local_ray(const mr_dgrad *gr, const mr_dbase *b, const mr_dray *r, mr_dray *lr)
{
    double od[3];
    for (int c = 0; c < 3; c++)
        od[c] = r->o[c] - gr->P0[c];
    for (int a = 0; a < 3; a++) {
        lr->o[a] = gr->inv[a][0] * od[0] + gr->inv[a][1] * od[1] + gr->inv[a][2] * od[2];
        lr->d[a] = gr->inv[a][0] * r->d[0] + gr->inv[a][1] * r->d[1] + gr->inv[a][2] * r->d[2];
        lr->par[a] = lr->d[a] == 0;
        lr->inv[a] = lr->d[a] != 0 ? 1.0 / lr->d[a] : 0.0;
    }
    lr->o[0] += b->g[0][0];
    lr->o[1] += b->g[0][1];
}

/* Entry distance of a node whose grid rectangle and heights are given (the
 * local frame's box, or the 3D box), or false. */
static inline bool node_hit(const mr_dbase *b, const mr_dgrad *gr, const mr_dray *r,
                            const mr_dray *lr, double x0, double x1, double y0, double y1,
                            double hlo, double hhi, double tmin, double tmax, double *tn)
{
    double lo[3], hi[3];
    if (gr->local) {
        local_box(gr, x0, x1, y0, y1, hlo, hhi, lo, hi);
        return slab(lr, lo, hi, tmin, tmax, tn);
    }
    return rect_box_d(b, gr, x0, x1, y0, y1, hlo, hhi, lo, hi) && slab(r, lo, hi, tmin, tmax, tn);
}

/* ---- a texture node's children, two at a time ------------------------------------ */

#if defined(__SSE2__)
/* One axis of slab for two lanes: the box lo..hi, the rays' origins and
 * reciprocal directions; narrows the entry t0 and exit t1 with slab's
 * operations (min and max as a < b ? a : b and a > b ? a : b, which minpd
 * and maxpd are), so each lane is what slab computes one by one. */
static inline void slab_axis2(__m128d lo, __m128d hi, __m128d o, __m128d inv, __m128d *t0,
                              __m128d *t1)
{
    __m128d nn = _mm_mul_pd(_mm_sub_pd(lo, o), inv);
    __m128d ff = _mm_mul_pd(_mm_sub_pd(hi, o), inv);
    __m128d near = _mm_min_pd(ff, nn), far = _mm_max_pd(nn, ff);
    far = _mm_mul_pd(far, _mm_set1_pd(1 + 4 * DBL_EPSILON)); /* Ize 2013 */
    *t0 = _mm_max_pd(near, *t0);
    *t1 = _mm_min_pd(far, *t1);
}
#endif

typedef struct tentry {
    tnode n;
    double tnear;
} tentry;

#if defined(__SSE2__)
/* rect_normals for two rectangles [x0, x1] (lanes) x [y0, y1]: its
 * operations lane by lane (min and max as minpd and maxpd are, a < b ? a :
 * b and a > b ? a : b; the selections by mask), so the same bounds. */
static inline void rect_normals2(const mr_dgrad *gr, __m128d x0, __m128d x1, double y0, double y1,
                                 __m128d nlo[3], __m128d nhi[3])
{
    const __m128d gx = _mm_set1_pd(gr->g0[0]), zero = _mm_setzero_pd();
    const __m128d dx0 = _mm_sub_pd(x0, gx), dx1 = _mm_sub_pd(x1, gx);
    const double dy0 = y0 - gr->g0[1], dy1 = y1 - gr->g0[1];
    const __m128d inv = _mm_set1_pd(gr->inv_ndist);
    for (int a = 0; a < 2; a++) {
        const double *c = gr->nl[a];
        const __m128d c1 = _mm_set1_pd(c[1]);
        __m128d ax0 = _mm_mul_pd(c1, dx0), ax1 = _mm_mul_pd(c1, dx1);
        double ay0 = c[2] * dy0, ay1 = c[2] * dy1;
        __m128d lo = _mm_add_pd(_mm_add_pd(_mm_set1_pd(c[0]), _mm_min_pd(ax0, ax1)),
                                _mm_set1_pd(dmin(ay0, ay1)));
        __m128d hi = _mm_add_pd(_mm_add_pd(_mm_set1_pd(c[0]), _mm_max_pd(ax0, ax1)),
                                _mm_set1_pd(dmax(ay0, ay1)));
        const __m128d slack = _mm_set1_pd(gr->nslack[a]);
        __m128d lpos = _mm_cmpge_pd(lo, zero), hpos = _mm_cmpge_pd(hi, zero);
        lo = _mm_sub_pd(_mm_or_pd(_mm_and_pd(lpos, lo), _mm_andnot_pd(lpos, _mm_mul_pd(lo, inv))), slack);
        hi = _mm_add_pd(_mm_or_pd(_mm_and_pd(hpos, _mm_mul_pd(hi, inv)), _mm_andnot_pd(hpos, hi)), slack);
        const __m128d b0 = _mm_set1_pd(gr->nb[a][0]), b1 = _mm_set1_pd(gr->nb[a][1]);
        lo = _mm_max_pd(lo, b0), hi = _mm_min_pd(hi, b1);
        __m128d ok = _mm_cmple_pd(lo, hi);
        nlo[a] = _mm_or_pd(_mm_and_pd(ok, lo), _mm_andnot_pd(ok, b0));
        nhi[a] = _mm_or_pd(_mm_and_pd(ok, hi), _mm_andnot_pd(ok, b1));
    }
    nlo[2] = _mm_set1_pd(gr->nb[2][0]), nhi[2] = _mm_set1_pd(gr->nb[2][1]);
}

/* The boxes of node n's children (level 1 .. the pyramid's top) in T's
 * local frame, a row of two at a time (SSE2): what mr_dtrace_overlaps,
 * node_heights and local_box compute for each child, the same operations in
 * the same order lane by lane (min and max as a < b ? a : b and
 * a > b ? a : b, which minpd and maxpd are), so the boxes are the ones made
 * one by one. Child 2 r + a is (2 I + a, 2 J + r); returns the mask of
 * children that exist and may overlap T, their boxes in lo and hi
 * [axis][child]. */
static unsigned tex_child_boxes(const mr_dgrid *g, const mr_dbase *b, const mr_dgrad *gr,
                                const dnode *n, double lo[3][4], double hi[3][4], mr_dstats *st)
{
    const int c = n->level - 1;
    const uint32_t I0 = n->I * 2, J0 = n->J * 2;
    const bool two_x = I0 + 1 < g->lw[c];
    const uint64_t s = (uint64_t)1 << c;
    const double bx = (double)n->tx * g->w, by = (double)n->ty * g->h;
    /* the two columns' x extents (lane a: child I0 + a) */
    uint64_t xa0 = I0 * s, xa1 = (I0 + 1) * s, xb1 = (I0 + 2) * s;
    __m128d x0 = _mm_set_pd(bx + (double)xa1, bx + (double)xa0);
    __m128d x1 = _mm_set_pd(bx + (double)(xb1 < g->w ? xb1 : g->w),
                            bx + (double)(xa1 < g->w ? xa1 : g->w));
    const __m128d gx0 = _mm_set1_pd(gr->gx0), gx1 = _mm_set1_pd(gr->gx1);
    /* mr_dtrace_overlaps' x part, and the x terms of its edge tests */
    __m128d xin = _mm_andnot_pd(_mm_or_pd(_mm_cmplt_pd(x1, gx0), _mm_cmpgt_pd(x0, gx1)),
                                _mm_castsi128_pd(_mm_set1_epi32(-1)));
    if (!two_x)
        xin = _mm_and_pd(xin, _mm_castsi128_pd(_mm_set_epi32(0, 0, -1, -1)));
    __m128d ex[3];
    for (int e = 0; e < 3; e++)
        ex[e] = _mm_mul_pd(_mm_set1_pd(b->edge[e][0]), b->edge[e][0] > 0 ? x1 : x0);
    /* local_box's x extent before the height offsets */
    const __m128d lx0 = _mm_max_pd(x0, gx0), lx1 = _mm_min_pd(x1, gx1);
    const double m = b->margin;
    unsigned mask = 0;
    for (int r = 0; r < 2; r++) {
        uint32_t J = J0 + (uint32_t)r;
        if (J >= g->lh[c])
            break;
        if (st)
            st->nodes += two_x ? 2 : 1;
        uint64_t ya = J * s, yb = (J + 1) * s;
        double y0 = by + (double)ya, y1 = by + (double)(yb < g->h ? yb : g->h);
        if (y1 < gr->gy0 || y0 > gr->gy1)
            continue;
        __m128d in = xin;
        for (int e = 0; e < 3; e++) {
            const double *l = b->edge[e];
            __m128d v = _mm_add_pd(_mm_add_pd(ex[e], _mm_set1_pd(l[1] * (l[1] > 0 ? y1 : y0))),
                                   _mm_set1_pd(l[2]));
            in = _mm_andnot_pd(_mm_cmplt_pd(v, _mm_set1_pd(-m)), in);
        }
        unsigned inm = (unsigned)_mm_movemask_pd(in);
        if (!inm)
            continue;
        double hl[2], hh[2];
        mr_dgrid_node_heights(g, (unsigned)c, I0, J, &hl[0], &hh[0]);
        if (inm & 2)
            mr_dgrid_node_heights(g, (unsigned)c, I0 + 1, J, &hl[1], &hh[1]);
        else
            hl[1] = hl[0], hh[1] = hh[0];
        const __m128d hlo = _mm_loadu_pd(hl), hhi = _mm_loadu_pd(hh);
        /* local_box (each lane's normal bounds from its own rectangle) */
        const double ry0 = y0 > gr->gy0 ? y0 : gr->gy0, ry1 = y1 < gr->gy1 ? y1 : gr->gy1;
        __m128d nlo[3], nhi[3];
        if (gr->nrect) {
            rect_normals2(gr, lx0, lx1, ry0, ry1, nlo, nhi);
        } else {
            for (int a = 0; a < 3; a++)
                nlo[a] = _mm_set1_pd(gr->nb[a][0]), nhi[a] = _mm_set1_pd(gr->nb[a][1]);
        }
        __m128d l[3], h[3];
        for (int a = 0; a < 3; a++) {
            __m128d n0 = nlo[a], n1 = nhi[a];
            __m128d p0 = _mm_mul_pd(hlo, n0), p1 = _mm_mul_pd(hlo, n1);
            __m128d p2 = _mm_mul_pd(hhi, n0), p3 = _mm_mul_pd(hhi, n1);
            __m128d pad = _mm_set1_pd(gr->lpad[a]);
            l[a] = _mm_sub_pd(_mm_min_pd(_mm_min_pd(p0, p1), _mm_min_pd(p2, p3)), pad);
            h[a] = _mm_add_pd(_mm_max_pd(_mm_max_pd(p0, p1), _mm_max_pd(p2, p3)), pad);
        }
        l[0] = _mm_add_pd(lx0, l[0]);
        h[0] = _mm_add_pd(lx1, h[0]);
        l[1] = _mm_add_pd(_mm_set1_pd(ry0), l[1]);
        h[1] = _mm_add_pd(_mm_set1_pd(ry1), h[1]);
        for (int a = 0; a < 3; a++) {
            _mm_storeu_pd(lo[a] + 2 * r, l[a]);
            _mm_storeu_pd(hi[a] + 2 * r, h[a]);
        }
        mask |= inm << 2 * r;
    }
    return mask;
}

#if defined(__x86_64__) && defined(__GNUC__)
/* A vector selecting lanes q of in (bit q set: all ones). */
__attribute__((target("avx2"))) static inline __m256d lanes_avx2(uint32_t in)
{
    return _mm256_castsi256_pd(_mm256_set_epi64x(-(int64_t)(in >> 3 & 1u), -(int64_t)(in >> 2 & 1u),
                                                 -(int64_t)(in >> 1 & 1u), -(int64_t)(in & 1u)));
}

/* rect_normals2 for four rectangles [x0, x1] x [y0, y1] (lanes), AVX2:
 * its operations lane by lane (its scalar y terms' dmin and dmax are
 * minpd and maxpd), so the same bounds. */
__attribute__((target("avx2"))) static inline void rect_normals4(const mr_dgrad *gr, __m256d x0,
                                                                  __m256d x1, __m256d y0,
                                                                  __m256d y1, __m256d nlo[3],
                                                                  __m256d nhi[3])
{
    const __m256d gx = _mm256_set1_pd(gr->g0[0]), gy = _mm256_set1_pd(gr->g0[1]);
    const __m256d zero = _mm256_setzero_pd(), inv = _mm256_set1_pd(gr->inv_ndist);
    const __m256d dx0 = _mm256_sub_pd(x0, gx), dx1 = _mm256_sub_pd(x1, gx);
    const __m256d dy0 = _mm256_sub_pd(y0, gy), dy1 = _mm256_sub_pd(y1, gy);
    for (int a = 0; a < 2; a++) {
        const double *c = gr->nl[a];
        const __m256d c0 = _mm256_set1_pd(c[0]), c1 = _mm256_set1_pd(c[1]),
                      c2 = _mm256_set1_pd(c[2]);
        const __m256d ax0 = _mm256_mul_pd(c1, dx0), ax1 = _mm256_mul_pd(c1, dx1);
        const __m256d ay0 = _mm256_mul_pd(c2, dy0), ay1 = _mm256_mul_pd(c2, dy1);
        __m256d lo = _mm256_add_pd(_mm256_add_pd(c0, _mm256_min_pd(ax0, ax1)),
                                   _mm256_min_pd(ay0, ay1));
        __m256d hi = _mm256_add_pd(_mm256_add_pd(c0, _mm256_max_pd(ax0, ax1)),
                                   _mm256_max_pd(ay0, ay1));
        const __m256d slack = _mm256_set1_pd(gr->nslack[a]);
        const __m256d lpos = _mm256_cmp_pd(lo, zero, _CMP_GE_OQ);
        const __m256d hpos = _mm256_cmp_pd(hi, zero, _CMP_GE_OQ);
        lo = _mm256_sub_pd(_mm256_blendv_pd(_mm256_mul_pd(lo, inv), lo, lpos), slack);
        hi = _mm256_add_pd(_mm256_blendv_pd(hi, _mm256_mul_pd(hi, inv), hpos), slack);
        const __m256d b0 = _mm256_set1_pd(gr->nb[a][0]), b1 = _mm256_set1_pd(gr->nb[a][1]);
        lo = _mm256_max_pd(lo, b0), hi = _mm256_min_pd(hi, b1);
        const __m256d ok = _mm256_cmp_pd(lo, hi, _CMP_LE_OQ);
        nlo[a] = _mm256_blendv_pd(b0, lo, ok);
        nhi[a] = _mm256_blendv_pd(b1, hi, ok);
    }
    nlo[2] = _mm256_set1_pd(gr->nb[2][0]), nhi[2] = _mm256_set1_pd(gr->nb[2][1]);
}

/* mr_dtrace_overlaps' x part and edge tests for four rectangles [x0, x1]
 * x [ylo, yhi] (lanes) of the lanes `lanes` (whose rows already meet T's
 * grid box): its operations lane by lane, so the same answers; returns
 * the mask of those that may overlap T. */
__attribute__((target("avx2"), always_inline)) static inline unsigned
overlaps4_avx2(const mr_dbase *b, const mr_dgrad *gr, __m256d x0, __m256d x1, __m256d ylo,
               __m256d yhi, unsigned lanes)
{
    const __m256d gx0 = _mm256_set1_pd(gr->gx0), gx1 = _mm256_set1_pd(gr->gx1);
    __m256d in = _mm256_andnot_pd(_mm256_or_pd(_mm256_cmp_pd(x1, gx0, _CMP_LT_OQ),
                                               _mm256_cmp_pd(x0, gx1, _CMP_GT_OQ)),
                                  lanes_avx2(lanes));
    const __m256d negm = _mm256_set1_pd(-b->margin);
    for (int e = 0; e < 3; e++) {
        const double *l = b->edge[e];
        const __m256d ex = _mm256_mul_pd(_mm256_set1_pd(l[0]), l[0] > 0 ? x1 : x0);
        const __m256d ey = _mm256_mul_pd(_mm256_set1_pd(l[1]), l[1] > 0 ? yhi : ylo);
        const __m256d v = _mm256_add_pd(_mm256_add_pd(ex, ey), _mm256_set1_pd(l[2]));
        in = _mm256_andnot_pd(_mm256_cmp_pd(v, negm, _CMP_LT_OQ), in);
    }
    return (unsigned)_mm256_movemask_pd(in);
}

/* local_box for four rectangles [x0, x1] x [ylo, yhi] (lanes) with heights
 * [hl, hh]: its operations lane by lane (each lane's normal bounds from its
 * own rectangle), so the same boxes, in lo and hi [axis][lane]. */
__attribute__((target("avx2"), always_inline)) static inline void
boxes4_avx2(const mr_dgrad *gr, __m256d x0, __m256d x1, __m256d ylo, __m256d yhi,
            const double hl[4], const double hh[4], double lo[3][4], double hi[3][4])
{
    const __m256d hlo = _mm256_loadu_pd(hl), hhi = _mm256_loadu_pd(hh);
    const __m256d lx0 = _mm256_max_pd(x0, _mm256_set1_pd(gr->gx0));
    const __m256d lx1 = _mm256_min_pd(x1, _mm256_set1_pd(gr->gx1));
    const __m256d ry0 = _mm256_max_pd(ylo, _mm256_set1_pd(gr->gy0));
    const __m256d ry1 = _mm256_min_pd(yhi, _mm256_set1_pd(gr->gy1));
    __m256d nlo[3], nhi[3];
    if (gr->nrect) {
        rect_normals4(gr, lx0, lx1, ry0, ry1, nlo, nhi);
    } else {
        for (int a = 0; a < 3; a++)
            nlo[a] = _mm256_set1_pd(gr->nb[a][0]), nhi[a] = _mm256_set1_pd(gr->nb[a][1]);
    }
    __m256d l[3], h[3];
    for (int a = 0; a < 3; a++) {
        const __m256d p0 = _mm256_mul_pd(hlo, nlo[a]), p1 = _mm256_mul_pd(hlo, nhi[a]);
        const __m256d p2 = _mm256_mul_pd(hhi, nlo[a]), p3 = _mm256_mul_pd(hhi, nhi[a]);
        const __m256d pad = _mm256_set1_pd(gr->lpad[a]);
        l[a] = _mm256_sub_pd(_mm256_min_pd(_mm256_min_pd(p0, p1), _mm256_min_pd(p2, p3)), pad);
        h[a] = _mm256_add_pd(_mm256_max_pd(_mm256_max_pd(p0, p1), _mm256_max_pd(p2, p3)), pad);
    }
    l[0] = _mm256_add_pd(lx0, l[0]);
    h[0] = _mm256_add_pd(lx1, h[0]);
    l[1] = _mm256_add_pd(ry0, l[1]);
    h[1] = _mm256_add_pd(ry1, h[1]);
    for (int a = 0; a < 3; a++) {
        _mm256_storeu_pd(lo[a], l[a]);
        _mm256_storeu_pd(hi[a], h[a]);
    }
}

/* tex_child_boxes with the four children in one AVX2 vector (child c in
 * lane c: column c & 1, row c >> 1), for CPUs that have it: its
 * operations lane by lane (the row's scalar y terms made per lane), so
 * the same boxes, mask and node count. */
__attribute__((target("avx2"))) static unsigned tex_child_boxes_avx2(const mr_dgrid *g,
                                                                      const mr_dbase *b,
                                                                      const mr_dgrad *gr,
                                                                      const dnode *n,
                                                                      double lo[3][4],
                                                                      double hi[3][4],
                                                                      mr_dstats *st)
{
    const int c = n->level - 1;
    const uint32_t I0 = n->I * 2, J0 = n->J * 2;
    const bool two_x = I0 + 1 < g->lw[c];
    const uint64_t s = (uint64_t)1 << c;
    const double bx = (double)n->tx * g->w, by = (double)n->ty * g->h;
    /* the rows that exist and meet T's grid box, and their y extents */
    unsigned rows = 0;
    double y0[2] = {by, by}, y1[2] = {by, by};
    for (int r = 0; r < 2; r++) {
        const uint32_t J = J0 + (uint32_t)r;
        if (J >= g->lh[c])
            break;
        if (st)
            st->nodes += two_x ? 2 : 1;
        const uint64_t ya = J * s, yb = (J + 1) * s;
        y0[r] = by + (double)ya, y1[r] = by + (double)(yb < g->h ? yb : g->h);
        if (!(y1[r] < gr->gy0 || y0[r] > gr->gy1))
            rows |= 3u << 2 * r;
    }
    if (!two_x)
        rows &= 5u;
    if (!rows)
        return 0;
    const uint64_t xa0 = I0 * s, xa1 = (I0 + 1) * s, xb1 = (I0 + 2) * s;
    const double cx0 = bx + (double)xa0, cx1 = bx + (double)xa1;
    const double dx0 = bx + (double)(xa1 < g->w ? xa1 : g->w);
    const double dx1 = bx + (double)(xb1 < g->w ? xb1 : g->w);
    const __m256d x0 = _mm256_set_pd(cx1, cx0, cx1, cx0), x1 = _mm256_set_pd(dx1, dx0, dx1, dx0);
    const __m256d ylo = _mm256_set_pd(y0[1], y0[1], y0[0], y0[0]);
    const __m256d yhi = _mm256_set_pd(y1[1], y1[1], y1[0], y1[0]);
    const unsigned inm = overlaps4_avx2(b, gr, x0, x1, ylo, yhi, rows);
    if (!inm)
        return 0;
    double hl[4] = {0}, hh[4] = {0};
    mr_dgrid_child_heights_avx2(g, (unsigned)c, I0, J0, inm, hl, hh);
    boxes4_avx2(gr, x0, x1, ylo, yhi, hl, hh, lo, hi);
    return inm;
}
#define TEX_CHILD_BOXES(g, b, gr, n, lo, hi, st)                                                   \
    (__builtin_cpu_supports("avx2") ? tex_child_boxes_avx2(g, b, gr, n, lo, hi, st)                \
                                    : tex_child_boxes(g, b, gr, n, lo, hi, st))
#else
#define TEX_CHILD_BOXES tex_child_boxes
#endif

/* The children of node n (level 1 .. the pyramid's top) the ray enters,
 * tested a row of two at a time: slab's operations lane by lane, so the
 * same children pass with the same entry distances as one by one. Passing
 * children go to out in child order; returns how many. */
static int tex_children_local(const mr_dgrid *g, const mr_dbase *b, const mr_dgrad *gr,
                              const mr_dray *lr, const dnode *n, double tmin, double tmax,
                              tentry out[4], mr_dstats *st)
{
    double lo[3][4], hi[3][4];
    unsigned mask = TEX_CHILD_BOXES(g, b, gr, n, lo, hi, st);
    int k = 0;
    for (int r = 0; r < 2; r++) {
        if (!(mask >> 2 * r & 3u))
            continue;
        __m128d in = _mm_castsi128_pd(_mm_set_epi32(mask >> (2 * r + 1) & 1u ? -1 : 0,
                                                    mask >> (2 * r + 1) & 1u ? -1 : 0,
                                                    mask >> 2 * r & 1u ? -1 : 0,
                                                    mask >> 2 * r & 1u ? -1 : 0));
        __m128d t0 = _mm_set1_pd(tmin), t1 = _mm_set1_pd(tmax);
        for (int a = 0; a < 3; a++) {
            __m128d o = _mm_set1_pd(lr->o[a]);
            __m128d l = _mm_loadu_pd(lo[a] + 2 * r), h = _mm_loadu_pd(hi[a] + 2 * r);
            if (lr->par[a]) {
                in = _mm_andnot_pd(_mm_or_pd(_mm_cmplt_pd(o, l), _mm_cmpgt_pd(o, h)), in);
                continue;
            }
            slab_axis2(l, h, o, _mm_set1_pd(lr->inv[a]), &t0, &t1);
        }
        in = _mm_andnot_pd(_mm_cmpgt_pd(t0, t1), in);
        int inm = _mm_movemask_pd(in);
        double tn[2];
        _mm_storeu_pd(tn, t0);
        for (int a = 0; a < 2; a++)
            if (inm & (1 << a))
                out[k++] = (tentry){{.d = {.level = n->level - 1, .tx = n->tx, .ty = n->ty,
                                           .I = n->I * 2 + (uint32_t)a,
                                           .J = n->J * 2 + (uint32_t)r}},
                                    tn[a]};
    }
    return k;
}
#endif

/* ---- the procedural source: squares of cells --------------------------------- */

static void pnode_rect(const pnode *n, double *x0, double *x1, double *y0, double *y1)
{
    double sz = ldexp(1.0, n->level);
    *x0 = (double)n->x * sz, *x1 = ((double)n->x + 1) * sz;
    *y0 = (double)n->y * sz, *y1 = ((double)n->y + 1) * sz;
}

static int pnode_children(const pnode *n, pnode out[4])
{
    for (int k = 0; k < 4; k++)
        out[k] = (pnode){n->level - 1, n->x * 2 + (k & 1), n->y * 2 + (k >> 1)};
    return 4;
}

/* T's roots: the squares of the lowest level where T's cells span at most
 * two per axis, in row order. */
static int proc_roots(const mr_dbase *b, pnode out[4])
{
    int64_t i0, i1, j0, j1;
    mr_dbase_cells(b, &i0, &i1, &j0, &j1);
    int level = 0;
    while (level < 62 && ((i1 >> level) - (i0 >> level) > 1 || (j1 >> level) - (j0 >> level) > 1))
        level++;
    int n = 0;
    for (int64_t y = j0 >> level; y <= (j1 >> level); y++)
        for (int64_t x = i0 >> level; x <= (i1 >> level); x++)
            out[n++] = (pnode){level, x, y};
    return n;
}

/* Node n's heights over T: its own bound (above a lattice square: the
 * global one), capped by T's (mr_dtrace_proc_roots). */
static void pnode_heights(const mr_dproc *p, const mr_dgrad *gr, const pnode *n, double *lo,
                          double *hi)
{
    if (n->level > p->top) {
        *lo = gr->hlo, *hi = gr->hhi;
        return;
    }
    mr_dproc_square_heights(p, n->level, n->x, n->y, lo, hi);
    *lo = dmax(*lo, gr->hlo), *hi = dmin(*hi, gr->hhi);
}

static mr_dproots tri_proots(const mr_dscene *s, uint32_t t)
{
    mr_dproots rs;
    if (s->proots) {
        rs = s->proots[t];
    } else {
        double lo, hi;
        mr_dtrace_proc_roots(s->proc, &s->bases[t], &rs, &lo, &hi);
    }
    return rs;
}

/* Whether node n's own bound is dear enough to be worth a test with its
 * parent's heights first: the blend bounds within a lattice square (three
 * pyramid searches a half) and the exact bound of the largest exact
 * squares (25 heights, seldom made before), not the smaller exact ones,
 * whose grid points are their parent's, just made (plane at range 512,
 * 160x90, with triforce nodes: 89 -> 73 ms with the exact ones alone, ->
 * 67 with the blend ones too). */
static inline bool worth_parent_test(const mr_dproc *p, const pnode *n)
{
    return n->level <= p->top && ((int64_t)1 << n->level) > MR_DPROC_EXACT_LEG / 2;
}

/* ---- either source ------------------------------------------------------------- */

/* T's roots in rs; returns how many. */
static int tri_tnodes(const mr_dscene *s, uint32_t t, tnode rs[4])
{
    int n;
    if (s->proc) {
        mr_dproots r = tri_proots(s, t);
        for (n = 0; n < r.n; n++)
            rs[n].p = r.r[n];
    } else {
        mr_droots r = tri_roots(s, t);
        for (n = 0; n < r.n; n++)
            rs[n].d = r.r[n];
    }
    return n;
}

/* Whether n is a leaf, and then the cell (*i, *j) and its half (0 lower, 1
 * upper, 2 both) that it stands for. */
static inline bool tnode_leaf(const mr_dscene *s, const tnode *n, int64_t *i, int64_t *j, int *half)
{
    if (s->proc) { /* a square of one cell */
        if (n->p.level != 0)
            return false;
        *i = n->p.x;
        *j = n->p.y;
        *half = 2;
        return true;
    }
    if (n->d.level != 0)
        return false;
    *i = n->d.tx * s->grid->w + n->d.I;
    *j = n->d.ty * s->grid->h + n->d.J;
    *half = 2;
    return true;
}

/* n's children; returns how many. */
static inline int tnode_children(const mr_dscene *s, const tnode *n, tnode out[4])
{
    int k;
    if (s->proc) {
        pnode c[4];
        k = pnode_children(&n->p, c);
        for (int a = 0; a < k; a++)
            out[a].p = c[a];
    } else {
        dnode c[4];
        k = children(s->grid, &n->d, c);
        for (int a = 0; a < k; a++)
            out[a].d = c[a];
    }
    return k;
}

/* n's grid rectangle. */
static inline void tnode_rect(const mr_dscene *s, const tnode *n, double *x0, double *x1,
                              double *y0, double *y1)
{
    if (s->proc)
        pnode_rect(&n->p, x0, x1, y0, y1);
    else
        node_rect(s->grid, &n->d, x0, x1, y0, y1);
}

/* n's grid rectangle and heights over T, or false when it cannot overlap
 * T. (Inlined into its two callers: called, it cost the procedural
 * sphere 4 % of its trace.) */
__attribute__((always_inline)) static inline bool
tnode_region(const mr_dscene *s, const mr_dbase *b, const mr_dgrad *gr, const tnode *n, double *x0,
             double *x1, double *y0, double *y1, double *hlo, double *hhi, mr_dstats *st)
{
    tnode_rect(s, n, x0, x1, y0, y1);
    if (st)
        st->nodes++;
    if (!mr_dtrace_overlaps(b, gr, *x0, *x1, *y0, *y1))
        return false;
    if (s->proc)
        pnode_heights(s->proc, gr, &n->p, hlo, hhi);
    else
        node_heights(s->grid, &n->d, hlo, hhi);
    return true;
}

/* The nodes of nodes[0 .. n) that may overlap T and the ray enters before
 * tmax (cull_limit), with their entry distances, in order; returns how
 * many. */
static int tnodes_entered(const mr_dscene *s, const mr_dbase *b, const mr_dgrad *gr,
                          const mr_dray *r, const mr_dray *lr, const tnode *nodes, int n,
                          float tmin, float tmax, tentry out[4], mr_dstats *st)
{
    int nh = 0;
    for (int k = 0; k < n; k++) {
        double x0, x1, y0, y1, hlo, hhi, tn;
        if (tnode_region(s, b, gr, &nodes[k], &x0, &x1, &y0, &y1, &hlo, &hhi, st) &&
            node_hit(b, gr, r, lr, x0, x1, y0, y1, hlo, hhi, tmin, cull_limit(tmax), &tn))
            out[nh++] = (tentry){nodes[k], tn};
    }
    return nh;
}

/* ---- a base triangle's nodes, once per object ------------------------------------ */

/* Nodes a base triangle's height bound splits its region into at most. */
#define BOUND_NODES 256

/* The union of the height bounds of nodes n[0 .. count) of the texture g
 * or, p not NULL, the procedural source (squares: its global bound). */
static void tnodes_heights(const mr_dgrid *g, const mr_dproc *p, const tnode *n, int count,
                           double *lo, double *hi)
{
    double glo = 0, ghi = 0;
    if (p)
        mr_dproc_global_heights(p, &glo, &ghi);
    *lo = INFINITY, *hi = -INFINITY;
    for (int k = 0; k < count; k++) {
        double l = glo, h = ghi;
        if (!p)
            node_heights(g, &n[k].d, &l, &h);
        else
            mr_dproc_square_heights(p, n[k].p.level, n[k].p.x, n[k].p.y, &l, &h);
        *lo = fmin(*lo, l), *hi = fmax(*hi, h);
    }
}

/* T's nodes below roots[0 .. n), a level at a time, those the overlap test
 * passes while they number at most BOUND_NODES: *hlo, *hhi the tightest
 * of the levels' height bounds (each holds T's heights, so their
 * intersection does) and T's corner heights; deep[0 .. *ndeep) the
 * deepest level of at most four nodes. */
static void nodes_below(const mr_dgrid *g, const mr_dproc *p, const mr_dbase *b,
                        const tnode roots[4], int n, double *hlo, double *hhi, tnode deep[4],
                        int *ndeep)
{
    static _Thread_local tnode cur[BOUND_NODES], next[BOUND_NODES];
    memcpy(cur, roots, (size_t)n * sizeof *cur);
    double gx0, gx1, gy0, gy1;
    tri_gbox(b, &gx0, &gx1, &gy0, &gy1);
    *ndeep = n;
    memcpy(deep, cur, (size_t)n * sizeof *cur);
    tnodes_heights(g, p, cur, n, hlo, hhi);
    const mr_dscene src = {.grid = g, .proc = p}; /* (the source alone) */
    int64_t li, lj;
    int lh;
    while (n > 0 && !tnode_leaf(&src, &cur[0], &li, &lj, &lh)) { /* down to the leaves */
        int m = 0;
        for (int k = 0; k < n && m >= 0; k++) {
            tnode ch[4];
            int nc = tnode_children(&src, &cur[k], ch);
            for (int c = 0; c < nc && m >= 0; c++) {
                double x0, x1, y0, y1;
                tnode_rect(&src, &ch[c], &x0, &x1, &y0, &y1);
                if (!rect_overlaps(b, gx0, gx1, gy0, gy1, x0, x1, y0, y1))
                    continue;
                if (m == BOUND_NODES)
                    m = -1; /* too many: stop at this level */
                else
                    next[m++] = ch[c];
            }
        }
        if (m <= 0)
            break; /* (m = 0: cells T only touches; the level above keeps them) */
        memcpy(cur, next, (size_t)m * sizeof *cur);
        n = m;
        if (n <= 4) {
            *ndeep = n;
            memcpy(deep, cur, (size_t)n * sizeof *cur);
        }
        double lo, hi;
        tnodes_heights(g, p, cur, n, &lo, &hi);
        *hlo = fmax(*hlo, lo), *hhi = fmin(*hhi, hi);
    }
    if (n == 0) /* no cells: a degenerate box; the corners' heights */
        *hlo = INFINITY, *hhi = -INFINITY;
    for (int k = 0; k < 3; k++)
        *hlo = fmin(*hlo, b->h[k]), *hhi = fmax(*hhi, b->h[k]);
}

void mr_dtrace_root_heights(const mr_dgrid *g, const mr_dbase *b, double *hlo, double *hhi)
{
    dnode r[4];
    tnode rs[4], deep[4];
    int n = roots(g, b, r), nd;
    for (int k = 0; k < n; k++)
        rs[k].d = r[k];
    nodes_below(g, NULL, b, rs, n, hlo, hhi, deep, &nd);
}

void mr_dtrace_proc_roots(const mr_dproc *p, const mr_dbase *b, mr_dproots *out, double *hlo,
                          double *hhi)
{
    pnode r[4];
    tnode rs[4], deep[4];
    int n = proc_roots(b, r);
    for (int k = 0; k < n; k++)
        rs[k].p = r[k];
    nodes_below(NULL, p, b, rs, n, hlo, hhi, deep, &out->n);
    for (int k = 0; k < out->n; k++)
        out->r[k] = deep[k].p;
}

bool mr_dtrace_intersect(const mr_dscene *s, uint32_t t, const mr_dray *r, float tmin, float *tmax,
                         bool any, mr_dhit *hit, mr_dstats *st)
{
    const mr_dbase *b = &s->bases[t];
    const mr_dgrad *gr = &s->grads[t];
    const mr_dgrid *g = s->grid;
    best bh = {0};
    if (b->flat) {
        flat_leaf(s, b, r, tmin, tmax, &bh, st);
        if (bh.hit)
            finish(b, &bh, hit);
        return bh.hit;
    }
    if (gr->ob && !oriented_hit(gr, r, tmin, cull_limit(*tmax)))
        return false;
    mr_dray lr;
    if (gr->local)
        local_ray(gr, b, r, &lr);
    tentry stack[STACK_MAX];
    int sp = 0;
    {
        /* the roots the ray enters, nearest first: at coarse levels they
         * are the cells themselves, whose micro-triangles a ray would
         * otherwise test without a box */
        tnode rs[4];
        int nr = tri_tnodes(s, t, rs);
        tentry hitc[4];
        int nh = tnodes_entered(s, b, gr, r, &lr, rs, nr, tmin, *tmax, hitc, st);
        PUSH_NEAREST_LAST(stack, sp, hitc, nh);
    }
    while (sp > 0) {
        tentry e = stack[--sp];
        if (e.tnear > cull_limit(*tmax))
            continue;
        int64_t i, j;
        int half;
        if (tnode_leaf(s, &e.n, &i, &j, &half)) {
            leaf(s, t, b, i, j, half, r, tmin, tmax, &bh, st);
            if (bh.hit && any)
                break;
            continue;
        }
        tentry hitc[4];
        int nh = 0;
#if defined(__SSE2__)
        if (!s->proc && gr->local && e.n.d.level <= (int)g->levels) {
            nh = tex_children_local(g, b, gr, &lr, &e.n.d, tmin, cull_limit(*tmax), hitc, st);
        } else
#endif
        {
            tnode ch[4];
            int nc = tnode_children(s, &e.n, ch);
            nh = tnodes_entered(s, b, gr, r, &lr, ch, nc, tmin, *tmax, hitc, st);
        }
        PUSH_NEAREST_LAST(stack, sp, hitc, nh);
    }
    if (bh.hit)
        finish(b, &bh, hit);
    return bh.hit;
}

/* ---- packets of rays -------------------------------------------------------------- */

#define PK MR_DPACKET_MAX

/* The packet's rays in T's local frame, lane by lane (a lane outside the
 * packet never passes: t0 > t1), and each ray's current [tmin, tmax]. */
typedef struct pack {
    double o[3][PK], inv[3][PK];
    double d[2][PK]; /* x and y of the direction (packet_footprint) */
    double t0[PK], t1[PK];
    double s0[PK], s1[PK]; /* the part of each span inside T's box (tbox_lanes) */
} pack;

typedef struct pentry {
    tnode n;
    uint32_t mask;   /* the rays that entered the node */
    double tnear;    /* the nearest of their entries */
    double hlo, hhi; /* its heights (procedural source: they bound its children's) */
} pentry;

/* The nearest entry distance among the rays `in` (entries tn). */
static inline double nearest_entry(uint32_t in, const double tn[PK])
{
    double near = INFINITY;
    for (uint32_t m = in; m; m &= m - 1) {
        int k = __builtin_ctz(m);
        near = tn[k] < near ? tn[k] : near;
    }
    return near;
}

/* The packet's rays `live` into the box lo..hi: the slab of one ray, lane
 * by lane; returns the rays that enter, and the nearest of their entry
 * distances in *near. */
static uint32_t slab_pack(const pack *p, uint32_t live, const double lo[3], const double hi[3],
                          double *near)
{
    double tn[PK];
    uint32_t m = 0;
    for (int k = 0; k < PK; k += 2) {
        if (!(live >> k & 3u))
            continue;
#if defined(__SSE2__)
        __m128d t0 = _mm_loadu_pd(p->t0 + k), t1 = _mm_loadu_pd(p->t1 + k);
        for (int a = 0; a < 3; a++)
            slab_axis2(_mm_set1_pd(lo[a]), _mm_set1_pd(hi[a]), _mm_loadu_pd(p->o[a] + k),
                       _mm_loadu_pd(p->inv[a] + k), &t0, &t1);
        _mm_storeu_pd(tn + k, t0);
        m |= (uint32_t)(~_mm_movemask_pd(_mm_cmpgt_pd(t0, t1)) & 3) << k;
#else
        for (int q = k; q < k + 2; q++) {
            double t0 = p->t0[q], t1 = p->t1[q];
            for (int a = 0; a < 3; a++) {
                double nn = (lo[a] - p->o[a][q]) * p->inv[a][q];
                double ff = (hi[a] - p->o[a][q]) * p->inv[a][q];
                double near = ff < nn ? ff : nn, far = nn > ff ? nn : ff;
                far *= 1 + 4 * DBL_EPSILON;
                t0 = near > t0 ? near : t0;
                t1 = far < t1 ? far : t1;
            }
            tn[q] = t0;
            m |= (uint32_t)!(t0 > t1) << q;
        }
#endif
    }
    m &= live;
    *near = nearest_entry(m, tn);
    return m;
}

#if defined(__x86_64__) && defined(__GNUC__)
/* Lanes k .. k + 3 of the packet against the box lo..hi (AVX2): slab's
 * operations lane by lane narrow each lane's entry and exit from p->t0
 * and p->t1 into *t0 and *t1; returns the lanes of `lanes` (bit q: lane k
 * + q) that enter (0 at once, *t0 and *t1 unset, when `lanes` is 0). */
__attribute__((target("avx2"))) static inline uint32_t slab_quad_avx2(const pack *p, int k,
                                                                       uint32_t lanes,
                                                                       const double lo[3],
                                                                       const double hi[3],
                                                                       __m256d *t0, __m256d *t1)
{
    if (!lanes)
        return 0;
    *t0 = _mm256_loadu_pd(p->t0 + k), *t1 = _mm256_loadu_pd(p->t1 + k);
    for (int a = 0; a < 3; a++) {
        __m256d o = _mm256_loadu_pd(p->o[a] + k), inv = _mm256_loadu_pd(p->inv[a] + k);
        __m256d nn = _mm256_mul_pd(_mm256_sub_pd(_mm256_set1_pd(lo[a]), o), inv);
        __m256d ff = _mm256_mul_pd(_mm256_sub_pd(_mm256_set1_pd(hi[a]), o), inv);
        __m256d n = _mm256_min_pd(ff, nn), far = _mm256_max_pd(nn, ff);
        far = _mm256_mul_pd(far, _mm256_set1_pd(1 + 4 * DBL_EPSILON)); /* Ize 2013 */
        *t0 = _mm256_max_pd(n, *t0);
        *t1 = _mm256_min_pd(far, *t1);
    }
    return (uint32_t)~_mm256_movemask_pd(_mm256_cmp_pd(*t0, *t1, _CMP_GT_OQ)) & lanes;
}

/* slab_pack four lanes at a time, for CPUs with AVX2: the same operations
 * lane by lane as the SSE2 loop (sub, mul, minpd / maxpd, the far bound's
 * scaling, an ordered greater-than), so the same entries and the same
 * lanes bit for bit; half its instructions, in the displaced kind's
 * hottest loop. */
__attribute__((target("avx2"))) static uint32_t slab_pack_avx2(const pack *p, uint32_t live,
                                                                const double lo[3],
                                                                const double hi[3], double *near)
{
    _Static_assert(PK % 4 == 0, "packets are whole AVX2 vectors");
    const __m256d inf = _mm256_set1_pd(INFINITY);
    __m256d nearv = inf;
    uint32_t m = 0;
    for (int k = 0; k < PK; k += 4) {
        __m256d t0, t1;
        const uint32_t in = slab_quad_avx2(p, k, live >> k & 15u, lo, hi, &t0, &t1);
        if (!in)
            continue;
        m |= in << k;
        /* the nearest entry of the lanes that enter: min_pd is
         * a < b ? a : b, nearest_entry's rule (a NaN entry never wins) */
        nearv = _mm256_min_pd(_mm256_blendv_pd(inf, t0, lanes_avx2(in)), nearv);
    }
    /* (no lane of nearv is NaN: the least of its four in registers) */
    __m128d two = _mm_min_pd(_mm256_castpd256_pd128(nearv), _mm256_extractf128_pd(nearv, 1));
    *near = _mm_cvtsd_f64(_mm_min_sd(two, _mm_unpackhi_pd(two, two)));
    return m;
}
#define SLAB_PACK(p, live, lo, hi, near)                                                          \
    (__builtin_cpu_supports("avx2") ? slab_pack_avx2(p, live, lo, hi, near)                       \
                                    : slab_pack(p, live, lo, hi, near))

/* The packet's rays `live` into a node's four child boxes at once, ray by
 * ray (AVX2): box c (lo[.][c], hi[.][c]) in vector lane c, each ray's
 * numbers broadcast. For every ray and box these are slab_quad_avx2's
 * operations in its order, so in[c] and near[c] are what
 * slab_pack_avx2(p, live, box c) returns, bit for bit (the nearest entry
 * is a min over the same entries, and min_pd never lets a NaN in). A
 * node's rays are few and spread over the packet's quads (a camera
 * packet is 4 x 4 pixels), so one pass per ray does fewer operations
 * than one pass per box over every quad holding a ray. */
__attribute__((target("avx2"))) static void slab_four_avx2(const pack *p, uint32_t live,
                                                            const double lo[3][4],
                                                            const double hi[3][4], uint32_t in[4],
                                                            double near[4])
{
    const __m256d inf = _mm256_set1_pd(INFINITY), grow = _mm256_set1_pd(1 + 4 * DBL_EPSILON);
    __m256d l[3], h[3];
    for (int a = 0; a < 3; a++)
        l[a] = _mm256_loadu_pd(lo[a]), h[a] = _mm256_loadu_pd(hi[a]);
    __m256d nearv = inf;
    __m256i ins = _mm256_setzero_si256(); /* box c's rays in lane c: bit k, ray k */
    for (uint32_t m = live; m; m &= m - 1) {
        const int k = __builtin_ctz(m);
        __m256d t0 = _mm256_broadcast_sd(p->t0 + k), t1 = _mm256_broadcast_sd(p->t1 + k);
        for (int a = 0; a < 3; a++) {
            const __m256d o = _mm256_broadcast_sd(p->o[a] + k);
            const __m256d inv = _mm256_broadcast_sd(p->inv[a] + k);
            const __m256d nn = _mm256_mul_pd(_mm256_sub_pd(l[a], o), inv);
            const __m256d ff = _mm256_mul_pd(_mm256_sub_pd(h[a], o), inv);
            const __m256d n = _mm256_min_pd(ff, nn);
            const __m256d far = _mm256_mul_pd(_mm256_max_pd(nn, ff), grow); /* Ize 2013 */
            t0 = _mm256_max_pd(n, t0);
            t1 = _mm256_min_pd(far, t1);
        }
        /* enters: not t0 > t1 (ordered), slab_quad_avx2's rule */
        const __m256d enters = _mm256_cmp_pd(t0, t1, _CMP_NGT_UQ);
        nearv = _mm256_min_pd(_mm256_blendv_pd(inf, t0, enters), nearv);
        ins = _mm256_or_si256(ins, _mm256_and_si256(_mm256_castpd_si256(enters),
                                                    _mm256_set1_epi64x((int64_t)1 << k)));
    }
    uint64_t w[4];
    _mm256_storeu_si256((__m256i *)w, ins);
    for (int c = 0; c < 4; c++)
        in[c] = (uint32_t)w[c];
    _mm256_storeu_pd(near, nearv);
}

/* slab_four_avx2 two rays a pass, for CPUs with AVX-512: lanes 0-3 the
 * four boxes against one ray, lanes 4-7 against the next (the last ray of
 * an odd count twice), each lane the same operations in the same order,
 * so the same rays enter the same boxes. The nearest entries of the two
 * halves are joined at the end: a min over the same entries, which may
 * only differ from the one-ray-a-pass order in the sign of a zero, and an
 * entry distance is only ever compared. */
__attribute__((target("avx512f"))) static void slab_four_avx512(const pack *p, uint32_t live,
                                                                 const double lo[3][4],
                                                                 const double hi[3][4],
                                                                 uint32_t in[4], double near[4])
{
    const __m512d grow = _mm512_set1_pd(1 + 4 * DBL_EPSILON);
    __m512d l[3], h[3];
    for (int a = 0; a < 3; a++)
        l[a] = _mm512_broadcast_f64x4(_mm256_loadu_pd(lo[a])),
        h[a] = _mm512_broadcast_f64x4(_mm256_loadu_pd(hi[a]));
    __m512d nearv = _mm512_set1_pd(INFINITY);
    __m512i ins = _mm512_setzero_si512();
    for (uint32_t m = live; m;) {
        const int ka = __builtin_ctz(m);
        m &= m - 1;
        const int kb = m ? __builtin_ctz(m) : ka;
        m &= m - 1;
/* ray ka's value of q in lanes 0-3, ray kb's in lanes 4-7 */
#define PAIR(q) _mm512_insertf64x4(_mm512_set1_pd((q)[ka]), _mm256_set1_pd((q)[kb]), 1)
        __m512d t0 = PAIR(p->t0), t1 = PAIR(p->t1);
        for (int a = 0; a < 3; a++) {
            const __m512d o = PAIR(p->o[a]), inv = PAIR(p->inv[a]);
            const __m512d nn = _mm512_mul_pd(_mm512_sub_pd(l[a], o), inv);
            const __m512d ff = _mm512_mul_pd(_mm512_sub_pd(h[a], o), inv);
            const __m512d n = _mm512_min_pd(ff, nn);
            const __m512d far = _mm512_mul_pd(_mm512_max_pd(nn, ff), grow);
            t0 = _mm512_max_pd(n, t0);
            t1 = _mm512_min_pd(far, t1);
        }
#undef PAIR
        const __mmask8 e = _mm512_cmp_pd_mask(t0, t1, _CMP_NGT_UQ);
        nearv = _mm512_mask_min_pd(nearv, e, t0, nearv);
        const __m512i bits = _mm512_inserti64x4(_mm512_set1_epi64((int64_t)1 << ka),
                                                _mm256_set1_epi64x((int64_t)1 << kb), 1);
        ins = _mm512_mask_or_epi64(ins, e, ins, bits);
    }
    const __m256i both = _mm256_or_si256(_mm512_castsi512_si256(ins), _mm512_extracti64x4_epi64(ins, 1));
    uint64_t w[4];
    _mm256_storeu_si256((__m256i *)w, both);
    for (int c = 0; c < 4; c++)
        in[c] = (uint32_t)w[c];
    _mm256_storeu_pd(near, _mm256_min_pd(_mm512_castpd512_pd256(nearv),
                                         _mm512_extractf64x4_pd(nearv, 1)));
}

/* The packet's rays `live` into four boxes at once (slab_four_avx2 or
 * _avx512, the same answers); for CPUs with AVX2. */
__attribute__((target("avx2"))) static inline void slab_four(const pack *p, uint32_t live,
                                                              const double lo[3][4],
                                                              const double hi[3][4], uint32_t in[4],
                                                              double near[4])
{
    if (mr_simd_avx512())
        slab_four_avx512(p, live, lo, hi, in, near);
    else
        slab_four_avx2(p, live, lo, hi, in, near);
}
#define HAS_SLAB_FOUR 1

/* The boxes of procedural square e->n's four children (child c: column c
 * & 1, row c >> 1; level 0 .. ) in T's local frame, four lanes at once
 * (AVX2): what tnode_region and local_box make for each child one by one.
 * A child whose own bound is dear and not at hand (worth_parent_test) is
 * first boxed with its parent's heights, which bound its own: when none of
 * the packet's rays `live` enters that box, its bound is not made and it
 * is dropped (p NULL: no such test, every child's own bound made). Returns
 * the mask of children boxed (their heights, capped by T's, in hl and
 * hh); the children in out. */
__attribute__((target("avx2"))) static unsigned proc_child_boxes_avx2(
    const mr_dproc *pr, const mr_dbase *b, const mr_dgrad *gr, const pentry *e, const pack *p,
    uint32_t live, tnode out[4], double lo[3][4], double hi[3][4], double hl[4], double hh[4],
    mr_dstats *st)
{
    const pnode *n = &e->n.p;
    const int c = n->level - 1;
    const double side = (double)((uint64_t)1 << c);
    unsigned rows = 0;
    double y0[2], y1[2];
    for (int r = 0; r < 2; r++) {
        y0[r] = (double)(n->y * 2 + r) * side, y1[r] = y0[r] + side;
        if (!(y1[r] < gr->gy0 || y0[r] > gr->gy1))
            rows |= 3u << 2 * r;
    }
    for (int k = 0; k < 4; k++)
        out[k].p = (pnode){c, n->x * 2 + (k & 1), n->y * 2 + (k >> 1)};
    if (st)
        st->nodes += 4;
    if (!rows)
        return 0;
    const double cx0 = (double)(n->x * 2) * side, cx1 = cx0 + side, dx1 = cx1 + side;
    const __m256d x0 = _mm256_set_pd(cx1, cx0, cx1, cx0), x1 = _mm256_set_pd(dx1, cx1, dx1, cx1);
    const __m256d ylo = _mm256_set_pd(y0[1], y0[1], y0[0], y0[0]);
    const __m256d yhi = _mm256_set_pd(y1[1], y1[1], y1[0], y1[0]);
    unsigned inm = overlaps4_avx2(b, gr, x0, x1, ylo, yhi, rows);
    if (!inm)
        return 0;
    if (n->level <= pr->top && ((int64_t)1 << n->level) <= MR_DPROC_EXACT_LEG) {
        /* exact bounds from one tile of heights (cheap: no parent test) */
        mr_dproc_child_heights(pr, n->level, n->x, n->y, hl, hh);
    } else {
        /* the bounds at hand; the children whose bounds are to be made */
        unsigned make = 0, test = 0;
        const bool tighter = p && (e->hlo > gr->hlo || e->hhi < gr->hhi);
        for (unsigned m = inm; m; m &= m - 1) {
            const unsigned k = (unsigned)__builtin_ctz(m);
            if (c > pr->top) {
                hl[k] = gr->hlo, hh[k] = gr->hhi;
            } else if (!mr_dproc_square_heights_kept(pr, c, out[k].p.x, out[k].p.y, &hl[k],
                                                     &hh[k])) {
                make |= 1u << k;
                if (tighter && worth_parent_test(pr, &out[k].p))
                    test |= 1u << k;
            }
        }
        if (test) { /* the parent's heights first */
            double ph[4] = {e->hlo, e->hlo, e->hlo, e->hlo};
            double pH[4] = {e->hhi, e->hhi, e->hhi, e->hhi};
            uint32_t in[4];
            double near[4];
            boxes4_avx2(gr, x0, x1, ylo, yhi, ph, pH, lo, hi);
            slab_four(p, live, lo, hi, in, near);
            for (unsigned m = test; m; m &= m - 1) {
                const unsigned k = (unsigned)__builtin_ctz(m);
                if (!in[k])
                    inm &= ~(1u << k), make &= ~(1u << k);
            }
        }
        for (unsigned m = make; m; m &= m - 1) {
            const unsigned k = (unsigned)__builtin_ctz(m);
            mr_dproc_square_heights(pr, c, out[k].p.x, out[k].p.y, &hl[k], &hh[k]);
        }
    }
    for (unsigned m = inm; m; m &= m - 1) {
        const unsigned k = (unsigned)__builtin_ctz(m);
        hl[k] = dmax(hl[k], gr->hlo), hh[k] = dmin(hh[k], gr->hhi);
    }
    boxes4_avx2(gr, x0, x1, ylo, yhi, hl, hh, lo, hi);
    return inm;
}

/* proc_child_boxes_avx2 for base triangle t of scene s, its squares'
 * children kept in the thread's cache (node_boxes: made without the
 * parent test, which saves bounds only for the one packet); the same
 * children and boxes, as many children boxed or more, read where they are
 * kept (copying them out cost the procedural plane at range 64 1.5 %);
 * NULL when the thread keeps nothing. */
__attribute__((target("avx2"))) static const node_boxes *proc_child_boxes_kept(
    const mr_dscene *s, uint32_t t, const mr_dbase *b, const mr_dgrad *gr, const pentry *e,
    tnode out[4], mr_dstats *st)
{
    walk_cache *wc = walk_cache_of(s);
    if (!wc)
        return NULL;
    const pnode *n = &e->n.p;
    const walk_key k = {.pose = s->pose, .t = t, .x = n->x, .y = n->y, .which = n->level};
    const uint64_t h = walk_hash(t, n->x, n->y, n->level);
    size_t w;
    const bool kept = walk_find(wc, wc->node_sets, wc->node_keys, NODE_SETS, h, &k, &w);
    node_boxes *nb = &wc->nodes[w];
    if (kept) {
        for (int c = 0; c < 4; c++)
            out[c].p = (pnode){n->level - 1, n->x * 2 + (c & 1), n->y * 2 + (c >> 1)};
        if (st)
            st->nodes += 4; /* (as proc_child_boxes_avx2 counts them) */
    } else {
        nb->boxed = proc_child_boxes_avx2(s->proc, b, gr, e, NULL, 0, out, nb->lo, nb->hi, nb->hl,
                                          nb->hh, st);
    }
    return nb;
}
#else
#define SLAB_PACK slab_pack
#define HAS_SLAB_FOUR 0
#endif

#if defined(__x86_64__) && defined(__GNUC__)
/* rays_before for CPUs with AVX-512: the packet's spans in two loads (the
 * same comparisons), eight lanes each, as spans_after_avx512 writes them. */
__attribute__((target("avx512f"))) static inline uint32_t rays_before_avx512(const pack *p,
                                                                             uint32_t mask,
                                                                             double tnear)
{
    const __m512d tv = _mm512_set1_pd(tnear);
    const uint32_t past = (uint32_t)_mm512_cmp_pd_mask(tv, _mm512_loadu_pd(p->t1), _CMP_GT_OQ) |
                          (uint32_t)_mm512_cmp_pd_mask(tv, _mm512_loadu_pd(p->t1 + 8), _CMP_GT_OQ) << 8;
    return mask & ~past;
}
#endif

/* The rays of mask whose tmax (p->t1: its cull_limit) a node entered at
 * tnear does not lie beyond. */
static inline uint32_t rays_before(const pack *p, uint32_t mask, double tnear)
{
#if defined(__x86_64__) && defined(__GNUC__)
    _Static_assert(PK == 16, "two vectors of eight");
    if (mr_simd_avx512())
        return rays_before_avx512(p, mask, tnear);
#endif
    uint32_t past = 0;
#if defined(__SSE2__)
    const __m128d tv = _mm_set1_pd(tnear);
    for (int k = 0; k < PK; k += 2)
        past |= (uint32_t)_mm_movemask_pd(_mm_cmpgt_pd(tv, _mm_loadu_pd(p->t1 + k))) << k;
#else
    for (int k = 0; k < PK; k++)
        past |= (uint32_t)(tnear > p->t1[k]) << k;
#endif
    return mask & ~past;
}

/* A ray of world origin o and direction d in T's local frame (local_ray)
 * into lane k of the packet; false when it is parallel to a local axis
 * (slab's parallel case goes alone: the lane is left holding zeros, as
 * slab_pack tests whole pairs). */
static bool pack_lane(const mr_dgrad *gr, const mr_dbase *b, const double o[3], const double d[3],
                      pack *p, int k)
{
    mr_dray w, lr;
    for (int a = 0; a < 3; a++)
        w.o[a] = o[a], w.d[a] = d[a];
    local_ray(gr, b, &w, &lr);
    const bool par = lr.par[0] || lr.par[1] || lr.par[2];
    for (int a = 0; a < 3; a++)
        p->o[a][k] = par ? 0 : lr.o[a], p->inv[a][k] = par ? 0 : lr.inv[a];
    for (int a = 0; a < 2; a++)
        p->d[a][k] = par ? 0 : lr.d[a];
    return !par;
}

/* Lanes `lanes` of a callback's rays (rays->n <= PK of them: the packet's
 * lanes of the same numbers) in T's local frame into the packet; returns
 * those that can go in it (pack_lane). Every other lane holds zeros. The
 * same numbers as local_ray on the rays' set-ups: mr_dray_setup widens the
 * same floats. */
static uint32_t pack_lanes(const mr_dgrad *gr, const mr_dbase *b, const mr_drays *rays,
                           uint32_t lanes, pack *p)
{
    uint32_t in = 0;
    for (int k = 0; k < PK; k++) {
        if (lanes >> k & 1u) {
            const double o[3] = {rays->o[0][k], rays->o[1][k], rays->o[2][k]};
            const double d[3] = {rays->d[0][k], rays->d[1][k], rays->d[2][k]};
            in |= (uint32_t)pack_lane(gr, b, o, d, p, k) << k;
            continue;
        }
        for (int a = 0; a < 3; a++)
            p->o[a][k] = p->inv[a][k] = 0;
        p->d[0][k] = p->d[1][k] = 0;
    }
    return in;
}

#if defined(__x86_64__) && defined(__GNUC__)
/* Four rays' world origins o and directions d into lanes k .. k + 3 of
 * the pack (AVX2): local_ray's operations in its order lane by lane (no
 * fused multiply-add), so the same lanes bit for bit; returns the lanes
 * (bit q: lane k + q) parallel to an axis of the local frame. */
__attribute__((target("avx2"))) static inline uint32_t local_quad_avx2(const mr_dgrad *gr,
                                                                        const mr_dbase *b,
                                                                        const __m256d o[3],
                                                                        const __m256d d[3],
                                                                        pack *p, int k)
{
    __m256d od[3];
    for (int c = 0; c < 3; c++)
        od[c] = _mm256_sub_pd(o[c], _mm256_set1_pd(gr->P0[c]));
    __m256d par = _mm256_setzero_pd();
    for (int a = 0; a < 3; a++) {
        __m256d i0 = _mm256_set1_pd(gr->inv[a][0]), i1 = _mm256_set1_pd(gr->inv[a][1]);
        __m256d i2 = _mm256_set1_pd(gr->inv[a][2]);
        __m256d lo = _mm256_add_pd(_mm256_mul_pd(i0, od[0]), _mm256_mul_pd(i1, od[1]));
        __m256d ld = _mm256_add_pd(_mm256_mul_pd(i0, d[0]), _mm256_mul_pd(i1, d[1]));
        lo = _mm256_add_pd(lo, _mm256_mul_pd(i2, od[2]));
        ld = _mm256_add_pd(ld, _mm256_mul_pd(i2, d[2]));
        if (a < 2)
            lo = _mm256_add_pd(lo, _mm256_set1_pd(b->g[0][a]));
        __m256d zero = _mm256_cmp_pd(ld, _mm256_setzero_pd(), _CMP_EQ_OQ);
        par = _mm256_or_pd(par, zero);
        __m256d inv = _mm256_andnot_pd(zero, _mm256_div_pd(_mm256_set1_pd(1.0), ld));
        _mm256_storeu_pd(p->o[a] + k, lo);
        _mm256_storeu_pd(p->inv[a] + k, inv);
        if (a < 2)
            _mm256_storeu_pd(p->d[a] + k, ld);
    }
    return (uint32_t)_mm256_movemask_pd(par);
}

#endif

/* Whether base triangle t's rays go through mr_dtrace_intersect_packet's
 * packets (dtrace.h): a shaped, local T with micro-triangle leaves. */
static bool packs(const mr_dscene *s, const mr_dbase *b, const mr_dgrad *gr)
{
    return !b->flat && gr->local && s->local == MR_DLOCAL_TRIANGLES;
}

/* The lanes of `live` whose rays enter T's box (gr->tlo .. thi) within
 * their spans, and the part of each span inside it into p->s0, p->s1:
 * slab_pack's test lane by lane (a NaN lane is kept, as slab_pack keeps
 * it). Every micro-vertex lies in that box, so a ray that misses it
 * misses T. */
static uint32_t tbox_lanes(const mr_dgrad *gr, pack *p, uint32_t live)
{
    uint32_t in = 0;
    for (uint32_t m = live; m; m &= m - 1) {
        const int k = __builtin_ctz(m);
        double t0 = p->t0[k], t1 = p->t1[k];
        for (int a = 0; a < 3; a++) {
            double nn = (gr->tlo[a] - p->o[a][k]) * p->inv[a][k];
            double ff = (gr->thi[a] - p->o[a][k]) * p->inv[a][k];
            t0 = dmax(dmin(ff, nn), t0);
            t1 = dmin(dmax(nn, ff) * (1 + 4 * DBL_EPSILON), t1);
        }
        p->s0[k] = t0, p->s1[k] = t1;
        in |= (uint32_t)!(t0 > t1) << k;
    }
    return in;
}

/* The lanes `lanes` of a callback's rays in T's local frame with their
 * spans [tmin, cull_limit(tmax)] (pack_lanes), and those of them whose
 * rays enter T's box (tbox_lanes), which it returns; the lanes that went
 * into the packet go to *packed. Every other lane's span is empty. */
static uint32_t pack_enter(const mr_dgrad *gr, const mr_dbase *b, const mr_drays *rays,
                           uint32_t lanes, pack *p, uint32_t *packed)
{
    for (int k = 0; k < PK; k++)
        p->t0[k] = INFINITY, p->t1[k] = -INFINITY;
    const uint32_t in = pack_lanes(gr, b, rays, lanes, p);
    for (uint32_t m = in; m; m &= m - 1) {
        const int k = __builtin_ctz(m);
        p->t0[k] = rays->tmin[k];
        p->t1[k] = cull_limit(rays->tmax[k]);
    }
    const uint32_t near = tbox_lanes(gr, p, in);
    for (uint32_t m = in & ~near; m; m &= m - 1)
        p->t1[__builtin_ctz(m)] = -INFINITY;
    *packed = in;
    return near;
}

#if defined(__x86_64__) && defined(__GNUC__)
/* pack_enter four lanes at a time, for CPUs with AVX2 (rays->n a multiple
 * of four): local_quad_avx2, the spans (cull_limit's operations) and
 * slab_quad_avx2's test of T's box, one quad after another, so each test
 * reads what the step before just wrote; the same lanes and numbers. A
 * quad with no lane holds zeros and empty spans. */
__attribute__((target("avx2"))) static uint32_t pack_enter_avx2(const mr_dgrad *gr,
                                                                 const mr_dbase *b,
                                                                 const mr_drays *rays,
                                                                 uint32_t lanes, pack *p,
                                                                 uint32_t *packed)
{
    const __m256d inf = _mm256_set1_pd(INFINITY), ninf = _mm256_set1_pd(-INFINITY);
    uint32_t in = 0, near = 0;
    for (int k = 0; k < PK; k += 4) {
        const uint32_t lq = lanes >> k & 15u;
        if (!lq) {
            const __m256d zero = _mm256_setzero_pd();
            for (int a = 0; a < 3; a++) {
                _mm256_storeu_pd(p->o[a] + k, zero), _mm256_storeu_pd(p->inv[a] + k, zero);
                if (a < 2)
                    _mm256_storeu_pd(p->d[a] + k, zero);
            }
            _mm256_storeu_pd(p->t0 + k, inf), _mm256_storeu_pd(p->t1 + k, ninf);
            continue;
        }
        __m256d o[3], d[3];
        for (int a = 0; a < 3; a++) {
            o[a] = _mm256_cvtps_pd(_mm_loadu_ps(rays->o[a] + k));
            d[a] = _mm256_cvtps_pd(_mm_loadu_ps(rays->d[a] + k));
        }
        const uint32_t iq = ~local_quad_avx2(gr, b, o, d, p, k) & lq;
        const __m256d sel = lanes_avx2(iq);
        const __m256d tmax = _mm256_cvtps_pd(_mm_loadu_ps(rays->tmax + k));
        const __m256d lim = _mm256_add_pd(
            tmax, _mm256_mul_pd(_mm256_andnot_pd(_mm256_set1_pd(-0.0), tmax),
                                _mm256_set1_pd(0x1p-20))); /* cull_limit */
        const __m256d t0 = _mm256_blendv_pd(inf, _mm256_cvtps_pd(_mm_loadu_ps(rays->tmin + k)), sel);
        const __m256d t1 = _mm256_blendv_pd(ninf, lim, sel);
        _mm256_storeu_pd(p->t0 + k, t0), _mm256_storeu_pd(p->t1 + k, t1);
        __m256d s0, s1;
        const uint32_t nq = slab_quad_avx2(p, k, iq, gr->tlo, gr->thi, &s0, &s1);
        if (iq) {
            _mm256_storeu_pd(p->s0 + k, s0), _mm256_storeu_pd(p->s1 + k, s1);
            /* the packed lanes that miss T's box: an empty span */
            _mm256_storeu_pd(p->t1 + k, _mm256_blendv_pd(t1, ninf, lanes_avx2(iq & ~nq)));
        }
        in |= iq << k, near |= nq << k;
    }
    *packed = in;
    return near;
}

/* pack_enter_avx2 eight lanes at a time, for CPUs with AVX-512 (rays->n a
 * multiple of eight): local_quad_avx2's, the spans' and slab_quad_avx2's
 * operations lane by lane (a lane parallel to an axis takes no division,
 * and holds 0 there as the AVX2 code's mask leaves it), so the same lanes
 * and numbers. */
__attribute__((target("avx512f"))) static uint32_t pack_enter_avx512(const mr_dgrad *gr,
                                                                     const mr_dbase *b,
                                                                     const mr_drays *rays,
                                                                     uint32_t lanes, pack *p,
                                                                     uint32_t *packed)
{
    const __m512d inf = _mm512_set1_pd(INFINITY), ninf = _mm512_set1_pd(-INFINITY);
    const __m512d zero = _mm512_setzero_pd();
    uint32_t in = 0, near = 0;
    for (int k = 0; k < PK; k += 8) {
        const __mmask8 lq = (__mmask8)(lanes >> k);
        if (!lq) {
            for (int a = 0; a < 3; a++) {
                _mm512_storeu_pd(p->o[a] + k, zero), _mm512_storeu_pd(p->inv[a] + k, zero);
                if (a < 2)
                    _mm512_storeu_pd(p->d[a] + k, zero);
            }
            _mm512_storeu_pd(p->t0 + k, inf), _mm512_storeu_pd(p->t1 + k, ninf);
            continue;
        }
        /* local_ray */
        __m512d od[3], d[3];
        for (int c = 0; c < 3; c++) {
            od[c] = _mm512_sub_pd(_mm512_cvtps_pd(_mm256_loadu_ps(rays->o[c] + k)),
                                  _mm512_set1_pd(gr->P0[c]));
            d[c] = _mm512_cvtps_pd(_mm256_loadu_ps(rays->d[c] + k));
        }
        __mmask8 par = 0;
        for (int a = 0; a < 3; a++) {
            const __m512d i0 = _mm512_set1_pd(gr->inv[a][0]), i1 = _mm512_set1_pd(gr->inv[a][1]);
            const __m512d i2 = _mm512_set1_pd(gr->inv[a][2]);
            __m512d lo = _mm512_add_pd(_mm512_mul_pd(i0, od[0]), _mm512_mul_pd(i1, od[1]));
            __m512d ld = _mm512_add_pd(_mm512_mul_pd(i0, d[0]), _mm512_mul_pd(i1, d[1]));
            lo = _mm512_add_pd(lo, _mm512_mul_pd(i2, od[2]));
            ld = _mm512_add_pd(ld, _mm512_mul_pd(i2, d[2]));
            if (a < 2)
                lo = _mm512_add_pd(lo, _mm512_set1_pd(b->g[0][a]));
            const __mmask8 z = _mm512_cmp_pd_mask(ld, zero, _CMP_EQ_OQ);
            par |= z;
            _mm512_storeu_pd(p->o[a] + k, lo);
            _mm512_storeu_pd(p->inv[a] + k, _mm512_maskz_div_pd((__mmask8)~z, _mm512_set1_pd(1.0), ld));
            if (a < 2)
                _mm512_storeu_pd(p->d[a] + k, ld);
        }
        const __mmask8 iq = (__mmask8)(~par & lq);
        /* the spans: [tmin, cull_limit(tmax)] */
        const __m512d lim = cull_limit8(_mm256_loadu_ps(rays->tmax + k));
        __m512d t0 = _mm512_mask_blend_pd(iq, inf, _mm512_cvtps_pd(_mm256_loadu_ps(rays->tmin + k)));
        const __m512d t1 = _mm512_mask_blend_pd(iq, ninf, lim);
        _mm512_storeu_pd(p->t0 + k, t0), _mm512_storeu_pd(p->t1 + k, t1);
        /* T's box */
        __mmask8 nq = 0;
        if (iq) {
            __m512d u1 = t1;
            for (int a = 0; a < 3; a++) {
                const __m512d o = _mm512_loadu_pd(p->o[a] + k), inv = _mm512_loadu_pd(p->inv[a] + k);
                const __m512d nn = _mm512_mul_pd(_mm512_sub_pd(_mm512_set1_pd(gr->tlo[a]), o), inv);
                const __m512d ff = _mm512_mul_pd(_mm512_sub_pd(_mm512_set1_pd(gr->thi[a]), o), inv);
                const __m512d n = _mm512_min_pd(ff, nn);
                const __m512d far = _mm512_mul_pd(_mm512_max_pd(nn, ff), _mm512_set1_pd(1 + 4 * DBL_EPSILON));
                t0 = _mm512_max_pd(n, t0);
                u1 = _mm512_min_pd(far, u1);
            }
            nq = (__mmask8)(~_mm512_cmp_pd_mask(t0, u1, _CMP_GT_OQ) & iq);
            _mm512_storeu_pd(p->s0 + k, t0), _mm512_storeu_pd(p->s1 + k, u1);
            /* the packed lanes that miss T's box: an empty span */
            _mm512_storeu_pd(p->t1 + k, _mm512_mask_blend_pd((__mmask8)(iq & ~nq), t1, ninf));
        }
        in |= (uint32_t)iq << k, near |= (uint32_t)nq << k;
    }
    *packed = in;
    return near;
}
#define PACK_ENTER(gr, b, rays, lanes, p, packed)                                                 \
    (mr_simd_avx512() && rays->n % 8 == 0                                                         \
         ? pack_enter_avx512(gr, b, rays, lanes, p, packed)                                       \
     : __builtin_cpu_supports("avx2") && rays->n % 4 == 0                                         \
         ? pack_enter_avx2(gr, b, rays, lanes, p, packed)                                         \
         : pack_enter(gr, b, rays, lanes, p, packed))
#else
#define PACK_ENTER pack_enter
#endif

/* Lane k's grid coordinate along axis a (0: x, 1: y) where its ray enters
 * T's box (x0) and leaves it (x1): tbox_lanes' span s0 .. s1. */
static inline void span_ends(const pack *p, int a, int k, double *x0, double *x1)
{
    *x0 = p->o[a][k] + p->s0[k] * p->d[a][k];
    *x1 = p->o[a][k] + p->s1[k] * p->d[a][k];
}

#if defined(__x86_64__) && defined(__GNUC__)
/* span_ends for lanes k .. k + 3 (AVX2): the same operations lane by lane. */
__attribute__((target("avx2"))) static inline void span_ends_avx2(const pack *p, int a, int k, __m256d *x0,
                                                                  __m256d *x1)
{
    const __m256d o = _mm256_loadu_pd(p->o[a] + k), d = _mm256_loadu_pd(p->d[a] + k);
    *x0 = _mm256_add_pd(o, _mm256_mul_pd(_mm256_loadu_pd(p->s0 + k), d));
    *x1 = _mm256_add_pd(o, _mm256_mul_pd(_mm256_loadu_pd(p->s1 + k), d));
}
#endif

/* The lanes of `live` (rays that enter T's box: tbox_lanes) whose x and y
 * while in the box come near enough T to hit it: each ray's segment from
 * its entry to its exit is not wholly beyond one of T's edges moved out by
 * reach (mr_dgrad.en, ec; footprint_frame). T's box is its grid box, twice
 * T's area: a ray that hits T's neighbour across the box's diagonal enters
 * it too (a NaN lane is kept). */
static uint32_t tri_lanes(const mr_dgrad *gr, const pack *p, uint32_t live)
{
    uint32_t in = live;
    for (uint32_t m = live; m; m &= m - 1) {
        const int k = __builtin_ctz(m);
        double x0, x1, y0, y1;
        span_ends(p, 0, k, &x0, &x1);
        span_ends(p, 1, k, &y0, &y1);
        for (int e = 0; e < 3; e++)
            if (gr->en[e][0] * x0 + gr->en[e][1] * y0 > gr->ec[e] &&
                gr->en[e][0] * x1 + gr->en[e][1] * y1 > gr->ec[e])
                in &= ~(1u << k);
    }
    return in;
}

#if defined(__x86_64__) && defined(__GNUC__)
/* tri_lanes four lanes at a time, for CPUs with AVX2: the same operations
 * lane by lane (no fused multiply-add), so the same lanes. */
__attribute__((target("avx2"))) static uint32_t tri_lanes_avx2(const mr_dgrad *gr, const pack *p,
                                                                uint32_t live)
{
    uint32_t in = 0;
    for (int k = 0; k < PK; k += 4) {
        const uint32_t lq = live >> k & 15u;
        if (!lq)
            continue;
        __m256d x0, x1, y0, y1;
        span_ends_avx2(p, 0, k, &x0, &x1);
        span_ends_avx2(p, 1, k, &y0, &y1);
        __m256d out = _mm256_setzero_pd();
        for (int e = 0; e < 3; e++) {
            const __m256d ex = _mm256_set1_pd(gr->en[e][0]), ey = _mm256_set1_pd(gr->en[e][1]);
            const __m256d c = _mm256_set1_pd(gr->ec[e]);
            const __m256d v0 = _mm256_add_pd(_mm256_mul_pd(ex, x0), _mm256_mul_pd(ey, y0));
            const __m256d v1 = _mm256_add_pd(_mm256_mul_pd(ex, x1), _mm256_mul_pd(ey, y1));
            const __m256d beyond0 = _mm256_cmp_pd(v0, c, _CMP_GT_OQ), beyond1 = _mm256_cmp_pd(v1, c, _CMP_GT_OQ);
            out = _mm256_or_pd(out, _mm256_and_pd(beyond0, beyond1));
        }
        in |= (lq & ~(uint32_t)_mm256_movemask_pd(out)) << k;
    }
    return in;
}

#define TRI_LANES(gr, p, live)                                                                    \
    (__builtin_cpu_supports("avx2") ? tri_lanes_avx2(gr, p, live) : tri_lanes(gr, p, live))
#else
#define TRI_LANES tri_lanes
#endif

/* packet_footprint's rays: the x and y the rays `live` (which enter T's
 * box: tbox_lanes) cross inside it into f, the largest magnitude among
 * them and their origins' into *size; -1 on a NaN. */
static int footprint_rays(const pack *p, uint32_t live, double f[2][2], double *size)
{
    f[0][0] = f[1][0] = INFINITY, f[0][1] = f[1][1] = -INFINITY;
    *size = 0;
    for (uint32_t m = live; m; m &= m - 1) {
        const int k = __builtin_ctz(m);
        for (int a = 0; a < 2; a++) {
            double x0, x1;
            span_ends(p, a, k, &x0, &x1);
            if (isnan(x0) || isnan(x1))
                return -1;
            f[a][0] = dmin(f[a][0], dmin(x0, x1));
            f[a][1] = dmax(f[a][1], dmax(x0, x1));
            *size = dmax(*size, dmax(dmax(fabs(x0), fabs(x1)), fabs(p->o[a][k])));
        }
    }
    return 0;
}

#if defined(__x86_64__) && defined(__GNUC__)
/* footprint_rays four lanes at a time, for CPUs with AVX2 (the same
 * rectangle: min and max are a < b ? a : b and a > b ? a : b in both, and
 * lanes left out hold infinities). */
__attribute__((target("avx2"))) static int footprint_rays_avx2(const pack *p, uint32_t live,
                                                               double f[2][2], double *size)
{
    const __m256d inf = _mm256_set1_pd(INFINITY), ninf = _mm256_set1_pd(-INFINITY);
    const __m256d sign = _mm256_set1_pd(-0.0);
    __m256d fl[2] = {inf, inf}, fh[2] = {ninf, ninf}, sz = _mm256_setzero_pd();
    uint32_t nan = 0;
    for (int k = 0; k < PK; k += 4) {
        const uint32_t in = live >> k & 15u;
        if (!in)
            continue;
        const __m256d sel = lanes_avx2(in);
        for (int a = 0; a < 2; a++) {
            __m256d x0, x1;
            span_ends_avx2(p, a, k, &x0, &x1);
            const __m256d o = _mm256_loadu_pd(p->o[a] + k);
            nan |= (uint32_t)_mm256_movemask_pd(_mm256_cmp_pd(x0, x1, _CMP_UNORD_Q)) & in;
            fl[a] = _mm256_min_pd(_mm256_blendv_pd(inf, _mm256_min_pd(x0, x1), sel), fl[a]);
            fh[a] = _mm256_max_pd(_mm256_blendv_pd(ninf, _mm256_max_pd(x0, x1), sel), fh[a]);
            const __m256d ax0 = _mm256_andnot_pd(sign, x0), ax1 = _mm256_andnot_pd(sign, x1);
            const __m256d m = _mm256_max_pd(_mm256_max_pd(ax0, ax1), _mm256_andnot_pd(sign, o));
            sz = _mm256_max_pd(_mm256_and_pd(sel, m), sz);
        }
    }
    if (nan)
        return -1;
    double v[4];
    for (int a = 0; a < 2; a++) {
        _mm256_storeu_pd(v, fl[a]);
        f[a][0] = dmin(dmin(v[0], v[1]), dmin(v[2], v[3]));
        _mm256_storeu_pd(v, fh[a]);
        f[a][1] = dmax(dmax(v[0], v[1]), dmax(v[2], v[3]));
    }
    _mm256_storeu_pd(v, sz);
    *size = dmax(dmax(v[0], v[1]), dmax(v[2], v[3]));
    return 0;
}
#define FOOTPRINT_RAYS(p, live, f, size)                                                        \
    (__builtin_cpu_supports("avx2") ? footprint_rays_avx2(p, live, f, size)                   \
                                    : footprint_rays(p, live, f, size))
#else
#define FOOTPRINT_RAYS footprint_rays
#endif

/* The grid rectangle f ([axis][lo, hi]) that holds every grid point a hit
 * of the packet's rays `live` (which enter T's box: tbox_lanes) on T can
 * lie over: 1; 0 when none is left (none hits); -1 when it cannot be told
 * (a NaN or an infinity).
 *
 * Why: a hit lies on a micro-triangle of T, inside T's local box (every
 * micro-vertex is in it), so at a t where the ray is in that box; its
 * local x and y are those of a grid point q of T moved by h (a, b) (h in
 * T's heights, (a, b) in the normal's bounds nb) and the local box's pad,
 * so q lies within e of the x and y the ray crosses while inside the box,
 * and within T's grid box. The rounding of x and y (o + t d) is
 * covered by a margin of 1e-9 of their size plus 1e-6 of a cell. */
static int packet_footprint(const mr_dgrad *gr, const pack *p, uint32_t live, double f[2][2])
{
    double size;
    if (FOOTPRINT_RAYS(p, live, f, &size) < 0)
        return -1;
    const double margin = 1e-6 + 1e-9 * size;
    const double gb[2][2] = {{gr->gx0, gr->gx1}, {gr->gy0, gr->gy1}};
    for (int a = 0; a < 2; a++) {
        const double e = gr->reach[a] + margin;
        if (!isfinite(f[a][0] - e) || !isfinite(f[a][1] + e))
            return -1;
        f[a][0] = dmax(f[a][0] - e, gb[a][0]), f[a][1] = dmin(f[a][1] + e, gb[a][1]);
        if (f[a][0] > f[a][1])
            return 0;
        if (!(fabs(f[a][0]) < 0x1p60 && fabs(f[a][1]) < 0x1p60)) /* (no cell index to take) */
            return -1;
    }
    return 1;
}

/* A texture's nodes over the grid rectangle f: the lowest level below T's
 * roots (at most the pyramid's top) at which f's cells span at most two
 * nodes per axis (as roots), those nodes; 0 when there is none. Cells are
 * closed squares, so a grid point on a node's edge takes the nodes on both
 * sides (f's margin). */
static int tex_start(const mr_dgrid *g, int root_level, const double f[2][2], tnode out[4])
{
    const int top = (int)g->levels;
    const int64_t c[2][2] = {{(int64_t)floor(f[0][0]), (int64_t)floor(f[0][1])},
                             {(int64_t)floor(f[1][0]), (int64_t)floor(f[1][1])}};
    for (int l = 0; l < root_level && l <= top; l++) {
        const int64_t x0 = node_index(c[0][0], g->w, g->lw[l], l, top);
        const int64_t x1 = node_index(c[0][1], g->w, g->lw[l], l, top);
        const int64_t y0 = node_index(c[1][0], g->h, g->lh[l], l, top);
        const int64_t y1 = node_index(c[1][1], g->h, g->lh[l], l, top);
        if (x1 - x0 > 1 || y1 - y0 > 1)
            continue;
        int k = 0;
        for (int64_t y = y0; y <= y1; y++)
            for (int64_t x = x0; x <= x1; x++)
                out[k++].d = node_at(g, l, x, y);
        return k;
    }
    return 0;
}

/* A procedural source's nodes over the grid rectangle f: the least side
 * h (1 .. range) at which f's cells span at most two squares per axis,
 * those squares; 0 when there is none. Cells are closed squares, so a
 * grid point on a square's edge takes the squares on both sides. */
static int proc_start(const mr_dproc *pr, const double f[2][2], tnode out[4])
{
    for (int l = 0; l <= pr->top; l++) {
        const int64_t i0 = (int64_t)floor(f[0][0]) >> l, i1 = (int64_t)floor(f[0][1]) >> l;
        const int64_t j0 = (int64_t)floor(f[1][0]) >> l, j1 = (int64_t)floor(f[1][1]) >> l;
        if (i1 - i0 > 1 || j1 - j0 > 1)
            continue;
        int k = 0;
        for (int64_t j = j0; j <= j1; j++)
            for (int64_t i = i0; i <= i1; i++)
                out[k++].p = (pnode){l, i, j};
        return k;
    }
    return 0;
}

/* Where a packet's rays start down T's nodes: the few nodes over their
 * footprint (packet_footprint; a walk from them finds what a walk from
 * T's roots finds, as every node above a hit's leaf holds the hit point in
 * its box), or T's roots; returns how many (0: no ray hits). A packet of a
 * camera's neighbouring pixels falls on a few cells, and every packet
 * walked down from T's roots through the same upper nodes. */
static int packet_start(const mr_dscene *s, uint32_t t, const mr_dgrad *gr, const pack *p,
                        uint32_t live, tnode out[4])
{
    const int nr = tri_tnodes(s, t, out);
    if (!s->proc && nr && out[0].d.level == 0)
        return nr; /* (already at the leaves) */
    double f[2][2];
    const int fp = nr ? packet_footprint(gr, p, live, f) : -1;
    if (fp <= 0)
        return fp == 0 ? 0 : nr;
    tnode st[4];
    const int n = s->proc ? proc_start(s->proc, f, st) : tex_start(s->grid, out[0].d.level, f, st);
    if (!n)
        return nr;
    for (int k = 0; k < n; k++)
        out[k] = st[k];
    return n;
}

/* The nodes n[0 .. count) (at most 4) the packet's rays `live` enter:
 * node c, when bit c of `boxed` is set, has its box in lo[.][c] ..
 * hi[.][c] and its heights in hlo[c], hhi[c]. The entered ones, each with
 * its rays and their nearest entry, are pushed onto the stack (sp
 * entries; returns how many after) in PUSH_NEAREST_LAST's order:
 * farthest first, ties in node order. Each is written once, in its place
 * (built, sorted and copied, they cost the procedural sphere's trace
 * 0.4 %). */
static int packet_push(const pack *p, uint32_t live, const tnode *n, int count, unsigned boxed,
                       const double lo[3][4], const double hi[3][4], const double hlo[4],
                       const double hhi[4], pentry *stack, int sp)
{
    uint32_t in[4] = {0};
    double near[4];
#if HAS_SLAB_FOUR
    if (boxed && __builtin_cpu_supports("avx2")) {
        slab_four(p, live, lo, hi, in, near);
    } else
#endif
    {
        for (int c = 0; c < count; c++) {
            if (!(boxed >> c & 1u))
                continue;
            const double l[3] = {lo[0][c], lo[1][c], lo[2][c]};
            const double h[3] = {hi[0][c], hi[1][c], hi[2][c]};
            in[c] = SLAB_PACK(p, live, l, h, &near[c]);
        }
    }
    int order[4], nh = 0; /* the entered nodes, farthest first (an insertion sort) */
    for (int c = 0; c < count; c++) {
        if (!(boxed >> c & 1u) || !in[c])
            continue;
        int m = nh++;
        for (; m > 0 && near[c] > near[order[m - 1]]; m--)
            order[m] = order[m - 1];
        order[m] = c;
    }
    for (int k = 0; k < nh && sp < STACK_MAX; k++) {
        const int c = order[k];
        stack[sp++] = (pentry){n[c], in[c], near[c], hlo[c], hhi[c]};
    }
    return sp;
}

/* The packed rays' watertight set-ups (the micro-triangle test's:
 * mr_dray_setup's wt, of the same floats), made on a lane's first cell and
 * kept for the rest of the call, as columns: lane k's fields in element k,
 * which cell_test8 reads eight lanes at a time. A packed ray needs no more
 * of its set-up: the rest of mr_dray (and the set-ups' cache across calls)
 * cost 6 % of the sphere's frame at 100 texels per unit. */
typedef struct pack_wt {
    uint32_t made;       /* the lanes set up */
    float col[6][PK];    /* org x, y, z; sx, sy, sz */
    int32_t axis[3][PK]; /* kx, ky, kz */
} pack_wt;

/* Lane k's set-up as a record (made). */
static inline mr_wt_ray wt_get(const pack_wt *w, int k)
{
    return (mr_wt_ray){.org = {w->col[0][k], w->col[1][k], w->col[2][k]},
                       .kx = w->axis[0][k],
                       .ky = w->axis[1][k],
                       .kz = w->axis[2][k],
                       .sx = w->col[3][k],
                       .sy = w->col[4][k],
                       .sz = w->col[5][k]};
}

/* Sets up lane k (pack_wt) if it is not yet; false when its direction
 * hits nothing. */
static inline bool lane_wt(const mr_drays *rays, pack_wt *w, int k)
{
    if (w->made >> k & 1u)
        return true;
    const mr_vec3 d = mr_v3_gather(rays->d[0] + k, rays->d[1] + k, rays->d[2] + k);
    if (!mr_v3_is_dir(d))
        return false;
    const mr_wt_ray r =
        mr_wt_ray_setup(mr_v3_gather(rays->o[0] + k, rays->o[1] + k, rays->o[2] + k), d);
    w->col[0][k] = r.org.x, w->col[1][k] = r.org.y, w->col[2][k] = r.org.z;
    w->col[3][k] = r.sx, w->col[4][k] = r.sy, w->col[5][k] = r.sz;
    w->axis[0][k] = r.kx, w->axis[1][k] = r.ky, w->axis[2][k] = r.kz;
    w->made |= 1u << k;
    return true;
}

#if defined(__x86_64__) && defined(__GNUC__)
/* Per lane: v0 where z0, else v1 where z1, else v2. */
__attribute__((target("avx2"))) static inline __m256i pick3_avx2(__m256 z0, __m256 z1, int v0,
                                                                  int v1, int v2)
{
    const __m256 a = _mm256_castsi256_ps(_mm256_set1_epi32(v0));
    const __m256 b = _mm256_castsi256_ps(_mm256_set1_epi32(v1));
    const __m256 c = _mm256_castsi256_ps(_mm256_set1_epi32(v2));
    return _mm256_castps_si256(_mm256_blendv_ps(_mm256_blendv_ps(c, b, z1), a, z0));
}

/* lane_wt for the eight lanes of half h of the packet at once (AVX2, the
 * packet has them: rays->n >= 8 h + 8): mr_v3_is_dir's and
 * mr_wt_ray_setup's float comparisons and divisions lane by lane, their
 * choices as selections, so the same set-ups bit for bit. The lanes
 * whose direction can hit are then set up (w->made). */
__attribute__((target("avx2"))) static void half_wt_avx2(const mr_drays *rays, pack_wt *w, int h)
{
    const int o = 8 * h;
    const __m256 dx = _mm256_loadu_ps(rays->d[0] + o), dy = _mm256_loadu_ps(rays->d[1] + o);
    const __m256 dz = _mm256_loadu_ps(rays->d[2] + o);
    const __m256 sign = _mm256_set1_ps(-0.0f), inf = _mm256_set1_ps(INFINITY);
    const __m256 zero = _mm256_setzero_ps();
    const __m256 ax = _mm256_andnot_ps(sign, dx), ay = _mm256_andnot_ps(sign, dy);
    const __m256 az = _mm256_andnot_ps(sign, dz);
    /* mr_v3_is_dir: some component not 0, all finite */
    const __m256 nonzero = _mm256_or_ps(
        _mm256_or_ps(_mm256_cmp_ps(dx, zero, _CMP_NEQ_UQ), _mm256_cmp_ps(dy, zero, _CMP_NEQ_UQ)),
        _mm256_cmp_ps(dz, zero, _CMP_NEQ_UQ));
    const __m256 finite = _mm256_and_ps(
        _mm256_and_ps(_mm256_cmp_ps(ax, inf, _CMP_LT_OQ), _mm256_cmp_ps(ay, inf, _CMP_LT_OQ)),
        _mm256_cmp_ps(az, inf, _CMP_LT_OQ));
    const uint32_t ok = (uint32_t)_mm256_movemask_ps(_mm256_and_ps(nonzero, finite));
    /* kz = ax > ay ? (ax > az ? 0 : 2) : (ay > az ? 1 : 2) */
    const __m256 x_over_y = _mm256_cmp_ps(ax, ay, _CMP_GT_OQ);
    const __m256 z0 = _mm256_and_ps(x_over_y, _mm256_cmp_ps(ax, az, _CMP_GT_OQ));
    const __m256 z1 = _mm256_andnot_ps(x_over_y, _mm256_cmp_ps(ay, az, _CMP_GT_OQ));
    /* along kz; then kx = kz + 1, ky = kz + 2 (mod 3), swapped where the
     * ray runs along -kz */
    const __m256 along = _mm256_blendv_ps(_mm256_blendv_ps(dz, dy, z1), dx, z0);
    const __m256 swap = _mm256_cmp_ps(along, zero, _CMP_LT_OQ);
    const __m256 next = _mm256_blendv_ps(_mm256_blendv_ps(dx, dz, z1), dy, z0);
    const __m256 after = _mm256_blendv_ps(_mm256_blendv_ps(dy, dx, z1), dz, z0);
    const __m256 cx = _mm256_blendv_ps(next, after, swap);
    const __m256 cy = _mm256_blendv_ps(after, next, swap);
    _mm256_storeu_ps(w->col[3] + o, _mm256_div_ps(cx, along));
    _mm256_storeu_ps(w->col[4] + o, _mm256_div_ps(cy, along));
    _mm256_storeu_ps(w->col[5] + o, _mm256_div_ps(_mm256_set1_ps(1.0f), along));
    const __m256i kz = pick3_avx2(z0, z1, 0, 1, 2), kx = pick3_avx2(z0, z1, 1, 2, 0);
    const __m256i ky = pick3_avx2(z0, z1, 2, 0, 1);
    const __m256i sw = _mm256_castps_si256(swap);
    _mm256_storeu_si256((__m256i *)(w->axis[0] + o), _mm256_blendv_epi8(kx, ky, sw));
    _mm256_storeu_si256((__m256i *)(w->axis[1] + o), _mm256_blendv_epi8(ky, kx, sw));
    _mm256_storeu_si256((__m256i *)(w->axis[2] + o), kz);
    for (int a = 0; a < 3; a++)
        _mm256_storeu_ps(w->col[a] + o, _mm256_loadu_ps(rays->o[a] + o));
    w->made |= ok << o;
}
#endif

/* What a vector test (cell_test8, cell_test16) of micro-triangle k of a
 * cell found: lanes `hits` (their distance and barycentrics in tv, uv,
 * vv) and lanes `edge0` (an edge function exactly 0: the scalar test
 * again, from the lane's sheared vertices sh[vertex][axis][lane]), each
 * kept by tri_keep for packet lane o + q, its span tmin[q] .. lim[q], lim
 * following its tmax. */
static inline void keep_lanes(const cell_tris *ct, int k, uint32_t hits, uint32_t edge0,
                              const float *tv, const float *uv, const float *vv,
                              const float sh[3][3][PK], const float *tmin, float *lim,
                              const mr_drays *rays, int o, best *bh)
{
    const mr_dcell *c = &ct->c;
    const uint8_t *tr = c->tri[k];
    for (uint32_t m = hits | edge0; m; m &= m - 1) {
        const int q = __builtin_ctz(m);
        mr_wt_hit hit = {tv[q], uv[q], vv[q]};
        if (edge0 >> q & 1u) {
            mr_wt_vertex sv[3];
            for (int e = 0; e < 3; e++)
                sv[e] = (mr_wt_vertex){sh[e][0][q], sh[e][1][q], sh[e][2][q]};
            if (!mr_wt_intersect_sheared(&sv[0], &sv[1], &sv[2], tmin[q], lim[q], &hit))
                continue;
        }
        tri_keep(&hit, ct->V[tr[0]], ct->V[tr[1]], ct->V[tr[2]], &c->v[tr[0]], &c->v[tr[1]],
                 &c->v[tr[2]], (tri_key){ct->j, ct->i, c->half[k], k}, &rays->tmax[o + q],
                 &bh[o + q]);
        lim[q] = (float)cull_limit(rays->tmax[o + q]);
    }
}

/* The fewest of a half packet's rays at a cell that cell_test8 takes
 * together: a lone ray's scalar test costs less than the eight lanes, two
 * rays' more (with 2 rather than 3, trace 0.97-0.99 on the sphere at 100
 * and 400 texels per unit and the plane at 200; with 1, 1.00-1.03). */
#define CELL8_MIN 2

#if defined(__x86_64__) && defined(__GNUC__)
/* cell_test for the rays `lanes` (bits 0 .. 7) of half h of the packet
 * (lanes 8 h .. 8 h + 7, which the packet has: rays->n >= 8 h + 8) at
 * once, AVX2: lane q of every vector is packet
 * lane 8 h + q, its set-up read from w's columns (every lane of `lanes`
 * set up), its span rays->tmin .. rays->tmax, its best bh. mr_wt_shear's
 * and mr_wt_intersect_sheared's float operations in their order lane by
 * lane, no fused multiply-add, the same ordered comparisons, so the same
 * hits bit for bit; a lane whose edge function comes out exactly 0 takes
 * the scalar test (its recomputation in double). The triangles go in the
 * cell's order, each ray's tmax shrinking after each, as in cell_test. */
__attribute__((target("avx2"))) static void cell_test8(const cell_tris *ct, const pack_wt *w, int h,
                                                        uint32_t lanes, const mr_drays *rays,
                                                        best *bh, mr_dstats *st)
{
    const mr_dcell *c = &ct->c;
    const int o = 8 * h;
    if (st)
        st->triangles += (uint64_t)c->nt * (uint64_t)mr_popcount32(lanes);
    /* (lanes not in `lanes` compute on whatever their columns hold; their
     * results are never read) */
    const __m256 ox = _mm256_loadu_ps(w->col[0] + o), oy = _mm256_loadu_ps(w->col[1] + o);
    const __m256 oz = _mm256_loadu_ps(w->col[2] + o), sx = _mm256_loadu_ps(w->col[3] + o);
    const __m256 sy = _mm256_loadu_ps(w->col[4] + o), sz = _mm256_loadu_ps(w->col[5] + o);
    __m256 is0[3], is1[3]; /* per permuted axis: the lanes where it is x, where y */
    for (int a = 0; a < 3; a++) {
        const __m256i k = _mm256_loadu_si256((const __m256i *)(w->axis[a] + o));
        is0[a] = _mm256_castsi256_ps(_mm256_cmpeq_epi32(k, _mm256_setzero_si256()));
        is1[a] = _mm256_castsi256_ps(_mm256_cmpeq_epi32(k, _mm256_set1_epi32(1)));
    }
    __m256 X[2 * MR_DSURF_MAX_POLY], Y[2 * MR_DSURF_MAX_POLY], Z[2 * MR_DSURF_MAX_POLY];
    for (int v = 0; v < c->nv; v++) {
        const __m256 a0 = _mm256_sub_ps(_mm256_set1_ps(ct->V[v].x), ox);
        const __m256 a1 = _mm256_sub_ps(_mm256_set1_ps(ct->V[v].y), oy);
        const __m256 a2 = _mm256_sub_ps(_mm256_set1_ps(ct->V[v].z), oz);
        __m256 p[3];
        for (int a = 0; a < 3; a++)
            p[a] = _mm256_blendv_ps(_mm256_blendv_ps(a2, a1, is1[a]), a0, is0[a]);
        X[v] = _mm256_sub_ps(p[0], _mm256_mul_ps(sx, p[2]));
        Y[v] = _mm256_sub_ps(p[1], _mm256_mul_ps(sy, p[2]));
        Z[v] = _mm256_mul_ps(p[2], sz);
    }
    _Static_assert(PK % 8 == 0, "packets are whole halves");
    float lim[8];
    for (int q = 0; q < 8; q++)
        lim[q] = (float)cull_limit(rays->tmax[o + q]);
    const float *tmin = rays->tmin + o;
    const __m256 vtmin = _mm256_loadu_ps(tmin), zero = _mm256_setzero_ps();
    for (int k = 0; k < c->nt; k++) {
        const uint8_t *tr = c->tri[k];
        const __m256 ax = X[tr[0]], ay = Y[tr[0]], bx = X[tr[1]], by = Y[tr[1]];
        const __m256 cx = X[tr[2]], cy = Y[tr[2]];
        const __m256 u = _mm256_sub_ps(_mm256_mul_ps(cx, by), _mm256_mul_ps(cy, bx));
        const __m256 v = _mm256_sub_ps(_mm256_mul_ps(ax, cy), _mm256_mul_ps(ay, cx));
        const __m256 wv = _mm256_sub_ps(_mm256_mul_ps(bx, ay), _mm256_mul_ps(by, ax));
        /* the lanes where an edge function is exactly 0, negative, positive */
        const __m256 zu = _mm256_cmp_ps(u, zero, _CMP_EQ_OQ), zv = _mm256_cmp_ps(v, zero, _CMP_EQ_OQ);
        const __m256 zw = _mm256_cmp_ps(wv, zero, _CMP_EQ_OQ);
        const uint32_t edge0 =
            (uint32_t)_mm256_movemask_ps(_mm256_or_ps(_mm256_or_ps(zu, zv), zw)) & lanes;
        const __m256 nu = _mm256_cmp_ps(u, zero, _CMP_LT_OQ), nv = _mm256_cmp_ps(v, zero, _CMP_LT_OQ);
        const __m256 nw = _mm256_cmp_ps(wv, zero, _CMP_LT_OQ);
        const __m256 pu = _mm256_cmp_ps(u, zero, _CMP_GT_OQ), pv = _mm256_cmp_ps(v, zero, _CMP_GT_OQ);
        const __m256 pw = _mm256_cmp_ps(wv, zero, _CMP_GT_OQ);
        const __m256 neg = _mm256_or_ps(_mm256_or_ps(nu, nv), nw);
        const __m256 pos = _mm256_or_ps(_mm256_or_ps(pu, pv), pw);
        const __m256 det = _mm256_add_ps(_mm256_add_ps(u, v), wv);
        const __m256 adet = _mm256_andnot_ps(_mm256_set1_ps(-0.0f), det);
        __m256 ok = _mm256_andnot_ps(_mm256_and_ps(neg, pos),
                                     _mm256_cmp_ps(adet, _mm256_set1_ps(FLT_MIN), _CMP_GE_OQ));
        const __m256 ts = _mm256_add_ps(
            _mm256_add_ps(_mm256_mul_ps(u, Z[tr[0]]), _mm256_mul_ps(v, Z[tr[1]])),
            _mm256_mul_ps(wv, Z[tr[2]]));
        const __m256 vlim = _mm256_loadu_ps(lim);
        const __m256 lo = _mm256_mul_ps(vtmin, det), hi = _mm256_mul_ps(vlim, det);
        const __m256 dneg = _mm256_cmp_ps(det, zero, _CMP_LT_OQ);
        const __m256 out_neg =
            _mm256_or_ps(_mm256_cmp_ps(ts, lo, _CMP_GT_OQ), _mm256_cmp_ps(ts, hi, _CMP_LT_OQ));
        const __m256 out_pos =
            _mm256_or_ps(_mm256_cmp_ps(ts, lo, _CMP_LT_OQ), _mm256_cmp_ps(ts, hi, _CMP_GT_OQ));
        ok = _mm256_andnot_ps(_mm256_blendv_ps(out_pos, out_neg, dneg), ok);
        const __m256 inv = _mm256_div_ps(_mm256_set1_ps(1.0f), det);
        const __m256 t = _mm256_mul_ps(ts, inv);
        ok = _mm256_and_ps(ok, _mm256_and_ps(_mm256_cmp_ps(t, vtmin, _CMP_GE_OQ),
                                             _mm256_cmp_ps(t, vlim, _CMP_LE_OQ)));
        ok = _mm256_and_ps(ok, _mm256_cmp_ps(t, _mm256_set1_ps(INFINITY), _CMP_LT_OQ));
        const uint32_t hits = (uint32_t)_mm256_movemask_ps(ok) & lanes & ~edge0;
        if (!(hits | edge0))
            continue;
        float tv[8], uv[8], vv[8], sh[3][3][PK];
        _mm256_storeu_ps(tv, t);
        _mm256_storeu_ps(uv, _mm256_mul_ps(v, inv));
        _mm256_storeu_ps(vv, _mm256_mul_ps(wv, inv));
        for (int e = 0; edge0 && e < 3; e++) {
            _mm256_storeu_ps(sh[e][0], X[tr[e]]), _mm256_storeu_ps(sh[e][1], Y[tr[e]]);
            _mm256_storeu_ps(sh[e][2], Z[tr[e]]);
        }
        keep_lanes(ct, k, hits, edge0, tv, uv, vv, sh, tmin, lim, rays, o, bh);
    }
}

/* cell_test8 for the packet's sixteen lanes at once, for CPUs with
 * AVX-512 (rays->n == PK == 16, every lane of `lanes` set up): lane k of
 * every vector is packet lane k, and each lane does cell_test8's float
 * operations in their order, so the same hits bit for bit. */
__attribute__((target("avx512f"))) static void cell_test16(const cell_tris *ct, const pack_wt *w,
                                                           uint32_t lanes, const mr_drays *rays,
                                                           best *bh, mr_dstats *st)
{
    _Static_assert(PK == 16, "a packet is one vector of sixteen floats");
    const mr_dcell *c = &ct->c;
    if (st)
        st->triangles += (uint64_t)c->nt * (uint64_t)mr_popcount32(lanes);
    const __m512 ox = _mm512_loadu_ps(w->col[0]), oy = _mm512_loadu_ps(w->col[1]);
    const __m512 oz = _mm512_loadu_ps(w->col[2]), sx = _mm512_loadu_ps(w->col[3]);
    const __m512 sy = _mm512_loadu_ps(w->col[4]), sz = _mm512_loadu_ps(w->col[5]);
    __mmask16 is0[3], is1[3]; /* per permuted axis: the lanes where it is x, where y */
    for (int a = 0; a < 3; a++) {
        const __m512i k = _mm512_loadu_si512(w->axis[a]);
        is0[a] = _mm512_cmpeq_epi32_mask(k, _mm512_setzero_si512());
        is1[a] = _mm512_cmpeq_epi32_mask(k, _mm512_set1_epi32(1));
    }
    __m512 X[2 * MR_DSURF_MAX_POLY], Y[2 * MR_DSURF_MAX_POLY], Z[2 * MR_DSURF_MAX_POLY];
    for (int v = 0; v < c->nv; v++) {
        const __m512 a0 = _mm512_sub_ps(_mm512_set1_ps(ct->V[v].x), ox);
        const __m512 a1 = _mm512_sub_ps(_mm512_set1_ps(ct->V[v].y), oy);
        const __m512 a2 = _mm512_sub_ps(_mm512_set1_ps(ct->V[v].z), oz);
        __m512 p[3];
        for (int a = 0; a < 3; a++)
            p[a] = _mm512_mask_blend_ps(is0[a], _mm512_mask_blend_ps(is1[a], a2, a1), a0);
        X[v] = _mm512_sub_ps(p[0], _mm512_mul_ps(sx, p[2]));
        Y[v] = _mm512_sub_ps(p[1], _mm512_mul_ps(sy, p[2]));
        Z[v] = _mm512_mul_ps(p[2], sz);
    }
    float lim[PK];
    for (int q = 0; q < PK; q++)
        lim[q] = (float)cull_limit(rays->tmax[q]);
    const float *tmin = rays->tmin;
    const __m512 vtmin = _mm512_loadu_ps(tmin), zero = _mm512_setzero_ps();
    for (int k = 0; k < c->nt; k++) {
        const uint8_t *tr = c->tri[k];
        const __m512 ax = X[tr[0]], ay = Y[tr[0]], bx = X[tr[1]], by = Y[tr[1]];
        const __m512 cx = X[tr[2]], cy = Y[tr[2]];
        const __m512 u = _mm512_sub_ps(_mm512_mul_ps(cx, by), _mm512_mul_ps(cy, bx));
        const __m512 v = _mm512_sub_ps(_mm512_mul_ps(ax, cy), _mm512_mul_ps(ay, cx));
        const __m512 wv = _mm512_sub_ps(_mm512_mul_ps(bx, ay), _mm512_mul_ps(by, ax));
        /* the lanes where an edge function is exactly 0, negative, positive */
        const uint32_t edge0 = (uint32_t)(_mm512_cmp_ps_mask(u, zero, _CMP_EQ_OQ) |
                                          _mm512_cmp_ps_mask(v, zero, _CMP_EQ_OQ) |
                                          _mm512_cmp_ps_mask(wv, zero, _CMP_EQ_OQ)) &
                               lanes;
        const __mmask16 neg = _mm512_cmp_ps_mask(u, zero, _CMP_LT_OQ) |
                              _mm512_cmp_ps_mask(v, zero, _CMP_LT_OQ) |
                              _mm512_cmp_ps_mask(wv, zero, _CMP_LT_OQ);
        const __mmask16 pos = _mm512_cmp_ps_mask(u, zero, _CMP_GT_OQ) |
                              _mm512_cmp_ps_mask(v, zero, _CMP_GT_OQ) |
                              _mm512_cmp_ps_mask(wv, zero, _CMP_GT_OQ);
        const __m512 det = _mm512_add_ps(_mm512_add_ps(u, v), wv);
        const __m512 adet = _mm512_abs_ps(det);
        __mmask16 ok = (__mmask16)(~(neg & pos) &
                                   _mm512_cmp_ps_mask(adet, _mm512_set1_ps(FLT_MIN), _CMP_GE_OQ));
        const __m512 ts = _mm512_add_ps(
            _mm512_add_ps(_mm512_mul_ps(u, Z[tr[0]]), _mm512_mul_ps(v, Z[tr[1]])),
            _mm512_mul_ps(wv, Z[tr[2]]));
        const __m512 vlim = _mm512_loadu_ps(lim);
        const __m512 lo = _mm512_mul_ps(vtmin, det), hi = _mm512_mul_ps(vlim, det);
        const __mmask16 dneg = _mm512_cmp_ps_mask(det, zero, _CMP_LT_OQ);
        const __mmask16 out_neg = _mm512_cmp_ps_mask(ts, lo, _CMP_GT_OQ) |
                                  _mm512_cmp_ps_mask(ts, hi, _CMP_LT_OQ);
        const __mmask16 out_pos = _mm512_cmp_ps_mask(ts, lo, _CMP_LT_OQ) |
                                  _mm512_cmp_ps_mask(ts, hi, _CMP_GT_OQ);
        ok &= (__mmask16) ~((dneg & out_neg) | (~dneg & out_pos));
        const __m512 inv = _mm512_div_ps(_mm512_set1_ps(1.0f), det);
        const __m512 t = _mm512_mul_ps(ts, inv);
        ok &= _mm512_cmp_ps_mask(t, vtmin, _CMP_GE_OQ) & _mm512_cmp_ps_mask(t, vlim, _CMP_LE_OQ) &
              _mm512_cmp_ps_mask(t, _mm512_set1_ps(INFINITY), _CMP_LT_OQ);
        const uint32_t hits = (uint32_t)ok & lanes & ~edge0;
        if (!(hits | edge0))
            continue;
        float tv[PK], uv[PK], vv[PK], sh[3][3][PK];
        _mm512_storeu_ps(tv, t);
        _mm512_storeu_ps(uv, _mm512_mul_ps(v, inv));
        _mm512_storeu_ps(vv, _mm512_mul_ps(wv, inv));
        for (int e = 0; edge0 && e < 3; e++) {
            _mm512_storeu_ps(sh[e][0], X[tr[e]]), _mm512_storeu_ps(sh[e][1], Y[tr[e]]);
            _mm512_storeu_ps(sh[e][2], Z[tr[e]]);
        }
        keep_lanes(ct, k, hits, edge0, tv, uv, vv, sh, tmin, lim, rays, 0, bh);
    }
}
#define HAS_CELL8 1
#else
#define HAS_CELL8 0
#endif

#if defined(__x86_64__) && defined(__GNUC__)
/* spans_after for CPUs with AVX-512 (rays->n == PK): the same spans, each
 * eight lanes written whole, so that rays_before's loads of them find one
 * write to read from (written lane by lane, the next node's test waited
 * for them to land). cull_limit's operations lane by lane. */
__attribute__((target("avx512f"))) static void spans_after_avx512(pack *p, const mr_drays *rays,
                                                                  uint32_t live, uint32_t ready)
{
    for (int h = 0; h < PK; h += 8) {
        const __m512d lim = cull_limit8(_mm256_loadu_ps(rays->tmax + h));
        const __m512d t1 = _mm512_mask_blend_pd((__mmask8)(ready >> h), _mm512_set1_pd(-INFINITY), lim);
        _mm512_storeu_pd(p->t1 + h, _mm512_mask_blend_pd((__mmask8)(live >> h), _mm512_loadu_pd(p->t1 + h), t1));
    }
}
#endif

/* After a cell: each of the rays `live` has its span limit p->t1 follow
 * its tmax (`ready`: the rays tested; any other, whose direction hits
 * nothing: -inf). */
static inline void spans_after(pack *p, const mr_drays *rays, uint32_t live, uint32_t ready)
{
#if defined(__x86_64__) && defined(__GNUC__)
    if (rays->n == PK && mr_simd_avx512()) {
        spans_after_avx512(p, rays, live, ready);
        return;
    }
#endif
    for (uint32_t m = live; m; m &= m - 1) {
        const int k = __builtin_ctz(m);
        p->t1[k] = ready >> k & 1u ? cull_limit(rays->tmax[k]) : -INFINITY;
    }
}

/* The packet's rays `live` against the cell's micro-triangles (cell_test
 * each, eight at a time, or the packet's sixteen at once); each one's span
 * limit p->t1 follows its tmax (spans_after). */
static void cell_rays(const cell_tris *ct, const mr_drays *rays, pack *p, pack_wt *w, uint32_t live,
                      best *bh, mr_dstats *st)
{
    uint32_t ready = 0, rest = live;
#if HAS_CELL8
    if (mr_popcount32(live) >= CELL8_MIN && rays->n == PK && mr_simd_avx512()) {
        for (int h = 0; h < PK / 8; h++)
            if (live >> 8 * h & ~(w->made >> 8 * h) & 0xffu)
                half_wt_avx2(rays, w, h);
        ready = live & w->made;
        cell_test16(ct, w, ready, rays, bh, st);
        rest = 0;
    }
#endif
    for (int h = 0; h < PK / 8; h++) {
        uint32_t half = rest >> 8 * h & 0xffu;
        if (!half)
            continue;
#if HAS_CELL8
        if (mr_popcount32(half) >= CELL8_MIN && rays->n >= 8 * h + 8 &&
            __builtin_cpu_supports("avx2")) {
            if (half & ~(w->made >> 8 * h))
                half_wt_avx2(rays, w, h);
            half &= w->made >> 8 * h;
            cell_test8(ct, w, h, half, rays, bh, st);
            ready |= half << 8 * h;
            continue;
        }
#endif
        for (uint32_t m = half; m; m &= m - 1) {
            const int k = 8 * h + __builtin_ctz(m);
            if (!lane_wt(rays, w, k))
                continue;
            const mr_wt_ray wk = wt_get(w, k);
            cell_test(ct, &wk, rays->tmin[k], &rays->tmax[k], &bh[k], st);
            ready |= 1u << k;
        }
    }
    spans_after(p, rays, live, ready);
}

uint32_t mr_dtrace_intersect_packet(const mr_dscene *s, uint32_t t, const mr_drays *rays,
                                    uint32_t lanes, mr_dhit hits[MR_DPACKET_MAX], mr_dstats *st)
{
    const mr_dbase *b = &s->bases[t];
    const mr_dgrad *gr = &s->grads[t];
    const mr_dgrid *g = s->grid;
    uint32_t hit = 0, inpack = 0;
    pack_wt wt; /* the packed rays' set-ups at cells */
    wt.made = 0;
    pack p;
    if (packs(s, b, gr)) {
        /* T's box, in its frame: much tighter than its Embree box, which
         * is axis-aligned in the world (the sphere of 960 faces: 40 % of
         * the calls had no ray in it); the rays that miss it miss T */
        uint32_t packed;
        const uint32_t near_t = TRI_LANES(gr, &p, PACK_ENTER(gr, b, rays, lanes, &p, &packed));
        lanes &= ~(packed & ~near_t);
        /* a lone ray too: the packet's walk finds its nodes' child boxes
         * kept, where mr_dtrace_intersect makes them again (the
         * procedural sphere at range 64: 0.964 of the trace's
         * instructions; the texture sphere at 100 texels a unit: 0.983) */
        inpack = near_t;
    }
    for (uint32_t m = lanes & ~inpack; m; m &= m - 1) {
        const int k = __builtin_ctz(m);
        const mr_dray *rk = rays->setup(rays->ctx, (unsigned)rays->n, (unsigned)k);
        if (rk && mr_dtrace_intersect(s, t, rk, rays->tmin[k], &rays->tmax[k], false, &hits[k], st))
            hit |= 1u << k;
    }
    if (!inpack)
        return hit;
    best bh[PK]; /* the packed rays' (a hit's fields are read once .hit is set) */
    for (uint32_t m = inpack; m; m &= m - 1)
        bh[__builtin_ctz(m)].hit = false;
    pentry stack[STACK_MAX];
    int sp = 0;
    const mr_dproc *pr = s->proc;
    { /* the nodes the rays start at (packet_start) that they enter */
        tnode rs[4];
        const int nr = packet_start(s, t, gr, &p, inpack, rs);
        double blo[3][4], bhi[3][4], rhlo[4] = {0}, rhhi[4] = {0};
        unsigned boxed = 0;
        for (int k = 0; k < nr; k++) {
            double lo[3], hi[3], x0, x1, y0, y1;
            if (!tnode_region(s, b, gr, &rs[k], &x0, &x1, &y0, &y1, &rhlo[k], &rhhi[k], st))
                continue;
            local_box(gr, x0, x1, y0, y1, rhlo[k], rhhi[k], lo, hi);
            for (int a = 0; a < 3; a++)
                blo[a][k] = lo[a], bhi[a][k] = hi[a];
            boxed |= 1u << k;
        }
        sp = packet_push(&p, inpack, rs, nr, boxed, blo, bhi, rhlo, rhhi, stack, sp);
    }
    while (sp > 0) {
        /* read in place, field by field as packet_push wrote it (a copy
         * of the whole entry waited for those writes to land: read in
         * place, the procedural sphere's trace takes 0.996 of the time);
         * every read of e comes before the push that overwrites its slot */
        const pentry *e = &stack[--sp];
        uint32_t live = rays_before(&p, e->mask, e->tnear);
        if (!live)
            continue;
        int64_t ci, cj;
        int half;
        if (tnode_leaf(s, &e->n, &ci, &cj, &half)) {
            const cell_tris *ct = cell_get(s, t, b, ci, cj, half, st);
            if (ct)
                cell_rays(ct, rays, &p, &wt, live, bh, st);
            continue;
        }
        tnode ch[4];
        double blo[3][4], bhi[3][4], chlo[4] = {0}, chhi[4] = {0};
        unsigned boxed = 0;
        int nc;
#if defined(__SSE2__)
        if (!pr && e->n.d.level <= (int)g->levels) { /* within a period: made together */
            boxed = TEX_CHILD_BOXES(g, b, gr, &e->n.d, blo, bhi, st);
            nc = 4;
            for (int c = 0; c < 4; c++)
                ch[c].d = (dnode){.level = e->n.d.level - 1, .tx = e->n.d.tx, .ty = e->n.d.ty,
                                  .I = e->n.d.I * 2 + (uint32_t)(c & 1),
                                  .J = e->n.d.J * 2 + (uint32_t)(c >> 1)};
        } else
#endif
#if HAS_SLAB_FOUR
        if (pr && __builtin_cpu_supports("avx2")) {
            const node_boxes *nb = proc_child_boxes_kept(s, t, b, gr, e, ch, st);
            if (nb) { /* entered where they are kept (both paths through pointers to
                       * the boxes cost the texture sphere 3 %: a texture's stay here) */
                sp = packet_push(&p, live, ch, 4, nb->boxed, nb->lo, nb->hi, nb->hl, nb->hh,
                                 stack, sp);
                continue;
            }
            boxed = proc_child_boxes_avx2(pr, b, gr, e, &p, live, ch, blo, bhi, chlo, chhi, st);
            nc = 4;
        } else
#endif
        {
            nc = tnode_children(s, &e->n, ch);
            for (int c = 0; c < nc; c++) {
                double lo[3], hi[3], x0, x1, y0, y1;
                double klo, khi;
                lrect lrc;
                bool framed = false;
                /* (where the parent's heights are T's, T's box test was
                 * already this one but for the rectangle: it seldom culls,
                 * and cost the procedural sphere at range 64 up to 6 %) */
                if (pr && (e->hlo > gr->hlo || e->hhi < gr->hhi) && worth_parent_test(pr, &ch[c].p) &&
                    !mr_dproc_square_heights_kept(pr, ch[c].p.level, ch[c].p.x, ch[c].p.y, &klo,
                                                  &khi)) {
                    /* the parent's heights bound the child's: rays that
                     * miss that box miss it, and its own bound need not be
                     * made */
                    double near;
                    pnode_rect(&ch[c].p, &x0, &x1, &y0, &y1);
                    local_rect(gr, x0, x1, y0, y1, &lrc);
                    framed = true;
                    lrect_box(gr, &lrc, e->hlo, e->hhi, lo, hi);
                    if (!SLAB_PACK(&p, live, lo, hi, &near))
                        continue;
                }
                if (!tnode_region(s, b, gr, &ch[c], &x0, &x1, &y0, &y1, &chlo[c], &chhi[c], st))
                    continue;
                if (!framed)
                    local_rect(gr, x0, x1, y0, y1, &lrc);
                lrect_box(gr, &lrc, chlo[c], chhi[c], lo, hi);
                for (int a = 0; a < 3; a++)
                    blo[a][c] = lo[a], bhi[a][c] = hi[a];
                boxed |= 1u << c;
            }
        }
        sp = packet_push(&p, live, ch, nc, boxed, blo, bhi, chlo, chhi, stack, sp);
    }
    for (uint32_t m = inpack; m; m &= m - 1) {
        int k = __builtin_ctz(m);
        if (bh[k].hit) {
            finish(b, &bh[k], &hits[k]);
            hit |= 1u << k;
        }
    }
    return hit;
}

/* ---- ray marching ------------------------------------------------------------------- */

/* The signed height of x above the surface of T: x is mapped back to its
 * base point b by following the unit interpolated normal (x = P(b) + s
 * N(b) / |N(b)|, the displacement's own direction, so the shells of
 * neighbouring triangles meet without gaps), found by three fixed-point
 * steps from the projection along the face normal (each: the plane point
 * x - s n of the last normal n); the height above is s - h(b), and the
 * barycentrics of b come back for the hit. */
static double height_above(const mr_dscene *s, const mr_dbase *b, const double x[3],
                           const double fn[3], double *b1, double *b2)
{
    double e1[3], e2[3];
    for (int c = 0; c < 3; c++) {
        e1[c] = b->p[1][c] - b->p[0][c];
        e2[c] = b->p[2][c] - b->p[0][c];
    }
    double d11 = e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2];
    double d12 = e1[0] * e2[0] + e1[1] * e2[1] + e1[2] * e2[2];
    double d22 = e2[0] * e2[0] + e2[1] * e2[1] + e2[2] * e2[2];
    double det = d11 * d22 - d12 * d12;
    double n[3] = {fn[0], fn[1], fn[2]}, dist = 0, P[3] = {0}, N[3];
    for (int it = 0; it < 4; it++) {
        double xn = (x[0] - b->p[0][0]) * fn[0] + (x[1] - b->p[0][1]) * fn[1] + (x[2] - b->p[0][2]) * fn[2];
        double nf = n[0] * fn[0] + n[1] * fn[1] + n[2] * fn[2];
        dist = nf > 1e-6 ? xn / nf : xn;
        double w[3];
        for (int c = 0; c < 3; c++)
            w[c] = x[c] - dist * (nf > 1e-6 ? n[c] : fn[c]) - b->p[0][c];
        double w1 = w[0] * e1[0] + w[1] * e1[1] + w[2] * e1[2];
        double w2 = w[0] * e2[0] + w[1] * e2[1] + w[2] * e2[2];
        *b1 = det != 0 ? (d22 * w1 - d12 * w2) / det : 0;
        *b2 = det != 0 ? (d11 * w2 - d12 * w1) / det : 0;
        for (int c = 0; c < 3; c++) {
            P[c] = b->p[0][c] + *b1 * e1[c] + *b2 * e2[c];
            N[c] = b->n[0][c] + *b1 * (b->n[1][c] - b->n[0][c]) + *b2 * (b->n[2][c] - b->n[0][c]);
        }
        double l = sqrt(N[0] * N[0] + N[1] * N[1] + N[2] * N[2]);
        if (!(l > 1e-9))
            break;
        for (int c = 0; c < 3; c++)
            n[c] = N[c] / l;
    }
    double q[2];
    for (int c = 0; c < 2; c++)
        q[c] = b->g[0][c] + *b1 * (b->g[1][c] - b->g[0][c]) + *b2 * (b->g[2][c] - b->g[0][c]);
    double h = mr_dsurf_height_at(&s->heights, q[0], q[1]);
    (void)P;
    return dist - h;
}

/* Geometric normal of the micro-triangle of base triangle t holding its
 * barycentric point (b1, b2): a marched hit's. */
static mr_vec3 marched_normal(const mr_dscene *s, uint32_t t, float b1, float b2)
{
    const mr_dbase *b = &s->bases[t];
    mr_vec3 face = mr_v3((float)((b->p[1][1] - b->p[0][1]) * (b->p[2][2] - b->p[0][2]) -
                                 (b->p[1][2] - b->p[0][2]) * (b->p[2][1] - b->p[0][1])),
                         (float)((b->p[1][2] - b->p[0][2]) * (b->p[2][0] - b->p[0][0]) -
                                 (b->p[1][0] - b->p[0][0]) * (b->p[2][2] - b->p[0][2])),
                         (float)((b->p[1][0] - b->p[0][0]) * (b->p[2][1] - b->p[0][1]) -
                                 (b->p[1][1] - b->p[0][1]) * (b->p[2][0] - b->p[0][0])));
    if (b->flat)
        return face;
    double x = b->g[0][0] + b1 * (b->g[1][0] - b->g[0][0]) + b2 * (b->g[2][0] - b->g[0][0]);
    double y = b->g[0][1] + b1 * (b->g[1][1] - b->g[0][1]) + b2 * (b->g[2][1] - b->g[0][1]);
    /* the hit's cell: usually the one the traversal just made */
    const cell_tris *ct = cell_get(s, t, b, (int64_t)floor(x), (int64_t)floor(y), 2, NULL);
    if (!ct)
        return face;
    const mr_dcell *c = &ct->c;
    int bestk = -1;
    double bestw = -INFINITY;
    for (int k = 0; k < c->nt; k++) {
        const mr_dvert *a = &c->v[c->tri[k][0]], *bb = &c->v[c->tri[k][1]], *cc = &c->v[c->tri[k][2]];
        double d = (bb->x - a->x) * (cc->y - a->y) - (bb->y - a->y) * (cc->x - a->x);
        if (d == 0)
            continue;
        double w1 = ((x - a->x) * (cc->y - a->y) - (y - a->y) * (cc->x - a->x)) / d;
        double w2 = ((bb->x - a->x) * (y - a->y) - (bb->y - a->y) * (x - a->x)) / d;
        double w = fmin(fmin(w1, w2), 1 - w1 - w2);
        if (w > bestw)
            bestw = w, bestk = k;
    }
    if (bestk < 0)
        return face;
    const uint8_t *v = c->tri[bestk];
    return mr_v3_cross(mr_v3_sub(ct->V[v[1]], ct->V[v[0]]), mr_v3_sub(ct->V[v[2]], ct->V[v[0]]));
}

bool mr_dtrace_march(const mr_dscene *s, uint32_t t, const mr_dray *r, float tmin, float *tmax,
                     mr_dhit *hit, mr_dstats *st)
{
    const mr_dbase *b = &s->bases[t];
    const mr_dgrad *gr = &s->grads[t];
    float flo[3], fhi[3];
    mr_dtrace_tri_box(b, &s->heights, gr, flo, fhi);
    double lo[3] = {flo[0], flo[1], flo[2]}, hi[3] = {fhi[0], fhi[1], fhi[2]}, t0;
    if (!slab(r, lo, hi, tmin, *tmax, &t0))
        return false;
    /* the exit distance: the same slab test from the far side */
    double t1 = *tmax;
    for (int a = 0; a < 3; a++)
        if (!r->par[a]) {
            double n = (lo[a] - r->o[a]) * r->inv[a], f = (hi[a] - r->o[a]) * r->inv[a];
            t1 = fmin(t1, fmax(n, f));
        }
    if (!(t1 > t0))
        return false;
    double e1[3], e2[3], fn[3];
    for (int c = 0; c < 3; c++) {
        e1[c] = b->p[1][c] - b->p[0][c];
        e2[c] = b->p[2][c] - b->p[0][c];
    }
    fn[0] = e1[1] * e2[2] - e1[2] * e2[1];
    fn[1] = e1[2] * e2[0] - e1[0] * e2[2];
    fn[2] = e1[0] * e2[1] - e1[1] * e2[0];
    double fl = sqrt(fn[0] * fn[0] + fn[1] * fn[1] + fn[2] * fn[2]);
    if (!(fl > 0))
        return false;
    for (int c = 0; c < 3; c++)
        fn[c] /= fl;
    unsigned n = s->march_steps ? s->march_steps : 1;
    double dt = (t1 - t0) / n, prev_f = 0, prev_t = t0;
    for (unsigned k = 0; k <= n; k++) {
        double tk = t0 + dt * k, x[3], b1, b2;
        for (int c = 0; c < 3; c++)
            x[c] = r->o[c] + tk * r->d[c];
        double f = height_above(s, b, x, fn, &b1, &b2);
        if (st)
            st->nodes++;
        if (k > 0 && ((prev_f > 0) != (f > 0))) {
            double ts = prev_t + (tk - prev_t) * (prev_f / (prev_f - f));
            for (int c = 0; c < 3; c++)
                x[c] = r->o[c] + ts * r->d[c];
            height_above(s, b, x, fn, &b1, &b2);
            if (b1 >= 0 && b2 >= 0 && b1 + b2 <= 1 && ts >= tmin && ts <= *tmax) {
                *tmax = (float)ts;
                if (hit) {
                    hit->t = (float)ts;
                    hit->b1 = (float)b1;
                    hit->b2 = (float)b2;
                    hit->ng = marched_normal(s, t, (float)b1, (float)b2);
                }
                return true;
            }
        }
        prev_f = f;
        prev_t = tk;
    }
    return false;
}
