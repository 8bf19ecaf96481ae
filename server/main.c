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
#include "usage.h"

int main(int argc, char **argv)
{
    if (argc < 2) {
        mr_usage_all(stderr);
        return 2;
    }
    const char *cmd = argv[1];
    /* `microrayd CMD --help`: that command's usage on stdout, exit 0 */
    if (mr_usage_find(cmd))
        for (int i = 2; i < argc; i++)
            if (!strcmp(argv[i], "--help") || !strcmp(argv[i], "-h")) {
                mr_usage_command_print(stdout, cmd);
                return 0;
            }
    if (!strcmp(cmd, "man")) { /* the manual page, from the same table (make man) */
        mr_usage_man(stdout);
        return 0;
    }
    if (!strcmp(cmd, "completion")) { /* bash completion, from the same table */
        mr_usage_completion(stdout);
        return 0;
    }
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
        if (argc > 2 && mr_usage_find(argv[2]))
            mr_usage_command_print(stdout, argv[2]);
        else
            mr_usage_all(stdout);
        return 0;
    }
    fprintf(stderr, "microrayd: unknown command '%s'\n", cmd);
    mr_usage_all(stderr);
    return 2;
}
