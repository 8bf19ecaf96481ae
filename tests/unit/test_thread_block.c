/*
 * test_thread_block.c - memory of one thread's own (util/thread_block.c):
 * a thread gets the same zeroed block on every call, another thread a
 * block of its own, and a thread's block goes when the thread ends (under
 * make check's LeakSanitizer a block left behind by the threads here is a
 * reported leak).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <pthread.h>
#include <stdbool.h>
#include <string.h>

#include "util/thread_block.h"

#define SIZE 4096

static mr_thread_block block = MR_THREAD_BLOCK_INIT;
static _Thread_local void *mine;

static unsigned char *take(void) { return mr_thread_block_get(&block, &mine, SIZE); }

static bool zeroed(const unsigned char *p)
{
    for (size_t k = 0; k < SIZE; k++)
        if (p[k])
            return false;
    return true;
}

/* A thread's look at its block: whether it came zeroed and stayed its own,
 * after writing its mark into it. */
typedef struct seen {
    unsigned char mark;
    unsigned char *block;
    bool was_zeroed, kept;
} seen;

static void *other_thread(void *arg)
{
    seen *s = arg;
    s->block = take();
    s->was_zeroed = s->block && zeroed(s->block);
    if (s->block)
        memset(s->block, s->mark, SIZE);
    s->kept = take() == s->block;
    return NULL;
}

static void test_same_block_each_call(void **state)
{
    (void)state;
    unsigned char *a = take();
    assert_non_null(a);
    assert_true(zeroed(a));
    a[0] = 7, a[SIZE - 1] = 9;
    unsigned char *b = take();
    assert_ptr_equal(a, b);
    assert_int_equal(b[0], 7);
    assert_int_equal(b[SIZE - 1], 9);
}

static void test_threads_apart(void **state)
{
    (void)state;
    unsigned char *main_block = take();
    assert_non_null(main_block);
    memset(main_block, 0x11, SIZE);
    seen s[4];
    pthread_t th[4];
    for (int k = 0; k < 4; k++) {
        s[k] = (seen){.mark = (unsigned char)(0x21 + k)};
        assert_int_equal(pthread_create(&th[k], NULL, other_thread, &s[k]), 0);
    }
    for (int k = 0; k < 4; k++)
        assert_int_equal(pthread_join(th[k], NULL), 0);
    for (int k = 0; k < 4; k++) {
        assert_non_null(s[k].block);
        assert_true(s[k].was_zeroed);
        assert_true(s[k].kept);
        assert_ptr_not_equal(s[k].block, main_block);
    }
    /* the others' marks went to their blocks, not this thread's */
    for (size_t k = 0; k < SIZE; k++)
        assert_int_equal(main_block[k], 0x11);
}

/* Threads that end one after another: each gets a fresh zeroed block
 * (the last one's was freed with it, and whatever memory comes back is
 * zeroed again), many times over. */
static void test_block_per_thread_life(void **state)
{
    (void)state;
    for (int k = 0; k < 64; k++) {
        seen s = {.mark = 0x5a};
        pthread_t th;
        assert_int_equal(pthread_create(&th, NULL, other_thread, &s), 0);
        assert_int_equal(pthread_join(th, NULL), 0);
        assert_non_null(s.block);
        assert_true(s.was_zeroed);
        assert_true(s.kept);
    }
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_same_block_each_call),
        cmocka_unit_test(test_threads_apart),
        cmocka_unit_test(test_block_per_thread_life),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
