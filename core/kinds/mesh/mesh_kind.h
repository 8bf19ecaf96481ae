/* mesh_kind.h - the triangle mesh kind ("kind": "mesh", the default): every
 * mesh of an asset, skinned or rigid, as one Embree triangle geometry. It
 * takes no parameters and keeps no derived data. */
#ifndef MR_MESH_KIND_H
#define MR_MESH_KIND_H

#include "kinds/kind.h"

extern const mr_kind mr_kind_mesh;

#endif
