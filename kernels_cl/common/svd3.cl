/* Batched 3x3 SVD (common/svd3.h): F [n, 9] -> U [n, 9], s [n, 3], V [n, 9], row-major. */
#include "common/svd3.h"

__kernel void svd3_batch(const int n, __global const real *F, __global real *U, __global real *s,
                         __global real *V)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    real f[9], u[9], sv[3], v[9];
    for (int k = 0; k < 9; ++k)
        f[k] = F[9 * i + k];
    svd3(f, u, sv, v);
    for (int k = 0; k < 9; ++k) {
        U[9 * i + k] = u[k];
        V[9 * i + k] = v[k];
    }
    for (int k = 0; k < 3; ++k)
        s[3 * i + k] = sv[k];
}
