/* Per-tile compositing of sorted splats for CPU devices (plan raster "tile_rows",
 * clflow/runtime/plan.py): forward (front to back) and adjoint (back to front).
 * rasterize_workgroup.cl is the GPU shape of the same kernels; splat/composite.h holds the maths
 * both share.
 *
 * Inputs per tile t: ranges[t] = [start, end) into the (tile, depth) sorted list, whose entry
 * i names slot sorted_slots[i], and entries [M, ENTRY_STRIDE]: the records of the sorted
 * entries (entries.cl). Pixel p (centre at i + 0.5) composites, front to back,
 *   out_p = sum_i f_i alpha_i T_i + T_final background,  T_{i+1} = T_i (1 - alpha_i)
 * skipping alpha < ALPHA_MIN and stopping before T would fall below T_MIN. */
#include "splat/composite.h"

/* Layout for CPU devices: a work-item owns one 16 x 16 tile and holds each of its rows in a
 * 16-wide vector (rowv), so every step runs on 16 pixels at once in SIMD registers (PoCL
 * did not vectorise per-pixel loops across work-items). No barriers, no local memory. */
#if TILE_SIZE != 16
#error "rasterize_tile_rows.cl holds a tile row in a 16-wide vector: TILE_SIZE must be 16"
#endif
#if REAL_IS_DOUBLE
typedef double16 rowv;
typedef long16 maskv;
typedef double8 real8;
typedef double4 real4;
typedef double2 real2;
#define INT_TO_MASK(m) convert_long16(m)
#define MASK_TO_INT(m) convert_int16(m)
#else
typedef float16 rowv;
typedef int16 maskv;
typedef float8 real8;
typedef float4 real4;
typedef float2 real2;
#define INT_TO_MASK(m) (m)
#define MASK_TO_INT(m) (m)
#endif

#define LANES ((rowv)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15))

/* Sum of the 16 lanes in a fixed order (pairwise halving): deterministic. */
inline real hsum(const rowv v)
{
    const real8 a = v.lo + v.hi;
    const real4 b = a.lo + a.hi;
    const real2 c = b.lo + b.hi;
    return c.x + c.y;
}

/* Lanes [0, count) of row values p[0], p[stride], ...; 0 beyond. */
inline rowv load_row(__global const real *p, const int stride, const int count)
{
    real tmp[16];
    for (int l = 0; l < 16; ++l)
        tmp[l] = l < count ? p[l * stride] : 0;
    return vload16(0, tmp);
}

/* The falloff and alpha of Gaussian (mx, my, A, B, C, o) over a row at x = cx (lanes),
 * y = cy (SPLAT_ALPHA). */
#define ROW_ALPHA(dx, dy, sigma, falloff, alpha)                                                                       \
    const rowv dx = mx - cx;                                                                                           \
    const real dy = my - cy;                                                                                           \
    SPLAT_ALPHA(rowv, dx, dy, sigma, falloff, alpha)

/* Which rows of a tile a Gaussian can reach, and the exact per-row test.
 *
 * A pixel is skipped when sigma > cut = log(o / ALPHA_MIN) (its alpha is below ALPHA_MIN).
 * Over all x, sigma at row offset dy is at least 0.5 dy^2 det / A (det = AC - B^2), so only
 * rows with |dy| <= sqrt(2 cut A / det) can be reached: entry_rows() returns that range.
 * Within it, sigma is convex in dx, so its minimum over the row's 16 lanes is at
 * dx* = -B dy / A clamped to the lanes' range: row_culled() skips rows whose minimum exceeds
 * cut. Both tests keep a margin ROW_CULL_MARGIN (in sigma) far beyond rounding, so a skip
 * never changes a result. */
typedef struct {
    real mx, my, A, B, C, o, cut, slope; /* slope = -B / A */
    int r0, r1;                          /* rows [r0, r1) of the tile it can reach */
} entry_t;

/* Entry i of the sorted list, with the rows [r0, r1) of the tile at py0 it can reach. */
inline entry_t load_entry(const int i, __global const real *entries, const int py0, const int n_rows)
{
    __global const real *rec = entries + (size_t)i * ENTRY_STRIDE;
    entry_t e;
    e.mx = rec[0];
    e.my = rec[1];
    e.A = rec[2];
    e.B = rec[3];
    e.C = rec[4];
    e.o = rec[5];
    e.cut = rec[6];
    e.slope = rec[7];
    const real reach = rec[8];
    /* row r has centre py0 + r + 0.5; keep |my - centre| <= reach */
    const real lo = e.my - reach - py0 - (real)0.5, hi = e.my + reach - py0 - (real)0.5;
    e.r0 = (int)ceil(clamp(lo, (real)0, (real)n_rows));
    e.r1 = (int)floor(clamp(hi, (real)-1, (real)(n_rows - 1))) + 1;
    return e;
}

inline bool row_culled(const entry_t *e, const real dy, const int px0)
{
    const real dx = clamp(e->slope * dy, e->mx - px0 - (real)(TILE_SIZE - 0.5), e->mx - px0 - (real)0.5);
    const real sigma_min = (real)0.5 * (e->A * dx * dx + e->C * dy * dy) + e->B * dx * dy;
    return sigma_min > e->cut;
}

