/* Adjoint of the stress stage (stress.cl): F_tr = (I + dt C) F, F' = Z(F_tr), tau(F').
 *
 * Given taubar (from the P2G adjoint) and F'bar, plastic'bar of state n+1:
 *   F_trbar = dZ/dF_tr^T F'bar + dtau/dF_tr^T taubar (elastic models: Z is the identity)
 *   Fbar = (I + dt C)^T F_trbar,   Cbar += dt F_trbar F^T,   param_bar += dtau/dparam^T taubar,
 *   plasticbar = dplastic'/dplastic^T plastic'bar (+ the yield stress's share for metal)
 * C_bar holds the P2G adjoint's part on entry; param_bar [n, PARAM_COUNT] is accumulated into
 * (one row per particle, summed over substeps: the host reduces rows in a fixed order).
 * U, s, V = svd3(F_tr) come from the forward's SVD kernel (stress.cl: trial_svd_simd or
 * trial_svd, the plan's stress shape); scenes of fixed-corotated elastic particles only take
 * the fused update_stress_elastic_adjoint_simd (CPU devices: SIMD lanes) or
 * update_stress_elastic_adjoint (GPUs: a particle a work-item) instead. */
#include "mpm/mpm.h"
#include "mpm/materials/elastic.h"
#include "mpm/materials/elastic_adjoint.h"
#include "mpm/materials/hencky_adjoint.h"
#include "mpm/materials/newtonian_adjoint.h"

__kernel void update_stress_adjoint(const int n, const real dt, __global const real *F_in, __global const real *C_in,
                                    __global const real *U_in, __global const real *s_in, __global const real *V_in,
                                    __global const real *plastic_in, __global const int *material,
                                    __global const real *param, __global const real *tau_bar,
                                    __global const real *F_bar_out, __global const real *plastic_bar_out,
                                    __global real *F_bar, __global real *C_bar, __global real *plastic_bar,
                                    __global real *param_bar)
{
    const int p = get_global_id(0);
    if (p >= n)
        return;
    real F[9], C[9], step[9], F_tr[9], F_new_bar[9], F_tr_bar[9], tb[9], Cb[9], Fb[9], dCb[9], U[9], s[3], V[9];
    load_stress_inputs(p, dt, F_in, C_in, U_in, s_in, V_in, F, C, step, F_tr, U, s, V);
    load_row(tau_bar, p, 9, tb);
    load_row(F_bar_out, p, 9, F_new_bar);
    __global const real *q = param + (long)p * PARAM_COUNT;
    real q_bar[PARAM_COUNT];
    for (int k = 0; k < PARAM_COUNT; ++k)
        q_bar[k] = 0;
    real C_direct_bar[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0}; /* models whose stress reads C */
    real plastic_b = plastic_bar_out[p];                /* the plastic state passes through unchanged by default */
    const int elastic = material[p] == MAT_ELASTIC || material[p] == MAT_NEO_HOOKEAN;
    for (int k = 0; k < 9; ++k) /* elastic models: F' = F_tr */
        F_tr_bar[k] = elastic ? F_new_bar[k] : (real)0;
    switch (material[p]) {
#if MATERIALS_PRESENT & (1 << MAT_ELASTIC)
    case MAT_ELASTIC:
        fixed_corotated_adjoint(F_tr, U, s, V, q[0], q[1], tb, F_tr_bar, &q_bar[0], &q_bar[1]);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_NEO_HOOKEAN)
    case MAT_NEO_HOOKEAN:
        neo_hookean_stress_adjoint(F_tr, q[0], q[1], tb, F_tr_bar, &q_bar[0], &q_bar[1]);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_PLASTICINE)
    case MAT_PLASTICINE:
        plasticine_stress_adjoint(U, s, V, q[0], q[1], q[2], tb, F_new_bar, F_tr_bar, q_bar);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_METAL)
    case MAT_METAL:
        plastic_b = metal_stress_adjoint(U, s, V, q[0], q[1], q[2], q[3], plastic_in[p], tb, F_new_bar, plastic_b,
                                         F_tr_bar, q_bar);
        break;
#endif
#if MATERIALS_PRESENT & ((1 << MAT_FOAM) | (1 << MAT_NON_NEWTONIAN))
    case MAT_FOAM:
    case MAT_NON_NEWTONIAN:
        viscoplastic_stress_adjoint(U, s, V, q[0], q[1], q[2], q[3], dt, tb, F_new_bar, F_tr_bar, q_bar);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_SAND)
    case MAT_SAND: /* v_c = 0; the unused plastic state passes through */
        sand_stress_adjoint(F_tr, U, s, V, q[0], q[1], q[2], q[3], 0, tb, F_new_bar, 0, F_tr_bar, q_bar);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_SAND_VOLUME_CORRECTED)
    case MAT_SAND_VOLUME_CORRECTED:
        plastic_b = sand_stress_adjoint(F_tr, U, s, V, q[0], q[1], q[2], q[3], plastic_in[p], tb, F_new_bar, plastic_b,
                                        F_tr_bar, q_bar);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_NEWTONIAN)
    case MAT_NEWTONIAN:
        newtonian_stress_adjoint(F_tr, C, q[0], q[1], tb, F_new_bar, F_tr_bar, C_direct_bar, q_bar);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_SNOW)
    case MAT_SNOW:
        plastic_b = snow_stress_adjoint(U, s, V, q[0], q[1], q[2], q[3], q[4], plastic_in[p], tb, F_new_bar, plastic_b,
                                        F_tr_bar, q_bar);
        break;
