/* Viscoplastic (Perzyna-like) return on Hencky strain, the model of foam and of the
 * non-Newtonian fluid (they differ only in how the host derives mu and lambda).
 * param = (mu, lambda, tau_Y, eta).
 *
 * s = 2 mu eps_hat, y = ||s|| - sqrt(2/3) tau_Y. If y > 0:
 *   mu_hat = mu tr(S^2)/3 (S the singular values of F_tr),
 *   ||s'|| = ||s|| - y / (1 + eta / (2 mu_hat dt)),  eps' = s'/(2 mu) + tr(eps)/3.
 * eta -> 0 recovers the von Mises return. */
#ifndef CLFLOW_MPM_VISCOPLASTIC_H
#define CLFLOW_MPM_VISCOPLASTIC_H

#include "mpm/materials/hencky.h"

inline void viscoplastic_stress(const real *F_tr, const real *U, const real *s, const real *V, const real mu,
                                const real lambda, const real tau_Y, const real eta, const real dt, real *F_new,
                                real *tau)
{
    real eps[3], eps_hat[3];
    hencky_strain(s, eps);
    deviator3(eps, eps_hat);
    const real s_norm = 2 * mu * safe_norm3(eps_hat);
    const real y = s_norm - sqrt((real)2 / 3) * tau_Y;
    if (y > 0) {
        const real mu_hat = mu * (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]) / 3;
        const real s_norm_new = s_norm - y / (1 + eta / (2 * mu_hat * dt));
        const real mean = (eps[0] + eps[1] + eps[2]) / 3;
        for (int a = 0; a < 3; ++a) /* s' = (||s'||/||s||) 2 mu eps_hat */
            eps[a] = s_norm_new / s_norm * eps_hat[a] + mean;
        f_from_strain(U, eps, V, F_new);
    } else {
        mat3_copy(F_tr, F_new);
    }
    hencky_tau(U, eps, mu, lambda, tau);
}

#endif /* CLFLOW_MPM_VISCOPLASTIC_H */
