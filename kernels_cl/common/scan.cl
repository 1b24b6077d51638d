/* Exclusive prefix sums of int32: out[i] = sum_{j < i} in[j] for i = 0..n (out[n] = the total).
 *
 * Two shapes (clflow.runtime.plan decides which a device takes):
 *  - scan_serial: one work-item walks the array. On a CPU device a launch of one work-item
 *    over a short array (histograms, counts) costs less than any parallel scheme.
 *  - reduce-then-scan for GPUs, in blocks of SCAN_BLOCK = SCAN_WG x SCAN_ITEMS:
 *      scan_block_sums    : sums[b] = sum of block b                (a work-group per block)
 *      scan_blocks_summed : out = sum of sums[0..b) + the block's own exclusive scan, each
 *                           work-group adding the sums before it itself (two launches in all,
 *                           one where the sums were counted with the elements; clflow.runtime
 *                           .sort takes it up to SCAN_SUMMED_BLOCKS blocks)
 *    or, for more blocks, the sums scanned the same way, recursively, into offsets[0..nblocks]
 *    and scan_blocks: out = offsets[b] + the block's own exclusive scan.
 *    Every work-item handles SCAN_ITEMS elements; no work-item walks more. Decoupled
 *    look-back (one pass) needs forward progress between work-groups, which OpenCL does
 *    not promise; this needs none. in and out may be the same buffer: a work-group reads
 *    its whole block into local memory before it writes. */

#include "common/scan.h"

__kernel void scan_serial(__global const int *in, __global int *out, const int n)
{
    if (get_global_id(0) != 0)
        return;
    int total = 0;
    for (int i = 0; i < n; ++i) {
        const int x = in[i];
        out[i] = total;
        total += x;
    }
    out[n] = total;
}

__kernel __attribute__((reqd_work_group_size(SCAN_WG, 1, 1))) void scan_block_sums(__global const int *in, const int n,
                                                                                   __global int *sums)
{
    __local int vals[SCAN_WG], tmp[SCAN_WG];
    const int l = get_local_id(0), b = get_group_id(0);
    const long base = (long)b * SCAN_BLOCK;
    int s = 0;
    for (int j = 0; j < SCAN_ITEMS; ++j) { /* strided by the group: neighbours read neighbours */
        const long i = base + j * SCAN_WG + l;
        s += i < n ? in[i] : 0;
    }
    vals[l] = s;
    const int total = scan_local(vals, tmp, l);
    if (l == 0)
        sums[b] = total;
}

/* Block b's exclusive scan plus `offset` into out (in and out may be one buffer: the block is
 * read whole into local memory first); the last block also writes out[n], the total. Called
 * by every work-item of the group. */
inline void scan_block(__global const int *in, __global int *out, const int n, const int b, const int l,
                       const int offset, __local int *block, __local int *vals, __local int *tmp)
{
    const long base = (long)b * SCAN_BLOCK;
    for (int j = 0; j < SCAN_ITEMS; ++j) {
        const long i = base + j * SCAN_WG + l;
        block[j * SCAN_WG + l] = i < n ? in[i] : 0;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    int run = 0; /* work-item l scans its SCAN_ITEMS contiguous elements */
    for (int j = 0; j < SCAN_ITEMS; ++j) {
        const int x = block[l * SCAN_ITEMS + j];
        block[l * SCAN_ITEMS + j] = run;
        run += x;
    }
    vals[l] = run;
    const int total = scan_local(vals, tmp, l);
    const int mine = offset + vals[l];
    for (int j = 0; j < SCAN_ITEMS; ++j)
        block[l * SCAN_ITEMS + j] += mine;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int j = 0; j < SCAN_ITEMS; ++j) {
        const long i = base + j * SCAN_WG + l;
        if (i < n)
            out[i] = block[j * SCAN_WG + l];
    }
    if (l == 0 && base + SCAN_BLOCK >= n)
        out[n] = offset + total;
}

/* Block b's exclusive scan plus offsets[b] (has_offsets; else 0). */
__kernel __attribute__((reqd_work_group_size(SCAN_WG, 1, 1))) void
scan_blocks(__global const int *in, __global int *out, const int n, __global const int *offsets, const int has_offsets)
{
    __local int block[SCAN_BLOCK], vals[SCAN_WG], tmp[SCAN_WG];
    const int b = get_group_id(0);
    scan_block(in, out, n, b, get_local_id(0), has_offsets ? offsets[b] : 0, block, vals, tmp);
}

/* Block b's exclusive scan plus the sum of the block sums before it, sums[sums_at .. sums_at + b)
 * (scan_block_sums', or counted with the elements: mpm/cells.h count_cell), which the group adds
 * up itself, a strided share a work-item. */
__kernel __attribute__((reqd_work_group_size(SCAN_WG, 1, 1))) void
scan_blocks_summed(__global const int *in, __global int *out, const int n, __global const int *sums, const int sums_at)
{
    __local int block[SCAN_BLOCK], vals[SCAN_WG], tmp[SCAN_WG];
    const int l = get_local_id(0), b = get_group_id(0);
    int before = 0;
    for (int j = l; j < b; j += SCAN_WG)
        before += sums[sums_at + j];
    vals[l] = before;
    const int offset = scan_local(vals, tmp, l); /* the group's total: every sum before block b */
    scan_block(in, out, n, b, l, offset, block, vals, tmp);
}
