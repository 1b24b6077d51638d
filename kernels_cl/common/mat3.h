/* 3x3 matrix helpers on private row-major arrays: m[3*r + c].
 *
 * Small, inline and allocation-free so constitutive models read like their equations.
 * Defined for `real` (mat3_mul, ...) and, when a kernel defines CLFLOW_SIMD_LANES, for
 * `realv` (common/lanes.h) holding one matrix entry of several particles (mat3_mul_v, ...):
 * explicit SIMD that CPU compilers do not find on their own in loop-heavy code such as the
 * SVD. */
#ifndef CLFLOW_MAT3_H
#define CLFLOW_MAT3_H

#include "common/lanes.h"

/* The helpers for element type T, names suffixed with SFX. */
#define CLFLOW_DEFINE_MAT3(SFX, T)                                                                                     \
    inline void mat3_identity##SFX(T *a)                                                                               \
    {                                                                                                                  \
        for (int k = 0; k < 9; ++k)                                                                                    \
            a[k] = (k % 4 == 0) ? (T)1 : (T)0;                                                                         \
    }                                                                                                                  \
                                                                                                                       \
    inline void mat3_copy##SFX(const T *a, T *out)                                                                     \
    {                                                                                                                  \
        for (int k = 0; k < 9; ++k)                                                                                    \
            out[k] = a[k];                                                                                             \
    }                                                                                                                  \
                                                                                                                       \
    /* out = a b (out must not alias a or b) */                                                                        \
    inline void mat3_mul##SFX(const T *a, const T *b, T *out)                                                          \
    {                                                                                                                  \
        for (int r = 0; r < 3; ++r)                                                                                    \
            for (int c = 0; c < 3; ++c)                                                                                \
                out[3 * r + c] = a[3 * r] * b[c] + a[3 * r + 1] * b[3 + c] + a[3 * r + 2] * b[6 + c];                  \
    }                                                                                                                  \
                                                                                                                       \
    /* out = a b^T */                                                                                                  \
    inline void mat3_mul_bt##SFX(const T *a, const T *b, T *out)                                                       \
    {                                                                                                                  \
        for (int r = 0; r < 3; ++r)                                                                                    \
            for (int c = 0; c < 3; ++c)                                                                                \
                out[3 * r + c] = a[3 * r] * b[3 * c] + a[3 * r + 1] * b[3 * c + 1] + a[3 * r + 2] * b[3 * c + 2];      \
    }                                                                                                                  \
                                                                                                                       \
    /* out = u diag(d) v^T: the composition every SVD-based model ends with */                                         \
    inline void mat3_udvt##SFX(const T *u, const T *d, const T *v, T *out)                                             \
    {                                                                                                                  \
        for (int r = 0; r < 3; ++r)                                                                                    \
            for (int c = 0; c < 3; ++c)                                                                                \
                out[3 * r + c] = u[3 * r] * d[0] * v[3 * c] + u[3 * r + 1] * d[1] * v[3 * c + 1] +                     \
                                 u[3 * r + 2] * d[2] * v[3 * c + 2];                                                   \
    }                                                                                                                  \
                                                                                                                       \
    inline T mat3_det##SFX(const T *a)                                                                                 \
    {                                                                                                                  \
        return a[0] * (a[4] * a[8] - a[5] * a[7]) - a[1] * (a[3] * a[8] - a[5] * a[6]) +                               \
               a[2] * (a[3] * a[7] - a[4] * a[6]);                                                                     \
    }                                                                                                                  \
                                                                                                                       \
    /* out = a^T b */                                                                                                  \
    inline void mat3_mul_at##SFX(const T *a, const T *b, T *out)                                                       \
    {                                                                                                                  \
        for (int r = 0; r < 3; ++r)                                                                                    \
            for (int c = 0; c < 3; ++c)                                                                                \
                out[3 * r + c] = a[r] * b[c] + a[3 + r] * b[3 + c] + a[6 + r] * b[6 + c];                              \
    }                                                                                                                  \
                                                                                                                       \
    inline T trace3##SFX(const T *a)                                                                                   \
    {                                                                                                                  \
        return a[0] + a[4] + a[8];                                                                                     \
    }                                                                                                                  \
                                                                                                                       \
    /* Cofactor matrix of a: d det(a)/d a, finite for singular a. */                                                   \
    inline void mat3_cofactor##SFX(const T *a, T *out)                                                                 \
    {                                                                                                                  \
        out[0] = a[4] * a[8] - a[5] * a[7];                                                                            \
        out[1] = a[5] * a[6] - a[3] * a[8];                                                                            \
        out[2] = a[3] * a[7] - a[4] * a[6];                                                                            \
        out[3] = a[2] * a[7] - a[1] * a[8];                                                                            \
        out[4] = a[0] * a[8] - a[2] * a[6];                                                                            \
        out[5] = a[1] * a[6] - a[0] * a[7];                                                                            \
        out[6] = a[1] * a[5] - a[2] * a[4];                                                                            \
        out[7] = a[2] * a[3] - a[0] * a[5];                                                                            \
        out[8] = a[0] * a[4] - a[1] * a[3];                                                                            \
    }

CLFLOW_DEFINE_MAT3(, real)
#ifdef CLFLOW_SIMD_LANES
CLFLOW_DEFINE_MAT3(_v, realv)
#endif

#endif /* CLFLOW_MAT3_H */
