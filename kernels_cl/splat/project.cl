/* EWA projection of 3D Gaussians to screen space, and its adjoint.
 *
 * Per Gaussian i (forward: CLFLOW_SIMD_LANES per work-item in vector lanes; adjoint: one per
 * work-item; no atomics):
 *   mu_c = W mu + t                     camera-space mean (viewmat = [W t; 0 1], OpenCV axes)
 *   culled when z <= near, det(Sigma_2D) <= 0 or its tile box is empty (radius = 0)
 *   u = x/z, v = y/z; J evaluated at (u, v) clamped to LIM_FOV x the field of view
 *   Sigma_2D = J W Sigma W^T J^T + EPS2D I,  conic = Sigma_2D^-1 = (A, B, C)
 *   mean2d = (fx u + cx, fy v + cy),  depth = z
 *   radius = ceil(3 sqrt(lambda_max(Sigma_2D))), at most MAX_RADIUS (an overflowed or
 *   absurd covariance still gives a valid int; such a box covers the image anyway)
 * Sigma is read symmetrised, 0.5 (Sigma + Sigma^T), so its gradient is exact for all nine
 * entries. Buffers: means [N,3], covars [N,3,3], viewmat [4,4], intrinsics [3,3] (row-major). */
#include "splat/common.h"

#if !defined(LIM_FOV) || !defined(MIN_RADIUS_EIGEN) || !defined(MAX_RADIUS)
#error "build with -DLIM_FOV=... -DMIN_RADIUS_EIGEN=... -DMAX_RADIUS=..."
#endif

typedef struct {
    real W[9], t[3]; /* world-to-camera rotation (row-major) and translation */
    real fx, fy, cx, cy;
    real lim_u_neg, lim_u_pos, lim_v_neg, lim_v_pos; /* clamp of x/z and y/z for J */
} camera_t;

inline camera_t load_camera(__global const real *viewmat, __global const real *intrinsics, const int width,
                            const int height)
{
    camera_t cam;
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c)
            cam.W[3 * r + c] = viewmat[4 * r + c];
        cam.t[r] = viewmat[4 * r + 3];
    }
    cam.fx = intrinsics[0];
    cam.cx = intrinsics[2];
    cam.fy = intrinsics[4];
    cam.cy = intrinsics[5];
    /* (LIM_FOV - 1) x the half field of view beyond each image border */
    const real margin_u = (real)(LIM_FOV - 1) * (real)0.5 * width / cam.fx;
    const real margin_v = (real)(LIM_FOV - 1) * (real)0.5 * height / cam.fy;
    cam.lim_u_neg = cam.cx / cam.fx + margin_u;
    cam.lim_u_pos = (width - cam.cx) / cam.fx + margin_u;
    cam.lim_v_neg = cam.cy / cam.fy + margin_v;
    cam.lim_v_pos = (height - cam.cy) / cam.fy + margin_v;
    return cam;
}

/* Everything the forward computes for one Gaussian (the adjoint recomputes it), from its
 * mean [3] and covariance [9]: projection_t / project_one for T = real, projection_v_t /
 * project_one_v for CLFLOW_SIMD_LANES Gaussians in vector lanes (the same operations lane by
 * lane, so the same results). */
