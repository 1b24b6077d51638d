/* Robust 3x3 SVD: F = U diag(s) V^T with U, V proper rotations (det +1) and
 * s0 >= s1 >= |s2|; s2 < 0 exactly when det F < 0 (an inverted element), the "signed"
 * convention of graphics MPM codes, so rotations never pick up reflections.
 *
 * Method:
 *   1. one-sided (Hestenes) Jacobi: rotate the columns of B = F V (V a product of
 *      rotations) until they are mutually orthogonal to working precision, each pair judged
 *      relative to its own norms, so tiny singular values stay accurate (working on F's
 *      columns, never on F^T F, does not square the condition number);
 *   2. sort the columns by norm (a swap is paired with a sign flip: det V stays +1);
 *   3. Givens QR of B = U R -> U (a product of rotations), s = diag(R); R's diagonal carries
 *      the sign of det F in its last entry.
 *
 * svd3 works on `real`; with CLFLOW_SIMD_LANES (see mat3.h) svd3_v works on `realv`, one
 * matrix per lane (data-dependent choices are select()s; the sweeps stop when every lane
 * has converged). */
#ifndef CLFLOW_SVD3_H
#define CLFLOW_SVD3_H

#include "common/mat3.h"

#if REAL_IS_DOUBLE
#define SVD3_EPS      DBL_EPSILON
#define SVD3_SQRT_EPS 1.4901161193847656e-08 /* sqrt(DBL_EPSILON) */
#else
#define SVD3_EPS      FLT_EPSILON
#define SVD3_SQRT_EPS 3.4526698e-04f /* sqrt(FLT_EPSILON) */
#endif
#define SVD3_MAX_SWEEPS             16
#define SVD3_SCALAR_ALL(x)          (x)
#define SVD3_SCALAR_SELECT(a, b, c) ((c) ? (b) : (a)) /* select() of scalars wants a long mask for double */

/* The SVD for element type T, names suffixed with SFX; ALL reduces a comparison to "every
 * lane", SEL(a, b, c) is c ? b : a per lane. */
