/* Substep stage 2, the GPU shape (clflow/runtime/plan.py: P2G "gather", GPUs by default):
 * particle to grid as gathers over blocks of cells, over particles sorted by cell, reading each
 * particle once.
 *
 * The same sums as p2g_private.cl (per node i and particle p with d = x_i - x_p:
 *   m_i += w m_p,  mv_i += w [m_p (v_p + dt a_p) + affine d],  mv0_i += w m_p (v_p + C_p d))
 * in a fixed order, with no atomics on reals and no private grid copies: the result repeats to
 * the bit on any device and any number of work-groups.
 *
 *   particle_cells    : x -> key[p] = flat index of p's base cell, counted (cells.h count_cell;
 *                       in the GPU plan the stress kernel counts them, mpm/stress.cl)
 *   (counting sort, clflow.runtime.sort: the counts scanned into starts[cell], the first slot
 *   of each cell's run, and each particle placed in its cell's run)
 *   p2g_blocks        : a work-group per block of P2G_BLOCK^3 base cells and a work-item per
 *                       node of the block's tile, the P2G_TILE^3 nodes its particles' stencils
 *                       reach. The group puts each cell's run in index order, then stages the
 *                       block's particles, P2G_STAGE at a time, as records in local memory (each
 *                       particle read from global memory once, by the one block that holds its
 *                       base cell), and each work-item adds those whose stencil reaches its
 *                       node. Its tile's sums go to `partials`; an empty block only says so.
 *   p2g_blocks_update : a work-item per node: the partial sums of the (up to 8) tiles that
 *                       hold it, in block order, then its grid update (grid.cl update_node).
 *
 * A node's order: the blocks in increasing index; in each, the stages in order; in each stage,
 * the 27 base cells of gather_run's order (mpm/cells.h), each cell's particles in index order. */
#include "common/runs.h"
#include "mpm/cells.h"
/* update_node and GRID_UPDATE_ARGS, for p2g_blocks_update */
#include "mpm/grid.cl"

/* The blocks: P2G_BLOCK base cells a side; a tile, the nodes its stencils reach, P2G_TILE a
 * side (clflow.mpm.substep.P2G_BLOCK); P2G_STAGE particles staged at a time. */
#define P2G_BLOCK       4
#define P2G_TILE        (P2G_BLOCK + 2)
#define P2G_BLOCK_CELLS (P2G_BLOCK * P2G_BLOCK * P2G_BLOCK)
#define P2G_TILE_NODES  (P2G_TILE * P2G_TILE * P2G_TILE)
#define P2G_STAGE       64
/* a staged particle: x (3), m, momentum m (v + dt a) (3), affine = m C - dt V (4/dx^2) tau
 * (3 x 3)[, m v (3), m C (3 x 3)], then its stencil's fx (3) and weights w[axis][0..2] (9) */
#define P2G_REC   (CLFLOW_FLIP ? 28 : 16)
#define STAGE_REC (P2G_REC + 12)

/* Blocks along one axis of n nodes: the base cells are 0 .. n - 3. */
inline int blocks_along(const int n)
{
    return (n - 2 + P2G_BLOCK - 1) / P2G_BLOCK;
}

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

/* With CLFLOW_COUNT_READS, the P2G kernels count the particles they read from global memory
 * into reads[0] (tests/mpm: the design's one read a particle). */
#if CLFLOW_COUNT_READS
#define P2G_READS_ARG , __global int *reads
#define COUNT_READ()  atomic_inc(reads)
#else
#define P2G_READS_ARG
#define COUNT_READ()
#endif

/* Particle p's staged record at rec (local memory). */
inline void stage_particle(const grid_t *g, const int p, const real dt, __global const real *x, __global const real *v,
                           __global const real *C, __global const real *tau, __global const real *mass,
                           __global const real *volume, __global const int *group, __global const real *accel,
                           __local real *rec)
{
    const real m = mass[p];
    const real stress_scale = -dt * volume[p] * 4 / (g->dx * g->dx);
    const int gp = group[p];
    const vec3r vp = vload3(p, v), xp = vload3(p, x);
    const vec3r momentum = m * (vp + (gp >= 0 ? dt * vload3(gp, accel) : (vec3r)0));
    const real xa[3] = {xp.x, xp.y, xp.z};
    const stencil_t st = make_stencil(g, xa);
    rec[0] = xp.x, rec[1] = xp.y, rec[2] = xp.z;
    rec[3] = m;
    rec[4] = momentum.x, rec[5] = momentum.y, rec[6] = momentum.z;
    for (int r = 0; r < 3; ++r) {
        const vec3r affine = stress_scale * vload3(3 * p + r, tau) + m * vload3(3 * p + r, C);
        rec[7 + 3 * r] = affine.x, rec[8 + 3 * r] = affine.y, rec[9 + 3 * r] = affine.z;
    }
#if CLFLOW_FLIP
    rec[16] = m * vp.x, rec[17] = m * vp.y, rec[18] = m * vp.z;
    for (int r = 0; r < 3; ++r) {
        const vec3r mC = m * vload3(3 * p + r, C);
        rec[19 + 3 * r] = mC.x, rec[20 + 3 * r] = mC.y, rec[21 + 3 * r] = mC.z;
    }
#endif
    for (int a = 0; a < 3; ++a) {
        rec[P2G_REC + a] = st.fx[a];
        for (int b = 0; b < 3; ++b)
            rec[P2G_REC + 3 + 3 * a + b] = st.w[a][b];
    }
}

