/*
 * dmm_encode.c - hierarchical DMM displacement encoding, min/max pyramid and
 * the binary file (dmm_encode.h, docs/dmm-format.md). Encoder and decoder
 * share one prediction routine and work on integers only, so the decoder
 * reproduces the encoder's values bit for bit on any machine; floats appear
 * only at the ends (input quantisation, value_to_float).
 */
#include "kinds/dmm/dmm_encode.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "util/crc32.h"
#include "util/file_io.h"
#include "util/le.h"

#define SHIFT_BITS 4u
#define MAX_SHIFT 15
#define GROUPS 4 /* edges 0, 1, 2 and the interior */
#define FILE_VERSION 2u
#define MAX_FILE_BYTES ((uint64_t)1 << 31)

static const uint8_t file_magic[8] = {'M', 'R', 'D', 'M', 'M', 0, '\r', '\n'};

void mr_dmm_default_bits(uint8_t bits[MR_UMESH_MAX_LEVEL + 1])
{
    static const uint8_t def[MR_UMESH_MAX_LEVEL + 1] = {16, 11, 10, 9, 8, 7};
    memcpy(bits, def, sizeof def);
}

static bool bits_valid(unsigned level, const uint8_t *bits)
{
    if (level > MR_UMESH_MAX_LEVEL || !bits)
        return false;
    if (bits[0] < 1 || bits[0] > MR_DMM_MAX_BITS)
        return false;
    /* a 1-bit two's complement correction cannot be positive: useless */
    for (unsigned l = 1; l <= level; l++)
        if (bits[l] < 2 || bits[l] > MR_DMM_MAX_BITS)
            return false;
    return true;
}

uint32_t mr_dmm_record_bytes(unsigned level, const uint8_t bits[MR_UMESH_MAX_LEVEL + 1])
{
    if (!bits_valid(level, bits))
        return 0;
    uint64_t nbits = 3u * bits[0];
    for (unsigned l = 1; l <= level; l++) {
        uint64_t fresh = mr_umesh_vertex_count(l) - mr_umesh_vertex_count(l - 1);
        nbits += GROUPS * SHIFT_BITS + fresh * bits[l];
    }
    return (uint32_t)((nbits + 7) / 8);
}

/* ---- bit stream: bit i lives in byte i / 8 at bit i % 8 (little-endian) */

static void put_bits(uint8_t *buf, uint32_t *pos, uint32_t value, unsigned n)
{
    for (unsigned i = 0; i < n; i++, (*pos)++)
        if (value >> i & 1u)
            buf[*pos >> 3] |= (uint8_t)(1u << (*pos & 7u));
}

static uint32_t get_bits(const uint8_t *buf, uint32_t *pos, unsigned n)
{
    uint32_t v = 0;
    for (unsigned i = 0; i < n; i++, (*pos)++)
        v |= (uint32_t)(buf[*pos >> 3] >> (*pos & 7u) & 1u) << i;
    return v;
}

/* ---- hierarchy */

/* Level-L lattice vertex (a, b) is new at level l (1 <= l <= L) when both
 * coordinates are multiples of t = 2^(L-l) but not both of 2t. Its two
 * parent-edge neighbours (at level l - 1) are returned as indices; they lie
 * on the same base edge as the vertex when it is on one. */
static bool new_at_level(unsigned L, unsigned l, uint32_t a, uint32_t b, uint32_t *p, uint32_t *q)
{
    uint32_t t = 1u << (L - l);
    if (a % t || b % t)
        return false;
    uint32_t i = a / t, j = b / t;
    if (i % 2 == 0 && j % 2 == 0)
        return false;
    if (i % 2 && j % 2 == 0) { /* on a horizontal edge */
        *p = mr_umesh_vertex_index(L, a - t, b);
        *q = mr_umesh_vertex_index(L, a + t, b);
    } else if (i % 2 == 0) { /* on a vertical edge */
        *p = mr_umesh_vertex_index(L, a, b - t);
        *q = mr_umesh_vertex_index(L, a, b + t);
    } else { /* on an anti-diagonal edge */
        *p = mr_umesh_vertex_index(L, a + t, b - t);
        *q = mr_umesh_vertex_index(L, a - t, b + t);
    }
    return true;
}

