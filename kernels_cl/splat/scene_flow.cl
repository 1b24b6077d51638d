/* The "mean" flow features of a simulated frame step on the device, and their adjoint.
 *
 * mean_flow_features: each Gaussian's projected displacement between frames t and t+1,
 *   f_i = pi(mu_i(t+1)) - pi(mu_i(t)),  pi(p) = (q0 / q2, q1 / q2), q = K (W p + t)
 * and 0 for a Gaussian not in front of the near plane at both frames (it has no projected
 * motion; its gradient is 0 too). One Gaussian a work-item, no atomics.
 * Buffers: means [N,3], features [N,2], viewmat [4,4], intrinsics [3,3] (row-major). */
#include "splat/common.h"

typedef struct {
    real W[9], t[3], K[9];
} pinhole_t;

inline pinhole_t load_pinhole(__global const real *viewmat, __global const real *intrinsics)
{
    pinhole_t cam;
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c)
            cam.W[3 * r + c] = viewmat[4 * r + c];
        cam.t[r] = viewmat[4 * r + 3];
    }
    for (int k = 0; k < 9; ++k)
        cam.K[k] = intrinsics[k];
    return cam;
}

/* q = K (W p + t), and the camera depth (W p + t)_z; as the torch reference orders them. */
inline real image_point(const pinhole_t *cam, __global const real *p, real q[3])
{
    real c[3];
    for (int r = 0; r < 3; ++r)
        c[r] = p[0] * cam->W[3 * r] + p[1] * cam->W[3 * r + 1] + p[2] * cam->W[3 * r + 2] + cam->t[r];
    for (int r = 0; r < 3; ++r)
        q[r] = c[0] * cam->K[3 * r] + c[1] * cam->K[3 * r + 1] + c[2] * cam->K[3 * r + 2];
    return c[2];
}

__kernel void mean_flow_features(__global const real *means_t, __global const real *means_t1,
                                 __global const real *viewmat, __global const real *intrinsics, const real near_plane,
                                 __global real *features, const int n)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    const pinhole_t cam = load_pinhole(viewmat, intrinsics);
    real q0[3], q1[3];
    const real z0 = image_point(&cam, means_t + 3 * i, q0);
    const real z1 = image_point(&cam, means_t1 + 3 * i, q1);
    const bool ahead = z0 > near_plane && z1 > near_plane;
    features[2 * i] = ahead ? q1[0] / q1[2] - q0[0] / q0[2] : (real)0;
    features[2 * i + 1] = ahead ? q1[1] / q1[2] - q0[1] / q0[2] : (real)0;
}

/* d(q0 / q2, q1 / q2)/dp = [[1 / q2, 0, -q0 / q2^2], [0, 1 / q2, -q1 / q2^2]] K W. */
inline void point_gradient(const pinhole_t *cam, const real q[3], const real gu, const real gv, real sign, real out[3])
{
    const real dq[3] = {sign * gu / q[2], sign * gv / q[2], -sign * (gu * q[0] + gv * q[1]) / (q[2] * q[2])};
    real dc[3];
    for (int c = 0; c < 3; ++c)
        dc[c] = dq[0] * cam->K[c] + dq[1] * cam->K[3 + c] + dq[2] * cam->K[6 + c];
    for (int c = 0; c < 3; ++c)
        out[c] = dc[0] * cam->W[c] + dc[1] * cam->W[3 + c] + dc[2] * cam->W[6 + c];
}

/* dL/dmu(t) is added to v_means_t (it holds the projection's share already); dL/dmu(t+1)
 * is written to v_means_t1. */
__kernel void mean_flow_features_backward(__global const real *means_t, __global const real *means_t1,
                                          __global const real *viewmat, __global const real *intrinsics,
                                          const real near_plane, __global const real *v_features,
                                          __global real *v_means_t, __global real *v_means_t1, const int n)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    const pinhole_t cam = load_pinhole(viewmat, intrinsics);
    real q0[3], q1[3], g0[3] = {0, 0, 0}, g1[3] = {0, 0, 0};
    const real z0 = image_point(&cam, means_t + 3 * i, q0);
    const real z1 = image_point(&cam, means_t1 + 3 * i, q1);
    if (z0 > near_plane && z1 > near_plane) {
        const real gu = v_features[2 * i], gv = v_features[2 * i + 1];
        point_gradient(&cam, q0, gu, gv, (real)-1, g0);
        point_gradient(&cam, q1, gu, gv, (real)1, g1);
    }
    for (int k = 0; k < 3; ++k) {
        v_means_t[3 * i + k] += g0[k];
        v_means_t1[3 * i + k] = g1[k];
    }
}
