/* Snow (Stomakhin et al. 2013). param = (mu0, lambda0, theta_c, theta_s, xi); state J_P.
 *
 * The singular values of the elastic part F_tr are clamped to [1 - theta_c, 1 + theta_s];
 * what the clamp removes moves into the plastic volume J_P <- J_P det(F_tr) / det(F_E);
 * hardening scales the Lame parameters by h = exp(xi (1 - J_P)); the stress is fixed
 * corotated on the clamped F_E. */
#ifndef CLFLOW_MPM_SNOW_H
#define CLFLOW_MPM_SNOW_H

#include "mpm/materials/elastic.h"

inline void snow_stress(const real *F_tr, const real *U, const real *s, const real *V, const real mu0,
                        const real lambda0, const real theta_c, const real theta_s, const real xi, const real J_P,
                        real *F_new, real *J_P_new, real *tau)
{
    real s_E[3];
    for (int a = 0; a < 3; ++a)
        s_E[a] = clamp(s[a], 1 - theta_c, 1 + theta_s);
    mat3_udvt(U, s_E, V, F_new);
    *J_P_new = J_P * (s[0] * s[1] * s[2]) / (s_E[0] * s_E[1] * s_E[2]);
    const real h = exp(xi * (1 - *J_P_new));
    fixed_corotated_tau(F_new, U, s_E, V, mu0 * h, lambda0 * h, tau);
}

#endif /* CLFLOW_MPM_SNOW_H */
