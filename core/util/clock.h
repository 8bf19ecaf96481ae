/*
 * clock.h - the one clock every duration in microray is measured with:
 * frame stats, asset import and cache savings, request log lines, event
 * stream keepalives, benchmarks and the tests' timings. It is
 * CLOCK_MONOTONIC, which never jumps when the wall clock is set, so the
 * difference of two readings is always an elapsed time. (Timestamps people
 * read, such as a job's "created", are wall-clock time and not from here.)
 */
#ifndef MR_CLOCK_H
#define MR_CLOCK_H

#include <stdint.h>

/* Monotonic clock, seconds (nanosecond resolution). */
double mr_now(void);
/* The same clock in whole milliseconds, for integer deadlines. */
int64_t mr_now_ms(void);

#endif
