/* dsurf.c - the displaced surface over a base triangle (dsurf.h). */
#include "kinds/displaced/dsurf.h"

#include <math.h>
#include <string.h>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif

/* A zero-area triangle in grid space: |det| at most this times the
 * squared size of its grid bounding box (or not finite). */
#define FLAT_REL 1e-12
/* A cell whose corners are all at least this far (relative to the size of
 * the grid coordinates) inside every edge of T is whole: cutting it would
 * make crossings that all lie outside it (their rounding is ~1e-16 of the
 * coordinates), so its two triangles are made directly (mr_dsurf_cell). */
#define INSIDE_MARGIN 1e-9
/* Interpolated normals shorter than this displace nothing (unit corner
 * normals that cancel out: opposing normals, REFERENCE.md 003). */
#define MIN_NORMAL 1e-9

double mr_dsurf_height_at(const mr_dheights *hs, double x, double y)
{
    double fx0 = floor(x), fy0 = floor(y);
    int64_t i = (int64_t)fx0, j = (int64_t)fy0;
    double fx = x - fx0, fy = y - fy0;
    if (fx + fy <= 1.0) {
        double h00 = hs->at(hs->src, i, j);
        return h00 + fx * (hs->at(hs->src, i + 1, j) - h00) + fy * (hs->at(hs->src, i, j + 1) - h00);
    }
    double h11 = hs->at(hs->src, i + 1, j + 1);
    return h11 + (1.0 - fx) * (hs->at(hs->src, i, j + 1) - h11) +
           (1.0 - fy) * (hs->at(hs->src, i + 1, j) - h11);
}

static void set_normal(double out[3], const float *n)
{
    double x = n[0], y = n[1], z = n[2];
    double l = sqrt(x * x + y * y + z * z);
    if (!(l > 0) || !isfinite(l)) {
        out[0] = out[1] = out[2] = 0;
        return;
    }
    out[0] = x / l, out[1] = y / l, out[2] = z / l;
}

void mr_dbase_pose(mr_dbase *b, const float *p[3], const float *n[3])
{
    for (int k = 0; k < 3; k++) {
        for (int c = 0; c < 3; c++)
            b->p[k][c] = p[k][c];
        set_normal(b->n[k], n[k]);
    }
}

static bool lex_less(const double a[2], const double b[2])
{
    return a[0] < b[0] || (a[0] == b[0] && a[1] < b[1]);
}

void mr_dbase_init(mr_dbase *b, const double g[3][2], const float *p[3], const float *n[3],
                   const mr_dheights *hs)
{
    memset(b, 0, sizeof *b);
    memcpy(b->g, g, sizeof b->g);
    mr_dbase_pose(b, p, n);
    for (int e = 0; e < 3; e++)
        b->canon[e] = lex_less(g[(e + 1) % 3], g[e]) ? 1 : 0;
    double ax = g[1][0] - g[0][0], ay = g[1][1] - g[0][1];
    double bx = g[2][0] - g[0][0], by = g[2][1] - g[0][1];
    double det = ax * by - ay * bx;
    double ex = fmax(fmax(g[0][0], g[1][0]), g[2][0]) - fmin(fmin(g[0][0], g[1][0]), g[2][0]);
    double ey = fmax(fmax(g[0][1], g[1][1]), g[2][1]) - fmin(fmin(g[0][1], g[1][1]), g[2][1]);
    double size2 = fmax(ex, ey) * fmax(ex, ey);
    b->flat = !isfinite(det) || !(fabs(det) > FLAT_REL * size2);
    b->orient = det > 0 ? 1 : -1;
    double gm = 0;
    for (int k = 0; k < 3; k++)
        gm = fmax(gm, fmax(fabs(g[k][0]), fabs(g[k][1])));
    b->margin = INSIDE_MARGIN * (1 + gm);
    for (int e = 0; e < 3; e++) {
        const double *a = g[e], *c = g[(e + 1) % 3];
        double nx = -(c[1] - a[1]), ny = c[0] - a[0], l = sqrt(nx * nx + ny * ny);
        if (!(l > 0))
            l = 1;
        nx = b->orient * nx / l, ny = b->orient * ny / l;
        b->edge[e][0] = nx;
        b->edge[e][1] = ny;
        b->edge[e][2] = -(nx * a[0] + ny * a[1]);
    }
    if (!b->flat) {
        b->m[0] = by / det;
        b->m[1] = -ay / det;
        b->m[2] = -bx / det;
        b->m[3] = ax / det;
    }
    for (int k = 0; k < 3; k++)
        b->h[k] = mr_dsurf_height_at(hs, g[k][0], g[k][1]);
}

