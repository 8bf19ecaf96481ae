/*
 * renderer.h - renders the frames of one job (mr_renderer).
 *
 * All of it is public API and declared, with its documentation, in
 * microray.h; this header only forwards there so core code and the tests
 * can keep naming the module.
 */
#ifndef MR_RENDERER_H
#define MR_RENDERER_H

#include "microray.h"

#endif
