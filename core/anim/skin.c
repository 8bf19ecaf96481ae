/*
 * skin.c - linear blend skinning and rigid placement of one mesh (pose.h).
 *
 * Per joint j the skin matrix is K_j = object * global(joint_j) *
 * inverse_bind_j (computed once per call). Per vertex the weighted sum
 * B = sum_i w_i K_{j_i} moves the position, and the cofactor of B (via
 * mr_mat4_normal_matrix) moves the normal, which is then renormalised; a
 * tangent (a direction in the surface) moves by B itself and is made
 * orthogonal to the moved normal again (mr_v3_tangent_to). A
 * vertex without influences, and every vertex of a rigid mesh, uses
 * object * global(mesh node).
 *
 * Determinism: each vertex is computed from its own inputs only, with the
 * same operations in the same order whichever worker runs it, so the output
 * is bit-identical for any thread count.
 */
#include "anim/pose.h"
#include "util/parallel.h"

#include <stdlib.h>
#include <string.h>

#define SKIN_GRAIN 4096

typedef struct skin_ctx {
    const mr_asset *asset;
    const mr_mesh *mesh;
    const mr_pose *pose;
    mr_mat4 object;
    mr_mat4 rigid;        /* object * global(mesh node) */
    mr_mat4 rigid_normal; /* its cofactor */
    bool skinned;         /* joint arrays present and usable */
    const mr_mat4 *skin;  /* K_j per joint; NULL: computed per use (allocation failed) */
    float *out_p, *out_n, *out_t;
    mr_affine *out_m;
    const uint32_t *subset; /* NULL: every vertex; else item k is vertex subset[k] */
} skin_ctx;

static mr_mat4 node_global(const skin_ctx *c, int node)
{
    if (node < 0 || (size_t)node >= c->pose->node_count)
        return mr_mat4_identity();
    return c->pose->global[node];
}

static mr_mat4 joint_matrix(const skin_ctx *c, uint32_t j)
{
    /* Same operations as the precomputed path, so results match bit for bit. */
    mr_mat4 g = node_global(c, c->mesh->joint_nodes[j]);
    mr_mat4 gb = mr_mat4_mul(&g, &c->mesh->inverse_bind[j]);
    return mr_mat4_mul(&c->object, &gb);
}

static void put(float *dst, size_t i, mr_vec3 v)
{
    dst[i * 3] = v.x;
    dst[i * 3 + 1] = v.y;
    dst[i * 3 + 2] = v.z;
}

static void skin_range(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    const skin_ctx *c = ctx;
    const mr_mesh *m = c->mesh;
    for (size_t item = begin; item < end; item++) {
        size_t i = c->subset ? c->subset[item] : item;
        mr_vec3 p = mr_v3(m->positions[i * 3], m->positions[i * 3 + 1], m->positions[i * 3 + 2]);
        mr_vec3 n = mr_v3(m->normals[i * 3], m->normals[i * 3 + 1], m->normals[i * 3 + 2]);
        const mr_mat4 *M = &c->rigid;
        const mr_mat4 *N = &c->rigid_normal;
        mr_mat4 blend, blend_n;
        if (c->skinned) {
            const uint16_t *js = &m->joints[i * MR_MAX_INFLUENCES];
            const float *ws = &m->weights[i * MR_MAX_INFLUENCES];
            bool any = false;
            memset(&blend, 0, sizeof blend);
            for (int k = 0; k < MR_MAX_INFLUENCES; k++) {
                float w = ws[k];
                if (!(w != 0.0f) || !isfinite(w) || js[k] >= m->joint_count)
                    continue;
                mr_mat4 tmp;
                const mr_mat4 *K = c->skin ? &c->skin[js[k]] : (tmp = joint_matrix(c, js[k]), &tmp);
                /* Only the top 3 rows matter for points and directions. */
                for (int e = 0; e < 12; e++)
                    blend.m[e] += w * K->m[e];
                any = true;
            }
            if (any) {
                blend.m[15] = 1.0f;
                blend_n = mr_mat4_normal_matrix(&blend);
                M = &blend;
                N = &blend_n;
            }
        }
        if (c->out_m)
            memcpy(c->out_m[i].m, M->m, sizeof c->out_m[i].m);
        if (c->out_p)
            put(c->out_p, i, mr_mat4_point(M, p));
        if (c->out_n || c->out_t) {
            /* the bind normal (normalised) where the moved one collapses:
             * made only then */
            const mr_vec3 nan3 = mr_v3(NAN, NAN, NAN);
            mr_vec3 moved = mr_v3_normalize_or(mr_mat4_dir(N, n), nan3);
            if (isnan(moved.x))
                moved = mr_v3_normalize_or(n, mr_v3(0, 0, 1));
            if (c->out_n)
                put(c->out_n, i, moved);
            if (c->out_t) {
                const float *t = &m->tangents[i * 4];
                put(c->out_t, i, mr_v3_tangent_to(mr_mat4_dir(M, mr_v3(t[0], t[1], t[2])), moved, true));
            }
        }
    }
}