static int group_of(unsigned L, uint32_t a, uint32_t b)
{
    int e = mr_umesh_vertex_edge(L, a, b, NULL);
    return e >= 0 && e < 3 ? e : 3;
}

/* Symmetric about zero, so an edge read in either direction rounds alike. */
static int32_t round_shift(int32_t c, unsigned s)
{
    int32_t h = (int32_t)((1u << s) >> 1);
    return c >= 0 ? (c + h) >> s : -((-c + h) >> s);
}

static uint16_t clamp_value(int64_t v, uint32_t vmax)
{
    return (uint16_t)(v < 0 ? 0 : v > (int64_t)vmax ? vmax : v);
}

/* Encodes one triangle: target grid values in, record and decoded values
 * out. Returns the number of clamped corrections. */
static uint64_t encode_triangle(unsigned L, const uint8_t *bits, const uint16_t *target,
                                uint16_t *dec, uint8_t *rec, mr_dmm_encode_stats *st)
{
    uint32_t n = mr_umesh_segments(L), vc = mr_umesh_vertex_count(L), pos = 0;
    uint32_t vmax = (1u << bits[0]) - 1u;
    uint64_t clamped = 0;
    const uint32_t corner[3] = {mr_umesh_vertex_index(L, 0, 0), mr_umesh_vertex_index(L, n, 0),
                                mr_umesh_vertex_index(L, 0, n)};
    for (int k = 0; k < 3; k++) {
        dec[corner[k]] = target[corner[k]];
        put_bits(rec, &pos, target[corner[k]], bits[0]);
    }
    for (unsigned l = 1; l <= L; l++) {
        int32_t lo = -(int32_t)(1u << (bits[l] - 1)), hi = (int32_t)(1u << (bits[l] - 1)) - 1;
        int32_t cmin[GROUPS] = {0}, cmax[GROUPS] = {0};
        /* corrections against predictions from the decoded coarser levels */
        for (uint32_t v = 0; v < vc; v++) {
            uint32_t a, b, p, q;
            mr_umesh_vertex_coords(L, v, &a, &b);
            if (!new_at_level(L, l, a, b, &p, &q))
                continue;
            int32_t c = (int32_t)target[v] - (int32_t)((dec[p] + dec[q] + 1u) >> 1);
            int g = group_of(L, a, b);
            cmin[g] = c < cmin[g] ? c : cmin[g];
            cmax[g] = c > cmax[g] ? c : cmax[g];
        }
        unsigned shift[GROUPS];
        for (int g = 0; g < GROUPS; g++) {
            unsigned s = 0;
            /* rounding is monotone in c, so the extremes decide */
            while (s < MAX_SHIFT && (round_shift(cmin[g], s) < lo || round_shift(cmax[g], s) > hi))
                s++;
            shift[g] = s;
            put_bits(rec, &pos, s, SHIFT_BITS);
        }
        for (uint32_t v = 0; v < vc; v++) {
            uint32_t a, b, p, q;
            mr_umesh_vertex_coords(L, v, &a, &b);
            if (!new_at_level(L, l, a, b, &p, &q))
                continue;
            int32_t pred = (int32_t)((dec[p] + dec[q] + 1u) >> 1);
            unsigned s = shift[group_of(L, a, b)];
            if (s) {
                st->shifted++;
                st->max_shift = s > st->max_shift ? s : st->max_shift;
            }
            int32_t r = round_shift((int32_t)target[v] - pred, s);
            if (r < lo || r > hi) {
                clamped++;
                r = r < lo ? lo : hi;
            }
            dec[v] = clamp_value((int64_t)pred + (int64_t)r * ((int64_t)1 << s), vmax);
            put_bits(rec, &pos, (uint32_t)r & ((1u << bits[l]) - 1u), bits[l]);
        }
    }
    return clamped;
}

