/* Adjoint of the Newtonian fluid (newtonian.h): J = max(det F_tr, J_min),
 * tau = 2 mu J dev(sym C) - p(J) J I with p = (kappa/7)(J^-7 - 1), F' = J^(1/3) I.
 *   Jbar = <taubar, 2 mu dev(sym C)> - tr(taubar) (p - kappa J^-7) + tr(F'bar) J^(1/3)/(3J)
 *   F_trbar += Jbar cof(F_tr) (0 below the floor),  Cbar += 2 mu J dev(sym taubar)
 *   mubar = <taubar, 2 J dev(sym C)>,  kappabar = -tr(taubar) J (J^-7 - 1)/7 */
#ifndef CLFLOW_MPM_NEWTONIAN_ADJOINT_H
#define CLFLOW_MPM_NEWTONIAN_ADJOINT_H

#include "common/svd3_adjoint.h"

/* out = dev(sym(a)) */
inline void mat3_sym_dev(const real *a, real *out)
{
    const real mean = (a[0] + a[4] + a[8]) / 3;
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            out[3 * r + c] = (a[3 * r + c] + a[3 * c + r]) / 2 - (r == c ? mean : 0);
}

inline void newtonian_stress_adjoint(const real *F_tr, const real *C, const real mu, const real kappa,
                                     const real *tau_bar, const real *F_new_bar, real *F_tr_bar, real *C_bar,
                                     real *q_bar)
{
    const real det = mat3_det(F_tr);
    const real J = fmax(det, (real)NEWTONIAN_J_MIN);
    const real J2 = J * J, J7 = J2 * J2 * J2 * J;
    const real p = kappa / 7 * (1 / J7 - 1);
    real D_dev[9], T_dev[9], cof[9];
    mat3_sym_dev(C, D_dev);
    mat3_sym_dev(tau_bar, T_dev);
    real rate_work = 0; /* <taubar, dev(sym C)> */
    for (int k = 0; k < 9; ++k) {
        rate_work += tau_bar[k] * D_dev[k];
        C_bar[k] += 2 * mu * J * T_dev[k];
    }
    const real tr_bar = trace3(tau_bar);
    const real J_bar = 2 * mu * rate_work - tr_bar * (p - kappa / J7) + trace3(F_new_bar) * cbrt(J) / (3 * J);
    if (det > (real)NEWTONIAN_J_MIN) {
        mat3_cofactor(F_tr, cof);
        for (int k = 0; k < 9; ++k)
            F_tr_bar[k] += J_bar * cof[k];
    }
    q_bar[0] = 2 * J * rate_work;
    q_bar[1] = -tr_bar * J * (1 / J7 - 1) / 7;
}

#endif /* CLFLOW_MPM_NEWTONIAN_ADJOINT_H */
