/* Particles sorted by cell (clflow.runtime.sort.counting_sort of particle_cells' keys): the
 * particles of base cell c, in index order, are the slots [starts[c], starts[c + 1]). A node's
 * gather visits the 27 base cells whose stencil reaches it. */
#ifndef CLFLOW_MPM_CELLS_H
#define CLFLOW_MPM_CELLS_H

#include "mpm/mpm.h"

/* The slots [x, y) of base cell (bi, bj, bk); empty when no stencil can be based there (a
 * stencil's base lies in [0, n - 3] per axis). */
inline int2 cell_run(const grid_t *g, __global const int *starts, const int bi, const int bj, const int bk)
{
    if (bi < 0 || bj < 0 || bk < 0 || bi > g->nx - 3 || bj > g->ny - 3 || bk > g->nz - 3)
        return (int2)(0, 0);
    const long cell = grid_index(g, bi, bj, bk);
    return (int2)(starts[cell], starts[cell + 1]);
}

#endif /* CLFLOW_MPM_CELLS_H */
