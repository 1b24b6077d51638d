/* Substep stage 4: grid to particle (APIC, or a PIC/FLIP blend) and advection.
 *
 *   v_pic = sum_i w v_i ;  C_p' = (4/dx^2) sum_i w v_i d^T ;  x_p' = x_p + dt v_pic
 *   v_p' = v_pic, or with CLFLOW_FLIP: v_p' = flip (v_p + sum_i w dv_i) + (1 - flip) v_pic
 * (dv_i: the grid's velocity change in this substep, grid.cl). The FLIP part keeps what the
 * grid cannot represent instead of filtering it out at every transfer, so the numerical
 * dissipation no longer grows with the number of substeps (docs/mpm.md).
 * A particle not yet released (t < release_time[p], layer release) stays put: x' = x,
 * v' = 0, C' = 0. A particle leaving [CLAMP_MARGIN, n - 1 - CLAMP_MARGIN] cells is clamped
 * back in and flagged: clamped[p] = 1 (the host zeroes the flags and counts them per frame;
 * an atomic counter would keep PoCL from vectorising the kernel). */
#include "mpm/mpm.h"

#define G2P_ARGS                                                                                                       \
    const real dt, const real t, const real flip, __global const real *restrict x_in,                                  \
        __global const real *restrict v_in, __global const real *restrict grid_v,                                      \
        __global const real *restrict grid_dv, __global const real *restrict release_time,                             \
        __global real *restrict x_out, __global real *restrict v_out, __global real *restrict C_out,                   \
        __global uchar *restrict clamped

/* Particle p's G2P and advection on grid g (its member's). */
inline void g2p_particle(const grid_t g, const int p, G2P_ARGS)
{
    const real dx = g.dx;
    real xp[3];
    vec3r v = 0, C0 = 0, C1 = 0, C2 = 0; /* v_pic and the rows of C */
#if CLFLOW_FLIP
    vec3r dv = 0;
#endif
    load_row(x_in, p, 3, xp);
    if (t >= release_time[p]) {
        const stencil_t st = make_stencil(&g, xp);
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                for (int k = 0; k < 3; ++k) {
                    const real w = st.w[0][i] * st.w[1][j] * st.w[2][k];
                    const vec3r d = (vec3r)((i - st.fx[0]) * dx, (j - st.fx[1]) * dx, (k - st.fx[2]) * dx);
                    const long node = grid_index(&g, st.base[0] + i, st.base[1] + j, st.base[2] + k);
                    const vec3r wv = w * vload3(node, grid_v);
#if CLFLOW_FLIP
                    dv += w * vload3(node, grid_dv);
#endif
                    v += wv;
                    C0 += wv.x * d;
                    C1 += wv.y * d;
                    C2 += wv.z * d;
                }
        const real scale = 4 / (dx * dx);
        C0 *= scale;
        C1 *= scale;
        C2 *= scale;
        int out = 0;
        for (int a = 0; a < 3; ++a) {
            const real lo = g.origin[a] + CLAMP_MARGIN * dx;
            const real hi = g.origin[a] + (grid_extent(&g, a) - 1 - CLAMP_MARGIN) * dx;
            const real moved = xp[a] + dt * (a == 0 ? v.x : (a == 1 ? v.y : v.z));
            xp[a] = clamp(moved, lo, hi);
            out |= xp[a] != moved;
        }
        if (out)
            clamped[p] = 1;
#if CLFLOW_FLIP
        v = flip * (vload3(p, v_in) + dv) + (1 - flip) * v;
#endif
    }
    store_row(x_out, p, 3, xp);
    vstore3(v, p, v_out);
    vstore3(C0, 3 * p, C_out);
    vstore3(C1, 3 * p + 1, C_out);
    vstore3(C2, 3 * p + 2, C_out);
}

#define G2P_PASS dt, t, flip, x_in, v_in, grid_v, grid_dv, release_time, x_out, v_out, C_out, clamped

/* A work-item per particle, in index order (after the private P2G, CPU devices' default, and
 * the atomic one: the state streams in order). */
__kernel void g2p(MPM_GRID_ARGS, const int n, G2P_ARGS)
{
    const int p = get_global_id(0);
    const grid_t g = MPM_GRID;
    if (p < n)
        g2p_particle(particle_grid(&g, p, n), p, G2P_PASS);
}

/* A work-item per slot of the particles sorted by cell (p = order[slot], mpm/p2g_gather.cl),
 * after the gather P2G (GPUs' default): neighbouring work-items read neighbouring grid nodes. */
__kernel void g2p_sorted(MPM_GRID_ARGS, const int n, __global const int *order, G2P_ARGS)
{
    const int s = get_global_id(0);
    const grid_t g = MPM_GRID;
    if (s < n)
        g2p_particle(particle_grid(&g, order[s], n), order[s], G2P_PASS);
}
