/*
 * bench_util.h - what every benchmark program needs: medians of repeated
 * measurements (timings on a shared 2-core machine are noisy; the benchmarks
 * report medians of interleaved runs) and a frame's stats fields by name.
 * Header-only, one include per program. Benchmarks use the public API only
 * (microray.h; scripts/check-layout.sh checks it).
 */
#ifndef MR_BENCH_UTIL_H
#define MR_BENCH_UTIL_H

#include <dirent.h>
#include <math.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "microray.h"

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

static int bench_cmp_name(const void *a, const void *b)
{
    return strcmp(*(char *const *)a, *(char *const *)b);
}

/* Every benchmark keeps freed memory between frames as microrayd's render
 * commands do (mr_heap_keep_freed), so frame times match the daemon's. */
__attribute__((constructor)) static void bench_heap_policy(void) { mr_heap_keep_freed(); }

/* The example jobs (examples/<stem>.json, run from the repository root):
 * their stems, malloc'ed, sorted, at most max into names; exits when the
 * folder cannot be read. Returns how many. */
static inline size_t bench_examples(char **names, size_t max)
{
    DIR *d = opendir("examples");
    if (!d) {
        fprintf(stderr, "bench: examples: cannot open the folder (run from the repository root)\n");
        exit(1);
    }
    size_t n = 0;
    for (struct dirent *e; (e = readdir(d)) && n < max;) {
        size_t len = strlen(e->d_name);
        if (len > 5 && strcmp(e->d_name + len - 5, ".json") == 0)
            names[n++] = strndup(e->d_name, len - 5);
    }
    closedir(d);
    qsort(names, n, sizeof *names, bench_cmp_name);
    return n;
}

/* A kind's own field of a rendered frame (its extras: the svo_* figures,
 * say); exits naming the field when the frame does not carry it, so a
 * renamed field cannot print zeros silently. */
static inline double frame_extra(const mr_frame_stats *st, const char *name)
{
    for (uint32_t i = 0; i < st->extra_count; i++)
        if (strcmp(st->extras[i].name, name) == 0)
            return st->extras[i].value;
    fprintf(stderr, "bench: frame %d has no stats field %s\n", st->frame, name);
    exit(1);
}

/* CPU seconds of the whole process: while a program measures one thing,
 * that thing's work on all its threads, whatever else the machine runs
 * (wall times on a shared 2-core machine swing with other load; this does
 * much less). */
static inline double bench_cpu_now(void)
{
    struct timespec t;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

/* A job's asset as the daemon's import gives it: the file, refined when
 * the job says "refine" (on the given threads). Exits naming the file on
 * failure. */
static inline mr_asset *bench_load_asset(const mr_asset_desc *d, unsigned threads)
{
    mr_asset *a = NULL, *r = NULL;
    mr_error err;
    if (mr_asset_load(d->path, &a, &err) < 0) {
        fprintf(stderr, "bench: %s: %s\n", d->path, err.msg);
        exit(1);
    }
    if (!d->refine)
        return a;
    mr_refine_params p = d->refine_params;
    p.threads = threads;
    if (mr_refine_asset(a, &p, &r, &err) < 0) {
        fprintf(stderr, "bench: refine %s: %s\n", d->path, err.msg);
        exit(1);
    }
    mr_asset_free(a);
    return r;
}

/* One point of a speed-against-error curve for bench/report.md: a method of
 * a kind at one level (subdivision level, depth, range) on one scene, its
 * time and its error against the named reference. Appended as a tab-
 * separated line to $MR_BENCH_DATA/points.tsv when that folder is set
 * (scripts/run-bench.sh sets it; bench/report.sh plots the points), else
 * nothing. Names must not hold tabs or newlines. per_level: the error is
 * against each level's own reference (not one truth for all levels), so
 * the report compares methods within a level only (its Pareto front is
 * found per level). */
static inline void bench_point(const char *kind, const char *scene, const char *method,
                               const char *level, double ms, const char *error_name,
                               double error, bool per_level)
{
    const char *dir = getenv("MR_BENCH_DATA");
    if (!dir || !*dir)
        return;
    char path[4096];
    snprintf(path, sizeof path, "%s/points.tsv", dir);
    FILE *f = fopen(path, "a");
    if (!f) {
        fprintf(stderr, "bench: cannot append to %s\n", path);
        return;
    }
    fprintf(f, "%s\t%s\t%s\t%s\t%.6g\t%s\t%.6g\t%s\n", kind, scene, method, level, ms, error_name,
            error, per_level ? level : "");
    fclose(f);
}

/* Bytes the kernel says are available for new work (MemAvailable), or
 * 8 GiB when it cannot be read: what the benchmarks size their jobs'
 * memory budgets by on a machine shared with other work. */
static inline double bench_mem_available(void)
{
    char line[256];
    double kib = 0;
    FILE *f = fopen("/proc/meminfo", "r");
    if (!f)
        return 8.0 * 1024 * 1024 * 1024;
    while (fgets(line, sizeof line, f))
        if (sscanf(line, "MemAvailable: %lf kB", &kib) == 1)
            break;
    fclose(f);
    return kib * 1024.0;
}

/* The growth exponent b of y ~ x^b: the least-squares slope of log y
 * against log x over the pairs with both positive (NAN with fewer than
 * two). 1 is linear, 0 flat. */
static inline double bench_growth(const double *x, const double *y, int n)
{
    double sx = 0, sy = 0, sxx = 0, sxy = 0;
    int m = 0;
    for (int i = 0; i < n; i++) {
        if (!(x[i] > 0) || !(y[i] > 0))
            continue;
        const double lx = log(x[i]), ly = log(y[i]);
        sx += lx;
        sy += ly;
        sxx += lx * lx;
        sxy += lx * ly;
        m++;
    }
    const double d = m * sxx - sx * sx;
    return m >= 2 && d > 0 ? (m * sxy - sx * sy) / d : NAN;
}

/* ---- process memory (Linux /proc; not microray's own accounting) ---- */

/* Resident bytes now. */
static inline double bench_rss_now(void)
{
    long pages = 0, resident = 0;
    FILE *f = fopen("/proc/self/statm", "r");
    if (f) {
        if (fscanf(f, "%ld %ld", &pages, &resident) != 2)
            resident = 0;
        fclose(f);
    }
    return (double)resident * (double)sysconf(_SC_PAGESIZE);
}

/* Starts a new peak: bench_peak_rss then gives the peak resident bytes
 * (VmHWM) since this call (clear_refs "5"), so one part of a benchmark
 * measures its own peak after earlier parts. False when the kernel does
 * not allow it (the peak is then the process'). */
static inline bool bench_peak_reset(void)
{
    FILE *f = fopen("/proc/self/clear_refs", "w");
    if (!f)
        return false;
    bool ok = fputs("5", f) >= 0;
    ok = fclose(f) == 0 && ok;
    return ok;
}

static inline double bench_peak_rss(void)
{
    char line[256];
    double kib = 0;
    FILE *f = fopen("/proc/self/status", "r");
    if (!f)
        return (double)mr_peak_rss_bytes();
    while (fgets(line, sizeof line, f))
        if (sscanf(line, "VmHWM: %lf kB", &kib) == 1)
            break;
    fclose(f);
    return kib > 0 ? kib * 1024.0 : (double)mr_peak_rss_bytes();
}

#endif
