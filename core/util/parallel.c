/* parallel.c - dynamic chunked parallel-for on pthreads (see parallel.h). */
#include "util/parallel.h"

#include <pthread.h>
#include <stdatomic.h>
#include <stdlib.h>
#include <unistd.h>


typedef struct {
    mr_range_fn fn;
    void *ctx;
    size_t count, grain;
    atomic_size_t next;
} job_t;

typedef struct {
    job_t *job;
    unsigned worker;
} worker_arg_t;

static void run_chunks(job_t *job, unsigned worker)
{
    for (;;) {
        size_t begin = atomic_fetch_add(&job->next, job->grain);
        if (begin >= job->count)
            return;
        size_t end = begin + job->grain;
        if (end > job->count)
            end = job->count;
        job->fn(job->ctx, begin, end, worker);
    }
}

static void *worker_main(void *p)
{
    worker_arg_t *arg = p;
    run_chunks(arg->job, arg->worker);
    return NULL;
}

unsigned mr_cpu_count(void)
{
    long n = sysconf(_SC_NPROCESSORS_ONLN);
    if (n < 1)
        return 1;
    return n > MR_MAX_THREADS ? MR_MAX_THREADS : (unsigned)n;
}

void mr_parallel_for(unsigned threads, size_t count, size_t grain, mr_range_fn fn, void *ctx)
{
    if (count == 0)
        return;
    if (grain == 0)
        grain = 1;
    if (threads == 0)
        threads = mr_cpu_count();
    if (threads > MR_MAX_THREADS)
        threads = MR_MAX_THREADS;
    size_t chunks = (count + grain - 1) / grain;
    if (threads > chunks)
        threads = (unsigned)chunks;

    job_t job = {.fn = fn, .ctx = ctx, .count = count, .grain = grain};
    atomic_init(&job.next, 0);
    if (threads <= 1) {
        run_chunks(&job, 0);
        return;
    }
    pthread_t tids[MR_MAX_THREADS];
    worker_arg_t args[MR_MAX_THREADS];
    unsigned started = 0;
    for (unsigned i = 1; i < threads; i++) {
        args[i] = (worker_arg_t){&job, i};
        if (pthread_create(&tids[i], NULL, worker_main, &args[i]) != 0)
            break; /* the threads we have (and the caller) finish the work */
        started = i;
    }
    run_chunks(&job, 0);
    for (unsigned i = 1; i <= started; i++)
        pthread_join(tids[i], NULL);
}
