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

/* Adjoint of fixed_corotated_tau at F = U diag(s) V^T; F_bar is accumulated into. For
 * T = real, and realv with CLFLOW_SIMD_LANES. The rotation's part (the block form of
 * svd3_adjoint.h with p = (1, 1, 1)), with Rbar = -2 mu taubar F and G = U^T taubar F V:
 * Fhat_ij = -2 mu (G_ij - G_ji)/(s_i + s_j) for i != j (antisymmetric), Fhat_ii = 0,
 * Fbar += U Fhat V^T. */
#define CLFLOW_DEFINE_FIXED_COROTATED_ADJOINT(SFX, T)                                                                  \
    inline void fixed_corotated_adjoint##SFX(const T *F, const T *U, const T *s, const T *V, const T mu,               \
                                             const T lambda, const T *tau_bar, T *F_bar, T *mu_bar, T *lambda_bar)     \
    {                                                                                                                  \
        const T ones[3] = {(T)1, (T)1, (T)1};                                                                          \
        T R[9], F_minus_R[9], tau_bar_F[9], Ut_X[9], G[9], U_F_hat[9], R_part[9], cof[9];                              \
        mat3_udvt##SFX(U, ones, V, R);                                                                                 \
        for (int k = 0; k < 9; ++k)                                                                                    \
            F_minus_R[k] = F[k] - R[k];                                                                                \
        mat3_mul##SFX(tau_bar, F, tau_bar_F);                                                                          \
        mat3_mul_at##SFX(U, tau_bar_F, Ut_X);                                                                          \
        mat3_mul##SFX(Ut_X, V, G);                                                                                     \
        const T h01 = -2 * mu * (G[1] - G[3]) / (s[0] + s[1]);                                                         \
        const T h02 = -2 * mu * (G[2] - G[6]) / (s[0] + s[2]);                                                         \
        const T h12 = -2 * mu * (G[5] - G[7]) / (s[1] + s[2]);                                                         \
        const T F_hat[9] = {(T)0, h01, h02, -h01, (T)0, h12, -h02, -h12, (T)0};                                        \
        mat3_mul##SFX(U, F_hat, U_F_hat);                                                                              \
        mat3_mul_bt##SFX(U_F_hat, V, R_part);                                                                          \
        mat3_cofactor##SFX(F, cof);                                                                                    \
        const T J = s[0] * s[1] * s[2];                                                                                \
        const T trace_bar = trace3##SFX(tau_bar);                                                                      \
        const T volume_scale = lambda * (2 * J - 1) * trace_bar;                                                       \
        T energy = (T)0; /* <taubar, (F - R) F^T> = <taubar F, F - R> */                                               \
        for (int r = 0; r < 3; ++r)                                                                                    \
            for (int c = 0; c < 3; ++c) {                                                                              \
                const int rc = 3 * r + c;                                                                              \
                /* (taubar^T (F - R))_rc = sum_k taubar_kr (F - R)_kc */                                               \
                const T tbt_fr =                                                                                       \
                    tau_bar[r] * F_minus_R[c] + tau_bar[3 + r] * F_minus_R[3 + c] + tau_bar[6 + r] * F_minus_R[6 + c]; \
                F_bar[rc] += 2 * mu * (tau_bar_F[rc] + tbt_fr) + volume_scale * cof[rc] + R_part[rc];                  \
                energy += tau_bar_F[rc] * F_minus_R[rc];                                                               \
            }                                                                                                          \
        *mu_bar = 2 * energy;                                                                                          \
        *lambda_bar = trace_bar * (J - 1) * J;                                                                         \
    }

CLFLOW_DEFINE_FIXED_COROTATED_ADJOINT(, real)
#ifdef CLFLOW_SIMD_LANES
CLFLOW_DEFINE_FIXED_COROTATED_ADJOINT(_v, realv)
#endif

