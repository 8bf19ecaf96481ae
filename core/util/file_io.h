/*
 * file_io.h - capped reads, atomic writes, mkdir -p, removal (mr_fs_*).
 *
 * All of it is public API and declared, with its documentation, in
 * microray.h; this header only forwards there so core code and the tests
 * can keep naming the module.
 */
#ifndef MR_FILE_IO_H
#define MR_FILE_IO_H

#include "microray.h"

#endif
