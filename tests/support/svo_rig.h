/*
 * svo_rig.h - deformers with their own storage for the svo deformation
 * tests (core/kinds/svo/deform.h): every mesh and joint matrix of an asset, set
 * by hand. Include after <cmocka.h>. (Skinned poses use deform.h's
 * mr_svo_skin, the svo kind's own.)
 */
#ifndef MR_TEST_SVO_RIG_H
#define MR_TEST_SVO_RIG_H

#include <stdlib.h>
#include <string.h>

#include "asset/asset.h"
#include "kinds/svo/deform.h"

static inline mr_affine affine_rows(float a, float b, float c, float d, float e, float f, float g,
                                    float h, float i, float j, float k, float l)
{
    return (mr_affine){{a, b, c, d, e, f, g, h, i, j, k, l}};
}

static inline mr_affine affine_identity(void) { return affine_rows(1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0); }

/* A deformer with storage: every mesh and joint matrix of an asset. */
typedef struct rig {
    mr_svo_deformer d;
    mr_affine *mesh;
    mr_affine **joint;
    uint32_t *joint_count;
} rig;

static inline void rig_alloc(rig *r, const mr_asset *a)
{
    memset(r, 0, sizeof *r);
    r->mesh = calloc(a->mesh_count, sizeof *r->mesh);
    r->joint = calloc(a->mesh_count, sizeof *r->joint);
    r->joint_count = calloc(a->mesh_count, sizeof *r->joint_count);
    assert_true(r->mesh && r->joint && r->joint_count);
    for (size_t m = 0; m < a->mesh_count; m++) {
        r->joint_count[m] = a->meshes[m].joint_count;
        if (r->joint_count[m]) {
            r->joint[m] = calloc(r->joint_count[m], sizeof **r->joint);
            assert_non_null(r->joint[m]);
        }
    }
    r->d.mesh_count = a->mesh_count;
    r->d.mesh = r->mesh;
    r->d.joint = (const mr_affine *const *)r->joint;
    r->d.joint_count = r->joint_count;
}

static inline void rig_free(rig *r)
{
    for (size_t m = 0; m < r->d.mesh_count; m++)
        free(r->joint[m]);
    free(r->joint);
    free(r->mesh);
    free(r->joint_count);
    memset(r, 0, sizeof *r);
}

/* Every matrix = M: the whole asset moved rigidly. */
static inline void rig_uniform(rig *r, const mr_asset *a, mr_affine M)
{
    rig_alloc(r, a);
    for (size_t m = 0; m < a->mesh_count; m++) {
        r->mesh[m] = M;
        for (uint32_t j = 0; j < r->joint_count[m]; j++)
            r->joint[m][j] = M;
    }
}

#endif /* MR_TEST_SVO_RIG_H */