/* Forward: one work-item per tile, its 16 rows held as 16-wide vectors. Entries front to
 * back; each row a Gaussian can reach composites it until the row is done (T would fall
 * below T_MIN); the tile stops when all rows are done. Writes out [H,W,CHANNELS],
 * T_final [H,W] and n_contrib [H,W] (entries walked up to the pixel's last contributor). */
__kernel void rasterize_forward(__global const int *ranges, __global const real *entries,
                                __global const real *background, __global real *out, __global real *T_final,
                                __global int *n_contrib, const int width, const int height, const int tiles_x,
                                const int n_tiles)
{
    const int tile = get_global_id(0);
    if (tile >= n_tiles)
        return;
    const int px0 = (tile % tiles_x) * TILE_SIZE, py0 = (tile / tiles_x) * TILE_SIZE;
    const int n_px = min(TILE_SIZE, width - px0);
    const int n_rows = min(TILE_SIZE, height - py0);
    const rowv cx = LANES + (real)px0 + (real)0.5;
    const int start = ranges[2 * tile], end = ranges[2 * tile + 1];

    rowv acc[TILE_SIZE][CHANNELS], T[TILE_SIZE];
    int16 last[TILE_SIZE];
    maskv done[TILE_SIZE];
    for (int r = 0; r < n_rows; ++r) {
        for (int k = 0; k < CHANNELS; ++k)
            acc[r][k] = 0;
        T[r] = 1;
        last[r] = 0;
        done[r] = isgreaterequal(LANES, (rowv)n_px); /* lanes beyond the image */
    }
    int rows_left = n_rows;
    for (int i = start; i < end && rows_left > 0; ++i) {
        const entry_t e = load_entry(i, entries, py0, n_rows);
        const real mx = e.mx, my = e.my, A = e.A, B = e.B, C = e.C, o = e.o;
        __global const real *f = entries + (size_t)i * ENTRY_STRIDE + ENTRY_FIELDS;
        for (int r = e.r0; r < e.r1; ++r) {
            const real cy = py0 + r + (real)0.5;
            if (all(done[r]) || row_culled(&e, my - cy, px0))
                continue;
            ROW_ALPHA(dx, dy, sigma, falloff, alpha);
            const maskv hit = !done[r] & isgreaterequal(sigma, (rowv)0) & isgreaterequal(alpha, (rowv)(real)ALPHA_MIN);
            /* no early exit when no lane is hit: the masked update is cheaper than the
             * mispredicted branch (and adds exact zeros) */
            const rowv T_next = T[r] * (1 - alpha);
            const maskv stop = hit & isless(T_next, (rowv)(real)T_MIN);
            const maskv take = hit & !stop;
            const rowv w = select((rowv)0, alpha * T[r], take);
#pragma unroll
            for (int k = 0; k < CHANNELS; ++k)
                acc[r][k] += f[k] * w;
            T[r] = select(T[r], T_next, take);
            last[r] = select(last[r], (int16)(i - start + 1), MASK_TO_INT(take));
            done[r] |= stop;
            rows_left -= all(done[r]) ? 1 : 0;
        }
    }
    real row[16 * CHANNELS]; /* a row's pixels, channels interleaved as in out */
    for (int r = 0; r < n_rows; ++r) {
        const size_t p0 = (size_t)(py0 + r) * width + px0;
        for (int k = 0; k < CHANNELS; ++k) {
            const rowv value = acc[r][k] + T[r] * background[k];
            for (int l = 0; l < 16; ++l)
                row[l * CHANNELS + k] = LANE(value, l);
        }
        if (n_px == 16) { /* whole rows: vector stores */
            vstore16(T[r], 0, T_final + p0);
            vstore16(last[r], 0, n_contrib + p0);
            for (int q = 0; q < CHANNELS; ++q)
                vstore16(vload16(q, row), q, out + p0 * CHANNELS);
        } else {
            for (int l = 0; l < n_px; ++l) {
                T_final[p0 + l] = LANE(T[r], l);
                n_contrib[p0 + l] = ((const int *)&last[r])[l];
            }
            for (int e = 0; e < n_px * CHANNELS; ++e)
                out[p0 * CHANNELS + e] = row[e];
        }
    }
}

/* Adjoint, one work-item per tile. The tile's 16 rows keep their state (T, S, dL/dout) in
 * 16-wide vectors; the entries are walked once, back to front from the tile's last
 * contributor, and at each entry every row that it reaches steps back
 * (T_i = T_{i+1} / (1 - alpha_i)). The entry's gradient is summed over the rows lane-wise,
 * then over the lanes in a fixed order, and written to row sorted_slots[i] of
 * slot_grads [M, GRAD_FIELDS] = (dmean2d x, y, dconic A, B, C, dopacity, dfeatures...).
 * Each slot row belongs to one (tile, Gaussian) pair, hence to this work-item only: no
 * atomics, deterministic sums. In: v_out [H,W,CHANNELS] = dL/dout, v_T [H,W] = dL/dT_final. */
