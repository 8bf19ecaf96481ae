/*
 * hex.h - lowercase hexadecimal (mr_hex_encode, mr_hex_is_lower).
 *
 * All of it is public API and declared, with its documentation, in
 * microray.h; this header only forwards there so core code and the tests
 * can keep naming the module.
 */
#ifndef MR_HEX_H
#define MR_HEX_H

#include "microray.h"

#endif
