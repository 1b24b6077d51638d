/* 3x3 matrix helpers on private row-major arrays: m[3*r + c].
 *
 * Small, inline and allocation-free so constitutive models read like their equations. */
#ifndef CLFLOW_MAT3_H
#define CLFLOW_MAT3_H

#include "common/real.h"

inline void mat3_identity(real *a)
{
    for (int k = 0; k < 9; ++k)
        a[k] = (k % 4 == 0) ? (real)1 : (real)0;
}

inline void mat3_copy(const real *a, real *out)
{
    for (int k = 0; k < 9; ++k)
        out[k] = a[k];
}

/* out = a b (out must not alias a or b) */
inline void mat3_mul(const real *a, const real *b, real *out)
{
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            out[3 * r + c] = a[3 * r] * b[c] + a[3 * r + 1] * b[3 + c] + a[3 * r + 2] * b[6 + c];
}

/* out = a b^T */
inline void mat3_mul_bt(const real *a, const real *b, real *out)
{
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            out[3 * r + c] = a[3 * r] * b[3 * c] + a[3 * r + 1] * b[3 * c + 1] + a[3 * r + 2] * b[3 * c + 2];
}

/* out = u diag(d) v^T: the composition every SVD-based model ends with */
inline void mat3_udvt(const real *u, const real *d, const real *v, real *out)
{
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            out[3 * r + c] = u[3 * r] * d[0] * v[3 * c] + u[3 * r + 1] * d[1] * v[3 * c + 1] +
                             u[3 * r + 2] * d[2] * v[3 * c + 2];
}

inline real mat3_det(const real *a)
{
    return a[0] * (a[4] * a[8] - a[5] * a[7]) - a[1] * (a[3] * a[8] - a[5] * a[6]) +
           a[2] * (a[3] * a[7] - a[4] * a[6]);
}

inline real mat3_trace(const real *a)
{
    return a[0] + a[4] + a[8];
}

#endif /* CLFLOW_MAT3_H */
