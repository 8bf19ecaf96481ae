/*
 * thread_block.h - a block of memory each thread has to itself, on the
 * heap, for caches too large for thread-local storage (which comes out of
 * every thread's stack, the HTTP server's too). A thread's block is made,
 * zeroed, on its first call and freed when the thread ends.
 *
 * One mr_thread_block per kind of block, and a thread-local pointer to
 * this thread's:
 *
 *     static mr_thread_block cells = MR_THREAD_BLOCK_INIT;
 *     static _Thread_local void *my_cells;
 *     cell_cache *c = mr_thread_block_get(&cells, &my_cells, sizeof *c);
 *
 * NULL when there is no memory (the next call tries again): the caller
 * then keeps nothing.
 */
#ifndef MR_THREAD_BLOCK_H
#define MR_THREAD_BLOCK_H

#include <pthread.h>
#include <stdatomic.h>
#include <stddef.h>

typedef struct mr_thread_block {
    pthread_mutex_t lock;
    _Atomic int state; /* 0: no key yet; 1: keyed; -1: no key to be had */
    pthread_key_t key;
} mr_thread_block;

#define MR_THREAD_BLOCK_INIT {PTHREAD_MUTEX_INITIALIZER, 0, 0}

/* mr_thread_block_get's first call in a thread. */
void *mr_thread_block_make(mr_thread_block *b, void **mine, size_t size);

/* This thread's block of `size` bytes (*mine, once made), or NULL. */
static inline void *mr_thread_block_get(mr_thread_block *b, void **mine, size_t size)
{
    return *mine ? *mine : mr_thread_block_make(b, mine, size);
}

#endif /* MR_THREAD_BLOCK_H */