#endif
    default: /* unreachable: the host refuses materials without an adjoint */
        for (int k = 0; k < 9; ++k)
            F_tr_bar[k] = NAN;
    }
    mat3_mul_at(step, F_tr_bar, Fb);
    mat3_mul_bt(F_tr_bar, F, dCb);
    load_row(C_bar, p, 9, Cb);
    for (int k = 0; k < 9; ++k)
        Cb[k] += dt * dCb[k] + C_direct_bar[k];
    store_row(F_bar, p, 9, Fb);
    store_row(C_bar, p, 9, Cb);
    plastic_bar[p] = plastic_b;
    for (int k = 0; k < PARAM_COUNT; ++k)
        param_bar[(long)p * PARAM_COUNT + k] += q_bar[k];
}

/* update_stress_adjoint for scenes whose particles are all fixed-corotated elastic (the
 * forward's update_stress_elastic), fused with svd3(F_tr), a particle a work-item (the
 * "plain" shape of update_stress_elastic_adjoint_simd). F' = F_tr and the plastic state
 * passes through. */
__kernel void update_stress_elastic_adjoint(const int n, const real dt, __global const real *F_in,
                                            __global const real *C_in, __global const real *param,
                                            __global const real *tau_bar, __global const real *F_bar_out,
                                            __global const real *plastic_bar_out, __global real *F_bar,
                                            __global real *C_bar, __global real *plastic_bar, __global real *param_bar)
{
    const int p = get_global_id(0);
    if (p >= n)
        return;
    real F[9], C[9], step[9], F_tr[9], U[9], s[3], V[9], tb[9], F_tr_bar[9], Fb[9], Cb[9], dCb[9];
    load_row(F_in, p, 9, F);
    load_row(C_in, p, 9, C);
    load_row(tau_bar, p, 9, tb);
    load_row(F_bar_out, p, 9, F_tr_bar);
    load_row(C_bar, p, 9, Cb);
    __global const real *q = param + (long)p * PARAM_COUNT;
    trial_deformation(F, C, dt, step, F_tr);
    svd3(F_tr, U, s, V);
    real mu_bar, lambda_bar;
    fixed_corotated_adjoint(F_tr, U, s, V, q[0], q[1], tb, F_tr_bar, &mu_bar, &lambda_bar);
    mat3_mul_at(step, F_tr_bar, Fb);
    mat3_mul_bt(F_tr_bar, F, dCb);
    for (int k = 0; k < 9; ++k)
        Cb[k] += dt * dCb[k];
    store_row(F_bar, p, 9, Fb);
    store_row(C_bar, p, 9, Cb);
    plastic_bar[p] = plastic_bar_out[p];
    param_bar[(long)p * PARAM_COUNT] += mu_bar;
    param_bar[(long)p * PARAM_COUNT + 1] += lambda_bar;
}

#ifdef CLFLOW_SIMD_LANES
/* update_stress_adjoint for scenes whose particles are all fixed-corotated elastic (the
 * forward's update_stress_elastic_simd), fused with svd3(F_tr): CLFLOW_SIMD_LANES particles
 * per work-item. F' = F_tr and the plastic state passes through. */
__kernel void update_stress_elastic_adjoint_simd(const int n, const real dt, __global const real *F_in,
                                                 __global const real *C_in, __global const real *param,
                                                 __global const real *tau_bar, __global const real *F_bar_out,
                                                 __global const real *plastic_bar_out, __global real *F_bar,
                                                 __global real *C_bar, __global real *plastic_bar,
                                                 __global real *param_bar)
{
    const int p0 = get_global_id(0) * CLFLOW_SIMD_LANES;
    if (p0 >= n)
        return;
    realv F[9], C[9], step[9], F_tr[9], U[9], s[3], V[9], tb[9], F_tr_bar[9], Fb[9], Cb[9], dCb[9];
    load_lanes_v(n, p0, 9, F_in, F);
    load_lanes_v(n, p0, 9, C_in, C);
    load_lanes_v(n, p0, 9, tau_bar, tb);
    load_lanes_v(n, p0, 9, F_bar_out, F_tr_bar);
    load_lanes_v(n, p0, 9, C_bar, Cb);
    const realv mu = load_param_lanes_v(n, p0, param, 0), lambda = load_param_lanes_v(n, p0, param, 1);
    trial_deformation_v(F, C, dt, step, F_tr);
    svd3_v(F_tr, U, s, V);
    realv mu_bar, lambda_bar;
    fixed_corotated_adjoint_v(F_tr, U, s, V, mu, lambda, tb, F_tr_bar, &mu_bar, &lambda_bar);
    mat3_mul_at_v(step, F_tr_bar, Fb);
    mat3_mul_bt_v(F_tr_bar, F, dCb);
    for (int k = 0; k < 9; ++k)
        Cb[k] += dt * dCb[k];
    store_lanes_v(n, p0, 9, Fb, F_bar);
    store_lanes_v(n, p0, 9, Cb, C_bar);
    for (int l = 0; l < CLFLOW_SIMD_LANES && p0 + l < n; ++l) {
        const long p = p0 + l;
        plastic_bar[p] = plastic_bar_out[p];
        param_bar[p * PARAM_COUNT] += LANE(mu_bar, l);
        param_bar[p * PARAM_COUNT + 1] += LANE(lambda_bar, l);
    }
}
#endif
