/*
 * bcn_fixture.h - the real skinned test character the dmm tests share:
 * Debian's assimp-testmodels BCN_Epileptic.X (5k triangles, 3 meshes, one
 * clip), as imported, or refined into a detailed mesh (core/asset/refine.h).
 * Include after <cmocka.h>; failures end the test with the library's message.
 */
#ifndef MR_TEST_BCN_FIXTURE_H
#define MR_TEST_BCN_FIXTURE_H

#include "asset/asset.h"
#include "asset/refine.h"

#define BCN_MODEL "/usr/share/assimp/models/X/BCN_Epileptic.X"

static inline mr_asset *bcn_load(void)
{
    mr_asset *a = NULL;
    mr_error err = {0};
    if (mr_asset_load(BCN_MODEL, &a, &err) != MR_OK)
        fail_msg("load %s: %s", BCN_MODEL, err.msg);
    return a;
}

/* The character refined with p (its surface detail made by refine.h). */
static inline mr_asset *bcn_load_refined(const mr_refine_params *p)
{
    mr_asset *a = bcn_load(), *r = NULL;
    mr_error err = {0};
    if (mr_refine_asset(a, p, &r, &err) != MR_OK)
        fail_msg("refine %s: %s", BCN_MODEL, err.msg);
    mr_asset_free(a);
    return r;
}

#endif /* MR_TEST_BCN_FIXTURE_H */
