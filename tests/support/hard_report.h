/*
 * hard_report.h - the figures of the hard cases (tests/hard) that `make hard`
 * tabulates (scripts/run-hard.sh).
 *
 * A hard case checks what it measured against its tolerance with
 * HARD_CHECK(type, measured, op, bound, figure...). The call prints one line
 *
 *   HARD <tab> kind <tab> case <tab> type <tab> figure <tab> measured <tab> op <tab> bound <tab> ok|FAIL
 *
 * and, when "measured op bound" does not hold, fails the case (cmocka's
 * fail_msg), so the figure printed is the one asserted. A NaN satisfies no
 * comparison: a NaN figure fails. op is "<", "<=", "==", ">=" or ">". type
 * says what the figure is about:
 *   "leaks"  rays that pass through the surface, uncovered points or pixels;
 *   "nan"    non-finite outputs (NaN, Inf), counted (HARD_NONFINITE);
 *   "error"  distance from an oracle, or a numerical error bound;
 *   "other"  counts and properties that must hold (a pass/fail case counts
 *            its bad outputs with HARD_EXPECT and checks the count is 0).
 *
 * The program defines HARD_KIND (the geometry kind it exercises: "mesh",
 * "dmm", "svo", "displaced" or "springmass") before including this header.
 * The case is the calling function's name (__func__): report from the cmocka
 * test function itself, helpers hand their figures back. Aggregate worst
 * values with hard_max / hard_min, which keep a NaN (fmax would drop it).
 * Every case of tests/hard reports at least one figure; the runner fails a
 * passing case that reported none. Include after cmocka.h.
 */
#ifndef MR_TEST_HARD_REPORT_H
#define MR_TEST_HARD_REPORT_H

#include <math.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stdio.h>
#include <string.h>

#ifndef HARD_KIND
#error "define HARD_KIND (the kind the program's hard cases exercise) before hard_report.h"
#endif

/* stdout line by line, like stderr: cmocka prints its status lines to
 * stdout and failure messages to stderr, and the runner reads them from one
 * log in the order they happened (a file would get stdout in blocks). */
__attribute__((constructor)) static void hard_report_line_buffered(void)
{
    setvbuf(stdout, NULL, _IOLBF, 0);
}

/* The larger / smaller of two figures; NaN if either is NaN. */
static inline double hard_max(double a, double b)
{
    return isnan(a) || isnan(b) ? NAN : a > b ? a : b;
}

static inline double hard_min(double a, double b)
{
    return isnan(a) || isnan(b) ? NAN : a < b ? a : b;
}

/* Whether "measured op bound" holds; -1 for an unknown op. */
static inline int hard_holds(double measured, const char *op, double bound)
{
    if (!strcmp(op, "<"))
        return measured < bound;
    if (!strcmp(op, "<="))
        return measured <= bound;
    if (!strcmp(op, "=="))
        return measured == bound;
    if (!strcmp(op, ">="))
        return measured >= bound;
    if (!strcmp(op, ">"))
        return measured > bound;
    return -1;
}

static inline void hard_check(const char *test, const char *type, double measured, const char *op,
                              double bound, const char *fmt, ...)
    __attribute__((format(printf, 6, 7)));

static inline void hard_check(const char *test, const char *type, double measured, const char *op,
                              double bound, const char *fmt, ...)
{
    char figure[256];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(figure, sizeof figure, fmt, ap);
    va_end(ap);
    for (char *c = figure; *c; c++)
        if (*c == '\t' || *c == '\n' || *c == '\r')
            *c = ' ';
    if (strcmp(type, "leaks") && strcmp(type, "nan") && strcmp(type, "error") && strcmp(type, "other"))
        fail_msg("%s: figure '%s' has an unknown type '%s'", test, figure, type);
    int holds = hard_holds(measured, op, bound);
    if (holds < 0)
        fail_msg("%s: figure '%s' has an unknown comparison '%s'", test, figure, op);
    printf("HARD\t%s\t%s\t%s\t%s\t%.9g\t%s\t%.9g\t%s\n", HARD_KIND, test, type, figure, measured, op, bound,
           holds ? "ok" : "FAIL");
    fflush(stdout);
    if (!holds)
        fail_msg("%s: %s is %.9g, not %s %.9g", test, figure, measured, op, bound);
}

#define HARD_CHECK(type, measured, op, bound, ...) \
    hard_check(__func__, type, (double)(measured), op, (double)(bound), __VA_ARGS__)

/* A count of non-finite outputs, which must be 0. */
#define HARD_NONFINITE(count, ...) HARD_CHECK("nan", count, "==", 0, __VA_ARGS__)

/* Counts a condition that does not hold into bad (and says which, where);
 * for cases that are pass/fail by nature, which then check bad == 0. */
#define HARD_EXPECT(bad, cond)                                                                 \
    ((cond) ? (void)0                                                                          \
            : (void)(print_error("%s:%d: expected %s\n", __FILE__, __LINE__, #cond), (bad)++))

#endif
