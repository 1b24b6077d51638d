/* Constants and helpers shared by the splat kernels (projection, binning, compositing).
 *
 * The constants come from the host as -D defines (clflow/splat/constants.py, one Python
 * constant each) so forward, backward and the torch reference use the same numbers:
 *   TILE_SIZE      pixels per tile side (a work-item or a work-group composites one tile)
 *   EPS2D          low-pass dilation added to the 2D covariance (pixel^2)
 *   ALPHA_MIN      a Gaussian with alpha below this is skipped at a pixel
 *   ALPHA_MAX      alpha is clamped to at most this
 *   T_MIN          compositing stops before a Gaussian that takes T below this
 *   ROW_CULL_MARGIN  margin (in sigma) of the exact row cull in rasterize_tile_rows.cl
 * Contraction to fma is off so the forward and backward kernels take the same
 * skip/stop decisions from the same inputs. */
#ifndef CLFLOW_SPLAT_COMMON_H
#define CLFLOW_SPLAT_COMMON_H

/* realv (common/lanes.h): the per-Gaussian forward kernels take CLFLOW_SIMD_LANES at a time */
#include "common/lanes.h"

#pragma OPENCL FP_CONTRACT OFF

#if !defined(TILE_SIZE) || !defined(EPS2D) || !defined(ALPHA_MIN) || !defined(ALPHA_MAX) || !defined(T_MIN) ||         \
    !defined(ROW_CULL_MARGIN)
#error "build with the splat constants (clflow/splat/constants.py: SPLAT_DEFINES)"
#endif

/* Tiles [x0, x1) x [y0, y1) whose pixels [16k, 16k+16) meet the box mean2d +- radius.
 * Returns the number of tiles (0: the box lies outside the image). */
inline int tile_rect(const real mx, const real my, const int radius, const int tiles_x, const int tiles_y, int *x0,
                     int *y0, int *x1, int *y1)
{
    const real r = (real)radius;
    /* clamp in real first: converting an out-of-range real to int is undefined */
    *x0 = (int)floor(clamp((mx - r) / TILE_SIZE, (real)0, (real)tiles_x));
    *y0 = (int)floor(clamp((my - r) / TILE_SIZE, (real)0, (real)tiles_y));
    *x1 = (int)floor(clamp((mx + r) / TILE_SIZE + 1, (real)0, (real)tiles_x));
    *y1 = (int)floor(clamp((my + r) / TILE_SIZE + 1, (real)0, (real)tiles_y));
    return max(*x1 - *x0, 0) * max(*y1 - *y0, 0);
}

#endif /* CLFLOW_SPLAT_COMMON_H */
