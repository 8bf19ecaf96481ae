/* geom.c - the geometry kind table (geom.h). */
#include "geom/geom.h"

#include <stdlib.h>

const mr_geom_ops *mr_geom_kind_ops(mr_geom_kind kind)
{
    switch (kind) {
    case MR_GEOM_MESH: return &mr_geom_mesh_ops;
    case MR_GEOM_DMM: return &mr_geom_dmm_ops;
    }
    return NULL;
}

void mr_trimesh_free(mr_trimesh *m)
{
    if (!m)
        return;
    free(m->positions);
    free(m->indices);
    *m = (mr_trimesh){0};
}
