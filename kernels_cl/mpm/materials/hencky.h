/* Hencky (logarithmic) strain on singular values, shared by the plastic models.
 *
 * eps_i = log(max(s_i, HENCKY_S_MIN)); eps_hat = eps - tr(eps)/3;
 * Kirchhoff stress tau = U diag(2 mu eps + lambda tr(eps)) U^T (no extra factor s_i:
 * PhysGaussian's "StVK-Hencky" has one, a peer bug; see docs/mpm.md). */
#ifndef CLFLOW_MPM_HENCKY_H
#define CLFLOW_MPM_HENCKY_H

#include "common/svd3.h"

/* sqrt(x.x + SAFE_NORM_EPS2): a norm that is safe to divide by */
inline real safe_norm3(const real *x)
{
    return sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2] + (real)SAFE_NORM_EPS2);
}

inline void hencky_strain(const real *s, real *eps)
{
    for (int a = 0; a < 3; ++a)
        eps[a] = log(fmax(s[a], (real)HENCKY_S_MIN));
}

inline void deviator3(const real *eps, real *eps_hat)
{
    const real mean = (eps[0] + eps[1] + eps[2]) / 3;
    for (int a = 0; a < 3; ++a)
        eps_hat[a] = eps[a] - mean;
}

inline void hencky_tau(const real *U, const real *eps, const real mu, const real lambda, real *tau)
{
    const real tr = eps[0] + eps[1] + eps[2];
    real d[3];
    for (int a = 0; a < 3; ++a)
        d[a] = 2 * mu * eps[a] + lambda * tr;
    mat3_udvt(U, d, U, tau);
}

/* F = U diag(exp(eps)) V^T: the elastic deformation a return mapping leaves */
inline void f_from_strain(const real *U, const real *eps, const real *V, real *F)
{
    real s[3];
    for (int a = 0; a < 3; ++a)
        s[a] = exp(eps[a]);
    mat3_udvt(U, s, V, F);
}

/* Von Mises return of the Hencky strain (uniaxial yield stress tau_Y, surface
 * ||dev tau|| = sqrt(2/3) tau_Y): dgamma = ||eps_hat|| - sqrt(2/3) tau_Y / (2 mu);
 * if dgamma > 0, eps <- eps - dgamma eps_hat / ||eps_hat||. Returns dgamma (<= 0: elastic). */
inline real von_mises_return(real *eps, const real mu, const real tau_Y)
{
    real eps_hat[3];
    deviator3(eps, eps_hat);
    const real norm = safe_norm3(eps_hat);
    const real dgamma = norm - sqrt((real)2 / 3) * tau_Y / (2 * mu);
    if (dgamma > 0)
        for (int a = 0; a < 3; ++a)
            eps[a] -= dgamma * eps_hat[a] / norm;
    return dgamma;
}

#endif /* CLFLOW_MPM_HENCKY_H */
