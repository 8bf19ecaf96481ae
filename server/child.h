/*
 * child.h - the daemon's child processes: imports (import_worker.h) and
 * renders (render_proc.h) run in processes of their own, so that nothing a
 * job or a model file does to its process takes the daemon down (issue 12).
 *
 * One way to start such a child, and one way to say how it ended:
 *  - mr_child_spawn forks and, in the child, makes only async-signal-safe
 *    calls before it execs a fresh image (the daemon has many threads; a
 *    lock one of them held at the fork, an allocator's say, would stay held
 *    for ever in a child that went on in the daemon's image). The child
 *    dies with the thread that started it, inherits no descriptor but the
 *    one it talks on (as descriptor 3), dumps no core, lets crash signals
 *    kill it (so the parent sees the signal) and may be given an
 *    address-space limit, a CPU-time limit and a lower CPU priority.
 *  - mr_child_describe_exit turns a wait status into words for an error
 *    message ("killed by SIGSEGV", "exit 3").
 */
#ifndef MR_CHILD_H
#define MR_CHILD_H

#include <stdbool.h>
#include <stddef.h>
#include <sys/types.h>

/* The descriptor a child talks to its parent on. */
#define MR_CHILD_FD 3

/* Whether this is a sanitizer build: AddressSanitizer reserves terabytes of
 * shadow memory, so children get no address-space limit then. */
#if defined(__SANITIZE_ADDRESS__)
#define MR_SANITIZED 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
#define MR_SANITIZED 1
#endif
#endif
#ifndef MR_SANITIZED
#define MR_SANITIZED 0
#endif

typedef struct mr_child_limits {
    size_t address_space; /* RLIMIT_AS in bytes; 0: none */
    unsigned cpu_seconds; /* RLIMIT_CPU (SIGXCPU past it); 0: none */
    int nice;             /* CPU niceness to run at; 0: the parent thread's */
} mr_child_limits;

/* Forks and execs exe with argv (NULL-terminated) in the child, whose
 * descriptor MR_CHILD_FD is fd (the parent keeps its own copy open; the
 * caller closes it after the call). exe NULL: the child instead calls
 * run(user) and exits with its result - only for single-threaded callers
 * (tests), see above. Returns the child's pid, or -1 with errno set. */
pid_t mr_child_spawn(const char *exe, char *const *argv, int fd, const mr_child_limits *lim,
                     int (*run)(void *user), void *user);

/* "killed by SIGSEGV", "exit 3" (status from waitpid). */
void mr_child_describe_exit(int status, char *out, size_t size);

/* Bytes of memory a process uses, from /proc/PID/statm: its address space
 * (resident false) or its resident set (true); 0 if it cannot be read. */
size_t mr_child_memory(pid_t pid, bool resident);

/* waitpid(pid) retried on EINTR; the wait status (0 if it failed). */
int mr_child_reap(pid_t pid);

#endif
