/*
 * compare.h - error metrics between two frames (mr_film_compare).
 *
 * All of it is public API and declared, with its documentation, in
 * microray.h; this header only forwards there so core code and the tests
 * can keep naming the module.
 */
#ifndef MR_COMPARE_H
#define MR_COMPARE_H

#include "microray.h"

#endif
