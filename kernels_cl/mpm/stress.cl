/* Substep stage 1: deformation update, return mapping and Kirchhoff stress.
 *
 *   F_tr = (I + dt C_n) F_n;  (F_{n+1}, plastic_{n+1}) = Z(F_tr; param);  tau = tau(F_{n+1})
 *
 * Two kernels, an SVD of F_tr then update_stress (each particle's model, a particle a
 * work-item), or one fused kernel (SVD included) when every particle is fixed-corotated
 * elastic. The SVD and the fused kernel come in the two shapes of the plan's stress stage
 * (clflow/runtime/plan.py):
 *  - "simd_lanes" (CPU devices): trial_svd_simd, update_stress_elastic_simd hold
 *    CLFLOW_SIMD_LANES particles per work-item in vector registers (CPU compilers do not
 *    vectorise the SVD's Jacobi loop across work-items themselves);
 *  - "plain" (GPUs): trial_svd, update_stress_elastic, a particle a work-item; where P2G
 *    gathers over particles sorted by cell, update_stress_cells (the SVD inline) and
 *    update_stress_elastic_cells also count each particle into its cell (mpm/cells.h), so
 *    the stage and the cell sort's first pass are one launch.
 *
 * Reads state n, writes state n+1's F and plastic state and this substep's tau: nothing
 * is overwritten that the adjoint needs. param[p] holds PARAM_COUNT kernel parameters per
 * particle (their meaning per material: clflow/mpm/constants.py, kernel_params()).
 * MATERIALS_PRESENT (a bit mask of material ids) leaves out the models a scene does not use:
 * smaller code that the compiler vectorises better. */
#include "mpm/cells.h"
#include "mpm/materials/elastic.h"
#include "mpm/materials/metal.h"
#include "mpm/materials/newtonian.h"
#include "mpm/materials/plasticine.h"
#include "mpm/materials/sand.h"
#include "mpm/materials/snow.h"
#include "mpm/materials/viscoplastic.h"

/* Particle p's return mapping and stress (its model's) from C and F_tr = (I + dt C) F, and
 * U s V = svd3(F_tr) where a model present needs it: F_out, plastic_out, tau_out of p. */
inline void model_stress(const int p, const real dt, real *C, real *F_tr, real *U, real *s, real *V,
                         __global const real *plastic_in, __global const int *material, __global const real *param,
                         __global real *F_out, __global real *plastic_out, __global real *tau_out)
{
    real F_new[9], tau[9];
    __global const real *q = param + (long)p * PARAM_COUNT;
    const real plastic = plastic_in[p];
    real plastic_new = plastic;
    switch (material[p]) {
#if MATERIALS_PRESENT & (1 << MAT_ELASTIC)
    case MAT_ELASTIC:
        mat3_copy(F_tr, F_new);
        fixed_corotated_tau(F_tr, U, s, V, q[0], q[1], tau);
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
        plasticine_stress(F_tr, U, s, V, q[0], q[1], q[2], F_new, tau);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_METAL)
    case MAT_METAL:
        metal_stress(F_tr, U, s, V, q[0], q[1], q[2], q[3], plastic, F_new, &plastic_new, tau);
        break;
#endif
#if MATERIALS_PRESENT & ((1 << MAT_FOAM) | (1 << MAT_NON_NEWTONIAN))
    case MAT_FOAM:
    case MAT_NON_NEWTONIAN:
        viscoplastic_stress(F_tr, U, s, V, q[0], q[1], q[2], q[3], dt, F_new, tau);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_SAND)
    case MAT_SAND: { /* no volume correction: v_c = 0, the plastic state is unused */
        real v_c_new;
        sand_stress(F_tr, U, s, V, q[0], q[1], q[2], q[3], 0, F_new, &v_c_new, tau);
        break;
    }
#endif
#if MATERIALS_PRESENT & (1 << MAT_SAND_VOLUME_CORRECTED)
    case MAT_SAND_VOLUME_CORRECTED: /* plastic state: the log volume correction v_c */
        sand_stress(F_tr, U, s, V, q[0], q[1], q[2], q[3], plastic, F_new, &plastic_new, tau);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_NEWTONIAN)
    case MAT_NEWTONIAN:
        newtonian_stress(F_tr, C, q[0], q[1], F_new, tau);
        break;
