/* The REAL switch shared by every clflow kernel.
 *
 * The host builds each program with -DREAL=float|double and -DREAL_IS_DOUBLE=0|1
 * (clflow/runtime/programs.py); kernels use the `real` type and the real3 helpers so the
 * same source runs in float32 (production) and float64 (tests against torch references). */
#ifndef CLFLOW_REAL_H
#define CLFLOW_REAL_H

#ifndef REAL_IS_DOUBLE
#define REAL_IS_DOUBLE 0
#endif

#if REAL_IS_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
#else
typedef float real;
#endif

#endif /* CLFLOW_REAL_H */
