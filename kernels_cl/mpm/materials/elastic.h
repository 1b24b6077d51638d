/* Elastic: fixed corotated (default) or neo-Hookean hyperelasticity. param = (mu, lambda).
 *
 * fixed corotated: tau = 2 mu (F - R) F^T + lambda (J - 1) J I, R = U V^T
 * neo-Hookean:     tau = mu (F F^T - I) + lambda log(J) I   (J floored at HENCKY_S_MIN^3)
 * The SVD-based models here and in the other headers take U, s, V = svd3(F_tr) from the
 * caller (stress.cl computes it for 8 particles at a time in SIMD lanes). */
#ifndef CLFLOW_MPM_ELASTIC_H
#define CLFLOW_MPM_ELASTIC_H

#include "common/svd3.h"

#define CLFLOW_DEFINE_FIXED_COROTATED(SFX, T)                                                                          \
    inline void fixed_corotated_tau##SFX(const T *F, const T *U, const T *s, const T *V, const T mu, const T lambda,   \
                                         T *tau)                                                                       \
    {                                                                                                                  \
        const T ones[3] = {(T)1, (T)1, (T)1};                                                                          \
        T R[9], F_minus_R[9];                                                                                          \
        mat3_udvt##SFX(U, ones, V, R);                                                                                 \
        for (int k = 0; k < 9; ++k)                                                                                    \
            F_minus_R[k] = F[k] - R[k];                                                                                \
        mat3_mul_bt##SFX(F_minus_R, F, tau);                                                                           \
        const T J = s[0] * s[1] * s[2];                                                                                \
        for (int k = 0; k < 9; ++k)                                                                                    \
            tau[k] *= 2 * mu;                                                                                          \
        for (int a = 0; a < 3; ++a)                                                                                    \
            tau[4 * a] += lambda * (J - 1) * J;                                                                        \
    }

CLFLOW_DEFINE_FIXED_COROTATED(, real)
#ifdef CLFLOW_SIMD_LANES
CLFLOW_DEFINE_FIXED_COROTATED(_v, realv)
#endif

inline void neo_hookean_stress(const real *F, const real mu, const real lambda, real *tau)
{
    const real J = fmax(mat3_det(F), (real)(HENCKY_S_MIN * HENCKY_S_MIN * HENCKY_S_MIN));
    mat3_mul_bt(F, F, tau);
    for (int k = 0; k < 9; ++k)
        tau[k] *= mu;
    for (int a = 0; a < 3; ++a)
        tau[4 * a] += lambda * log(J) - mu;
}

#endif /* CLFLOW_MPM_ELASTIC_H */
