/*
 * usage.h - the one description of microray's command line: every command,
 * its arguments and every option it takes. The option parser (main.c)
 * takes its options from here, and `microray --help`, `microray CMD
 * --help`, the manual page (`microray man`, installed as microray.1) and
 * the bash completion (`microray completion`) are printed from it, so none
 * can know an option the others do not. microrayd has its own table
 * (server/usage.h); both print theirs with common/usage_text.h.
 */
#ifndef MRC_USAGE_H
#define MRC_USAGE_H

#include <stdbool.h>
#include <stddef.h>
#include <stdio.h>

#include "usage_text.h"

/* name "submit" or "cluster submit"; NULL when there is none. */
const mr_usage_command *mrc_usage_find(const char *name);
/* The option of c named name ("--out"), or NULL. */
const mr_usage_flag *mrc_usage_flag_find(const mr_usage_command *c, const char *name);
/* Whether some command's option of this name takes a value (so the word
 * after it is not a command or a global option). */
bool mrc_usage_takes_value(const char *name);
/* The options every command takes (--server, --token-file, --quiet, ...). */
const mr_usage_flag *mrc_usage_global(const char *name);

void mrc_usage_all(FILE *to);
void mrc_usage_command_print(FILE *to, const mr_usage_command *c);
void mrc_usage_man(FILE *to);
void mrc_usage_completion(FILE *to);

#endif
