/* Substep stage 2: particle to grid (APIC / MLS-MPM momentum and mass transfer), the CPU
 * shape (clflow/runtime/plan.py: P2G "private", CPU devices by default).
 *
 * For each of the 27 nodes i of particle p, with d = x_i - x_p:
 *   m_i  += w m_p
 *   mv_i += w [ m_p (v_p + dt a_p) + affine d ],  affine = m_p C_p - dt V_p (4/dx^2) tau_p
 * and, with the PIC/FLIP blend (CLFLOW_FLIP), the momentum before the forces:
 *   mv0_i += w m_p (v_p + C_p d)
 * a_p = accel[group[p]] is the particle's driver acceleration (group -1: none).
 * Grid layout: grid[GRID_CH*node + (0: m, 1..3: mv, 4..6: mv0 with CLFLOW_FLIP)].
 *
 * p2g_private + sum_copies_update_grid (grid.cl): work-item k scatters the contiguous particle
 * chunk k into its own grid copy with plain adds, then the copies are summed node by node in
 * the fixed order k = 0, 1, ...: deterministic, bit-identical. Each copy is zeroed and summed
 * only in the box of nodes its chunk touches (chunk_box). sum_grid_copies is the same column
 * sum for the G2P adjoint's private copies. The other shapes of the same sums:
 * p2g_gather.cl (GPUs: a gather over blocks of cells, particles sorted by cell) and p2g_atomic.cl
 * (asked for: atomic adds). */
#include "mpm/mpm.h"

/* dot(a, b) of 3-vectors in lanes, as the dot builtin rounds it: (a0 b0 + a1 b1) + a2 b2, each
 * product and sum rounded on its own (separate statements: no fused multiply-add). */
inline realv dot3_v(const realv *a, const realv *b)
{
    const realv xx = a[0] * b[0];
    const realv yy = a[1] * b[1];
    const realv zz = a[2] * b[2];
    const realv xy = xx + yy;
    return xy + zz;
}

/* Particles p0 .. min(p0 + CLFLOW_SIMD_LANES, end) - 1 (of n) into a grid copy with plain adds: their
 * node values computed in vector lanes, lane by lane the operations of p2g_particle_atomic (p2g_atomic.cl),
 * then added particle after particle, each one's 27 nodes in order: the sums of a scalar loop
 * over the particles to the bit, for a fraction of the arithmetic (CPU compilers do not
 * vectorise p2g_private's loop). */
