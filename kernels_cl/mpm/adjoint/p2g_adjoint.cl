/* Adjoint of P2G (p2g_private.cl and its other shapes), a gather: each particle reads the adjoint of its 27 nodes.
 *
 * Forward: m_i += w m,  mv_i += w [m (v + dt a) + A d],  A = m C - dt V (4/dx^2) tau.
 * Given grid_bar = (mbar_i, pbar_i) per node (GRID_CH reals; p2g_flip_adjoint reads the rest):
 *   vbar  = m sum_i w pbar_i
 *   Abar  = sum_i w pbar_i d^T;  Cbar = m Abar;  taubar = -dt V (4/dx^2) Abar
 *   mbar += sum_i w [mbar_i + pbar_i . (v + dt a)] + <Abar, C>
 *   xbar += sum_i grad(w) [m mbar_i + pbar_i . (m (v + dt a) + A d)] - A^T sum_i w pbar_i
 * x_bar and mass_bar are accumulated into; v_bar, C_bar, tau_bar are written.
 *
 * CLFLOW_SIMD_LANES particles per work-item in vector registers (the compiler does not
 * vectorise this gather across work-items itself); only the node loads are per lane. The
 * node sums are separable (w = w0[i] w1[j] w2[k], d = dx ((i, j, k) - fx)): the k loop sums
 * with the axis-2 weights, the (i, j) level with the others. */
#include "mpm/adjoint/adjoint.h"

