/* Adjoint of the grid update (grid.cl), for every shape of the G2P adjoint's scatter
 * (clflow/runtime/plan.py): it reads vbar from grid_v_bar, which that scatter wrote (the
 * column sum of its private grid copies, p2g_private.cl sum_grid_copies, on CPU devices, then
 * grid_update_adjoint; the gather per node, g2p_adjoint_gather.cl, on GPUs, which calls
 * update_node_adjoint itself), only on nodes with mass:
 * boundary conditions in reverse table order, then
 * v = mv/m + dt g:  pbar = vbar/m,  mbar = -(mv . vbar)/m^2  (0 on empty nodes).
 * With CLFLOW_FLIP grid_v_bar also holds dvbar of dv = v - mv0/m: vbar += dvbar before the
 * boundary conditions' adjoint (dv reads v after them), p0bar = -dvbar/m and
 * mbar += (mv0 . dvbar)/m^2; grid_bar holds (mbar, pbar[, p0bar]) in GRID_CH reals per node.
 *
 * The velocity before boundary b is recomputed from v0 = mv/m + dt g by replaying
 * conditions 0..b-1 (tables are short). Per condition:
 *   half-space, node inside: sticky -> 0; separate with v.n >= 0 -> unchanged; otherwise
 *     v' = keep vt, vt = v - (v.n) n, with friction f = mu_f max(-v.n, 0) (only moving in):
 *     f = 0: v' = vt, vbar = P v'bar, P = I - n n^T; |vt| <= f: v' = 0, vbar = 0; else
 *     keep = 1 - f/|vt|, vtbar = keep v'bar + (f/|vt|) (vt . v'bar) vt/|vt|^2,
 *     vnbar = mu_f (vt . v'bar)/|vt|,   vbar = P vtbar + vnbar n;
 *   box / cylinder, node inside: v is overridden -> vbar = 0 (their velocities are not
 *     differentiated). */
#include "mpm/grid.cl"

inline void halfspace_adjoint(__global const real *rec, const real *xi, const real *v, real *v_bar)
{
    real n[3], vn;
    if (!halfspace_contact(rec, xi, v, n, &vn))
        return;
    const int mode = (int)rec[BC_MODE];
    if (mode == COLLIDE_SEPARATE && vn >= 0)
        return;
    real vt[3], vt2 = 0, vt_dot = 0;
    for (int a = 0; a < 3; ++a) {
        vt[a] = v[a] - vn * n[a];
        vt2 += vt[a] * vt[a];
        vt_dot += vt[a] * v_bar[a];
    }
    const real vt_norm = sqrt(vt2);
    const real friction = vn < 0 ? -rec[BC_FRICTION] * vn : (real)0;
    if (mode == COLLIDE_STICKY || (friction > 0 && vt_norm <= friction)) {
        for (int a = 0; a < 3; ++a)
            v_bar[a] = 0;
        return;
    }
    /* here |vt| > f > 0, or f = 0 (then |vt| may be 0) */
    const real ratio = friction > 0 ? friction / vt_norm : (real)0;
    const real along = friction > 0 ? ratio * vt_dot / vt2 : (real)0;
    const real vn_bar = friction > 0 ? rec[BC_FRICTION] * vt_dot / vt_norm : (real)0;
    real vt_bar[3], vt_bar_n = 0;
    for (int a = 0; a < 3; ++a) {
        vt_bar[a] = (1 - ratio) * v_bar[a] + along * vt[a];
        vt_bar_n += vt_bar[a] * n[a];
    }
    for (int a = 0; a < 3; ++a)
        v_bar[a] = vt_bar[a] - vt_bar_n * n[a] + vn_bar * n[a];
}

/* 1 if node xi lies inside the box / cylinder record (mirrors apply_box / apply_cylinder). */
inline int overrides(__global const real *rec, const real *xi)
{
    real probe[3] = {NAN, NAN, NAN};
    if ((int)rec[BC_KIND] == BC_BOX)
        apply_box(rec, xi, probe);
    else
        apply_cylinder(rec, xi, probe);
    return !isnan(probe[0]);
}

/* The adjoint of node (i, j, k), flat index `node`: grid_bar[node] from grid_v_bar[node]. */
inline void update_node_adjoint(const long node, const int i, const int j, const int k, const real dx, const real ox,
                                const real oy, const real oz, const real dt, const real t, const real gx, const real gy,
                                const real gz, const real mass_eps, __global const real *grid,
                                __global const real *grid_v_bar, __global const real *bc, const int n_bc,
                                __global real *grid_bar)
{
    const real m = grid[GRID_CH * node];
    real out[GRID_CH];
    for (int c = 0; c < GRID_CH; ++c)
        out[c] = 0;
    if (m > mass_eps) {
        const real g[3] = {gx, gy, gz};
        real v0[3], v_bar[3], mv[3];
        for (int a = 0; a < 3; ++a) {
            mv[a] = grid[GRID_CH * node + 1 + a];
            v0[a] = mv[a] / m + dt * g[a];
            v_bar[a] = grid_v_bar[GV_CH * node + a];
        }
#if CLFLOW_FLIP
        real mv0_dot = 0;
        for (int a = 0; a < 3; ++a) {
            const real dv_bar = grid_v_bar[GV_CH * node + 3 + a];
            v_bar[a] += dv_bar;
            out[4 + a] = -dv_bar / m;
            mv0_dot += grid[GRID_CH * node + 4 + a] * dv_bar;
        }
        out[0] = mv0_dot / (m * m);
#endif
        const real xi[3] = {ox + i * dx, oy + j * dx, oz + k * dx};
        for (int b = n_bc - 1; b >= 0; --b) {
            __global const real *rec = bc + (long)b * BC_STRIDE;
            if (!bc_active(rec, t))
                continue;
            const int kind = (int)rec[BC_KIND];
            if (kind == BC_HALFSPACE) {
                real v[3] = {v0[0], v0[1], v0[2]};
                for (int e = 0; e < b; ++e)
                    if (bc_active(bc + (long)e * BC_STRIDE, t))
                        apply_condition(bc + (long)e * BC_STRIDE, xi, v);
                halfspace_adjoint(rec, xi, v, v_bar);
            } else if (overrides(rec, xi)) {
                for (int a = 0; a < 3; ++a)
                    v_bar[a] = 0;
            }
        }
        real mv_dot = 0;
        for (int a = 0; a < 3; ++a) {
            out[1 + a] = v_bar[a] / m;
            mv_dot += mv[a] * v_bar[a];
        }
        out[0] -= mv_dot / (m * m);
    }
    store_row(grid_bar, node, GRID_CH, out);
}

/* A work-item per node (after the private scatter's column sum). */
__kernel void grid_update_adjoint(GRID_UPDATE_ARGS, __global const real *grid, __global const real *grid_v_bar,
                                  __global const real *bc, const int n_bc, __global real *grid_bar)
{
    const long node = get_global_id(0);
    const grid_t g0 = MPM_GRID;
    if (node >= population_nodes(&g0))
        return;
    int i, j, k;
    node_grid(&g0, node, &i, &j, &k);
    update_node_adjoint(node, i, j, k, dx, ox, oy, oz, dt, t, gx, gy, gz, mass_eps, grid, grid_v_bar, bc, n_bc,
                        grid_bar);
}
