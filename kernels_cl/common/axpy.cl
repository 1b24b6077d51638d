/* y[i] += a x[i] for i < n: adds one device array into another (the adjoint's gradient
 * accumulators). Not contracted into an fma, so the sum rounds as torch's y += a * x does. */
#include "common/real.h"

#pragma OPENCL FP_CONTRACT OFF

__kernel void axpy(const long n, const real a, __global const real *x, __global real *y)
{
    const long i = get_global_id(0);
    if (i >= n)
        return;
    const real ax = a * x[i];
    y[i] = y[i] + ax;
}
