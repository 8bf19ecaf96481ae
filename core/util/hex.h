/*
 * hex.h - bytes as lowercase hexadecimal, and the check for it: SHA-256
 * digests become asset ids, idempotency body hashes and the file names of
 * the derived-data caches; random bytes become job ids. Ids arrive back in
 * URLs and job documents, and only exact lowercase hex is ever turned into
 * a path, so the spelling is checked by one function too.
 */
#ifndef MR_HEX_H
#define MR_HEX_H

#include <stdbool.h>
#include <stddef.h>

/* Writes 2 * n lowercase hex digits of bytes[0, n) and a NUL into out
 * (2 * n + 1 bytes). */
void mr_hex_encode(const void *bytes, size_t n, char *out);

/* Whether s is exactly `digits` characters of 0-9a-f (false for NULL, for
 * uppercase, and for shorter or longer strings). */
bool mr_hex_is_lower(const char *s, size_t digits);

#endif