/* floor(x) as an integer, held to +-2^60 (a coordinate beyond, or NaN,
 * converted as it is would be undefined; such a triangle is refused by
 * its caller for the cells it spans, and its cells' squares at level 62
 * still fit in two per axis) */
static int64_t floor_held(double x)
{
    const int64_t lim = (int64_t)1 << 60;
    return !(x > (double)-lim) ? -lim : x >= (double)lim ? lim : (int64_t)floor(x);
}

void mr_dbase_cells(const mr_dbase *b, int64_t *i0, int64_t *i1, int64_t *j0, int64_t *j1)
{
    double x0 = fmin(fmin(b->g[0][0], b->g[1][0]), b->g[2][0]);
    double x1 = fmax(fmax(b->g[0][0], b->g[1][0]), b->g[2][0]);
    double y0 = fmin(fmin(b->g[0][1], b->g[1][1]), b->g[2][1]);
    double y1 = fmax(fmax(b->g[0][1], b->g[1][1]), b->g[2][1]);
    /* closed squares touching the box: a box edge on a grid line touches
     * the cells on both sides (clipping decides what is there) */
    *i0 = floor_held(x0) - (x0 == floor(x0) ? 1 : 0);
    *i1 = floor_held(x1);
    *j0 = floor_held(y0) - (y0 == floor(y0) ? 1 : 0);
    *j1 = floor_held(y1);
}

/* ---- cutting ------------------------------------------------------------------ */

typedef struct line {
    uint8_t fam;
    int64_t value;
    bool keep_ge; /* keep the side where the coordinate is >= value */
} line;

/* A grid point's x and y are its (double)a and (double)b (every maker
 * sets them so); its diagonal coordinate is a + b rounded once. */
static inline double coord(const mr_dvert *v, uint8_t fam)
{
    if (fam == MR_DLINE_X)
        return v->x;
    if (fam == MR_DLINE_Y)
        return v->y;
    return v->kind == MR_DV_GRID ? (double)(v->a + v->b) : v->x + v->y;
}

/* +1 inside, 0 on the line, -1 outside. */
static inline int side(const mr_dvert *v, const line *l)
{
    double c = coord(v, l->fam), val = (double)l->value;
    int s = c > val ? 1 : c < val ? -1 : 0;
    return l->keep_ge ? s : -s;
}

/* Where base edge e crosses line l: from the edge's canonical endpoints. */
static mr_dvert edge_cross(const mr_dbase *b, int e, const line *l)
{
    int ka = b->canon[e] ? (e + 1) % 3 : e, kb = b->canon[e] ? e : (e + 1) % 3;
    const double *A = b->g[ka], *B = b->g[kb];
    double ca, cb;
    if (l->fam == MR_DLINE_X)
        ca = A[0], cb = B[0];
    else if (l->fam == MR_DLINE_Y)
        ca = A[1], cb = B[1];
    else
        ca = A[0] + A[1], cb = B[0] + B[1];
    double t = cb != ca ? ((double)l->value - ca) / (cb - ca) : 0.5;
    t = t < 0 ? 0 : t > 1 ? 1 : t;
    mr_dvert v = {.kind = MR_DV_EDGE, .idx = (uint8_t)e, .fam = l->fam, .a = l->value, .t = t};
    v.x = l->fam == MR_DLINE_X ? (double)l->value : A[0] + t * (B[0] - A[0]);
    v.y = l->fam == MR_DLINE_Y ? (double)l->value : A[1] + t * (B[1] - A[1]);
    return v;
}

