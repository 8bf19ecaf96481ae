/*
 * parallel.c - chunked parallel-for (microray.h, "cores and the
 * parallel loop") on a persistent pool of worker threads.
 *
 * Why a pool: starting and joining threads on every call cost tens of
 * microseconds, about a tenth of a spring-mass step (two loops per
 * substep, 15 substeps a frame), and a thread that started late held up
 * the join even when the caller had done all the work.
 *
 * The pool. Workers are started lazily, the first time a loop asks for
 * more threads than there are (up to MR_MAX_THREADS - 1; the caller is
 * worker 0), and live until mr_parallel_shutdown or the end of the
 * process. Worker i owns slot i, whose state word is
 * (generation << 2 | phase): the caller posts a loop by storing POSTED
 * into the slots of workers 1..threads-1; a worker takes it by turning
 * POSTED into RUNNING (compare-and-swap), runs chunks, then stores IDLE
 * and counts itself in `finished`. Once the caller has run out of chunks
 * it revokes every post not yet taken (POSTED -> IDLE), so it never waits
 * for a worker that has not woken up (on a loaded machine that can be a
 * whole time slice), and waits only for the workers that took part, which
 * are at most finishing one chunk.
 * Waiting: spin a little (a loop often follows a loop: the mappings'
 * per-triangle pass, then their per-vertex one), then sleep on the word
 * with a futex; the other side wakes a sleeper only when its `sleeping`
 * flag is up (seq_cst store of the word, then load of the flag, against
 * store of the flag, then load of the word: one of the two sees the
 * other).
 *
 * Rules (documented in microray.h):
 *  - one loop at a time runs on the pool. A call while another thread's
 *    loop holds it starts threads of its own for that call, as before the
 *    pool (so two renderers in one process still get their cores);
 *  - a call from inside a task of a loop that runs on several threads runs
 *    serially on the calling thread: the outer loop already occupies the
 *    threads, and waiting for the pool from one of its own tasks would
 *    deadlock;
 *  - after fork the child has no workers: a pthread_atfork handler
 *    forgets the parent's (the next call in the child starts its own).
 *    The daemon's children exec before touching the pool; the import
 *    worker without an executable (tests) imports in the forked image.
 *    (A fork from inside a task would leave the child's copy of the loop
 *    waiting for workers it does not have: nothing does that.)
 * Results do not depend on any of this: fn's items are independent.
 *
 * Which thread runs which items. A loop's chunks are split into one
 * contiguous range per thread; a thread takes chunks from its own range
 * first and then from the others', front first, so a slow or sleeping
 * worker holds up nobody. Successive loops over the same items (a frame's
 * levels, the next frame's) then run mostly where they ran before, and
 * find the lines they wrote in their own core's cache: on the 2-vCPU
 * machine a cache line written by one core reaches the other in about
 * 220 ns (a ping-pong between the two measured 445 ns a round trip).
 * Every chunk taken from one shared counter, as before, sent half of a
 * loop's data across each time. Two threads, the same code otherwise: the
 * dancer's selection at depth 8, every leaf, 2.71-2.74 ms that way and
 * 2.27-2.38 ms with the shares (one thread: 3.4-3.5 ms); the spring-mass
 * probe's simulation (two loops over the grid's nodes per substep)
 * 7.3-10.1 ms a frame that way and 5.6-7.9 ms with the shares (eight
 * alternations, the median ratio 0.72-0.74).
 */
#define _GNU_SOURCE
#include "util/parallel.h"

#include <linux/futex.h>
#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <stdatomic.h>
#include <stdbool.h>
#include <stdint.h>
#include <string.h>
#include <sys/syscall.h>
#include <unistd.h>

typedef struct job {
    mr_range_fn fn;
    void *ctx;
    size_t grain;
    unsigned ranges;     /* one per thread of the loop */
    struct range *range;
} job_t;

/* Thread w's share of a loop's items, [next, end): taken a grain at a time
 * by w, then by the others once their own are done. A cache line each:
 * owners count on their own counters without moving a line between cores. */
typedef struct range {
    _Alignas(64) atomic_size_t next;
    size_t end;
} range_t;

/* Worker or caller: inside a task of a loop that runs on several threads
 * (a nested call runs serially). */
static _Thread_local bool in_task;

/* Runs chunks until none is left: the worker's own range, then the
 * others' in turn. */
static void run_chunks(job_t *job, unsigned worker)
{
    for (unsigned k = 0; k < job->ranges; k++) {
        range_t *r = &job->range[(worker + k) % job->ranges];
        for (;;) {
            size_t begin = atomic_fetch_add_explicit(&r->next, job->grain, memory_order_relaxed);
            if (begin >= r->end)
                break;
            size_t end = begin + job->grain;
            if (end > r->end)
                end = r->end;
            job->fn(job->ctx, begin, end, worker);
        }
    }
}

