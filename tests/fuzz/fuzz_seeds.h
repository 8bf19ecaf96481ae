/*
 * fuzz_seeds.h - the `-seeds DIR` option of a harness that makes its own
 * seed inputs (docs/fuzzing.md): LLVMFuzzerInitialize hands its arguments
 * here, and with the option the harness writes its seeds into DIR and
 * exits instead of fuzzing. Header-only: each harness includes it once.
 */
#ifndef MR_FUZZ_SEEDS_H
#define MR_FUZZ_SEEDS_H

#include <stdlib.h>
#include <string.h>

static void fuzz_seeds_option(int argc, char **argv, void (*write_seeds)(const char *dir))
{
    for (int i = 1; i + 1 < argc; i++)
        if (!strcmp(argv[i], "-seeds")) {
            write_seeds(argv[i + 1]);
            exit(0);
        }
}

#endif /* MR_FUZZ_SEEDS_H */
