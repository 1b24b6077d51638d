/* Adjoint of G2P (g2p.cl), one particle's part, which both shapes of its scatter onto the grid
 * share (clflow/runtime/plan.py, stage adjoint_scatter: the forward P2G's shape, the plan's own
 * after an atomic P2G), each deterministic without float atomics: g2p_adjoint_private.cl (CPU
 * devices: private grid copies) and g2p_adjoint_gather.cl (GPUs: a gather per node).
 *
 * Forward: v_pic = sum_i w v_i,  C' = (4/dx^2) sum_i w v_i d^T,  x' = clamp(x + dt v_pic),
 * v' = v_pic, or with CLFLOW_FLIP v' = flip (v + sum_i w dv_i) + (1 - flip) v_pic.
 * Given xbar', vbar', Cbar' of state n+1, with u = (1 - flip) vbar' + dt xbar' (flip = 0
 * without CLFLOW_FLIP; xbar' zeroed on clamped axes) and B = (4/dx^2) Cbar':
 *   vbar_i  += w (u + B d)
 *   dvbar_i += w flip vbar'                                   (CLFLOW_FLIP)
 *   xbar     = xbar' (unclamped axes) + sum_i grad(w) (v_i . (u + B d) + flip dv_i . vbar')
 *              - B^T v_pic
 * (v_pic: the forward's v' read back, or with CLFLOW_FLIP summed again; the flip vbar' that
 * reaches the particle's own v is added by p2g_flip_adjoint). Grid copies hold GV_CH reals
 * per node: vbar_i, and dvbar_i with CLFLOW_FLIP.
 * Unreleased particles (t < release_time) do not move: xbar = xbar', nothing to the grid. */
#ifndef CLFLOW_MPM_G2P_ADJOINT_H
#define CLFLOW_MPM_G2P_ADJOINT_H

#include "mpm/adjoint/adjoint.h"

/* record of a slot in the gather shape: x (3), u (3), B (3 x 3)[, flip vbar' (3)] */
#define G2P_ADJ_REC (CLFLOW_FLIP ? 18 : 15)

/* Particle p's G2P adjoint: x_bar[p] written; its grid terms added into grid_v_bar (a private
 * copy) or, when grid_v_bar is 0, written to `record` (G2P_ADJ_REC reals) for the gather. */
inline void g2p_adjoint_particle(const grid_t *g, const int p, const real dt, const real t, const real flip,
                                 __global const real *x_in, __global const real *v_out,
                                 __global const real *release_time, __global const real *grid_v,
                                 __global const real *grid_dv, __global const real *x_bar_out,
                                 __global const real *v_bar_out, __global const real *C_bar_out,
                                 __global real *grid_v_bar, __global real *x_bar, __global real *record)
{
    const real dx = g->dx;
    real xp[3], vp[3], xb[3], u[3], B[9], vi[3];
    load_row(x_in, p, 3, xp);
    load_row(x_bar_out, p, 3, xb);
    if (t < release_time[p]) {
        store_row(x_bar, p, 3, xb);
        if (record != 0) /* weight 0: a record that adds nothing */
            for (int q = 0; q < G2P_ADJ_REC; ++q)
                record[q] = q < 3 ? xp[q] : 0;
        return;
    }
    load_row(v_bar_out, p, 3, u);
    load_row(C_bar_out, p, 9, B);
#if CLFLOW_FLIP
    real fv[3]; /* flip vbar' */
    for (int a = 0; a < 3; ++a) {
        fv[a] = flip * u[a];
        u[a] -= fv[a];
    }
    const stencil_t st = make_stencil(g, xp);
    for (int a = 0; a < 3; ++a)
        vp[a] = 0;
    for (int i = 0; i < 3; ++i) /* v_pic */
        for (int j = 0; j < 3; ++j)
            for (int k = 0; k < 3; ++k) {
                const real w = st.w[0][i] * st.w[1][j] * st.w[2][k];
                load_row(grid_v, grid_index(g, st.base[0] + i, st.base[1] + j, st.base[2] + k), 3, vi);
                for (int a = 0; a < 3; ++a)
                    vp[a] += w * vi[a];
            }
#else
    load_row(v_out, p, 3, vp);
    const stencil_t st = make_stencil(g, xp);
#endif
    for (int a = 0; a < 3; ++a) {
        const real lo = g->origin[a] + CLAMP_MARGIN * dx;
        const real hi = g->origin[a] + (grid_extent(g, a) - 1 - CLAMP_MARGIN) * dx;
        const real moved = xp[a] + dt * vp[a];
        if (clamp(moved, lo, hi) != moved)
            xb[a] = 0;
        u[a] += dt * xb[a];
    }
    for (int k = 0; k < 9; ++k)
        B[k] *= 4 / (dx * dx);
    if (record != 0) {
        for (int a = 0; a < 3; ++a) {
            record[a] = xp[a];
            record[3 + a] = u[a];
        }
        for (int k = 0; k < 9; ++k)
            record[6 + k] = B[k];
#if CLFLOW_FLIP
        for (int a = 0; a < 3; ++a)
            record[15 + a] = fv[a];
#endif
    }
    const stencil_gradient_t sg = make_stencil_gradient(&st, dx);
#pragma unroll
    for (int i = 0; i < 3; ++i)
#pragma unroll
        for (int j = 0; j < 3; ++j)
#pragma unroll
            for (int k = 0; k < 3; ++k) {
                const real w = st.w[0][i] * st.w[1][j] * st.w[2][k];
                const real d[3] = {(i - st.fx[0]) * dx, (j - st.fx[1]) * dx, (k - st.fx[2]) * dx};
                const long node = grid_index(g, st.base[0] + i, st.base[1] + j, st.base[2] + k);
                load_row(grid_v, node, 3, vi);
                real grad_w[3], s = 0;
                weight_gradient(&st, &sg, i, j, k, grad_w);
                for (int a = 0; a < 3; ++a) {
                    const real Bd = B[3 * a] * d[0] + B[3 * a + 1] * d[1] + B[3 * a + 2] * d[2];
                    if (grid_v_bar != 0)
                        grid_v_bar[GV_CH * node + a] += w * (u[a] + Bd);
                    s += vi[a] * (u[a] + Bd);
                }
#if CLFLOW_FLIP
                load_row(grid_dv, node, 3, vi);
                for (int a = 0; a < 3; ++a) {
                    if (grid_v_bar != 0)
                        grid_v_bar[GV_CH * node + 3 + a] += w * fv[a];
                    s += vi[a] * fv[a];
                }
#endif
                for (int a = 0; a < 3; ++a)
                    xb[a] += grad_w[a] * s;
            }
    for (int a = 0; a < 3; ++a) /* sum_i w B^T v_i = B^T v' */
        xb[a] -= B[a] * vp[0] + B[3 + a] * vp[1] + B[6 + a] * vp[2];
    store_row(x_bar, p, 3, xb);
}

#endif /* CLFLOW_MPM_G2P_ADJOINT_H */
