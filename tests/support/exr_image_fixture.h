/*
 * exr_image_fixture.h - EXR files of any channel set for the image tests
 * (height textures: "Y", "R" "G" "B", one channel of any name, or a set
 * the reader must refuse), written with OpenEXR's own C API, uncompressed
 * scanlines. Header-only; include after microray.h.
 */
#ifndef MR_TEST_EXR_IMAGE_FIXTURE_H
#define MR_TEST_EXR_IMAGE_FIXTURE_H

#include <openexr.h>
#include <stdbool.h>
#include <stdint.h>
#include <string.h>

/* Writes a width x height scanline EXR at path with nch channels named
 * names[c], of type types[c] (EXR_PIXEL_HALF / FLOAT / UINT), whose values
 * come from planes[c] (width * height floats, row 0 first; UINT channels
 * get the values truncated). Returns true on success. */
static bool fx_exr_write(const char *path, int width, int height, int nch, const char *const *names,
                         const exr_pixel_type_t *types, const float *const *planes)
{
    exr_context_initializer_t init = EXR_DEFAULT_CONTEXT_INITIALIZER;
    exr_context_t ctxt = NULL;
    int part = 0;
    bool ok = false;
    /* converted rows, one per channel, in the channel's own type */
    uint8_t *rows[8] = {0};
    if (nch < 1 || nch > 8)
        return false;
    if (exr_start_write(&ctxt, path, EXR_WRITE_FILE_DIRECTLY, &init) != EXR_ERR_SUCCESS)
        return false;
    if (exr_add_part(ctxt, NULL, EXR_STORAGE_SCANLINE, &part) != EXR_ERR_SUCCESS ||
        exr_initialize_required_attr_simple(ctxt, part, width, height, EXR_COMPRESSION_NONE) !=
            EXR_ERR_SUCCESS)
        goto done;
    for (int c = 0; c < nch; c++)
        if (exr_add_channel(ctxt, part, names[c], types[c], EXR_PERCEPTUALLY_LOGARITHMIC, 1, 1) !=
            EXR_ERR_SUCCESS)
            goto done;
    if (exr_write_header(ctxt) != EXR_ERR_SUCCESS)
        goto done;
    int32_t lines = 0;
    if (exr_get_scanlines_per_chunk(ctxt, part, &lines) != EXR_ERR_SUCCESS || lines != 1)
        goto done;
    for (int c = 0; c < nch; c++)
        if (!(rows[c] = malloc((size_t)width * 4)))
            goto done;
    exr_encode_pipeline_t enc = EXR_ENCODE_PIPELINE_INITIALIZER;
    bool started = false;
    for (int y = 0; y < height; y++) {
        exr_chunk_info_t cinfo;
        if (exr_write_scanline_chunk_info(ctxt, part, y, &cinfo) != EXR_ERR_SUCCESS)
            goto fail_enc;
        if (!started) {
            if (exr_encoding_initialize(ctxt, part, &cinfo, &enc) != EXR_ERR_SUCCESS)
                goto done;
            started = true;
        } else if (exr_encoding_update(ctxt, part, &cinfo, &enc) != EXR_ERR_SUCCESS) {
            goto fail_enc;
        }
        for (int k = 0; k < enc.channel_count; k++) {
            exr_coding_channel_info_t *ch = &enc.channels[k];
            int c = 0;
            while (c < nch && strcmp(names[c], ch->channel_name) != 0)
                c++;
            if (c == nch)
                goto fail_enc;
            const float *src = planes[c] + (size_t)y * width;
            for (int x = 0; x < width; x++) {
                if (types[c] == EXR_PIXEL_UINT)
                    ((uint32_t *)(void *)rows[c])[x] = (uint32_t)src[x];
                else
                    ((float *)(void *)rows[c])[x] = src[x];
            }
            ch->encode_from_ptr = rows[c];
            ch->user_data_type = types[c] == EXR_PIXEL_UINT ? EXR_PIXEL_UINT : EXR_PIXEL_FLOAT;
            ch->user_bytes_per_element = 4;
            ch->user_pixel_stride = 4;
            ch->user_line_stride = 4 * width;
        }
        if (y == 0 && exr_encoding_choose_default_routines(ctxt, part, &enc) != EXR_ERR_SUCCESS)
            goto fail_enc;
        if (exr_encoding_run(ctxt, part, &enc) != EXR_ERR_SUCCESS)
            goto fail_enc;
    }
    ok = true;
fail_enc:
    if (started)
        exr_encoding_destroy(ctxt, &enc);
done:
    if (ctxt && exr_finish(&ctxt) != EXR_ERR_SUCCESS)
        ok = false;
    for (int c = 0; c < 8; c++)
        free(rows[c]);
    return ok;
}

#endif
