/* Per-tile compositing of sorted splats for GPUs (plan raster "workgroup",
 * clflow/runtime/plan.py): forward (front to back) and adjoint (back to front), with the
 * outputs of rasterize_tile_rows.cl (the CPU shape). splat/composite.h holds the maths both share.
 *
 * Layout: one work-group of TILE_PIXELS = TILE_SIZE^2 work-items per tile, one work-item per
 * pixel (launch: local size TILE_PIXELS, global size n_tiles * TILE_PIXELS; group g is tile
 * g). The tile's entries are staged in local memory in batches that the work-group copies
 * together; pixels outside the image are work-items that composite nothing and write nothing.
 * Inputs per tile t: ranges[t] = [start, end) into the (tile, depth) sorted list, whose entry
 * i names slot sorted_slots[i], and entries [M, ENTRY_STRIDE] (entries.cl).
 *
 * LOCAL_MEM_BYTES (a define: the local memory the kernels may take) sizes the batches.
 * Every barrier is reached by the whole work-group: the loops that hold one run on values
 * all work-items read alike (the tile's range, local counters read after a barrier). */
#include "splat/composite.h"

#ifndef LOCAL_MEM_BYTES
#error "build with -DLOCAL_MEM_BYTES=<bytes of local memory the kernels may take>"
#endif

#define TILE_PIXELS (TILE_SIZE * TILE_SIZE)
#define REAL_BYTES  (REAL_IS_DOUBLE ? 8 : 4)
/* bytes left for the batch arrays after the local counters */
#define BATCH_BYTES (LOCAL_MEM_BYTES - 64)

/* A staged entry: mean2d x, y, conic A, B, C, opacity, then its CHANNELS features. */
#define STAGED_FIELDS (6 + CHANNELS)

/* Entries [first, first + count) into staged [count, STAGED_FIELDS], copied by the whole
 * work-group (consecutive work-items, consecutive reals). A barrier must follow before the
 * batch is read. */
inline void stage_entries(__local real *staged, __global const real *entries, const int first, const int count,
                          const int lid)
{
    for (int q = lid; q < count * STAGED_FIELDS; q += TILE_PIXELS) {
        const int j = q / STAGED_FIELDS, k = q % STAGED_FIELDS;
        staged[q] = entries[(size_t)(first + j) * ENTRY_STRIDE + (k < 6 ? k : ENTRY_FIELDS + k - 6)];
    }
}

/* Forward batch: one entry per work-item, fewer when their records would not fit. */
#define FORWARD_FIT   (BATCH_BYTES / (STAGED_FIELDS * REAL_BYTES))
#define FORWARD_BATCH (FORWARD_FIT < TILE_PIXELS ? FORWARD_FIT : TILE_PIXELS)
#if FORWARD_FIT < 1
#error "LOCAL_MEM_BYTES cannot hold one staged entry"
#endif

/* Forward, a work-item per pixel. Per batch: the work-group stages the entries, barrier, each
 * pixel composites them front to back until it is done (T would fall below T_MIN) and counts
 * itself in n_done, barrier; the tile stops when every pixel inside the image is done.
 * Writes out [H,W,CHANNELS], T_final [H,W] and n_contrib [H,W] (entries walked up to the
 * pixel's last contributor, counted from the tile's start). */
