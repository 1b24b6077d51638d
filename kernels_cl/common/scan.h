/* Work-group scan helpers shared by common/scan.cl and common/sort.cl. */
#ifndef CLFLOW_SCAN_H
#define CLFLOW_SCAN_H

#define SCAN_WG    256
#define SCAN_ITEMS 8
#define SCAN_BLOCK (SCAN_WG * SCAN_ITEMS)

/* In-place exclusive scan of the SCAN_WG values of `vals` (local), by the work-group's
 * work-item `l`; returns the total. Hillis-Steele over a second buffer: log2(SCAN_WG) steps,
 * every barrier reached by the whole group. */
inline int scan_local(__local int *vals, __local int *tmp, const int l)
{
    const int mine = vals[l];
    __local int *src = vals, *dst = tmp;
    for (int offset = 1; offset < SCAN_WG; offset <<= 1) {
        barrier(CLK_LOCAL_MEM_FENCE);
        dst[l] = src[l] + (l >= offset ? src[l - offset] : 0);
        __local int *swap = src;
        src = dst;
        dst = swap;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    const int inclusive = src[l], total = src[SCAN_WG - 1];
    barrier(CLK_LOCAL_MEM_FENCE);
    vals[l] = inclusive - mine;
    barrier(CLK_LOCAL_MEM_FENCE);
    return total;
}

#endif /* CLFLOW_SCAN_H */
