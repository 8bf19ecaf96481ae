/*
 * stats_openapi.c - the frame-stats schemas of schemas/openapi.yaml from
 * the field table and the registered kinds' own stats fields
 * (stats_openapi.h). YAML is written by hand in the
 * document's own style: one flow mapping per field, groups as nested
 * objects (the "seconds" group as the Seconds component it has always
 * been, since the job's totals and medians refer to it too).
 */
#include "stats_openapi.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "files.h"
#include "microray.h"

#define DOC_MAX_BYTES (4u << 20)

/* A YAML double-quoted scalar. */
static void put_quoted(FILE *f, const char *s)
{
    fputc('"', f);
    for (; *s; s++) {
        if (*s == '"' || *s == '\\')
            fputc('\\', f);
        fputc(*s, f);
    }
    fputc('"', f);
}

static void put_field(FILE *f, const mr_stat_field *fd, int indent)
{
    fprintf(f, "%*s%s: { ", indent, "", fd->name);
    switch (fd->type) {
    case MR_STAT_INT:
    case MR_STAT_U32:
    case MR_STAT_U64: fputs("type: integer, minimum: 0", f); break;
    case MR_STAT_F32:
    case MR_STAT_F64: fputs("type: number", f); break;
    case MR_STAT_BVH:
        fprintf(f, "type: string, enum: [%s, %s, %s]", mr_bvh_update_name(MR_BVH_NONE),
                mr_bvh_update_name(MR_BVH_BUILD), mr_bvh_update_name(MR_BVH_REFIT));
        break;
    case MR_STAT_FRAME_FILE: fputs("type: string", f); break;
    case MR_STAT_CACHE_RESULT: fputs("type: string, enum: [hit, partial, miss]", f); break;
    case MR_STAT_REFERENCE:
        fputs("type: string, enum: [", f);
        for (int t = 0; t < MR_REFERENCE_TYPES; t++)
            fprintf(f, "%s%s", t ? ", " : "", mr_reference_name(t));
        fputc(']', f);
        break;
    }
    char text[512];
    snprintf(text, sizeof text, "%s%s%s%s", fd->description, fd->unit[0] ? " Unit: " : "", fd->unit,
             fd->unit[0] ? "." : "");
    fputs(", description: ", f);
    put_quoted(f, text);
    fputs(" }\n", f);
}

/* "required: [a, b, ...]" of the members of group (NULL: the frame object,
 * whose groups count as members unless optional). */
static void put_required(FILE *f, const mr_stat_group *group, int indent)
{
    fprintf(f, "%*srequired: [", indent, "");
    const char *sep = "";
    const mr_stat_group *last = NULL;
    for (size_t i = 0; i < mr_frame_stat_field_count; i++) {
        const mr_stat_field *fd = &mr_frame_stat_fields[i];
        const char *name = NULL;
        if (fd->group == group && !(fd->flags & MR_STAT_OPTIONAL))
            name = fd->name;
        else if (!group && fd->group != last && !fd->group->optional)
            name = fd->group->name;
        last = fd->group;
        if (name) {
            fprintf(f, "%s%s", sep, name);
            sep = ", ";
        }
    }
    fputs("]\n", f);
}

static void put_group_header(FILE *f, const mr_stat_group *g, int indent)
{
    fprintf(f, "%*stype: object\n%*sdescription: ", indent, "", indent, "");
    put_quoted(f, g->description);
    fputc('\n', f);
    put_required(f, g, indent);
    fprintf(f, "%*sproperties:\n", indent, "");
}

static void put_group_fields(FILE *f, const mr_stat_group *g, int indent)
{
    for (size_t i = 0; i < mr_frame_stat_field_count; i++)
        if (mr_frame_stat_fields[i].group == g)
            put_field(f, &mr_frame_stat_fields[i], indent);
}

/* FrameError (an entry of a frame's "error") and JobErrors (the job's
 * "error": medians and worst frames per reference), from the error-entry
 * table. */
