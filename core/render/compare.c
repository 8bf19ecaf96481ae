/*
 * compare.c - error metrics between a frame and its reference (compare.h).
 *
 * One pass over the pixels, accumulating in double so a 16 M pixel frame
 * sums without losing the small per-pixel errors the metrics exist to show.
 * The pixel order is fixed (row-major), so the figures are deterministic.
 */
#include "render/compare.h"

#include <math.h>
#include <stdatomic.h>
#include <stddef.h>
#include <string.h>

#include "util/parallel.h"

#define MR_PI 3.14159265358979323846

static bool film_usable(const mr_film *f)
{
    return f && f->width > 0 && f->height > 0 && f->r && f->g && f->b && f->z &&
           f->nx && f->ny && f->nz && f->object_id;
}

/* Clamping first makes PSNR a figure about displayable colour, and maps NaN
 * to 0 (fmax returns the non-NaN operand) so one bad pixel cannot poison it. */
static double clamp01(float v)
{
    return fmin(fmax((double)v, 0.0), 1.0);
}

/* Angle in degrees between two normals. They are meant to be unit length,
 * but dividing by the lengths keeps slightly denormalised input honest; a
 * zero normal on a hit pixel is a defect and reads as 90 degrees. */
static double normal_angle_deg(double ax, double ay, double az, double bx, double by,
                               double bz)
{
    double dot = ax * bx + ay * by + az * bz;
    double len = sqrt((ax * ax + ay * ay + az * az) * (bx * bx + by * by + bz * bz));
    double c = len > 0.0 ? dot / len : 0.0;

    if (!(c >= -1.0)) /* also catches NaN */
        c = c != c ? 0.0 : -1.0;
    if (c > 1.0)
        c = 1.0;
    return acos(c) * (180.0 / MR_PI);
}

/* A NaN colour reads as black: it is a speckle itself and moves no
 * neighbour's median more than one dark pixel does. */
static float luminance(const mr_film *f, size_t p)
{
    float y = 0.2126f * f->r[p] + 0.7152f * f->g[p] + 0.0722f * f->b[p];
    return y == y ? y : 0.0f;
}

/* Compare-exchange: *a gets the smaller, *b the larger (branchless). */
static inline void sort2(float *a, float *b)
{
    float lo = *a < *b ? *a : *b, hi = *a < *b ? *b : *a;
    *a = lo, *b = hi;
}

/* The mean of the 4th and 5th smallest of eight: Batcher's odd-even merge
 * network for eight (19 compare-exchanges, no branch to mispredict; the
 * sorted values are the inputs themselves, so the median is bit for bit
 * any sort's). No NaN reaches it (luminance). */
static float median8(float v[8])
{
    sort2(&v[0], &v[1]); sort2(&v[2], &v[3]); sort2(&v[4], &v[5]); sort2(&v[6], &v[7]);
    sort2(&v[0], &v[2]); sort2(&v[1], &v[3]); sort2(&v[4], &v[6]); sort2(&v[5], &v[7]);
    sort2(&v[1], &v[2]); sort2(&v[5], &v[6]);
    sort2(&v[0], &v[4]); sort2(&v[1], &v[5]); sort2(&v[2], &v[6]); sort2(&v[3], &v[7]);
    sort2(&v[2], &v[4]); sort2(&v[3], &v[5]);
    sort2(&v[1], &v[2]); sort2(&v[3], &v[4]); sort2(&v[5], &v[6]);
    return 0.5f * (v[3] + v[4]);
}

typedef struct speckle_pass {
    const mr_film *f;
    atomic_size_t interior, speckles;
} speckle_pass;

