/* The per-view scratch of the compositing kernels, whichever shape runs (rasterize_tile_rows.cl,
 * rasterize_workgroup.cl): the records of the sorted tile entries they read, and the sum of the
 * per-slot gradient rows they write into per-Gaussian gradients.
 *
 * Inputs per Gaussian g: mean2d [N,2] (pixels), conic [N,3] (A, B, C), opacity [N],
 * features [N, CHANNELS]; entry i of the (tile, depth) sorted list names slot sorted_slots[i]
 * of Gaussian slot_gaussian[slot]. */
#include "splat/composite.h"

/* Per Gaussian, once per view (not per tile entry: the log, root and divisions would be
 * redone for every tile a Gaussian touches): records [N, ENTRY_FIELDS] = (mean2d x, y,
 * conic A, B, C, opacity, cut, slope, reach), the last three for rasterize_tile_rows.cl's row cull.
 * Culled Gaussians get records no tile reads. */
__kernel void entry_records(__global const real *means2d, __global const real *conics, __global const real *opacities,
                            __global real *records, const int n)
{
    const int g = get_global_id(0);
    if (g >= n)
        return;
    const real A = conics[3 * g], B = conics[3 * g + 1], C = conics[3 * g + 2], o = opacities[g];
    const real cut = log(o / (real)ALPHA_MIN) + (real)ROW_CULL_MARGIN;
    const real det = A * C - B * B;
    __global real *rec = records + (size_t)g * ENTRY_FIELDS;
    rec[0] = means2d[2 * g];
    rec[1] = means2d[2 * g + 1];
    rec[2] = A;
    rec[3] = B;
    rec[4] = C;
    rec[5] = o;
    rec[6] = cut;
    rec[7] = -B / A;
    rec[8] = cut > 0 ? sqrt(2 * cut * A / det) + (real)ROW_CULL_MARGIN : -1;
}

/* The records of the sorted tile entries, in entry order: entries [M, ENTRY_STRIDE] = (the
 * record of the entry's Gaussian, its CHANNELS features). The compositing loops then read
 * memory in order: chasing entry -> slot -> Gaussian -> record instead (two scattered,
 * dependent reads per entry) left them waiting on memory for a third of their time. */
__kernel void sort_entry_records(__global const int *sorted_slots, __global const int *slot_gaussian,
                                 __global const real *records, __global const real *features, __global real *entries,
                                 const int m)
{
    const int i = get_global_id(0);
    if (i >= m)
        return;
    const int g = slot_gaussian[sorted_slots[i]];
    __global real *out = entries + (size_t)i * ENTRY_STRIDE;
    for (int k = 0; k < ENTRY_FIELDS; ++k)
        out[k] = records[(size_t)g * ENTRY_FIELDS + k];
    for (int k = 0; k < CHANNELS; ++k)
        out[ENTRY_FIELDS + k] = features[(size_t)g * CHANNELS + k];
}

/* Per Gaussian g: the sum of its slot rows [first_slot[g], first_slot[g] + tiles_touched[g])
 * of slot_grads [M, GRAD_FIELDS] in slot order, split into dL/dmean2d [N,2], dL/dconic [N,3],
 * dL/dopacity [N] and dL/dfeatures [N, CHANNELS]. */
__kernel void reduce_slots(__global const real *slot_grads, __global const int *first_slot,
                           __global const int *tiles_touched, __global real *v_means2d, __global real *v_conics,
                           __global real *v_opacities, __global real *v_features, const int n)
{
    const int g = get_global_id(0);
    if (g >= n)
        return;
    real sum[GRAD_FIELDS];
    for (int k = 0; k < GRAD_FIELDS; ++k)
        sum[k] = 0;
    const int first = first_slot[g];
    for (int s = first; s < first + tiles_touched[g]; ++s)
        for (int k = 0; k < GRAD_FIELDS; ++k)
            sum[k] += slot_grads[(size_t)s * GRAD_FIELDS + k];
    v_means2d[2 * g] = sum[0];
    v_means2d[2 * g + 1] = sum[1];
    for (int k = 0; k < 3; ++k)
        v_conics[3 * g + k] = sum[2 + k];
    v_opacities[g] = sum[5];
    for (int k = 0; k < CHANNELS; ++k)
        v_features[(size_t)g * CHANNELS + k] = sum[6 + k];
}