inline void p2g_lanes(const grid_t *g, const int n, const int p0, const int end, const real dt, __global const real *x,
                      __global const real *v, __global const real *C, __global const real *tau,
                      __global const real *mass, __global const real *volume, __global const int *group,
                      __global const real *accel, __global real *grid)
{
    realv xv[3], m, momentum[3], affine[3][3];
#if CLFLOW_FLIP
    realv vel[3], mC[3][3];
#endif
    for (int l = 0; l < CLFLOW_SIMD_LANES; ++l) { /* the per-particle values */
        const int p = min(p0 + l, end - 1);
        const real mp = mass[p];
        const real stress_scale = -dt * volume[p] * 4 / (g->dx * g->dx);
        const int gp = group[p];
        const vec3r vp = vload3(p, v);
        const vec3r mom = mp * (vp + (gp >= 0 ? dt * vload3(gp, accel) : (vec3r)0));
        ((real *)&m)[l] = mp;
        for (int a = 0; a < 3; ++a) {
            ((real *)&xv[a])[l] = x[3 * (long)p + a];
            ((real *)&momentum[a])[l] = a == 0 ? mom.x : (a == 1 ? mom.y : mom.z);
        }
        for (int r = 0; r < 3; ++r) {
            const vec3r row = stress_scale * vload3(3 * p + r, tau) + mp * vload3(3 * p + r, C);
            ((real *)&affine[r][0])[l] = row.x;
            ((real *)&affine[r][1])[l] = row.y;
            ((real *)&affine[r][2])[l] = row.z;
#if CLFLOW_FLIP
            const vec3r mCr = mp * vload3(3 * p + r, C);
            ((real *)&mC[r][0])[l] = mCr.x;
            ((real *)&mC[r][1])[l] = mCr.y;
            ((real *)&mC[r][2])[l] = mCr.z;
            ((real *)&vel[r])[l] = r == 0 ? vp.x : (r == 1 ? vp.y : vp.z);
#endif
        }
    }
    const stencil_v_t st = make_stencil_v(g, xv, p0, n);
    realv node_w[27], node_mv[27][3];
#if CLFLOW_FLIP
    realv node_mv0[27][3];
#endif
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            for (int k = 0; k < 3; ++k) {
                const int o = 9 * i + 3 * j + k;
                const realv w = st.w[0][i] * st.w[1][j] * st.w[2][k];
                const realv d[3] = {((real)i - st.fx[0]) * g->dx, ((real)j - st.fx[1]) * g->dx,
                                    ((real)k - st.fx[2]) * g->dx};
                node_w[o] = w;
                for (int r = 0; r < 3; ++r) {
                    node_mv[o][r] = w * (momentum[r] + dot3_v(affine[r], d));
#if CLFLOW_FLIP
                    node_mv0[o][r] = w * (m * vel[r] + dot3_v(mC[r], d));
#endif
                }
            }
    for (int l = 0; l < min(CLFLOW_SIMD_LANES, end - p0); ++l) {
        const real mp = LANE(m, l);
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                for (int k = 0; k < 3; ++k) {
                    const int o = 9 * i + 3 * j + k;
                    __global real *node = grid + GRID_CH * (st.corner[l] + node_offset(g, i, j, k));
                    node[0] += LANE(node_w[o], l) * mp;
                    node[1] += LANE(node_mv[o][0], l);
                    node[2] += LANE(node_mv[o][1], l);
                    node[3] += LANE(node_mv[o][2], l);
#if CLFLOW_FLIP
                    node[4] += LANE(node_mv0[o][0], l);
                    node[5] += LANE(node_mv0[o][1], l);
                    node[6] += LANE(node_mv0[o][2], l);
#endif
                }
    }
}

/* Work-item k zeroes grid copy k in the box its particles [k*chunk, (k+1)*chunk) touch (saved
 * in boxes[6k .. 6k+5]) and scatters them into it. */
__kernel void p2g_private(MPM_GRID_ARGS, P2G_PARTICLE_ARGS, const int copies, const int chunk,
                          __global real *grid_copies, __global int *boxes)
{
    const int k = get_global_id(0);
    if (k >= copies)
        return;
    const grid_t g = MPM_GRID;
    int begin, end;
    __global real *grid = chunk_copy(&g, x, n, k, chunk, GRID_CH, grid_copies, boxes, &begin, &end);
    for (int p0 = begin; p0 < end; p0 += CLFLOW_SIMD_LANES)
        p2g_lanes(&g, n, p0, end, dt, x, v, C, tau, mass, volume, group, accel, grid);
}

/* grid[node] = the sum over copies k = 0, 1, ..., in that order, of copies[k][node] ([nodes,
 * channels] each), each copy counted as zero outside its box (chunk_box): the column sum of the
 * private-copy scatters (g2p_adjoint_private's here; p2g_private's in grid.cl's
 * sum_copies_update_grid). A work-item per row of nodes (sum_copies_row) of the stacked grid:
 * nx counts all members' nodes along x (mpm.h). */
__kernel void sum_grid_copies(const int nx, const int ny, const int nz, const int channels, const int copies,
                              __global const int *boxes, __global const real *grid_copies, __global real *grid)
{
    const int row = get_global_id(0);
    if (row >= nx * ny)
        return;
    int lo, hi;
    sum_copies_row(nx, ny, nz, channels, copies, boxes, grid_copies, grid, row, &lo, &hi);
}