#define CLFLOW_DEFINE_PROJECT_ONE(SFX, T)                                                                              \
    typedef struct {                                                                                                   \
        T mc[3];  /* camera-space mean */                                                                              \
        T u, v;   /* x/z, y/z */                                                                                       \
        T tu, tv; /* clamped u, v used in J */                                                                         \
        T J00, J02, J11, J12;                                                                                          \
        T Sc[9];   /* W Sigma W^T */                                                                                   \
        T a, b, c; /* Sigma_2D = [[a, b], [b, c]] */                                                                   \
        T det;                                                                                                         \
    } projection##SFX##_t;                                                                                             \
                                                                                                                       \
    inline projection##SFX##_t project_one##SFX(const camera_t *cam, const T *mean, const T *covar)                    \
    {                                                                                                                  \
        projection##SFX##_t p;                                                                                         \
        for (int r = 0; r < 3; ++r)                                                                                    \
            p.mc[r] = cam->W[3 * r] * mean[0] + cam->W[3 * r + 1] * mean[1] + cam->W[3 * r + 2] * mean[2] + cam->t[r]; \
        const T z = p.mc[2];                                                                                           \
        p.u = p.mc[0] / z;                                                                                             \
        p.v = p.mc[1] / z;                                                                                             \
        p.tu = clamp(p.u, -cam->lim_u_neg, cam->lim_u_pos);                                                            \
        p.tv = clamp(p.v, -cam->lim_v_neg, cam->lim_v_pos);                                                            \
        p.J00 = cam->fx / z;                                                                                           \
        p.J02 = -cam->fx * p.tu / z;                                                                                   \
        p.J11 = cam->fy / z;                                                                                           \
        p.J12 = -cam->fy * p.tv / z;                                                                                   \
        T S[9], WS[9];                                                                                                 \
        for (int r = 0; r < 3; ++r)                                                                                    \
            for (int c = 0; c < 3; ++c)                                                                                \
                S[3 * r + c] = (real)0.5 * (covar[3 * r + c] + covar[3 * c + r]);                                      \
        for (int r = 0; r < 3; ++r)                                                                                    \
            for (int c = 0; c < 3; ++c)                                                                                \
                WS[3 * r + c] = cam->W[3 * r] * S[c] + cam->W[3 * r + 1] * S[3 + c] + cam->W[3 * r + 2] * S[6 + c];    \
        for (int r = 0; r < 3; ++r)                                                                                    \
            for (int c = 0; c < 3; ++c)                                                                                \
                p.Sc[3 * r + c] =                                                                                      \
                    WS[3 * r] * cam->W[3 * c] + WS[3 * r + 1] * cam->W[3 * c + 1] + WS[3 * r + 2] * cam->W[3 * c + 2]; \
        /* rows of J: j0 = (J00, 0, J02), j1 = (0, J11, J12) */                                                        \
        const T *Sc = p.Sc;                                                                                            \
        p.a = p.J00 * (p.J00 * Sc[0] + p.J02 * Sc[2]) + p.J02 * (p.J00 * Sc[6] + p.J02 * Sc[8]) + (real)EPS2D;         \
        p.b = p.J00 * (p.J11 * Sc[1] + p.J12 * Sc[2]) + p.J02 * (p.J11 * Sc[7] + p.J12 * Sc[8]);                       \
        p.c = p.J11 * (p.J11 * Sc[4] + p.J12 * Sc[5]) + p.J12 * (p.J11 * Sc[7] + p.J12 * Sc[8]) + (real)EPS2D;         \
        p.det = p.a * p.c - p.b * p.b;                                                                                 \
        return p;                                                                                                      \
    }

CLFLOW_DEFINE_PROJECT_ONE(, real)
CLFLOW_DEFINE_PROJECT_ONE(_v, realv)

/* Forward, CLFLOW_SIMD_LANES Gaussians per work-item in vector lanes (PoCL does not vectorise
 * this kernel across work-items itself: its loads and stores are strided); the culling and
 * the tile box are per lane. */
__kernel void project_forward(__global const real *means, __global const real *covars, __global const real *viewmat,
                              __global const real *intrinsics, __global real *means2d, __global real *conics,
                              __global real *depths, __global int *radii, __global int *tiles_touched, const int n,
                              const int width, const int height, const real near_plane)
{
    const int i0 = get_global_id(0) * CLFLOW_SIMD_LANES;
    if (i0 >= n)
        return;
    const camera_t cam = load_camera(viewmat, intrinsics, width, height);
    realv mean[3], covar[9];
    load_lanes_v(n, i0, 3, means, mean);
    load_lanes_v(n, i0, 9, covars, covar);
    const projection_v_t p = project_one_v(&cam, mean, covar);
    const realv mid = (real)0.5 * (p.a + p.c);
    const realv lambda_max = mid + sqrt(fmax((realv)(real)MIN_RADIUS_EIGEN, mid * mid - p.det));
    const realv radius_real = fmin(ceil(3 * sqrt(lambda_max)), (realv)(real)MAX_RADIUS);
    const realv mx = cam.fx * p.u + cam.cx, my = cam.fy * p.v + cam.cy;
    const realv A = p.c / p.det, B = -p.b / p.det, C = p.a / p.det;
    const int tiles_x = (width + TILE_SIZE - 1) / TILE_SIZE, tiles_y = (height + TILE_SIZE - 1) / TILE_SIZE;
    for (int l = 0; l < CLFLOW_SIMD_LANES && i0 + l < n; ++l) {
        const int i = i0 + l;
        depths[i] = LANE(p.mc[2], l);
        int radius = 0, touched = 0, x0, y0, x1, y1;
        if (LANE(p.mc[2], l) > near_plane && LANE(p.det, l) > 0) {
            radius = (int)LANE(radius_real, l);
            touched = tile_rect(LANE(mx, l), LANE(my, l), radius, tiles_x, tiles_y, &x0, &y0, &x1, &y1);
        }
        const int seen = touched > 0;
        means2d[2 * i] = seen ? LANE(mx, l) : 0;
        means2d[2 * i + 1] = seen ? LANE(my, l) : 0;
        conics[3 * i] = seen ? LANE(A, l) : 0;
        conics[3 * i + 1] = seen ? LANE(B, l) : 0;
        conics[3 * i + 2] = seen ? LANE(C, l) : 0;
        radii[i] = seen ? radius : 0;
        tiles_touched[i] = touched;
    }
}