/* Where grid lines a and b (different families) meet: a grid point. */
static mr_dvert grid_cross(const line *a, const line *b)
{
    int64_t x = 0, y = 0;
    const line *l[2] = {a, b};
    bool hx = false, hy = false;
    int64_t d = 0;
    bool hd = false;
    for (int k = 0; k < 2; k++) {
        if (l[k]->fam == MR_DLINE_X)
            x = l[k]->value, hx = true;
        else if (l[k]->fam == MR_DLINE_Y)
            y = l[k]->value, hy = true;
        else
            d = l[k]->value, hd = true;
    }
    if (hd && hx)
        y = d - x;
    else if (hd && hy)
        x = d - y;
    (void)hx, (void)hy;
    mr_dvert v = {.kind = MR_DV_GRID, .a = x, .b = y, .x = (double)x, .y = (double)y};
    return v;
}

/* The vertices one cell's cutting makes: T's corners (or the square's
 * four), then each crossing as it is made (each takes a place in the
 * cut's polygon: at most MR_DSURF_MAX_POLY a cut, six cuts). Polygons name
 * them by index, so a cut moves a byte a vertex, not the record. */
#define POOL_MAX (4 + 6 * MR_DSURF_MAX_POLY)

typedef struct pool {
    int n;
    mr_dvert v[POOL_MAX];
} pool;

/* A polygon whose edge m (vertex m -> m + 1) lies on tag[m]: a base edge
 * (0..2) or a cut line (3 + its index in the cut list); its vertices are
 * the pool's v[m]. */
typedef struct poly {
    int n;
    uint8_t v[MR_DSURF_MAX_POLY];
    uint8_t tag[MR_DSURF_MAX_POLY];
} poly;

/* A crossing made from the edge tagged t and line l into the pool: its index. */
static uint8_t add_cross(const mr_dbase *b, pool *pl, uint8_t t, const line *lines, const line *l)
{
    pl->v[pl->n] = t < 3 ? edge_cross(b, t, l) : grid_cross(&lines[t - 3], l);
    return (uint8_t)pl->n++;
}

static void cut(const mr_dbase *b, pool *pl, const poly *in, const line *lines, int li, poly *out)
{
    const line *l = &lines[li];
    uint8_t ltag = (uint8_t)(3 + li);
    out->n = 0;
    bool wrap_line = false; /* the edge into the first output runs along l */
    int sp = in->n ? side(&pl->v[in->v[in->n - 1]], l) : 0;
    for (int m = 0; m < in->n; m++) {
        int pm = m ? m - 1 : in->n - 1;
        uint8_t tpq = in->tag[pm], tq = in->tag[m];
        int sq = side(&pl->v[in->v[m]], l);
        if (sq >= 0) {
            if (sp < 0) {
                if (out->n)
                    out->tag[out->n - 1] = ltag;
                else
                    wrap_line = true;
                if (sq > 0 && out->n < MR_DSURF_MAX_POLY) {
                    out->v[out->n] = add_cross(b, pl, tpq, lines, l);
                    out->tag[out->n++] = tpq;
                }
            }
            if (out->n < MR_DSURF_MAX_POLY) {
                out->v[out->n] = in->v[m];
                out->tag[out->n++] = tq;
            }
        } else if (sp > 0) {
            if (out->n < MR_DSURF_MAX_POLY) {
                out->v[out->n] = add_cross(b, pl, tpq, lines, l);
                out->tag[out->n++] = ltag;
            }
        } else if (sp == 0 && out->n) {
            out->tag[out->n - 1] = ltag;
        }
        sp = sq;
    }
    if (wrap_line && out->n)
        out->tag[out->n - 1] = ltag;
    if (out->n < 3)
        out->n = 0;
}

static bool same_vert(const mr_dvert *a, const mr_dvert *b)
{
    if (a->kind != b->kind)
        return false;
    switch (a->kind) {
    case MR_DV_BASE: return a->idx == b->idx;
    case MR_DV_GRID: return a->a == b->a && a->b == b->b;
    default: return a->idx == b->idx && a->fam == b->fam && a->a == b->a;
    }
}

static int add_vert(mr_dcell *c, const mr_dvert *v)
{
    for (int k = 0; k < c->nv; k++)
        if (same_vert(&c->v[k], v))
            return k;
    c->v[c->nv] = *v;
    return c->nv++;
}

