/*
 * proc_stats.c - process figures from /proc (proc_stats.h).
 */
#include "proc_stats.h"

#include <dirent.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <time.h>
#include <unistd.h>

/* Seconds since the epoch at which the machine booted (/proc/stat btime). */
static double boot_time(void)
{
    FILE *f = fopen("/proc/stat", "r");
    char line[256];
    double t = 0;
    while (f && fgets(line, sizeof line, f))
        if (!strncmp(line, "btime ", 6)) {
            t = atof(line + 6);
            break;
        }
    if (f)
        fclose(f);
    return t;
}

bool mr_proc_stats_read(pid_t pid, mr_proc_stats *out)
{
    memset(out, 0, sizeof *out);
    char path[64], buf[1024];
    if (pid)
        snprintf(path, sizeof path, "/proc/%d/stat", (int)pid);
    else
        snprintf(path, sizeof path, "/proc/self/stat");
    FILE *f = fopen(path, "r");
    size_t n = f ? fread(buf, 1, sizeof buf - 1, f) : 0;
    if (f)
        fclose(f);
    buf[n] = '\0';
    /* the command may hold spaces and parentheses: fields follow the last ')' */
    char *p = strrchr(buf, ')');
    if (!p)
        return false;
    /* from field 3 (state) on; utime and stime are fields 14 and 15,
     * starttime 22, vsize 23, rss (pages) 24 */
    unsigned long long field[25] = {0};
    int k = 3;
    for (char *tok = strtok(p + 2, " "); tok && k < 25; tok = strtok(NULL, " "), k++)
        field[k] = strtoull(tok, NULL, 10);
    long tick = sysconf(_SC_CLK_TCK), page = sysconf(_SC_PAGESIZE);
    if (tick <= 0 || page <= 0)
        return false;
    out->cpu_seconds = (double)(field[14] + field[15]) / (double)tick;
    out->start_time = boot_time() + (double)field[22] / (double)tick;
    out->virtual_bytes = field[23];
    out->resident_bytes = field[24] * (uint64_t)page;
    if (pid)
        snprintf(path, sizeof path, "/proc/%d/fd", (int)pid);
    else
        snprintf(path, sizeof path, "/proc/self/fd");
    DIR *d = opendir(path);
    for (struct dirent *e; d && (e = readdir(d));)
        out->open_fds += e->d_name[0] != '.';
    if (d) {
        closedir(d);
        if (!pid)
            out->open_fds--; /* the one opendir itself holds */
    }
    struct rlimit rl;
    if (!pid && getrlimit(RLIMIT_NOFILE, &rl) == 0)
        out->max_fds = rl.rlim_cur;
    return true;
}
