/*
 * test_parallel.c - mr_parallel_for on its pool of workers (util/parallel.c):
 *  - a helper starts at the front of its own contiguous share of the
 *    items;
 *  - every item is handed out exactly once and a worker index is never
 *    used by two threads at the same time, for 1..17 threads, over many
 *    back-to-back calls (the pool's workers spinning) and calls with gaps
 *    (the workers asleep, spin 0), so a post revoked by a caller that ran
 *    out of chunks first is exercised too;
 *  - a call from inside a task runs serially on the calling thread, as
 *    worker 0, and finishes (no deadlock on the pool);
 *  - two threads calling at once both get their results (one on the pool,
 *    the other on threads of its own);
 *  - shutdown joins the workers and a later call starts them again; a
 *    shutdown from inside a task does nothing;
 *  - a forked child calls on a pool of its own (the parent's workers do
 *    not exist there) and the parent's pool still works afterwards;
 *  - mr_parallel_use_pool(false) gives the same results on threads started
 *    per call.
 * A deadlock would hang the program: alarm() ends it after 5 minutes (a
 * guard for CI, not a timing assertion: the whole program takes about a
 * second).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <pthread.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>
#include <unistd.h>

#include "util/parallel.h"

#define ITEMS 10000

typedef struct count_ctx {
    atomic_uint hits[ITEMS];
    atomic_uint busy[MR_MAX_THREADS]; /* worker index in use right now */
    atomic_uint overlap;              /* a worker index used twice at once */
    atomic_uint bad_worker;           /* an index >= threads */
    unsigned threads;
} count_ctx;

static void count_items(void *ctx, size_t begin, size_t end, unsigned worker)
{
    count_ctx *c = ctx;
    if (worker >= c->threads) {
        atomic_fetch_add(&c->bad_worker, 1);
        return;
    }
    if (atomic_exchange(&c->busy[worker], 1) != 0)
        atomic_fetch_add(&c->overlap, 1);
    for (size_t i = begin; i < end; i++)
        atomic_fetch_add(&c->hits[i], 1);
    atomic_store(&c->busy[worker], 0);
}

/* One call over `count` items; true when every item was hit once and the
 * worker indices behaved. */
static bool run_once(count_ctx *c, unsigned threads, size_t count, size_t grain)
{
    memset(c, 0, sizeof *c);
    c->threads = threads ? threads : mr_cpu_count();
    mr_parallel_for(threads, count, grain, count_items, c);
    bool ok = atomic_load(&c->overlap) == 0 && atomic_load(&c->bad_worker) == 0;
    for (size_t i = 0; i < ITEMS; i++)
        ok = ok && atomic_load(&c->hits[i]) == (i < count ? 1u : 0u);
    return ok;
}

static void test_thread_counts(void **state)
{
    (void)state;
    count_ctx *c = malloc(sizeof *c);
    assert_non_null(c);
    for (unsigned threads = 0; threads <= 17; threads++) {
        assert_true(run_once(c, threads, ITEMS, 7));
        assert_true(run_once(c, threads, ITEMS, 1));
        assert_true(run_once(c, threads, 3, 1));     /* fewer chunks than threads */
        assert_true(run_once(c, threads, ITEMS, ITEMS + 5)); /* one chunk */
    }
    mr_parallel_for(4, 0, 1, count_items, c); /* nothing to do: fn never called */
    /* the pool grew to the most threads asked for, less the caller */
    assert_int_equal(mr_parallel_pool_workers(), 16);
    free(c);
}

static void test_many_calls(void **state)
{
    (void)state;
    count_ctx *c = malloc(sizeof *c);
    assert_non_null(c);
    for (int spin = 1; spin >= 0; spin--) {
        mr_parallel_pool_spin(spin ? -1 : 0);
        for (int i = 0; i < 3000; i++) {
            unsigned threads = 2 + (unsigned)(i % 3);
            size_t count = (size_t)(1 + (i * 37) % 500);
            if (!run_once(c, threads, count, 1 + (size_t)(i % 4)))
                fail_msg("call %d (spin %d, %u threads, %zu items) went wrong", i, spin, threads, count);
            if (!spin && i % 100 == 0)
                usleep(2000); /* the workers fall asleep */
        }
    }
    mr_parallel_pool_spin(-1);
    free(c);
}

