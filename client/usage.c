/*
 * usage.c - microray's command line, described once (usage.h).
 */
#include "usage.h"

#include <string.h>

#include "client.h"

#define COUNT(a) (sizeof(a) / sizeof((a)[0]))
#define JSON_FLAG {"--json", NULL, "print the result as JSON on standard output"}

static const mr_usage_flag GLOBAL[] = {
    {"--server", "URL", "the daemon (default: $MICRORAY_SERVER, else " MRC_DEFAULT_SERVER ")"},
    {"--token-file", "FILE", "send the bearer token of FILE's first line (default: $MICRORAY_TOKEN)"},
    {"--quiet", NULL, "no progress or confirmations (-q; ids, tables, JSON and errors still print)"},
    {"--help", NULL, "this help, or with a command that command's (-h)"},
    {"--version", NULL, "the client's version (-V)"},
};

static const mr_usage_flag SUBMIT[] = {
    {"--wait", NULL, "follow the job to its end with a progress display (exit 1 if it fails or is canceled)"},
    {"--out", "DIR", "download DIR/NNNN.exr and DIR/stats.json as frames finish (implies --wait)"},
    {"--png", NULL, "with --out: 8-bit sRGB previews DIR/NNNN.png and DIR/contact-sheet.png instead of the EXRs"},
    {"--idempotency-key", "KEY", "the same key with the same body returns the same job (1..200 printable ASCII characters)"},
    {"--json", NULL, "print the server's answer as JSON (with --wait: the job as it ended)"},
};
static const mr_usage_flag STATUS[] = {
    {"--errors", NULL, "a table of time against error per frame and reference, with medians and worst frames (jobs with \"reference\": true)"},
    JSON_FLAG,
};
static const mr_usage_flag LIST[] = {
    {"--state", "S", "only jobs in state S: queued, running, succeeded, failed or canceled"},
    {"--name", "NAME", "only jobs of this name"},
    {"--limit", "N", "at most N jobs (default: every page)"},
    JSON_FLAG,
};
static const mr_usage_flag WAIT[] = {
    {"--out", "DIR", "download the frames and stats.json into DIR as they finish"},
    {"--png", NULL, "with --out: PNG previews and a contact sheet instead of EXRs"},
    {"--json", NULL, "print the job as it ended as JSON"},
};
static const mr_usage_flag FETCH[] = {
    {"--out", "DIR", "where the frames and stats.json go (required)"},
    {"--png", NULL, "PNG previews and a contact sheet instead of EXRs"},
    {"--json", NULL, "print what was fetched as JSON"},
};
static const mr_usage_flag ONLY_JSON[] = {JSON_FLAG};
static const mr_usage_flag CLUSTER_SUBMIT[] = {
    {"--slurm", NULL, "submit to Slurm (sbatch; the one scheduler supported)"},
    {"--out", "DIR", "shared folder of the frames, stats.json and the cluster's state"},
    {"--chunk", "N", "frames per array task"},
    {"--partition", "P", "Slurm partition"},
    {"--time", "T", "Slurm time limit per task"},
    {"--threads", "N", "render threads per task (1..256)"},
    {"--microrayd", "PATH", "the microrayd the tasks run (default: microrayd on their PATH)"},
    JSON_FLAG,
};

