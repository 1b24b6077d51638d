/* Shared pieces of the MPM adjoint kernels: gradients of the B-spline stencil weights.
 *
 * With f = (x - origin)/dx - base per axis, dw0/dx = -(1.5 - f)/dx, dw1/dx = -2(f - 1)/dx,
 * dw2/dx = (f - 0.5)/dx; base is piecewise constant (its jumps are where w is C^1 anyway),
 * and d = x_i - x_p has dd/dx_p = -I. */
#ifndef CLFLOW_MPM_ADJOINT_H
#define CLFLOW_MPM_ADJOINT_H

#include "mpm/mpm.h"

/* stencil_gradient_t (for stencil_t) and, with CLFLOW_SIMD_LANES, stencil_gradient_v_t in
 * lanes (for stencil_v_t): dw[axis][offset] = d w[axis][offset] / d x_axis (1/m). */
#define CLFLOW_DEFINE_STENCIL_GRADIENT(SFX, T)                                                                         \
    typedef struct {                                                                                                   \
        T dw[3][3];                                                                                                    \
    } stencil_gradient##SFX##_t;                                                                                       \
                                                                                                                       \
    inline stencil_gradient##SFX##_t make_stencil_gradient##SFX(const stencil##SFX##_t *st, const real dx)             \
    {                                                                                                                  \
        stencil_gradient##SFX##_t sg;                                                                                  \
        for (int a = 0; a < 3; ++a) {                                                                                  \
            const T f = st->fx[a];                                                                                     \
            sg.dw[a][0] = -((real)1.5 - f) / dx;                                                                       \
            sg.dw[a][1] = -2 * (f - 1) / dx;                                                                           \
            sg.dw[a][2] = (f - (real)0.5) / dx;                                                                        \
        }                                                                                                              \
        return sg;                                                                                                     \
    }
CLFLOW_DEFINE_STENCIL_GRADIENT(, real)
#ifdef CLFLOW_SIMD_LANES
CLFLOW_DEFINE_STENCIL_GRADIENT(_v, realv)
#endif

/* Gradient (1/m) of the node weight w = w[0][i] w[1][j] w[2][k] with respect to x_p. */
inline void weight_gradient(const stencil_t *st, const stencil_gradient_t *sg, const int i, const int j, const int k,
                            real *grad)
{
    grad[0] = sg->dw[0][i] * st->w[1][j] * st->w[2][k];
    grad[1] = st->w[0][i] * sg->dw[1][j] * st->w[2][k];
    grad[2] = st->w[0][i] * st->w[1][j] * sg->dw[2][k];
}

#endif /* CLFLOW_MPM_ADJOINT_H */
