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
 *      the sign of det F in its last entry. */
#ifndef CLFLOW_SVD3_H
#define CLFLOW_SVD3_H

#include "common/mat3.h"

#if REAL_IS_DOUBLE
#define SVD3_EPS DBL_EPSILON
#else
#define SVD3_EPS FLT_EPSILON
#endif
#define SVD3_MAX_SWEEPS 16

/* Rotate columns p, q of b (and of v) to make them orthogonal. Returns 0 if they already are. */
inline int svd3_orthogonalize(real *b, real *v, const int p, const int q)
{
    real alpha = 0, beta = 0, gamma = 0;
    for (int k = 0; k < 3; ++k) {
        alpha += b[3 * k + p] * b[3 * k + p];
        beta += b[3 * k + q] * b[3 * k + q];
        gamma += b[3 * k + p] * b[3 * k + q];
    }
    if (fabs(gamma) <= SVD3_EPS * sqrt(alpha * beta))
        return 0;
    const real zeta = (beta - alpha) / (2 * gamma);
    const real t = (zeta >= 0 ? (real)1 : (real)-1) / (fabs(zeta) + sqrt(1 + zeta * zeta));
    const real c = 1 / sqrt(1 + t * t), s = t * c;
    for (int k = 0; k < 3; ++k) {
        const real bp = b[3 * k + p], bq = b[3 * k + q];
        b[3 * k + p] = c * bp - s * bq;
        b[3 * k + q] = s * bp + c * bq;
        const real vp = v[3 * k + p], vq = v[3 * k + q];
        v[3 * k + p] = c * vp - s * vq;
        v[3 * k + q] = s * vp + c * vq;
    }
    return 1;
}

/* Put the longer of columns i, j of b first: swap them in b and v, negating one (det v stays +1). */
inline void svd3_sort_pair(real *b, real *v, const int i, const int j)
{
    real ni = 0, nj = 0;
    for (int k = 0; k < 3; ++k) {
        ni += b[3 * k + i] * b[3 * k + i];
        nj += b[3 * k + j] * b[3 * k + j];
    }
    if (ni >= nj)
        return;
    for (int k = 0; k < 3; ++k) {
        const real bi = b[3 * k + i], vi = v[3 * k + i];
        b[3 * k + i] = b[3 * k + j];
        b[3 * k + j] = -bi;
        v[3 * k + i] = v[3 * k + j];
        v[3 * k + j] = -vi;
    }
}

/* Zero b[j][i] (j > i) with a Givens rotation G of rows i, j: b <- G b, q <- q G^T. */
inline void svd3_givens(real *b, real *q, const int i, const int j)
{
    const real x = b[3 * i + i], y = b[3 * j + i];
    const real rho = sqrt(x * x + y * y);
    if (rho == (real)0)
        return;
    const real c = x / rho, s = y / rho;
    for (int k = 0; k < 3; ++k) {
        const real bi = b[3 * i + k], bj = b[3 * j + k];
        b[3 * i + k] = c * bi + s * bj;
        b[3 * j + k] = -s * bi + c * bj;
        const real qi = q[3 * k + i], qj = q[3 * k + j];
        q[3 * k + i] = c * qi + s * qj;
        q[3 * k + j] = -s * qi + c * qj;
    }
}

inline void svd3(const real *F, real *U, real *s, real *V)
{
    real b[9];
    mat3_copy(F, b);
    mat3_identity(V);
    for (int sweep = 0; sweep < SVD3_MAX_SWEEPS; ++sweep) {
        int rotated = svd3_orthogonalize(b, V, 0, 1);
        rotated += svd3_orthogonalize(b, V, 0, 2);
        rotated += svd3_orthogonalize(b, V, 1, 2);
        if (!rotated)
            break;
    }
    svd3_sort_pair(b, V, 0, 1);
    svd3_sort_pair(b, V, 0, 2);
    svd3_sort_pair(b, V, 1, 2);
    mat3_identity(U);
    svd3_givens(b, U, 0, 1);
    svd3_givens(b, U, 0, 2);
    svd3_givens(b, U, 1, 2);
    s[0] = b[0];
    s[1] = b[4];
    s[2] = b[8];
}

#endif /* CLFLOW_SVD3_H */
