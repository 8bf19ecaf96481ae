/*
 * usage_text.c - the printers of a usage table (usage_text.h).
 */
#include "usage_text.h"

#include <string.h>

void mr_usage_print_flag(FILE *to, const mr_usage_flag *f)
{
    char head[64];
    snprintf(head, sizeof head, "    %s%s%s", f->name, f->arg ? " " : "", f->arg ? f->arg : "");
    fputs(head, to);
    int col = (int)strlen(head);
    const int indent = 28;
    if (col >= indent - 1) {
        fputc('\n', to);
        col = 0;
    }
    fprintf(to, "%*s", indent - col, "");
    col = indent;
    for (const char *p = f->text; *p;) {
        while (*p == ' ')
            p++;
        size_t w = strcspn(p, " ");
        if (!w)
            break;
        if (col > indent && col + 1 + (int)w > 78) {
            fprintf(to, "\n%*s", indent, "");
            col = indent;
        } else if (col > indent) {
            fputc(' ', to);
            col++;
        }
        fwrite(p, 1, w, to);
        col += (int)w;
        p += w;
    }
    fputc('\n', to);
}

void mr_usage_print_command(FILE *to, const char *program, const mr_usage_command *c)
{
    fprintf(to, "  %s %s%s%s%s\n", program, c->name, c->args[0] ? " " : "", c->args,
            c->flag_count ? " [OPTIONS]" : "");
    fprintf(to, "      %s\n", c->summary);
    for (size_t i = 0; i < c->flag_count; i++)
        mr_usage_print_flag(to, &c->flags[i]);
}

void mr_usage_roff(FILE *to, const char *s)
{
    if (*s == '.' || *s == '\'')
        fputs("\\&", to);
    for (; *s; s++) {
        if (*s == '\\')
            fputs("\\e", to);
        else if (*s == '-')
            fputs("\\-", to);
        else
            fputc(*s, to);
    }
}

void mr_usage_man_flag(FILE *to, const mr_usage_flag *f)
{
    fputs(".TP\n.B ", to);
    mr_usage_roff(to, f->name);
    if (f->arg) {
        fputs(" \\fI", to);
        mr_usage_roff(to, f->arg);
        fputs("\\fR", to);
    }
    fputs("\n", to);
    mr_usage_roff(to, f->text);
    fputs("\n", to);
}

void mr_usage_man_command(FILE *to, const mr_usage_command *c)
{
    fputs(".SS ", to);
    mr_usage_roff(to, c->name);
    if (c->args[0]) {
        fputc(' ', to);
        mr_usage_roff(to, c->args);
    }
    fputs("\n", to);
    mr_usage_roff(to, c->summary);
    fputs(".\n", to);
    if (c->text) {
        fputs(".PP\n", to);
        mr_usage_roff(to, c->text);
        fputs("\n", to);
    }
    for (size_t k = 0; k < c->flag_count; k++)
        mr_usage_man_flag(to, &c->flags[k]);
}
