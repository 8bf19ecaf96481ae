/*
 * dup.h - malloc'ed copies of strings and byte ranges: names and arrays
 * copied between assets, meshes and rigs, and text columns read out of
 * sqlite. Plain C11 has no strdup, and copies that must also work on a
 * range that is not NUL-terminated were written again in every module.
 * Every result is the caller's to free.
 */
#ifndef MR_DUP_H
#define MR_DUP_H

#include <stddef.h>

/* A copy of the string s; NULL for a NULL s or when out of memory. */
char *mr_strdup(const char *s);

/* A copy of bytes [src, src + n); NULL for a NULL src, for n == 0 (there
 * is nothing to own) or when out of memory. */
void *mr_memdup(const void *src, size_t n);

/* The n bytes at src followed by a NUL, as a string; the bytes are copied
 * as they are (a NUL among them is copied too). src may be NULL when n is
 * 0, which gives "". NULL only when out of memory. */
char *mr_memdup_str(const void *src, size_t n);

#endif
