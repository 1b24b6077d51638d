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
 * The diagonal part goes through the transpose of each return's Jacobian d eps'/d eps. */
#ifndef CLFLOW_MPM_HENCKY_ADJOINT_H
#define CLFLOW_MPM_HENCKY_ADJOINT_H

#include "mpm/materials/hencky.h"
#include "common/svd3_adjoint.h"

/* (log max(|s_i|, s_min) - log max(|s_j|, s_min)) / (s_i - s_j), exact at s_i = s_j
 * (absolute: |s| as sand's strain; else s, which the floor keeps positive) */
inline real log_divided_difference(const real s_i, const real s_j, const real s_min, const int absolute)
{
    const real a = fmax(absolute ? fabs(s_i) : s_i, s_min), b = fmax(absolute ? fabs(s_j) : s_j, s_min);
    if (a == b)
        return s_i == s_j && a > s_min ? 1 / s_i : (real)0;
    return log1p((a - b) / b) / (s_i - s_j);
}

/* expm1(x)/x, 1 at x = 0 */
inline real expm1_ratio(const real x)
{
    return x == 0 ? (real)1 : expm1(x) / x;
}

/* What a Hencky model's adjoint shares: the SVD of F_tr (the forward's own, from
 * trial_svd_simd, so branches agree bit for bit), its strain eps = log max(s, s_min) and the
 * returned strain eps' with eps'_i - eps'_j = c (eps_i - eps_j). */
typedef struct {
    real U[9], s[3], V[9];
    real eps[3], eps_new[3];
    real c;
    int yielded; /* F' = U diag(exp eps') V^T, else F' = F_tr */
    real s_min;
    int absolute;
} hencky_t;

inline void hencky_begin(hencky_t *h, const real *U, const real *s, const real *V, const real s_min, const int absolute)
{
    mat3_copy(U, h->U);
    mat3_copy(V, h->V);
    for (int a = 0; a < 3; ++a)
        h->s[a] = s[a];
    h->s_min = s_min;
    h->absolute = absolute;
    for (int a = 0; a < 3; ++a) {
        h->eps[a] = log(fmax(absolute ? fabs(h->s[a]) : h->s[a], s_min));
        h->eps_new[a] = h->eps[a];
    }
    h->c = 1;
    h->yielded = 0;
}

/* The stress and F' part of the adjoint, common to every return: given taubar and F'bar,
 * fills the off-diagonal F_hat (in the singular bases), eps_new_bar = dL/d eps' and the
 * explicit parameter gradients of t = 2 mu eps' + lambda tr(eps'); F_tr_bar gets F'bar when
 * the return left F_tr unchanged. */
