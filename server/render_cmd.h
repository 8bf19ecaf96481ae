/*
 * render_cmd.h - the one-shot commands of microrayd:
 *   microrayd render JOB.json --out DIR [--threads N] [--frames LIST] [--quiet]
 *   microrayd stats-merge DIR JOB.json
 *   microrayd compare A.exr B.exr [--diagonal D]
 */
#ifndef MR_RENDER_CMD_H
#define MR_RENDER_CMD_H

/* All return a process exit status (see the README's exit codes). */
int mr_cmd_render(int argc, char **argv);
int mr_cmd_compare(int argc, char **argv);
/* microrayd plan JOB.json: the job validated, and what splitting it
 * into parts needs (frames, max_retries) as JSON on stdout. */
int mr_cmd_plan(int argc, char **argv);
/* microrayd stats-merge DIR JOB.json: stats.json of the parts that
 * render --frames wrote. */
int mr_cmd_stats_merge(int argc, char **argv);
/* microrayd serve (server/serve_cmd.c). */
int mr_cmd_serve(int argc, char **argv);

#endif