/* A work-group per (member, block), a work-item per node of the block's tile (local size
 * P2G_TILE_NODES): the tile's sums of the block's particles into partials [blocks, P2G_TILE_NODES,
 * GRID_CH] and the block's particle count into block_counts [blocks] (0: the block is empty and
 * wrote no sums). Also puts each cell's run of `order` in index order (G2P and the adjoint read it). */
__kernel void p2g_blocks(MPM_GRID_ARGS, P2G_PARTICLE_ARGS, __global const int *starts, __global int *order,
                         __global real *partials, __global int *block_counts P2G_READS_ARG)
{
    __local int cell_first[P2G_BLOCK_CELLS];     /* the first slot of each cell's run */
    __local int cell_begin[P2G_BLOCK_CELLS + 1]; /* each cell's first particle among the block's */
    __local real stage[P2G_STAGE * STAGE_REC];
    const int l = get_local_id(0), group_id = get_group_id(0);
    const grid_t g0 = MPM_GRID;
    const int bx = blocks_along(nx), by = blocks_along(ny), bz = blocks_along(nz);
    const int member_blocks = bx * by * bz, block = group_id % member_blocks;
    grid_t g = g0;
    g.offset = (long)(group_id / member_blocks) * grid_nodes(&g0);
    const int b0[3] = {P2G_BLOCK * (block / (by * bz)), P2G_BLOCK * (block / bz % by), P2G_BLOCK * (block % bz)};

    if (l < P2G_BLOCK_CELLS) {
        const int2 run = cell_run(&g, starts, b0[0] + l / (P2G_BLOCK * P2G_BLOCK), b0[1] + l / P2G_BLOCK % P2G_BLOCK,
                                  b0[2] + l % P2G_BLOCK);
        sort_run(order, run.x, run.y);
        cell_first[l] = run.x;
        cell_begin[l + 1] = run.y - run.x;
    }
    barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
    if (l == 0) {
        cell_begin[0] = 0;
        for (int c = 0; c < P2G_BLOCK_CELLS; ++c)
            cell_begin[c + 1] += cell_begin[c];
        block_counts[group_id] = cell_begin[P2G_BLOCK_CELLS];
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    const int total = cell_begin[P2G_BLOCK_CELLS];
    if (total == 0)
        return; /* the whole group: total is the same for every work-item */

    /* this work-item's node, at (ta, tb, tc) in the tile, and the block's cells (ca, cb, cc) whose
     * stencils reach it: node - cell in 0..2 per axis */
    const int t[3] = {l / (P2G_TILE * P2G_TILE), l / P2G_TILE % P2G_TILE, l % P2G_TILE};
    int lo[3], hi[3];
    for (int a = 0; a < 3; ++a) {
        lo[a] = max(0, t[a] - 2);
        hi[a] = min(P2G_BLOCK - 1, t[a]);
    }
    real m_sum = 0;
    vec3r mv_sum = 0;
#if CLFLOW_FLIP
    vec3r mv0_sum = 0;
#endif
    for (int q0 = 0; q0 < total; q0 += P2G_STAGE) {
        for (int q = l; q < P2G_STAGE && q0 + q < total; q += P2G_TILE_NODES) {
            int c = 0; /* the cell of the block's particle q0 + q: cell_begin[c] <= q0 + q < cell_begin[c + 1] */
            for (int step = P2G_BLOCK_CELLS / 2; step > 0; step >>= 1)
                if (cell_begin[c + step] <= q0 + q)
                    c += step;
            const int p = order[cell_first[c] + q0 + q - cell_begin[c]];
            COUNT_READ();
            stage_particle(&g, p, dt, x, v, C, tau, mass, volume, group, accel, stage + STAGE_REC * q);
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        /* the cells in gather_run's order: o = 9a + 3b + c increasing, cell = node - (a, b, c) */
        for (int ca = hi[0]; ca >= lo[0]; --ca)
            for (int cb = hi[1]; cb >= lo[1]; --cb)
                for (int cc = hi[2]; cc >= lo[2]; --cc) {
                    const int cell = (ca * P2G_BLOCK + cb) * P2G_BLOCK + cc;
                    const int a = t[0] - ca, b = t[1] - cb, c = t[2] - cc;
                    const int from = max(cell_begin[cell], q0) - q0;
                    const int to = min(cell_begin[cell + 1], q0 + P2G_STAGE) - q0;
                    for (int s = from; s < to; ++s) {
                        __local const real *rec = stage + STAGE_REC * s;
                        __local const real *fx = rec + P2G_REC, *w = rec + P2G_REC + 3;
                        const real weight = w[a] * w[3 + b] * w[6 + c];
                        const vec3r d = (vec3r)((a - fx[0]) * dx, (b - fx[1]) * dx, (c - fx[2]) * dx);
                        const vec3r affine0 = vload3(0, rec + 7), affine1 = vload3(0, rec + 10);
                        const vec3r affine2 = vload3(0, rec + 13);
                        m_sum += weight * rec[3];
                        mv_sum +=
                            weight * (vload3(0, rec + 4) + (vec3r)(dot(affine0, d), dot(affine1, d), dot(affine2, d)));
#if CLFLOW_FLIP
                        const vec3r mC0 = vload3(0, rec + 19), mC1 = vload3(0, rec + 22), mC2 = vload3(0, rec + 25);
                        mv0_sum += weight * (vload3(0, rec + 16) + (vec3r)(dot(mC0, d), dot(mC1, d), dot(mC2, d)));
#endif
                    }
                }
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    __global real *out = partials + GRID_CH * ((long)P2G_TILE_NODES * group_id + l);
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

/* A work-item per node: its sums from the tiles of the non-empty blocks that hold it
 * (p2g_blocks), in increasing block index, into grid[node] (the adjoint reads them), then its
 * grid update (grid.cl update_node: velocity, gravity, boundary conditions[, dv]). */
__kernel void p2g_blocks_update(GRID_UPDATE_ARGS, __global const real *partials, __global const int *block_counts,
                                __global real *grid, __global real *grid_v, __global real *grid_dv,
                                __global const real *bc, const int n_bc)
{
    const long node = get_global_id(0);
    const grid_t g0 = MPM_GRID;
    if (node >= population_nodes(&g0))
        return;
    int ni, nj, nk;
    const grid_t g = node_grid(&g0, node, &ni, &nj, &nk);
    const int n3[3] = {ni, nj, nk}, nb[3] = {blocks_along(nx), blocks_along(ny), blocks_along(nz)};
    int lo[3], hi[3]; /* the blocks whose tile holds the node: b P2G_BLOCK <= n < b P2G_BLOCK + P2G_TILE */
    for (int a = 0; a < 3; ++a) {
        lo[a] = max(0, (n3[a] - P2G_TILE + P2G_BLOCK) / P2G_BLOCK);
        hi[a] = min(nb[a] - 1, n3[a] / P2G_BLOCK);
    }
    real sum[GRID_CH];
    for (int q = 0; q < GRID_CH; ++q)
        sum[q] = 0;
    const long first_block = (g.offset / grid_nodes(&g0)) * nb[0] * nb[1] * nb[2];
    for (int bi = lo[0]; bi <= hi[0]; ++bi)
        for (int bj = lo[1]; bj <= hi[1]; ++bj)
            for (int bk = lo[2]; bk <= hi[2]; ++bk) {
                const long block = first_block + ((long)bi * nb[1] + bj) * nb[2] + bk;
                if (block_counts[block] == 0)
                    continue;
                const int tile =
                    ((ni - P2G_BLOCK * bi) * P2G_TILE + nj - P2G_BLOCK * bj) * P2G_TILE + nk - P2G_BLOCK * bk;
                __global const real *part = partials + GRID_CH * (P2G_TILE_NODES * block + tile);
                for (int q = 0; q < GRID_CH; ++q)
                    sum[q] += part[q];
            }
    __global real *out = grid + GRID_CH * node;
    for (int q = 0; q < GRID_CH; ++q)
        out[q] = sum[q];
    const real gravity[3] = {gx, gy, gz};
    update_node(&g, node, ni, nj, nk, dt, t, gravity, mass_eps, grid, grid_v, grid_dv, bc, n_bc);
}
