/*
 * openapi_stats.c - `make openapi`: writes the frame-stats schemas of an
 * OpenAPI document (schemas/openapi.yaml) from the frame-stats field table
 * (server/stats_openapi.h). With --check it only reports whether the block
 * is stale (exit 1), as test_stats_json does.
 */
#include <stdio.h>
#include <string.h>

#include "stats_openapi.h"

int main(int argc, char **argv)
{
    bool check = argc == 3 && !strcmp(argv[1], "--check");
    if (argc != 2 + check) {
        fprintf(stderr, "usage: openapi_stats [--check] schemas/openapi.yaml\n");
        return 2;
    }
    const char *path = argv[argc - 1];
    bool stale = false;
    mr_error err = {0};
    if (mr_stats_openapi_update(path, !check, &stale, &err) < 0) {
        fprintf(stderr, "openapi_stats: %s\n", err.msg);
        return 1;
    }
    if (stale)
        printf(check ? "%s: the frame-stats schemas are stale (run make openapi)\n"
                     : "%s: frame-stats schemas rewritten\n", path);
    return check && stale ? 1 : 0;
}
