/* Sorting on the device: a stable LSD radix sort of (uint key, int value) pairs in two
 * shapes, a counting sort of small keys, and where each key's run lies in sorted keys.
 * Every position depends on the keys alone: the results are deterministic.
 *
 * Radix sort, one pass per digit (key >> shift) & mask; `hist` is scanned between the
 * histogram and the scatter (common/scan.cl), digit-major: hist[d * nblocks + b] = where
 * block b's keys of digit d start.
 *  - blocks shape (CPU devices): n pairs cut into nblocks contiguous blocks, work-item b
 *    walks block b in order (radix_histogram, radix_scatter): no barriers, no atomics;
 *    each core streams through its memory.
 *  - work-group shape (GPUs; radix_histogram_wg, radix_scatter_wg): a block of RADIX_BLOCK
 *    pairs per work-group of RADIX_WG, RADIX_ITEMS per work-item, digits of RADIX_BITS.
 *    The scatter stages the block in local memory, counts each work-item's keys per digit,
 *    scans those counts (digit-major, so in block order within a digit) and writes each pair
 *    at its block's start plus its rank: stable. 26 KiB of local memory: within the 32 KiB
 *    every OpenCL device of the full profile has.
 *
 * Counting sort of keys in [0, K) (count_keys, place_keys, order_runs): counts per key
 * (integer atomics), their exclusive scan gives each key's start, each element lands at its
 * key's start plus the rank its atomic returned, then each key's run is put in index order
 * (common/runs.h).
 * One pass over the data for any key width, and the order is fixed. */
#include "common/runs.h"
#include "common/scan.h"

__kernel void radix_histogram(__global const uint *keys, const int n, const int shift, const uint mask,
                              __global int *hist, const int nblocks, const int block_len)
{
    const int b = get_global_id(0);
    if (b >= nblocks)
        return;
    for (uint d = 0; d <= mask; ++d)
        hist[d * nblocks + b] = 0;
    const int end = min(n, (b + 1) * block_len);
    for (int i = b * block_len; i < end; ++i)
        hist[((keys[i] >> shift) & mask) * nblocks + b] += 1;
}

__kernel void radix_scatter(__global const uint *keys_in, __global const int *values_in, __global uint *keys_out,
                            __global int *values_out, const int n, const int shift, const uint mask,
                            __global int *starts, const int nblocks, const int block_len)
{
    const int b = get_global_id(0);
    if (b >= nblocks)
        return;
    const int end = min(n, (b + 1) * block_len);
    for (int i = b * block_len; i < end; ++i) {
        const uint key = keys_in[i];
        const int slot = ((key >> shift) & mask) * nblocks + b;
        const int at = starts[slot];
        starts[slot] = at + 1;
        keys_out[at] = key;
        values_out[at] = values_in[i];
    }
}

/* ranges[2 k] = first position of key k in the sorted keys, ranges[2 k + 1] = one past its
 * last; keys absent from them keep what the host filled in (zeros: empty). */
__kernel void key_ranges(__global const uint *keys, __global int *ranges, const int n)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    const uint k = keys[i];
    if (i == 0 || keys[i - 1] != k)
        ranges[2 * k] = i;
    if (i == n - 1 || keys[i + 1] != k)
        ranges[2 * k + 1] = i + 1;
}

#define RADIX_BITS   4
#define RADIX_DIGITS (1 << RADIX_BITS)
#define RADIX_WG     SCAN_WG
#define RADIX_ITEMS  4
#define RADIX_BLOCK  (RADIX_WG * RADIX_ITEMS)

/* hist[d * nblocks + b] = keys of digit d in block b (mask < RADIX_DIGITS). */
__kernel __attribute__((reqd_work_group_size(RADIX_WG, 1, 1))) void
radix_histogram_wg(__global const uint *keys, const int n, const int shift, const uint mask, __global int *hist,
                   const int nblocks)
{
    __local int counts[RADIX_DIGITS];
    const int l = get_local_id(0), b = get_group_id(0);
    const long base = (long)b * RADIX_BLOCK;
    if (l < RADIX_DIGITS)
        counts[l] = 0;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int j = 0; j < RADIX_ITEMS; ++j) {
        const long i = base + j * RADIX_WG + l;
        if (i < n)
            atomic_inc(&counts[(keys[i] >> shift) & mask]);
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (l <= (int)mask)
        hist[l * nblocks + b] = counts[l];
}

