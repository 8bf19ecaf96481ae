/*
 * params.h - a geometry kind's job parameters as a table (mr_param_table).
 *
 * All of it is public API and declared, with its documentation, in
 * microray.h; this header only forwards there so core code and the tests
 * can keep naming the module.
 */
#ifndef MR_PARAMS_H
#define MR_PARAMS_H

#include "microray.h"

#endif
