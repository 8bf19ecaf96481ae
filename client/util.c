/*
 * util.c - the client's small helpers: error records, clocks, file reading,
 * directory creation and defensive JSON access (see client.h).
 */
#include "client.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>

int mrc_fail(mrc_error *err, int code, const char *fmt, ...)
{
    if (err) {
        va_list ap;
        va_start(ap, fmt);
        vsnprintf(err->msg, sizeof err->msg, fmt, ap);
        va_end(ap);
        err->code = code;
    }
    return -code;
}

double mrc_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

void mrc_sanitize(char *dst, size_t size, const char *src)
{
    if (size == 0)
        return;
    size_t i = 0;
    for (; src && src[i] && i + 1 < size; i++) {
        unsigned char c = (unsigned char)src[i];
        dst[i] = (c < 0x20 || c == 0x7f) ? '?' : (char)c;
    }
    dst[i] = '\0';
}

int mrc_read_file(const char *path, size_t limit, char **data, size_t *len, mrc_error *err)
{
    int rc = 0;
    FILE *f = NULL;
    char *buf = NULL;
    size_t used = 0, cap = 0;
    bool is_stdin = strcmp(path, "-") == 0;

    *data = NULL;
    *len = 0;
    f = is_stdin ? stdin : fopen(path, "rb");
    if (!f) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "%s: %s", path, strerror(errno));
        goto cleanup;
    }
    for (;;) {
        if (cap - used < 65536) {
            /* grow geometrically, but never beyond limit + 1 (one byte more
             * than allowed is enough to notice the file is too large) */
            size_t ncap = cap ? cap * 2 : 65536 + 1;
            if (ncap > limit + 1)
                ncap = limit + 1;
            if (ncap <= used) {
                rc = mrc_fail(err, MRC_EXIT_LOCAL, "%s: larger than %zu bytes", path, limit);
                goto cleanup;
            }
            char *nbuf = realloc(buf, ncap + 1);
            if (!nbuf) {
                rc = mrc_fail(err, MRC_EXIT_LOCAL, "%s: out of memory", path);
                goto cleanup;
            }
            buf = nbuf;
            cap = ncap;
        }
        size_t n = fread(buf + used, 1, cap - used, f);
        used += n;
        if (used > limit) {
            rc = mrc_fail(err, MRC_EXIT_LOCAL, "%s: larger than %zu bytes", path, limit);
            goto cleanup;
        }
        if (n == 0) {
            if (ferror(f)) {
                rc = mrc_fail(err, MRC_EXIT_LOCAL, "%s: %s", path, strerror(errno));
                goto cleanup;
            }
            break;
        }
    }
    if (!buf) { /* empty file */
        buf = malloc(1);
        if (!buf) {
            rc = mrc_fail(err, MRC_EXIT_LOCAL, "%s: out of memory", path);
            goto cleanup;
        }
    }
    buf[used] = '\0';
    *data = buf;
    *len = used;
    buf = NULL;
cleanup:
    free(buf);
    if (f && !is_stdin)
        fclose(f);
    return rc;
}

int mrc_mkdirs(const char *dir, mrc_error *err)
{
    int rc = 0;
    char *p = strdup(dir);
    if (!p)
        return mrc_fail(err, MRC_EXIT_LOCAL, "%s: out of memory", dir);
    size_t n = strlen(p);
    while (n > 1 && p[n - 1] == '/')
        p[--n] = '\0';
    /* create each prefix in turn; EEXIST is fine as long as it is a directory */
    for (size_t i = 1; i <= n; i++) {
        if (p[i] != '/' && p[i] != '\0')
            continue;
        char saved = p[i];
        p[i] = '\0';
        if (mkdir(p, 0777) != 0 && errno != EEXIST) {
            rc = mrc_fail(err, MRC_EXIT_LOCAL, "cannot create directory %s: %s", p, strerror(errno));
            goto cleanup;
        }
        p[i] = saved;
    }
    struct stat st;
    if (stat(p, &st) != 0 || !S_ISDIR(st.st_mode)) {
        rc = mrc_fail(err, MRC_EXIT_LOCAL, "%s: not a directory", dir);
        goto cleanup;
    }
cleanup:
    free(p);
    return rc;
}

bool mrc_valid_id(const char *id)
{
    size_t n = 0;
    for (; id[n]; n++) {
        char c = id[n];
        bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') ||
                  c == '-' || c == '_';
        if (!ok || n >= 128)
            return false;
    }
    return n > 0;
}

void mrc_format_bytes(char *dst, size_t size, double bytes)
{
    static const char *const unit[] = {"B", "KiB", "MiB", "GiB", "TiB"};
    int u = 0;
    while (bytes >= 1024.0 && u < 4) {
        bytes /= 1024.0;
        u++;
    }
    if (u == 0)
        snprintf(dst, size, "%.0f B", bytes);
    else
        snprintf(dst, size, "%.1f %s", bytes, unit[u]);
}

void mrc_format_seconds(char *dst, size_t size, double s)
{
    if (!(s >= 0.0)) /* also NaN */
        s = 0.0;
    if (s < 60.0) {
        snprintf(dst, size, "%.1f s", s);
    } else if (s < 3600.0) {
        long t = (long)s;
        snprintf(dst, size, "%ldm%02lds", t / 60, t % 60);
    } else {
        if (s > 1e9) /* keep the conversion below defined and the text short */
            s = 1e9;
        long t = (long)(s / 60.0);
        snprintf(dst, size, "%ldh%02ldm", t / 60, t % 60);
    }
}

long long mrc_json_int(const cJSON *obj, const char *key, long long def, long long lo, long long hi)
{
    const cJSON *v = cJSON_GetObjectItemCaseSensitive(obj, key);
    if (!cJSON_IsNumber(v))
        return def;
    double d = v->valuedouble;
    if (!isfinite(d) || d < (double)lo || d > (double)hi)
        return def;
    return (long long)d;
}

double mrc_json_num(const cJSON *obj, const char *key, double def)
{
    const cJSON *v = cJSON_GetObjectItemCaseSensitive(obj, key);
    if (!cJSON_IsNumber(v) || !isfinite(v->valuedouble))
        return def;
    return v->valuedouble;
}

const char *mrc_json_str(const cJSON *obj, const char *key)
{
    const cJSON *v = cJSON_GetObjectItemCaseSensitive(obj, key);
    return cJSON_IsString(v) && v->valuestring ? v->valuestring : NULL;
}

void mrc_format_time_field(char *dst, size_t size, const cJSON *obj, const char *key)
{
    const cJSON *v = cJSON_GetObjectItemCaseSensitive(obj, key);
    if (cJSON_IsString(v) && v->valuestring && v->valuestring[0]) {
        mrc_sanitize(dst, size, v->valuestring);
        return;
    }
    /* 0 .. year 9999: anything else is not a plausible timestamp */
    if (cJSON_IsNumber(v) && isfinite(v->valuedouble) && v->valuedouble > 0 &&
        v->valuedouble < 253402300800.0) {
        time_t t = (time_t)v->valuedouble;
        struct tm tm;
        if (gmtime_r(&t, &tm) && strftime(dst, size, "%Y-%m-%dT%H:%M:%SZ", &tm) > 0)
            return;
    }
    snprintf(dst, size, "-");
}
