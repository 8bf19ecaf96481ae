/*
 * film.h - the frame buffer (mr_film).
 *
 * All of it is public API and declared, with its documentation, in
 * microray.h; this header only forwards there so core code and the tests
 * can keep naming the module.
 */
#ifndef MR_FILM_H
#define MR_FILM_H

#include "microray.h"

#endif
