/* Adjoint of G2P, the GPU shape of its scatter (clflow/runtime/plan.py: adjoint_scatter
 * "gather", GPUs by default): a work-item per particle slot (particles sorted by cell,
 * mpm/p2g_gather.cl particle_cells) computes xbar and writes what the grid needs of the
 * particle into its slot's record (g2p_adjoint_records); then a work-item per node sums the
 * records of the particles whose stencil reaches it, cell by cell in a fixed order, and takes
 * the grid update's adjoint of the node (g2p_adjoint_gather_update). The maths: g2p_adjoint.h. */
#include "mpm/adjoint/g2p_adjoint.h"
#include "mpm/adjoint/grid_adjoint.cl"
#include "mpm/cells.h"

/* A work-item per slot of the particles sorted by cell (p = order[slot]): x_bar[p], and the
 * slot's record for g2p_adjoint_gather_update. */
__kernel void g2p_adjoint_records(MPM_GRID_ARGS, const int n, const real dt, const real t, const real flip,
                                  __global const real *x_in, __global const real *v_out,
                                  __global const real *release_time, __global const real *grid_v,
                                  __global const real *grid_dv, __global const real *x_bar_out,
                                  __global const real *v_bar_out, __global const real *C_bar_out,
                                  __global const int *order, __global real *records, __global real *x_bar)
{
    const int s = get_global_id(0);
    if (s >= n)
        return;
    const grid_t g0 = MPM_GRID, g = particle_grid(&g0, order[s], n);
    g2p_adjoint_particle(&g, order[s], dt, t, flip, x_in, v_out, release_time, grid_v, grid_dv, x_bar_out, v_bar_out,
                         C_bar_out, 0, x_bar, records + (long)G2P_ADJ_REC * s);
}

/* A work-item per node: grid_v_bar[node] = sum over the particles whose stencil reaches it (27
 * base cells in the order of gather_run, each cell's slots in order) of w (u + B d)[, w flip vbar'],
 * then the grid update's adjoint of the node from it (grid_adjoint.cl), in one launch. */
__kernel void g2p_adjoint_gather_update(GRID_UPDATE_ARGS, __global const real *records, __global const int *starts,
                                        __global real *grid_v_bar, __global const real *grid, __global const real *bc,
                                        const int n_bc, __global real *grid_bar)
{
    const long node = get_global_id(0);
    const grid_t g0 = MPM_GRID;
    if (node >= population_nodes(&g0))
        return;
    int ni, nj, nk;
    const grid_t g = node_grid(&g0, node, &ni, &nj, &nk);
    real sum[GV_CH];
    for (int q = 0; q < GV_CH; ++q)
        sum[q] = 0;
    for (int o = 0; o < 27; ++o) {
        const int2 run = gather_run(&g, starts, ni, nj, nk, o);
        for (int s = run.x; s < run.y; ++s) {
            real w, d[3];
            __global const real *rec = gather_record(&g, records, G2P_ADJ_REC, s, o, &w, d);
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
    update_node_adjoint(node, ni, nj, nk, dx, ox, oy, oz, dt, t, gx, gy, gz, mass_eps, grid, grid_v_bar, bc, n_bc,
                        grid_bar);
}