static const mr_usage_command COMMANDS[] = {
    {"submit", "JOB.json", "submit a job (\"-\" reads it from stdin) and print its id", NULL, SUBMIT, COUNT(SUBMIT)},
    {"status", "ID", "state, frame counts, timestamps and errors of a job", NULL, STATUS, COUNT(STATUS)},
    {"list", "", "jobs, newest first", NULL, LIST, COUNT(LIST)},
    {"wait", "ID", "follow a job already submitted, like submit --wait",
     "A dropped event stream is resumed after its last event; Ctrl-C leaves the job running on the "
     "server and says how to follow it again.",
     WAIT, COUNT(WAIT)},
    {"fetch", "ID", "download the job's finished frames and stats.json, whatever its state", NULL, FETCH, COUNT(FETCH)},
    {"cancel", "ID", "cancel a queued or running job", NULL, ONLY_JSON, COUNT(ONLY_JSON)},
    {"retry", "ID", "re-queue the unfinished frames of a failed or canceled job", NULL, ONLY_JSON, COUNT(ONLY_JSON)},
    {"delete", "ID", "delete a job and its frames on the server", NULL, ONLY_JSON, COUNT(ONLY_JSON)},
    {"upload", "FILE", "store a model or image on the server and print its asset id",
     "Name it in a job as \"assets\": {\"hero\": {\"id\": \"<that id>\"}}; asset paths in a job are "
     "resolved on the server, not rewritten.",
     ONLY_JSON, COUNT(ONLY_JSON)},
    {"health", "", "check the daemon's /healthz and /readyz", NULL, ONLY_JSON, COUNT(ONLY_JSON)},
    {"cluster submit", "JOB.json", "render a job on Slurm: a prepare job, an array of chunks, a merge",
     "The frames go into the shared --out DIR (docs/scale.md).", CLUSTER_SUBMIT, COUNT(CLUSTER_SUBMIT)},
    {"cluster status", "DIR", "every frame's and task's state of a cluster job", NULL, ONLY_JSON, COUNT(ONLY_JSON)},
    {"cluster wait", "DIR", "follow a cluster job; requeue tasks that ended without their frames", NULL,
     ONLY_JSON, COUNT(ONLY_JSON)},
    {"help", "[COMMAND]", "this help, or one command's", NULL, NULL, 0},
};

const mr_usage_command *mrc_usage_find(const char *name)
{
    for (size_t i = 0; name && i < COUNT(COMMANDS); i++)
        if (!strcmp(COMMANDS[i].name, name))
            return &COMMANDS[i];
    return NULL;
}

const mr_usage_flag *mrc_usage_flag_find(const mr_usage_command *c, const char *name)
{
    for (size_t i = 0; c && i < c->flag_count; i++)
        if (!strcmp(c->flags[i].name, name))
            return &c->flags[i];
    return NULL;
}

bool mrc_usage_takes_value(const char *name)
{
    for (size_t i = 0; i < COUNT(COMMANDS); i++) {
        const mr_usage_flag *f = mrc_usage_flag_find(&COMMANDS[i], name);
        if (f && f->arg)
            return true;
    }
    return false;
}

const mr_usage_flag *mrc_usage_global(const char *name)
{
    for (size_t i = 0; i < COUNT(GLOBAL); i++)
        if (!strcmp(GLOBAL[i].name, name))
            return &GLOBAL[i];
    return NULL;
}

void mrc_usage_command_print(FILE *to, const mr_usage_command *c)
{
    mr_usage_print_command(to, "microray", c);
    if (c->text)
        fprintf(to, "      %s\n", c->text);
}

void mrc_usage_all(FILE *to)
{
    fputs("usage: microray [--server URL] [--token-file FILE] [--quiet] COMMAND [ARGS]\n\n"
          "Submits render jobs to a microrayd daemon and follows and fetches their results.\n\n"
          "Commands:\n",
          to);
    for (size_t i = 0; i < COUNT(COMMANDS); i++)
        mrc_usage_command_print(to, &COMMANDS[i]);
    fputs("\nOptions of every command (anywhere on the line):\n", to);
    for (size_t i = 0; i < COUNT(GLOBAL); i++)
        mr_usage_print_flag(to, &GLOBAL[i]);
    fputs("\nExit codes:\n"
          "  0  success\n"
          "  1  the job failed or was canceled (submit --wait, wait)\n"
          "  2  usage error\n"
          "  3  the server rejected the request (4xx)\n"
          "  4  the server is unreachable, answered 5xx or answered nonsense\n"
          "  5  a local file could not be read or written\n"
          "\nSee microray(1) and docs/client.md.\n",
          to);
}

