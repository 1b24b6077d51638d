/* What both shapes of the compositing kernels share (rasterize_tile_rows.cl: a work-item per tile, for
 * CPU devices; rasterize_workgroup.cl: a work-group per tile, a work-item per pixel, for GPUs):
 * the layout of the entry records they read and of the gradient rows they write, the alpha
 * of a Gaussian at a pixel and the adjoint of the compositing step. The maths is written
 * once, as macros over a value type V (real for one pixel, a vector of reals for a row of
 * pixels), so both shapes take the same skip/stop decisions and give the same per-pixel terms.
 *
 * A pixel's centre is at (x + 0.5, y + 0.5); d = mean2d - centre; the Gaussian's
 *   sigma = 0.5 (A dx^2 + C dy^2) + B dx dy,  falloff = exp(-sigma),
 *   alpha = min(ALPHA_MAX, o falloff);
 * it contributes where sigma >= 0 and alpha >= ALPHA_MIN, unless T (1 - alpha) < T_MIN, when
 * the pixel stops (the constants: splat/common.h). */
#ifndef CLFLOW_SPLAT_COMPOSITE_H
#define CLFLOW_SPLAT_COMPOSITE_H

#include "splat/common.h"

#ifndef CHANNELS
#error "build with -DCHANNELS=<feature channels>"
#endif

/* Per-Gaussian record (entries.cl: entry_records): mean2d x, y, conic A, B, C, opacity, then
 * the row cull's cut, slope and reach (rasterize_tile_rows.cl). A sorted entry's record is followed by
 * the Gaussian's CHANNELS features: entries [M, ENTRY_STRIDE] (entries.cl: sort_entry_records). */
#define ENTRY_FIELDS 9
#define ENTRY_STRIDE (ENTRY_FIELDS + CHANNELS)

/* One gradient row per (tile, Gaussian) slot: slot_grads [M, GRAD_FIELDS] = (dmean2d x, y,
 * dconic A, B, C, dopacity, dfeatures...), written once by the slot's tile. */
#define GRAD_FIELDS (6 + CHANNELS)

/* sigma, falloff and alpha (all of type V) at offsets dx, dy from the Gaussian (A, B, C, o in
 * scope). No fma contraction (common.h): every shape rounds alike. */
#define SPLAT_ALPHA(V, dx, dy, sigma, falloff, alpha)                                                                  \
    const V sigma = (real)0.5 * (A * dx * dx + C * dy * dy) + B * dx * dy;                                             \
    const V falloff = exp(-sigma);                                                                                     \
    const V alpha = fmin((V)(real)ALPHA_MAX, o * falloff)

/* Walking back over a contributor i of a pixel, with T = T_i (already stepped back,
 * T_i = T_{i+1} / (1 - alpha_i)), inv_one_minus = 1 / (1 - alpha_i), w = alpha_i T_i,
 * f the entry's features, g = dL/dout and S = sum of f alpha T over the contributors behind:
 *   v_alpha = dL/dalpha_i = sum_k (f_k T_i - S_k / (1 - alpha_i)) g_k - T_final v_T_final / (1 - alpha_i)
 * with v_T_final = dL/dT_final + background . g; then S += f w. */
#define ALPHA_ADJOINT(V, f, g, S, T, w, inv_one_minus, T_end, v_T_end, v_alpha)                                        \
    V v_alpha = -T_end * inv_one_minus * v_T_end;                                                                      \
    for (int k = 0; k < CHANNELS; ++k) {                                                                               \
        v_alpha += (f[k] * T - S[k] * inv_one_minus) * g[k];                                                           \
        S[k] += f[k] * w;                                                                                              \
    }

/* Adds a pixel's terms to an entry's gradient sums given a = falloff dL/dalpha (0 where alpha
 * is clamped to ALPHA_MAX or the pixel is not hit): dL/dopacity += a, and with
 * dL/dsigma = -o a, dL/dmean2d and dL/dconic (A, B, C, o in scope). */
#define ADD_SIGMA_ADJOINT(V, a, dx, dy, v_mean_x, v_mean_y, v_A, v_B, v_C, v_o)                                        \
    do {                                                                                                               \
        const V v_sigma = -o * (a);                                                                                    \
        v_mean_x += v_sigma * (A * dx + B * dy);                                                                       \
        v_mean_y += v_sigma * (B * dx + C * dy);                                                                       \
        v_A += v_sigma * (real)0.5 * dx * dx;                                                                          \
        v_B += v_sigma * dx * dy;                                                                                      \
        v_C += v_sigma * (real)0.5 * dy * dy;                                                                          \
        v_o += (a);                                                                                                    \
    } while (0)

#endif /* CLFLOW_SPLAT_COMPOSITE_H */
