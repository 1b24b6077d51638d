/* Whether a state is finite, and its fastest particle's speed, reduced on the device so that
 * a run's NaN/inf and CFL checks read HEALTH_GROUPS pairs of reals, not the state.
 *
 * state_health: a fixed grid of HEALTH_GROUPS work-groups of HEALTH_WG items; item i visits
 * particles i, i + G, i + 2G, ... (G the global size) and keeps the largest |v|^2 of its finite
 * particles and whether any value of x [n, 3], v [n, 3], F [n, 3, 3] is not finite; the group
 * halves both in local memory. Output: partial[2 g] = the group's largest |v|^2 (m^2/s^2),
 * partial[2 g + 1] = 1 where a value is not finite, else 0. A maximum does not depend on
 * the order, so the result is exact and repeatable.
 * Barriers sit under uniform control flow only (PoCL 3.1 miscompiles anything else). */
#include "common/real.h"

#if !defined(HEALTH_WG) /* clflow/mpm/constants.py kernel_defines */
#error "build with -DHEALTH_WG=..."
#endif

__kernel __attribute__((reqd_work_group_size(HEALTH_WG, 1, 1))) void state_health(const int n, __global const real *x,
                                                                                  __global const real *v,
                                                                                  __global const real *F,
                                                                                  __global real *partial)
{
    __local real speed2[HEALTH_WG];
    __local int bad[HEALTH_WG];
    const int l = get_local_id(0);
    real fastest = 0;
    int not_finite = 0;
    for (int p = get_global_id(0); p < n; p += get_global_size(0)) {
        int ok = 1;
        for (int c = 0; c < 3; ++c)
            ok &= isfinite(x[3 * p + c]) && isfinite(v[3 * p + c]);
        for (int c = 0; c < 9; ++c)
            ok &= isfinite(F[9 * p + c]);
        const real vx = v[3 * p], vy = v[3 * p + 1], vz = v[3 * p + 2];
        if (ok)
            fastest = fmax(fastest, vx * vx + vy * vy + vz * vz);
        else
            not_finite = 1;
    }
    speed2[l] = fastest;
    bad[l] = not_finite;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int stride = HEALTH_WG / 2; stride > 0; stride >>= 1) {
        if (l < stride) {
            speed2[l] = fmax(speed2[l], speed2[l + stride]);
            bad[l] |= bad[l + stride];
        }
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (l == 0) {
        partial[2 * get_group_id(0)] = speed2[0];
        partial[2 * get_group_id(0) + 1] = bad[0];
    }
}