static void decode_triangle(unsigned L, const uint8_t *bits, const uint8_t *rec, uint16_t *dec)
{
    uint32_t n = mr_umesh_segments(L), vc = mr_umesh_vertex_count(L), pos = 0;
    uint32_t vmax = (1u << bits[0]) - 1u;
    const uint32_t corner[3] = {mr_umesh_vertex_index(L, 0, 0), mr_umesh_vertex_index(L, n, 0),
                                mr_umesh_vertex_index(L, 0, n)};
    for (int k = 0; k < 3; k++)
        dec[corner[k]] = (uint16_t)get_bits(rec, &pos, bits[0]);
    for (unsigned l = 1; l <= L; l++) {
        unsigned shift[GROUPS];
        for (int g = 0; g < GROUPS; g++)
            shift[g] = get_bits(rec, &pos, SHIFT_BITS);
        for (uint32_t v = 0; v < vc; v++) {
            uint32_t a, b, p, q;
            mr_umesh_vertex_coords(L, v, &a, &b);
            if (!new_at_level(L, l, a, b, &p, &q))
                continue;
            int32_t pred = (int32_t)((dec[p] + dec[q] + 1u) >> 1);
            uint32_t raw = get_bits(rec, &pos, bits[l]);
            /* sign-extend a bits[l]-wide two's complement value */
            int32_t r = (raw >> (bits[l] - 1)) ? (int32_t)raw - (int32_t)(1u << bits[l])
                                               : (int32_t)raw;
            dec[v] = clamp_value((int64_t)pred + (int64_t)r * ((int64_t)1 << shift[group_of(L, a, b)]),
                                 vmax);
        }
    }
}

/* ---- encode / decode API */

/* Checks each triangle's info byte against the largest level and lays the
 * records out: offset[t] and *total. MR_ERR_INVALID for a bad info byte,
 * MR_ERR_LIMIT when the records pass MAX_FILE_BYTES; *bad names the
 * triangle. No message: callers know their context. */
static int layout_records(unsigned level, const uint8_t *bits, uint32_t count,
                          const uint8_t *info, uint32_t *offset, uint64_t *total, uint32_t *bad)
{
    uint64_t sum = 0;
    for (uint32_t t = 0; t < count; t++) {
        unsigned l = mr_dmm_info_level(info[t]);
        *bad = t;
        if ((info[t] & 0x88u) || l > level || (l == 0 && mr_dmm_info_decimate(info[t])))
            return MR_ERR_INVALID;
        offset[t] = (uint32_t)sum;
        sum += mr_dmm_record_bytes(l, bits);
        if (sum > MAX_FILE_BYTES)
            return MR_ERR_LIMIT;
    }
    *total = sum;
    return MR_OK;
}