/* Film rows 1 + begin .. 1 + end - 1 (the interior rows). */
static void speckle_rows(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    speckle_pass *sp = ctx;
    const mr_film *f = sp->f;
    const ptrdiff_t w = f->width;
    const ptrdiff_t around[8] = {-w - 1, -w, -w + 1, -1, 1, w - 1, w, w + 1};
    const float ratio = (float)MR_SPECKLE_RATIO;
    size_t interior = 0, speckles = 0;
    for (size_t y = begin + 1; y < end + 1; y++)
        for (int x = 1; x + 1 < f->width; x++) {
            size_t p = y * (size_t)w + (size_t)x;
            uint32_t object = f->object_id[p + (size_t)around[0]];
            bool inside = object != 0;
            for (int k = 1; k < 8 && inside; k++)
                inside = f->object_id[p + (size_t)around[k]] == object;
            if (!inside)
                continue;
            interior++;
            float lum[8], top = 0.0f;
            for (int k = 0; k < 8; k++) {
                lum[k] = luminance(f, p + (size_t)around[k]);
                top = lum[k] > top ? lum[k] : top;
            }
            /* the median is at most the largest neighbour (the mean of two
             * of them, rounded), so a pixel at least ratio times that is
             * no speckle: most pixels, without the median */
            float centre = luminance(f, p);
            if (!(centre < ratio * top))
                continue;
            speckles += centre < ratio * median8(lum);
        }
    atomic_fetch_add(&sp->interior, interior);
    atomic_fetch_add(&sp->speckles, speckles);
}

void mr_film_speckles(const mr_film *f, mr_speckle_result *out)
{
    memset(out, 0, sizeof *out);
    if (!f || !f->object_id || !f->r || !f->g || !f->b || f->width < 3 || f->height < 3)
        return;
    /* on every core, 16 rows at a time: counts, so the order rows are
     * taken in cannot change them */
    speckle_pass sp = {.f = f};
    atomic_init(&sp.interior, 0);
    atomic_init(&sp.speckles, 0);
    mr_parallel_for(0, (size_t)f->height - 2, 16, speckle_rows, &sp);
    out->interior = atomic_load(&sp.interior);
    out->speckles = atomic_load(&sp.speckles);
    if (out->interior)
        out->speckle_pct = 100.0 * (double)out->speckles / (double)out->interior;
}

/* The depths pixel (x, y) of f may stand for: within the largest depth step
 * to a 4-neighbour f also hits. A surface at a grazing angle steps far in
 * depth from one pixel to the next, and a pixel at a depth edge may show
 * either side once the edge moves by less than a pixel. */
static double depth_span(const mr_film *f, int x, int y)
{
    size_t i = (size_t)y * (size_t)f->width + (size_t)x;
    double z = f->z[i], span = 0;
    static const int n[4][2] = {{-1, 0}, {1, 0}, {0, -1}, {0, 1}};
    for (int k = 0; k < 4; k++) {
        int qx = x + n[k][0], qy = y + n[k][1];
        if (qx < 0 || qy < 0 || qx >= f->width || qy >= f->height)
            continue;
        size_t q = (size_t)qy * (size_t)f->width + (size_t)qx;
        if (f->object_id[q])
            span = fmax(span, fabs((double)f->z[q] - z));
    }
    return span;
}

/* Where pixel centres say b's surface is more than this far from p, a probe
 * of b's scene looks between them (mr_film_compare_probed). */
#define PROBE_ABOVE 0.25
/* ... on a grid of this step, in pixels. */
#define PROBE_STEP 0.25

/* The least, over probe rays of b's scene on a PROBE_STEP grid around p's
 * centre (rings of growing Chebyshev radius, nearer than best), of the
 * distance of the ray from p's centre plus the depth difference beyond p's
 * span and the ray's share of the span of the pixel it lies in. */
