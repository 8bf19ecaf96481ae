/*
 * compare.c - error metrics between a frame and its reference (compare.h).
 *
 * One pass over the pixels, accumulating in double so a 16 M pixel frame
 * sums without losing the small per-pixel errors the metrics exist to show.
 * The pixel order is fixed (row-major), so the figures are deterministic.
 */
#include "render/compare.h"

#include <math.h>
#include <stddef.h>
#include <string.h>

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

/* The mean of the 4th and 5th smallest of eight (a full sort of eight is a
 * handful of compares; the film is walked once). */
static float median8(float v[8])
{
    for (int i = 1; i < 8; i++) {
        float x = v[i];
        int j = i - 1;
        while (j >= 0 && v[j] > x) {
            v[j + 1] = v[j];
            j--;
        }
        v[j + 1] = x;
    }
    return 0.5f * (v[3] + v[4]);
}

void mr_film_speckles(const mr_film *f, mr_speckle_result *out)
{
    memset(out, 0, sizeof *out);
    if (!f || !f->object_id || !f->r || !f->g || !f->b || f->width < 3 || f->height < 3)
        return;
    const ptrdiff_t w = f->width;
    const ptrdiff_t around[8] = {-w - 1, -w, -w + 1, -1, 1, w - 1, w, w + 1};
    for (int y = 1; y + 1 < f->height; y++)
        for (int x = 1; x + 1 < f->width; x++) {
            size_t p = (size_t)y * (size_t)w + (size_t)x;
            uint32_t object = f->object_id[p + (size_t)around[0]];
            bool interior = object != 0;
            float lum[8];
            for (int k = 0; k < 8 && interior; k++) {
                size_t q = p + (size_t)around[k];
                interior = f->object_id[q] == object;
                lum[k] = luminance(f, q);
            }
            if (!interior)
                continue;
            out->interior++;
            out->speckles += luminance(f, p) < (float)MR_SPECKLE_RATIO * median8(lum);
        }
    if (out->interior)
        out->speckle_pct = 100.0 * (double)out->speckles / (double)out->interior;
}

int mr_film_compare(const mr_film *a, const mr_film *b, double scene_diagonal,
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

    *out = res;
    return MR_OK;
}