/* T as the first polygon, its corners the pool's first three vertices. */
static void start(const mr_dbase *b, pool *pl, poly *p)
{
    pl->n = p->n = 3;
    for (int k = 0; k < 3; k++) {
        pl->v[k] = (mr_dvert){.kind = MR_DV_BASE, .idx = (uint8_t)k, .x = b->g[k][0], .y = b->g[k][1]};
        p->v[k] = (uint8_t)k;
        p->tag[k] = (uint8_t)k;
    }
}

/* Rotates a polygon to start at its lexicographically smallest vertex
 * (x, then y): pieces then come out the same whichever corner of T the
 * cutting started from, and whole cells match the direct path below. */
static void rotate_canonical(const pool *pl, poly *p)
{
    int m = 0;
    for (int k = 1; k < p->n; k++) {
        const mr_dvert *a = &pl->v[p->v[k]], *c = &pl->v[p->v[m]];
        if (a->x < c->x || (a->x == c->x && a->y < c->y))
            m = k;
    }
    if (m == 0)
        return;
    uint8_t v[MR_DSURF_MAX_POLY], tag[MR_DSURF_MAX_POLY];
    memcpy(v, p->v, (size_t)p->n);
    memcpy(tag, p->tag, (size_t)p->n);
    for (int k = 0; k < p->n; k++) {
        p->v[k] = v[(k + m) % p->n];
        p->tag[k] = tag[(k + m) % p->n];
    }
}

/* How T meets cell (i, j), from the signs of T's three edge lines at the
 * cell's four corners, each taken only when clearly away from the line
 * (b->margin, INSIDE_MARGIN): */
enum {
    CELL_WHOLE, /* every corner clearly inside every edge: the whole cell */
    CELL_EDGE,  /* clearly inside two edges, clearly on both sides of the
                 * third (*edge; *inside: its corners k (i + (k & 1),
                 * j + (k >> 1)) inside it): the square cut by that edge
                 * alone */
    CELL_CUT    /* anything else: T cut by the cell's lines */
};

/* Per edge of T, the corners k of cell (i, j) clearly inside it (bit k of
 * in[e]) and clearly outside (out[e]): each corner's value of the edge's
 * line, (a x + b y) + c, against the margin (a NaN is neither). SSE2
 * takes two corners a vector, the same operations lane by lane; the
 * branches of a corner-by-corner loop (which corners are in is anyone's
 * guess near T's edges) were 3 % of the texture sphere's walk. */
static void corner_sides(const mr_dbase *b, int64_t i, int64_t j, unsigned in[3], unsigned out[3])
{
#if defined(__SSE2__)
    const __m128d x = _mm_set_pd((double)(i + 1), (double)i); /* lanes: x = i, i + 1 */
    const __m128d y0 = _mm_set1_pd((double)j), y1 = _mm_set1_pd((double)(j + 1));
    const __m128d hi = _mm_set1_pd(b->margin), lo = _mm_set1_pd(-b->margin);
    for (int e = 0; e < 3; e++) {
        const double *l = b->edge[e];
        const __m128d ax = _mm_mul_pd(_mm_set1_pd(l[0]), x), by = _mm_set1_pd(l[1]), c = _mm_set1_pd(l[2]);
        const __m128d v0 = _mm_add_pd(_mm_add_pd(ax, _mm_mul_pd(by, y0)), c);
        const __m128d v1 = _mm_add_pd(_mm_add_pd(ax, _mm_mul_pd(by, y1)), c);
        in[e] = (unsigned)(_mm_movemask_pd(_mm_cmpgt_pd(v0, hi)) |
                           _mm_movemask_pd(_mm_cmpgt_pd(v1, hi)) << 2);
        out[e] = (unsigned)(_mm_movemask_pd(_mm_cmplt_pd(v0, lo)) |
                            _mm_movemask_pd(_mm_cmplt_pd(v1, lo)) << 2);
    }
#else
    for (int e = 0; e < 3; e++) {
        const double *l = b->edge[e];
        in[e] = out[e] = 0;
        for (int k = 0; k < 4; k++) {
            double x = (double)(i + (k & 1)), y = (double)(j + (k >> 1));
            double v = l[0] * x + l[1] * y + l[2];
            in[e] |= (unsigned)(v > b->margin) << k;
            out[e] |= (unsigned)(v < -b->margin) << k;
        }
    }
#endif
}