__kernel void rasterize_backward(__global const int *ranges, __global const int *sorted_slots,
                                 __global const real *entries, __global const real *background,
                                 __global const real *T_final, __global const int *n_contrib,
                                 __global const real *v_out, __global const real *v_T, __global real *slot_grads,
                                 const int width, const int height, const int tiles_x, const int n_tiles)
{
    const int tile = get_global_id(0);
    if (tile >= n_tiles)
        return;
    const int start = ranges[2 * tile], end = ranges[2 * tile + 1];
    const int px0 = (tile % tiles_x) * TILE_SIZE, py0 = (tile / tiles_x) * TILE_SIZE;
    const int n_px = min(TILE_SIZE, width - px0);
    const int n_rows = min(TILE_SIZE, height - py0);
    const rowv cx = LANES + (real)px0 + (real)0.5;

    /* per row r: T (walked back), T_final, dL/dT_final + bg . g, g = dL/dout, S = sum of
     * f alpha T over the contributors behind, and the entries walked up to the last one */
    rowv T[TILE_SIZE], T_end[TILE_SIZE], v_T_end[TILE_SIZE];
    rowv g[TILE_SIZE][CHANNELS], S[TILE_SIZE][CHANNELS];
    int16 n_row[TILE_SIZE];
    int n_max = 0;
    for (int r = 0; r < n_rows; ++r) {
        const size_t p0 = (size_t)(py0 + r) * width + px0;
        T_end[r] = T[r] = load_row(T_final + p0, 1, n_px);
        rowv bg_dot_g = 0;
        for (int k = 0; k < CHANNELS; ++k) {
            g[r][k] = load_row(v_out + p0 * CHANNELS + k, CHANNELS, n_px);
            S[r][k] = 0;
            bg_dot_g += background[k] * g[r][k];
        }
        v_T_end[r] = load_row(v_T + p0, 1, n_px) + bg_dot_g; /* background included */
        int tmp_n[16];
        for (int l = 0; l < 16; ++l) {
            tmp_n[l] = l < n_px ? n_contrib[p0 + l] : 0;
            n_max = max(n_max, tmp_n[l]);
        }
        n_row[r] = vload16(0, tmp_n);
    }
    /* entries behind every pixel's last contributor get no gradient */
    for (int i = start + n_max; i < end; ++i)
        for (int k = 0; k < GRAD_FIELDS; ++k)
            slot_grads[(size_t)sorted_slots[i] * GRAD_FIELDS + k] = 0;

    for (int i = start + n_max - 1; i >= start; --i) {
        const entry_t e = load_entry(i, entries, py0, n_rows);
        const real mx = e.mx, my = e.my, A = e.A, B = e.B, C = e.C, o = e.o;
        __global const real *f = entries + (size_t)i * ENTRY_STRIDE + ENTRY_FIELDS;
        rowv v_mean_x = 0, v_mean_y = 0, v_A = 0, v_B = 0, v_C = 0, v_o = 0, v_f[CHANNELS];
        for (int k = 0; k < CHANNELS; ++k)
            v_f[k] = 0;
        for (int r = e.r0; r < e.r1; ++r) {
            const real cy = py0 + r + (real)0.5;
            if (row_culled(&e, my - cy, px0))
                continue;
            ROW_ALPHA(dx, dy, sigma, falloff, alpha);
            const int16 active = (int16)(i - start) < n_row[r];
            const maskv hit =
                isgreaterequal(sigma, (rowv)0) & isgreaterequal(alpha, (rowv)(real)ALPHA_MIN) & INT_TO_MASK(active);
            const rowv inv_one_minus = 1 / (1 - alpha);
            T[r] = select(T[r], T[r] * inv_one_minus, hit);
            const rowv w = select((rowv)0, alpha * T[r], hit);
            for (int k = 0; k < CHANNELS; ++k)
                v_f[k] += w * g[r][k];
            ALPHA_ADJOINT(rowv, f, g[r], S[r], T[r], w, inv_one_minus, T_end[r], v_T_end[r], v_alpha);
            /* clamped alpha (o exp(-sigma) > ALPHA_MAX): no gradient to opacity or shape */
            const maskv free = hit & islessequal(o * falloff, (rowv)(real)ALPHA_MAX);
            const rowv a = select((rowv)0, falloff * v_alpha, free);
            ADD_SIGMA_ADJOINT(rowv, a, dx, dy, v_mean_x, v_mean_y, v_A, v_B, v_C, v_o);
        }
        __global real *row = slot_grads + (size_t)sorted_slots[i] * GRAD_FIELDS;
        row[0] = hsum(v_mean_x);
        row[1] = hsum(v_mean_y);
        row[2] = hsum(v_A);
        row[3] = hsum(v_B);
        row[4] = hsum(v_C);
        row[5] = hsum(v_o);
        for (int k = 0; k < CHANNELS; ++k)
            row[6 + k] = hsum(v_f[k]);
    }
}
