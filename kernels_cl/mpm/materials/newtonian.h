/* Newtonian fluid: J-only state (F kept as J^(1/3) I), Tait pressure and viscous stress.
 * param = (mu, kappa): dynamic viscosity (Pa s) and bulk modulus (Pa).
 *
 * J = max(det F_tr, NEWTONIAN_J_MIN); p = (kappa / 7) (J^-7 - 1) (Tait, gamma 7, scaled so
 * that -J dp/dJ = kappa at rest: kappa is the bulk modulus); D = sym(C);
 * tau = -p J I + 2 mu J dev(D). (PAC-NeRF writes mu J sym(C): its mu is twice the
 * viscosity, and its kappa (J^-7 - 1) has bulk modulus 7 kappa; see docs/mpm.md.) */
#ifndef CLFLOW_MPM_NEWTONIAN_H
#define CLFLOW_MPM_NEWTONIAN_H

#include "common/mat3.h"

inline void newtonian_stress(const real *F_tr, const real *C, const real mu, const real kappa, real *F_new, real *tau)
{
    const real J = fmax(mat3_det(F_tr), (real)NEWTONIAN_J_MIN);
    const real J2 = J * J, J7 = J2 * J2 * J2 * J;
    const real p = kappa / 7 * (1 / J7 - 1);
    const real cbrt_J = cbrt(J);
    const real mean_rate = (C[0] + C[4] + C[8]) / 3;
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) {
            const real D_dev = (C[3 * r + c] + C[3 * c + r]) / 2 - (r == c ? mean_rate : 0);
            tau[3 * r + c] = 2 * mu * J * D_dev - (r == c ? p * J : 0);
            F_new[3 * r + c] = r == c ? cbrt_J : 0;
        }
}

#endif /* CLFLOW_MPM_NEWTONIAN_H */