static int cell_case(const mr_dbase *b, int64_t i, int64_t j, int *edge, unsigned *inside)
{
    *edge = -1;
    if (b->flat)
        return CELL_CUT;
    unsigned in[3], out[3];
    corner_sides(b, i, j, in, out);
    /* the edges some corner is not clearly inside */
    const unsigned partial =
        (unsigned)(in[0] != 15u) | (unsigned)(in[1] != 15u) << 1 | (unsigned)(in[2] != 15u) << 2;
    if (!partial)
        return CELL_WHOLE;
    const int e = __builtin_ctz(partial);
    /* two edges, or a corner near the one edge's line: cut */
    if ((partial & (partial - 1)) || (in[e] | out[e]) != 15u)
        return CELL_CUT;
    *edge = e;
    *inside = in[e];
    return CELL_EDGE;
}

bool mr_dsurf_cell_inside(const mr_dbase *b, int64_t i, int64_t j)
{
    int e;
    unsigned inside;
    return cell_case(b, i, j, &e, &inside) == CELL_WHOLE;
}

/* A whole cell: corners 0 (i, j), 1 (i+1, j), 2 (i, j+1), 3 (i+1, j+1) and
 * the triangles the cutting would make (in T's orientation, starting at the
 * smallest corner). */
static void whole_cell(const mr_dbase *b, int64_t i, int64_t j, int half, mr_dcell *out)
{
    out->nv = 4;
    for (int k = 0; k < 4; k++) {
        int64_t x = i + (k & 1), y = j + (k >> 1);
        out->v[k] = (mr_dvert){.kind = MR_DV_GRID, .a = x, .b = y, .x = (double)x, .y = (double)y};
    }
    static const uint8_t CCW[2][3] = {{0, 1, 2}, {2, 1, 3}}, CW[2][3] = {{0, 2, 1}, {2, 3, 1}};
    out->nt = 0;
    for (int hf = 0; hf < 2; hf++) {
        if (half != 2 && half != hf)
            continue;
        memcpy(out->tri[out->nt], b->orient > 0 ? CCW[hf] : CW[hf], 3);
        out->half[out->nt++] = (uint8_t)hf;
    }
}

/* The cell's lines: x = i and x = i + 1, y = j and y = j + 1 (T's piece
 * keeps the side towards the cell), and the diagonal x + y = i + j + 1
 * (which side: set per half). */
static void cell_lines(int64_t i, int64_t j, line lines[5])
{
    lines[0] = (line){MR_DLINE_X, i, true};
    lines[1] = (line){MR_DLINE_X, i + 1, false};
    lines[2] = (line){MR_DLINE_Y, j, true};
    lines[3] = (line){MR_DLINE_Y, j + 1, false};
    lines[4] = (line){MR_DLINE_D, i + j + 1, false};
}

/* T's piece of the cell: T cut by the cell's four lines (the definition). */
static void cut_piece(const mr_dbase *b, const line lines[5], pool *pl, poly *out)
{
    poly a, c;
    start(b, pl, &a);
    cut(b, pl, &a, lines, 0, &c);
    cut(b, pl, &c, lines, 1, &a);
    cut(b, pl, &a, lines, 2, &c);
    cut(b, pl, &c, lines, 3, out);
}

/* T's piece of a CELL_EDGE cell: its square, corners in T's orientation,
 * cut by edge e (inside: cell_case's corners inside e). The polygon cut_piece makes, up to where it starts: the
 * same corners (grid points, as grid_cross makes them), the same two
 * crossings (edge_cross of e with the same lines), the same edge tags
 * (a side of the square: its line's; the stretch along e: e). Every
 * decision cut_piece takes on the way follows the exact geometry, as no
 * corner, and so no crossing, lies within the margin of a line (the
 * crossings' rounding is ~1e-16 of the coordinates). Where the cutting
 * starts does not matter: fan_halves' cut gives the same polygon from
 * each start, and rotate_canonical starts it at the same vertex. */
