/* Adjoints of the elastic models (elastic.h): given taubar = dL/dtau, accumulate
 * Fbar += dL/dF and return dL/dmu, dL/dlambda.
 *
 * fixed corotated, tau = 2 mu (F - R) F^T + lambda (J - 1) J I:
 *   Fbar = 2 mu [taubar F + taubar^T (F - R)] + R^T-adjoint(-2 mu taubar F)
 *          + lambda (2J - 1) tr(taubar) cof(F)
 *   R = U V^T is the isotropic map p(s) = (1, 1, 1): dp/ds = 0, divided differences 0 and
 *   mean terms 2/(s_i + s_j), so its adjoint is finite at F = I and at rotations.
 * neo-Hookean, tau = mu (F F^T - I) + lambda log(J) I (J floored):
 *   Fbar = mu (taubar + taubar^T) F + lambda tr(taubar) cof(F) / J   (0 below the floor) */
#ifndef CLFLOW_MPM_ELASTIC_ADJOINT_H
#define CLFLOW_MPM_ELASTIC_ADJOINT_H

#include "common/svd3.h"
#include "common/svd3_adjoint.h"

/* Adjoint of fixed_corotated_tau at F = U diag(s) V^T; F_bar is accumulated into. */
inline void fixed_corotated_adjoint(const real *F, const real *U, const real *s, const real *V,
                                    const real mu, const real lambda, const real *tau_bar,
                                    real *F_bar, real *mu_bar, real *lambda_bar)
{
    const real ones[3] = {1, 1, 1};
    const real zeros[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
    real R[9], F_minus_R[9], tau_bar_F[9], R_bar[9], cof[9];
    mat3_udvt(U, ones, V, R);
    for (int k = 0; k < 9; ++k)
        F_minus_R[k] = F[k] - R[k];
    mat3_mul(tau_bar, F, tau_bar_F);
    const real mean[3] = {2 / (s[0] + s[1]), 2 / (s[0] + s[2]), 2 / (s[1] + s[2])};
    for (int k = 0; k < 9; ++k)
        R_bar[k] = -2 * mu * tau_bar_F[k];
    svd3_isotropic_adjoint(U, V, zeros, zeros, mean, R_bar, F_bar);
    mat3_cofactor(F, cof);
    const real J = s[0] * s[1] * s[2];
    const real trace_bar = mat3_trace(tau_bar);
    real energy = 0; /* <taubar, (F - R) F^T> */
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) {
            const int rc = 3 * r + c;
            /* (taubar^T (F - R))_rc = sum_k taubar_kr (F - R)_kc */
            const real tbt_fr = tau_bar[r] * F_minus_R[c] + tau_bar[3 + r] * F_minus_R[3 + c] +
                                tau_bar[6 + r] * F_minus_R[6 + c];
            F_bar[rc] += 2 * mu * (tau_bar_F[rc] + tbt_fr) +
                         lambda * (2 * J - 1) * trace_bar * cof[rc];
            energy += tau_bar_F[rc] * F_minus_R[rc];
        }
    /* <taubar, (F - R) F^T> = <taubar F, F - R> */
    *mu_bar = 2 * energy;
    *lambda_bar = trace_bar * (J - 1) * J;
}

inline void elastic_stress_adjoint(const real *F, const real mu, const real lambda, const real *tau_bar,
                                   real *F_bar, real *mu_bar, real *lambda_bar)
{
    real U[9], s[3], V[9];
    svd3(F, U, s, V);
    fixed_corotated_adjoint(F, U, s, V, mu, lambda, tau_bar, F_bar, mu_bar, lambda_bar);
}

inline void neo_hookean_stress_adjoint(const real *F, const real mu, const real lambda, const real *tau_bar,
                                       real *F_bar, real *mu_bar, real *lambda_bar)
{
    const real det = mat3_det(F);
    const real floor_J = (real)(HENCKY_S_MIN * HENCKY_S_MIN * HENCKY_S_MIN);
    const real J = fmax(det, floor_J);
    const real trace_bar = mat3_trace(tau_bar);
    real sym[9], sym_F[9], FFt[9], cof[9];
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            sym[3 * r + c] = tau_bar[3 * r + c] + tau_bar[3 * c + r];
    mat3_mul(sym, F, sym_F);
    mat3_mul_bt(F, F, FFt);
    mat3_cofactor(F, cof);
    const real log_scale = det > floor_J ? lambda * trace_bar / J : (real)0;
    real energy = 0; /* <taubar, F F^T - I> */
    for (int k = 0; k < 9; ++k) {
        F_bar[k] += mu * sym_F[k] + log_scale * cof[k];
        energy += tau_bar[k] * (FFt[k] - ((k % 4 == 0) ? (real)1 : (real)0));
    }
    *mu_bar = energy;
    *lambda_bar = trace_bar * log(J);
}

#endif /* CLFLOW_MPM_ELASTIC_ADJOINT_H */