int mr_dmm_encode(unsigned level, const uint8_t bits[MR_UMESH_MAX_LEVEL + 1],
                  uint32_t triangle_count, const uint8_t *tri_info, const float *disp,
                  mr_dmm_encoded **out, mr_dmm_encode_stats *stats, mr_error *err)
{
    int rc = MR_OK;
    mr_dmm_encoded *enc = NULL;
    uint16_t *target = NULL, *dec = NULL;
    if (out)
        *out = NULL;
    if (!out || !disp || triangle_count == 0 || triangle_count > MR_DMM_MAX_TRIANGLES)
        return mr_error_set(err, MR_ERR_INVALID,
                            "dmm encode: need output, displacements and 1..%u triangles",
                            MR_DMM_MAX_TRIANGLES);
    if (!mr_dmm_record_bytes(level, bits))
        return mr_error_set(err, MR_ERR_INVALID,
                            "dmm encode: bad level %u or bits per level (bits[0] 1..16, "
                            "bits[1..level] 2..16)",
                            level);
    uint32_t stride = mr_umesh_vertex_count(level);
    enc = calloc(1, sizeof *enc);
    target = malloc(sizeof(uint16_t) * stride);
    dec = malloc(sizeof(uint16_t) * stride);
    if (enc) {
        enc->tri_info = malloc(triangle_count);
        enc->record_offset = malloc(sizeof(uint32_t) * triangle_count);
    }
    if (!enc || !target || !dec || !enc->tri_info || !enc->record_offset)
        goto nomem;
    for (uint32_t t = 0; t < triangle_count; t++)
        enc->tri_info[t] = tri_info ? tri_info[t] : mr_dmm_tri_info(level, 0);
    uint32_t bad = 0;
    uint64_t body = 0;
    if ((rc = layout_records(level, bits, triangle_count, enc->tri_info, enc->record_offset,
                             &body, &bad)) < 0) {
        rc = rc == MR_ERR_LIMIT
                 ? mr_error_set(err, rc, "dmm encode: the records pass 2 GiB at triangle %u", bad)
                 : mr_error_set(err, rc,
                                "dmm encode: triangle %u: level/decimation byte 0x%02x is not "
                                "valid under largest level %u",
                                bad, enc->tri_info[bad], level);
        goto cleanup;
    }
    double dmin = INFINITY, dmax = -INFINITY;
    uint64_t total = 0;
    for (uint32_t t = 0; t < triangle_count; t++) {
        uint32_t vc = mr_umesh_vertex_count(mr_dmm_info_level(enc->tri_info[t]));
        const float *d = disp + (size_t)t * stride;
        total += vc;
        for (uint32_t v = 0; v < vc; v++) {
            if (!isfinite(d[v])) {
                rc = mr_error_set(err, MR_ERR_INVALID,
                                  "dmm encode: displacement %u of triangle %u is not finite", v, t);
                goto cleanup;
            }
            dmin = fmin(dmin, d[v]);
            dmax = fmax(dmax, d[v]);
        }
    }
    uint32_t vmax = (1u << bits[0]) - 1u;
    double range = dmax - dmin;
    float scale = range > 0 ? (float)(range / vmax) : 1.0f;
    if (!isfinite(scale)) {
        rc = mr_error_set(err, MR_ERR_INVALID, "dmm encode: displacement range %g too large",
                          range);
        goto cleanup;
    }
    if (scale <= 0) /* a range so small it underflows: any positive step works */
        scale = 1.0f;
    enc->records = calloc(1, (size_t)body);
    if (!enc->records)
        goto nomem;
    enc->level = level;
    for (unsigned l = 0; l <= level; l++)
        enc->bits[l] = bits[l];
    enc->triangle_count = triangle_count;
    enc->records_bytes = (uint32_t)body;
    enc->bias = (float)dmin; /* the minimum is an input float: exact */
    enc->scale = scale;

    double sum2 = 0, worst = 0;
    uint64_t clamped = 0;
    mr_dmm_encode_stats acc = {0};
    for (uint32_t t = 0; t < triangle_count; t++) {
        unsigned l = mr_dmm_info_level(enc->tri_info[t]);
        uint32_t vc = mr_umesh_vertex_count(l);
        const float *d = disp + (size_t)t * stride;
        for (uint32_t v = 0; v < vc; v++) {
            /* a function of the float alone: shared vertices get equal values */
            double x = nearbyint(((double)d[v] - (double)enc->bias) / (double)scale);
            target[v] = clamp_value((int64_t)fmax(fmin(x, (double)vmax), 0.0), vmax);
        }
        clamped += encode_triangle(l, enc->bits, target, dec,
                                   enc->records + enc->record_offset[t], &acc);
        for (uint32_t v = 0; v < vc; v++) {
            double e = fabs((double)mr_dmm_value_to_float(enc, dec[v]) - (double)d[v]);
            worst = fmax(worst, e);
            sum2 += e * e;
        }
    }
    if (stats) {
        *stats = acc;
        stats->max_error = worst;
        stats->rms_error = sqrt(sum2 / (double)total);
        stats->clamped = clamped;
    }
    *out = enc;
    enc = NULL;
    goto cleanup;
nomem:
    rc = mr_error_set(err, MR_ERR_NOMEM, "dmm encode: out of memory for %u triangles",
                      triangle_count);
cleanup:
    mr_dmm_encoded_free(enc);
    free(target);
    free(dec);
    return rc;
}