/* ---- each worker's own share first ---- */

#define SHARE_ITEMS 12
#define HELPER_FRONT (SHARE_ITEMS / 2) /* the first item of the helper's share, on two threads */

typedef struct share_ctx {
    atomic_int first[2];   /* the first item each worker ran, -1: none */
    atomic_uint started[SHARE_ITEMS];
    atomic_uint waited_ok; /* item 0 saw the helper's front start */
} share_ctx;

static void share_item(void *ctx, size_t begin, size_t end, unsigned worker)
{
    share_ctx *c = ctx;
    int none = -1;
    atomic_compare_exchange_strong(&c->first[worker], &none, (int)begin);
    for (size_t i = begin; i < end; i++)
        atomic_store(&c->started[i], 1);
    if (begin != 0)
        return;
    /* item 0, worker 0's front, holds whoever runs it until the helper's
     * front has started, for at most a second: worker 0 cannot take that
     * front before it (its own share comes first) nor while holding it */
    for (int tick = 0; tick < 1000; tick++) {
        if (atomic_load(&c->started[HELPER_FRONT])) {
            atomic_store(&c->waited_ok, 1);
            return;
        }
        usleep(1000);
    }
}

/* On two threads the helper starts at the front of its own share, chunks
 * [n / 2, n): with one counter for all, as before, it would start at item
 * 0 or 1. Two threads only: with more, a helper that wakes late may find
 * its front taken by another helper, and start elsewhere. A helper that
 * has not woken within a second of its post (a loaded machine) gets
 * another try; ten in a row would mean a broken pool. */
static void test_own_share_first(void **state)
{
    (void)state;
    share_ctx c;
    bool done = false;
    for (int attempt = 0; attempt < 10 && !done; attempt++) {
        memset(&c, 0, sizeof c);
        atomic_init(&c.first[0], -1);
        atomic_init(&c.first[1], -1);
        mr_parallel_for(2, SHARE_ITEMS, 1, share_item, &c);
        for (unsigned i = 0; i < SHARE_ITEMS; i++)
            assert_int_equal(atomic_load(&c.started[i]), 1);
        done = atomic_load(&c.waited_ok);
    }
    assert_true(done);
    /* item 0 was held until the helper's front had started; worker 0, the
     * only other thread, was either holding it or had not started (the
     * helper, awake first, may run worker 0's share once its own is
     * done): the helper took its front, first */
    assert_int_equal(atomic_load(&c.first[1]), HELPER_FRONT);
}

/* ---- nested calls ---- */

typedef struct nest_ctx {
    atomic_uint inner_items, inner_elsewhere, inner_not_worker0, outer_items;
} nest_ctx;

typedef struct inner_ctx {
    nest_ctx *n;
    pthread_t caller;
} inner_ctx;

static void inner(void *ctx, size_t begin, size_t end, unsigned worker)
{
    inner_ctx *x = ctx;
    if (!pthread_equal(pthread_self(), x->caller))
        atomic_fetch_add(&x->n->inner_elsewhere, 1);
    if (worker != 0)
        atomic_fetch_add(&x->n->inner_not_worker0, 1);
    atomic_fetch_add(&x->n->inner_items, (unsigned)(end - begin));
}

static void outer(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    nest_ctx *n = ctx;
    for (size_t i = begin; i < end; i++) {
        inner_ctx x = {n, pthread_self()};
        mr_parallel_for(4, 100, 1, inner, &x);
        mr_parallel_shutdown(); /* inside a task: does nothing */
        atomic_fetch_add(&n->outer_items, 1);
    }
}

