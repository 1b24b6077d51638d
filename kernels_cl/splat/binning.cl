/* Tile lists: every visible Gaussian gets one entry per tile its box touches, ordered by
 * (tile, depth).
 *
 * 1. depth_keys: Gaussians sorted by depth (radix sort of the float bits: depth > near > 0,
 *    so the bits order like the values; culled Gaussians sort last).
 * 2. emit_entries: in depth order, Gaussian g writes its entries at slots
 *    [first_slot[g], first_slot[g] + tiles_touched[g]); key = tile id, value = slot.
 * 3. a stable radix sort by tile keeps the depth order inside each tile.
 * 4. key_ranges (common/sort.cl): [start, end) of each tile in the sorted list.
 * A slot is the row of the backward pass's per-(tile, Gaussian) gradient buffer; the slots
 * of one Gaussian are contiguous, so it sums them in a fixed order. */
#include "splat/common.h"

__kernel void depth_keys(__global const real *depths, __global const int *radii, __global uint *keys,
                         __global int *values, const int n)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    keys[i] = radii[i] > 0 ? as_uint((float)depths[i]) : 0xffffffffu;
    values[i] = i;
}

/* counts[s] = tiles_touched[order[s]]: entry counts in depth order, to be scanned. */
__kernel void gather_counts(__global const int *order, __global const int *tiles_touched, __global int *counts,
                            const int n)
{
    const int s = get_global_id(0);
    if (s >= n)
        return;
    counts[s] = tiles_touched[order[s]];
}

__kernel void emit_entries(__global const int *order, __global const int *offsets, __global const real *means2d,
                           __global const int *radii, __global uint *tile_keys, __global int *slots,
                           __global int *slot_gaussian, __global int *first_slot, const int n, const int tiles_x,
                           const int tiles_y)
{
    const int s = get_global_id(0);
    if (s >= n)
        return;
    const int g = order[s];
    int slot = offsets[s];
    first_slot[g] = slot;
    if (radii[g] <= 0)
        return;
    int x0, y0, x1, y1;
    tile_rect(means2d[2 * g], means2d[2 * g + 1], radii[g], tiles_x, tiles_y, &x0, &y0, &x1, &y1);
    for (int ty = y0; ty < y1; ++ty) {
        for (int tx = x0; tx < x1; ++tx) {
            tile_keys[slot] = (uint)(ty * tiles_x + tx);
            slots[slot] = slot;
            slot_gaussian[slot] = g;
            ++slot;
        }
    }
}
