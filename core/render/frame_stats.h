/*
 * frame_stats.h - a frame's statistics and their field table.
 *
 * All of it is public API and declared, with its documentation, in
 * microray.h; this header only forwards there so core code and the tests
 * can keep naming the module.
 */
#ifndef MR_FRAME_STATS_H
#define MR_FRAME_STATS_H

#include "microray.h"

#endif