void mrc_usage_man(FILE *to)
{
    fprintf(to, ".TH MICRORAY 1 \"\" \"microray %s\" \"User Commands\"\n", MRC_VERSION);
    fputs(".SH NAME\nmicroray \\- command\\-line client of the microrayd render daemon\n"
          ".SH SYNOPSIS\n.B microray\n[\\fIOPTIONS\\fR] \\fICOMMAND\\fR [\\fIARGS\\fR]\n"
          ".SH DESCRIPTION\nmicroray submits render jobs to a microrayd daemon over its HTTP API, "
          "follows them with a progress display, downloads frames and statistics and manages jobs "
          "and assets. Standard output carries only what a script may capture (ids, tables, JSON); "
          "progress, confirmations and errors go to standard error.\n.SH COMMANDS\n",
          to);
    for (size_t i = 0; i < COUNT(COMMANDS); i++)
        mr_usage_man_command(to, &COMMANDS[i]);
    fputs(".SH OPTIONS\nThese work with every command, anywhere on the line.\n", to);
    for (size_t i = 0; i < COUNT(GLOBAL); i++)
        mr_usage_man_flag(to, &GLOBAL[i]);
    fputs(".SH EXIT STATUS\n0 success; 1 the job failed or was canceled (submit \\-\\-wait, wait); "
          "2 usage error; 3 the server rejected the request (4xx); 4 the server is unreachable, "
          "answered 5xx or answered nonsense; 5 a local file could not be read or written.\n"
          ".SH ENVIRONMENT\n.TP\n.B MICRORAY_SERVER\nthe daemon's URL when \\-\\-server is not given.\n"
          ".TP\n.B MICRORAY_TOKEN\nthe bearer token when \\-\\-token\\-file is not given.\n"
          ".TP\n.B TERM\n\\fIdumb\\fR turns the progress bar into plain lines.\n"
          ".SH SEE ALSO\n.BR microrayd (1)\n",
          to);
}

void mrc_usage_completion(FILE *to)
{
    fputs("# bash completion for microray (generated by `microray completion`)\n"
          "_microray() {\n"
          "    local cur prev cmd sub i\n"
          "    cur=${COMP_WORDS[COMP_CWORD]}\n"
          "    prev=${COMP_WORDS[COMP_CWORD-1]}\n"
          "    cmd= sub=\n"
          "    for ((i = 1; i < COMP_CWORD; i++)); do\n"
          "        case ${COMP_WORDS[i]} in\n"
          "            --server|--token-file) ((i++)) ;;\n"
          "            -*) ;;\n"
          "            *) if [ -z \"$cmd\" ]; then cmd=${COMP_WORDS[i]}; "
          "elif [ \"$cmd\" = cluster ] && [ -z \"$sub\" ]; then sub=${COMP_WORDS[i]}; fi ;;\n"
          "        esac\n"
          "    done\n"
          "    case \"$prev\" in\n"
          "        --out) COMPREPLY=($(compgen -d -- \"$cur\")); return ;;\n"
          "        --token-file|--microrayd) COMPREPLY=($(compgen -f -- \"$cur\")); return ;;\n"
          "        --state) COMPREPLY=($(compgen -W \"queued running succeeded failed canceled\" -- \"$cur\")); return ;;\n"
          "    esac\n"
          "    local globals=\"",
          to);
    for (size_t i = 0; i < COUNT(GLOBAL); i++)
        fprintf(to, "%s%s", i ? " " : "", GLOBAL[i].name);
    fputs("\"\n    if [ -z \"$cmd\" ]; then\n        COMPREPLY=($(compgen -W \"$globals ", to);
    for (size_t i = 0; i < COUNT(COMMANDS); i++)
        if (!strchr(COMMANDS[i].name, ' '))
            fprintf(to, "%s ", COMMANDS[i].name);
    fputs("cluster\" -- \"$cur\"))\n        return\n    fi\n"
          "    [ \"$cmd\" = cluster ] && [ -z \"$sub\" ] && { COMPREPLY=($(compgen -W \"submit status wait\" -- \"$cur\")); return; }\n"
          "    case \"$cmd${sub:+ $sub}\" in\n",
          to);
    for (size_t i = 0; i < COUNT(COMMANDS); i++) {
        fprintf(to, "        \"%s\") COMPREPLY=($(compgen -W \"$globals ", COMMANDS[i].name);
        for (size_t k = 0; k < COMMANDS[i].flag_count; k++)
            fprintf(to, "%s ", COMMANDS[i].flags[k].name);
        fputs("\" -- \"$cur\") $(compgen -f -- \"$cur\")) ;;\n", to);
    }
    fputs("    esac\n}\ncomplete -F _microray microray\n", to);
}
