/*
 * mr_math.h - small vector, matrix and quaternion arithmetic.
 *
 * The value types (mr_vec3, mr_quat, mr_mat4), their conventions (row-major
 * matrices on column vectors, (x, y, z, w) quaternions, right-to-left
 * composition) and the functions a job parser needs are public:
 * microray.h. This is the rest of the arithmetic core uses.
 */
#ifndef MR_MATH_H
#define MR_MATH_H

#include <math.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include "microray.h"

#if defined(__SSE2__)
#include <xmmintrin.h>
#endif

/* The top three rows of a row-major affine mr_mat4 (the bottom row is
 * 0 0 0 1): m[4r + c]. */
typedef struct mr_affine { float m[12]; } mr_affine;

/* v rounded to a float towards -inf (mr_float_down) or +inf (mr_float_up):
 * the bound a float box needs to hold a double one. The nearest float,
 * moved one step when it lies on the wrong side of v; the step is on the
 * bit pattern (adjacent floats of one sign are adjacent integers, the sign
 * says whether "down" is up in magnitude), without a branch: in a loop over
 * boxes the side is a coin toss a branch would mispredict. -0 and +0 step
 * to -/+ FLT_TRUE_MIN, an infinity that overshoots to +/-FLT_MAX, NaN stays
 * NaN. */
static inline float mr_float_down(double v)
{
    float f = (float)v;
    uint32_t b;
    memcpy(&b, &f, sizeof b);
    const uint32_t step = (double)f > v, negative = b >> 31;
    b += step * (2u * negative - 1u); /* modulo 2^32: -1 for a positive f */
    memcpy(&f, &b, sizeof f);
    return f;
}

static inline float mr_float_up(double v)
{
    float f = (float)v;
    uint32_t b;
    memcpy(&b, &f, sizeof b);
    const uint32_t step = (double)f < v, negative = b >> 31;
    b += step * (1u - 2u * negative);
    memcpy(&f, &b, sizeof f);
    return f;
}

/* splitmix64's finaliser: every input bit reaches every output bit; cheap
 * and stateless (per-pixel jitter, procedural lattice offsets, cache set
 * indices). */
static inline uint64_t mr_mix64(uint64_t z)
{
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
}

/* floor(x) for finite |x| < 2^63 without a call into libm (which the
 * baseline x86-64 target makes of floor): the same value, but that -0
 * gives +0. */
static inline double mr_floor_small(double x)
{
    const double t = (double)(int64_t)x;
    return t > x ? t - 1 : t;
}

/* Bits set in v (SWAR: the build flags have no -mpopcnt, and
 * __builtin_popcount is a call into libgcc there, which the hot loops of
 * the renderer and the displaced kind paid at every packet). */
static inline unsigned mr_popcount32(uint32_t v)
{
    v = v - ((v >> 1) & 0x55555555u);
    v = (v & 0x33333333u) + ((v >> 2) & 0x33333333u);
    return (((v + (v >> 4)) & 0x0f0f0f0fu) * 0x01010101u) >> 24;
}

/* a / b rounded down (towards -infinity), b != 0. */
static inline int64_t mr_floor_div(int64_t a, int64_t b)
{
    const int64_t q = a / b;
    return (a % b != 0 && ((a < 0) != (b < 0))) ? q - 1 : q;
}

