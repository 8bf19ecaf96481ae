/*
 * usage.h - the one description of microrayd's command line: every
 * command, its arguments and every flag it takes. `microrayd --help`
 * (all of it), `microrayd CMD --help` and a command's usage errors, the
 * manual page (`microrayd man`, installed as microrayd.1) and the bash
 * completion (`microrayd completion`) are all printed from it, so none can
 * list a flag the others do not. The client keeps its own table
 * (client/usage.h); both print theirs with common/usage_text.h.
 */
#ifndef MR_USAGE_H
#define MR_USAGE_H

#include <stddef.h>
#include <stdio.h>

#include "usage_text.h"

/* The command named name, or NULL (internal commands are not listed). */
const mr_usage_command *mr_usage_find(const char *name);

/* `microrayd --help`: every command with every flag. */
void mr_usage_all(FILE *to);
/* One command's usage and flags (`microrayd CMD --help`, usage errors). */
void mr_usage_command_print(FILE *to, const char *name);
/* The manual page, roff (man(7) macros). */
void mr_usage_man(FILE *to);
/* A bash completion script for microrayd. */
void mr_usage_completion(FILE *to);

#endif