static void test_nested(void **state)
{
    (void)state;
    for (unsigned threads = 1; threads <= 4; threads++) {
        nest_ctx n = {0};
        mr_parallel_for(threads, 64, 1, outer, &n);
        assert_int_equal(atomic_load(&n.outer_items), 64);
        assert_int_equal(atomic_load(&n.inner_items), 64 * 100);
        if (threads > 1) { /* serial inside a loop on several threads */
            assert_int_equal(atomic_load(&n.inner_elsewhere), 0);
            assert_int_equal(atomic_load(&n.inner_not_worker0), 0);
        }
    }
    /* the same inner loop from outside any task may use the pool */
    nest_ctx n = {0};
    outer(&n, 0, 3, 0);
    assert_int_equal(atomic_load(&n.inner_items), 300);
}

/* ---- two callers at once ---- */

static void *caller_main(void *p)
{
    (void)p;
    count_ctx *c = malloc(sizeof *c);
    if (!c)
        return (void *)1;
    uintptr_t failures = 0;
    for (int i = 0; i < 1500; i++)
        failures += !run_once(c, 2 + (unsigned)(i % 2), (size_t)(50 + i % 300), 1);
    free(c);
    return (void *)failures;
}

static void test_two_callers(void **state)
{
    (void)state;
    pthread_t t[2];
    for (int i = 0; i < 2; i++)
        assert_int_equal(pthread_create(&t[i], NULL, caller_main, NULL), 0);
    for (int i = 0; i < 2; i++) {
        void *failures = (void *)1;
        pthread_join(t[i], &failures);
        assert_int_equal((uintptr_t)failures, 0);
    }
}

static void test_shutdown_restart(void **state)
{
    (void)state;
    count_ctx *c = malloc(sizeof *c);
    assert_non_null(c);
    assert_true(run_once(c, 3, ITEMS, 16));
    assert_true(mr_parallel_pool_workers() >= 2);
    mr_parallel_shutdown();
    assert_int_equal(mr_parallel_pool_workers(), 0);
    mr_parallel_shutdown(); /* twice is fine */
    assert_true(run_once(c, 3, ITEMS, 16));
    assert_int_equal(mr_parallel_pool_workers(), 2);
    mr_parallel_use_pool(false);
    mr_parallel_shutdown();
    for (unsigned threads = 1; threads <= 5; threads++)
        assert_true(run_once(c, threads, ITEMS, 3));
    assert_int_equal(mr_parallel_pool_workers(), 0); /* none started */
    mr_parallel_use_pool(true);
    free(c);
}

static void test_fork(void **state)
{
    (void)state;
    count_ctx *c = malloc(sizeof *c);
    assert_non_null(c);
    assert_true(run_once(c, 3, ITEMS, 4));
    assert_true(mr_parallel_pool_workers() >= 2);
    fflush(NULL);
    pid_t pid = fork();
    assert_true(pid >= 0);
    if (pid == 0) {
        /* the parent's workers are gone here: a pool of our own */
        int bad = mr_parallel_pool_workers() != 0;
        for (int i = 0; i < 200; i++)
            bad += !run_once(c, 3, ITEMS, 64);
        bad += mr_parallel_pool_workers() != 2;
        _exit(bad ? 1 : 0);
    }
    int status = 0;
    assert_int_equal(waitpid(pid, &status, 0), pid);
    assert_true(WIFEXITED(status));
    assert_int_equal(WEXITSTATUS(status), 0);
    assert_true(run_once(c, 3, ITEMS, 4)); /* the parent's pool goes on */
    free(c);
}

int main(void)
{
    alarm(300); /* deadlock guard (see the head of the file) */
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_thread_counts),  cmocka_unit_test(test_many_calls),
        cmocka_unit_test(test_own_share_first),
        cmocka_unit_test(test_nested),         cmocka_unit_test(test_two_callers),
        cmocka_unit_test(test_shutdown_restart), cmocka_unit_test(test_fork),
    };
    int rc = cmocka_run_group_tests(tests, NULL, NULL);
    mr_parallel_shutdown();
    return rc;
}
