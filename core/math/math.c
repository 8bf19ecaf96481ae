/*
 * math.c - vectors, 4x4 matrices and quaternions (see mr_math.h for the
 * storage and composition conventions).
 *
 * Tolerances: single precision throughout; the inverse refuses matrices whose
 * determinant is below 1e-12 of the scale of its entries to the 4th power,
 * where the cofactor formula has lost all significant digits.
 */
#include "math/mr_math.h"

#include <float.h>

mr_vec3 mr_v3_any_orthogonal(mr_vec3 n)
{
    float ax = fabsf(n.x), ay = fabsf(n.y), az = fabsf(n.z);
    mr_vec3 axis = ax <= ay && ax <= az ? mr_v3(1, 0, 0) : ay <= az ? mr_v3(0, 1, 0) : mr_v3(0, 0, 1);
    return mr_v3_normalize_or(mr_v3_cross(n, axis), mr_v3(1, 0, 0));
}

mr_mat4 mr_mat4_identity(void)
{
    mr_mat4 r = {{0}};
    r.m[0] = r.m[5] = r.m[10] = r.m[15] = 1.0f;
    return r;
}

mr_mat4 mr_mat4_mul(const mr_mat4 *a, const mr_mat4 *b)
{
    mr_mat4 r;
    for (int i = 0; i < 4; i++)
        for (int j = 0; j < 4; j++) {
            float s = 0.0f;
            for (int k = 0; k < 4; k++)
                s += a->m[i * 4 + k] * b->m[k * 4 + j];
            r.m[i * 4 + j] = s;
        }
    return r;
}

mr_mat4 mr_mat4_transpose(const mr_mat4 *a)
{
    mr_mat4 r;
    for (int i = 0; i < 4; i++)
        for (int j = 0; j < 4; j++)
            r.m[i * 4 + j] = a->m[j * 4 + i];
    return r;
}

bool mr_mat4_inverse(const mr_mat4 *a, mr_mat4 *out)
{
    /* Cofactor expansion in double: 2x2 sub-determinants of the top and
     * bottom row pairs. */
    const float *m = a->m;
    double s0 = (double)m[0] * m[5] - (double)m[4] * m[1];
    double s1 = (double)m[0] * m[6] - (double)m[4] * m[2];
    double s2 = (double)m[0] * m[7] - (double)m[4] * m[3];
    double s3 = (double)m[1] * m[6] - (double)m[5] * m[2];
    double s4 = (double)m[1] * m[7] - (double)m[5] * m[3];
    double s5 = (double)m[2] * m[7] - (double)m[6] * m[3];
    double c5 = (double)m[10] * m[15] - (double)m[14] * m[11];
    double c4 = (double)m[9] * m[15] - (double)m[13] * m[11];
    double c3 = (double)m[9] * m[14] - (double)m[13] * m[10];
    double c2 = (double)m[8] * m[15] - (double)m[12] * m[11];
    double c1 = (double)m[8] * m[14] - (double)m[12] * m[10];
    double c0 = (double)m[8] * m[13] - (double)m[12] * m[9];
    double det = s0 * c5 - s1 * c4 + s2 * c3 + s3 * c2 - s4 * c1 + s5 * c0;

    /* Singularity is judged relative to the size of the entries. For affine
     * matrices (last row 0 0 0 1, the common case) det is the 3x3 linear
     * part's determinant, so translation must not enter the scale: a large
     * offset does not make a rotation any less invertible. */
    bool affine = m[12] == 0 && m[13] == 0 && m[14] == 0 && m[15] == 1;
    double scale = 0.0;
    for (int i = 0; i < 16; i++)
        if (!affine || (i < 12 && i % 4 != 3))
            scale = fmax(scale, fabs((double)m[i]));
    double bound = affine ? scale * scale * scale : scale * scale * scale * scale;
    *out = mr_mat4_identity();
    if (!isfinite(det) || scale == 0.0 || fabs(det) <= 1e-12 * bound)
        return false;
    double inv = 1.0 / det;
    double r[16];
    r[0] = (m[5] * c5 - m[6] * c4 + m[7] * c3);
    r[1] = (-m[1] * c5 + m[2] * c4 - m[3] * c3);
    r[2] = (m[13] * s5 - m[14] * s4 + m[15] * s3);
    r[3] = (-m[9] * s5 + m[10] * s4 - m[11] * s3);
    r[4] = (-m[4] * c5 + m[6] * c2 - m[7] * c1);
    r[5] = (m[0] * c5 - m[2] * c2 + m[3] * c1);
    r[6] = (-m[12] * s5 + m[14] * s2 - m[15] * s1);
    r[7] = (m[8] * s5 - m[10] * s2 + m[11] * s1);
    r[8] = (m[4] * c4 - m[5] * c2 + m[7] * c0);
    r[9] = (-m[0] * c4 + m[1] * c2 - m[3] * c0);
    r[10] = (m[12] * s4 - m[13] * s2 + m[15] * s0);
    r[11] = (-m[8] * s4 + m[9] * s2 - m[11] * s0);
    r[12] = (-m[4] * c3 + m[5] * c1 - m[6] * c0);
    r[13] = (m[0] * c3 - m[1] * c1 + m[2] * c0);
    r[14] = (-m[12] * s3 + m[13] * s1 - m[14] * s0);
    r[15] = (m[8] * s3 - m[9] * s1 + m[10] * s0);
    for (int i = 0; i < 16; i++)
        out->m[i] = (float)(r[i] * inv);
    return true;
}

