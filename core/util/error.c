/* error.c - mr_error helpers: the one place messages are formatted. */
#include "microray.h"

#include <stdarg.h>
#include <stdio.h>
#include <string.h>

int mr_error_set(mr_error *err, int code, const char *fmt, ...)
{
    if (err) {
        va_list ap;
        va_start(ap, fmt);
        vsnprintf(err->msg, sizeof err->msg, fmt, ap);
        va_end(ap);
        err->code = code;
    }
    return code;
}

int mr_error_prefix(mr_error *err, const char *fmt, ...)
{
    if (!err)
        return MR_ERR_INVALID;
    char inner[sizeof err->msg];
    memcpy(inner, err->msg, sizeof inner);
    char prefix[sizeof err->msg];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(prefix, sizeof prefix, fmt, ap);
    va_end(ap);
    /* prefix + inner, cut to fit (a deliberate truncation, so no snprintf) */
    size_t np = strlen(prefix), ni = strlen(inner), cap = sizeof err->msg - 1;
    if (np > cap)
        np = cap;
    if (ni > cap - np)
        ni = cap - np;
    memcpy(err->msg, prefix, np);
    memcpy(err->msg + np, inner, ni);
    err->msg[np + ni] = '\0';
    return err->code;
}

const char *mr_err_name(int code)
{
    switch (code) {
    case MR_OK: return "MR_OK";
    case MR_ERR_NOMEM: return "MR_ERR_NOMEM";
    case MR_ERR_INVALID: return "MR_ERR_INVALID";
    case MR_ERR_IO: return "MR_ERR_IO";
    case MR_ERR_FORMAT: return "MR_ERR_FORMAT";
    case MR_ERR_EMBREE: return "MR_ERR_EMBREE";
    case MR_ERR_LIMIT: return "MR_ERR_LIMIT";
    case MR_ERR_CANCELLED: return "MR_ERR_CANCELLED";
    case MR_ERR_NOT_FOUND: return "MR_ERR_NOT_FOUND";
    case MR_ERR_CONFLICT: return "MR_ERR_CONFLICT";
    case MR_ERR_NO_SPACE: return "MR_ERR_NO_SPACE";
    case MR_ERR_CRASHED: return "MR_ERR_CRASHED";
    default: return "MR_ERR_UNKNOWN";
    }
}
