/*
 * fuzz_tmp.h - a harness's private temporary folder, named
 * <base>/<prefix>-<pid>-XXXXXX on /dev/shm when there is one. A harness
 * that crashes (the point of fuzzing) never runs its atexit cleanup, so the
 * folders of harness processes that no longer exist are removed first.
 * Header-only: each harness includes it once.
 */
#ifndef MR_FUZZ_TMP_H
#define MR_FUZZ_TMP_H

#include <dirent.h>
#include <ftw.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

static int fuzz_tmp_rm(const char *p, const struct stat *st, int flag, struct FTW *ftw)
{
    (void)st, (void)flag, (void)ftw;
    remove(p);
    return 0;
}

static void fuzz_tmp_remove(const char *dir)
{
    if (dir && dir[0])
        nftw(dir, fuzz_tmp_rm, 16, FTW_DEPTH | FTW_PHYS);
}

/* Makes the folder into out (size >= 128); returns 0, or -1. */
static int fuzz_tmp_make(const char *prefix, char *out, size_t size)
{
    const char *base = access("/dev/shm", W_OK) == 0 ? "/dev/shm" : getenv("TMPDIR");
    if (!base || strlen(base) > 40)
        base = "/tmp";
    DIR *d = opendir(base);
    size_t pl = strlen(prefix);
    for (struct dirent *e; d && (e = readdir(d));) {
        long pid;
        char path[512];
        if (strncmp(e->d_name, prefix, pl) != 0 || e->d_name[pl] != '-' ||
            sscanf(e->d_name + pl + 1, "%ld-", &pid) != 1 || pid <= 0 ||
            kill((pid_t)pid, 0) == 0)
            continue;
        snprintf(path, sizeof path, "%s/%s", base, e->d_name);
        fuzz_tmp_remove(path);
    }
    if (d)
        closedir(d);
    snprintf(out, size, "%s/%s-%ld-XXXXXX", base, prefix, (long)getpid());
    return mkdtemp(out) ? 0 : -1;
}

#endif
