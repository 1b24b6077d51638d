/* Substep stage 2: particle to grid (APIC / MLS-MPM momentum and mass transfer).
 *
 * For each of the 27 nodes i of particle p, with d = x_i - x_p:
 *   m_i  += w m_p
 *   mv_i += w [ m_p (v_p + dt a_p) + affine d ],  affine = m_p C_p - dt V_p (4/dx^2) tau_p
 * a_p = accel[group[p]] is the particle's driver acceleration (group -1: none).
 * Grid layout: grid[4*node + (0: m, 1..3: mv)].
 *
 * Two ways to sum, chosen by the host from the device record:
 *  - p2g_private + p2g_reduce (CPU devices, no float atomics): work-item k scatters the
 *    contiguous particle chunk k into its own grid copy with plain adds, then the copies
 *    are summed node by node in the fixed order k = 0, 1, ...: deterministic, bit-identical.
 *  - p2g_atomic (GPUs): one work-item per particle, atomic_add_real into one grid. */
#include "mpm/mpm.h"
#include "common/atomics.h"

inline void p2g_particle(const grid_t *g, const int p, const real dt, __global const real *x,
                         __global const real *v, __global const real *C, __global const real *tau,
                         __global const real *mass, __global const real *volume,
                         __global const int *group, __global const real *accel,
                         __global real *grid, const int use_atomics)
{
    real xp[3], vp[3], Cp[9], taup[9], affine[9];
    load_row(x, p, 3, xp);
    load_row(v, p, 3, vp);
    load_row(C, p, 9, Cp);
    load_row(tau, p, 9, taup);
    const real m = mass[p];
    const real stress_scale = -dt * volume[p] * 4 / (g->dx * g->dx);
    for (int k = 0; k < 9; ++k)
        affine[k] = stress_scale * taup[k] + m * Cp[k];
    const int gp = group[p];
    real momentum[3];
    for (int a = 0; a < 3; ++a)
        momentum[a] = m * (vp[a] + (gp >= 0 ? dt * accel[3 * gp + a] : 0));
    const stencil_t st = make_stencil(g, xp);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            for (int k = 0; k < 3; ++k) {
                const real w = st.w[0][i] * st.w[1][j] * st.w[2][k];
                const real d[3] = {(i - st.fx[0]) * g->dx, (j - st.fx[1]) * g->dx, (k - st.fx[2]) * g->dx};
                __global real *node = grid + 4 * grid_index(g, st.base[0] + i, st.base[1] + j, st.base[2] + k);
                real add[4];
                add[0] = w * m;
                for (int a = 0; a < 3; ++a)
                    add[1 + a] = w * (momentum[a] + affine[3 * a] * d[0] + affine[3 * a + 1] * d[1] +
                                      affine[3 * a + 2] * d[2]);
                if (use_atomics)
                    for (int c = 0; c < 4; ++c)
                        atomic_add_real(node + c, add[c]);
                else
                    for (int c = 0; c < 4; ++c)
                        node[c] += add[c];
            }
}

#define P2G_GRID_ARGS                                                                           \
    const int nx, const int ny, const int nz, const real dx, const real ox, const real oy,   \
        const real oz
#define P2G_PARTICLE_ARGS                                                                       \
    const int n, const real dt, __global const real *x, __global const real *v,              \
        __global const real *C, __global const real *tau, __global const real *mass,         \
        __global const real *volume, __global const int *group, __global const real *accel

/* Work-item k zeroes grid copy k and scatters particles [k*chunk, (k+1)*chunk) into it. */
__kernel void p2g_private(P2G_GRID_ARGS, P2G_PARTICLE_ARGS, const int copies, const int chunk,
                          __global real *grid_copies)
{
    const int k = get_global_id(0);
    if (k >= copies)
        return;
    const grid_t g = make_grid(nx, ny, nz, dx, ox, oy, oz);
    const long size = 4L * nx * ny * nz;
    __global real *grid = grid_copies + k * size;
    for (long e = 0; e < size; ++e)
        grid[e] = 0;
    const int end = min(n, (k + 1) * chunk);
    for (int p = k * chunk; p < end; ++p)
        p2g_particle(&g, p, dt, x, v, C, tau, mass, volume, group, accel, grid, 0);
}

/* grid[e] = sum over copies k = 0, 1, ... of grid_copies[k][e], in that order. */
__kernel void p2g_reduce(const long size, const int copies, __global const real *grid_copies,
                         __global real *grid)
{
    const long e = get_global_id(0);
    if (e >= size)
        return;
    real sum = grid_copies[e];
    for (int k = 1; k < copies; ++k)
        sum += grid_copies[k * size + e];
    grid[e] = sum;
}

/* One work-item per particle, atomic adds into `grid` (zeroed by the host). */
__kernel void p2g_atomic(P2G_GRID_ARGS, P2G_PARTICLE_ARGS, __global real *grid)
{
    const int p = get_global_id(0);
    if (p >= n)
        return;
    const grid_t g = make_grid(nx, ny, nz, dx, ox, oy, oz);
    p2g_particle(&g, p, dt, x, v, C, tau, mass, volume, group, accel, grid, 1);
}
