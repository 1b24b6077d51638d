/* Adjoints of the Hencky-strain models (hencky.h): von Mises return + Hencky stress.
 *
 * With F_tr = U diag(s) V^T, eps = log max(s, s_min), the return eps' = eps - dgamma n
 * (n = eps_hat/||eps_hat||, only when dgamma > 0), t = 2 mu eps' + lambda tr(eps') 1:
 *   tau = U diag(t) U^T = P R^T with P = U diag(t) V^T and R = U V^T, so
 *   Pbar = taubar R and Rbar = taubar^T P; F' = U diag(exp eps') V^T when yielded (else F_tr).
 * P, R and F' are isotropic maps of F_tr, pulled back with the block form
 * (common/svd3_adjoint.h). Their divided differences are stable closed forms:
 *   eps'_i - eps'_j = c (eps_i - eps_j), c = 1 - dgamma/||eps_hat|| (1 if elastic),
 *   (t_i - t_j)/(s_i - s_j) = 2 mu c L_ij,  L_ij = (eps_i - eps_j)/(s_i - s_j) (log1p form),
 *   (exp eps'_i - exp eps'_j)/(s_i - s_j) = exp(eps'_j) phi(c (eps_i - eps_j)) c L_ij,
 *   phi(x) = expm1(x)/x.
 * The diagonal part goes through the return's Jacobian J = d eps'/d eps (symmetric):
 *   J = 1 1^T/3 + y (P_dev/||eps_hat|| - eps_hat eps_hat^T/||eps_hat||^3),  y = sqrt(2/3) tau_Y/(2 mu). */
#ifndef CLFLOW_MPM_HENCKY_ADJOINT_H
#define CLFLOW_MPM_HENCKY_ADJOINT_H

#include "mpm/materials/hencky.h"
#include "common/svd3_adjoint.h"

/* (log max(s_i, s_min) - log max(s_j, s_min)) / (s_i - s_j), exact at s_i = s_j */
inline real log_divided_difference(const real s_i, const real s_j)
{
    const real a = fmax(s_i, (real)HENCKY_S_MIN), b = fmax(s_j, (real)HENCKY_S_MIN);
    if (a == b)
        return s_i == s_j && s_i > (real)HENCKY_S_MIN ? 1 / a : (real)0;
    return log1p((a - b) / b) / (s_i - s_j);
}

/* expm1(x)/x, 1 at x = 0 */
inline real expm1_ratio(const real x)
{
    return x == 0 ? (real)1 : expm1(x) / x;
}

/* The von Mises return of the Hencky strain of singular values s, with what its adjoint needs. */
typedef struct {
    real eps[3], eps_new[3], eps_hat[3];
    real norm;   /* safe ||eps_hat|| */
    real y;      /* sqrt(2/3) tau_Y / (2 mu): the yield radius in strain */
    real dgamma; /* > 0: yielded */
} von_mises_t;

inline von_mises_t von_mises_state(const real *s, const real mu, const real tau_Y)
{
    von_mises_t vm;
    hencky_strain(s, vm.eps);
    deviator3(vm.eps, vm.eps_hat);
    vm.norm = safe_norm3(vm.eps_hat);
    vm.y = sqrt((real)2 / 3) * tau_Y / (2 * mu);
    for (int a = 0; a < 3; ++a)
        vm.eps_new[a] = vm.eps[a];
    vm.dgamma = von_mises_return(vm.eps_new, mu, tau_Y);
    return vm;
}

/* out = J v, J = d eps'/d eps of the return (the identity when elastic) */
inline void von_mises_jacobian_apply(const von_mises_t *vm, const real *v, real *out)
{
    if (vm->dgamma <= 0) {
        for (int a = 0; a < 3; ++a)
            out[a] = v[a];
        return;
    }
    const real mean = (v[0] + v[1] + v[2]) / 3;
    const real hat_dot = vm->eps_hat[0] * v[0] + vm->eps_hat[1] * v[1] + vm->eps_hat[2] * v[2];
    const real n3 = vm->norm * vm->norm * vm->norm;
    for (int a = 0; a < 3; ++a)
        out[a] = mean + vm->y * ((v[a] - mean) / vm->norm - vm->eps_hat[a] * hat_dot / n3);
}

/* Adjoint of (F', tau, dgamma) = von Mises + Hencky stress of F_tr at yield stress tau_Y, with
 * dgamma_bar the gradient of whatever else uses the plastic step dgamma (metal hardening).
 * F_tr_bar is accumulated into; writes mu_bar, lambda_bar, *dgamma_out, and returns
 * tau_Y_bar. */
