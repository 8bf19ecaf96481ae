/*
 * clock.h - the monotonic clock (mr_now, mr_now_ms).
 *
 * All of it is public API and declared, with its documentation, in
 * microray.h; this header only forwards there so core code and the tests
 * can keep naming the module.
 */
#ifndef MR_CLOCK_H
#define MR_CLOCK_H

#include "microray.h"

#endif