static void edge_piece(const mr_dbase *b, int64_t i, int64_t j, int e, unsigned inside,
                       const line lines[5], pool *pl, poly *out)
{
    /* the square's corners counter-clockwise from (i, j), and the line
     * the side from corner k to corner k + 1 lies on */
    static const int X[4] = {0, 1, 1, 0}, Y[4] = {0, 0, 1, 1}, SIDE[4] = {2, 1, 3, 0};
    uint8_t tag[4];
    bool in[4];
    for (int k = 0; k < 4; k++) {
        /* clockwise: (i, j), (i, j + 1), (i + 1, j + 1), (i + 1, j) */
        const int q = b->orient > 0 ? k : (4 - k) % 4, next = b->orient > 0 ? q : (q + 3) % 4;
        const int64_t x = i + X[q], y = j + Y[q];
        pl->v[k] = (mr_dvert){.kind = MR_DV_GRID, .a = x, .b = y, .x = (double)x, .y = (double)y};
        tag[k] = (uint8_t)(3 + SIDE[next]);
        in[k] = inside >> (X[q] + 2 * Y[q]) & 1u;
    }
    pl->n = 4;
    out->n = 0;
    for (int m = 0; m < 4; m++) {
        const int pm = (m + 3) % 4;
        if (in[m] != in[pm]) { /* the side from pm to m crosses e */
            out->v[out->n] = add_cross(b, pl, (uint8_t)e, lines, &lines[tag[pm] - 3]);
            out->tag[out->n++] = in[m] ? tag[pm] : (uint8_t)e;
        }
        if (in[m]) {
            out->v[out->n] = (uint8_t)m;
            out->tag[out->n++] = tag[m];
        }
    }
}

/* The fan of a half's polygon into out, its vertices idx[0 .. n) (their
 * indices in out, from the polygon's canonical start): triangles (0, k,
 * k + 1) of half hf. */
static void fan_out(mr_dcell *out, const int *idx, int n, int hf)
{
    for (int k = 1; k + 1 < n; k++) {
        out->tri[out->nt][0] = (uint8_t)idx[0];
        out->tri[out->nt][1] = (uint8_t)idx[k];
        out->tri[out->nt][2] = (uint8_t)idx[k + 1];
        out->half[out->nt++] = (uint8_t)hf;
    }
}

/* The micro-triangles of T's piece a of the cell: each half of it (the
 * piece cut by the diagonal), started at its smallest vertex and fanned. */
static void fan_halves(const mr_dbase *b, pool *pl, const poly *a, line lines[5], int half,
                       mr_dcell *out)
{
    out->nv = out->nt = 0;
    if (!a->n)
        return;
    for (int hf = 0; hf < 2; hf++) {
        if (half != 2 && half != hf)
            continue;
        poly c;
        lines[4].keep_ge = hf == 1;
        cut(b, pl, a, lines, 4, &c);
        if (!c.n)
            continue;
        rotate_canonical(pl, &c);
        int idx[MR_DSURF_MAX_POLY];
        for (int k = 0; k < c.n; k++)
            idx[k] = add_vert(out, &pl->v[c.v[k]]);
        fan_out(out, idx, c.n, hf);
    }
}

/* fan_halves for a piece a of T that mr_dsurf_cell made (edge_piece's or
 * cut_piece's, its pool pl), without cutting: each half is a run of a's
 * vertices, with a crossing of the diagonal where an edge of a passes from
 * one side to the other (a convex piece: at most two). Each crossing is
 * made once for both halves, from the tag of the edge it is on, as `cut`
 * makes it (a side of the square never crosses the diagonal: it touches
 * it at most at a corner); vertices are then told apart by their place in
 * the pool (no two of its records are the same vertex; a crossing that is
 * the same record as an earlier one, which only a degenerate piece could
 * make, takes its place) instead of by comparing records. The same
 * vertices in the same order, the same triangles (test_cells_are_their_cuts).
 * The edge pieces' version: the texture sphere's trace 0.97-0.98 of the
 * time with cutting (docs/performance.md, stop 63); for the cut pieces
 * too, 0.991 of the procedural sphere's instructions at range 64 (stop 69). */