mr_vec3 mr_mat4_point(const mr_mat4 *a, mr_vec3 p)
{
    const float *m = a->m;
    return mr_v3(m[0] * p.x + m[1] * p.y + m[2] * p.z + m[3],
                 m[4] * p.x + m[5] * p.y + m[6] * p.z + m[7],
                 m[8] * p.x + m[9] * p.y + m[10] * p.z + m[11]);
}

mr_mat4 mr_mat4_normal_matrix(const mr_mat4 *a)
{
    /* Cofactor matrix of the 3x3 linear part = det * inverse transpose. Its
     * rows are cross products of the columns' partners, which stays well
     * defined when the matrix is singular. */
    const float *m = a->m;
    mr_vec3 c0 = mr_v3(m[0], m[4], m[8]);
    mr_vec3 c1 = mr_v3(m[1], m[5], m[9]);
    mr_vec3 c2 = mr_v3(m[2], m[6], m[10]);
    mr_vec3 r0 = mr_v3_cross(c1, c2), r1 = mr_v3_cross(c2, c0), r2 = mr_v3_cross(c0, c1);
    /* cofactor(A) has columns r0, r1, r2 (as column vectors of A^-T * det). */
    mr_mat4 n = mr_mat4_identity();
    n.m[0] = r0.x; n.m[1] = r1.x; n.m[2] = r2.x;
    n.m[4] = r0.y; n.m[5] = r1.y; n.m[6] = r2.y;
    n.m[8] = r0.z; n.m[9] = r1.z; n.m[10] = r2.z;
    return n;
}

static void quat_to_rows(mr_quat q, float r[9])
{
    float xx = q.x * q.x, yy = q.y * q.y, zz = q.z * q.z;
    float xy = q.x * q.y, xz = q.x * q.z, yz = q.y * q.z;
    float wx = q.w * q.x, wy = q.w * q.y, wz = q.w * q.z;
    r[0] = 1 - 2 * (yy + zz); r[1] = 2 * (xy - wz);     r[2] = 2 * (xz + wy);
    r[3] = 2 * (xy + wz);     r[4] = 1 - 2 * (xx + zz); r[5] = 2 * (yz - wx);
    r[6] = 2 * (xz - wy);     r[7] = 2 * (yz + wx);     r[8] = 1 - 2 * (xx + yy);
}

mr_mat4 mr_mat4_from_trs(mr_vec3 t, mr_quat r, mr_vec3 s)
{
    float rot[9];
    quat_to_rows(mr_quat_normalize(r), rot);
    mr_mat4 o = mr_mat4_identity();
    for (int i = 0; i < 3; i++) {
        o.m[i * 4 + 0] = rot[i * 3 + 0] * s.x;
        o.m[i * 4 + 1] = rot[i * 3 + 1] * s.y;
        o.m[i * 4 + 2] = rot[i * 3 + 2] * s.z;
    }
    o.m[3] = t.x; o.m[7] = t.y; o.m[11] = t.z;
    return o;
}

