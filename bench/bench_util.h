/*
 * bench_util.h - what every benchmark program needs: medians of repeated
 * measurements (timings on a shared 2-core machine are noisy; the benchmarks
 * report medians of interleaved runs). Header-only, one include per program.
 */
#ifndef MR_BENCH_UTIL_H
#define MR_BENCH_UTIL_H

#include <stdlib.h>

static int bench_cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* Median of v[0..n) (sorts v). */
static double median(double *v, int n)
{
    qsort(v, (size_t)n, sizeof *v, bench_cmp_double);
    return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

#endif
