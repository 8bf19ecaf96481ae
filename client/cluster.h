/*
 * cluster.h - `microray cluster`: a job's frames rendered by a batch
 * scheduler instead of a daemon (issue 18; docs/scale.md). microray brings
 * no scheduler of its own: it writes three small batch scripts into the
 * shared output folder and hands them to Slurm.
 *
 *   submit --slurm JOB.json --out DIR --chunk N [--partition P] [--time T]
 *          [--threads N] [--microrayd PATH]
 *       1. a prepare job imports the assets and derives each kind's data
 *          (bakes, voxelisations) once into DIR/cache
 *          (`microrayd render --prepare`);
 *       2. a job array (sbatch --array, --dependency=afterok on 1) whose
 *          task k renders frames k*N .. k*N+N-1 with
 *          `microrayd render --frames`, reading that cache;
 *       3. a merge job (--dependency=afterany on 2) joins the tasks'
 *          statistics into DIR/stats.json (`microrayd stats-merge`).
 *       DIR/cluster/ keeps the scripts, the tasks' logs and state.json
 *       (the Slurm job ids, the chunking, each task's requeues).
 *   status DIR [--json]
 *       every frame's state in the daemon's words (done: its file is
 *       there; running or queued: its task as squeue shows it; failed: its
 *       task ended without it, sacct saying how where accounting runs).
 *   wait DIR
 *       follows status with the daemon client's progress bar until every
 *       frame is done and merged (exit 0) or the job cannot finish (exit 1);
 *       a task that ended without its frames (failed, killed, timed out) is
 *       requeued (scontrol requeue) up to the job's max_retries, and the
 *       merge is submitted again behind it.
 * Exit codes as the rest of the client (client.h); a scheduler command that
 * fails is MRC_EXIT_SERVER, with its message.
 */
#ifndef MRC_CLUSTER_H
#define MRC_CLUSTER_H

#include <stdbool.h>

/* argv[0] is the subcommand ("submit", "status", "wait"). Returns the
 * process exit code. */
int mrc_cluster_main(int argc, char **argv, bool quiet);

#endif
