/* params.c - defaults and ownership of kind parameter tables (params.h). */
#include "kinds/params.h"

#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "anim/pose.h"
#include "math/mr_math.h"

#define AT(values, off, type) ((type *)((char *)(values) + (off)))

void mr_params_defaults(const mr_param_table *t, void *values)
{
    for (size_t i = 0; i < t->count; i++) {
        const mr_param *p = &t->params[i];
        switch (p->type) {
        case MR_PARAM_INT: *AT(values, p->offset, uint32_t) = (uint32_t)p->def; break;
        case MR_PARAM_NUMBER: *AT(values, p->offset, float) = (float)p->def; break;
        case MR_PARAM_BOOL: *AT(values, p->offset, bool) = p->def != 0; break;
        case MR_PARAM_ENUM: *AT(values, p->offset, int) = (int)p->def; break;
        case MR_PARAM_FLAG_OBJECT:
            *AT(values, p->offset, bool) = p->def != 0;
            mr_params_defaults(p->sub, values);
            break;
        case MR_PARAM_ARRAY:
            *AT(values, p->offset, void *) = NULL;
            *AT(values, p->count_offset, size_t) = 0;
            break;
        case MR_PARAM_TRANSFORM: *AT(values, p->offset, mr_mat4) = mr_mat4_identity(); break;
        case MR_PARAM_POSE:
            *AT(values, p->offset, mr_pose_desc) = (mr_pose_desc){0};
            *AT(values, p->present_offset, bool) = false;
            break;
        case MR_PARAM_ASSET: *AT(values, p->offset, uint32_t) = 0; break;
        case MR_PARAM_NUMBERS:
            for (size_t k = 0; k < p->max_items; k++)
                AT(values, p->offset, float)[k] = (float)p->def;
            break;
        case MR_PARAM_VEC3:
            *AT(values, p->offset, mr_vec3) =
                mr_v3((float)p->def3[0], (float)p->def3[1], (float)p->def3[2]);
            break;
        case MR_PARAM_QUAT: *AT(values, p->offset, mr_quat) = mr_quat_identity(); break;
        }
    }
}

void mr_params_clear(const mr_param_table *t, void *values)
{
    if (!values)
        return;
    for (size_t i = 0; i < t->count; i++) {
        const mr_param *p = &t->params[i];
        if (p->type == MR_PARAM_POSE) {
            mr_pose_desc_clear(AT(values, p->offset, mr_pose_desc));
        } else if (p->type == MR_PARAM_FLAG_OBJECT) {
            mr_params_clear(p->sub, values);
        } else if (p->type == MR_PARAM_ARRAY) {
            char *items = *AT(values, p->offset, char *);
            size_t n = *AT(values, p->count_offset, size_t);
            if (items)
                for (size_t k = 0; k < n; k++)
                    mr_params_clear(p->sub, items + k * p->sub->size);
            free(items);
            *AT(values, p->offset, void *) = NULL;
            *AT(values, p->count_offset, size_t) = 0;
        }
    }
}

int mr_param_index(const mr_param_table *t, const char *field)
{
    for (size_t i = 0; t && i < t->count; i++)
        if (strcmp(t->params[i].field, field) == 0)
            return (int)i;
    return -1;
}

const mr_param *mr_param_find(const mr_param_table *t, const char *field)
{
    int i = mr_param_index(t, field);
    return i < 0 ? NULL : &t->params[i];
}

int mr_param_fail(mr_param_error *err, int code, const char *field, const char *fmt, ...)
{
    va_list ap;
    err->code = code;
    snprintf(err->field, sizeof err->field, "%s", field ? field : "");
    va_start(ap, fmt);
    vsnprintf(err->message, sizeof err->message, fmt, ap);
    va_end(ap);
    return code;
}
