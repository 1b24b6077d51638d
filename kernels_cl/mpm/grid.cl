/* Substep stage 3: grid velocities and boundary conditions.
 *
 *   v_i = mv_i / m_i + dt g   where m_i > mass_eps, else 0
 * then every boundary record active at time t (t_start <= t < t_end) in table order. With the
 * PIC/FLIP blend (CLFLOW_FLIP) also the substep's velocity change dv_i = v_i - mv0_i / m_i
 * (forces, gravity and boundaries; 0 on empty nodes) into grid_dv.
 * Record layout: BC_STRIDE reals, read through the slot names of clflow/mpm/constants.py
 * (BC_SLOTS, passed as defines): [BC_KIND, BC_T_START, BC_T_END, BC_A (3), BC_B (3), BC_C (3) ...]
 *   BC_HALFSPACE: point a, outward normal b (unit), c0 = mode, c1 = friction mu_f. Nodes with
 *       (x_i - a).b < 0 are inside the collider: sticky v = 0; slip v -= (v.n) n; separate
 *       the same only when v.n < 0. While the node moves into the surface (v.n < 0), Coulomb
 *       friction shrinks the tangential part by mu_f |v.n| (to zero at most); a slip node
 *       moving away (v.n >= 0) keeps its tangential part.
 *   BC_BOX: lower corner a, upper corner b, velocity c: nodes inside get v = c.
 *   BC_CYLINDER: centre a, unit axis b, c0 radius, c1 half length, c2 angular velocity omega
 *       (rad/s, right-handed about b): nodes inside get v = omega b x (x_i - a). */
#include "mpm/mpm.h"

/* The half-space record's unit normal n and the node's normal velocity *vn = v.n; 1 when node
 * xi is inside the collider ((xi - point).n < 0), as apply_halfspace and its adjoint decide. */
inline int halfspace_contact(__global const real *rec, const real *xi, const real *v, real *n, real *vn)
{
    real rel = 0, dot = 0;
    for (int a = 0; a < 3; ++a) {
        n[a] = rec[BC_B + a];
        rel += (xi[a] - rec[BC_A + a]) * n[a];
        dot += v[a] * n[a];
    }
    *vn = dot;
    return !(rel >= 0);
}

inline void apply_halfspace(__global const real *rec, const real *xi, real *v)
{
    real n[3], vn;
    if (!halfspace_contact(rec, xi, v, n, &vn))
        return;
    const int mode = (int)rec[BC_MODE];
    if (mode == COLLIDE_STICKY) {
        for (int a = 0; a < 3; ++a)
            v[a] = 0;
        return;
    }
    if (mode == COLLIDE_SEPARATE && vn >= 0)
        return;
    const real friction = vn < 0 ? -rec[BC_FRICTION] * vn : (real)0; /* tangential speed it removes */
    real vt[3], vt2 = 0;
    for (int a = 0; a < 3; ++a) {
        vt[a] = v[a] - vn * n[a];
        vt2 += vt[a] * vt[a];
    }
    const real vt_norm = sqrt(vt2);
    const real keep = vt_norm > friction ? 1 - friction / vt_norm : (real)(friction == 0);
    for (int a = 0; a < 3; ++a)
        v[a] = keep * vt[a];
}

inline void apply_box(__global const real *rec, const real *xi, real *v)
{
    for (int a = 0; a < 3; ++a)
        if (xi[a] < rec[BC_A + a] || xi[a] > rec[BC_B + a])
            return;
    for (int a = 0; a < 3; ++a)
        v[a] = rec[BC_C + a];
}

inline void apply_cylinder(__global const real *rec, const real *xi, real *v)
{
    real r[3], along = 0;
    for (int a = 0; a < 3; ++a) {
        r[a] = xi[a] - rec[BC_A + a];
        along += r[a] * rec[BC_B + a];
    }
    real radial2 = 0;
    for (int a = 0; a < 3; ++a) {
        const real ra = r[a] - along * rec[BC_B + a];
        radial2 += ra * ra;
    }
    if (fabs(along) > rec[BC_HALF_LENGTH] || radial2 > rec[BC_RADIUS] * rec[BC_RADIUS])
        return;
    const real omega = rec[BC_OMEGA];
    v[0] = omega * (rec[BC_B + 1] * r[2] - rec[BC_B + 2] * r[1]);
    v[1] = omega * (rec[BC_B + 2] * r[0] - rec[BC_B] * r[2]);
    v[2] = omega * (rec[BC_B] * r[1] - rec[BC_B + 1] * r[0]);
}

