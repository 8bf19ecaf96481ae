/* thread_block.c - memory of one thread's own, on the heap (thread_block.h). */
#include "util/thread_block.h"

#include <stdlib.h>

void *mr_thread_block_make(mr_thread_block *b, void **mine, size_t size)
{
    int state = atomic_load_explicit(&b->state, memory_order_acquire);
    if (state == 0) {
        pthread_mutex_lock(&b->lock);
        state = atomic_load_explicit(&b->state, memory_order_relaxed);
        if (state == 0) {
            state = pthread_key_create(&b->key, free) == 0 ? 1 : -1;
            atomic_store_explicit(&b->state, state, memory_order_release);
        }
        pthread_mutex_unlock(&b->lock);
    }
    if (state < 0)
        return NULL;
    void *p = calloc(1, size);
    if (p && pthread_setspecific(b->key, p) != 0) {
        free(p);
        p = NULL;
    }
    return *mine = p;
}
