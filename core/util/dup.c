/* dup.c - copies of strings and byte ranges (dup.h). */
#include "util/dup.h"

#include <stdlib.h>
#include <string.h>

char *mr_strdup(const char *s)
{
    return s ? mr_memdup_str(s, strlen(s)) : NULL;
}

void *mr_memdup(const void *src, size_t n)
{
    if (!src || n == 0)
        return NULL;
    void *d = malloc(n);
    if (d)
        memcpy(d, src, n);
    return d;
}

char *mr_memdup_str(const void *src, size_t n)
{
    char *d = malloc(n + 1);
    if (!d)
        return NULL;
    if (n)
        memcpy(d, src, n);
    d[n] = '\0';
    return d;
}
