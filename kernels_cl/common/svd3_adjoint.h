/* Adjoint of an isotropic matrix function P(F) = U diag(p(s)) V^T of F = U diag(s) V^T,
 * in the block form that stays finite at equal singular values (F = I, pure rotations):
 *
 *   G = U^T Pbar V
 *   Fhat_kk = sum_i (dp_i/ds_k) G_ii
 *   for i < j, a, b = 0.5 [ (p_i - p_j)/(s_i - s_j) +- (p_i + p_j)/(s_i + s_j) ]:
 *       Fhat_ij = a G_ij + b G_ji,   Fhat_ji = b G_ij + a G_ji
 *   Fbar = U Fhat V^T
 *
 * No 1/(s_i^2 - s_j^2) appears: the caller passes the divided differences
 * (p_i - p_j)/(s_i - s_j), computed in closed form or by a Taylor branch near s_i = s_j. */
#ifndef CLFLOW_SVD3_ADJOINT_H
#define CLFLOW_SVD3_ADJOINT_H

#include "common/mat3.h"

/* The singular-value pairs (i, j), i < j, in the order of the `diff` and `mean` arrays. */
__constant int SVD3_PAIR_I[3] = {0, 0, 1};
__constant int SVD3_PAIR_J[3] = {1, 2, 2};

/* G = U^T X V: a matrix adjoint in the singular bases. */
inline void svd3_project(const real *U, const real *V, const real *X, real *G)
{
    real tmp[9];
    mat3_mul_at(U, X, tmp);
    mat3_mul(tmp, V, G);
}

/* Fhat_ij += a G_ij + b G_ji, Fhat_ji += b G_ij + a G_ji for each pair q = (i, j), i < j,
 * a, b = 0.5 (diff[q] +- mean[q]); diff[q] = (p_i - p_j)/(s_i - s_j), mean[q] = (p_i + p_j)/(s_i + s_j). */
inline void svd3_add_off_diagonal(const real *G, const real *diff, const real *mean, real *F_hat)
{
    for (int q = 0; q < 3; ++q) {
        const int i = SVD3_PAIR_I[q], j = SVD3_PAIR_J[q];
        const real a = (real)0.5 * (diff[q] + mean[q]), b = (real)0.5 * (diff[q] - mean[q]);
        const real g_ij = G[3 * i + j], g_ji = G[3 * j + i];
        F_hat[3 * i + j] += a * g_ij + b * g_ji;
        F_hat[3 * j + i] += b * g_ij + a * g_ji;
    }
}

/* F_bar += U F_hat V^T */
inline void svd3_add_back(const real *U, const real *V, const real *F_hat, real *F_bar)
{
    real tmp[9], out[9];
    mat3_mul(U, F_hat, tmp);
    mat3_mul_bt(tmp, V, out);
    for (int k = 0; k < 9; ++k)
        F_bar[k] += out[k];
}

/* F_bar += adjoint of P = U diag(p(s)) V^T for P_bar, with dp_ds[3*i + k] = dp_i/ds_k and
 * the pair arrays of svd3_add_off_diagonal. */
inline void svd3_isotropic_adjoint(const real *U, const real *V, const real *dp_ds, const real *diff, const real *mean,
                                   const real *P_bar, real *F_bar)
{
    real G[9], F_hat[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
    svd3_project(U, V, P_bar, G);
    for (int k = 0; k < 3; ++k)
        F_hat[4 * k] = dp_ds[k] * G[0] + dp_ds[3 + k] * G[4] + dp_ds[6 + k] * G[8];
    svd3_add_off_diagonal(G, diff, mean, F_hat);
    svd3_add_back(U, V, F_hat, F_bar);
}

#endif /* CLFLOW_SVD3_ADJOINT_H */
