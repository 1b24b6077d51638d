/* out[index[i]] += values[i] for i < n, with atomic_add_real (index_add / P2G primitive).
 * Each row i carries `width` consecutive values: out[index[i]*width + c] += values[i*width + c]. */
#include "common/atomics.h"

__kernel void scatter_add(__global const real *values, __global const int *index, __global real *out, const int n,
                          const int width)
{
    const int i = get_global_id(0);
    if (i >= n)
        return;
    const int row = index[i];
    for (int c = 0; c < width; ++c)
        atomic_add_real(out + (size_t)row * width + c, values[(size_t)i * width + c]);
}