/* Block b's pairs to starts[d * nblocks + b] + their rank among the block's keys of digit d. */
__kernel __attribute__((reqd_work_group_size(RADIX_WG, 1, 1))) void
radix_scatter_wg(__global const uint *keys_in, __global const int *values_in, __global uint *keys_out,
                 __global int *values_out, const int n, const int shift, const uint mask, __global const int *starts,
                 const int nblocks)
{
    __local uint keys[RADIX_BLOCK];
    __local int values[RADIX_BLOCK];
    __local int ranks[RADIX_DIGITS * RADIX_WG]; /* [digit][work-item] */
    __local int first[RADIX_DIGITS];            /* the block's first rank of each digit */
    __local int vals[RADIX_WG], tmp[RADIX_WG];
    const int l = get_local_id(0), b = get_group_id(0);
    const long base = (long)b * RADIX_BLOCK;
    const int count = (int)min((long)RADIX_BLOCK, n - base);
    for (int j = 0; j < RADIX_ITEMS; ++j) { /* coalesced loads */
        const int at = j * RADIX_WG + l;
        keys[at] = at < count ? keys_in[base + at] : 0;
        values[at] = at < count ? values_in[base + at] : 0;
    }
    for (int d = 0; d < RADIX_DIGITS; ++d)
        ranks[d * RADIX_WG + l] = 0;
    barrier(CLK_LOCAL_MEM_FENCE);
    /* work-item l owns the contiguous pairs [l RADIX_ITEMS, (l + 1) RADIX_ITEMS) of the block */
    const int own = l * RADIX_ITEMS, own_end = min(own + RADIX_ITEMS, count);
    for (int at = own; at < own_end; ++at)
        ranks[((keys[at] >> shift) & mask) * RADIX_WG + l] += 1;
    barrier(CLK_LOCAL_MEM_FENCE);
    /* exclusive scan of ranks in digit-major order: work-item l scans entries [l D, (l + 1) D) */
    int run = 0;
    for (int q = 0; q < RADIX_DIGITS; ++q) {
        const int x = ranks[l * RADIX_DIGITS + q];
        ranks[l * RADIX_DIGITS + q] = run;
        run += x;
    }
    vals[l] = run;
    scan_local(vals, tmp, l);
    for (int q = 0; q < RADIX_DIGITS; ++q)
        ranks[l * RADIX_DIGITS + q] += vals[l];
    barrier(CLK_LOCAL_MEM_FENCE);
    if (l < RADIX_DIGITS)
        first[l] = ranks[l * RADIX_WG];
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int at = own; at < own_end; ++at) {
        const uint key = keys[at];
        const uint d = (key >> shift) & mask;
        const int rank = ranks[d * RADIX_WG + l]++;
        const int to = starts[d * nblocks + b] + rank - first[d];
        keys_out[to] = key;
        values_out[to] = values[at];
    }
}

/* rank[i] = the count of keys[i] before this one was counted (in no fixed order); counts[k]
 * ends as the number of keys k, and counts[n_keys + 1 + b] as the number in block b of
 * SCAN_BLOCK keys, the scan's block sums (counts zeroed beforehand). */
__kernel void count_keys(__global const uint *keys, const int n, const int n_keys, __global int *counts,
                         __global int *rank)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    const uint key = keys[i];
    rank[i] = atomic_inc(&counts[key]);
    atomic_inc(&counts[n_keys + 1 + key / SCAN_BLOCK]);
}

/* order[starts[keys[i]] + rank[i]] = i: each element into its key's run. */
__kernel void place_keys(__global const uint *keys, __global const int *rank, __global const int *starts, const int n,
                         __global int *order)
{
    const int i = get_global_id(0);
    if (i < n)
        order[starts[keys[i]] + rank[i]] = i;
}

/* Key k's run order[starts[k] .. starts[k + 1]) in increasing index: the order the atomics
 * left becomes the one a sequential counting sort gives. */
__kernel void order_runs(__global const int *starts, const int n_keys, __global int *order)
{
    const int k = get_global_id(0);
    if (k < n_keys)
        sort_run(order, starts[k], starts[k + 1]);
}
