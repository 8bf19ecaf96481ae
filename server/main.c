/*
 * main.c - microrayd: the render daemon and its one-shot commands.
 */
#include <stdio.h>
#include <string.h>

#include "microray.h"
#include "import_worker.h"
#include "render_proc.h"
#include "render_cmd.h"
#include "schema_gen.h"

static void usage(FILE *to)
{
    fprintf(to,
            "microrayd %s - ray traced frames of deforming, detailed geometry\n"
            "usage:\n"
            "  microrayd render JOB.json --out DIR [--threads N] [--cache DIR] [--frames LIST | --prepare] [--png] [--quiet]\n"
            "  microrayd plan JOB.json  (validate; frames and retries as JSON, for splitting the job)\n"
            "  microrayd stats-merge DIR JOB.json  (stats.json of the parts render --frames wrote)\n"
            "  microrayd compare A.exr B.exr [--diagonal D]\n"
            "  microrayd serve [--listen HOST:PORT] [--data DIR] [--asset-root DIR]... [--workers N]\n"
            "                  [--threads N] [--http-threads N] [--cache-mb N]\n"
            "                  [--max-connections N] [--per-ip-connections N] [--request-timeout S]\n"
            "                  [--token-file FILE] [--insecure] [--tls-cert FILE --tls-key FILE]\n"
            "                  [--port-file FILE] [--quiet]\n"
            "  microrayd schema FILE [--check]  (the job schema's generated kind blocks)\n"
            "  microrayd version\n",
            MR_VERSION_STRING);
}

int main(int argc, char **argv)
{
    if (argc < 2) {
        usage(stderr);
        return 2;
    }
    const char *cmd = argv[1];
    if (!strcmp(cmd, "render"))
        return mr_cmd_render(argc - 2, argv + 2);
    if (!strcmp(cmd, "plan"))
        return mr_cmd_plan(argc - 2, argv + 2);
    if (!strcmp(cmd, "stats-merge"))
        return mr_cmd_stats_merge(argc - 2, argv + 2);
    if (!strcmp(cmd, "compare"))
        return mr_cmd_compare(argc - 2, argv + 2);
    if (!strcmp(cmd, "serve"))
        return mr_cmd_serve(argc - 2, argv + 2);
    if (!strcmp(cmd, "schema"))
        return mr_cmd_schema(argc - 2, argv + 2);
    if (!strcmp(cmd, "import-worker")) /* not for people: the daemon's import child */
        return mr_cmd_import_worker(argc - 2, argv + 2);
    if (!strcmp(cmd, "render-worker")) /* not for people: the daemon's render worker */
        return mr_cmd_render_worker(argc - 2, argv + 2);
    if (!strcmp(cmd, "version") || !strcmp(cmd, "--version")) {
        printf("microrayd %s\n", MR_VERSION_STRING);
        return 0;
    }
    if (!strcmp(cmd, "help") || !strcmp(cmd, "--help") || !strcmp(cmd, "-h")) {
        usage(stdout);
        return 0;
    }
    fprintf(stderr, "microrayd: unknown command '%s'\n", cmd);
    usage(stderr);
    return 2;
}