static double probe_between(const mr_film *b, const mr_surface_probe *probe, int x, int y,
                            double za, double span_a, double to_px, double best)
{
    for (int k = 1; k * PROBE_STEP < best && k * PROBE_STEP <= MR_SURFACE_WINDOW; k++)
        for (int j = -k; j <= k; j++)
            for (int i = -k; i <= k; i += (j == -k || j == k) ? 1 : 2 * k) {
                double ox = i * PROBE_STEP, oy = j * PROBE_STEP, d = sqrt(ox * ox + oy * oy);
                if (d >= best)
                    continue;
                double fx = x + 0.5 + ox, fy = y + 0.5 + oy;
                if (fx < 0 || fy < 0 || fx >= b->width || fy >= b->height)
                    continue;
                double z = probe->depth_at(probe->ctx, fx, fy);
                if (!(z > 0))
                    continue;
                double dz = fabs(za - z) - span_a - PROBE_STEP * depth_span(b, (int)fx, (int)fy);
                best = fmin(best, d + fmax(0.0, dz) * to_px);
            }
    return best;
}

/* The largest over a's hits of the pixels to b's surface (mr_compare_result
 * surface_px): for pixel p, the least over b's hits q within
 * MR_SURFACE_WINDOW of their screen distance (|p - q| - 1/2 for q != p: b's
 * edge lies between the two centres, halfway on average) plus the depth
 * difference beyond what the two pixels span (depth_span), in pixels at p's
 * depth (1 / (z * pixel size at depth 1)). Rings of Chebyshev radius r are
 * searched until a farther ring's screen distance alone, r + 1/2, cannot
 * beat the best. With a probe of b's scene, a value above PROBE_ABOVE is
 * then looked for between the pixel centres (probe_between). */
static double surface_px_one_way(const mr_film *a, const mr_film *b, const mr_surface_probe *probe,
                                 double pixel)
{
    int w = a->width, h = a->height;
    double worst = 0;
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            size_t i = (size_t)y * (size_t)w + (size_t)x;
            if (!a->object_id[i])
                continue;
            double za = a->z[i], span_a = depth_span(a, x, y), to_px = 1.0 / (za * pixel);
            double best = MR_SURFACE_WINDOW + 1; /* what the window rules out */
            for (int r = 0; r <= MR_SURFACE_WINDOW && best > r - 0.5; r++)
                for (int dy = -r; dy <= r; dy++)
                    for (int dx = -r; dx <= r; dx += (dy == -r || dy == r) ? 1 : 2 * r) {
                        int qx = x + dx, qy = y + dy;
                        if (qx < 0 || qy < 0 || qx >= w || qy >= h)
                            continue;
                        size_t q = (size_t)qy * (size_t)w + (size_t)qx;
                        if (!b->object_id[q])
                            continue;
                        double dz = fabs(za - (double)b->z[q]) - span_a - depth_span(b, qx, qy);
                        double screen = r ? sqrt((double)(dx * dx + dy * dy)) - 0.5 : 0.0;
                        best = fmin(best, screen + fmax(0.0, dz) * to_px);
                    }
            if (probe && best > PROBE_ABOVE)
                best = probe_between(b, probe, x, y, za, span_a, to_px, best);
            worst = fmax(worst, best);
        }
    return worst;
}

/* surface_px (mr_compare_result), with probes of the scenes or none. */
static double surface_px(const mr_film *a, const mr_film *b, const mr_surface_probe *probe_a,
                         const mr_surface_probe *probe_b)
{
    const mr_film *cam = a->has_camera ? a : b->has_camera ? b : NULL;
    if (!cam || !a->z || !b->z || !a->object_id || !b->object_id || a->width != b->width ||
        a->height != b->height)
        return 0;
    double pixel = 2.0 * tan(0.5 * (double)cam->yfov) / a->height; /* at depth 1 */
    return fmax(surface_px_one_way(a, b, probe_b, pixel), surface_px_one_way(b, a, probe_a, pixel));
}

int mr_film_compare(const mr_film *a, const mr_film *b, double scene_diagonal,
                    mr_compare_result *out, mr_error *err)
{
    return mr_film_compare_probed(a, b, scene_diagonal, NULL, NULL, out, err);
}

