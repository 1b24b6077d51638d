/* Shared definitions of the MLS-MPM kernels: grid indexing, quadratic B-spline weights.
 *
 * Grid: nx*ny*nz nodes, node (i, j, k) at origin + dx (i, j, k), flat index (i*ny + j)*nz + k.
 * A particle at x has xi = (x - origin)/dx, base = floor(xi - 0.5), f = xi - base, and
 * touches the 3x3x3 nodes base + (0..2) with weights w0 = 0.5(1.5-f)^2, w1 = 0.75-(f-1)^2,
 * w2 = 0.5(f-0.5)^2 per axis; D^-1 = 4/dx^2. Positions are kept inside
 * [CLAMP_MARGIN, n-1-CLAMP_MARGIN] cells by G2P, so base is always a valid node.
 *
 * A population of `members` simulations in lockstep (clflow.mpm.population): member m owns the
 * particles [m n / members, (m + 1) n / members) of the n and its own grid, the nodes [m nodes,
 * (m + 1) nodes) of every grid array, all members' grids alike (the same size, origin and
 * boundary table). Laid out member after member, the grids are one grid of members nx nodes
 * along x ("stacked"), which is how the private copies' boxes and rows count them. A
 * particle's grid_t is its member's (particle_grid: offset = m nodes); a node's, with its
 * node coordinates inside its member's grid, node_grid. One member: offset 0 throughout. */
#ifndef CLFLOW_MPM_H
#define CLFLOW_MPM_H

#include "common/mat3.h"

#if !defined(PARAM_COUNT) || !defined(CLAMP_MARGIN) || !defined(CLFLOW_FLIP)
#error "build the MPM kernels through clflow.mpm (it passes PARAM_COUNT, CLAMP_MARGIN, CLFLOW_FLIP, ...)"
#endif

/* Reals per node of the P2G grid: m, mv (3) and, with the PIC/FLIP blend (CLFLOW_FLIP),
 * mv0 (3), the momentum before this substep's forces (clflow.mpm.constants.grid_channels). */
#define GRID_CH (CLFLOW_FLIP ? 7 : 4)
/* Reals per node of the grid velocities (v[, dv]) and of their adjoint's grid copies
 * (clflow.mpm.constants.velocity_channels). */
#define GV_CH (CLFLOW_FLIP ? 6 : 3)

/* 3-vectors in registers for the transfer loops (private arrays indexed in loops may stay
 * in memory; vector accumulators do not). */
#if REAL_IS_DOUBLE
typedef double3 vec3r;
#else
typedef float3 vec3r;
#endif

/* One member's grid: nx*ny*nz nodes, its node (0, 0, 0) at flat index `offset` of the
 * population's grid arrays (`members` grids of the same shape). */
typedef struct {
    int nx, ny, nz, members;
    long offset;
    real dx;
    real origin[3];
} grid_t;

/* The grid's arguments of every MPM kernel (clflow.mpm.substep.Grid.kernel_args), and the
 * grid_t they make: member 0's. */
#define MPM_GRID_ARGS                                                                                                  \
    const int nx, const int ny, const int nz, const int members, const real dx, const real ox, const real oy,          \
        const real oz
#define MPM_GRID make_grid(nx, ny, nz, members, dx, ox, oy, oz)

inline grid_t make_grid(const int nx, const int ny, const int nz, const int members, const real dx, const real ox,
                        const real oy, const real oz)
{
    grid_t g;
    g.nx = nx;
    g.ny = ny;
    g.nz = nz;
    g.members = members;
    g.offset = 0;
    g.dx = dx;
    g.origin[0] = ox;
    g.origin[1] = oy;
    g.origin[2] = oz;
    return g;
}

inline int grid_extent(const grid_t *g, const int axis)
{
    return axis == 0 ? g->nx : (axis == 1 ? g->ny : g->nz);
}

/* Nodes of one member's grid, and of all members' together. */
inline long grid_nodes(const grid_t *g)
{
    return (long)g->nx * g->ny * g->nz;
}

inline long population_nodes(const grid_t *g)
{
    return g->members * grid_nodes(g);
}