void mr_dmm_encoded_free(mr_dmm_encoded *enc)
{
    if (!enc)
        return;
    free(enc->tri_info);
    free(enc->record_offset);
    free(enc->records);
    free(enc);
}

unsigned mr_dmm_tri_level(const mr_dmm_encoded *enc, uint32_t tri)
{
    return mr_dmm_info_level(enc->tri_info[tri]);
}

unsigned mr_dmm_tri_decimate(const mr_dmm_encoded *enc, uint32_t tri)
{
    return mr_dmm_info_decimate(enc->tri_info[tri]);
}

int mr_dmm_decode_values(const mr_dmm_encoded *enc, uint32_t tri, uint16_t *values,
                         mr_error *err)
{
    if (!enc || !values || tri >= enc->triangle_count || !enc->records || !enc->tri_info ||
        !enc->record_offset)
        return mr_error_set(err, MR_ERR_INVALID, "dmm decode: bad arguments (triangle %u)", tri);
    decode_triangle(mr_dmm_tri_level(enc, tri), enc->bits, enc->records + enc->record_offset[tri],
                    values);
    return MR_OK;
}

int mr_dmm_decode_floats(const mr_dmm_encoded *enc, uint32_t tri, float *out, mr_error *err)
{
    uint16_t values[561]; /* vertex count at MR_UMESH_MAX_LEVEL */
    if (!out)
        return mr_error_set(err, MR_ERR_INVALID, "dmm decode: no output");
    int rc = mr_dmm_decode_values(enc, tri, values, err);
    if (rc < 0)
        return rc;
    for (uint32_t v = 0; v < mr_umesh_vertex_count(mr_dmm_tri_level(enc, tri)); v++)
        out[v] = mr_dmm_value_to_float(enc, values[v]);
    return MR_OK;
}

/* ---- pyramid */

uint32_t mr_dmm_pyramid_size(unsigned level)
{
    return level > MR_UMESH_MAX_LEVEL ? 0u : ((1u << (2 * (level + 1))) - 1u) / 3u;
}

bool mr_dmm_subtri(unsigned level, unsigned sublevel, uint32_t id, uint32_t a[3], uint32_t b[3])
{
    if (level > MR_UMESH_MAX_LEVEL || sublevel > level || id >= (1u << (2 * sublevel)))
        return false;
    uint32_t n = mr_umesh_segments(level);
    uint32_t pa[3] = {0, n, 0}, pb[3] = {0, 0, n};
    for (unsigned k = 1; k <= sublevel; k++) {
        unsigned digit = id >> (2 * (sublevel - k)) & 3u;
        /* midpoints m01, m12, m20: even lattice distances, exact */
        uint32_t ma[3] = {(pa[0] + pa[1]) / 2, (pa[1] + pa[2]) / 2, (pa[2] + pa[0]) / 2};
        uint32_t mb[3] = {(pb[0] + pb[1]) / 2, (pb[1] + pb[2]) / 2, (pb[2] + pb[0]) / 2};
        uint32_t na[3], nb[3];
        switch (digit) {
        case 0: na[0] = pa[0], nb[0] = pb[0], na[1] = ma[0], nb[1] = mb[0], na[2] = ma[2], nb[2] = mb[2]; break;
        case 1: na[0] = ma[0], nb[0] = mb[0], na[1] = pa[1], nb[1] = pb[1], na[2] = ma[1], nb[2] = mb[1]; break;
        case 2: na[0] = ma[2], nb[0] = mb[2], na[1] = ma[1], nb[1] = mb[1], na[2] = pa[2], nb[2] = pb[2]; break;
        default: na[0] = ma[1], nb[0] = mb[1], na[1] = ma[2], nb[1] = mb[2], na[2] = ma[0], nb[2] = mb[0]; break;
        }
        memcpy(pa, na, sizeof pa);
        memcpy(pb, nb, sizeof pb);
    }
    memcpy(a, pa, sizeof pa);
    memcpy(b, pb, sizeof pb);
    return true;
}