inline void neo_hookean_stress_adjoint(const real *F, const real mu, const real lambda, const real *tau_bar,
                                       real *F_bar, real *mu_bar, real *lambda_bar)
{
    const real det = mat3_det(F);
    const real floor_J = (real)(HENCKY_S_MIN * HENCKY_S_MIN * HENCKY_S_MIN);
    const real J = fmax(det, floor_J);
    const real trace_bar = trace3(tau_bar);
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

/* Snow (snow.h): F_E = U diag(s_E) V^T, s_E = clamp(s, 1 - theta_c, 1 + theta_s),
 * J_P' = J_P prod(s)/prod(s_E), h = exp(xi (1 - J_P')), tau = fixed corotated of F_E at
 * (mu0 h, lambda0 h); F' = F_E. Through the clamp: ds_E/ds = 1 inside, 0 when clamped (then
 * s_E depends on theta_c or theta_s instead), and J_P' depends on s_k only where s_k is
 * clamped (dJ_P'/ds_k = J_P'/s_k). q_bar[0..4] = (mu0, lambda0, theta_c, theta_s, xi)
 * gradients; returns J_P bar of state n. */
inline real snow_stress_adjoint(const real *U, const real *s, const real *V, const real mu0, const real lambda0,
                                const real theta_c, const real theta_s, const real xi, const real J_P,
                                const real *tau_bar, const real *F_new_bar, const real J_P_new_bar, real *F_tr_bar,
                                real *q_bar)
{
    real s_E[3], F_E[9], F_E_bar[9], G[9], F_hat[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
    const real lo = 1 - theta_c, hi = 1 + theta_s;
    for (int a = 0; a < 3; ++a)
        s_E[a] = clamp(s[a], lo, hi);
    mat3_udvt(U, s_E, V, F_E);
    const real volume_ratio = (s[0] * s[1] * s[2]) / (s_E[0] * s_E[1] * s_E[2]);
    const real J_P_new = J_P * volume_ratio;
    const real h = exp(xi * (1 - J_P_new));
    real mu_bar, lambda_bar;
    mat3_copy(F_new_bar, F_E_bar);
    fixed_corotated_adjoint(F_E, U, s_E, V, mu0 * h, lambda0 * h, tau_bar, F_E_bar, &mu_bar, &lambda_bar);
    const real h_bar = mu_bar * mu0 + lambda_bar * lambda0;
    const real J_P_bar = J_P_new_bar - h_bar * h * xi; /* of J_P' */
    q_bar[0] = mu_bar * h;
    q_bar[1] = lambda_bar * h;
    q_bar[4] = h_bar * h * (1 - J_P_new);
    svd3_project(U, V, F_E_bar, G);
    for (int k = 0; k < 3; ++k) {
        if (s[k] < lo || s[k] > hi) {
            const real sign = s[k] < lo ? (real)-1 : (real)1; /* ds_E/dtheta_c = -1, ds_E/dtheta_s = +1 */
            const real s_E_bar = G[4 * k] - J_P_bar * J_P_new / s_E[k];
            q_bar[s[k] < lo ? 2 : 3] += sign * s_E_bar;
            F_hat[4 * k] = J_P_bar * J_P_new / s[k];
        } else {
            F_hat[4 * k] = G[4 * k];
        }
    }
    real diff[3], mean[3];
    for (int q = 0; q < 3; ++q) {
        const int i = SVD3_PAIR_I[q], j = SVD3_PAIR_J[q];
        const int inside_i = s[i] >= lo && s[i] <= hi;
        diff[q] = s[i] != s[j] ? (s_E[i] - s_E[j]) / (s[i] - s[j]) : (real)inside_i;
        mean[q] = (s_E[i] + s_E[j]) / (s[i] + s[j]);
    }
    svd3_add_off_diagonal(G, diff, mean, F_hat);
    svd3_add_back(U, V, F_hat, F_tr_bar);
    return J_P_bar * volume_ratio;
}

#endif /* CLFLOW_MPM_ELASTIC_ADJOINT_H */
