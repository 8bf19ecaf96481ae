/* affine_arith.c - affine forms with conservative rounding (affine_arith.h). */
#include "math/affine_arith.h"

#include <math.h>

/* 2^-48: the rounding allowance per operation (affine_arith.h). */
#define ROUND_REL 0x1p-48
#define ROUND_ABS 0x1p-1000

static inline double down(double x) { return nextafter(x, -INFINITY); }
static inline double up(double x) { return nextafter(x, INFINITY); }

/* k plus the rounding allowance for a result of magnitude m. */
static inline double widen(double k, double m)
{
    return (k + m * ROUND_REL) * (1.0 + ROUND_REL) + ROUND_ABS;
}

static inline double mag(mr_af a) { return fabs(a.c) + fabs(a.u) + fabs(a.v) + a.k; }

mr_af mr_af_from_interval(mr_interval i)
{
    double c = 0.5 * i.lo + 0.5 * i.hi;
    double r = fmax(c - i.lo, i.hi - c);
    return (mr_af){c, 0, 0, widen(r, fabs(c) + r)};
}

mr_af mr_af_add(mr_af a, mr_af b)
{
    mr_af r = {a.c + b.c, a.u + b.u, a.v + b.v, a.k + b.k};
    r.k = widen(r.k, mag(a) + mag(b));
    return r;
}

mr_af mr_af_sub(mr_af a, mr_af b)
{
    mr_af r = {a.c - b.c, a.u - b.u, a.v - b.v, a.k + b.k};
    r.k = widen(r.k, mag(a) + mag(b));
    return r;
}

mr_af mr_af_scale(mr_af a, double s)
{
    double as = fabs(s);
    mr_af r = {a.c * s, a.u * s, a.v * s, a.k * as};
    r.k = widen(r.k, mag(a) * as);
    return r;
}

mr_af mr_af_mul(mr_af a, mr_af b)
{
    double ra = fabs(a.u) + fabs(a.v) + a.k, rb = fabs(b.u) + fabs(b.v) + b.k;
    mr_af r = {a.c * b.c, a.u * b.c + a.c * b.u, a.v * b.c + a.c * b.v,
               a.k * fabs(b.c) + fabs(a.c) * b.k + ra * rb};
    r.k = widen(r.k, mag(a) * mag(b));
    return r;
}

mr_af mr_af_sqr(mr_af a)
{
    /* (c + d)^2 = c^2 + 2 c d + d^2 with d in [-ra, ra]: d^2 lies in
     * [0, ra^2], so its centre ra^2 / 2 moves into c and its radius is
     * ra^2 / 2 (mr_af_mul would use ra^2 around 0). */
    double ra = fabs(a.u) + fabs(a.v) + a.k;
    double half = 0.5 * ra * ra;
    mr_af r = {a.c * a.c + half, 2 * a.c * a.u, 2 * a.c * a.v, 2 * fabs(a.c) * a.k + half};
    double m = mag(a);
    r.k = widen(r.k, m * m);
    return r;
}

double mr_af_radius(mr_af a) { return up(up(fabs(a.u) + fabs(a.v)) + a.k); }

mr_interval mr_af_interval(mr_af a)
{
    double r = mr_af_radius(a);
    return (mr_interval){down(a.c - r), up(a.c + r)};
}

mr_interval mr_interval_sqrt(mr_interval a)
{
    double lo = a.lo > 0 ? down(sqrt(a.lo)) : 0.0;
    double hi = a.hi > 0 ? up(sqrt(a.hi)) : 0.0;
    return (mr_interval){lo > 0 ? lo : 0.0, hi};
}

bool mr_interval_recip(mr_interval a, mr_interval *out)
{
    if (!(a.lo > 0) || !isfinite(a.hi) || !(a.hi >= a.lo))
        return false;
    double lo = down(1.0 / a.hi), hi = up(1.0 / a.lo);
    if (!isfinite(hi))
        return false;
    *out = (mr_interval){lo, hi};
    return true;
}

mr_interval mr_interval_mul(mr_interval a, mr_interval b)
{
    double p[4] = {a.lo * b.lo, a.lo * b.hi, a.hi * b.lo, a.hi * b.hi};
    double lo = p[0], hi = p[0];
    for (int i = 1; i < 4; i++) {
        lo = fmin(lo, p[i]);
        hi = fmax(hi, p[i]);
    }
    return (mr_interval){down(lo), up(hi)};
}

mr_interval mr_interval_clamp(mr_interval a, double lo, double hi)
{
    return (mr_interval){fmax(a.lo, lo), fmin(a.hi, hi)};
}