int mr_dmm_pyramid_build(unsigned level, const uint16_t *values, uint16_t *minv, uint16_t *maxv,
                         mr_error *err)
{
    if (level > MR_UMESH_MAX_LEVEL || !values || !minv || !maxv)
        return mr_error_set(err, MR_ERR_INVALID, "dmm pyramid: bad arguments (level %u)", level);
    /* leaves: a finest sub-triangle covers exactly its three corners */
    uint32_t leaf0 = mr_dmm_pyramid_size(level) - (1u << (2 * level));
    for (uint32_t id = 0; id < (1u << (2 * level)); id++) {
        uint32_t a[3], b[3];
        mr_dmm_subtri(level, level, id, a, b);
        uint16_t lo = UINT16_MAX, hi = 0;
        for (int k = 0; k < 3; k++) {
            uint16_t v = values[mr_umesh_vertex_index(level, a[k], b[k])];
            lo = v < lo ? v : lo;
            hi = v > hi ? v : hi;
        }
        minv[leaf0 + id] = lo;
        maxv[leaf0 + id] = hi;
    }
    /* a parent's closed region is the union of its children's, so its
     * vertex set is too and the combined bounds stay tight */
    for (unsigned l = level; l-- > 0;) {
        uint32_t off = mr_dmm_pyramid_size(l) - (1u << (2 * l));
        uint32_t child = mr_dmm_pyramid_size(l + 1) - (1u << (2 * (l + 1)));
        for (uint32_t id = 0; id < (1u << (2 * l)); id++) {
            uint16_t lo = UINT16_MAX, hi = 0;
            for (uint32_t c = 0; c < 4; c++) {
                uint16_t cl = minv[child + 4 * id + c], ch = maxv[child + 4 * id + c];
                lo = cl < lo ? cl : lo;
                hi = ch > hi ? ch : hi;
            }
            minv[off + id] = lo;
            maxv[off + id] = hi;
        }
    }
    return MR_OK;
}

/* ---- file */

int mr_dmm_write(const mr_dmm_encoded *enc, uint8_t **buf, size_t *size, mr_error *err)
{
    if (buf)
        *buf = NULL;
    if (!enc || !buf || !size || !enc->records || !enc->tri_info ||
        enc->triangle_count == 0 || enc->triangle_count > MR_DMM_MAX_TRIANGLES ||
        !mr_dmm_record_bytes(enc->level, enc->bits) || !isfinite(enc->bias) ||
        !isfinite(enc->scale) || !(enc->scale > 0))
        return mr_error_set(err, MR_ERR_INVALID, "dmm write: bad or inconsistent DMM");
    size_t info = enc->triangle_count, body = enc->records_bytes;
    size_t total = MR_DMM_HEADER_BYTES + info + body + 4;
    uint8_t *p = calloc(1, total);
    if (!p)
        return mr_error_set(err, MR_ERR_NOMEM, "dmm write: out of memory for %zu bytes", total);
    memcpy(p, file_magic, 8);
    mr_le_put_u32(p + 8, FILE_VERSION);
    mr_le_put_u32(p + 12, MR_DMM_HEADER_BYTES);
    mr_le_put_u32(p + 16, enc->level);
    for (unsigned l = 0; l <= enc->level; l++)
        p[20 + l] = enc->bits[l]; /* bytes 20..27: widths, unused ones and padding 0 */
    mr_le_put_u32(p + 28, enc->triangle_count);
    mr_le_put_u32(p + 32, enc->records_bytes);
    mr_le_put_f32(p + 36, enc->bias);
    mr_le_put_f32(p + 40, enc->scale);
    mr_le_put_u32(p + 44, mr_crc32(p, 44));
    memcpy(p + MR_DMM_HEADER_BYTES, enc->tri_info, info);
    memcpy(p + MR_DMM_HEADER_BYTES + info, enc->records, body);
    mr_le_put_u32(p + MR_DMM_HEADER_BYTES + info + body,
            mr_crc32(p + MR_DMM_HEADER_BYTES, info + body));
    *buf = p;
    *size = total;
    return MR_OK;
}

