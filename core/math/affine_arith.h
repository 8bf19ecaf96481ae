/*
 * affine_arith.h - affine arithmetic with conservative rounding (paper 003,
 * section 2.4), for bounds that must contain a surface after every float
 * rounding.
 *
 * A quantity is x = c + u e_u + v e_v + k e_K with e_u, e_v, e_K in [-1, 1]:
 * u and v follow the two parameters of a region (a texel's extent in u and
 * v), k >= 0 collects everything else (products' cross terms, interval
 * inputs, rounding). The K term is kept as a non-negative radius (the
 * thesis' eq. 2.6 writes x_K y_K without absolute values, which is only
 * right under that invariant: REFERENCE.md 003).
 *
 * Rounding: values are doubles computed round-to-nearest; every operation
 * adds to k a bound on the rounding errors it made. An operation makes at
 * most 8 roundings of terms no larger than M = |c| + |u| + |v| + k of its
 * result (and of its inputs' products), each off by at most 2^-53 M, so
 * adding M 2^-48 to k covers them with a margin of 4x; the sum forming k
 * itself is non-negative and its own roundings are covered by scaling it by
 * (1 + 2^-48). A tiny absolute term (2^-1000) covers underflow. So the
 * interval of a result (mr_af_lo, mr_af_hi, themselves rounded outward)
 * contains the exact value of the expression for every e in [-1, 1]^2,
 * given exact inputs. Tested against exhaustive sampling and exact
 * rational arithmetic in tests/unit/test_affine.c.
 *
 * Hazards (REFERENCE.md 003): the square root of an interval whose lower
 * bound is negative is taken from 0; 1/x of an interval that reaches 0 or
 * below is not finite and reported as such (mr_interval_recip returns
 * false), so the caller falls back to a bound that needs no division (a
 * unit normal's components lie in [-1, 1]).
 */
#ifndef MR_AFFINE_ARITH_H
#define MR_AFFINE_ARITH_H

#include <stdbool.h>

typedef struct mr_af {
    double c, u, v, k; /* k >= 0 */
} mr_af;

typedef struct mr_interval {
    double lo, hi;
} mr_interval;

/* x = c exactly. */
static inline mr_af mr_af_const(double c) { return (mr_af){c, 0, 0, 0}; }
/* c + u e_u + v e_v with exact coefficients (a region's centre and half extents). */
static inline mr_af mr_af_uv(double c, double u, double v) { return (mr_af){c, u, v, 0}; }
/* The interval [lo, hi] as c + k e_K (rounded outward). */
mr_af mr_af_from_interval(mr_interval i);

mr_af mr_af_add(mr_af a, mr_af b);
mr_af mr_af_sub(mr_af a, mr_af b);
/* a * s for an exact double s. */
mr_af mr_af_scale(mr_af a, double s);
/* a * b (eq. 2.6 with |x_K|, |y_K| kept as radii). */
mr_af mr_af_mul(mr_af a, mr_af b);
/* a * a, tighter than mr_af_mul(a, a): the square is never negative. */
mr_af mr_af_sqr(mr_af a);

/* |u| + |v| + k, rounded up. */
double mr_af_radius(mr_af a);
/* The interval, rounded outward. */
mr_interval mr_af_interval(mr_af a);

/* sqrt of an interval; a negative lower bound counts as 0 (the square
 * root of a sum of squares whose bound dipped below 0). Rounded outward. */
mr_interval mr_interval_sqrt(mr_interval a);
/* 1 / a when a lies in (0, inf): true, rounded outward; false (and *out
 * unchanged) when a reaches 0 or below or is not finite. */
bool mr_interval_recip(mr_interval a, mr_interval *out);
/* The product of two intervals (all four corner products, outward). */
mr_interval mr_interval_mul(mr_interval a, mr_interval b);
/* a intersected with [lo, hi] (for a quantity known to lie there). */
mr_interval mr_interval_clamp(mr_interval a, double lo, double hi);

#endif
