/*
 * usage.c - microrayd's command line, described once (usage.h).
 */
#include "usage.h"

#include <string.h>

#include "microray.h"

#define COUNT(a) (sizeof(a) / sizeof((a)[0]))

static const mr_usage_flag RENDER_FLAGS[] = {
    {"--out", "DIR", "write DIR/NNNN.exr and DIR/stats.json (created if missing)"},
    {"--threads", "N", "render on N threads (default: every core); frames are bit-identical for any N"},
    {"--cache", "DIR", "keep derived data (bakes, voxelisations) in DIR/<kind>/ and reuse it (default: derive it again every time)"},
    {"--job-memory-mb", "N", "what the job's geometry may hold (default: half of the machine's memory)"},
    {"--frames", "LIST", "render only these frames (0-based: 3, 0-9, 0-9,20): the same files as a whole run, statistics in DIR/stats.frames-LIST.json (stats-merge joins them)"},
    {"--prepare", NULL, "render nothing: import the assets and derive each kind's data into --cache (the first task of a job split into parts)"},
    {"--png", NULL, "also write DIR/NNNN.png (8-bit sRGB previews) and DIR/contact-sheet.png"},
    {"--quiet", NULL, "no progress lines"},
};

static const mr_usage_flag COMPARE_FLAGS[] = {
    {"--diagonal", "D", "the scene's bounding diagonal, the unit of depth errors (default: from B's header, the reference's, else A's, else 1)"},
};

static const mr_usage_flag SERVE_FLAGS[] = {
    {"--listen", "HOST:PORT", "address to listen on (default 127.0.0.1:8470; port 0 picks a free one); a non-loopback address needs --token-file or --insecure"},
    {"--data", "DIR", "the data directory: database, assets, frames, derived data (default $MICRORAY_DATA, else $XDG_DATA_HOME/microray, else ~/.local/share/microray)"},
    {"--asset-root", "DIR", "a folder jobs may name server-side files below (repeatable); without one only uploaded assets can be used"},
    {"--workers", "N", "jobs rendered at once, each in a render worker process of its own (default 1)"},
    {"--threads", "N", "cores per frame (default: all)"},
    {"--http-threads", "N", "libmicrohttpd's thread pool (default: one per core)"},
    {"--cache-mb", "N", "each render worker's scene cache (default 1024)"},
    {"--job-memory-mb", "N", "what one job's geometry may hold (default: half of the machine's memory)"},
    {"--worker-memory-mb", "N", "a render worker's resident memory at which it is killed (default: job memory + cache + 1 GiB)"},
    {"--frame-timeout", "S", "a frame (or a job's preparation) that takes longer fails as over a limit (default: no limit)"},
    {"--import-memory-mb", "N", "an import child's memory (default: a quarter of the machine's, at least 1 GiB)"},
    {"--import-timeout", "S", "an import's wall clock (default 300)"},
    {"--disk-reserve-mb", "N", "space kept free, given up when the disk fills (default 64)"},
    {"--max-connections", "N", "connections open at once (default 1024)"},
    {"--per-ip-connections", "N", "connections one address may hold (default 128)"},
    {"--request-timeout", "S", "a request head must be complete within S seconds (default 10)"},
    {"--token-file", "FILE", "every request but /healthz and /readyz must carry the bearer token of FILE's first line"},
    {"--insecure", NULL, "allow a non-loopback --listen without a token (a network you trust)"},
    {"--tls-cert", "FILE", "serve HTTPS with this PEM certificate chain (with --tls-key)"},
    {"--tls-key", "FILE", "the PEM key of --tls-cert"},
    {"--port-file", "FILE", "write the port listened on to FILE once listening"},
    {"--quiet", NULL, "no log lines per request and frame"},
};

static const mr_usage_flag SCHEMA_FLAGS[] = {
    {"--check", NULL, "exit 1 if FILE differs from what it would print"},
};

static const mr_usage_flag NO_FLAGS[] = {{NULL, NULL, NULL}};

static const mr_usage_command COMMANDS[] = {
    {"render", "JOB.json --out DIR", "render a job without the daemon",
     "Validates the job, imports its assets (paths relative to the job file), renders every frame "
     "and writes DIR/0000.exr, ... and DIR/stats.json, each file written to a temporary name and "
     "renamed into place.",
     RENDER_FLAGS, COUNT(RENDER_FLAGS)},
    {"plan", "JOB.json", "validate a job; print what splitting it needs as JSON",
     "Validates the job as the daemon would and prints {\"name\", \"frames\", \"max_retries\", "
     "\"width\", \"height\", \"references\"} (the reference passes its frames get).",
     NO_FLAGS, 0},
    {"stats-merge", "DIR JOB.json", "join the statistics of render --frames parts",
     "Joins DIR/stats.frames-*.json into DIR/stats.json (the newest part's figures for a frame "
     "rendered twice) and says which frames have none.",
     NO_FLAGS, 0},
    {"compare", "A.exr B.exr", "error metrics of frame A against reference B, as JSON",
     "Coverage, depth (relative to the scene's diagonal), normal and colour errors.",
     COMPARE_FLAGS, COUNT(COMPARE_FLAGS)},
    {"serve", "", "run the render service (HTTP API v1) until SIGTERM or SIGINT",
     "On SIGTERM or SIGINT it drains: /readyz, submissions and uploads answer 503 while reads are "
     "served and the frames in progress finish; unfinished jobs stay queued for the next start.",
     SERVE_FLAGS, COUNT(SERVE_FLAGS)},
    {"schema", "FILE", "print the job schema with its generated kind blocks",
     "Prints FILE (schemas/job.schema.json) with its geometry-kind parts generated from the "
     "kinds' parameter tables.",
     SCHEMA_FLAGS, COUNT(SCHEMA_FLAGS)},
    {"version", "", "print the version", NULL, NO_FLAGS, 0},
    {"help", "[COMMAND]", "this help, or one command's", NULL, NO_FLAGS, 0},
};