#endif
#if MATERIALS_PRESENT & (1 << MAT_SNOW)
    case MAT_SNOW:
        snow_stress(F_tr, U, s, V, q[0], q[1], q[2], q[3], q[4], plastic, F_new, &plastic_new, tau);
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

/* Particle p's fixed-corotated elastic update, SVD included: F_out = F_tr, tau_out. */
inline void elastic_stress(const int p, const real dt, __global const real *F_in, __global const real *C_in,
                           __global const real *plastic_in, __global const real *param, __global real *F_out,
                           __global real *plastic_out, __global real *tau_out)
{
    real F[9], C[9], step[9], F_tr[9], U[9], s[3], V[9], tau[9];
    load_row(F_in, p, 9, F);
    load_row(C_in, p, 9, C);
    trial_deformation(F, C, dt, step, F_tr);
    svd3(F_tr, U, s, V);
    __global const real *q = param + (long)p * PARAM_COUNT;
    fixed_corotated_tau(F_tr, U, s, V, q[0], q[1], tau);
    store_row(F_out, p, 9, F_tr);
    store_row(tau_out, p, 9, tau);
    plastic_out[p] = plastic_in[p];
}

/* Each particle's model after the SVD of F_tr (trial_svd[_simd]: U_in, s_in, V_in). */
__kernel void update_stress(const int n, const real dt, __global const real *F_in, __global const real *C_in,
                            __global const real *U_in, __global const real *s_in, __global const real *V_in,
                            __global const real *plastic_in, __global const int *material, __global const real *param,
                            __global real *F_out, __global real *plastic_out, __global real *tau_out)
{
    const int p = get_global_id(0);
    if (p >= n)
        return;
    real F[9], C[9], step[9], F_tr[9], U[9], s[3], V[9];
    load_stress_inputs(p, dt, F_in, C_in, U_in, s_in, V_in, F, C, step, F_tr, U, s, V);
    model_stress(p, dt, C, F_tr, U, s, V, plastic_in, material, param, F_out, plastic_out, tau_out);
}

/* update_stress with the SVD of F_tr inline, and each particle counted into its base cell at x
 * (mpm/cells.h count_cell: the gather's cell sort): the "plain" shape's stage 1 in one launch. */
__kernel void update_stress_cells(MPM_GRID_ARGS, const int n, const real dt, __global const real *F_in,
                                  __global const real *C_in, __global const real *plastic_in,
                                  __global const int *material, __global const real *param, __global real *F_out,
                                  __global real *plastic_out, __global real *tau_out, __global const real *x,
                                  CELL_KEY_ARGS)
{
    const int p = get_global_id(0);
    if (p >= n)
        return;
    real F[9], C[9], step[9], F_tr[9], U[9], s[3], V[9], xp[3];
    load_row(F_in, p, 9, F);
    load_row(C_in, p, 9, C);
    trial_deformation(F, C, dt, step, F_tr);
#if MATERIALS_PRESENT & SVD_MATERIALS
    svd3(F_tr, U, s, V);
#endif
    model_stress(p, dt, C, F_tr, U, s, V, plastic_in, material, param, F_out, plastic_out, tau_out);
    const grid_t g0 = MPM_GRID, g = particle_grid(&g0, p, n);
    load_row(x, p, 3, xp);
    count_cell(&g, p, xp, key, counts, rank);
}

/* U, s, V = svd3(F_tr), a particle a work-item (the "plain" shape of trial_svd_simd). */
__kernel void trial_svd(const int n, const real dt, __global const real *F_in, __global const real *C_in,
                        __global real *U_out, __global real *s_out, __global real *V_out)
{
    const int p = get_global_id(0);
    if (p >= n)
        return;
    real F[9], C[9], step[9], F_tr[9], U[9], s[3], V[9];
    load_row(F_in, p, 9, F);
    load_row(C_in, p, 9, C);
    trial_deformation(F, C, dt, step, F_tr);
    svd3(F_tr, U, s, V);
    store_row(U_out, p, 9, U);
    store_row(s_out, p, 3, s);
    store_row(V_out, p, 9, V);
}

