/* atomic_add_real(p, v): *p += v atomically for a __global real, in the fastest way the
 * device has, first found first:
 *  1. NVIDIA's OpenCL (it defines cl_nv_pragma_unroll; it announces no float atomics, but its
 *     compiler takes inline PTX): red.global.add.f32 / .f64, the hardware's reduction;
 *  2. AMD's global float add (__builtin_amdgcn_global_atomic_fadd_f32/_f64) where the host
 *     found a chip that has it (CLFLOW_AMD_GLOBAL_FADD: gfx90a and the gfx94x/gfx950 series);
 *  3. cl_ext_float_atomics where the host announced it (CLFLOW_FLOAT_ATOMICS) and the
 *     compiler confirms the matching feature macro;
 *  4. else a compare-and-swap loop on the value's bit pattern (32-bit for float, 64-bit for
 *     double via cl_khr_int64_base_atomics), slow under contention.
 * Comparing bit patterns, not values, keeps the loop finite when *p is NaN. The first
 * attempt guesses *p == 0 instead of reading it with a plain load, which would race with
 * the other work-items' compare-and-swaps (oclgrind reports it).
 *
 * The order of concurrent additions is not fixed, so sums through this helper are not
 * bit-reproducible: only the P2G asked for as "atomic" (p2g_atomic.cl) and scatter_add.cl take
 * it; the default P2G shapes sum in a fixed order without float atomics (private copies on CPU
 * devices, a gather over blocks of cells on GPUs). */
#ifndef CLFLOW_ATOMICS_H
#define CLFLOW_ATOMICS_H

#include "common/real.h"

#ifndef CLFLOW_FLOAT_ATOMICS
#define CLFLOW_FLOAT_ATOMICS 0
#endif
#ifndef CLFLOW_AMD_GLOBAL_FADD
#define CLFLOW_AMD_GLOBAL_FADD 0
#endif
#if defined(cl_nv_pragma_unroll)
#define CLFLOW_PTX_ATOMIC_ADD 1
#else
#define CLFLOW_PTX_ATOMIC_ADD 0
#endif

/* For the width of real: whether the device's own float add is there (CLFLOW_NATIVE_ATOMIC_ADD)
 * and, for the compare-and-swap fallback, an unsigned integer of that width (real_bits), the
 * bit casts both ways and that width's compare-and-swap. */
#if REAL_IS_DOUBLE
#if CLFLOW_FLOAT_ATOMICS && defined(__opencl_c_ext_fp64_global_atomic_add)
#define CLFLOW_NATIVE_ATOMIC_ADD 1
#else
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
#define CLFLOW_NATIVE_ATOMIC_ADD 0
#endif
typedef ulong real_bits;
#define REAL_AS_BITS as_ulong
#define BITS_AS_REAL as_double
#define BITS_CMPXCHG atom_cmpxchg
#else
#if CLFLOW_FLOAT_ATOMICS && defined(__opencl_c_ext_fp32_global_atomic_add)
#define CLFLOW_NATIVE_ATOMIC_ADD 1
#else
#define CLFLOW_NATIVE_ATOMIC_ADD 0
#endif
typedef uint real_bits;
#define REAL_AS_BITS as_uint
#define BITS_AS_REAL as_float
#define BITS_CMPXCHG atomic_cmpxchg
#endif

inline void atomic_add_real(volatile __global real *p, real v)
{
#if CLFLOW_PTX_ATOMIC_ADD
#if REAL_IS_DOUBLE
    asm volatile("red.global.add.f64 [%0], %1;" ::"l"(p), "d"(v) : "memory");
#else
    asm volatile("red.global.add.f32 [%0], %1;" ::"l"(p), "f"(v) : "memory");
#endif
#elif CLFLOW_AMD_GLOBAL_FADD
#if REAL_IS_DOUBLE
    __builtin_amdgcn_global_atomic_fadd_f64((__global double *)p, v);
#else
    __builtin_amdgcn_global_atomic_fadd_f32((__global float *)p, v);
#endif
#elif CLFLOW_NATIVE_ATOMIC_ADD
#if REAL_IS_DOUBLE
    atomic_fetch_add_explicit((volatile __global atomic_double *)p, v, memory_order_relaxed, memory_scope_device);
#else
    atomic_fetch_add_explicit((volatile __global atomic_float *)p, v, memory_order_relaxed, memory_scope_device);
#endif
#else
    volatile __global real_bits *bits = (volatile __global real_bits *)p;
    real_bits seen = REAL_AS_BITS((real)0), expected;
    do {
        expected = seen;
        seen = BITS_CMPXCHG(bits, expected, REAL_AS_BITS(BITS_AS_REAL(expected) + v));
    } while (seen != expected);
#endif
}

#endif /* CLFLOW_ATOMICS_H */