__kernel __attribute__((reqd_work_group_size(TILE_PIXELS, 1, 1))) void
rasterize_tiles_forward(__global const int *ranges, __global const real *entries, __global const real *background,
                        __global real *out, __global real *T_final, __global int *n_contrib, const int width,
                        const int height, const int tiles_x)
{
    __local real staged[FORWARD_BATCH * STAGED_FIELDS];
    __local int n_done; /* pixels of the tile inside the image that are done */
    const int tile = get_group_id(0), lid = get_local_id(0);
    const int px0 = (tile % tiles_x) * TILE_SIZE, py0 = (tile / tiles_x) * TILE_SIZE;
    const int px = px0 + lid % TILE_SIZE, py = py0 + lid / TILE_SIZE;
    const bool inside = px < width && py < height;
    const int n_inside = min(TILE_SIZE, width - px0) * min(TILE_SIZE, height - py0);
    const real cx = px + (real)0.5, cy = py + (real)0.5;
    const int start = ranges[2 * tile], end = ranges[2 * tile + 1];

    real acc[CHANNELS], T = 1;
    for (int k = 0; k < CHANNELS; ++k)
        acc[k] = 0;
    int last = 0;
    bool done = !inside;
    if (lid == 0)
        n_done = 0;
    bool tile_done = false;
    for (int first = start; first < end && !tile_done; first += FORWARD_BATCH) {
        const int count = min(FORWARD_BATCH, end - first);
        stage_entries(staged, entries, first, count, lid);
        barrier(CLK_LOCAL_MEM_FENCE);
        for (int j = 0; j < count && !done; ++j) {
            __local const real *e = staged + j * STAGED_FIELDS;
            const real A = e[2], B = e[3], C = e[4], o = e[5];
            const real dx = e[0] - cx, dy = e[1] - cy;
            SPLAT_ALPHA(real, dx, dy, sigma, falloff, alpha);
            if (!(sigma >= 0 && alpha >= (real)ALPHA_MIN))
                continue;
            const real T_next = T * (1 - alpha);
            if (T_next < (real)T_MIN) {
                done = true;
                atomic_inc(&n_done);
                break;
            }
            const real w = alpha * T;
            for (int k = 0; k < CHANNELS; ++k)
                acc[k] += e[6 + k] * w;
            T = T_next;
            last = first + j - start + 1;
        }
        /* also orders this batch's reads of staged before the next batch's copy */
        barrier(CLK_LOCAL_MEM_FENCE);
        tile_done = n_done == n_inside;
    }
    if (inside) {
        const size_t p = (size_t)py * width + px;
        for (int k = 0; k < CHANNELS; ++k)
            out[p * CHANNELS + k] = acc[k] + T * background[k];
        T_final[p] = T;
        n_contrib[p] = last;
    }
}

/* Backward batch: work-item (tile row, entry) sums an entry's terms over a row, so at most
 * TILE_SIZE entries; the most (halving) whose local arrays fit: the staged entries, w and a
 * per (entry, pixel) (rows padded by one real) and the row sums per (row, entry, field). */
#define BACKWARD_BYTES(b) ((b) * (STAGED_FIELDS + 2 * (TILE_PIXELS + 1) + TILE_SIZE * GRAD_FIELDS) * REAL_BYTES)
#if BACKWARD_BYTES(TILE_SIZE) <= BATCH_BYTES
#define BACKWARD_BATCH TILE_SIZE
#elif BACKWARD_BYTES(TILE_SIZE / 2) <= BATCH_BYTES
#define BACKWARD_BATCH (TILE_SIZE / 2)
#elif BACKWARD_BYTES(TILE_SIZE / 4) <= BATCH_BYTES
#define BACKWARD_BATCH (TILE_SIZE / 4)
#elif BACKWARD_BYTES(TILE_SIZE / 8) <= BATCH_BYTES
#define BACKWARD_BATCH (TILE_SIZE / 8)
#elif BACKWARD_BYTES(1) <= BATCH_BYTES
#define BACKWARD_BATCH 1
#else
#error "LOCAL_MEM_BYTES cannot hold the backward's arrays for one entry"
#endif

