/* Adjoint of G2P, the GPU shape of its scatter (clflow/runtime/plan.py: adjoint_scatter
 * "gather", GPUs by default): a work-item per particle slot (particles sorted by cell,
 * mpm/p2g_gather.cl particle_cells) computes xbar and writes what the grid needs of the
 * particle into its slot's record (g2p_adjoint_records); then a work-item per node sums the
 * records of the particles whose stencil reaches it, cell by cell in a fixed order
 * (g2p_adjoint_gather). The maths: g2p_adjoint.h. */
#include "mpm/adjoint/g2p_adjoint.h"
#include "mpm/cells.h"

/* A work-item per slot of the particles sorted by cell (p = order[slot]): x_bar[p], and the
 * slot's record for g2p_adjoint_gather. */
__kernel void g2p_adjoint_records(const int nx, const int ny, const int nz, const real dx, const real ox, const real oy,
                                  const real oz, const int n, const real dt, const real t, const real flip,
                                  __global const real *x_in, __global const real *v_out,
                                  __global const real *release_time, __global const real *grid_v,
                                  __global const real *grid_dv, __global const real *x_bar_out,
                                  __global const real *v_bar_out, __global const real *C_bar_out,
                                  __global const int *order, __global real *records, __global real *x_bar)
{
    const int s = get_global_id(0);
    if (s >= n)
        return;
    const grid_t g = make_grid(nx, ny, nz, dx, ox, oy, oz);
    g2p_adjoint_particle(&g, order[s], dt, t, flip, x_in, v_out, release_time, grid_v, grid_dv, x_bar_out, v_bar_out,
                         C_bar_out, 0, x_bar, records + (long)G2P_ADJ_REC * s);
}

/* A work-item per node: grid_v_bar[node] = sum over the particles whose stencil reaches it (27
 * base cells in the order (a, b, c), each cell's slots in order) of w (u + B d)[, w flip vbar']. */
__kernel void g2p_adjoint_gather(const int nx, const int ny, const int nz, const real dx, const real ox, const real oy,
                                 const real oz, __global const real *records, __global const int *starts,
                                 __global real *grid_v_bar)
{
    const long node = get_global_id(0);
    if (node >= (long)nx * ny * nz)
        return;
    const grid_t g = make_grid(nx, ny, nz, dx, ox, oy, oz);
    const int ni = node / ((long)ny * nz), nj = (node / nz) % ny, nk = node % nz;
    real sum[GV_CH];
    for (int q = 0; q < GV_CH; ++q)
        sum[q] = 0;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            for (int k = 0; k < 3; ++k) {
                const int2 run = cell_run(&g, starts, ni - i, nj - j, nk - k);
                for (int s = run.x; s < run.y; ++s) {
                    __global const real *rec = records + (long)G2P_ADJ_REC * s;
                    const real xp[3] = {rec[0], rec[1], rec[2]};
                    const stencil_t st = make_stencil(&g, xp);
                    const real w = st.w[0][i] * st.w[1][j] * st.w[2][k];
                    const real d[3] = {(i - st.fx[0]) * dx, (j - st.fx[1]) * dx, (k - st.fx[2]) * dx};
                    __global const real *u = rec + 3, *B = rec + 6;
                    for (int a = 0; a < 3; ++a) {
                        const real Bd = B[3 * a] * d[0] + B[3 * a + 1] * d[1] + B[3 * a + 2] * d[2];
                        sum[a] += w * (u[a] + Bd);
                    }
#if CLFLOW_FLIP
                    for (int a = 0; a < 3; ++a)
                        sum[3 + a] += w * rec[15 + a];
#endif
                }
            }
    for (int q = 0; q < GV_CH; ++q)
        grid_v_bar[GV_CH * node + q] = sum[q];
}
