/* Substep stage 2, the GPU shape (clflow/runtime/plan.py: P2G "gather", GPUs by default):
 * particle to grid as a gather per node, over particles sorted by cell.
 *
 * The same sums as p2g_private.cl (per node i and particle p with d = x_i - x_p:
 *   m_i += w m_p,  mv_i += w [m_p (v_p + dt a_p) + affine d],  mv0_i += w m_p (v_p + C_p d))
 * but each node adds its particles itself, in a fixed order: the 27 base cells whose
 * stencil reaches it in the order of gather_run (mpm/cells.h), each cell's particles in index
 * order. No atomics and no private grid copies: the result repeats to the bit on any device
 * and any number of work-items.
 *
 *   particle_cells : x -> key[p] = flat index of p's base cell, counted (cells.h count_cell;
 *                    in the GPU plan the stress kernel counts them, mpm/stress.cl)
 *   (counting sort, clflow.runtime.sort: the counts scanned into starts[cell], the first slot
 *   of each cell's run, and each particle placed in its cell's run)
 *   order_pack     : a work-item per cell: its run in index order, then the particle data P2G
 *                    reads in slot order, records [n, P2G_REC] (x, m, momentum, affine[, m v,
 *                    m C]): the gather then reads runs of contiguous memory instead of
 *                    chasing particle indices
 *   p2g_gather_update : one work-item per node, its sums and then its grid update */
#include "common/runs.h"
#include "mpm/cells.h"
/* update_node and GRID_UPDATE_ARGS, for p2g_gather_update */
#include "mpm/grid.cl"

/* record of a slot: x (3), m, momentum m (v + dt a) (3), affine = m C - dt V (4/dx^2) tau (3 x 3)
 * and, with CLFLOW_FLIP, m v (3) and m C (3 x 3) */
#define P2G_REC (CLFLOW_FLIP ? 28 : 16)

/* Each particle counted into its base cell (cells.h count_cell): the cell sort's keys where the
 * stress kernel does not count them itself (mpm/stress.cl update_stress_cells). */
__kernel void particle_cells(MPM_GRID_ARGS, const int n, __global const real *x, CELL_KEY_ARGS)
{
    const int p = get_global_id(0);
    if (p >= n)
        return;
    const grid_t g0 = MPM_GRID, g = particle_grid(&g0, p, n);
    real xp[3];
    load_row(x, p, 3, xp);
    count_cell(&g, p, xp, key, counts, rank);
}

/* Slot s's record, of particle p. */
inline void pack_slot(const int s, const int p, const real dx, const real dt, __global const real *x,
                      __global const real *v, __global const real *C, __global const real *tau,
                      __global const real *mass, __global const real *volume, __global const int *group,
                      __global const real *accel, __global real *records)
{
    __global real *rec = records + (long)P2G_REC * s;
    const real m = mass[p];
    const real stress_scale = -dt * volume[p] * 4 / (dx * dx);
    const int gp = group[p];
    const vec3r vp = vload3(p, v);
    vstore3(vload3(p, x), 0, rec);
    rec[3] = m;
    vstore3(m * (vp + (gp >= 0 ? dt * vload3(gp, accel) : (vec3r)0)), 0, rec + 4);
    for (int r = 0; r < 3; ++r)
        vstore3(stress_scale * vload3(3 * p + r, tau) + m * vload3(3 * p + r, C), 0, rec + 7 + 3 * r);
#if CLFLOW_FLIP
    vstore3(m * vp, 0, rec + 16);
    for (int r = 0; r < 3; ++r)
        vstore3(m * vload3(3 * p + r, C), 0, rec + 19 + 3 * r);
#endif
}

/* A work-item per cell: its run of `order` put in index order (common/runs.h; the atomics
 * placed it in no fixed order), then the record of each of its slots. */
__kernel void order_pack(const int n_cells, __global const int *starts, __global int *order, const real dx,
                         const real dt, __global const real *x, __global const real *v, __global const real *C,
                         __global const real *tau, __global const real *mass, __global const real *volume,
                         __global const int *group, __global const real *accel, __global real *records)
{
    const int cell = get_global_id(0);
    if (cell >= n_cells)
        return;
    const int begin = starts[cell], end = starts[cell + 1];
    sort_run(order, begin, end);
    for (int s = begin; s < end; ++s)
        pack_slot(s, order[s], dx, dt, x, v, C, tau, mass, volume, group, accel, records);
}

/* The sums of node (ni, nj, nk), flat index `node`, into grid[node] (GRID_CH reals). */
inline void gather_node(const grid_t *g, const long node, const int ni, const int nj, const int nk,
                        __global const real *records, __global const int *starts, __global real *grid)
{
    real m_sum = 0;
    vec3r mv_sum = 0;
#if CLFLOW_FLIP
    vec3r mv0_sum = 0;
#endif
    for (int o = 0; o < 27; ++o) {
        const int2 run = gather_run(g, starts, ni, nj, nk, o);
        for (int s = run.x; s < run.y; ++s) {
            real w, da[3];
            __global const real *rec = gather_record(g, records, P2G_REC, s, o, &w, da);
            const vec3r d = (vec3r)(da[0], da[1], da[2]);
            const vec3r affine0 = vload3(0, rec + 7), affine1 = vload3(0, rec + 10), affine2 = vload3(0, rec + 13);
            m_sum += w * rec[3];
            mv_sum += w * (vload3(0, rec + 4) + (vec3r)(dot(affine0, d), dot(affine1, d), dot(affine2, d)));
#if CLFLOW_FLIP
            const vec3r mC0 = vload3(0, rec + 19), mC1 = vload3(0, rec + 22), mC2 = vload3(0, rec + 25);
            mv0_sum += w * (vload3(0, rec + 16) + (vec3r)(dot(mC0, d), dot(mC1, d), dot(mC2, d)));
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

/* A work-item per node: its sums (kept in `grid`: the adjoint reads them), then its grid
 * update (grid.cl update_node: velocity, gravity, boundary conditions[, dv]) from them, in
 * one launch for the substep's stages 2 and 3. */
__kernel void p2g_gather_update(GRID_UPDATE_ARGS, __global const real *records, __global const int *starts,
                                __global real *grid, __global real *grid_v, __global real *grid_dv,
                                __global const real *bc, const int n_bc)
{
    const long node = get_global_id(0);
    const grid_t g0 = MPM_GRID;
    if (node >= population_nodes(&g0))
        return;
    int ni, nj, nk;
    const grid_t g = node_grid(&g0, node, &ni, &nj, &nk);
    gather_node(&g, node, ni, nj, nk, records, starts, grid);
    const real gravity[3] = {gx, gy, gz};
    update_node(&g, node, ni, nj, nk, dt, t, gravity, mass_eps, grid, grid_v, grid_dv, bc, n_bc);
}
