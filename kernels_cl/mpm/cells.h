/* Particles sorted by cell (clflow.runtime.sort.counting_sort of the keys count_cell writes):
 * the particles of base cell c, in index order, are the slots [starts[c], starts[c + 1]). A node's
 * gather visits the 27 base cells whose stencil reaches it (gather_run), each cell's slots in
 * order, and reads each slot's record (gather_record): the gathers of p2g_gather.cl and
 * g2p_adjoint_gather.cl. */
#ifndef CLFLOW_MPM_CELLS_H
#define CLFLOW_MPM_CELLS_H

#include "common/scan.h"
#include "mpm/mpm.h"

/* The arguments count_cell writes: each particle's cell key [n], the counts [cells + 1 +
 * cells / SCAN_BLOCK + 1] (cells: all members') (zeroed beforehand) and each particle's rank [n]. */
#define CELL_KEY_ARGS __global uint *key, __global int *counts, __global int *rank

/* Particle p at xp (m) counted into its base cell in grid g (its member's): key[p] = the cell, rank[p] = its place among
 * the cell's particles (in the order the atomics ran), counts[cell] += 1, and its SCAN_BLOCK
 * block of cells counted after the cells' counts and total, counts[cells + 1 + cell /
 * SCAN_BLOCK] += 1: the scan's block sums, so that it needs no pass of its own to add them. */
inline void count_cell(const grid_t *g, const int p, const real *xp, CELL_KEY_ARGS)
{
    const stencil_t st = make_stencil(g, xp);
    const uint cell = (uint)grid_index(g, st.base[0], st.base[1], st.base[2]);
    key[p] = cell;
    rank[p] = atomic_inc(&counts[cell]);
    atomic_inc(&counts[population_nodes(g) + 1 + cell / SCAN_BLOCK]);
}

/* The slots [x, y) of base cell (bi, bj, bk); empty when no stencil can be based there (a
 * stencil's base lies in [0, n - 3] per axis). */
inline int2 cell_run(const grid_t *g, __global const int *starts, const int bi, const int bj, const int bk)
{
    if (bi < 0 || bj < 0 || bk < 0 || bi > g->nx - 3 || bj > g->ny - 3 || bk > g->nz - 3)
        return (int2)(0, 0);
    const long cell = grid_index(g, bi, bj, bk);
    return (int2)(starts[cell], starts[cell + 1]);
}

/* The 27 base cells whose stencil reaches node (i, j, k), in the fixed order of a node's gather:
 * cell o = 9a + 3b + c (a, b, c in 0..2) is (i - a, j - b, k - c), and the node is at offset
 * (a, b, c) from the base of each of its particles' stencils. gather_run: cell o's slots. */
inline int2 gather_run(const grid_t *g, __global const int *starts, const int i, const int j, const int k, const int o)
{
    return cell_run(g, starts, i - o / 9, j - o / 3 % 3, k - o % 3);
}

/* Slot s's record (`width` reals a slot, the particle's position x first) and, at the node of
 * gather cell o (gather_run), the particle's weight *w and d = x_node - x (m). */
inline __global const real *gather_record(const grid_t *g, __global const real *records, const int width, const int s,
                                          const int o, real *w, real *d)
{
    __global const real *rec = records + (long)width * s;
    const real xp[3] = {rec[0], rec[1], rec[2]};
    const stencil_t st = make_stencil(g, xp);
    const int a = o / 9, b = o / 3 % 3, c = o % 3;
    *w = st.w[0][a] * st.w[1][b] * st.w[2][c];
    d[0] = (a - st.fx[0]) * g->dx;
    d[1] = (b - st.fx[1]) * g->dx;
    d[2] = (c - st.fx[2]) * g->dx;
    return rec;
}

#endif /* CLFLOW_MPM_CELLS_H */
