/* Substep stage 2: particle to grid with atomic adds, only when asked for (clflow/runtime/plan.py:
 * P2G "atomic", from a simulator's p2g="atomic" or CLFLOW_P2G=atomic, on any device): a
 * work-item per particle adds its 27 nodes into one grid (zeroed by the host) with
 * atomic_add_real, in the order work-items happen to run, so runs differ in the last bits.
 * The sums of p2g_private.cl; by default CPU devices take that file, GPUs p2g_gather.cl. */
#include "mpm/mpm.h"
#include "common/atomics.h"

/* Particle p's 27 nodes, atomic adds (p2g_atomic). */
inline void p2g_particle_atomic(const grid_t *g, const int p, const real dt, __global const real *x,
                                __global const real *v, __global const real *C, __global const real *tau,
                                __global const real *mass, __global const real *volume, __global const int *group,
                                __global const real *accel, __global real *grid)
{
    real xp[3];
    load_row(x, p, 3, xp);
    const real m = mass[p];
    const real stress_scale = -dt * volume[p] * 4 / (g->dx * g->dx);
    vec3r affine[3]; /* rows of m C - dt V (4/dx^2) tau */
    for (int r = 0; r < 3; ++r)
        affine[r] = stress_scale * vload3(3 * p + r, tau) + m * vload3(3 * p + r, C);
    const int gp = group[p];
    const vec3r vp = vload3(p, v);
    const vec3r momentum = m * (vp + (gp >= 0 ? dt * vload3(gp, accel) : (vec3r)0));
#if CLFLOW_FLIP
    const vec3r mC[3] = {m * vload3(3 * p, C), m * vload3(3 * p + 1, C), m * vload3(3 * p + 2, C)};
#endif
    const stencil_t st = make_stencil(g, xp);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            for (int k = 0; k < 3; ++k) {
                const real w = st.w[0][i] * st.w[1][j] * st.w[2][k];
                const vec3r d = (vec3r)((i - st.fx[0]) * g->dx, (j - st.fx[1]) * g->dx, (k - st.fx[2]) * g->dx);
                const vec3r mv = w * (momentum + (vec3r)(dot(affine[0], d), dot(affine[1], d), dot(affine[2], d)));
                __global real *node = grid + GRID_CH * grid_index(g, st.base[0] + i, st.base[1] + j, st.base[2] + k);
#if CLFLOW_FLIP
                const vec3r mv0 = w * (m * vp + (vec3r)(dot(mC[0], d), dot(mC[1], d), dot(mC[2], d)));
#endif
                atomic_add_real(node, w * m);
                atomic_add_real(node + 1, mv.x);
                atomic_add_real(node + 2, mv.y);
                atomic_add_real(node + 3, mv.z);
#if CLFLOW_FLIP
                atomic_add_real(node + 4, mv0.x);
                atomic_add_real(node + 5, mv0.y);
                atomic_add_real(node + 6, mv0.z);
#endif
            }
}

/* One work-item per particle, atomic adds into `grid` (zeroed by the host). */
__kernel void p2g_atomic(MPM_GRID_ARGS, P2G_PARTICLE_ARGS, __global real *grid)
{
    const int p = get_global_id(0);
    if (p >= n)
        return;
    const grid_t g0 = MPM_GRID, g = particle_grid(&g0, p, n);
    p2g_particle_atomic(&g, p, dt, x, v, C, tau, mass, volume, group, accel, grid);
}
