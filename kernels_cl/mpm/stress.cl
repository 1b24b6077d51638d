/* Substep stage 1: deformation update, return mapping and Kirchhoff stress.
 *
 *   F_tr = (I + dt C_n) F_n;  (F_{n+1}, plastic_{n+1}) = Z(F_tr; param);  tau = tau(F_{n+1})
 *
 * Reads state n, writes state n+1's F and plastic state and this substep's tau: nothing
 * is overwritten that the adjoint needs. param[p] holds PARAM_COUNT kernel parameters per
 * particle (their meaning per material: clflow/mpm/constants.py, kernel_params()).
 * MATERIALS_PRESENT (a bit mask of material ids) leaves out the models a scene does not use:
 * smaller code that the compiler vectorises better. */
#include "mpm/mpm.h"
#include "mpm/materials/elastic.h"
#include "mpm/materials/metal.h"
#include "mpm/materials/newtonian.h"
#include "mpm/materials/plasticine.h"
#include "mpm/materials/sand.h"
#include "mpm/materials/snow.h"
#include "mpm/materials/viscoplastic.h"

__kernel void update_stress(const int n, const real dt, __global const real *F_in,
                            __global const real *C_in, __global const real *plastic_in,
                            __global const int *material, __global const real *param,
                            __global real *F_out, __global real *plastic_out, __global real *tau_out)
{
    const int p = get_global_id(0);
    if (p >= n)
        return;
    real F[9], C[9], F_tr[9], F_new[9], tau[9], step[9];
    load_row(F_in, p, 9, F);
    load_row(C_in, p, 9, C);
    for (int k = 0; k < 9; ++k)
        step[k] = dt * C[k] + ((k % 4 == 0) ? (real)1 : (real)0);
    mat3_mul(step, F, F_tr);
    __global const real *q = param + (long)p * PARAM_COUNT;
    const real plastic = plastic_in[p];
    real plastic_new = plastic;
    switch (material[p]) {
#if MATERIALS_PRESENT & (1 << MAT_ELASTIC)
    case MAT_ELASTIC:
        mat3_copy(F_tr, F_new);
        elastic_stress(F_new, q[0], q[1], tau);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_NEO_HOOKEAN)
    case MAT_NEO_HOOKEAN:
        mat3_copy(F_tr, F_new);
        neo_hookean_stress(F_new, q[0], q[1], tau);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_PLASTICINE)
    case MAT_PLASTICINE:
        plasticine_stress(F_tr, q[0], q[1], q[2], F_new, tau);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_METAL)
    case MAT_METAL:
        metal_stress(F_tr, q[0], q[1], q[2], q[3], plastic, F_new, &plastic_new, tau);
        break;
#endif
#if MATERIALS_PRESENT & ((1 << MAT_FOAM) | (1 << MAT_NON_NEWTONIAN))
    case MAT_FOAM:
    case MAT_NON_NEWTONIAN:
        viscoplastic_stress(F_tr, q[0], q[1], q[2], q[3], dt, F_new, tau);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_SAND)
    case MAT_SAND:
        sand_stress(F_tr, q[0], q[1], q[2], q[3], F_new, tau);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_NEWTONIAN)
    case MAT_NEWTONIAN:
        newtonian_stress(F_tr, C, q[0], q[1], F_new, tau);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_SNOW)
    case MAT_SNOW:
        snow_stress(F_tr, q[0], q[1], q[2], q[3], q[4], plastic, F_new, &plastic_new, tau);
        break;
#endif
    default: /* unreachable: the host builds with every material id its particles use */
        for (int k = 0; k < 9; ++k)
            tau[k] = NAN;
        mat3_copy(F_tr, F_new);
    }
    store_row(F_out, p, 9, F_new);
    plastic_out[p] = plastic_new;
    store_row(tau_out, p, 9, tau);
}