#define CLFLOW_DEFINE_SVD3(SFX, T, ALL, SEL)                                                                           \
    /* Rotate columns p, q of b (and of v) to make them orthogonal; returns |tan| of the rotation          \
 * angle (0 where they already are orthogonal to working precision). */           \
    inline T svd3_orthogonalize##SFX(T *b, T *v, const int p, const int q)                                             \
    {                                                                                                                  \
        T alpha = 0, beta = 0, gamma = 0;                                                                              \
        for (int k = 0; k < 3; ++k) {                                                                                  \
            alpha += b[3 * k + p] * b[3 * k + p];                                                                      \
            beta += b[3 * k + q] * b[3 * k + q];                                                                       \
            gamma += b[3 * k + p] * b[3 * k + q];                                                                      \
        }                                                                                                              \
        const T zeta = (beta - alpha) / (2 * gamma);                                                                   \
        T t = SEL((T)-1, (T)1, zeta >= 0) / (fabs(zeta) + sqrt(1 + zeta * zeta));                                      \
        t = SEL((T)0, t, gamma * gamma > SVD3_EPS * SVD3_EPS * alpha * beta);                                          \
        const T c = 1 / sqrt(1 + t * t), s = t * c;                                                                    \
        for (int k = 0; k < 3; ++k) {                                                                                  \
            const T bp = b[3 * k + p], bq = b[3 * k + q];                                                              \
            b[3 * k + p] = c * bp - s * bq;                                                                            \
            b[3 * k + q] = s * bp + c * bq;                                                                            \
            const T vp = v[3 * k + p], vq = v[3 * k + q];                                                              \
            v[3 * k + p] = c * vp - s * vq;                                                                            \
            v[3 * k + q] = s * vp + c * vq;                                                                            \
        }                                                                                                              \
        return fabs(t);                                                                                                \
    }                                                                                                                  \
                                                                                                                       \
    /* Put the longer of columns i, j of b first: swap them in b and v, negating one (det v stays +1). */              \
    inline void svd3_sort_pair##SFX(T *b, T *v, const int i, const int j)                                              \
    {                                                                                                                  \
        T ni = 0, nj = 0;                                                                                              \
        for (int k = 0; k < 3; ++k) {                                                                                  \
            ni += b[3 * k + i] * b[3 * k + i];                                                                         \
            nj += b[3 * k + j] * b[3 * k + j];                                                                         \
        }                                                                                                              \
        for (int k = 0; k < 3; ++k) {                                                                                  \
            const T bi = b[3 * k + i], bj = b[3 * k + j], vi = v[3 * k + i], vj = v[3 * k + j];                        \
            b[3 * k + i] = SEL(bi, bj, ni < nj);                                                                       \
            b[3 * k + j] = SEL(bj, -bi, ni < nj);                                                                      \
            v[3 * k + i] = SEL(vi, vj, ni < nj);                                                                       \
            v[3 * k + j] = SEL(vj, -vi, ni < nj);                                                                      \
        }                                                                                                              \
    }                                                                                                                  \
                                                                                                                       \
    /* Zero b[j][i] (j > i) with a Givens rotation G of rows i, j: b <- G b, q <- q G^T.                   \
 * |F| << 1e19, so sqrt(x^2 + y^2) needs no overflow guard (Sleef's hypot is slow). */           \
    inline void svd3_givens##SFX(T *b, T *q, const int i, const int j)                                                 \
    {                                                                                                                  \
        const T x = b[3 * i + i], y = b[3 * j + i];                                                                    \
        const T rho = sqrt(x * x + y * y);                                                                             \
        const T c = SEL((T)1, x / rho, rho > 0), s = SEL((T)0, y / rho, rho > 0);                                      \
        for (int k = 0; k < 3; ++k) {                                                                                  \
            const T bi = b[3 * i + k], bj = b[3 * j + k];                                                              \
            b[3 * i + k] = c * bi + s * bj;                                                                            \
            b[3 * j + k] = -s * bi + c * bj;                                                                           \
            const T qi = q[3 * k + i], qj = q[3 * k + j];                                                              \
            q[3 * k + i] = c * qi + s * qj;                                                                            \
            q[3 * k + j] = -s * qi + c * qj;                                                                           \
        }                                                                                                              \
    }                                                                                                                  \
                                                                                                                       \
    inline void svd3##SFX(const T *F, T *U, T *s, T *V)                                                                \
    {                                                                                                                  \
        T b[9];                                                                                                        \
        mat3_copy##SFX(F, b);                                                                                          \
        mat3_identity##SFX(V);                                                                                         \
        /* Jacobi converges quadratically: once a sweep only needed rotations of angle below               \
     * sqrt(eps), what they left off the diagonal is O(angle^2) <= eps: no further sweep. */           \
        for (int sweep = 0; sweep < SVD3_MAX_SWEEPS; ++sweep) {                                                        \
            const T t01 = svd3_orthogonalize##SFX(b, V, 0, 1);                                                         \
            const T t02 = svd3_orthogonalize##SFX(b, V, 0, 2);                                                         \
            const T t12 = svd3_orthogonalize##SFX(b, V, 1, 2);                                                         \
            if (ALL(fmax(t01, fmax(t02, t12)) <= SVD3_SQRT_EPS))                                                       \
                break;                                                                                                 \
        }                                                                                                              \
        svd3_sort_pair##SFX(b, V, 0, 1);                                                                               \
        svd3_sort_pair##SFX(b, V, 0, 2);                                                                               \
        svd3_sort_pair##SFX(b, V, 1, 2);                                                                               \
        mat3_identity##SFX(U);                                                                                         \
        svd3_givens##SFX(b, U, 0, 1);                                                                                  \
        svd3_givens##SFX(b, U, 0, 2);                                                                                  \
        svd3_givens##SFX(b, U, 1, 2);                                                                                  \
        s[0] = b[0];                                                                                                   \
        s[1] = b[4];                                                                                                   \
        s[2] = b[8];                                                                                                   \
    }

CLFLOW_DEFINE_SVD3(, real, SVD3_SCALAR_ALL, SVD3_SCALAR_SELECT)
#ifdef CLFLOW_SIMD_LANES
CLFLOW_DEFINE_SVD3(_v, realv, all, select)
#endif

#endif /* CLFLOW_SVD3_H */
