/* Stable LSD radix sort of (uint key, int value) pairs, an exclusive prefix sum, and where
 * each key's run lies in sorted keys.
 *
 * One pass sorts by the digit (key >> shift) & mask. The n pairs are cut into nblocks
 * contiguous blocks of block_len; work-item b walks block b in order:
 *   radix_histogram   hist[d * nblocks + b] = number of keys of digit d in block b
 *   scan_exclusive    over hist, digit-major: where each (digit, block) run starts
 *   radix_scatter     block b writes its pairs, in order, from those starts
 * Every position depends only on the keys, so the result is deterministic and stable
 * (equal keys keep their input order). Walking contiguous blocks suits CPU devices: each
 * work-item streams through its memory; no barriers, no atomics. */

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

/* out[i] = sum_{j < i} in[j] for i = 0..n (out has n + 1 entries; out[n] is the total).
 * One work-item: the arrays scanned here are short (histograms, per-Gaussian counts). */
__kernel void scan_exclusive(__global const int *in, __global int *out, const int n)
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