/* 1 while the record is in force: start <= t < end (s). */
inline int bc_active(__global const real *rec, const real t)
{
    return t >= rec[BC_T_START] && t < rec[BC_T_END];
}

/* The record's condition on node xi's velocity v (unchanged where it does not apply). */
inline void apply_condition(__global const real *rec, const real *xi, real *v)
{
    const int kind = (int)rec[BC_KIND];
    if (kind == BC_HALFSPACE)
        apply_halfspace(rec, xi, v);
    else if (kind == BC_BOX)
        apply_box(rec, xi, v);
    else if (kind == BC_CYLINDER)
        apply_cylinder(rec, xi, v);
}

/* grid_update of node (i, j, k), flat index `node`. */
inline void update_node(const grid_t *g, const long node, const int i, const int j, const int k, const real dt,
                        const real t, const real *gravity, const real mass_eps, __global const real *grid,
                        __global real *grid_v, __global real *grid_dv, __global const real *bc, const int n_bc)
{
    const real m = grid[GRID_CH * node];
    real v[3] = {0, 0, 0};
    if (m > mass_eps) {
        for (int a = 0; a < 3; ++a)
            v[a] = grid[GRID_CH * node + 1 + a] / m + dt * gravity[a];
        const real xi[3] = {g->origin[0] + i * g->dx, g->origin[1] + j * g->dx, g->origin[2] + k * g->dx};
        for (int b = 0; b < n_bc; ++b) {
            __global const real *rec = bc + (long)b * BC_STRIDE;
            if (bc_active(rec, t))
                apply_condition(rec, xi, v);
        }
    }
    store_row(grid_v, node, 3, v);
#if CLFLOW_FLIP
    real dv[3] = {0, 0, 0};
    if (m > mass_eps)
        for (int a = 0; a < 3; ++a)
            dv[a] = v[a] - grid[GRID_CH * node + 4 + a] / m;
    store_row(grid_dv, node, 3, dv);
#endif
}

#define GRID_UPDATE_ARGS                                                                                               \
    MPM_GRID_ARGS, const real dt, const real t, const real gx, const real gy, const real gz, const real mass_eps

/* A work-item per node (the gather and atomic P2G paths). */
__kernel void grid_update(GRID_UPDATE_ARGS, __global const real *grid, __global real *grid_v, __global real *grid_dv,
                          __global const real *bc, const int n_bc)
{
    const long node = get_global_id(0);
    const grid_t g0 = MPM_GRID;
    if (node >= population_nodes(&g0))
        return;
    const real gravity[3] = {gx, gy, gz};
    int i, j, k;
    const grid_t g = node_grid(&g0, node, &i, &j, &k);
    update_node(&g, node, i, j, k, dt, t, gravity, mass_eps, grid, grid_v, grid_dv, bc, n_bc);
}

/* The private P2G path's grid stage, a work-item per row of nodes (i, j) of the stacked grid
 * (every member's, mpm.h): the row of the column sum of p2g_private's grid copies into `grid`
 * (sum_copies_row), then grid_update of the row's nodes that a copy's box holds; the others have no mass (with mass_eps >= 0:
 * velocity and change 0, as grid_update gives them). The same values as a sum kernel and
 * grid_update, in one launch, with the grid update only where the particles are. */
__kernel void sum_copies_update_grid(GRID_UPDATE_ARGS, const int copies, __global const int *boxes,
                                     __global const real *grid_copies, __global real *grid, __global real *grid_v,
                                     __global real *grid_dv, __global const real *bc, const int n_bc)
{
    const int row = get_global_id(0);
    if (row >= members * nx * ny)
        return;
    int lo, hi;
    sum_copies_row(members * nx, ny, nz, GRID_CH, copies, boxes, grid_copies, grid, row, &lo, &hi);
    if (!(mass_eps >= 0)) { /* an empty node is not simply at rest: update them all */
        lo = 0;
        hi = nz;
    }
    const grid_t g = MPM_GRID; /* update_node reads only its dx and origin */
    const real gravity[3] = {gx, gy, gz};
    for (int k = 0; k < nz; ++k) {
        const long node = (long)row * nz + k;
        if (k >= lo && k < hi) {
            update_node(&g, node, row / ny % nx, row % ny, k, dt, t, gravity, mass_eps, grid, grid_v, grid_dv, bc,
                        n_bc);
            continue;
        }
        for (int a = 0; a < 3; ++a) {
            grid_v[3 * node + a] = 0;
#if CLFLOW_FLIP
            grid_dv[3 * node + a] = 0;
#endif
        }
    }
}
