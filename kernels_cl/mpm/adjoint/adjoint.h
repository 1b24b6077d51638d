/* Shared pieces of the MPM adjoint kernels: gradients of the B-spline stencil weights.
 *
 * With f = (x - origin)/dx - base per axis, dw0/dx = -(1.5 - f)/dx, dw1/dx = -2(f - 1)/dx,
 * dw2/dx = (f - 0.5)/dx; base is piecewise constant (its jumps are where w is C^1 anyway),
 * and d = x_i - x_p has dd/dx_p = -I. */
#ifndef CLFLOW_MPM_ADJOINT_H
#define CLFLOW_MPM_ADJOINT_H

#include "mpm/mpm.h"

typedef struct {
    real dw[3][3]; /* dw[axis][offset] = d w[axis][offset] / d x_axis (1/m) */
} stencil_gradient_t;

inline stencil_gradient_t make_stencil_gradient(const stencil_t *st, const real dx)
{
    stencil_gradient_t sg;
    for (int a = 0; a < 3; ++a) {
        const real f = st->fx[a];
        sg.dw[a][0] = -((real)1.5 - f) / dx;
        sg.dw[a][1] = -2 * (f - 1) / dx;
        sg.dw[a][2] = (f - (real)0.5) / dx;
    }
    return sg;
}

/* Gradient (1/m) of the node weight w = w[0][i] w[1][j] w[2][k] with respect to x_p. */
inline void weight_gradient(const stencil_t *st, const stencil_gradient_t *sg, const int i, const int j,
                            const int k, real *grad)
{
    grad[0] = sg->dw[0][i] * st->w[1][j] * st->w[2][k];
    grad[1] = st->w[0][i] * sg->dw[1][j] * st->w[2][k];
    grad[2] = st->w[0][i] * st->w[1][j] * sg->dw[2][k];
}

#endif /* CLFLOW_MPM_ADJOINT_H */
