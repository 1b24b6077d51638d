/* Adjoint of G2P, the CPU shape of its scatter (clflow/runtime/plan.py: adjoint_scatter
 * "private", CPU devices by default): work-item k handles the contiguous particle chunk k into
 * its own grid copy; sum_grid_copies (p2g_private.cl) then sums the copies in a fixed order,
 * each only inside its box. The maths: g2p_adjoint.h. */
#include "mpm/adjoint/g2p_adjoint.h"

/* Work-item k zeroes grid copy k ([nodes, GV_CH]) in the box its particles [k*chunk, (k+1)*chunk)
 * touch (saved in boxes[6k .. 6k+5]) and scatters them into it; x_bar of those particles is
 * written directly. */
__kernel void g2p_adjoint_private(MPM_GRID_ARGS, const int n, const real dt, const real t, const real flip,
                                  __global const real *x_in, __global const real *v_out,
                                  __global const real *release_time, __global const real *grid_v,
                                  __global const real *grid_dv, __global const real *x_bar_out,
                                  __global const real *v_bar_out, __global const real *C_bar_out, const int copies,
                                  const int chunk, __global real *grid_v_bar_copies, __global int *boxes,
                                  __global real *x_bar)
{
    const int k = get_global_id(0);
    if (k >= copies)
        return;
    const grid_t g = MPM_GRID;
    int begin, end;
    __global real *grid_v_bar = chunk_copy(&g, x_in, n, k, chunk, GV_CH, grid_v_bar_copies, boxes, &begin, &end);
    for (int p = begin; p < end; ++p) {
        const grid_t gp = particle_grid(&g, p, n);
        g2p_adjoint_particle(&gp, p, dt, t, flip, x_in, v_out, release_time, grid_v, grid_dv, x_bar_out, v_bar_out,
                             C_bar_out, grid_v_bar, x_bar, 0);
    }
}
