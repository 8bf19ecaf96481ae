/*
 * job.h - a render job as plain C structs (mr_job).
 *
 * All of it is public API and declared, with its documentation, in
 * microray.h; this header only forwards there so core code and the tests
 * can keep naming the module.
 */
#ifndef MR_JOB_H
#define MR_JOB_H

#include "microray.h"

#endif