static void put_error_schemas(FILE *f)
{
    fputs("\n    FrameError:\n"
          "      type: object\n"
          "      description: \"A frame against one reference frame of the same camera "
          "(mr_film_compare; README, Error metrics).\"\n"
          "      required: [",
          f);
    for (size_t i = 0; i < mr_frame_error_field_count; i++)
        fprintf(f, "%s%s", i ? ", " : "", mr_frame_error_fields[i].name);
    fputs("]\n      additionalProperties: false\n      properties:\n", f);
    for (size_t i = 0; i < mr_frame_error_field_count; i++)
        put_field(f, &mr_frame_error_fields[i], 8);

    fputs("\n    ErrorFigures:\n"
          "      type: object\n"
          "      description: \"One number per figure of FrameError (its reference aside).\"\n"
          "      required: [",
          f);
    const char *sep = "";
    for (size_t i = 0; i < mr_frame_error_field_count; i++)
        if (mr_frame_error_fields[i].type != MR_STAT_REFERENCE) {
            fprintf(f, "%s%s", sep, mr_frame_error_fields[i].name);
            sep = ", ";
        }
    fputs("]\n      additionalProperties: false\n      properties:\n", f);
    for (size_t i = 0; i < mr_frame_error_field_count; i++)
        if (mr_frame_error_fields[i].type != MR_STAT_REFERENCE)
            fprintf(f, "        %s: { type: number }\n", mr_frame_error_fields[i].name);

    fputs("\n    WorstFrames:\n"
          "      type: object\n"
          "      description: \"Per figure of FrameError, the worst frame (the first of equals) "
          "and its value: the highest, the lowest for psnr_rgb_db.\"\n"
          "      additionalProperties: false\n      properties:\n",
          f);
    for (size_t i = 0; i < mr_frame_error_field_count; i++)
        if (mr_frame_error_fields[i].type != MR_STAT_REFERENCE)
            fprintf(f, "        %s: { $ref: \"#/components/schemas/WorstFrame\" }\n",
                    mr_frame_error_fields[i].name);
    fputs("\n    WorstFrame:\n"
          "      type: object\n"
          "      required: [frame, value]\n"
          "      additionalProperties: false\n"
          "      properties:\n"
          "        frame: { type: integer, minimum: 0 }\n"
          "        value: { type: number }\n",
          f);

    fputs("\n    JobErrors:\n"
          "      type: object\n"
          "      description: \"Per reference the job's frames were compared with (only with the "
          "job's `reference`): how many frames, the median of each figure over them and the "
          "worst frames.\"\n"
          "      additionalProperties: false\n      properties:\n",
          f);
    for (int t = 0; t < MR_REFERENCE_TYPES; t++)
        fprintf(f,
                "        %s:\n"
                "          type: object\n"
                "          required: [frames, medians, worst]\n"
                "          additionalProperties: false\n"
                "          properties:\n"
                "            frames: { type: integer, minimum: 1 }\n"
                "            medians: { $ref: \"#/components/schemas/ErrorFigures\" }\n"
                "            worst: { $ref: \"#/components/schemas/WorstFrames\" }\n",
                mr_reference_name(t));
}