int mr_film_compare_probed(const mr_film *a, const mr_film *b, double scene_diagonal,
                           const mr_surface_probe *probe_a, const mr_surface_probe *probe_b,
                           mr_compare_result *out, mr_error *err)
{
    mr_compare_result res;
    double depth_sq = 0.0, depth_max = 0.0, normal_sum = 0.0, normal_max = 0.0;
    double rgb_sq = 0.0, mse;
    size_t n, i;

    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "compare: result pointer is NULL");
    memset(out, 0, sizeof *out);
    if (!film_usable(a) || !film_usable(b))
        return mr_error_set(err, MR_ERR_INVALID, "compare: film is NULL or incomplete");
    if (a->width != b->width || a->height != b->height)
        return mr_error_set(err, MR_ERR_INVALID,
                            "compare: film sizes differ (%dx%d vs %dx%d)", a->width,
                            a->height, b->width, b->height);
    if (!isfinite(scene_diagonal) || !(scene_diagonal > 0.0))
        return mr_error_set(err, MR_ERR_INVALID,
                            "compare: scene_diagonal must be a positive finite number "
                            "(got %g)",
                            scene_diagonal);

    memset(&res, 0, sizeof res);
    n = (size_t)a->width * (size_t)a->height;
    res.pixels = n;

    for (i = 0; i < n; i++) {
        bool ha = a->object_id[i] != 0, hb = b->object_id[i] != 0;
        double dr = clamp01(a->r[i]) - clamp01(b->r[i]);
        double dg = clamp01(a->g[i]) - clamp01(b->g[i]);
        double db = clamp01(a->b[i]) - clamp01(b->b[i]);

        rgb_sq += dr * dr + dg * dg + db * db;
        if (ha || hb)
            res.hit_either++;
        if (ha != hb)
            res.hit_one++;
        if (ha && hb) {
            double dz = fabs((double)a->z[i] - (double)b->z[i]);
            double ang = normal_angle_deg(a->nx[i], a->ny[i], a->nz[i], b->nx[i],
                                          b->ny[i], b->nz[i]);
            res.hit_both++;
            depth_sq += dz * dz;
            if (dz > depth_max)
                depth_max = dz;
            normal_sum += ang;
            if (ang > normal_max)
                normal_max = ang;
        }
    }

    for (int y = 1; y + 1 < a->height; y++)
        for (int x = 1; x + 1 < a->width; x++) {
            size_t p = (size_t)y * (size_t)a->width + (size_t)x;
            bool ha = a->object_id[p] != 0, hb = b->object_id[p] != 0;
            if (ha == hb)
                continue;
            /* a hole: b hits p and its 8 neighbours; a stray: b misses
             * them all */
            bool all = true;
            for (int dy = -1; dy <= 1 && all; dy++)
                for (int dx = -1; dx <= 1; dx++)
                    if ((b->object_id[p + (size_t)((ptrdiff_t)dy * a->width + dx)] != 0) != hb) {
                        all = false;
                        break;
                    }
            res.holes += all && hb;
            res.strays += all && ha;
        }
    if (res.hit_either > 0)
        res.coverage_pct = 100.0 * (double)res.hit_one / (double)res.hit_either;
    if (res.hit_both > 0) {
        res.depth_rmse = sqrt(depth_sq / (double)res.hit_both) / scene_diagonal;
        res.depth_max = depth_max / scene_diagonal;
        res.normal_mean_deg = normal_sum / (double)res.hit_both;
        res.normal_max_deg = normal_max;
    }
    mse = rgb_sq / (3.0 * (double)n);
    res.psnr_rgb = mse > 0.0 ? 10.0 * log10(1.0 / mse) : MR_PSNR_IDENTICAL;
    res.surface_px = surface_px(a, b, probe_a, probe_b);

    *out = res;
    return MR_OK;
}
