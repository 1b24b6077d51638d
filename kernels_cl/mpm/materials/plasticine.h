/* Plasticine: von Mises perfect plasticity on Hencky strain. param = (mu, lambda, tau_Y).
 * The projection only happens when the yield test fails (PhysFlow projects always: peer bug). */
#ifndef CLFLOW_MPM_PLASTICINE_H
#define CLFLOW_MPM_PLASTICINE_H

#include "mpm/materials/hencky.h"

inline void plasticine_stress(const real *F_tr, const real *U, const real *s, const real *V, const real mu,
                              const real lambda, const real tau_Y, real *F_new, real *tau)
{
    real eps[3];
    hencky_strain(s, eps);
    if (von_mises_return(eps, mu, tau_Y) > 0)
        f_from_strain(U, eps, V, F_new);
    else
        mat3_copy(F_tr, F_new);
    hencky_tau(U, eps, mu, lambda, tau);
}

#endif /* CLFLOW_MPM_PLASTICINE_H */
