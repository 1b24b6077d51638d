/* World covariances of 3D Gaussians from rotation and scale, and the adjoint.
 *
 *   q = (w, x, y, z) / |q|,  R = R(q),  M = R diag(s),  Sigma = M M^T
 * Buffers: quats [N,4], scales [N,3] (standard deviations), covars [N,3,3] (row-major). */
#include "splat/common.h"

/* R(q) of a unit quaternion (row-major), and R of q / |q| with M = R diag(s), returning
 * 1 / |q|: for T = real, and realv (CLFLOW_SIMD_LANES Gaussians in lanes). */
#define CLFLOW_DEFINE_ROTATION(SFX, T)                                                                                 \
    inline void quat_to_rotation##SFX(const T w, const T x, const T y, const T z, T R[9])                              \
    {                                                                                                                  \
        R[0] = 1 - 2 * (y * y + z * z);                                                                                \
        R[1] = 2 * (x * y - w * z);                                                                                    \
        R[2] = 2 * (x * z + w * y);                                                                                    \
        R[3] = 2 * (x * y + w * z);                                                                                    \
        R[4] = 1 - 2 * (x * x + z * z);                                                                                \
        R[5] = 2 * (y * z - w * x);                                                                                    \
        R[6] = 2 * (x * z - w * y);                                                                                    \
        R[7] = 2 * (y * z + w * x);                                                                                    \
        R[8] = 1 - 2 * (x * x + y * y);                                                                                \
    }                                                                                                                  \
                                                                                                                       \
    inline T rotation_and_scale##SFX(const T *q, const T *s, T R[9], T M[9])                                           \
    {                                                                                                                  \
        const T inv_norm = 1 / sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);                            \
        quat_to_rotation##SFX(q[0] * inv_norm, q[1] * inv_norm, q[2] * inv_norm, q[3] * inv_norm, R);                  \
        for (int k = 0; k < 9; ++k)                                                                                    \
            M[k] = R[k] * s[k % 3];                                                                                    \
        return inv_norm;                                                                                               \
    }
CLFLOW_DEFINE_ROTATION(, real)
CLFLOW_DEFINE_ROTATION(_v, realv)

/* Sigma = M M^T, CLFLOW_SIMD_LANES Gaussians per work-item in vector lanes. */
__kernel void covariance_forward(__global const real *quats, __global const real *scales, __global real *covars,
                                 const int n)
{
    const int i0 = get_global_id(0) * CLFLOW_SIMD_LANES;
    if (i0 >= n)
        return;
    realv q[4], s[3], R[9], M[9], S[9];
    load_lanes_v(n, i0, 4, quats, q);
    load_lanes_v(n, i0, 3, scales, s);
    rotation_and_scale_v(q, s, R, M);
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            S[3 * r + c] = M[3 * r] * M[3 * c] + M[3 * r + 1] * M[3 * c + 1] + M[3 * r + 2] * M[3 * c + 2];
    store_lanes_v(n, i0, 9, S, covars);
}

/* dL/dSigma = G [N,3,3] -> dL/dM = (G + G^T) M -> dL/dR = dL/dM diag(s),
 * dL/ds_j = sum_i dL/dM_ij R_ij -> dL/dq through R(q) and the normalisation. */
__kernel void covariance_backward(__global const real *quats, __global const real *scales,
                                  __global const real *v_covars, __global real *v_quats, __global real *v_scales,
                                  const int n)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    real q[4], s[3], R[9], M[9], G[9], dR[9];
    for (int k = 0; k < 4; ++k)
        q[k] = quats[4 * i + k];
    for (int k = 0; k < 3; ++k)
        s[k] = scales[3 * i + k];
    const real inv_norm = rotation_and_scale(q, s, R, M);
    const real w = q[0] * inv_norm, x = q[1] * inv_norm, y = q[2] * inv_norm, z = q[3] * inv_norm;
    for (int k = 0; k < 9; ++k) {
        G[k] = v_covars[9 * i + k] + v_covars[9 * i + 3 * (k % 3) + k / 3]; /* G + G^T */
    }
    real ds[3] = {0, 0, 0};
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) {
            const real dM = G[3 * r] * M[c] + G[3 * r + 1] * M[3 + c] + G[3 * r + 2] * M[6 + c];
            dR[3 * r + c] = dM * s[c];
            ds[c] += dM * R[3 * r + c];
        }
    }
    for (int c = 0; c < 3; ++c)
        v_scales[3 * i + c] = ds[c];
    /* dL/d(unit quaternion) */
    const real dw = 2 * (-z * dR[1] + y * dR[2] + z * dR[3] - x * dR[5] - y * dR[6] + x * dR[7]);
    const real dx =
        2 * (y * dR[1] + z * dR[2] + y * dR[3] - 2 * x * dR[4] - w * dR[5] + z * dR[6] + w * dR[7] - 2 * x * dR[8]);
    const real dy =
        2 * (-2 * y * dR[0] + x * dR[1] + w * dR[2] + x * dR[3] + z * dR[5] - w * dR[6] + z * dR[7] - 2 * y * dR[8]);
    const real dz =
        2 * (-2 * z * dR[0] - w * dR[1] + x * dR[2] + w * dR[3] - 2 * z * dR[4] + y * dR[5] + x * dR[6] + y * dR[7]);
    /* through q / |q|: remove the radial part and divide by |q| */
    const real radial = w * dw + x * dx + y * dy + z * dz;
    v_quats[4 * i] = (dw - w * radial) * inv_norm;
    v_quats[4 * i + 1] = (dx - x * radial) * inv_norm;
    v_quats[4 * i + 2] = (dy - y * radial) * inv_norm;
    v_quats[4 * i + 3] = (dz - z * radial) * inv_norm;
}