static inline mr_vec3 mr_v3_add(mr_vec3 a, mr_vec3 b) { return mr_v3(a.x + b.x, a.y + b.y, a.z + b.z); }
static inline mr_vec3 mr_v3_sub(mr_vec3 a, mr_vec3 b) { return mr_v3(a.x - b.x, a.y - b.y, a.z - b.z); }
static inline mr_vec3 mr_v3_scale(mr_vec3 a, float s) { return mr_v3(a.x * s, a.y * s, a.z * s); }
static inline mr_vec3 mr_v3_mul(mr_vec3 a, mr_vec3 b) { return mr_v3(a.x * b.x, a.y * b.y, a.z * b.z); }
static inline float mr_v3_dot(mr_vec3 a, mr_vec3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
/* The same of two double triples, in the same order. */
static inline double mr_dot3d(const double a[3], const double b[3])
{
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}
static inline mr_vec3 mr_v3_cross(mr_vec3 a, mr_vec3 b)
{
    return mr_v3(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x);
}
static inline float mr_v3_len(mr_vec3 a) { return sqrtf(mr_v3_dot(a, a)); }
static inline mr_vec3 mr_v3_lerp(mr_vec3 a, mr_vec3 b, float t)
{
    return mr_v3(a.x + (b.x - a.x) * t, a.y + (b.y - a.y) * t, a.z + (b.z - a.z) * t);
}

/* The vector (*x, *y, *z) from three separate floats (a structure of
 * arrays). x and y are put together in a register and stored as one
 * 8-byte piece: passed on by value, a vector is read as one 8-byte load,
 * which the store buffer cannot forward from two 4-byte stores (perf put a
 * sixth of the displaced callbacks' set-up on that). */
static inline mr_vec3 mr_v3_gather(const float *x, const float *y, const float *z)
{
#if defined(__SSE2__)
    const __m128 xy = _mm_unpacklo_ps(_mm_load_ss(x), _mm_load_ss(y));
    mr_vec3 v;
    _mm_storel_pi((__m64 *)&v, xy);
    v.z = *z;
    return v;
#else
    return mr_v3(*x, *y, *z);
#endif
}

/* A direction a ray can have: not zero, every component finite. */
static inline bool mr_v3_is_dir(mr_vec3 d)
{
    return (d.x != 0 || d.y != 0 || d.z != 0) && isfinite(d.x) && isfinite(d.y) && isfinite(d.z);
}

static inline mr_vec3 mr_v3_min(mr_vec3 a, mr_vec3 b) { return mr_v3(fminf(a.x, b.x), fminf(a.y, b.y), fminf(a.z, b.z)); }
static inline mr_vec3 mr_v3_max(mr_vec3 a, mr_vec3 b) { return mr_v3(fmaxf(a.x, b.x), fmaxf(a.y, b.y), fmaxf(a.z, b.z)); }

/* Unit vector along a; returns fallback when |a| is zero or not finite.
 * (Inline, like mr_mat4_dir: skinning calls both for every vertex.) */
static inline mr_vec3 mr_v3_normalize_or(mr_vec3 a, mr_vec3 fallback)
{
    float len = mr_v3_len(a);
    if (!(len > 0.0f) || !isfinite(len))
        return fallback;
    return mr_v3_scale(a, 1.0f / len);
}
/* A unit vector orthogonal to the unit vector n: n crossed with the
 * coordinate axis least aligned with it (a fixed choice, so the same n
 * gives the same bits). */
mr_vec3 mr_v3_any_orthogonal(mr_vec3 n);

/* A tangent made to fit a unit normal n: t's part orthogonal to n,
 * normalised (Gram-Schmidt; taken twice where t was within 60 degrees of
 * n's direction, so the result is orthogonal to n to rounding however
 * close t was). Where that part is lost (t zero or not finite, or within
 * MR_TANGENT_PARALLEL of n's direction): when any_if_lost,
 * mr_v3_any_orthogonal(n); else (0, 0, 0). Inline: the per-vertex work
 * of every tangent carried (skinning, the spring-mass mappings). */
#define MR_TANGENT_PARALLEL 1e-3f /* |t's part across n| / |t|: 0.06 degrees */
static inline mr_vec3 mr_v3_tangent_to(mr_vec3 t, mr_vec3 n, bool any_if_lost)
{
    float len2 = mr_v3_dot(t, t);
    mr_vec3 across = mr_v3_sub(t, mr_v3_scale(n, mr_v3_dot(n, t)));
    float across2 = mr_v3_dot(across, across);
    if (!(across2 > MR_TANGENT_PARALLEL * MR_TANGENT_PARALLEL * len2) || !(len2 <= 3.4e38f))
        return any_if_lost ? mr_v3_any_orthogonal(n) : mr_v3(0, 0, 0);
    if (across2 < 0.25f * len2) {
        /* the rounding of a short difference leaves part of n in it, which
         * a second step takes out ("twice is enough") */
        across = mr_v3_scale(across, 1.0f / sqrtf(across2));
        across = mr_v3_sub(across, mr_v3_scale(n, mr_v3_dot(n, across)));
        across2 = mr_v3_dot(across, across);
    }
    return mr_v3_scale(across, 1.0f / sqrtf(across2));
}

mr_mat4 mr_mat4_mul(const mr_mat4 *a, const mr_mat4 *b);
mr_mat4 mr_mat4_transpose(const mr_mat4 *a);
/* w = 0 */
static inline mr_vec3 mr_mat4_dir(const mr_mat4 *a, mr_vec3 d)
{
    const float *m = a->m;
    return mr_v3(m[0] * d.x + m[1] * d.y + m[2] * d.z, m[4] * d.x + m[5] * d.y + m[6] * d.z,
                 m[8] * d.x + m[9] * d.y + m[10] * d.z);
}
/* Matrix that maps normals for transform a: inverse transpose of its linear
 * part, scaled by |det| so it also works for singular-ish skinning blends
 * (the cofactor matrix). Only the upper 3x3 is meaningful. Callers normalise. */
mr_mat4 mr_mat4_normal_matrix(const mr_mat4 *a);
/* Inverse of from_trs for matrices without shear. Returns false when the
 * matrix has a zero scale axis. */
bool mr_mat4_to_trs(const mr_mat4 *a, mr_vec3 *t, mr_quat *r, mr_vec3 *s);

mr_quat mr_quat_normalize(mr_quat q);            /* identity for |q| = 0 */
mr_quat mr_quat_mul(mr_quat a, mr_quat b);       /* applies b first */
mr_quat mr_quat_from_axis_angle(mr_vec3 axis, float radians);
mr_vec3 mr_quat_rotate(mr_quat q, mr_vec3 v);
/* Shortest-path spherical interpolation; falls back to normalised lerp when
 * the two rotations are within ~1e-3 rad, where slerp's 1/sin(theta) loses
 * precision. t outside [0,1] extrapolates. */
mr_quat mr_quat_slerp(mr_quat a, mr_quat b, float t);
/* Rotation part of an orthonormal 3x3 (upper-left of m), Shepperd's method. */
mr_quat mr_quat_from_mat4(const mr_mat4 *m);
/* Camera orientation looking from eye along forward with the given up:
 * the rotation maps -Z to forward and +Y to (the orthogonalised) up.
 * Falls back to another up when forward and up are parallel. */
mr_quat mr_quat_look_rotation(mr_vec3 forward, mr_vec3 up);

/* Catmull-Rom (uniform) through p1..p2 with neighbours p0 and p3, t in [0,1]. */
mr_vec3 mr_catmull_rom(mr_vec3 p0, mr_vec3 p1, mr_vec3 p2, mr_vec3 p3, float t);

#endif /* MR_MATH_H */
