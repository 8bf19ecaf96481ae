/*
 * usage_text.h - how both programs print a command-line description: the
 * types of a usage table and its printers (help text wrapped at 78 columns,
 * roff for the manual pages). The tables themselves, the one description
 * of each program's command line, are server/usage.c and client/usage.c.
 * common/ holds what microrayd and microray both link, and only that.
 */
#ifndef MR_USAGE_TEXT_H
#define MR_USAGE_TEXT_H

#include <stddef.h>
#include <stdio.h>

typedef struct mr_usage_flag {
    const char *name; /* "--threads" */
    const char *arg;  /* "N", or NULL for a switch */
    const char *text; /* what it does, one sentence or two */
} mr_usage_flag;

typedef struct mr_usage_command {
    const char *name;    /* "render", "cluster submit" */
    const char *args;    /* "JOB.json --out DIR" (positional and required parts) */
    const char *summary; /* one line */
    const char *text;    /* a paragraph, or NULL */
    const mr_usage_flag *flags;
    size_t flag_count;
} mr_usage_command;

/* "    --flag ARG" padded to column 28, then the text wrapped at 78. */
void mr_usage_print_flag(FILE *to, const mr_usage_flag *f);
/* "  PROGRAM NAME ARGS [OPTIONS]", the summary, then each flag. */
void mr_usage_print_command(FILE *to, const char *program, const mr_usage_command *c);
/* s as roff text: a leading '.' or '\'' escaped, '\' as \e, '-' as \-. */
void mr_usage_roff(FILE *to, const char *s);
/* A flag as a man(7) tagged paragraph. */
void mr_usage_man_flag(FILE *to, const mr_usage_flag *f);
/* A command's subsection of a manual page: name, arguments, summary, its
 * paragraph and its flags. */
void mr_usage_man_command(FILE *to, const mr_usage_command *c);

#endif