bool mr_mat4_to_trs(const mr_mat4 *a, mr_vec3 *t, mr_quat *r, mr_vec3 *s)
{
    const float *m = a->m;
    *t = mr_v3(m[3], m[7], m[11]);
    mr_vec3 c0 = mr_v3(m[0], m[4], m[8]), c1 = mr_v3(m[1], m[5], m[9]), c2 = mr_v3(m[2], m[6], m[10]);
    mr_vec3 sc = mr_v3(mr_v3_len(c0), mr_v3_len(c1), mr_v3_len(c2));
    *r = mr_quat_identity();
    *s = sc;
    if (!(sc.x > 0 && sc.y > 0 && sc.z > 0))
        return false;
    /* A mirrored matrix has a negative determinant: put the sign on x. */
    if (mr_v3_dot(mr_v3_cross(c0, c1), c2) < 0) {
        sc.x = -sc.x;
        *s = sc;
    }
    mr_mat4 rot = mr_mat4_identity();
    c0 = mr_v3_scale(c0, 1.0f / sc.x);
    c1 = mr_v3_scale(c1, 1.0f / sc.y);
    c2 = mr_v3_scale(c2, 1.0f / sc.z);
    rot.m[0] = c0.x; rot.m[4] = c0.y; rot.m[8] = c0.z;
    rot.m[1] = c1.x; rot.m[5] = c1.y; rot.m[9] = c1.z;
    rot.m[2] = c2.x; rot.m[6] = c2.y; rot.m[10] = c2.z;
    *r = mr_quat_from_mat4(&rot);
    return true;
}

bool mr_mat4_is_finite(const mr_mat4 *a)
{
    for (int i = 0; i < 16; i++)
        if (!isfinite(a->m[i]))
            return false;
    return true;
}

mr_quat mr_quat_identity(void) { return (mr_quat){0, 0, 0, 1}; }

mr_quat mr_quat_normalize(mr_quat q)
{
    float n = sqrtf(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w);
    if (!(n > 0.0f) || !isfinite(n))
        return mr_quat_identity();
    return (mr_quat){q.x / n, q.y / n, q.z / n, q.w / n};
}

mr_quat mr_quat_mul(mr_quat a, mr_quat b)
{
    return (mr_quat){
        a.w * b.x + a.x * b.w + a.y * b.z - a.z * b.y,
        a.w * b.y - a.x * b.z + a.y * b.w + a.z * b.x,
        a.w * b.z + a.x * b.y - a.y * b.x + a.z * b.w,
        a.w * b.w - a.x * b.x - a.y * b.y - a.z * b.z,
    };
}

mr_quat mr_quat_from_axis_angle(mr_vec3 axis, float radians)
{
    mr_vec3 n = mr_v3_normalize_or(axis, mr_v3(0, 0, 1));
    float s = sinf(radians * 0.5f);
    return (mr_quat){n.x * s, n.y * s, n.z * s, cosf(radians * 0.5f)};
}

mr_vec3 mr_quat_rotate(mr_quat q, mr_vec3 v)
{
    /* v' = v + 2w (u x v) + 2 u x (u x v), u = vector part. */
    mr_vec3 u = mr_v3(q.x, q.y, q.z);
    mr_vec3 t = mr_v3_scale(mr_v3_cross(u, v), 2.0f);
    return mr_v3_add(mr_v3_add(v, mr_v3_scale(t, q.w)), mr_v3_cross(u, t));
}

mr_quat mr_quat_slerp(mr_quat a, mr_quat b, float t)
{
    double d = (double)a.x * b.x + (double)a.y * b.y + (double)a.z * b.z + (double)a.w * b.w;
    if (d < 0) { /* q and -q are the same rotation: take the short way */
        b = (mr_quat){-b.x, -b.y, -b.z, -b.w};
        d = -d;
    }
    double wa, wb;
    if (d > 0.9999995) { /* angle below ~1e-3 rad: lerp is exact to float precision */
        wa = 1.0 - t;
        wb = t;
    } else {
        double theta = acos(d > 1.0 ? 1.0 : d);
        double s = sin(theta);
        wa = sin((1.0 - t) * theta) / s;
        wb = sin(t * theta) / s;
    }
    mr_quat r = {(float)(wa * a.x + wb * b.x), (float)(wa * a.y + wb * b.y),
                 (float)(wa * a.z + wb * b.z), (float)(wa * a.w + wb * b.w)};
    return mr_quat_normalize(r);
}

