/* Batched 3x3 SVD (common/svd3.h): F [n, 9] -> U [n, 9], s [n, 3], V [n, 9], row-major. */
#include "common/svd3.h"

__kernel void svd3_batch(const int n, __global const real *F, __global real *U, __global real *s, __global real *V)
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

#ifdef CLFLOW_SIMD_LANES
/* R = U V^T [n, 9], the rotation of the polar decomposition F = R S: proper even for
 * det F <= 0 (the signed SVD keeps the reflection in s). CLFLOW_SIMD_LANES matrices per
 * work-item in vector lanes. */
__kernel void polar_rotation(const int n, __global const real *F, __global real *R)
{
    const int i0 = get_global_id(0) * CLFLOW_SIMD_LANES;
    if (i0 >= n)
        return;
    const realv ones[3] = {(realv)1, (realv)1, (realv)1};
    realv f[9], u[9], s[3], v[9], r[9];
    load_lanes_v(n, i0, 9, F, f);
    svd3_v(f, u, s, v);
    mat3_udvt_v(u, ones, v, r);
    store_lanes_v(n, i0, 9, r, R);
}
#endif
