/* Substep stage 2, the deterministic parallel way: particle to grid as a gather per node.
 *
 * The same sums as p2g.cl (per node i and particle p with d = x_i - x_p:
 *   m_i += w m_p,  mv_i += w [m_p (v_p + dt a_p) + affine d],  mv0_i += w m_p (v_p + C_p d))
 * but each node adds its particles itself, in a fixed order: the particles sorted by the
 * cell of their stencil's base node (a stable sort of particle_cells' keys, so by index
 * within a cell), the 27 base cells that reach node i in the order (a, b, c). No atomics
 * and no private grid copies: the result repeats to the bit on any device and any number
 * of work-items, which the atomic scatter does not.
 *
 *   particle_cells : x -> key[p] = flat index of p's base node, id[p] = p
 *   (radix sort of (key, id), clflow.runtime.sort)
 *   key_ranges     : sorted keys -> ranges[2 cell] = [start, end) of the cell (zero-filled;
 *                    common/sort.cl, clflow.runtime.sort)
 *   p2g_gather     : one work-item per node */
#include "mpm/mpm.h"

#define P2G_GRID_ARGS                                                                                                  \
    const int nx, const int ny, const int nz, const real dx, const real ox, const real oy, const real oz

__kernel void particle_cells(P2G_GRID_ARGS, const int n, __global const real *x, __global uint *key, __global int *id)
{
    const int p = get_global_id(0);
    if (p >= n)
        return;
    const grid_t g = make_grid(nx, ny, nz, dx, ox, oy, oz);
    real xp[3];
    load_row(x, p, 3, xp);
    const stencil_t st = make_stencil(&g, xp);
    key[p] = (uint)grid_index(&g, st.base[0], st.base[1], st.base[2]);
    id[p] = p;
}

__kernel void p2g_gather(P2G_GRID_ARGS, const int n, const real dt, __global const real *x, __global const real *v,
                         __global const real *C, __global const real *tau, __global const real *mass,
                         __global const real *volume, __global const int *group, __global const real *accel,
                         __global const int *sorted_id, __global const int *ranges, __global real *grid)
{
    const long node = get_global_id(0);
    if (node >= (long)nx * ny * nz)
        return;
    const grid_t g = make_grid(nx, ny, nz, dx, ox, oy, oz);
    const int ni = node / ((long)ny * nz), nj = (node / nz) % ny, nk = node % nz;
    real m_sum = 0;
    vec3r mv_sum = 0;
#if CLFLOW_FLIP
    vec3r mv0_sum = 0;
#endif
    for (int a = 0; a < 3; ++a)
        for (int b = 0; b < 3; ++b)
            for (int c = 0; c < 3; ++c) {
                const int bi = ni - a, bj = nj - b, bk = nk - c; /* the base cell whose stencil has node at (a, b, c) */
                if (bi < 0 || bj < 0 || bk < 0 || bi > nx - 3 || bj > ny - 3 || bk > nz - 3)
                    continue;
                const long cell = grid_index(&g, bi, bj, bk);
                const int end = ranges[2 * cell + 1];
                for (int s = ranges[2 * cell]; s < end; ++s) {
                    const int p = sorted_id[s];
                    real xp[3];
                    load_row(x, p, 3, xp);
                    const stencil_t st = make_stencil(&g, xp);
                    const real w = st.w[0][a] * st.w[1][b] * st.w[2][c];
                    const vec3r d = (vec3r)((a - st.fx[0]) * dx, (b - st.fx[1]) * dx, (c - st.fx[2]) * dx);
                    const real m = mass[p];
                    const real stress_scale = -dt * volume[p] * 4 / (dx * dx);
                    vec3r affine[3];
                    for (int r = 0; r < 3; ++r)
                        affine[r] = stress_scale * vload3(3 * p + r, tau) + m * vload3(3 * p + r, C);
                    const int gp = group[p];
                    const vec3r vp = vload3(p, v);
                    const vec3r momentum = m * (vp + (gp >= 0 ? dt * vload3(gp, accel) : (vec3r)0));
                    m_sum += w * m;
                    mv_sum += w * (momentum + (vec3r)(dot(affine[0], d), dot(affine[1], d), dot(affine[2], d)));
#if CLFLOW_FLIP
                    const vec3r mC0 = m * vload3(3 * p, C), mC1 = m * vload3(3 * p + 1, C),
                                mC2 = m * vload3(3 * p + 2, C);
                    mv0_sum += w * (m * vp + (vec3r)(dot(mC0, d), dot(mC1, d), dot(mC2, d)));
#endif
                }
            }
    __global real *out = grid + GRID_CH * node;
    out[0] = m_sum;
    out[1] = mv_sum.x;
    out[2] = mv_sum.y;
    out[3] = mv_sum.z;
#if CLFLOW_FLIP
    out[4] = mv0_sum.x;
    out[5] = mv0_sum.y;
    out[6] = mv0_sum.z;
#endif
}