/* The flat offset of node (i, j, k) from node (0, 0, 0) of a grid. */
inline long node_offset(const grid_t *g, const int i, const int j, const int k)
{
    return ((long)i * g->ny + j) * g->nz + k;
}

/* The flat index of node (i, j, k) of grid g (its member's) in the grid arrays. */
inline long grid_index(const grid_t *g, const int i, const int j, const int k)
{
    return g->offset + node_offset(g, i, j, k);
}

/* The member of particle p of the population's n particles. */
inline int particle_member(const grid_t *g, const long p, const int n)
{
    return g->members == 1 ? 0 : (int)p / (n / g->members); /* a single run divides nothing */
}

/* The grid of particle p's member (n particles in all). */
inline grid_t particle_grid(const grid_t *g, const long p, const int n)
{
    grid_t m = *g;
    m.offset = particle_member(g, p, n) * grid_nodes(g);
    return m;
}

/* The grid of the member that owns flat node `node`, and the node's coordinates (*i, *j, *k) in it. */
inline grid_t node_grid(const grid_t *g, const long node, int *i, int *j, int *k)
{
    grid_t m = *g;
    const int own = g->members == 1 ? (int)node : (int)(node % grid_nodes(g)); /* < 2^31: one member's */
    m.offset = node - own;
    *k = own % g->nz;
    *j = (own / g->nz) % g->ny;
    *i = own / (g->nz * g->ny);
    return m;
}

/* The base node of a particle's 3x3x3 stencil along ``axis`` at coordinate xa (m): floor(xi -
 * 1/2), clamped so that even a position G2P has not clamped (the initial state) stays in memory. */
inline int stencil_base(const grid_t *g, const real xa, const int axis)
{
    const real xi = (xa - g->origin[axis]) / g->dx;
    return clamp((int)floor(xi - (real)0.5), 0, grid_extent(g, axis) - 3);
}

/* Private grid copies (p2g_private, g2p_adjoint_private): work-item k scatters the contiguous
 * particle chunk [begin, end) into copy k of `copies` consecutive [nodes, channels] arrays.
 * It zeroes and records only the box of nodes its particles' stencils touch, box[0..2] (lower)
 * to box[3..5] (upper, exclusive), in nodes; a column sum reads copy k only inside box k, so
 * nodes no particle of the chunk reaches cost neither a write nor a read (a small object in a
 * large domain: most of them). The box's x runs in the stacked grid of the population (a chunk
 * may hold particles of several members). An empty chunk has an empty box; one with a position
 * that is not finite (whose stencil make_stencil clamps somewhere) its members' whole grids. */
inline void chunk_box(const grid_t *g, __global const real *x, const int n, const int begin, const int end, int *box)
{
    if (begin >= end) {
        for (int a = 0; a < 6; ++a)
            box[a] = 0;
        return;
    }
    /* along x the box runs in the stacked grid from the chunk's first member's lowest node to its
     * last member's highest (every member between wholly): lo[0] of the first, hi[0] of the last */
    const int first = particle_member(g, begin, n), last = particle_member(g, end - 1, n);
    real lo[3], hi[3], finite = 0; /* finite: 0 while every coordinate is (inf * 0, NaN * 0: NaN) */
    for (int a = 0; a < 3; ++a)
        lo[a] = hi[a] = x[3 * (long)begin + a];
    hi[0] = x[3 * (long)(end - 1)];
    for (long p = begin; p < end; ++p) {
        const int m = particle_member(g, p, n);
        for (int a = 0; a < 3; ++a) {
            const real xa = x[3 * p + a];
            if (a > 0 || m == first)
                lo[a] = fmin(lo[a], xa);
            if (a > 0 || m == last)
                hi[a] = fmax(hi[a], xa);
            finite += xa * 0;
        }
    }
    for (int a = 0; a < 3; ++a) { /* stencil_base is monotonic: the extremes' stencils bound the box */
        box[a] = finite == 0 ? stencil_base(g, lo[a], a) : 0;
        box[3 + a] = finite == 0 ? stencil_base(g, hi[a], a) + 3 : grid_extent(g, a);
    }
    box[0] += first * g->nx;
    box[3] += last * g->nx;
}