/* Adjoint, a work-item per pixel. The entries are walked back to front from the tile's
 * largest n_contrib, BACKWARD_BATCH at a time; per batch (three barriers):
 *   1. the work-group stages the entries; barrier;
 *   2. each pixel steps back over them (T_i = T_{i+1} / (1 - alpha_i)) where it has
 *      contributed and stores, per entry, w = alpha T and a = falloff dL/dalpha (0 where not
 *      hit, a 0 also where alpha is clamped); barrier;
 *   3. work-item (row r, entry j) sums entry j's gradient over row r's pixels in order
 *      (dfeatures = sum w g, dopacity = sum a, dL/dsigma = -o a for dmean2d and dconic);
 *      barrier;
 *   4. work-item (entry j, field k) sums the TILE_SIZE row sums in order and writes field k
 *      of row sorted_slots[i] of slot_grads [M, GRAD_FIELDS] (composite.h).
 * Each slot row belongs to one (tile, Gaussian) pair and is written once, by one work-item,
 * with sums in a fixed order: no atomics, the same bits every run. Entries behind the tile's
 * largest n_contrib get zero rows. In: v_out [H,W,CHANNELS] = dL/dout, v_T [H,W] = dL/dT_final. */
__kernel __attribute__((reqd_work_group_size(TILE_PIXELS, 1, 1))) void
rasterize_tiles_backward(__global const int *ranges, __global const int *sorted_slots, __global const real *entries,
                         __global const real *background, __global const real *T_final, __global const int *n_contrib,
                         __global const real *v_out, __global const real *v_T, __global real *slot_grads,
                         const int width, const int height, const int tiles_x)
{
    __local real staged[BACKWARD_BATCH * STAGED_FIELDS];
    /* per (batch entry, pixel): w and a (2.); a row of one more real keeps the (row, entry)
     * work-items of 3. on distinct banks */
    __local real w_px[BACKWARD_BATCH][TILE_PIXELS + 1], a_px[BACKWARD_BATCH][TILE_PIXELS + 1];
    /* per tile row: the batch's gradient rows summed over the row (3.), entry-major */
    __local real row_sums[TILE_SIZE][BACKWARD_BATCH * GRAD_FIELDS];
    __local int n_max; /* the tile's largest n_contrib */
    const int tile = get_group_id(0), lid = get_local_id(0);
    const int px0 = (tile % tiles_x) * TILE_SIZE, py0 = (tile / tiles_x) * TILE_SIZE;
    const int px = px0 + lid % TILE_SIZE, py = py0 + lid / TILE_SIZE;
    const real cx = px + (real)0.5, cy = py + (real)0.5;
    const int start = ranges[2 * tile], end = ranges[2 * tile + 1];

    /* this pixel: T (walked back), T_final, dL/dT_final + bg . g, g = dL/dout, S = sum of
     * f alpha T over the contributors behind, and the entries walked up to its last one
     * (0 outside the image: such a pixel never steps back) */
    real T = 1, T_end = 1, v_T_end = 0, g[CHANNELS], S[CHANNELS];
    int n_own = 0;
    for (int k = 0; k < CHANNELS; ++k)
        g[k] = S[k] = 0;
    if (px < width && py < height) {
        const size_t p = (size_t)py * width + px;
        T_end = T = T_final[p];
        real bg_dot_g = 0;
        for (int k = 0; k < CHANNELS; ++k) {
            g[k] = v_out[p * CHANNELS + k];
            bg_dot_g += background[k] * g[k];
        }
        v_T_end = v_T[p] + bg_dot_g; /* background included */
        n_own = n_contrib[p];
    }
    if (lid == 0)
        n_max = 0;
    barrier(CLK_LOCAL_MEM_FENCE);
    atomic_max(&n_max, n_own);
    barrier(CLK_LOCAL_MEM_FENCE);
    const int walked = n_max;

    /* entries behind every pixel's last contributor get no gradient */
    for (int q = lid; q < (end - start - walked) * GRAD_FIELDS; q += TILE_PIXELS)
        slot_grads[(size_t)sorted_slots[start + walked + q / GRAD_FIELDS] * GRAD_FIELDS + q % GRAD_FIELDS] = 0;

    /* 3.'s work-item: row r of the tile, entry sum_entry of the batch */
    const int r = lid / BACKWARD_BATCH, sum_entry = lid % BACKWARD_BATCH;
    const int row_px = r < TILE_SIZE && py0 + r < height ? min(TILE_SIZE, width - px0) : 0;
    for (int hi = start + walked; hi > start; hi -= BACKWARD_BATCH) {
        const int count = min(BACKWARD_BATCH, hi - start), first = hi - count;
        /* 1. (the previous batch's readers of staged and w_px, a_px passed its 3rd barrier) */
        stage_entries(staged, entries, first, count, lid);
        barrier(CLK_LOCAL_MEM_FENCE);

        /* 2. */
        for (int j = count - 1; j >= 0; --j) {
            real w = 0, a = 0;
            if (first + j - start < n_own) {
                __local const real *e = staged + j * STAGED_FIELDS;
                __local const real *f = e + 6;
                const real A = e[2], B = e[3], C = e[4], o = e[5];
                const real dx = e[0] - cx, dy = e[1] - cy;
                SPLAT_ALPHA(real, dx, dy, sigma, falloff, alpha);
                if (sigma >= 0 && alpha >= (real)ALPHA_MIN) {
                    const real inv_one_minus = 1 / (1 - alpha);
                    T = T * inv_one_minus;
                    w = alpha * T;
                    ALPHA_ADJOINT(real, f, g, S, T, w, inv_one_minus, T_end, v_T_end, v_alpha);
                    /* clamped alpha (o exp(-sigma) > ALPHA_MAX): no gradient to opacity or shape */
                    if (o * falloff <= (real)ALPHA_MAX)
                        a = falloff * v_alpha;
                }
            }
            w_px[j][lid] = w;
            a_px[j][lid] = a;
        }
        barrier(CLK_LOCAL_MEM_FENCE);

        /* 3. (row_px = 0 for rows outside the tile or the image: zero sums) */
        if (sum_entry < count && r < TILE_SIZE) {
            __local const real *e = staged + sum_entry * STAGED_FIELDS;
            const real mx = e[0], A = e[2], B = e[3], C = e[4], o = e[5];
            const real dy = e[1] - (py0 + r + (real)0.5);
            real v_mean_x = 0, v_mean_y = 0, v_A = 0, v_B = 0, v_C = 0, v_o = 0, v_f[CHANNELS];
            for (int k = 0; k < CHANNELS; ++k)
                v_f[k] = 0;
            for (int l = 0; l < row_px; ++l) {
                const real w = w_px[sum_entry][r * TILE_SIZE + l], a = a_px[sum_entry][r * TILE_SIZE + l];
                if (w == 0 && a == 0) /* not hit: adds nothing (and needs no read of v_out) */
                    continue;
                const real dx = mx - (px0 + l + (real)0.5);
                ADD_SIGMA_ADJOINT(real, a, dx, dy, v_mean_x, v_mean_y, v_A, v_B, v_C, v_o);
                __global const real *g_px = v_out + ((size_t)(py0 + r) * width + px0 + l) * CHANNELS;
                for (int k = 0; k < CHANNELS; ++k)
                    v_f[k] += w * g_px[k];
            }
            __local real *sums = row_sums[r] + sum_entry * GRAD_FIELDS;
            sums[0] = v_mean_x;
            sums[1] = v_mean_y;
            sums[2] = v_A;
            sums[3] = v_B;
            sums[4] = v_C;
            sums[5] = v_o;
            for (int k = 0; k < CHANNELS; ++k)
                sums[6 + k] = v_f[k];
        }
        barrier(CLK_LOCAL_MEM_FENCE);

        /* 4. (the next batch writes row_sums only after its 1st barrier: these reads are done) */
        for (int q = lid; q < count * GRAD_FIELDS; q += TILE_PIXELS) {
            real sum = 0;
            for (int rr = 0; rr < TILE_SIZE; ++rr)
                sum += row_sums[rr][q];
            slot_grads[(size_t)sorted_slots[first + q / GRAD_FIELDS] * GRAD_FIELDS + q % GRAD_FIELDS] = sum;
        }
    }
}
