/* Adjoint of P2G (p2g.cl), a gather: each particle reads the adjoint of its 27 nodes.
 *
 * Forward: m_i += w m,  mv_i += w [m (v + dt a) + A d],  A = m C - dt V (4/dx^2) tau.
 * Given grid_bar = (mbar_i, pbar_i) per node:
 *   vbar  = m sum_i w pbar_i
 *   Abar  = sum_i w pbar_i d^T;  Cbar = m Abar;  taubar = -dt V (4/dx^2) Abar
 *   mbar += sum_i w [mbar_i + pbar_i . (v + dt a)] + <Abar, C>
 *   xbar += sum_i grad(w) [m mbar_i + pbar_i . (m (v + dt a) + A d)] - A^T sum_i w pbar_i
 * x_bar and mass_bar are accumulated into; v_bar, C_bar, tau_bar are written. */
#include "mpm/adjoint/adjoint.h"

__kernel void p2g_adjoint(const int nx, const int ny, const int nz, const real dx, const real ox,
                          const real oy, const real oz, const int n, const real dt, __global const real *x,
                          __global const real *v, __global const real *C, __global const real *tau,
                          __global const real *mass, __global const real *volume, __global const int *group,
                          __global const real *accel, __global const real *grid_bar, __global real *x_bar,
                          __global real *v_bar, __global real *C_bar, __global real *tau_bar,
                          __global real *mass_bar)
{
    const int p = get_global_id(0);
    if (p >= n)
        return;
    const grid_t g = make_grid(nx, ny, nz, dx, ox, oy, oz);
    real xp[3], vp[3], Cp[9], taup[9], A[9], xb[3];
    load_row(x, p, 3, xp);
    load_row(v, p, 3, vp);
    load_row(C, p, 9, Cp);
    load_row(tau, p, 9, taup);
    load_row(x_bar, p, 3, xb);
    const real m = mass[p];
    const real stress_scale = -dt * volume[p] * 4 / (dx * dx);
    for (int k = 0; k < 9; ++k)
        A[k] = stress_scale * taup[k] + m * Cp[k];
    const int gp = group[p];
    real vel[3]; /* v + dt a */
    for (int a = 0; a < 3; ++a)
        vel[a] = vp[a] + (gp >= 0 ? dt * accel[3 * gp + a] : 0);
    const stencil_t st = make_stencil(&g, xp);
    const stencil_gradient_t sg = make_stencil_gradient(&st, dx);
    real sum_p[3] = {0, 0, 0}, A_bar[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0}, sum_m = 0;
#pragma unroll
    for (int i = 0; i < 3; ++i)
#pragma unroll
        for (int j = 0; j < 3; ++j)
#pragma unroll
            for (int k = 0; k < 3; ++k) {
                const real w = st.w[0][i] * st.w[1][j] * st.w[2][k];
                const real d[3] = {(i - st.fx[0]) * dx, (j - st.fx[1]) * dx, (k - st.fx[2]) * dx};
                real gb[4], grad_w[3];
                load_row(grid_bar, grid_index(&g, st.base[0] + i, st.base[1] + j, st.base[2] + k), 4, gb);
                weight_gradient(&st, &sg, i, j, k, grad_w);
                real s = m * gb[0];
                sum_m += w * gb[0];
                for (int a = 0; a < 3; ++a) {
                    const real pb = gb[1 + a];
                    sum_p[a] += w * pb;
                    s += pb * (m * vel[a] + A[3 * a] * d[0] + A[3 * a + 1] * d[1] + A[3 * a + 2] * d[2]);
                    for (int b = 0; b < 3; ++b)
                        A_bar[3 * a + b] += w * pb * d[b];
                }
                for (int a = 0; a < 3; ++a)
                    xb[a] += grad_w[a] * s;
            }
    real mb = sum_m, vb[3], Cb[9], tb[9];
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
    store_row(x_bar, p, 3, xb);
    store_row(v_bar, p, 3, vb);
    store_row(C_bar, p, 9, Cb);
    store_row(tau_bar, p, 9, tb);
    mass_bar[p] += mb;
}