static void skin(const mr_asset *asset, size_t mesh_index, const mr_pose *pose,
                 const mr_mat4 *object_transform, const uint32_t *subset, size_t subset_count,
                 float *out_positions, float *out_normals, float *out_tangents,
                 mr_affine *out_matrices, unsigned threads)
{
    if (!asset || mesh_index >= asset->mesh_count)
        return;
    const mr_mesh *m = &asset->meshes[mesh_index];
    if (m->vertex_count == 0 || !m->positions || !m->normals)
        return;
    size_t items = subset ? subset_count : m->vertex_count;
    skin_ctx c = {.asset = asset, .mesh = m, .pose = pose, .out_p = out_positions,
                  .out_n = out_normals, .out_t = m->tangents ? out_tangents : NULL,
                  .out_m = out_matrices, .subset = subset};
    c.object = object_transform ? *object_transform : mr_mat4_identity();
    mr_mat4 *mats = NULL;
    if (!pose || pose->node_count != asset->node_count || !pose->global) {
        /* No usable pose: place the mesh as it is in mesh space (plus the
         * object transform) rather than leaving the buffers undefined. */
        c.rigid = c.object;
        c.rigid_normal = mr_mat4_normal_matrix(&c.rigid);
        mr_parallel_for(threads, items, SKIN_GRAIN, skin_range, &c);
        return;
    }
    mr_mat4 g = node_global(&c, m->node);
    c.rigid = mr_mat4_mul(&c.object, &g);
    c.rigid_normal = mr_mat4_normal_matrix(&c.rigid);
    c.skinned = m->joint_count > 0 && m->joint_nodes && m->inverse_bind && m->joints &&
                m->weights;
    if (c.skinned) {
        mats = malloc(m->joint_count * sizeof *mats);
        if (mats)
            for (uint32_t j = 0; j < m->joint_count; j++)
                mats[j] = joint_matrix(&c, j);
        c.skin = mats;
    }
    mr_parallel_for(threads, items, SKIN_GRAIN, skin_range, &c);
    free(mats);
}

void mr_skin_mesh(const mr_asset *asset, size_t mesh_index, const mr_pose *pose,
                  const mr_mat4 *object_transform, float *out_positions,
                  float *out_normals, unsigned threads)
{
    if (out_positions)
        skin(asset, mesh_index, pose, object_transform, NULL, 0, out_positions, out_normals, NULL,
             NULL, threads);
}

void mr_skin_mesh_tangents(const mr_asset *asset, size_t mesh_index, const mr_pose *pose,
                           const mr_mat4 *object_transform, float *out_positions,
                           float *out_normals, float *out_tangents, unsigned threads)
{
    if (out_positions)
        skin(asset, mesh_index, pose, object_transform, NULL, 0, out_positions, out_normals,
             out_tangents, NULL, threads);
}

void mr_skin_mesh_vertices(const mr_asset *asset, size_t mesh_index, const mr_pose *pose,
                           const mr_mat4 *object_transform, const uint32_t *vertices, size_t count,
                           float *out_positions, float *out_normals, float *out_tangents,
                           unsigned threads)
{
    if (out_positions && vertices)
        skin(asset, mesh_index, pose, object_transform, vertices, count, out_positions,
             out_normals, out_tangents, NULL, threads);
}

void mr_skin_matrices(const mr_asset *asset, size_t mesh_index, const mr_pose *pose,
                      const mr_mat4 *object_transform, mr_affine *out_matrices, unsigned threads)
{
    if (out_matrices)
        skin(asset, mesh_index, pose, object_transform, NULL, 0, NULL, NULL, NULL, out_matrices,
             threads);
}