/* ---- threads of one call (the fallback when the pool is taken) ---- */

typedef struct call_arg {
    job_t *job;
    unsigned worker;
} call_arg;

static void *call_worker_main(void *p)
{
    call_arg *arg = p;
    in_task = true;
    run_chunks(arg->job, arg->worker);
    return NULL;
}

static void run_on_own_threads(job_t *job, unsigned threads)
{
    pthread_t tids[MR_MAX_THREADS];
    call_arg args[MR_MAX_THREADS];
    unsigned started = 0;
    for (unsigned i = 1; i < threads; i++) {
        args[i] = (call_arg){job, i};
        if (pthread_create(&tids[i], NULL, call_worker_main, &args[i]) != 0)
            break; /* the threads we have (and the caller) finish the work */
        started = i;
    }
    in_task = true;
    run_chunks(job, 0);
    in_task = false;
    for (unsigned i = 1; i <= started; i++)
        pthread_join(tids[i], NULL);
}

/* ---- the pool ---- */

enum { IDLE, POSTED, RUNNING, STOP };
#define PHASE(v) ((v) & 3u)
#define GEN(v) ((v) & ~3u)

/* Pause-loop iterations a waiter spins before it sleeps: about 3 us on
 * the x86 cores measured (a pause is ~16 ns there), enough for a loop
 * that follows at once. Longer spins cost more than they saved on the
 * busy 2-core machine (a loop of 64 half-microsecond items on 2 threads:
 * 62-72 us per call spinning 0 or 3 us, 72-84 us spinning 30 us, 110 us
 * spinning 300 us): a spinning worker spends the time slices the
 * scheduler would otherwise give it when it has work. */
#ifndef MR_POOL_SPIN
#define MR_POOL_SPIN 200
#endif

typedef struct slot {
    _Alignas(64) atomic_uint state; /* generation << 2 | phase; the futex word */
    atomic_uint sleeping;
    pthread_t tid;
} slot;

static struct pool {
    atomic_uint taken;   /* 1 while a loop (or a shutdown) holds the pool */
    atomic_uint workers; /* running: slots 1..workers (changed only by the pool's holder) */
    unsigned generation; /* of the last post, in steps of 4 */
    job_t *job;          /* the loop the posts are for */
    _Alignas(64) atomic_uint finished; /* workers done with the loop; futex word */
    atomic_uint caller_sleeping;
    slot slots[MR_MAX_THREADS];
} pool;

static atomic_int use_pool = 1;
static atomic_int spin_limit = MR_POOL_SPIN;
static pthread_once_t atfork_once = PTHREAD_ONCE_INIT;

static inline void cpu_relax(void)
{
#if defined(__x86_64__) || defined(__i386__)
    __builtin_ia32_pause();
#endif
}

static void futex_wait(atomic_uint *word, unsigned expected)
{
    syscall(SYS_futex, (unsigned *)word, FUTEX_WAIT_PRIVATE, expected, NULL, NULL, 0);
}

static void futex_wake(atomic_uint *word)
{
    syscall(SYS_futex, (unsigned *)word, FUTEX_WAKE_PRIVATE, INT32_MAX, NULL, NULL, 0);
}

/* Waits until *word differs from seen (spin, then sleep); returns it. */
static unsigned wait_change(atomic_uint *word, atomic_uint *sleeping, unsigned seen)
{
    unsigned v;
    for (int i = atomic_load_explicit(&spin_limit, memory_order_relaxed); i > 0; i--) {
        if ((v = atomic_load(word)) != seen)
            return v;
        cpu_relax();
    }
    for (;;) {
        atomic_store(sleeping, 1);
        if ((v = atomic_load(word)) != seen)
            break;
        futex_wait(word, seen);
        if ((v = atomic_load(word)) != seen)
            break;
    }
    atomic_store(sleeping, 0);
    return v;
}

/* After a change of *word: wakes its waiter if it sleeps. */
static void wake(atomic_uint *word, atomic_uint *sleeping)
{
    if (atomic_load(sleeping))
        futex_wake(word);
}

static void *pool_worker_main(void *p)
{
    slot *s = p;
    const unsigned id = (unsigned)(s - pool.slots);
    in_task = true;
    unsigned v = atomic_load(&s->state);
    for (;;) {
        if (PHASE(v) == STOP)
            return NULL;
        if (PHASE(v) == POSTED) {
            if (!atomic_compare_exchange_strong(&s->state, &v, GEN(v) | RUNNING))
                continue; /* revoked meanwhile, or already the next post: look at v again */
            run_chunks(pool.job, id);
            v = GEN(v) | IDLE;
            atomic_store(&s->state, v);
            atomic_fetch_add(&pool.finished, 1);
            wake(&pool.finished, &pool.caller_sleeping);
        }
        v = wait_change(&s->state, &s->sleeping, v);
    }
}