__kernel void p2g_adjoint(MPM_GRID_ARGS, const int n, const real dt, __global const real *x, __global const real *v,
                          __global const real *C, __global const real *tau, __global const real *mass,
                          __global const real *volume, __global const int *group, __global const real *accel,
                          __global const real *grid_bar, __global real *x_bar, __global real *v_bar,
                          __global real *C_bar, __global real *tau_bar, __global real *mass_bar)
{
    const int p0 = get_global_id(0) * CLFLOW_SIMD_LANES;
    if (p0 >= n)
        return;
    const grid_t g = MPM_GRID;
    realv xp[3], vel[3], Cp[9], taup[9], A[9], xb[3], m, vol;
    load_lanes_v(n, p0, 3, x, xp);
    load_lanes_v(n, p0, 3, v, vel);
    load_lanes_v(n, p0, 9, C, Cp);
    load_lanes_v(n, p0, 9, tau, taup);
    load_lanes_v(n, p0, 3, x_bar, xb);
    load_lanes_v(n, p0, 1, mass, &m);
    load_lanes_v(n, p0, 1, volume, &vol);
    for (int l = 0; l < CLFLOW_SIMD_LANES; ++l) { /* vel = v + dt a (the driver group's) */
        const int gp = group[min(p0 + l, n - 1)];
        for (int a = 0; a < 3; ++a)
            ((real *)&vel[a])[l] += gp >= 0 ? dt * accel[3 * gp + a] : (real)0;
    }
    const realv stress_scale = -dt * vol * 4 / (dx * dx);
    for (int k = 0; k < 9; ++k)
        A[k] = stress_scale * taup[k] + m * Cp[k];
    const stencil_v_t st = make_stencil_v(&g, xp, p0, n);
    const stencil_gradient_v_t sg = make_stencil_gradient_v(&st, dx);
    /* u = m (v + dt a) + A d is affine in the node offsets: u = u0 + dx (A_:0 i + A_:1 j + A_:2 k) */
    realv u0[3];
    for (int a = 0; a < 3; ++a)
        u0[a] = m * vel[a] - dx * (A[3 * a] * st.fx[0] + A[3 * a + 1] * st.fx[1] + A[3 * a + 2] * st.fx[2]);
    /* sum_p[a] = sum_i w pbar_a; moment[3a + b] = sum_i w pbar_a (node offset)_b */
    realv sum_m = 0, sum_p[3] = {0, 0, 0}, moment[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
#pragma unroll
    for (int i = 0; i < 3; ++i)
#pragma unroll
        for (int j = 0; j < 3; ++j) {
            realv u[3]; /* u at node (i, j, 0) */
            for (int a = 0; a < 3; ++a)
                u[a] = u0[a] + dx * (A[3 * a] * i + A[3 * a + 1] * j);
            /* along k: sums of w2 mbar, w2 pbar, w2 k pbar, w2 s, dw2 s with
             * s = m mbar + pbar . u, the node's part of dL/dw */
            realv m_k = 0, p_k[3] = {0, 0, 0}, pk_k[3] = {0, 0, 0}, s_w = 0, s_dw = 0;
            const long row = node_offset(&g, i, j, 0);
#pragma unroll
            for (int k = 0; k < 3; ++k) {
                realv gb[4];
                for (int l = 0; l < CLFLOW_SIMD_LANES; ++l)
                    for (int c = 0; c < 4; ++c)
                        ((real *)&gb[c])[l] = grid_bar[GRID_CH * (st.corner[l] + row + k) + c];
                const realv w = st.w[2][k];
                realv s = m * gb[0];
                for (int a = 0; a < 3; ++a) {
                    s += gb[1 + a] * (u[a] + dx * A[3 * a + 2] * k);
                    p_k[a] += w * gb[1 + a];
                    pk_k[a] += (w * k) * gb[1 + a];
                }
                m_k += w * gb[0];
                s_w += w * s;
                s_dw += sg.dw[2][k] * s;
            }
            const realv w_ij = st.w[0][i] * st.w[1][j];
            sum_m += w_ij * m_k;
            for (int a = 0; a < 3; ++a) {
                sum_p[a] += w_ij * p_k[a];
                moment[3 * a] += (w_ij * i) * p_k[a];
                moment[3 * a + 1] += (w_ij * j) * p_k[a];
                moment[3 * a + 2] += w_ij * pk_k[a];
            }
            xb[0] += sg.dw[0][i] * st.w[1][j] * s_w;
            xb[1] += st.w[0][i] * sg.dw[1][j] * s_w;
            xb[2] += w_ij * s_dw;
        }
    realv mb = sum_m, vb[3], A_bar[9], Cb[9], tb[9];
    for (int a = 0; a < 3; ++a)
        for (int b = 0; b < 3; ++b) /* sum_i w pbar_i d^T */
            A_bar[3 * a + b] = dx * (moment[3 * a + b] - st.fx[b] * sum_p[a]);
    for (int a = 0; a < 3; ++a) {
        vb[a] = m * sum_p[a];
        mb += sum_p[a] * vel[a];
        xb[a] -= A[a] * sum_p[0] + A[3 + a] * sum_p[1] + A[6 + a] * sum_p[2]; /* sum_i w A^T pbar_i */
    }
    for (int k = 0; k < 9; ++k) {
        mb += A_bar[k] * Cp[k];
        Cb[k] = m * A_bar[k];
        tb[k] = stress_scale * A_bar[k];
    }
    store_lanes_v(n, p0, 3, xb, x_bar);
    store_lanes_v(n, p0, 3, vb, v_bar);
    store_lanes_v(n, p0, 9, Cb, C_bar);
    store_lanes_v(n, p0, 9, tb, tau_bar);
    for (int l = 0; l < CLFLOW_SIMD_LANES && p0 + l < n; ++l)
        mass_bar[p0 + l] += LANE(mb, l);
}

#if CLFLOW_FLIP
/* The PIC/FLIP blend's part of the P2G adjoint, after p2g_adjoint, one particle per work-item.
 *
 * Forward: mv0_i += w m (v + C d); G2P: v' = flip v + ... for released particles (t >=
 * release_time). Given p0bar_i = grid_bar[GRID_CH i + 4..6], S = sum_i w p0bar_i and
 * M = sum_i w p0bar_i d^T:
 *   vbar += m S + flip vbar' (released),   Cbar += m M,   mbar += S . v + <M, C>,
 *   xbar += sum_i grad(w) m p0bar_i . (v + C d) - m C^T S
 * all accumulated into. */
__kernel void p2g_flip_adjoint(MPM_GRID_ARGS, const int n, const real t, const real flip, __global const real *x,
                               __global const real *v, __global const real *C, __global const real *mass,
                               __global const real *release_time, __global const real *v_bar_out,
                               __global const real *grid_bar, __global real *x_bar, __global real *v_bar,
                               __global real *C_bar, __global real *mass_bar)
{
    const int p = get_global_id(0);
    if (p >= n)
        return;
    const grid_t g0 = MPM_GRID, g = particle_grid(&g0, p, n);
    real xp[3], vp[3], Cp[9], xb[3], S[3] = {0, 0, 0}, M[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
    load_row(x, p, 3, xp);
    load_row(v, p, 3, vp);
    load_row(C, p, 9, Cp);
    load_row(x_bar, p, 3, xb);
    const real m = mass[p];
    const stencil_t st = make_stencil(&g, xp);
    const stencil_gradient_t sg = make_stencil_gradient(&st, dx);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            for (int k = 0; k < 3; ++k) {
                const real w = st.w[0][i] * st.w[1][j] * st.w[2][k];
                const real d[3] = {(i - st.fx[0]) * dx, (j - st.fx[1]) * dx, (k - st.fx[2]) * dx};
                const long node = grid_index(&g, st.base[0] + i, st.base[1] + j, st.base[2] + k);
                const real q[3] = {grid_bar[GRID_CH * node + 4], grid_bar[GRID_CH * node + 5],
                                   grid_bar[GRID_CH * node + 6]};
                real grad_w[3], s = 0;
                for (int a = 0; a < 3; ++a) {
                    s += q[a] * (vp[a] + Cp[3 * a] * d[0] + Cp[3 * a + 1] * d[1] + Cp[3 * a + 2] * d[2]);
                    S[a] += w * q[a];
                    for (int b = 0; b < 3; ++b)
                        M[3 * a + b] += w * q[a] * d[b];
                }
                weight_gradient(&st, &sg, i, j, k, grad_w);
                for (int a = 0; a < 3; ++a)
                    xb[a] += grad_w[a] * m * s;
            }
    real mb = 0;
    const real keep = t >= release_time[p] ? flip : (real)0;
    for (int a = 0; a < 3; ++a) {
        xb[a] -= m * (Cp[a] * S[0] + Cp[3 + a] * S[1] + Cp[6 + a] * S[2]);
        v_bar[3 * p + a] += m * S[a] + keep * v_bar_out[3 * p + a];
        mb += S[a] * vp[a];
    }
    for (int e = 0; e < 9; ++e) {
        C_bar[9 * p + e] += m * M[e];
        mb += M[e] * Cp[e];
    }
    store_row(x_bar, p, 3, xb);
    mass_bar[p] += mb;
}
#endif
