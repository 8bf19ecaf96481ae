/*
 * progress.h - how `microray submit --wait` shows a job's progress on stderr.
 *
 * On a terminal one line is redrawn in place with \r:
 *   [#########...........] 12/49 frames  3.1 s  ETA 9 s
 * never wider than the terminal less one column (asked at every redraw, so
 * a resize is followed): a narrower bar first, then none, then the text
 * cut, because a line that reaches the last column wraps and every redraw
 * would then leave a line behind.
 * Anywhere else (a log file, CI) redrawing would only produce noise, so the
 * caller's per-frame messages are printed as plain lines and the bar is
 * never drawn. --quiet silences both; errors are not printed here.
 */
#ifndef MRC_PROGRESS_H
#define MRC_PROGRESS_H

#include <stdbool.h>
#include <stdio.h>

typedef struct mrc_progress {
    FILE *out;          /* stderr */
    bool tty;           /* redraw a bar instead of printing lines */
    bool quiet;
    bool drawn;         /* a bar is on screen, the cursor sits at its end */
    int drawn_len;      /* its length, for blanking a shorter redraw */
    int columns;        /* the terminal's width at the last redraw */
    double start;       /* when following began */
    double last_draw;
    int done0;          /* frames already finished when following began */
    double first_done;  /* when the first frame finished while we watched (0 = none yet) */
    int done_at_first;
} mrc_progress;

void mrc_progress_init(mrc_progress *p, FILE *out, bool tty, bool quiet);

/* Redraws the bar (terminal only) unless it was redrawn less than 0.1 s
 * ago and force is false. state is shown when it is not "running". */
void mrc_progress_update(mrc_progress *p, int done, int failed, int total, const char *state,
                         bool force);

/* Prints one message line (both modes; not when quiet). On a terminal the
 * bar is cleared first and redrawn by the next update. */
void mrc_progress_message(mrc_progress *p, const char *fmt, ...)
    __attribute__((format(printf, 2, 3)));

/* Leaves the bar on screen and ends its line. */
void mrc_progress_finish(mrc_progress *p);

/* Seconds since mrc_progress_init. */
double mrc_progress_elapsed(const mrc_progress *p);

/* The bar text without drawing it, at most max_len characters (0: no
 * limit). eta < 0 = unknown. */
void mrc_progress_format(char *dst, size_t size, int done, int failed, int total,
                         const char *state, double elapsed, double eta, int max_len);

/* Columns of the terminal at out (TIOCGWINSZ), else $COLUMNS, else 80. */
int mrc_terminal_columns(FILE *out);

#endif