/* The child of a fork has only the forking thread: no workers, and no
 * loop holding the pool. */
static void forget_pool_in_child(void)
{
    memset(&pool, 0, sizeof pool);
}

static void register_atfork(void) { pthread_atfork(NULL, NULL, forget_pool_in_child); }

/* Starts workers up to `want` (holding the pool). Workers block every
 * signal: they live on, and signals are the process' other threads'
 * business (the daemon sigwaits for its stop signals). */
static void grow(unsigned want)
{
    if (want <= pool.workers)
        return;
    pthread_once(&atfork_once, register_atfork);
    sigset_t all, old;
    sigfillset(&all);
    pthread_sigmask(SIG_SETMASK, &all, &old);
    while (pool.workers < want) {
        slot *s = &pool.slots[pool.workers + 1];
        atomic_store(&s->state, GEN(pool.generation) | IDLE);
        atomic_store(&s->sleeping, 0);
        if (pthread_create(&s->tid, NULL, pool_worker_main, s) != 0)
            break; /* the workers we have (and the caller) do the work */
        pool.workers++;
    }
    pthread_sigmask(SIG_SETMASK, &old, NULL);
}

static bool take_pool(void)
{
    unsigned free_ = 0;
    return atomic_compare_exchange_strong(&pool.taken, &free_, 1);
}

static void run_on_pool(job_t *job, unsigned threads)
{
    grow(threads - 1);
    unsigned helpers = threads - 1 < pool.workers ? threads - 1 : pool.workers;
    pool.generation += 4;
    const unsigned posted = GEN(pool.generation) | POSTED;
    pool.job = job;
    atomic_store(&pool.finished, 0);
    for (unsigned i = 1; i <= helpers; i++) {
        atomic_store(&pool.slots[i].state, posted);
        wake(&pool.slots[i].state, &pool.slots[i].sleeping);
    }
    in_task = true;
    run_chunks(job, 0);
    in_task = false;
    /* every chunk is taken: revoke the posts no worker took yet */
    unsigned ran = 0;
    for (unsigned i = 1; i <= helpers; i++) {
        unsigned expected = posted;
        if (!atomic_compare_exchange_strong(&pool.slots[i].state, &expected, GEN(posted) | IDLE))
            ran++;
    }
    unsigned done;
    while ((done = atomic_load(&pool.finished)) != ran)
        wait_change(&pool.finished, &pool.caller_sleeping, done);
}

/* Asked once: sysconf reads /sys each time (8 us measured), and a loop
 * with threads = 0 asks on every call. */
unsigned mr_cpu_count(void)
{
    static atomic_uint known;
    unsigned n = atomic_load_explicit(&known, memory_order_relaxed);
    if (n)
        return n;
    long online = sysconf(_SC_NPROCESSORS_ONLN);
    n = online < 1 ? 1 : online > MR_MAX_THREADS ? MR_MAX_THREADS : (unsigned)online;
    atomic_store_explicit(&known, n, memory_order_relaxed);
    return n;
}

bool mr_parallel_nested(void) { return in_task; }

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
    if (in_task)
        threads = 1; /* nested: the outer loop has the threads */

    /* chunks [chunks * w / threads, chunks * (w + 1) / threads) are w's */
    range_t range[threads];
    for (unsigned w = 0; w < threads; w++) {
        atomic_init(&range[w].next, (size_t)((uint64_t)chunks * w / threads) * grain);
        const size_t end = (size_t)((uint64_t)chunks * (w + 1) / threads) * grain;
        range[w].end = end < count ? end : count;
    }
    job_t job = {.fn = fn, .ctx = ctx, .grain = grain, .ranges = threads, .range = range};
    if (threads <= 1) {
        run_chunks(&job, 0);
        return;
    }
    if (atomic_load_explicit(&use_pool, memory_order_relaxed) && take_pool()) {
        run_on_pool(&job, threads);
        atomic_store(&pool.taken, 0);
        return;
    }
    run_on_own_threads(&job, threads);
}

void mr_parallel_shutdown(void)
{
    if (in_task)
        return; /* the pool is (or may be) running this very loop */
    while (!take_pool())
        sched_yield();
    pool.generation += 4;
    for (unsigned i = 1; i <= pool.workers; i++) {
        atomic_store(&pool.slots[i].state, GEN(pool.generation) | STOP);
        futex_wake(&pool.slots[i].state);
    }
    for (unsigned i = 1; i <= pool.workers; i++)
        pthread_join(pool.slots[i].tid, NULL);
    pool.workers = 0;
    atomic_store(&pool.taken, 0);
}

void mr_parallel_use_pool(bool on) { atomic_store(&use_pool, on); }

unsigned mr_parallel_pool_workers(void) { return pool.workers; }

void mr_parallel_pool_spin(int iterations)
{
    atomic_store(&spin_limit, iterations < 0 ? MR_POOL_SPIN : iterations);
}
