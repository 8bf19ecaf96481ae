/*
 * format.c - numbers for people (mr_format_bytes, mr_format_rfc3339;
 * microray.h).
 */
#include "microray.h"

#include <math.h>
#include <stdio.h>
#include <string.h>
#include <time.h>

void mr_format_bytes(size_t bytes, char *out, size_t size)
{
    const double b = (double)bytes;
    if (bytes >= ((size_t)1 << 30))
        snprintf(out, size, "%.1f GiB", b / (double)(1u << 30));
    else if (bytes >= ((size_t)1 << 20))
        snprintf(out, size, "%.1f MiB", b / (double)(1u << 20));
    else if (bytes >= 1024)
        snprintf(out, size, "%.1f KiB", b / 1024.0);
    else
        snprintf(out, size, "%zu bytes", bytes);
}

bool mr_format_rfc3339(double t, char *out, size_t size)
{
    if (!(t >= 0 && t < 253402300800.0)) /* years 1970..9999 */
        return false;
    time_t whole = (time_t)floor(t);
    int ms = (int)((t - (double)whole) * 1000.0);
    if (ms > 999)
        ms = 999;
    struct tm tm;
    char date[32];
    if (!gmtime_r(&whole, &tm) || strftime(date, sizeof date, "%Y-%m-%dT%H:%M:%S", &tm) == 0)
        return false;
    char text[40];
    int n = snprintf(text, sizeof text, "%s.%03dZ", date, ms);
    if (n < 0 || (size_t)n >= size)
        return false;
    memcpy(out, text, (size_t)n + 1);
    return true;
}