char *mr_stats_openapi_block(void)
{
    char *text = NULL;
    size_t len = 0;
    FILE *f = open_memstream(&text, &len);
    if (!f)
        return NULL;
    fputs(MR_STATS_OPENAPI_BEGIN, f);
    fputs("    Seconds:\n", f);
    put_group_header(f, &mr_stat_group_seconds, 6);
    put_group_fields(f, &mr_stat_group_seconds, 8);
    fputs("\n    FrameStats:\n"
          "      type: object\n"
          "      description: \"One frame's statistics (an entry of stats.json's `frames`, the stored "
          "frame stats, the `frame` event). A geometry kind may add numeric fields of its own "
          "after these (extras).\"\n",
          f);
    put_required(f, NULL, 6);
    fputs("      properties:\n", f);
    const mr_stat_group *group = NULL;
    for (size_t i = 0; i < mr_frame_stat_field_count; i++) {
        const mr_stat_field *fd = &mr_frame_stat_fields[i];
        if (!fd->group) {
            put_field(f, fd, 8);
        } else if (fd->group != group && fd->group == &mr_stat_group_seconds) {
            fprintf(f, "        %s: { $ref: \"#/components/schemas/Seconds\" }\n", fd->group->name);
        } else if (fd->group != group) {
            fprintf(f, "        %s:\n", fd->group->name);
            put_group_header(f, fd->group, 10);
            put_group_fields(f, fd->group, 12);
        }
        group = fd->group;
    }
    fputs("        error:\n"
          "          type: array\n"
          "          description: \"The frame against each reference it was rendered through "
          "(only with the job's `reference`): one entry per reference.\"\n"
          "          items: { $ref: \"#/components/schemas/FrameError\" }\n",
          f);
    fprintf(f,
            "        lod:\n"
            "          type: array\n"
            "          description: \"The level of detail each object with a `tolerance_px` traced "
            "(the first %d such objects, in the job's order; README, Level of detail).\"\n"
            "          maxItems: %d\n"
            "          items: { $ref: \"#/components/schemas/ObjectLod\" }\n",
            MR_FRAME_LOD_MAX, MR_FRAME_LOD_MAX);
    /* the registered kinds' own fields (mr_kind_stat_at), summed over a job's
     * objects of the kind or the largest of theirs; creation figures on the
     * first frame only */
    for (size_t k = 0; k < mr_kind_count(); k++) {
        const mr_kind *kind = mr_kind_at(k);
        for (size_t i = 0; i < mr_kind_stat_count(kind); i++) {
            const mr_kind_stat *st = mr_kind_stat_at(kind, i);
            char about[512];
            snprintf(about, sizeof about, "Kind %s, %s: %s. Unit: %s.", mr_kind_name(kind),
                     st->combine == MR_STAT_MAX    ? "the largest over its objects"
                     : st->combine == MR_STAT_ONCE ? "summed over its objects, on the first "
                                                     "frame only (0 after)"
                                                   : "summed over its objects",
                     st->description, st->unit);
            fprintf(f, "        %s: { type: number, description: ", st->name);
            put_quoted(f, about);
            fputs(" }\n", f);
        }
    }
    fputs("      additionalProperties: { type: number, description: \"A geometry kind's own "
          "per-frame field (extras).\" }\n",
          f);
    put_error_schemas(f);
    fputs("\n    ObjectLod:\n"
          "      type: object\n"
          "      required: [object, level, error_px]\n"
          "      additionalProperties: false\n"
          "      properties:\n"
          "        object: { type: integer, minimum: 0, description: \"The object's index in the "
          "job's `objects`.\" }\n"
          "        level: { type: integer, minimum: 0, description: \"The level traced, as the "
          "object's kind counts levels (README, Level of detail).\" }\n"
          "        error_px: { type: number, minimum: 0, description: \"The level's predicted "
          "error in pixels at this frame's camera.\" }\n",
          f);
    fputs(MR_STATS_OPENAPI_END, f);
    if (fclose(f) != 0) {
        free(text);
        return NULL;
    }
    return text;
}

int mr_stats_openapi_update(const char *path, bool write, bool *stale, mr_error *err)
{
    *stale = false;
    char *doc = NULL, *block = NULL, *out = NULL;
    size_t size = 0;
    int rc = mr_file_read(path, DOC_MAX_BYTES, &doc, &size, err);
    if (rc < 0)
        return rc;
    char *begin = strstr(doc, MR_STATS_OPENAPI_BEGIN);
    char *end = begin ? strstr(begin, MR_STATS_OPENAPI_END) : NULL;
    if (!begin || !end || (begin > doc && begin[-1] != '\n')) {
        rc = mr_error_set(err, MR_ERR_FORMAT, "%s: no frame-stats block (a line '%.*s' and a later '%.*s')",
                          path, (int)strlen(MR_STATS_OPENAPI_BEGIN) - 1, MR_STATS_OPENAPI_BEGIN,
                          (int)strlen(MR_STATS_OPENAPI_END) - 1, MR_STATS_OPENAPI_END);
        goto cleanup;
    }
    end += strlen(MR_STATS_OPENAPI_END);
    if (!(block = mr_stats_openapi_block())) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory");
        goto cleanup;
    }
    size_t bl = strlen(block), head = (size_t)(begin - doc), tail = size - (size_t)(end - doc);
    *stale = (size_t)(end - begin) != bl || memcmp(begin, block, bl) != 0;
    if (!write || !*stale)
        goto cleanup;
    if (!(out = malloc(head + bl + tail))) {
        rc = mr_error_set(err, MR_ERR_NOMEM, "out of memory");
        goto cleanup;
    }
    memcpy(out, doc, head);
    memcpy(out + head, block, bl);
    memcpy(out + head + bl, end, tail);
    rc = mr_fs_write_atomic(path, out, head + bl + tail, "openapi document", err);
cleanup:
    free(doc);
    free(block);
    free(out);
    return rc;
}
