/* hex.c - lowercase hexadecimal (hex.h). */
#include "util/hex.h"

#include <stdint.h>

void mr_hex_encode(const void *bytes, size_t n, char *out)
{
    static const char digits[] = "0123456789abcdef";
    const uint8_t *b = bytes;
    for (size_t i = 0; i < n; i++) {
        out[2 * i] = digits[b[i] >> 4];
        out[2 * i + 1] = digits[b[i] & 15];
    }
    out[2 * n] = '\0';
}

bool mr_hex_is_lower(const char *s, size_t digits)
{
    if (!s)
        return false;
    for (size_t i = 0; i < digits; i++) {
        char c = s[i];
        if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f')))
            return false;
    }
    return s[digits] == '\0';
}
