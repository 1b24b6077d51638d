/* A simulated frame's Gaussians on the device, its adjoint, and a rendered image as bytes.
 *
 * object_frame: the object's n Gaussians of a frame written over the first n rows of the
 * scene's N (the static Gaussians after them stay as written once):
 *   mu_i = x_i,  Sigma_i = F_i Sigma0_i F_i^T          (Sigma0: the rest covariance)
 * rgb_uint8: clamp(v, 0, 1) (NaN as 0) x 255 rounded half up, in float, as clflow.media.to_uint8.
 * One Gaussian (or value) a work-item, no atomics.
 * Buffers: x [n,3], F [n,3,3], rest_covars [n,3,3], means [N,3], covars [N,3,3] (row-major). */
#include "splat/common.h"

__kernel void object_frame(__global const real *x, __global const real *F, __global const real *rest_covars,
                           __global real *means, __global real *covars, const int n)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    real f[9], S[9], A[9];
    for (int k = 0; k < 9; ++k) {
        f[k] = F[9 * i + k];
        S[k] = rest_covars[9 * i + k];
    }
    for (int r = 0; r < 3; ++r) /* A = F Sigma0 */
        for (int c = 0; c < 3; ++c)
            A[3 * r + c] = f[3 * r] * S[c] + f[3 * r + 1] * S[3 + c] + f[3 * r + 2] * S[6 + c];
    for (int r = 0; r < 3; ++r) /* Sigma = A F^T */
        for (int c = 0; c < 3; ++c)
            covars[9 * i + 3 * r + c] = A[3 * r] * f[3 * c] + A[3 * r + 1] * f[3 * c + 1] + A[3 * r + 2] * f[3 * c + 2];
    for (int k = 0; k < 3; ++k)
        means[3 * i + k] = x[3 * i + k];
}

/* dL/dx_i = dL/dmu_i; dL/dF_i = (G + G^T) F_i Sigma0_i with G = dL/dSigma_i. */
__kernel void object_frame_backward(__global const real *F, __global const real *rest_covars,
                                    __global const real *v_means, __global const real *v_covars, __global real *v_x,
                                    __global real *v_F, const int n)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    real f[9], S[9], G[9], B[9];
    for (int k = 0; k < 9; ++k) {
        f[k] = F[9 * i + k];
        S[k] = rest_covars[9 * i + k];
        G[k] = v_covars[9 * i + k] + v_covars[9 * i + 3 * (k % 3) + k / 3];
    }
    for (int r = 0; r < 3; ++r) /* B = (G + G^T) F */
        for (int c = 0; c < 3; ++c)
            B[3 * r + c] = G[3 * r] * f[c] + G[3 * r + 1] * f[3 + c] + G[3 * r + 2] * f[6 + c];
    for (int r = 0; r < 3; ++r) /* dL/dF = B Sigma0 */
        for (int c = 0; c < 3; ++c)
            v_F[9 * i + 3 * r + c] = B[3 * r] * S[c] + B[3 * r + 1] * S[3 + c] + B[3 * r + 2] * S[6 + c];
    for (int k = 0; k < 3; ++k)
        v_x[3 * i + k] = v_means[3 * i + k];
}

__kernel void rgb_uint8(__global const real *image, __global uchar *out, const int n)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    const float v = (float)image[i];
    out[i] = (uchar)(clamp(isnan(v) ? 0.0f : v, 0.0f, 1.0f) * 255.0f + 0.5f);
}