static void fan_piece_halves(const mr_dbase *b, pool *pl, const poly *a, const line lines[5], int half,
                             mr_dcell *out)
{
    out->nv = out->nt = 0;
    if (!a->n)
        return;
    const line *d = &lines[4];
    const double dv = (double)d->value;
    int sd[MR_DSURF_MAX_POLY]; /* each vertex's side of the diagonal: the upper half's */
    int xd[MR_DSURF_MAX_POLY]; /* the crossing on a's edge into vertex m: its place in the pool, once made */
    for (int m = 0; m < a->n; m++) {
        const double c = coord(&pl->v[a->v[m]], MR_DLINE_D);
        sd[m] = c > dv ? 1 : c < dv ? -1 : 0;
        xd[m] = -1;
    }
    const int first_cross = pl->n;
    int at[POOL_MAX]; /* a pool vertex's index in out, or -1 (the pool's and the crossings') */
    for (int k = 0; k < pl->n + a->n && k < POOL_MAX; k++)
        at[k] = -1;
    for (int hf = 0; hf < 2; hf++) {
        if (half != 2 && half != hf)
            continue;
        const int sign = hf == 1 ? 1 : -1;
        poly c = {0}; /* (its tags are not read after the diagonal) */
        int sp = sign * sd[a->n - 1];
        for (int m = 0; m < a->n; m++) {
            const int sq = sign * sd[m];
            if ((sp < 0 && sq > 0) || (sp > 0 && sq < 0)) {
                if (xd[m] < 0) {
                    const int pm = m ? m - 1 : a->n - 1;
                    const int x = add_cross(b, pl, a->tag[pm], lines, d);
                    xd[m] = x;
                    for (int k = first_cross; k < x; k++)
                        if (same_vert(&pl->v[k], &pl->v[x])) {
                            xd[m] = k;
                            break;
                        }
                }
                if (c.n < MR_DSURF_MAX_POLY) /* (as `cut` holds it) */
                    c.v[c.n++] = (uint8_t)xd[m];
            }
            if (sq >= 0 && c.n < MR_DSURF_MAX_POLY)
                c.v[c.n++] = a->v[m];
            sp = sq;
        }
        if (c.n < 3)
            continue;
        rotate_canonical(pl, &c);
        int idx[MR_DSURF_MAX_POLY];
        for (int k = 0; k < c.n; k++) {
            const int v = c.v[k];
            if (at[v] < 0) {
                out->v[out->nv] = pl->v[v];
                at[v] = out->nv++;
            }
            idx[k] = at[v];
        }
        fan_out(out, idx, c.n, hf);
    }
}

void mr_dsurf_cell(const mr_dbase *b, int64_t i, int64_t j, int half, mr_dcell *out)
{
    int e;
    unsigned inside;
    const int how = cell_case(b, i, j, &e, &inside);
    if (how == CELL_WHOLE) {
        whole_cell(b, i, j, half, out);
        return;
    }
    line lines[5];
    cell_lines(i, j, lines);
    pool pl;
    poly a;
    if (how == CELL_EDGE)
        edge_piece(b, i, j, e, inside, lines, &pl, &a);
    else
        cut_piece(b, lines, &pl, &a);
    fan_piece_halves(b, &pl, &a, lines, half, out);
}

void mr_dsurf_cell_cut(const mr_dbase *b, int64_t i, int64_t j, int half, mr_dcell *out)
{
    line lines[5];
    cell_lines(i, j, lines);
    pool pl;
    poly a;
    cut_piece(b, lines, &pl, &a);
    fan_halves(b, &pl, &a, lines, half, out);
}

/* ---- evaluation ---------------------------------------------------------------- */

static double edge_height(const mr_dheights *hs, const mr_dvert *v)
{
    int64_t k = v->a;
    if (v->fam == MR_DLINE_X) {
        double f0 = floor(v->y);
        int64_t j0 = (int64_t)f0;
        double f = v->y - f0, h0 = hs->at(hs->src, k, j0);
        return h0 + f * (hs->at(hs->src, k, j0 + 1) - h0);
    }
    double f0 = floor(v->x);
    int64_t i0 = (int64_t)f0;
    double f = v->x - f0;
    if (v->fam == MR_DLINE_Y) {
        double h0 = hs->at(hs->src, i0, k);
        return h0 + f * (hs->at(hs->src, i0 + 1, k) - h0);
    }
    double h0 = hs->at(hs->src, i0, k - i0);
    return h0 + f * (hs->at(hs->src, i0 + 1, k - i0 - 1) - h0);
}

