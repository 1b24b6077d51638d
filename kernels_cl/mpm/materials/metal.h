/* Metal: von Mises plasticity with linear isotropic hardening on Hencky strain.
 * param = (mu, lambda, tau_Y, xi); state `hardening` = the yield stress gained so far (Pa):
 * the current yield stress is tau_Y + hardening, and a plastic step dgamma adds
 * 2 mu xi dgamma to it. */
#ifndef CLFLOW_MPM_METAL_H
#define CLFLOW_MPM_METAL_H

#include "mpm/materials/hencky.h"

inline void metal_stress(const real *F_tr, const real *U, const real *s, const real *V, const real mu,
                         const real lambda, const real tau_Y, const real xi, const real hardening, real *F_new,
                         real *hardening_new, real *tau)
{
    real eps[3];
    hencky_strain(s, eps);
    const real dgamma = von_mises_return(eps, mu, tau_Y + hardening);
    if (dgamma > 0) {
        f_from_strain(U, eps, V, F_new);
        *hardening_new = hardening + 2 * mu * xi * dgamma;
    } else {
        mat3_copy(F_tr, F_new);
        *hardening_new = hardening;
    }
    hencky_tau(U, eps, mu, lambda, tau);
}

#endif /* CLFLOW_MPM_METAL_H */