inline real hencky_von_mises_adjoint(const real *F_tr, const real mu, const real lambda, const real tau_Y,
                                     const real *tau_bar, const real *F_new_bar, const real dgamma_bar,
                                     real *F_tr_bar, real *mu_bar, real *lambda_bar, real *dgamma_out)
{
    real U[9], s[3], V[9];
    svd3(F_tr, U, s, V);
    const von_mises_t vm = von_mises_state(s, mu, tau_Y);
    *dgamma_out = vm.dgamma;
    const int yielded = vm.dgamma > 0;
    const real tr_new = vm.eps_new[0] + vm.eps_new[1] + vm.eps_new[2];
    const real ones[3] = {1, 1, 1};
    real t[3], p_F[3], P[9], R[9], X[9], G_t[9], G_R[9], G_F[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
    for (int a = 0; a < 3; ++a) {
        t[a] = 2 * mu * vm.eps_new[a] + lambda * tr_new;
        p_F[a] = exp(vm.eps_new[a]);
    }
    mat3_udvt(U, t, V, P);
    mat3_udvt(U, ones, V, R);
    mat3_mul(tau_bar, R, X); /* Pbar = taubar R */
    svd3_project(U, V, X, G_t);
    mat3_mul_at(tau_bar, P, X); /* Rbar = taubar^T P */
    svd3_project(U, V, X, G_R);
    if (yielded)
        svd3_project(U, V, F_new_bar, G_F);
    else
        for (int k = 0; k < 9; ++k)
            F_tr_bar[k] += F_new_bar[k];

    /* diagonal: epsbar' from t and F', through J (and dgamma = ||eps_hat|| - y: d/d eps = n),
     * then d eps/d s */
    const real g_sum = G_t[0] + G_t[4] + G_t[8];
    real eps_new_bar[3], eps_bar[3], F_hat[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
    for (int a = 0; a < 3; ++a)
        eps_new_bar[a] = 2 * mu * G_t[4 * a] + lambda * g_sum + G_F[4 * a] * p_F[a];
    von_mises_jacobian_apply(&vm, eps_new_bar, eps_bar);
    if (yielded)
        for (int a = 0; a < 3; ++a)
            eps_bar[a] += dgamma_bar * vm.eps_hat[a] / vm.norm;
    for (int k = 0; k < 3; ++k)
        F_hat[4 * k] = s[k] > (real)HENCKY_S_MIN ? eps_bar[k] / s[k] : (real)0;

    /* off-diagonal: one pair term per map */
    const real c = yielded ? 1 - vm.dgamma / vm.norm : (real)1;
    real diff_t[3], mean_t[3], diff_R[3], mean_R[3], diff_F[3], mean_F[3];
    for (int q = 0; q < 3; ++q) {
        const int i = SVD3_PAIR_I[q], j = SVD3_PAIR_J[q];
        const real L = log_divided_difference(s[i], s[j]);
        const real s_sum = s[i] + s[j];
        diff_t[q] = 2 * mu * c * L;
        mean_t[q] = (t[i] + t[j]) / s_sum;
        diff_R[q] = 0;
        mean_R[q] = 2 / s_sum;
        diff_F[q] = p_F[j] * expm1_ratio(c * (vm.eps[i] - vm.eps[j])) * c * L;
        mean_F[q] = (p_F[i] + p_F[j]) / s_sum;
    }
    svd3_add_off_diagonal(G_t, diff_t, mean_t, F_hat);
    svd3_add_off_diagonal(G_R, diff_R, mean_R, F_hat);
    if (yielded)
        svd3_add_off_diagonal(G_F, diff_F, mean_F, F_hat);
    svd3_add_back(U, V, F_hat, F_tr_bar);

    /* parameters: t depends on mu, lambda directly; eps' = mean(eps) + y n and dgamma on
     * y = sqrt(2/3) tau_Y/(2 mu) (only when yielded) */
    real y_bar = 0, g_eps = 0;
    for (int a = 0; a < 3; ++a) {
        y_bar += eps_new_bar[a] * vm.eps_hat[a] / vm.norm;
        g_eps += G_t[4 * a] * vm.eps_new[a];
    }
    y_bar = yielded ? y_bar - dgamma_bar : (real)0;
    *mu_bar = 2 * g_eps - y_bar * vm.y / mu;
    *lambda_bar = tr_new * g_sum;
    return y_bar * sqrt((real)2 / 3) / (2 * mu);
}

/* Plasticine (plasticine.h): q_bar[0..2] = (mu_bar, lambda_bar, tau_Y_bar). */
inline void plasticine_stress_adjoint(const real *F_tr, const real mu, const real lambda, const real tau_Y,
                                      const real *tau_bar, const real *F_new_bar, real *F_tr_bar,
                                      real *q_bar)
{
    real dgamma;
    q_bar[2] = hencky_von_mises_adjoint(F_tr, mu, lambda, tau_Y, tau_bar, F_new_bar, 0, F_tr_bar, &q_bar[0],
                                        &q_bar[1], &dgamma);
}

/* Metal (metal.h): yield stress tau_Y + h (h: hardening state), h' = h + 2 mu xi dgamma when
 * yielded. q_bar[0..3] = (mu_bar, lambda_bar, tau_Y_bar, xi_bar); returns hbar of state n. */
inline real metal_stress_adjoint(const real *F_tr, const real mu, const real lambda, const real tau_Y,
                                 const real xi, const real hardening, const real *tau_bar,
                                 const real *F_new_bar, const real hardening_new_bar, real *F_tr_bar,
                                 real *q_bar)
{
    real dgamma;
    /* dgamma_bar of h': used only if yielded, where h' = h + 2 mu xi dgamma */
    const real dgamma_bar = 2 * mu * xi * hardening_new_bar;
    const real yield_bar = hencky_von_mises_adjoint(F_tr, mu, lambda, tau_Y + hardening, tau_bar, F_new_bar,
                                                    dgamma_bar, F_tr_bar, &q_bar[0], &q_bar[1], &dgamma);
    q_bar[2] = yield_bar;
    if (dgamma > 0) {
        q_bar[0] += 2 * xi * dgamma * hardening_new_bar;
        q_bar[3] = 2 * mu * dgamma * hardening_new_bar;
    }
    return hardening_new_bar + yield_bar;
}

#endif /* CLFLOW_MPM_HENCKY_ADJOINT_H */