mr_vec3 mr_dsurf_vertex(const mr_dbase *b, const mr_dheights *hs, const mr_dvert *v)
{
    double P[3], N[3], h;
    if (v->kind == MR_DV_BASE) {
        memcpy(P, b->p[v->idx], sizeof P);
        memcpy(N, b->n[v->idx], sizeof N);
        h = b->h[v->idx];
    } else if (v->kind == MR_DV_EDGE) {
        int e = v->idx;
        int ka = b->canon[e] ? (e + 1) % 3 : e, kb = b->canon[e] ? e : (e + 1) % 3;
        for (int c = 0; c < 3; c++) {
            P[c] = b->p[ka][c] + v->t * (b->p[kb][c] - b->p[ka][c]);
            N[c] = b->n[ka][c] + v->t * (b->n[kb][c] - b->n[ka][c]);
        }
        h = edge_height(hs, v);
    } else {
        double b1, b2;
        mr_dbase_bary(b, (double)v->a, (double)v->b, &b1, &b2);
        for (int c = 0; c < 3; c++) {
            P[c] = b->p[0][c] + b1 * (b->p[1][c] - b->p[0][c]) + b2 * (b->p[2][c] - b->p[0][c]);
            N[c] = b->n[0][c] + b1 * (b->n[1][c] - b->n[0][c]) + b2 * (b->n[2][c] - b->n[0][c]);
        }
        h = hs->at(hs->src, v->a, v->b);
    }
    double l = sqrt(N[0] * N[0] + N[1] * N[1] + N[2] * N[2]);
    double s = l > MIN_NORMAL ? h / l : 0.0;
    return mr_v3((float)(P[0] + s * N[0]), (float)(P[1] + s * N[1]), (float)(P[2] + s * N[2]));
}

/* ---- flat triangles --------------------------------------------------------------- */

/* Position along the boundary: corner k at (k, 0); an edge point on edge e
 * at (e, its parameter from corner e). */
static double boundary_key(const mr_dbase *b, const mr_dvert *v)
{
    if (v->kind == MR_DV_BASE)
        return (double)v->idx * 2.0;
    double s = b->canon[v->idx] ? 1.0 - v->t : v->t;
    return (double)v->idx * 2.0 + (s <= 0 ? 1e-9 : s >= 1 ? 2.0 - 1e-9 : s * 2.0);
}

int mr_dsurf_flat_boundary(const mr_dbase *b, mr_dvert *out, int max)
{
    int64_t i0, i1, j0, j1;
    mr_dbase_cells(b, &i0, &i1, &j0, &j1);
    int n = 0;
    for (int k = 0; k < 3 && n < max; k++)
        out[n++] = (mr_dvert){.kind = MR_DV_BASE, .idx = (uint8_t)k, .x = b->g[k][0], .y = b->g[k][1]};
    for (int64_t j = j0; j <= j1; j++)
        for (int64_t i = i0; i <= i1; i++) {
            mr_dcell c;
            mr_dsurf_cell(b, i, j, 2, &c);
            for (int k = 0; k < c.nv; k++) {
                if (c.v[k].kind != MR_DV_EDGE)
                    continue;
                bool dup = false;
                for (int m = 0; m < n && !dup; m++)
                    dup = same_vert(&out[m], &c.v[k]);
                if (!dup && n < max)
                    out[n++] = c.v[k];
            }
        }
    /* insertion sort by boundary position (few points) */
    for (int a = 1; a < n; a++) {
        mr_dvert v = out[a];
        double key = boundary_key(b, &v);
        int m = a - 1;
        while (m >= 0 && boundary_key(b, &out[m]) > key) {
            out[m + 1] = out[m];
            m--;
        }
        out[m + 1] = v;
    }
    return n;
}