/* Adjoint of project_forward for the visible Gaussians (radius > 0; others get zeros).
 * In: dL/dmean2d [N,2], dL/dconic [N,3] (A, B, C as in sigma = 0.5 A dx^2 + B dx dy + ...),
 * dL/ddepth [N]. Out: dL/dmean [N,3], dL/dSigma [N,3,3] (symmetric). */
__kernel void project_backward(__global const real *means, __global const real *covars, __global const real *viewmat,
                               __global const real *intrinsics, __global const int *radii,
                               __global const real *v_means2d, __global const real *v_conics,
                               __global const real *v_depths, __global real *v_means, __global real *v_covars,
                               const int n, const int width, const int height)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    for (int k = 0; k < 3; ++k)
        v_means[3 * i + k] = 0;
    for (int k = 0; k < 9; ++k)
        v_covars[9 * i + k] = 0;
    if (radii[i] <= 0)
        return;
    const camera_t cam = load_camera(viewmat, intrinsics, width, height);
    real mean[3], covar[9];
    for (int k = 0; k < 3; ++k)
        mean[k] = means[3 * i + k];
    for (int k = 0; k < 9; ++k)
        covar[k] = covars[9 * i + k];
    const projection_t p = project_one(&cam, mean, covar);
    const real z = p.mc[2];

    /* conic = Sigma_2D^-1: dL/dSigma_2D = -Q G Q with G = [[gA, gB/2], [gB/2, gC]] */
    const real qa = p.c / p.det, qb = -p.b / p.det, qc = p.a / p.det;
    const real gA = v_conics[3 * i], gB = (real)0.5 * v_conics[3 * i + 1], gC = v_conics[3 * i + 2];
    const real QG00 = qa * gA + qb * gB, QG01 = qa * gB + qb * gC;
    const real QG10 = qb * gA + qc * gB, QG11 = qb * gB + qc * gC;
    const real g2a = -(QG00 * qa + QG01 * qb);
    const real g2b = -(QG00 * qb + QG01 * qc);
    const real g2c = -(QG10 * qb + QG11 * qc);

    /* Sigma_2D = J Sc J^T: dL/dSc = J^T G2 J, dL/dJ = 2 G2 J Sc */
    const real J[6] = {p.J00, 0, p.J02, 0, p.J11, p.J12};
    const real G2[4] = {g2a, g2b, g2b, g2c};
    real GJ[6]; /* G2 J, 2x3 */
    for (int r = 0; r < 2; ++r)
        for (int c = 0; c < 3; ++c)
            GJ[3 * r + c] = G2[2 * r] * J[c] + G2[2 * r + 1] * J[3 + c];
    real GSc[9];
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            GSc[3 * r + c] = J[r] * GJ[c] + J[3 + r] * GJ[3 + c];
    real vJ[6]; /* 2 (G2 J) Sc */
    for (int r = 0; r < 2; ++r)
        for (int c = 0; c < 3; ++c)
            vJ[3 * r + c] = 2 * (GJ[3 * r] * p.Sc[c] + GJ[3 * r + 1] * p.Sc[3 + c] + GJ[3 * r + 2] * p.Sc[6 + c]);

    /* Sc = W Sigma W^T: dL/dSigma = W^T GSc W */
    real WtG[9];
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            WtG[3 * r + c] = cam.W[r] * GSc[c] + cam.W[3 + r] * GSc[3 + c] + cam.W[6 + r] * GSc[6 + c];
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            v_covars[9 * i + 3 * r + c] =
                WtG[3 * r] * cam.W[c] + WtG[3 * r + 1] * cam.W[3 + c] + WtG[3 * r + 2] * cam.W[6 + c];

    /* camera-space mean: through mean2d, depth and J (J00 = fx/z, J02 = -fx tu/z, ...;
     * a clamped tu = lim is constant, so J02 = -fx lim/z then depends on z alone) */
    const real gmx = v_means2d[2 * i], gmy = v_means2d[2 * i + 1];
    real gx = gmx * cam.fx / z;
    real gy = gmy * cam.fy / z;
    real gz = -(gmx * cam.fx * p.u + gmy * cam.fy * p.v) / z + v_depths[i];
    gz -= (vJ[0] * cam.fx + vJ[4] * cam.fy) / (z * z);
    if (p.tu == p.u) {
        gx -= vJ[2] * cam.fx / (z * z);
        gz += vJ[2] * 2 * cam.fx * p.tu / (z * z);
    } else {
        gz += vJ[2] * cam.fx * p.tu / (z * z);
    }
    if (p.tv == p.v) {
        gy -= vJ[5] * cam.fy / (z * z);
        gz += vJ[5] * 2 * cam.fy * p.tv / (z * z);
    } else {
        gz += vJ[5] * cam.fy * p.tv / (z * z);
    }
    /* mu_c = W mu + t: dL/dmu = W^T dL/dmu_c */
    for (int k = 0; k < 3; ++k)
        v_means[3 * i + k] = cam.W[k] * gx + cam.W[3 + k] * gy + cam.W[6 + k] * gz;
}
