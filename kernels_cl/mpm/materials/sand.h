/* Sand: Drucker-Prager plasticity on Hencky strain (Klar et al. 2016).
 * param = (mu, lambda, alpha, c): alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi)) from the
 * friction angle phi, c the cohesion as a log-strain offset of the cone tip.
 *
 * eps = log(max(|s|, SAND_S_MIN)). If tr(eps) - 3c >= 0 the state is past the tip:
 * eps <- (c, c, c). Otherwise dgamma = ||eps_hat|| + (3 lambda + 2 mu)/(2 mu) (tr(eps) - 3c) alpha
 * and, if dgamma > 0, eps <- eps - dgamma eps_hat / ||eps_hat||. F' = U diag(exp eps) V^T. */
#ifndef CLFLOW_MPM_SAND_H
#define CLFLOW_MPM_SAND_H

#include "mpm/materials/hencky.h"

inline void sand_stress(const real *F_tr, const real *U, const real *s, const real *V,
                              const real mu, const real lambda, const real alpha,
                        const real c, real *F_new, real *tau)
{
    real eps[3], eps_hat[3];
    for (int a = 0; a < 3; ++a)
        eps[a] = log(fmax(fabs(s[a]), (real)SAND_S_MIN));
    const real excess = eps[0] + eps[1] + eps[2] - 3 * c;
    deviator3(eps, eps_hat);
    const real norm = safe_norm3(eps_hat);
    const real dgamma = norm + (3 * lambda + 2 * mu) / (2 * mu) * excess * alpha;
    if (excess >= 0) {
        for (int a = 0; a < 3; ++a)
            eps[a] = c;
        f_from_strain(U, eps, V, F_new);
    } else if (dgamma > 0) {
        for (int a = 0; a < 3; ++a)
            eps[a] -= dgamma * eps_hat[a] / norm;
        f_from_strain(U, eps, V, F_new);
    } else {
        mat3_copy(F_tr, F_new);
    }
    hencky_tau(U, eps, mu, lambda, tau);
}

#endif /* CLFLOW_MPM_SAND_H */
