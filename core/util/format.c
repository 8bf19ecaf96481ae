/*
 * format.c - numbers for people (mr_format_bytes, microray.h).
 */
#include "microray.h"

#include <stdio.h>

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