/* Work-item k's grid copy: its particle chunk [*begin, *end) = [k*chunk, (k+1)*chunk) cut at n,
 * and copy k of the consecutive [nodes, channels] arrays at `copies`, zeroed inside the chunk's
 * box (chunk_box), the box saved as boxes[6k .. 6k+5] for the column sum. */
inline __global real *chunk_copy(const grid_t *g, __global const real *x, const int n, const int k, const int chunk,
                                 const int channels, __global real *copies, __global int *boxes, int *begin, int *end)
{
    *begin = min(n, k * chunk);
    *end = min(n, (k + 1) * chunk);
    int box[6];
    chunk_box(g, x, n, *begin, *end, box);
    __global real *copy = copies + (long)k * channels * population_nodes(g);
    for (int i = box[0]; i < box[3]; ++i)
        for (int j = box[1]; j < box[4]; ++j) {
            const long row = channels * node_offset(g, i, j, 0); /* i: in the stacked grid */
            for (int e = channels * box[2]; e < channels * box[5]; ++e)
                copy[row + e] = 0;
        }
    for (int a = 0; a < 6; ++a)
        boxes[6 * k + a] = box[a];
    return copy;
}

/* Row (i, j) = (row / ny, row % ny) of the column sum of `copies` private grid copies
 * ([nodes, channels] each, consecutive in grid_copies): the row's channels * nz contiguous
 * reals of grid = the sum over copies k = 0, 1, ..., in that order, of copy k's part of the
 * row that lies in box k (chunk_copy; zero elsewhere). Returns the nodes [*lo, *hi) of the row
 * that some box holds (lo = nz, hi = 0 when none): outside them the row is zero. */
inline void sum_copies_row(const int nx, const int ny, const int nz, const int channels, const int copies,
                           __global const int *boxes, __global const real *grid_copies, __global real *grid,
                           const int row, int *lo, int *hi)
{
    *lo = nz;
    *hi = 0;
    const int i = row / ny, j = row % ny;
    const long width = (long)channels * nz, size = width * nx * ny;
    __global real *out = grid + row * width;
    for (long e = 0; e < width; ++e)
        out[e] = 0;
    for (int k = 0; k < copies; ++k) {
        __global const int *box = boxes + 6 * k;
        if (i < box[0] || i >= box[3] || j < box[1] || j >= box[4])
            continue;
        __global const real *in = grid_copies + k * size + row * width;
        for (long e = (long)channels * box[2]; e < (long)channels * box[5]; ++e)
            out[e] += in[e];
        *lo = min(*lo, box[2]);
        *hi = max(*hi, box[5]);
    }
}

/* Quadratic B-spline weights w[0..2] of one axis at f = xi - base (real or realv). */
#define STENCIL_WEIGHTS(f, w)                                                                                          \
    do {                                                                                                               \
        (w)[0] = (real)0.5 * ((real)1.5 - (f)) * ((real)1.5 - (f));                                                    \
        (w)[1] = (real)0.75 - ((f)-1) * ((f)-1);                                                                       \
        (w)[2] = (real)0.5 * ((f) - (real)0.5) * ((f) - (real)0.5);                                                    \
    } while (0)

/* The 3x3x3 stencil of a particle: base node, and weights w[axis][0..2] of each axis. */
typedef struct {
    int base[3];
    real fx[3]; /* xi - base, in [0.5, 1.5) */
    real w[3][3];
} stencil_t;

inline stencil_t make_stencil(const grid_t *g, const real *x)
{
    stencil_t st;
    for (int a = 0; a < 3; ++a) {
        const int base = stencil_base(g, x[a], a);
        const real f = (x[a] - g->origin[a]) / g->dx - base;
        st.base[a] = base;
        st.fx[a] = f;
        STENCIL_WEIGHTS(f, st.w[a]);
    }
    return st;
}

/* Row i of a [rows, width] array (x, v: width 3; C, F, tau: width 9, row-major 3x3). */
inline void load_row(__global const real *a, const long i, const int width, real *row)
{
    for (int c = 0; c < width; ++c)
        row[c] = a[width * i + c];
}