mr_quat mr_quat_from_mat4(const mr_mat4 *mat)
{
    const float *m = mat->m;
    float m00 = m[0], m01 = m[1], m02 = m[2];
    float m10 = m[4], m11 = m[5], m12 = m[6];
    float m20 = m[8], m21 = m[9], m22 = m[10];
    float tr = m00 + m11 + m22;
    mr_quat q;
    if (tr > 0) {
        float s = sqrtf(tr + 1.0f) * 2.0f;
        q = (mr_quat){(m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25f * s};
    } else if (m00 > m11 && m00 > m22) {
        float s = sqrtf(1.0f + m00 - m11 - m22) * 2.0f;
        q = (mr_quat){0.25f * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s};
    } else if (m11 > m22) {
        float s = sqrtf(1.0f + m11 - m00 - m22) * 2.0f;
        q = (mr_quat){(m01 + m10) / s, 0.25f * s, (m12 + m21) / s, (m02 - m20) / s};
    } else {
        float s = sqrtf(1.0f + m22 - m00 - m11) * 2.0f;
        q = (mr_quat){(m02 + m20) / s, (m12 + m21) / s, 0.25f * s, (m10 - m01) / s};
    }
    return mr_quat_normalize(q);
}

mr_quat mr_quat_look_rotation(mr_vec3 forward, mr_vec3 up)
{
    mr_vec3 f = mr_v3_normalize_or(forward, mr_v3(0, 0, -1));
    mr_vec3 z = mr_v3_scale(f, -1.0f); /* the camera looks down -Z */
    mr_vec3 x = mr_v3_cross(up, z);
    if (mr_v3_len(x) < 1e-6f * (mr_v3_len(up) + 1e-30f)) {
        /* forward parallel to up: any perpendicular up will do */
        mr_vec3 alt = fabsf(z.y) < 0.9f ? mr_v3(0, 1, 0) : mr_v3(1, 0, 0);
        x = mr_v3_cross(alt, z);
    }
    x = mr_v3_normalize_or(x, mr_v3(1, 0, 0));
    mr_vec3 y = mr_v3_cross(z, x);
    mr_mat4 r = mr_mat4_identity();
    r.m[0] = x.x; r.m[4] = x.y; r.m[8] = x.z;
    r.m[1] = y.x; r.m[5] = y.y; r.m[9] = y.z;
    r.m[2] = z.x; r.m[6] = z.y; r.m[10] = z.z;
    return mr_quat_from_mat4(&r);
}

mr_vec3 mr_catmull_rom(mr_vec3 p0, mr_vec3 p1, mr_vec3 p2, mr_vec3 p3, float t)
{
    float t2 = t * t, t3 = t2 * t;
    float w0 = -0.5f * t3 + t2 - 0.5f * t;
    float w1 = 1.5f * t3 - 2.5f * t2 + 1.0f;
    float w2 = -1.5f * t3 + 2.0f * t2 + 0.5f * t;
    float w3 = 0.5f * t3 - 0.5f * t2;
    return mr_v3(w0 * p0.x + w1 * p1.x + w2 * p2.x + w3 * p3.x,
                 w0 * p0.y + w1 * p1.y + w2 * p2.y + w3 * p3.y,
                 w0 * p0.z + w1 * p1.z + w2 * p2.z + w3 * p3.z);
}

bool mr_normalize_d(double *d, size_t n)
{
    double m = 0, l = 0;
    for (size_t i = 0; i < n; i++)
        m = fmax(m, fabs(d[i]));
    if (!(m > 0))
        return false;
    for (size_t i = 0; i < n; i++) {
        d[i] /= m;
        l += d[i] * d[i];
    }
    l = sqrt(l);
    for (size_t i = 0; i < n; i++)
        d[i] /= l;
    return true;
}
