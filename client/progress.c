/*
 * progress.c - the progress bar and progress lines of `submit --wait`
 * (see progress.h).
 *
 * The ETA uses the pace of frames finished while we watched: from the
 * first such frame on (so the time a job sat in the queue or spent
 * importing assets does not count), and before that from the moment
 * following began.
 */
#include "progress.h"
#include "client.h"

#include <stdarg.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <unistd.h>

#define BAR_WIDTH 20

void mrc_progress_init(mrc_progress *p, FILE *out, bool tty, bool quiet)
{
    memset(p, 0, sizeof *p);
    p->out = out;
    p->tty = tty;
    p->quiet = quiet;
    p->start = mrc_now();
    p->done0 = -1;
}

double mrc_progress_elapsed(const mrc_progress *p)
{
    return mrc_now() - p->start;
}

int mrc_terminal_columns(FILE *out)
{
    struct winsize ws;
    if (out && ioctl(fileno(out), TIOCGWINSZ, &ws) == 0 && ws.ws_col > 0)
        return ws.ws_col;
    const char *env = getenv("COLUMNS");
    long cols = env ? strtol(env, NULL, 10) : 0;
    return cols > 0 && cols < 10000 ? (int)cols : 80;
}

/* Narrowest bar still worth drawing. */
#define BAR_MIN 5

void mrc_progress_format(char *dst, size_t size, int done, int failed, int total,
                         const char *state, double elapsed, double eta, int max_len)
{
    char el[32], et[32], extra[96];
    mrc_format_seconds(el, sizeof el, elapsed);
    extra[0] = '\0';
    size_t used = 0;
    if (failed > 0)
        used += (size_t)snprintf(extra + used, sizeof extra - used, "  %d failed", failed);
    /* "queued" and the like; not the end states, which get a summary line */
    bool shown = state && strcmp(state, "running") != 0 && strcmp(state, "succeeded") != 0 &&
                 strcmp(state, "failed") != 0 && strcmp(state, "canceled") != 0;
    if (shown && used < sizeof extra)
        used += (size_t)snprintf(extra + used, sizeof extra - used, "  %s", state);
    if (eta >= 0.0 && used < sizeof extra) {
        if (eta < 1.0)
            snprintf(et, sizeof et, "<1 s");
        else if (eta < 60.0)
            snprintf(et, sizeof et, "%.0f s", eta);
        else
            mrc_format_seconds(et, sizeof et, eta);
        snprintf(extra + used, sizeof extra - used, "  ETA %s", et);
    }
    char text[160];
    int tl = snprintf(text, sizeof text, "%d/%d frames  %s%s", done, total, el, extra);
    if (tl < 0)
        tl = 0;
    if (tl > (int)sizeof text - 1)
        tl = (int)sizeof text - 1;
    /* "[bar] " takes width + 3: as wide as fits, down to BAR_MIN, else none */
    int width = BAR_WIDTH;
    if (max_len > 0 && tl + 3 + width > max_len)
        width = max_len - tl - 3;
    char bar[BAR_WIDTH + 1] = "";
    if (width >= BAR_MIN) {
        int filled = 0;
        if (total > 0) {
            int finished = done + failed;
            if (finished > total)
                finished = total;
            filled = (int)((long long)finished * width / total);
        }
        for (int i = 0; i < width; i++)
            bar[i] = i < filled ? '#' : '.';
        bar[width] = '\0';
        snprintf(dst, size, "[%s] %s", bar, text);
    } else {
        snprintf(dst, size, "%s", text);
    }
    /* the text is ASCII: a byte is a column */
    if (max_len > 0 && strlen(dst) > (size_t)max_len)
        dst[max_len] = '\0';
}

static void clear_bar(mrc_progress *p)
{
    if (!p->drawn)
        return;
    int room = p->columns > 1 ? p->columns - 1 : 1;
    fprintf(p->out, "\r%*s\r", p->drawn_len < room ? p->drawn_len : room, "");
    p->drawn = false;
    p->drawn_len = 0;
}

void mrc_progress_update(mrc_progress *p, int done, int failed, int total, const char *state,
                         bool force)
{
    double now = mrc_now();
    if (p->done0 < 0)
        p->done0 = done;
    if (p->first_done == 0.0 && done > p->done0) {
        p->first_done = now;
        p->done_at_first = done;
    }
    if (p->quiet || !p->tty)
        return;
    if (!force && p->drawn && now - p->last_draw < 0.1)
        return;

    double eta = -1.0;
    int remaining = total - done - failed;
    bool running = !state || strcmp(state, "running") == 0;
    if (running && remaining > 0) {
        if (done > p->done_at_first && p->first_done > 0.0)
            eta = (now - p->first_done) / (done - p->done_at_first) * remaining;
        else if (done > p->done0)
            eta = (now - p->start) / (done - p->done0) * remaining;
    }
    char line[256];
    /* one column short of the width: a line reaching the last column wraps */
    p->columns = mrc_terminal_columns(p->out);
    int room = p->columns - 1 < (int)sizeof line - 1 ? p->columns - 1 : (int)sizeof line - 1;
    if (room < 1)
        room = 1;
    mrc_progress_format(line, sizeof line, done, failed, total, state, now - p->start, eta, room);
    int len = (int)strlen(line);
    /* pad with blanks over a longer previous line instead of relying on
     * terminal escape sequences (never past the room: that would wrap) */
    int old = p->drawn_len < room ? p->drawn_len : room;
    fprintf(p->out, "\r%s%*s", line, old > len ? old - len : 0, "");
    fflush(p->out);
    p->drawn = true;
    p->drawn_len = len > p->drawn_len ? len : p->drawn_len;
    p->last_draw = now;
}

void mrc_progress_message(mrc_progress *p, const char *fmt, ...)
{
    if (p->quiet)
        return;
    clear_bar(p);
    va_list ap;
    va_start(ap, fmt);
    vfprintf(p->out, fmt, ap);
    va_end(ap);
    fputc('\n', p->out);
    fflush(p->out);
}

void mrc_progress_finish(mrc_progress *p)
{
    if (p->drawn) {
        fputc('\n', p->out);
        fflush(p->out);
    }
    p->drawn = false;
    p->drawn_len = 0;
}