inline void store_row(__global real *a, const long i, const int width, const real *row)
{
    for (int c = 0; c < width; ++c)
        a[width * i + c] = row[c];
}

/* F_tr = (I + dt C) F, the trial deformation of the stress stage; step = I + dt C is
 * returned too (the adjoint needs it). For T = real, and realv with CLFLOW_SIMD_LANES. */
#define CLFLOW_DEFINE_TRIAL_DEFORMATION(SFX, T)                                                                        \
    inline void trial_deformation##SFX(const T *F, const T *C, const real dt, T *step, T *F_tr)                        \
    {                                                                                                                  \
        for (int k = 0; k < 9; ++k)                                                                                    \
            step[k] = dt * C[k] + ((k % 4 == 0) ? (T)1 : (T)0);                                                        \
        mat3_mul##SFX(step, F, F_tr);                                                                                  \
    }
CLFLOW_DEFINE_TRIAL_DEFORMATION(, real)

/* The stress stage's inputs of particle p, forward and adjoint alike: F and C (rows p of F_in,
 * C_in), step and F_tr (trial_deformation) and, when the scene has SVD materials, the SVD
 * U, s, V of F_tr that trial_svd wrote (rows p of U_in, s_in, V_in; left unset otherwise). */
inline void load_stress_inputs(const int p, const real dt, __global const real *F_in, __global const real *C_in,
                               __global const real *U_in, __global const real *s_in, __global const real *V_in, real *F,
                               real *C, real *step, real *F_tr, real *U, real *s, real *V)
{
    load_row(F_in, p, 9, F);
    load_row(C_in, p, 9, C);
    trial_deformation(F, C, dt, step, F_tr);
#if MATERIALS_PRESENT & SVD_MATERIALS
    load_row(U_in, p, 9, U);
    load_row(s_in, p, 3, s);
    load_row(V_in, p, 9, V);
#endif
}

#ifdef CLFLOW_SIMD_LANES
CLFLOW_DEFINE_TRIAL_DEFORMATION(_v, realv)

/* Column `column` of a [n, PARAM_COUNT] parameter array in lanes, as load_lanes_v. */
inline realv load_param_lanes_v(const int n, const int p0, __global const real *param, const int column)
{
    realv q;
    for (int l = 0; l < CLFLOW_SIMD_LANES; ++l)
        ((real *)&q)[l] = param[(long)min(p0 + l, n - 1) * PARAM_COUNT + column];
    return q;
}
/* make_stencil for the lanes of a SIMD work-item, particles p0 + lane of n (x[axis] in lanes):
 * each lane's base node as a flat index in its member's grid, fx and the weights in lanes. */
typedef struct {
    long corner[CLFLOW_SIMD_LANES];
    realv fx[3];
    realv w[3][3];
} stencil_v_t;

inline stencil_v_t make_stencil_v(const grid_t *g, const realv *x, const int p0, const int n)
{
    stencil_v_t st;
    for (int l = 0; l < CLFLOW_SIMD_LANES; ++l) {
        int base[3];
        for (int a = 0; a < 3; ++a) {
            base[a] = stencil_base(g, LANE(x[a], l), a);
            ((real *)&st.fx[a])[l] = (LANE(x[a], l) - g->origin[a]) / g->dx - base[a];
        }
        const grid_t gl = particle_grid(g, min(p0 + l, n - 1), n);
        st.corner[l] = grid_index(&gl, base[0], base[1], base[2]);
    }
    for (int a = 0; a < 3; ++a)
        STENCIL_WEIGHTS(st.fx[a], st.w[a]);
    return st;
}
#endif

/* The particles' arguments of the P2G kernels (p2g_private.cl, p2g_atomic.cl,
 * p2g_gather.cl; clflow.mpm.substep.p2g_particle_args). */
#define P2G_PARTICLE_ARGS                                                                                              \
    const int n, const real dt, __global const real *x, __global const real *v, __global const real *C,                \
        __global const real *tau, __global const real *mass, __global const real *volume, __global const int *group,   \
        __global const real *accel

#endif /* CLFLOW_MPM_H */
