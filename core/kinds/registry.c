/*
 * registry.c - the geometry kinds a job may name (kind.h).
 *
 * Adding a kind is one line in BUILTIN (its descriptor, declared in its own
 * folder's header). Order matters only for messages and the generated
 * schema: "one of: \"mesh\", \"dmm\", \"svo\", ...".
 */
#include "kinds/kind.h"

#include "render/frame_stats.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "kinds/displaced/displaced_kind.h"
#include "kinds/dmm/dmm_kind.h"
#include "kinds/mesh/mesh_kind.h"
#include "kinds/springmass/springmass_kind.h"
#include "kinds/svo/svo_kind.h"

static const mr_kind *const BUILTIN[] = {
    &mr_kind_mesh,
    &mr_kind_dmm,
    &mr_kind_svo,
    &mr_kind_displaced,
    &mr_kind_springmass,
};

#define BUILTIN_COUNT (sizeof BUILTIN / sizeof BUILTIN[0])
#define MAX_ADDED 16

static const mr_kind *added[MAX_ADDED];
static size_t added_count;

size_t mr_kind_count(void) { return BUILTIN_COUNT + added_count; }

const mr_kind *mr_kind_triangles(void) { return &mr_kind_mesh; }

const mr_kind *mr_kind_at(size_t i)
{
    if (i < BUILTIN_COUNT)
        return BUILTIN[i];
    i -= BUILTIN_COUNT;
    return i < added_count ? added[i] : NULL;
}

const mr_kind *mr_kind_find(const char *name)
{
    for (size_t i = 0; name && i < mr_kind_count(); i++)
        if (strcmp(mr_kind_at(i)->name, name) == 0)
            return mr_kind_at(i);
    return NULL;
}

int mr_kind_register(const mr_kind *kind, mr_error *err)
{
    if (!kind || !kind->name || !kind->name[0] || !kind->create || !kind->free)
        return mr_error_set(err, MR_ERR_INVALID, "a kind needs a name, create and free");
    if (mr_kind_find(kind->name))
        return mr_error_set(err, MR_ERR_CONFLICT, "a kind named \"%s\" is already registered",
                            kind->name);
    if (kind->params && kind->params->count > MR_PARAM_MAX_FIELDS)
        return mr_error_set(err, MR_ERR_LIMIT, "kind \"%s\": at most %u parameters", kind->name,
                            MR_PARAM_MAX_FIELDS);
    if (kind->stat_count && !kind->frame_stats)
        return mr_error_set(err, MR_ERR_INVALID, "kind \"%s\": stats fields need frame_stats",
                            kind->name);
    if (kind->frame_order == MR_FRAMES_SEQUENTIAL && !kind->rewind)
        return mr_error_set(err, MR_ERR_INVALID, "kind \"%s\": a sequential kind needs rewind",
                            kind->name);
    bool any = kind->checkpoint_every || kind->checkpoint_id || kind->checkpoint_save ||
               kind->checkpoint_load,
         all = kind->checkpoint_every && kind->checkpoint_id && kind->checkpoint_save &&
               kind->checkpoint_load;
    if (any && (!all || kind->frame_order != MR_FRAMES_SEQUENTIAL))
        return mr_error_set(err, MR_ERR_INVALID,
                            "kind \"%s\": checkpoints need all four ops and a sequential kind",
                            kind->name);
    /* a job may hold every kind: all their fields fit one frame's extras */
    size_t fields = kind->stat_count;
    for (size_t i = 0; i < mr_kind_count(); i++)
        fields += mr_kind_at(i)->stat_count;
    if (fields + MR_FRAME_EXTRAS_CALLER > MR_FRAME_EXTRAS_MAX)
        return mr_error_set(err, MR_ERR_LIMIT,
                            "kind \"%s\": its %zu stats fields would bring the registered kinds' "
                            "to %zu, more than the %d a frame carries besides the caller's %d",
                            kind->name, kind->stat_count, fields,
                            MR_FRAME_EXTRAS_MAX - MR_FRAME_EXTRAS_CALLER, MR_FRAME_EXTRAS_CALLER);
    if (added_count == MAX_ADDED)
        return mr_error_set(err, MR_ERR_LIMIT, "at most %d kinds can be added", MAX_ADDED);
    added[added_count++] = kind;
    return MR_OK;
}

int mr_kind_cache_dir(const mr_kind *kind, const char *root, char **out, mr_error *err)
{
    *out = NULL;
    if (!kind->has_derived || !root || !root[0])
        return MR_OK;
    size_t n = strlen(root) + 1 + strlen(kind->name) + 1;
    if (!(*out = malloc(n)))
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    snprintf(*out, n, "%s/%s", root, kind->name);
    return MR_OK;
}
