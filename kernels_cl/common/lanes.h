/* Explicit SIMD across items: with CLFLOW_SIMD_LANES defined, `realv` is a vector of that
 * many reals holding one value of as many particles / Gaussians / matrices (one per lane).
 * PoCL leaves per-item kernels scalar when their loads and stores are strided or their
 * bodies loop; kernels that matter take CLFLOW_SIMD_LANES items per work-item instead, with
 * only the memory accesses per lane. */
#ifndef CLFLOW_LANES_H
#define CLFLOW_LANES_H

#include "common/real.h"

#ifdef CLFLOW_SIMD_LANES
#define CLFLOW_VEC_(T, N) T##N
#define CLFLOW_VEC(T, N)  CLFLOW_VEC_(T, N)
typedef CLFLOW_VEC(REAL, CLFLOW_SIMD_LANES) realv;

/* Lane l of v, as a real. */
#define LANE(v, l) (((const real *)&(v))[l])

/* Rows p0 .. p0 + CLFLOW_SIMD_LANES - 1 of a [n, width] array, one lane each: m[c] holds
 * column c of every lane. Lanes past the end repeat row n - 1; they are computed but never
 * stored. */
inline void load_lanes_v(const int n, const int p0, const int width, __global const real *a, realv *m)
{
    for (int l = 0; l < CLFLOW_SIMD_LANES; ++l) {
        const int p = min(p0 + l, n - 1);
        for (int c = 0; c < width; ++c)
            ((real *)&m[c])[l] = a[(long)width * p + c];
    }
}

/* The lanes of real rows (p0 + l < n) back into a [n, width] array. */
inline void store_lanes_v(const int n, const int p0, const int width, const realv *m, __global real *a)
{
    for (int l = 0; l < CLFLOW_SIMD_LANES && p0 + l < n; ++l)
        for (int c = 0; c < width; ++c)
            a[(long)width * (p0 + l) + c] = LANE(m[c], l);
}
#endif

#endif /* CLFLOW_LANES_H */