/* update_stress for scenes whose particles are all fixed-corotated elastic, fused with the
 * SVD, a particle a work-item (the "plain" shape of update_stress_elastic_simd). */
__kernel void update_stress_elastic(const int n, const real dt, __global const real *F_in, __global const real *C_in,
                                    __global const real *plastic_in, __global const real *param, __global real *F_out,
                                    __global real *plastic_out, __global real *tau_out)
{
    const int p = get_global_id(0);
    if (p < n)
        elastic_stress(p, dt, F_in, C_in, plastic_in, param, F_out, plastic_out, tau_out);
}

/* update_stress_elastic with each particle counted into its base cell at x (as update_stress_cells). */
__kernel void update_stress_elastic_cells(MPM_GRID_ARGS, const int n, const real dt, __global const real *F_in,
                                          __global const real *C_in, __global const real *plastic_in,
                                          __global const real *param, __global real *F_out, __global real *plastic_out,
                                          __global real *tau_out, __global const real *x, CELL_KEY_ARGS)
{
    const int p = get_global_id(0);
    if (p >= n)
        return;
    elastic_stress(p, dt, F_in, C_in, plastic_in, param, F_out, plastic_out, tau_out);
    const grid_t g0 = MPM_GRID, g = particle_grid(&g0, p, n);
    real xp[3];
    load_row(x, p, 3, xp);
    count_cell(&g, p, xp, key, counts, rank);
}

#ifdef CLFLOW_SIMD_LANES
inline void load_trial_deformation_v(const int n, const int p0, const real dt, __global const real *F_in,
                                     __global const real *C_in, realv *F_tr)
{
    realv F[9], C[9], step[9];
    load_lanes_v(n, p0, 9, F_in, F);
    load_lanes_v(n, p0, 9, C_in, C);
    trial_deformation_v(F, C, dt, step, F_tr);
}

/* U, s, V = svd3(F_tr) for CLFLOW_SIMD_LANES particles per work-item. */
__kernel void trial_svd_simd(const int n, const real dt, __global const real *F_in, __global const real *C_in,
                             __global real *U_out, __global real *s_out, __global real *V_out)
{
    const int p0 = get_global_id(0) * CLFLOW_SIMD_LANES;
    if (p0 >= n)
        return;
    realv F_tr[9], U[9], s[3], V[9];
    load_trial_deformation_v(n, p0, dt, F_in, C_in, F_tr);
    svd3_v(F_tr, U, s, V);
    store_lanes_v(n, p0, 9, U, U_out);
    store_lanes_v(n, p0, 3, s, s_out);
    store_lanes_v(n, p0, 9, V, V_out);
}

/* update_stress for scenes whose particles are all fixed-corotated elastic (the common
 * case), fused with the SVD: CLFLOW_SIMD_LANES particles per work-item. */
__kernel void update_stress_elastic_simd(const int n, const real dt, __global const real *F_in,
                                         __global const real *C_in, __global const real *plastic_in,
                                         __global const real *param, __global real *F_out, __global real *plastic_out,
                                         __global real *tau_out)
{
    const int p0 = get_global_id(0) * CLFLOW_SIMD_LANES;
    if (p0 >= n)
        return;
    realv F_tr[9], U[9], s[3], V[9], tau[9], mu, lambda;
    load_trial_deformation_v(n, p0, dt, F_in, C_in, F_tr);
    mu = load_param_lanes_v(n, p0, param, 0);
    lambda = load_param_lanes_v(n, p0, param, 1);
    svd3_v(F_tr, U, s, V);
    fixed_corotated_tau_v(F_tr, U, s, V, mu, lambda, tau);
    store_lanes_v(n, p0, 9, F_tr, F_out);
    store_lanes_v(n, p0, 9, tau, tau_out);
    for (int p = p0; p < min(n, p0 + CLFLOW_SIMD_LANES); ++p)
        plastic_out[p] = plastic_in[p];
}
#endif
