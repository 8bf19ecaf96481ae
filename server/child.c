/*
 * child.c - starting the daemon's child processes and reading how they
 * ended (child.h).
 */
#define _GNU_SOURCE
#include "child.h"

#include <errno.h>
#include <signal.h>
#include <stdio.h>
#include <string.h>
#include <sys/prctl.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

/* After fork, in the child: only async-signal-safe calls until the exec. */
static _Noreturn void child_main(const char *exe, char *const *argv, int fd,
                                 const mr_child_limits *lim, pid_t parent, int (*run)(void *user),
                                 void *user)
{
    /* die with the daemon; nothing inherited but the descriptor given */
    prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (getppid() != parent)
        _exit(120);
    if (fd != MR_CHILD_FD && dup2(fd, MR_CHILD_FD) != MR_CHILD_FD)
        _exit(121);
    close_range(MR_CHILD_FD + 1, ~0u, 0);
    /* a crash kills the child, so the parent sees the signal (not a
     * handler the parent installed, nor a sanitizer's report and exit);
     * the daemon's blocked stop signals are not the child's */
    const int crash[] = {SIGSEGV, SIGBUS, SIGILL, SIGFPE, SIGABRT};
    for (size_t i = 0; i < sizeof crash / sizeof *crash; i++)
        signal(crash[i], SIG_DFL);
    signal(SIGPIPE, SIG_DFL);
    sigset_t none_blocked;
    sigemptyset(&none_blocked);
    sigprocmask(SIG_SETMASK, &none_blocked, NULL);
    struct rlimit none = {0, 0};
    setrlimit(RLIMIT_CORE, &none);
    if (lim && lim->cpu_seconds) {
        struct rlimit r = {lim->cpu_seconds, (rlim_t)lim->cpu_seconds + 1};
        setrlimit(RLIMIT_CPU, &r);
    }
    if (lim && lim->address_space) {
        struct rlimit r = {lim->address_space, lim->address_space};
        setrlimit(RLIMIT_AS, &r);
    }
    if (lim && lim->nice)
        setpriority(PRIO_PROCESS, 0, lim->nice);
    if (exe) {
        execv(exe, argv);
        _exit(127);
    }
    _exit(run(user));
}

pid_t mr_child_spawn(const char *exe, char *const *argv, int fd, const mr_child_limits *lim,
                     int (*run)(void *user), void *user)
{
    pid_t parent = getpid();
    fflush(NULL); /* nothing buffered is written twice */
    pid_t pid = fork();
    if (pid == 0)
        child_main(exe, argv, fd, lim, parent, run, user);
    return pid;
}

void mr_child_describe_exit(int status, char *out, size_t size)
{
    if (WIFSIGNALED(status)) {
        int sig = WTERMSIG(status);
        const char *name = sigabbrev_np(sig);
        if (name)
            snprintf(out, size, "killed by SIG%s", name);
        else
            snprintf(out, size, "killed by signal %d", sig);
    } else if (WIFEXITED(status)) {
        snprintf(out, size, "exit %d", WEXITSTATUS(status));
    } else {
        snprintf(out, size, "wait status %d", status);
    }
}

size_t mr_child_memory(pid_t pid, bool resident)
{
    char path[64];
    snprintf(path, sizeof path, "/proc/%d/statm", (int)pid);
    FILE *f = fopen(path, "re");
    if (!f)
        return 0;
    unsigned long v[2] = {0, 0};
    int n = fscanf(f, "%lu %lu", &v[0], &v[1]);
    fclose(f);
    if (n != 2)
        return 0;
    return (size_t)v[resident ? 1 : 0] * (size_t)sysconf(_SC_PAGESIZE);
}

int mr_child_reap(pid_t pid)
{
    int status = 0;
    while (waitpid(pid, &status, 0) < 0) {
        if (errno != EINTR)
            return 0;
    }
    return status;
}