const mr_usage_command *mr_usage_find(const char *name)
{
    for (size_t i = 0; name && i < COUNT(COMMANDS); i++)
        if (!strcmp(COMMANDS[i].name, name))
            return &COMMANDS[i];
    return NULL;
}

void mr_usage_all(FILE *to)
{
    fprintf(to, "microrayd %s - ray traced frames of deforming, detailed geometry\n\nusage:\n",
            MR_VERSION_STRING);
    for (size_t i = 0; i < COUNT(COMMANDS); i++)
        mr_usage_print_command(to, "microrayd", &COMMANDS[i]);
    fputs("\nEvery command takes --help (its usage on standard output, exit 0).\n"
          "Exit codes: 0 success, 1 rendering failed on our side, 2 usage error, 3 invalid input\n"
          "(job, asset, EXR), 4 a file could not be read or written. See microrayd(1), README.md.\n",
          to);
}

void mr_usage_command_print(FILE *to, const char *name)
{
    const mr_usage_command *c = mr_usage_find(name);
    if (!c)
        return;
    fputs("usage:\n", to);
    mr_usage_print_command(to, "microrayd", c);
    if (c->text)
        fprintf(to, "\n%s\n", c->text);
}

void mr_usage_man(FILE *to)
{
    fprintf(to, ".TH MICRORAYD 1 \"\" \"microray %s\" \"User Commands\"\n", MR_VERSION_STRING);
    fputs(".SH NAME\nmicrorayd \\- render daemon and one\\-shot renderer of microray\n.SH SYNOPSIS\n", to);
    for (size_t i = 0; i < COUNT(COMMANDS); i++) {
        fputs(".B microrayd\n", to);
        fprintf(to, ".I %s", COMMANDS[i].name);
        if (COMMANDS[i].args[0]) {
            fputc(' ', to);
            mr_usage_roff(to, COMMANDS[i].args);
        }
        fputs(COMMANDS[i].flag_count ? " [OPTIONS]\n.br\n" : "\n.br\n", to);
    }
    fputs(".SH DESCRIPTION\nmicrorayd renders deforming, highly detailed geometry by CPU ray tracing "
          "(Embree) into OpenEXR frames, as a service with an HTTP API (serve) or one job at a time "
          "(render). Jobs are JSON documents; see the job format in the documentation.\n"
          ".SH COMMANDS\n",
          to);
    for (size_t i = 0; i < COUNT(COMMANDS); i++)
        mr_usage_man_command(to, &COMMANDS[i]);
    fputs(".SH OPTIONS\n.TP\n.B \\-\\-help\nafter a command: that command's usage on standard "
          "output (exit 0); alone: every command with every flag (also \\-h).\n"
          ".TP\n.B \\-\\-version\nthe version (also the command version).\n", to);
    fputs(".SH EXIT STATUS\n0 success; 1 rendering failed on our side (out of memory, Embree); 2 usage "
          "error; 3 invalid input (the job, an asset, EXR files that cannot be compared); 4 a file "
          "could not be read or written.\n"
          ".SH ENVIRONMENT\n.TP\n.B MICRORAY_DATA\nthe data directory of serve when \\-\\-data is not "
          "given.\n.SH FILES\n.TP\n.I DATA/microray.sqlite\njobs, frames and assets.\n"
          ".TP\n.I DATA/frames/ID/NNNN.exr\nrendered frames.\n.SH SEE ALSO\n.BR microray (1)\n",
          to);
}

void mr_usage_completion(FILE *to)
{
    fputs("# bash completion for microrayd (generated by `microrayd completion`)\n"
          "_microrayd() {\n"
          "    local cur prev cmd\n"
          "    cur=${COMP_WORDS[COMP_CWORD]}\n"
          "    prev=${COMP_WORDS[COMP_CWORD-1]}\n"
          "    cmd=${COMP_WORDS[1]}\n"
          "    if [ \"$COMP_CWORD\" -eq 1 ]; then\n"
          "        COMPREPLY=($(compgen -W \"",
          to);
    for (size_t i = 0; i < COUNT(COMMANDS); i++)
        fprintf(to, "%s%s", i ? " " : "", COMMANDS[i].name);
    fputs(" --help --version\" -- \"$cur\"))\n"
          "        return\n"
          "    fi\n"
          "    case \"$prev\" in\n"
          "        --out|--cache|--data|--asset-root) COMPREPLY=($(compgen -d -- \"$cur\")); return ;;\n"
          "        --token-file|--tls-cert|--tls-key|--port-file) COMPREPLY=($(compgen -f -- \"$cur\")); return ;;\n"
          "    esac\n"
          "    case \"$cmd\" in\n",
          to);
    for (size_t i = 0; i < COUNT(COMMANDS); i++) {
        fprintf(to, "        %s) COMPREPLY=($(compgen -W \"", COMMANDS[i].name);
        for (size_t k = 0; k < COMMANDS[i].flag_count; k++)
            fprintf(to, "%s ", COMMANDS[i].flags[k].name);
        fputs("--help\" -- \"$cur\") $(compgen -f -- \"$cur\")) ;;\n", to);
    }
    fputs("    esac\n"
          "}\n"
          "complete -F _microrayd microrayd\n",
          to);
}
