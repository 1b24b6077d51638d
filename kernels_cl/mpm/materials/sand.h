/* Sand: Drucker-Prager plasticity on Hencky strain (Klar et al. 2016), with the optional
 * volume correction of Tampubolon et al. 2017 (Sec. 4.3.4).
 * param = (mu, lambda, alpha, c): alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi)) from the
 * friction angle phi, c the cohesion as a log-strain offset of the cone tip; v_c the
 * particle's log volume correction (0 without the correction).
 *
 * eps = log(max(|s|, SAND_S_MIN)) + v_c/3. If tr(eps) - 3c >= 0 the state is past the tip:
 * eps <- (c, c, c). Otherwise dgamma = ||eps_hat|| + (3 lambda + 2 mu)/(2 mu) (tr(eps) - 3c) alpha
 * and, if dgamma > 0, eps <- eps - dgamma eps_hat / ||eps_hat||. F' = U diag(exp eps) V^T
 * (inside the cone: F' = exp(v_c/3) F_tr, the same up to the floor, keeping det F's sign).
 *
 * Volume correction: v_c' = v_c + log det F_tr - log det F' = v_c + tr(eps_tr) - tr(eps') with
 * eps_tr = eps - v_c/3 (Tampubolon eq. 26). The cone return is deviatoric (tr eps' = tr eps),
 * so v_c' = 0 inside and on the cone, and v_c' = tr(eps) - 3c at the tip: the volume the tip
 * projection removes is kept and given back when the sand is compressed again. */
#ifndef CLFLOW_MPM_SAND_H
#define CLFLOW_MPM_SAND_H

#include "mpm/materials/hencky.h"

inline void sand_stress(const real *F_tr, const real *U, const real *s, const real *V, const real mu, const real lambda,
                        const real alpha, const real c, const real v_c, real *F_new, real *v_c_new, real *tau)
{
    real eps[3], eps_hat[3];
    for (int a = 0; a < 3; ++a)
        eps[a] = log(fmax(fabs(s[a]), (real)SAND_S_MIN)) + v_c / 3;
    const real excess = eps[0] + eps[1] + eps[2] - 3 * c;
    deviator3(eps, eps_hat);
    const real norm = safe_norm3(eps_hat);
    const real dgamma = norm + (3 * lambda + 2 * mu) / (2 * mu) * excess * alpha;
    if (excess >= 0) {
        for (int a = 0; a < 3; ++a)
            eps[a] = c;
        f_from_strain(U, eps, V, F_new);
        *v_c_new = excess;
    } else if (dgamma > 0) {
        for (int a = 0; a < 3; ++a)
            eps[a] -= dgamma * eps_hat[a] / norm;
        f_from_strain(U, eps, V, F_new);
        *v_c_new = 0;
    } else {
        const real scale = exp(v_c / 3);
        for (int k = 0; k < 9; ++k)
            F_new[k] = scale * F_tr[k];
        *v_c_new = 0;
    }
    hencky_tau(U, eps, mu, lambda, tau);
}

#endif /* CLFLOW_MPM_SAND_H */
