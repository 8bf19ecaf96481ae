/*
 * proc_stats.h - what /metrics says about processes (the daemon's own and
 * its render workers'), read from Linux's /proc: CPU seconds, resident
 * memory, open descriptors, start time. The Prometheus names they are
 * exported under are the client libraries' standard process_* metrics.
 */
#ifndef MR_PROC_STATS_H
#define MR_PROC_STATS_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <sys/types.h>

typedef struct mr_proc_stats {
    double cpu_seconds;      /* user + system */
    double start_time;       /* unix seconds */
    uint64_t resident_bytes;
    uint64_t virtual_bytes;
    unsigned open_fds;
    uint64_t max_fds;        /* RLIMIT_NOFILE's soft limit (the calling process's only) */
} mr_proc_stats;

/* The figures of process pid (0: this one); false when /proc cannot say
 * (the process is gone). */
bool mr_proc_stats_read(pid_t pid, mr_proc_stats *out);

#endif
