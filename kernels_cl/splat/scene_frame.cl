/* A simulated frame's Gaussians on the device, its adjoint, and a rendered image as bytes.
 *
 * object_frame: the object's n Gaussians of a frame written over the first n rows of the
 * scene's N (the static Gaussians after them stay as written once):
 *   mu_i = x_i,  Sigma_i = F_i Sigma0_i F_i^T          (Sigma0: the rest covariance)
 * object_colors: the object's colours at a frame from its SH coefficients (clflow/splat/sh.py):
 *   d = (R_i R0_i)^T (mu_i - c) / |...|,  rgb_i = max(sum_k Y_k(d) sh_ik + 0.5, 0)
 * with R_i the rotation of F_i's polar decomposition, R0_i the rest sh_rotations, c the
 * camera centre (the rasteriser's sh_rotations, clflow.splat.ops.view_directions).
 * rgb_uint8: clamp(v, 0, 1) (NaN as 0) x 255 rounded half up, in float, as clflow.media.to_uint8.
 * One Gaussian (or value) a work-item, no atomics.
 * Buffers: x [n,3], F [n,3,3], rest_covars [n,3,3], means [N,3], covars [N,3,3] (row-major). */
#include "splat/common.h"

#if !defined(SH_C0) || !defined(SH_C1) || !defined(SH_C2_0) || !defined(SH_C3_0) || !defined(STATE_REAL)
#error "build with the SH constants and STATE_REAL (clflow/splat/device_scene.py: _frame_kernel)"
#endif

/* x [>= n, 3], F [>= n, 3, 3] of STATE_REAL (a simulation's state, or the scene's own real);
 * F_out [n, 3, 3] the object's F in real (what the adjoint and the colours read). */
__kernel void object_frame(__global const STATE_REAL *x, __global const STATE_REAL *F, __global const real *rest_covars,
                           __global real *means, __global real *covars, __global real *F_out, const int n)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    real f[9], S[9], A[9];
    for (int k = 0; k < 9; ++k) {
        f[k] = (real)F[9 * i + k];
        S[k] = rest_covars[9 * i + k];
        F_out[9 * i + k] = f[k];
    }
    for (int r = 0; r < 3; ++r) /* A = F Sigma0 */
        for (int c = 0; c < 3; ++c)
            A[3 * r + c] = f[3 * r] * S[c] + f[3 * r + 1] * S[3 + c] + f[3 * r + 2] * S[6 + c];
    for (int r = 0; r < 3; ++r) /* Sigma = A F^T */
        for (int c = 0; c < 3; ++c)
            covars[9 * i + 3 * r + c] = A[3 * r] * f[3 * c] + A[3 * r + 1] * f[3 * c + 1] + A[3 * r + 2] * f[3 * c + 2];
    for (int k = 0; k < 3; ++k)
        means[3 * i + k] = (real)x[3 * i + k];
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

/* Y_k(d), k < (degree + 1)^2, degree <= 3, in clflow.splat.sh.sh_basis's order. */
inline void sh_basis(const int degree, const real x, const real y, const real z, real Y[16])
{
    Y[0] = (real)SH_C0;
    if (degree < 1)
        return;
    Y[1] = -(real)SH_C1 * y;
    Y[2] = (real)SH_C1 * z;
    Y[3] = -(real)SH_C1 * x;
    if (degree < 2)
        return;
    const real xx = x * x, yy = y * y, zz = z * z;
    Y[4] = (real)SH_C2_0 * x * y;
    Y[5] = (real)SH_C2_1 * y * z;
    Y[6] = (real)SH_C2_2 * (2 * zz - xx - yy);
    Y[7] = (real)SH_C2_3 * x * z;
    Y[8] = (real)SH_C2_4 * (xx - yy);
    if (degree < 3)
        return;
    Y[9] = (real)SH_C3_0 * y * (3 * xx - yy);
    Y[10] = (real)SH_C3_1 * x * y * z;
    Y[11] = (real)SH_C3_2 * y * (4 * zz - xx - yy);
    Y[12] = (real)SH_C3_3 * z * (2 * zz - 3 * xx - 3 * yy);
    Y[13] = (real)SH_C3_4 * x * (4 * zz - xx - yy);
    Y[14] = (real)SH_C3_5 * z * (xx - yy);
    Y[15] = (real)SH_C3_6 * x * (xx - 3 * yy);
}

/* sh [n, bases, 3], polar [n, 3, 3], rest_rotations [n, 3, 3] (read when has_rest),
 * camera [3] (its centre), colors [N, 3] (the first n rows written). */
__kernel void object_colors(__global const real *means, __global const real *polar, __global const real *rest_rotations,
                            const int has_rest, __global const real *sh, const int bases, const int degree,
                            __global const real *camera, __global real *colors, const int n)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    real R[9];
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) {
            const __global real *P = polar + 9 * i + 3 * r;
            const __global real *Q = rest_rotations + 9 * i + c;
            R[3 * r + c] = has_rest ? P[0] * Q[0] + P[1] * Q[3] + P[2] * Q[6] : P[c];
        }
    real d[3], e[3];
    for (int k = 0; k < 3; ++k)
        d[k] = means[3 * i + k] - camera[k];
    for (int c = 0; c < 3; ++c) /* R^T d */
        e[c] = R[c] * d[0] + R[3 + c] * d[1] + R[6 + c] * d[2];
    const real norm = sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2]);
    real Y[16];
    sh_basis(degree, e[0] / norm, e[1] / norm, e[2] / norm, Y);
    const int used = (degree + 1) * (degree + 1);
    for (int ch = 0; ch < 3; ++ch) {
        real rgb = 0;
        for (int k = 0; k < used; ++k)
            rgb += Y[k] * sh[(i * bases + k) * 3 + ch];
        colors[3 * i + ch] = max(rgb + (real)0.5, (real)0);
    }
}

/* out[i] = rows[i] (i < count) in STATE_REAL: the object's gradient rows into a state's
 * gradient (the rows after them, the fill particles', stay as they are). */
__kernel void rows_to_state(__global const real *rows, __global STATE_REAL *out, const int count)
{
    const int i = get_global_id(0);
    if (i >= count)
        return;
    out[i] = (STATE_REAL)rows[i];
}

/* out [H, W, C] = the mean of each factor x factor block of image [H factor, W factor, C],
 * rounded half up: (sum + factor^2 / 2) / factor^2 (OpenCV's INTER_AREA for a whole factor).
 * One output byte a work-item. */
__kernel void area_average_uint8(__global const uchar *image, __global uchar *out, const int height, const int width,
                                 const int channels, const int factor)
{
    const int i = get_global_id(0);
    if (i >= height * width * channels)
        return;
    const int c = i % channels, col = (i / channels) % width, row = i / (channels * width);
    const int fine_width = width * factor, area = factor * factor;
    int sum = 0;
    for (int dy = 0; dy < factor; ++dy)
        for (int dx = 0; dx < factor; ++dx)
            sum += image[((row * factor + dy) * fine_width + col * factor + dx) * channels + c];
    out[i] = (uchar)((sum + area / 2) / area);
}
