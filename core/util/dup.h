/*
 * dup.h - malloc'ed copies (mr_strdup, mr_memdup, mr_memdup_str).
 *
 * All of it is public API and declared, with its documentation, in
 * microray.h; this header only forwards there so core code and the tests
 * can keep naming the module.
 */
#ifndef MR_DUP_H
#define MR_DUP_H

#include "microray.h"

#endif
