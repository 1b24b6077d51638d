/* Per-tile compositing of sorted splats: forward (front to back) and adjoint (back to front).
 *
 * Inputs per Gaussian g: mean2d [N,2] (pixels), conic [N,3] (A, B, C), opacity [N],
 * features [N, CHANNELS]; per tile t: ranges[t] = [start, end) into the (tile, depth)
 * sorted list, whose entry i names slot sorted_slots[i] of Gaussian slot_gaussian[slot].
 * Pixel p (centre at i + 0.5) composites, front to back,
 *   out_p = sum_i f_i alpha_i T_i + T_final background,  T_{i+1} = T_i (1 - alpha_i)
 * skipping alpha < ALPHA_MIN and stopping before T would fall below T_MIN. */
#include "splat/common.h"

#ifndef CHANNELS
#error "build with -DCHANNELS=<feature channels>"
#endif

#define TILE_PIXELS (TILE_SIZE * TILE_SIZE)

/* One work-group of TILE_PIXELS work-items per tile, one work-item per pixel. The tile's
 * Gaussians are staged TILE_PIXELS at a time in local memory; the group stops early once
 * every pixel is done (the count of done pixels is read after a barrier: uniform). */
__kernel __attribute__((reqd_work_group_size(TILE_PIXELS, 1, 1))) void rasterize_forward(
    __global const int *ranges, __global const int *sorted_slots,
    __global const int *slot_gaussian, __global const real *means2d,
    __global const real *conics, __global const real *opacities, __global const real *features,
    __global const real *background, __global real *out, __global real *T_final,
    __global int *n_contrib, const int width, const int height, const int tiles_x)
{
    __local int l_gaussian[TILE_PIXELS];
    __local real l_mx[TILE_PIXELS], l_my[TILE_PIXELS];
    __local real l_A[TILE_PIXELS], l_B[TILE_PIXELS], l_C[TILE_PIXELS], l_o[TILE_PIXELS];
    __local volatile int n_done;

    const int tile = get_group_id(0);
    const int lid = get_local_id(0);
    const int px = (tile % tiles_x) * TILE_SIZE + lid % TILE_SIZE;
    const int py = (tile / tiles_x) * TILE_SIZE + lid / TILE_SIZE;
    const bool inside = px < width && py < height;
    const real cx = px + (real)0.5, cy = py + (real)0.5;
    const int start = ranges[2 * tile], end = ranges[2 * tile + 1];

    real acc[CHANNELS];
    for (int k = 0; k < CHANNELS; ++k)
        acc[k] = 0;
    real T = 1;
    int seen = 0, last = 0;  /* entries walked; entries up to the last contributor */
    bool done = !inside;

    if (lid == 0)
        n_done = 0;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (done)
        atomic_inc(&n_done);
    for (int batch = start; batch < end; batch += TILE_PIXELS) {
        barrier(CLK_LOCAL_MEM_FENCE);
        if (n_done == TILE_PIXELS)
            break;
        const int i = batch + lid;
        if (i < end) {
            const int g = slot_gaussian[sorted_slots[i]];
            l_gaussian[lid] = g;
            l_mx[lid] = means2d[2 * g];
            l_my[lid] = means2d[2 * g + 1];
            l_A[lid] = conics[3 * g];
            l_B[lid] = conics[3 * g + 1];
            l_C[lid] = conics[3 * g + 2];
            l_o[lid] = opacities[g];
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        const int count = min(TILE_PIXELS, end - batch);
        for (int j = 0; !done && j < count; ++j) {
            ++seen;
            real sigma, falloff;
            const real alpha = splat_alpha(l_mx[j] - cx, l_my[j] - cy, l_A[j], l_B[j], l_C[j],
                                           l_o[j], &sigma, &falloff);
            if (alpha == 0)
                continue;
            const real T_next = T * (1 - alpha);
            if (T_next < (real)T_MIN) {
                done = true;
                atomic_inc(&n_done);
                break;
            }
            __global const real *f = features + (size_t)l_gaussian[j] * CHANNELS;
            const real w = alpha * T;
            for (int k = 0; k < CHANNELS; ++k)
                acc[k] += f[k] * w;
            T = T_next;
            last = seen;
        }
    }
    if (!inside)
        return;
    const size_t p = (size_t)py * width + px;
    for (int k = 0; k < CHANNELS; ++k)
        out[p * CHANNELS + k] = acc[k] + T * background[k];
    T_final[p] = T;
    n_contrib[p] = last;
}

/* Adjoint, one work-item per tile walking its pixels in order and, per pixel, its
 * contributors back to front (T_i = T_{i+1} / (1 - alpha_i)). The gradient of entry i is
 * added into row sorted_slots[i] of slot_grads [M, 6 + CHANNELS] =
 * (dmean2d x, y, dconic A, B, C, dopacity, dfeatures...): each row belongs to one
 * (tile, Gaussian) pair, hence to this work-item only, and the pixel order is fixed, so the
 * sums are deterministic. In: v_out [H,W,CHANNELS] = dL/dout, v_T [H,W] = dL/dT_final. */
__kernel void rasterize_backward(
    __global const int *ranges, __global const int *sorted_slots,
    __global const int *slot_gaussian, __global const real *means2d,
    __global const real *conics, __global const real *opacities, __global const real *features,
    __global const real *background, __global const real *T_final,
    __global const int *n_contrib, __global const real *v_out, __global const real *v_T,
    __global real *slot_grads, const int width, const int height, const int tiles_x,
    const int n_tiles)
{
    const int tile = get_global_id(0);
    if (tile >= n_tiles)
        return;
    const int start = ranges[2 * tile];
    const int x0 = (tile % tiles_x) * TILE_SIZE, y0 = (tile / tiles_x) * TILE_SIZE;
    const int x1 = min(x0 + TILE_SIZE, width), y1 = min(y0 + TILE_SIZE, height);
    for (int py = y0; py < y1; ++py) {
        for (int px = x0; px < x1; ++px) {
            const size_t p = (size_t)py * width + px;
            const real cx = px + (real)0.5, cy = py + (real)0.5;
            const real T_end = T_final[p];
            real g[CHANNELS], S[CHANNELS];  /* dL/dout_k; sum over later contributors of f alpha T */
            real bg_dot_g = 0;
            for (int k = 0; k < CHANNELS; ++k) {
                g[k] = v_out[p * CHANNELS + k];
                S[k] = 0;
                bg_dot_g += background[k] * g[k];
            }
            const real v_T_end = v_T[p] + bg_dot_g;  /* dL/dT_final, background included */
            real T = T_end;
            for (int i = start + n_contrib[p] - 1; i >= start; --i) {
                const int slot = sorted_slots[i];
                const int gid = slot_gaussian[slot];
                const real dx = means2d[2 * gid] - cx, dy = means2d[2 * gid + 1] - cy;
                const real A = conics[3 * gid], B = conics[3 * gid + 1], C = conics[3 * gid + 2];
                const real o = opacities[gid];
                real sigma, falloff;
                const real alpha = splat_alpha(dx, dy, A, B, C, o, &sigma, &falloff);
                if (alpha == 0)
                    continue;
                const real one_minus = 1 - alpha;
                T = T / one_minus;
                const real w = alpha * T;
                __global const real *f = features + (size_t)gid * CHANNELS;
                __global real *row = slot_grads + (size_t)slot * (6 + CHANNELS);
                real v_alpha = 0;
                for (int k = 0; k < CHANNELS; ++k) {
                    row[6 + k] += w * g[k];
                    v_alpha += (f[k] * T - S[k] / one_minus) * g[k];
                    S[k] += f[k] * w;
                }
                v_alpha -= T_end / one_minus * v_T_end;
                if (o * falloff > (real)ALPHA_MAX)
                    continue;  /* clamped alpha: no gradient to opacity or shape */
                const real v_sigma = -o * falloff * v_alpha;
                row[0] += v_sigma * (A * dx + B * dy);
                row[1] += v_sigma * (B * dx + C * dy);
                row[2] += v_sigma * (real)0.5 * dx * dx;
                row[3] += v_sigma * dx * dy;
                row[4] += v_sigma * (real)0.5 * dy * dy;
                row[5] += falloff * v_alpha;
            }
        }
    }
}

/* Per Gaussian g: the sum of its slot rows [first_slot[g], first_slot[g] + tiles_touched[g])
 * in slot order, split into dL/dmean2d [N,2], dL/dconic [N,3], dL/dopacity [N] and
 * dL/dfeatures [N, CHANNELS]. */
__kernel void reduce_slots(__global const real *slot_grads, __global const int *first_slot,
                           __global const int *tiles_touched, __global real *v_means2d,
                           __global real *v_conics, __global real *v_opacities,
                           __global real *v_features, const int n)
{
    const int g = get_global_id(0);
    if (g >= n)
        return;
    real sum[6 + CHANNELS];
    for (int k = 0; k < 6 + CHANNELS; ++k)
        sum[k] = 0;
    const int first = first_slot[g];
    for (int s = first; s < first + tiles_touched[g]; ++s)
        for (int k = 0; k < 6 + CHANNELS; ++k)
            sum[k] += slot_grads[(size_t)s * (6 + CHANNELS) + k];
    v_means2d[2 * g] = sum[0];
    v_means2d[2 * g + 1] = sum[1];
    for (int k = 0; k < 3; ++k)
        v_conics[3 * g + k] = sum[2 + k];
    v_opacities[g] = sum[5];
    for (int k = 0; k < CHANNELS; ++k)
        v_features[(size_t)g * CHANNELS + k] = sum[6 + k];
}