inline void hencky_stress_adjoint(const hencky_t *h, const real mu, const real lambda, const real *tau_bar,
                                  const real *F_new_bar, real *F_tr_bar, real *F_hat, real *eps_new_bar, real *mu_bar,
                                  real *lambda_bar)
{
    const real tr_new = h->eps_new[0] + h->eps_new[1] + h->eps_new[2];
    const real ones[3] = {1, 1, 1};
    real t[3], p_F[3], P[9], R[9], X[9], G_t[9], G_R[9], G_F[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
    for (int a = 0; a < 3; ++a) {
        t[a] = 2 * mu * h->eps_new[a] + lambda * tr_new;
        p_F[a] = exp(h->eps_new[a]);
    }
    mat3_udvt(h->U, t, h->V, P);
    mat3_udvt(h->U, ones, h->V, R);
    mat3_mul(tau_bar, R, X); /* Pbar = taubar R */
    svd3_project(h->U, h->V, X, G_t);
    mat3_mul_at(tau_bar, P, X); /* Rbar = taubar^T P */
    svd3_project(h->U, h->V, X, G_R);
    if (h->yielded)
        svd3_project(h->U, h->V, F_new_bar, G_F);
    else
        for (int k = 0; k < 9; ++k)
            F_tr_bar[k] += F_new_bar[k];
    const real g_sum = G_t[0] + G_t[4] + G_t[8];
    real g_eps = 0;
    for (int a = 0; a < 3; ++a) {
        eps_new_bar[a] = 2 * mu * G_t[4 * a] + lambda * g_sum + G_F[4 * a] * p_F[a];
        g_eps += G_t[4 * a] * h->eps_new[a];
    }
    *mu_bar = 2 * g_eps;
    *lambda_bar = tr_new * g_sum;

    real diff_t[3], mean_t[3], diff_R[3], mean_R[3], diff_F[3], mean_F[3];
    for (int k = 0; k < 9; ++k)
        F_hat[k] = 0;
    for (int q = 0; q < 3; ++q) {
        const int i = SVD3_PAIR_I[q], j = SVD3_PAIR_J[q];
        const real L = log_divided_difference(h->s[i], h->s[j], h->s_min, h->absolute);
        const real s_sum = h->s[i] + h->s[j];
        diff_t[q] = 2 * mu * h->c * L;
        mean_t[q] = (t[i] + t[j]) / s_sum;
        diff_R[q] = 0;
        mean_R[q] = 2 / s_sum;
        diff_F[q] = p_F[j] * expm1_ratio(h->c * (h->eps[i] - h->eps[j])) * h->c * L;
        mean_F[q] = (p_F[i] + p_F[j]) / s_sum;
    }
    svd3_add_off_diagonal(G_t, diff_t, mean_t, F_hat);
    svd3_add_off_diagonal(G_R, diff_R, mean_R, F_hat);
    if (h->yielded)
        svd3_add_off_diagonal(G_F, diff_F, mean_F, F_hat);
}

/* Finish: F_hat_kk = eps_bar_k d eps_k/d s_k (+ s_bar_k, a direct dependence on s), then
 * F_tr_bar += U F_hat V^T. */
inline void hencky_end(const hencky_t *h, const real *eps_bar, const real *s_bar, real *F_hat, real *F_tr_bar)
{
    for (int k = 0; k < 3; ++k) {
        const real mag = h->absolute ? fabs(h->s[k]) : h->s[k];
        F_hat[4 * k] = (mag > h->s_min ? eps_bar[k] / h->s[k] : (real)0) + s_bar[k];
    }
    svd3_add_back(h->U, h->V, F_hat, F_tr_bar);
}

/* Adjoint of von Mises + Hencky stress at yield stress tau_Y (plasticine, metal), with
 * dgamma_bar the gradient of whatever else uses the plastic step dgamma (metal hardening).
 * eps' = mean(eps) + y n (yielded), y = sqrt(2/3) tau_Y/(2 mu), n = eps_hat/||eps_hat||,
 * J = d eps'/d eps = 1 1^T/3 + y (P_dev/||eps_hat|| - eps_hat eps_hat^T/||eps_hat||^3) (symmetric).
 * F_tr_bar is accumulated into; writes mu_bar, lambda_bar, *dgamma_out; returns tau_Y_bar. */
inline real hencky_von_mises_adjoint(const real *U, const real *s, const real *V, const real mu, const real lambda,
                                     const real tau_Y, const real *tau_bar, const real *F_new_bar,
                                     const real dgamma_bar, real *F_tr_bar, real *mu_bar, real *lambda_bar,
                                     real *dgamma_out)
{
    hencky_t h;
    hencky_begin(&h, U, s, V, (real)HENCKY_S_MIN, 0);
    real eps_hat[3];
    deviator3(h.eps, eps_hat);
    const real norm = safe_norm3(eps_hat);
    const real y = sqrt((real)2 / 3) * tau_Y / (2 * mu);
    const real dgamma = von_mises_return(h.eps_new, mu, tau_Y);
    *dgamma_out = dgamma;
    h.yielded = dgamma > 0;
    h.c = h.yielded ? 1 - dgamma / norm : (real)1;
    real F_hat[9], eps_new_bar[3], eps_bar[3];
    hencky_stress_adjoint(&h, mu, lambda, tau_bar, F_new_bar, F_tr_bar, F_hat, eps_new_bar, mu_bar, lambda_bar);
    real y_bar = 0;
    if (h.yielded) {
        const real mean = (eps_new_bar[0] + eps_new_bar[1] + eps_new_bar[2]) / 3;
        real hat_dot = 0;
        for (int a = 0; a < 3; ++a)
            hat_dot += eps_hat[a] * eps_new_bar[a];
        const real n3 = norm * norm * norm;
        for (int a = 0; a < 3; ++a) /* J eps_new_bar + dgamma_bar n */
            eps_bar[a] = mean + y * ((eps_new_bar[a] - mean) / norm - eps_hat[a] * hat_dot / n3) +
                         dgamma_bar * eps_hat[a] / norm;
        y_bar = hat_dot / norm - dgamma_bar; /* eps' = mean + y n, dgamma = ||eps_hat|| - y */
    } else {
        for (int a = 0; a < 3; ++a)
            eps_bar[a] = eps_new_bar[a];
    }
    const real zeros[3] = {0, 0, 0};
    hencky_end(&h, eps_bar, zeros, F_hat, F_tr_bar);
    *mu_bar -= y_bar * y / mu;
    return y_bar * sqrt((real)2 / 3) / (2 * mu);
}

/* Plasticine (plasticine.h): q_bar[0..2] = (mu_bar, lambda_bar, tau_Y_bar). */
inline void plasticine_stress_adjoint(const real *U, const real *s, const real *V, const real mu, const real lambda,
                                      const real tau_Y, const real *tau_bar, const real *F_new_bar, real *F_tr_bar,
                                      real *q_bar)
{
    real dgamma;
    q_bar[2] = hencky_von_mises_adjoint(U, s, V, mu, lambda, tau_Y, tau_bar, F_new_bar, 0, F_tr_bar, &q_bar[0],
                                        &q_bar[1], &dgamma);
}

/* Metal (metal.h): yield stress tau_Y + h (h: hardening state), h' = h + 2 mu xi dgamma when
 * yielded. q_bar[0..3] = (mu_bar, lambda_bar, tau_Y_bar, xi_bar); returns hbar of state n. */
inline real metal_stress_adjoint(const real *U, const real *s, const real *V, const real mu, const real lambda,
                                 const real tau_Y, const real xi, const real hardening, const real *tau_bar,
                                 const real *F_new_bar, const real hardening_new_bar, real *F_tr_bar, real *q_bar)
{
    real dgamma;
    /* dgamma_bar of h': used only if yielded, where h' = h + 2 mu xi dgamma */
    const real dgamma_bar = 2 * mu * xi * hardening_new_bar;
    const real yield_bar = hencky_von_mises_adjoint(U, s, V, mu, lambda, tau_Y + hardening, tau_bar, F_new_bar,
                                                    dgamma_bar, F_tr_bar, &q_bar[0], &q_bar[1], &dgamma);
    q_bar[2] = yield_bar;
    if (dgamma > 0) {
        q_bar[0] += 2 * xi * dgamma * hardening_new_bar;
        q_bar[3] = 2 * mu * dgamma * hardening_new_bar;
    }
    return hardening_new_bar + yield_bar;
}

/* Foam / non-Newtonian (viscoplastic.h): q_bar[0..3] = (mu, lambda, tau_Y, eta) gradients.
 * eps' = mean(eps) + r eps_hat, r = 1 - beta + beta sqrt(2/3) tau_Y/(2 mu ||eps_hat||),
 * beta = 1/(1 + eta/(2 mu_hat dt)), mu_hat = mu sum(s^2)/3 (a direct dependence on s). */
inline void viscoplastic_stress_adjoint(const real *U, const real *s, const real *V, const real mu, const real lambda,
                                        const real tau_Y, const real eta, const real dt, const real *tau_bar,
                                        const real *F_new_bar, real *F_tr_bar, real *q_bar)
{
    hencky_t h;
    hencky_begin(&h, U, s, V, (real)HENCKY_S_MIN, 0);
    real eps_hat[3];
    deviator3(h.eps, eps_hat);
    const real norm = safe_norm3(eps_hat);
    const real s_norm = 2 * mu * norm;
    const real y = s_norm - sqrt((real)2 / 3) * tau_Y;
    const real S2 = h.s[0] * h.s[0] + h.s[1] * h.s[1] + h.s[2] * h.s[2];
    const real mu_hat = mu * S2 / 3;
    h.yielded = y > 0;
    if (h.yielded) { /* the forward's expressions, so the branch and eps' agree bit for bit */
        const real s_norm_new = s_norm - y / (1 + eta / (2 * mu_hat * dt));
        const real mean = (h.eps[0] + h.eps[1] + h.eps[2]) / 3;
        for (int a = 0; a < 3; ++a)
            h.eps_new[a] = s_norm_new / s_norm * eps_hat[a] + mean;
        h.c = s_norm_new / s_norm;
    }
    real F_hat[9], eps_new_bar[3], eps_bar[3], s_bar[3] = {0, 0, 0};
    hencky_stress_adjoint(&h, mu, lambda, tau_bar, F_new_bar, F_tr_bar, F_hat, eps_new_bar, &q_bar[0], &q_bar[1]);
    if (h.yielded) {
        const real beta = 1 / (1 + eta / (2 * mu_hat * dt));
        const real k = sqrt((real)2 / 3) / (2 * mu * norm); /* dr/dtau_Y = beta k */
        real r_bar = 0, hat_bar[3];
        for (int a = 0; a < 3; ++a)
            r_bar += eps_hat[a] * eps_new_bar[a];
        const real beta_bar = r_bar * (k * tau_Y - 1);
        const real norm_bar = -r_bar * beta * k * tau_Y / norm;
        const real mu_hat_bar = beta_bar * beta * beta * eta / (2 * mu_hat * mu_hat * dt);
        q_bar[0] += -r_bar * beta * k * tau_Y / mu + mu_hat_bar * S2 / 3;
        q_bar[2] = r_bar * beta * k;
        q_bar[3] = -beta_bar * beta * beta / (2 * mu_hat * dt);
        const real mean_bar = (eps_new_bar[0] + eps_new_bar[1] + eps_new_bar[2]) / 3;
        for (int a = 0; a < 3; ++a)
            hat_bar[a] = h.c * eps_new_bar[a] + norm_bar * eps_hat[a] / norm;
        const real hat_mean = (hat_bar[0] + hat_bar[1] + hat_bar[2]) / 3;
        for (int a = 0; a < 3; ++a) {
            eps_bar[a] = mean_bar + hat_bar[a] - hat_mean;
            s_bar[a] = mu_hat_bar * mu * 2 * h.s[a] / 3;
        }
    } else {
        for (int a = 0; a < 3; ++a)
            eps_bar[a] = eps_new_bar[a];
    }
    hencky_end(&h, eps_bar, s_bar, F_hat, F_tr_bar);
}

/* Sand (sand.h): q_bar[0..3] = (mu, lambda, alpha, c) gradients; returns v_c_bar of state n.
 * eps = log max(|s|, s_min) + v_c/3. Tip: eps' = (c, c, c) (no dependence on eps),
 * v_c' = tr(eps) - 3c; cone: eps' = eps - dgamma eps_hat/||eps_hat||,
 * dgamma = ||eps_hat|| + K alpha (tr(eps) - 3c), K = (3 lambda + 2 mu)/(2 mu), v_c' = 0;
 * inside: eps' = eps, F' = exp(v_c/3) F_tr, v_c' = 0. Every eps_k depends on v_c by 1/3. */
inline real sand_stress_adjoint(const real *F_tr, const real *U, const real *s, const real *V, const real mu,
                                const real lambda, const real alpha, const real c, const real v_c, const real *tau_bar,
                                const real *F_new_bar, const real v_c_new_bar, real *F_tr_bar, real *q_bar)
{
    hencky_t h;
    hencky_begin(&h, U, s, V, (real)SAND_S_MIN, 1);
    for (int a = 0; a < 3; ++a) { /* the forward's expressions: branches agree bit for bit */
        h.eps[a] += v_c / 3;
        h.eps_new[a] = h.eps[a];
    }
    real eps_hat[3];
    const real excess = h.eps[0] + h.eps[1] + h.eps[2] - 3 * c;
    deviator3(h.eps, eps_hat);
    const real norm = safe_norm3(eps_hat);
    const real K = (3 * lambda + 2 * mu) / (2 * mu);
    const real dgamma = norm + K * excess * alpha;
    const int tip = excess >= 0, cone = !tip && dgamma > 0;
    if (tip) {
        for (int a = 0; a < 3; ++a)
            h.eps_new[a] = c;
        h.c = 0;
    } else if (cone) {
        for (int a = 0; a < 3; ++a)
            h.eps_new[a] -= dgamma * eps_hat[a] / norm;
        h.c = 1 - dgamma / norm;
    }
    h.yielded = tip || cone;
    /* inside the cone F' = exp(v_c/3) F_tr: F_tr_bar gets exp(v_c/3) F'bar, v_c the rest */
    const real scale = h.yielded ? (real)1 : exp(v_c / 3);
    real F_scaled_bar[9], v_c_bar = 0;
    for (int k = 0; k < 9; ++k) {
        F_scaled_bar[k] = scale * F_new_bar[k];
        v_c_bar += h.yielded ? (real)0 : F_scaled_bar[k] * F_tr[k] / 3;
    }
    real F_hat[9], eps_new_bar[3], eps_bar[3] = {0, 0, 0};
    const real zeros[3] = {0, 0, 0};
    hencky_stress_adjoint(&h, mu, lambda, tau_bar, F_scaled_bar, F_tr_bar, F_hat, eps_new_bar, &q_bar[0], &q_bar[1]);
    if (tip) {
        q_bar[3] = eps_new_bar[0] + eps_new_bar[1] + eps_new_bar[2] - 3 * v_c_new_bar;
        for (int a = 0; a < 3; ++a)
            eps_bar[a] = v_c_new_bar;
    } else if (cone) {
        real hat_dot = 0;
        for (int a = 0; a < 3; ++a)
            hat_dot += eps_hat[a] * eps_new_bar[a];
        const real mean = (eps_new_bar[0] + eps_new_bar[1] + eps_new_bar[2]) / 3;
        const real n3 = norm * norm * norm;
        const real dgamma_bar = -hat_dot / norm;
        for (int a = 0; a < 3; ++a)
            eps_bar[a] = eps_new_bar[a] - dgamma * ((eps_new_bar[a] - mean) / norm - eps_hat[a] * hat_dot / n3) +
                         dgamma_bar * (eps_hat[a] / norm + K * alpha);
        const real K_bar = dgamma_bar * alpha * excess;
        q_bar[0] += -K_bar * 3 * lambda / (2 * mu * mu);
        q_bar[1] += K_bar * 3 / (2 * mu);
        q_bar[2] = dgamma_bar * K * excess;
        q_bar[3] = -3 * dgamma_bar * K * alpha;
    } else {
        for (int a = 0; a < 3; ++a)
            eps_bar[a] = eps_new_bar[a];
    }
    hencky_end(&h, eps_bar, zeros, F_hat, F_tr_bar);
    return v_c_bar + (eps_bar[0] + eps_bar[1] + eps_bar[2]) / 3;
}

#endif /* CLFLOW_MPM_HENCKY_ADJOINT_H */
