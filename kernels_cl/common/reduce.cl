/* Deterministic column sums: x[N, K] (real) -> sums[K] (double), in a fixed order.
 *
 * Pass 1 (sum_rows_partial): work-group g of REDUCE_WG items owns rows
 *   [g*CHUNK, (g+1)*CHUNK), CHUNK = REDUCE_WG * ROWS_PER_ITEM; item l adds rows
 *   g*CHUNK + l + j*REDUCE_WG (j = 0..ROWS_PER_ITEM-1) in that order, in double; the group
 *   then halves its REDUCE_WG sums in local memory. Output: partial[g, K].
 * Pass 2.. (sum_rows_partial_acc): the same over the double partials, until one row is left.
 * The order depends only on N, never on the device or on timing, so results are
 * bit-identical across runs (and across devices with IEEE double addition).
 * Barriers sit under uniform control flow only (PoCL 3.1 miscompiles anything else). */
#include "common/real.h"
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

/* REDUCE_WG and ROWS_PER_ITEM come from the host (clflow/runtime/reduction.py). */
#if !defined(REDUCE_WG) || !defined(ROWS_PER_ITEM)
#error "build with -DREDUCE_WG=... -DROWS_PER_ITEM=..."
#endif

#define DEFINE_SUM_ROWS_PARTIAL(NAME, IN_T)                                                                            \
    __kernel __attribute__((reqd_work_group_size(REDUCE_WG, 1, 1))) void NAME(                                         \
        __global const IN_T *x, __global double *partial, const int n, const int k)                                    \
    {                                                                                                                  \
        __local double scratch[REDUCE_WG];                                                                             \
        const int l = get_local_id(0);                                                                                 \
        const int g = get_group_id(0);                                                                                 \
        const int col = get_global_id(1);                                                                              \
        const long first = (long)g * (REDUCE_WG * ROWS_PER_ITEM) + l;                                                  \
        double acc = 0.0;                                                                                              \
        for (int j = 0; j < ROWS_PER_ITEM; ++j) {                                                                      \
            const long row = first + (long)j * REDUCE_WG;                                                              \
            if (row < n)                                                                                               \
                acc += (double)x[row * k + col];                                                                       \
        }                                                                                                              \
        scratch[l] = acc;                                                                                              \
        barrier(CLK_LOCAL_MEM_FENCE);                                                                                  \
        for (int stride = REDUCE_WG / 2; stride > 0; stride >>= 1) {                                                   \
            if (l < stride)                                                                                            \
                scratch[l] += scratch[l + stride];                                                                     \
            barrier(CLK_LOCAL_MEM_FENCE);                                                                              \
        }                                                                                                              \
        if (l == 0)                                                                                                    \
            partial[(long)g * k + col] = scratch[0];                                                                   \
    }

DEFINE_SUM_ROWS_PARTIAL(sum_rows_partial, real)
DEFINE_SUM_ROWS_PARTIAL(sum_rows_partial_acc, double)