int mr_dmm_read(const uint8_t *buf, size_t size, mr_dmm_encoded **out, mr_error *err)
{
    if (out)
        *out = NULL;
    if (!out || (!buf && size))
        return mr_error_set(err, MR_ERR_INVALID, "dmm read: bad arguments");
    if (size < MR_DMM_HEADER_BYTES)
        return mr_error_set(err, MR_ERR_FORMAT,
                            "dmm file: truncated header at byte offset %zu (need %u bytes)", size,
                            MR_DMM_HEADER_BYTES);
    for (size_t i = 0; i < 8; i++)
        if (buf[i] != file_magic[i])
            return mr_error_set(err, MR_ERR_FORMAT, "dmm file: bad magic at byte offset %zu", i);
    uint32_t version = mr_le_get_u32(buf + 8);
    if (version != FILE_VERSION)
        return mr_error_set(err, MR_ERR_FORMAT,
                            "dmm file: unsupported version %u at byte offset 8 (want %u)",
                            version, FILE_VERSION);
    if (mr_le_get_u32(buf + 12) != MR_DMM_HEADER_BYTES)
        return mr_error_set(err, MR_ERR_FORMAT,
                            "dmm file: header size %u at byte offset 12 (want %u)",
                            mr_le_get_u32(buf + 12), MR_DMM_HEADER_BYTES);
    if (!mr_crc32_matches(mr_le_get_u32(buf + 44), buf, 44))
        return mr_error_set(err, MR_ERR_FORMAT,
                            "dmm file: header checksum mismatch at byte offset 44 "
                            "(bytes 0..43 corrupted)");
    uint32_t level = mr_le_get_u32(buf + 16);
    if (level > MR_UMESH_MAX_LEVEL)
        return mr_error_set(err, MR_ERR_FORMAT, "dmm file: level %u at byte offset 16 (max %u)",
                            level, MR_UMESH_MAX_LEVEL);
    uint8_t bits[MR_UMESH_MAX_LEVEL + 1] = {0};
    for (unsigned i = 0; i < 8; i++) {
        uint8_t v = buf[20 + i];
        bool ok = i == 0 ? v >= 1 && v <= MR_DMM_MAX_BITS
                  : i <= level ? v >= 2 && v <= MR_DMM_MAX_BITS
                               : v == 0;
        if (!ok)
            return mr_error_set(err, MR_ERR_FORMAT,
                                "dmm file: bad bit width %u at byte offset %u", v, 20 + i);
        if (i <= MR_UMESH_MAX_LEVEL)
            bits[i] = v;
    }
    uint32_t count = mr_le_get_u32(buf + 28);
    if (count == 0 || count > MR_DMM_MAX_TRIANGLES)
        return mr_error_set(err, MR_ERR_FORMAT,
                            "dmm file: triangle count %u at byte offset 28 (1..%u)", count,
                            MR_DMM_MAX_TRIANGLES);
    uint32_t declared = mr_le_get_u32(buf + 32);
    float bias = mr_le_get_f32(buf + 36), scale = mr_le_get_f32(buf + 40);
    if (!isfinite(bias))
        return mr_error_set(err, MR_ERR_FORMAT, "dmm file: non-finite bias at byte offset 36");
    if (!isfinite(scale) || !(scale > 0))
        return mr_error_set(err, MR_ERR_FORMAT,
                            "dmm file: scale at byte offset 40 is not a positive finite number");
    /* count and records_bytes are 32-bit: no 64-bit overflow below */
    uint64_t want = MR_DMM_HEADER_BYTES + (uint64_t)count + declared + 4;
    if ((uint64_t)size < want)
        return mr_error_set(err, MR_ERR_FORMAT,
                            "dmm file: truncated at byte offset %zu (declared size %llu)", size,
                            (unsigned long long)want);
    if ((uint64_t)size > want)
        return mr_error_set(err, MR_ERR_FORMAT,
                            "dmm file: %llu unexpected trailing bytes at byte offset %llu",
                            (unsigned long long)((uint64_t)size - want),
                            (unsigned long long)want);
    const uint8_t *info = buf + MR_DMM_HEADER_BYTES;
    uint64_t body_end = MR_DMM_HEADER_BYTES + (uint64_t)count + declared;
    if (!mr_crc32_matches(mr_le_get_u32(buf + body_end), info, (size_t)(count + (uint64_t)declared)))
        return mr_error_set(err, MR_ERR_FORMAT,
                            "dmm file: record checksum mismatch at byte offset %llu (bytes "
                            "%u..%llu corrupted)",
                            (unsigned long long)body_end, MR_DMM_HEADER_BYTES,
                            (unsigned long long)(body_end - 1));
    mr_dmm_encoded *enc = calloc(1, sizeof *enc);
    if (enc) {
        enc->tri_info = malloc(count);
        enc->record_offset = malloc(sizeof(uint32_t) * count);
        enc->records = malloc(declared ? declared : 1);
    }
    if (!enc || !enc->tri_info || !enc->record_offset || !enc->records) {
        mr_dmm_encoded_free(enc);
        return mr_error_set(err, MR_ERR_NOMEM, "dmm read: out of memory for %u triangles", count);
    }
    memcpy(enc->tri_info, info, count);
    uint32_t bad = 0;
    uint64_t body = 0;
    int rc = layout_records(level, bits, count, enc->tri_info, enc->record_offset, &body, &bad);
    if (rc < 0 || body != declared) {
        rc = rc < 0 ? mr_error_set(err, MR_ERR_FORMAT,
                                   "dmm file: level/decimation byte 0x%02x of triangle %u at byte "
                                   "offset %u is not valid under level %u",
                                   enc->tri_info[bad], bad, MR_DMM_HEADER_BYTES + bad, level)
                    : mr_error_set(err, MR_ERR_FORMAT,
                                   "dmm file: records size %u at byte offset 32 (the triangles' "
                                   "levels and widths give %llu)",
                                   declared, (unsigned long long)body);
        mr_dmm_encoded_free(enc);
        return rc;
    }
    memcpy(enc->records, info + count, declared);
    enc->level = level;
    memcpy(enc->bits, bits, sizeof bits);
    enc->triangle_count = count;
    enc->records_bytes = declared;
    enc->bias = bias;
    enc->scale = scale;
    /* every record bit pattern decodes to in-range values (shifts are 4-bit,
     * results clamped), so nothing further can be invalid */
    *out = enc;
    return MR_OK;
}

int mr_dmm_write_file(const mr_dmm_encoded *enc, const char *path, mr_error *err)
{
    uint8_t *buf = NULL;
    size_t size = 0;
    if (!path)
        return mr_error_set(err, MR_ERR_INVALID, "dmm write: no path");
    int rc = mr_dmm_write(enc, &buf, &size, err);
    if (rc == MR_OK)
        rc = mr_fs_write_atomic(path, buf, size, "dmm write", err);
    free(buf);
    return rc;
}

int mr_dmm_read_file(const char *path, mr_dmm_encoded **out, mr_error *err)
{
    if (out)
        *out = NULL;
    if (!path || !out)
        return mr_error_set(err, MR_ERR_INVALID, "dmm read: bad arguments");
    uint8_t *buf = NULL;
    size_t size = 0;
    int rc = mr_fs_read_capped(path, MAX_FILE_BYTES, &buf, &size, "dmm file", err);
    if (rc == MR_OK && (rc = mr_dmm_read(buf, size, out, err)) < 0)
        mr_error_prefix(err, "%s: ", path);
    free(buf);
    return rc;
}
