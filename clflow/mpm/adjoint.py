"""Hand-written adjoint of one MLS-MPM substep (kernels in kernels_cl/mpm/adjoint/).

The substep (clflow/mpm/substep.py) maps state n to state n+1 through tau, the grid (m, mv)
and the grid velocities. Its adjoint maps dL/d(state n+1) to dL/d(state n) and accumulates
the gradients of the per-particle kernel parameters and masses, in reverse kernel order:

    g2p_adjoint_private              : (xbar', vbar', Cbar', grid_v[, grid_dv]) -> grid_vbar copies, xbar (part)
    grid_update_adjoint              : (grid_vbar copies, grid, boundaries) -> grid_bar (mbar_i, pbar_i[, p0bar_i])
    p2g_adjoint                      : (grid_bar, x, v, C, tau)      -> xbar, vbar, Cbar (part), taubar, massbar
    p2g_flip_adjoint (flip > 0)      : (grid_bar, vbar', x, v, C)    -> xbar, vbar, Cbar, massbar (parts)
    trial_svd_simd + update_stress_adjoint : (taubar, Fbar', F, C, param) -> Fbar, Cbar, parambar
      (update_stress_elastic_adjoint_simd when every particle is fixed-corotated elastic)

Every sum has a fixed order (private grid copies reduced in order, per-node and per-particle
gathers), so gradients are bit-identical across runs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from clflow.mpm.constants import SIMD_LANES, grid_channels, velocity_channels
from clflow.mpm.substep import Grid, State, StressStage, SubstepInputs, SubstepTape, grid_copies, launch_stress
from clflow.runtime.bridge import numpy_real, real_of


@dataclass
class StateGrad:
    """dL/d(state) of one instant: x, v [N, 3], C, F [N, 3, 3], plastic [N] (units: 1/State's)."""

    x: torch.Tensor
    v: torch.Tensor
    C: torch.Tensor
    F: torch.Tensor
    plastic: torch.Tensor

    @staticmethod
    def zeros(n: int, dtype: torch.dtype) -> "StateGrad":
        return StateGrad(
            torch.zeros(n, 3, dtype=dtype),
            torch.zeros(n, 3, dtype=dtype),
            torch.zeros(n, 3, 3, dtype=dtype),
            torch.zeros(n, 3, 3, dtype=dtype),
            torch.zeros(n, dtype=dtype),
        )


class SubstepAdjoint:
    """The adjoint kernels of one device, precision, particle count, grid, material set and
    PIC/FLIP blend, with their scratch buffers (grid adjoint, taubar, U s V, private grid copies)."""

    def __init__(self, device, dtype: torch.dtype, n: int, grid: Grid, materials: torch.Tensor, flip: float = 0.0):
        import pyopencl as cl

        self.device, self.dtype, self.n, self.grid, self.flip = device, dtype, n, grid, float(flip)
        real, self.real_t = real_of(dtype, "simulation"), numpy_real(dtype, "simulation")
        stage = StressStage.of(materials)  # as the forward: fused SIMD adjoint for all-elastic scenes
        defines = stage.defines(self.flip)
        k = lambda src, name: device.kernel(src, name, real, defines)  # noqa: E731
        self.elastic_only = stage.elastic_only
        self.k_stress, self.k_svd = stage.kernels(device, real, adjoint=True)
        self.U, self.s, self.V = stage.svd_buffers(n, dtype)
        self.k_g2p = k("mpm/adjoint/g2p_adjoint.cl", "g2p_adjoint_private")
        self.k_grid = k("mpm/adjoint/grid_adjoint.cl", "grid_update_adjoint")
        self.k_p2g = k("mpm/adjoint/p2g_adjoint.cl", "p2g_adjoint")
        self.k_flip = k("mpm/adjoint/p2g_adjoint.cl", "p2g_flip_adjoint") if self.flip > 0 else None
        itemsize = torch.tensor([], dtype=dtype).element_size()
        copy_bytes = velocity_channels(self.flip) * grid.nodes * itemsize  # vbar[, dvbar] per node
        self.copies = grid_copies(device, copy_bytes, n)
        self.chunk = -(-n // self.copies)
        self.grid_v_bar_copies = cl.Buffer(device.context, cl.mem_flags.READ_WRITE, self.copies * copy_bytes)
        self.grid_bar = torch.empty(grid.nodes, grid_channels(self.flip), dtype=dtype)
        self.tau_bar = torch.empty(n, 3, 3, dtype=dtype)

    def run(
        self,
        state: State,
        after: State,
        tape: SubstepTape,
        inputs: SubstepInputs,
        grad_after: StateGrad,
        grad: StateGrad,
        param_grad: torch.Tensor,
        mass_grad: torch.Tensor,
    ) -> None:
        """Pull ``grad_after`` = dL/d(after) back through the substep state -> after (run with
        ``inputs``, recorded in ``tape``) into ``grad`` = dL/d(state) (overwritten); adds the
        parameter and mass gradients into ``param_grad`` [N, PARAM_COUNT] and ``mass_grad`` [N]."""
        dev, R, n = self.device, self.real_t, np.int32(self.n)
        grid_args = self.grid.kernel_args(R)
        particles, t, dt, accel = inputs.particles, inputs.t, inputs.dt, inputs.accel
        with dev.bind() as b:
            x = b.input(state.x, "x")
            C = b.input(state.C, "C")
            x_bar = b.inout(grad.x, "x_bar")
            C_bar = b.inout(grad.C, "C_bar")
            grid_bar = b.inout(self.grid_bar, "grid_bar")
            tau_bar = b.inout(self.tau_bar, "tau_bar")
            release_time, v_bar_out = (
                b.input(particles.release_time, "release_time"),
                b.input(grad_after.v, "v_bar_out"),
            )
            grid_v = b.input(tape.grid_v, "grid_v")
            # v' read back as v_pic; with FLIP the kernel sums v_pic itself (any buffer will do)
            v_out = grid_v if self.flip > 0 else b.input(after.v, "v_out")
            dev.launch(
                self.k_g2p,
                self.copies,
                grid_args
                + [
                    n,
                    R(dt),
                    R(t),
                    R(self.flip),
                    x,
                    v_out,
                    release_time,
                    grid_v,
                    b.input(tape.grid_dv, "grid_dv"),
                    b.input(grad_after.x, "x_bar_out"),
                    v_bar_out,
                    b.input(grad_after.C, "C_bar_out"),
                    np.int32(self.copies),
                    np.int32(self.chunk),
                    self.grid_v_bar_copies,
                    x_bar,
                ],
                local_size=1,
            )
            dev.launch(
                self.k_grid,
                self.grid.nodes,
                grid_args
                + inputs.grid_update_args(R)
                + [b.input(tape.grid_mv, "grid"), self.grid_v_bar_copies, np.int32(self.copies)]
                + inputs.boundary_args(b)
                + [grid_bar],
            )
            # p2g_adjoint writes v_bar, which p2g_flip_adjoint then reads and adds to
            v_bar = (b.output if self.k_flip is None else b.inout)(grad.v, "v_bar")
            v, mass, mass_bar = b.input(state.v, "v"), b.input(particles.mass, "mass"), b.inout(mass_grad, "mass_bar")
            dev.launch(
                self.k_p2g,
                -(-self.n // SIMD_LANES),
                grid_args
                + [
                    n,
                    R(dt),
                    x,
                    v,
                    C,
                    b.input(tape.tau, "tau"),
                    mass,
                    b.input(particles.volume, "volume"),
                    b.input(particles.group, "group"),
                    b.input(accel, "accel"),
                    grid_bar,
                    x_bar,
                    v_bar,
                    C_bar,
                    tau_bar,
                    mass_bar,
                ],
            )
            if self.k_flip is not None:
                dev.launch(
                    self.k_flip,
                    self.n,
                    grid_args
                    + [
                        n,
                        R(t),
                        R(self.flip),
                        x,
                        v,
                        C,
                        mass,
                        release_time,
                        v_bar_out,
                        grid_bar,
                        x_bar,
                        v_bar,
                        C_bar,
                        mass_bar,
                    ],
                )
            self.launch_stress_adjoint(
                b,
                dt,
                b.input(state.F, "F"),
                C,
                b.input(state.plastic, "plastic"),
                b.input(particles.material, "material"),
                b.input(particles.param, "param"),
                tau_bar,
                b.input(grad_after.F, "F_bar_out"),
                b.input(grad_after.plastic, "plastic_bar_out"),
                b.output(grad.F, "F_bar"),
                C_bar,
                b.output(grad.plastic, "plastic_bar"),
                b.inout(param_grad, "param_bar"),
            )

    def launch_stress_adjoint(
        self,
        b,
        dt: float,
        F,
        C,
        plastic,
        material,
        param,
        tau_bar,
        F_bar_out,
        plastic_bar_out,
        F_bar,
        C_bar,
        plastic_bar,
        param_bar,
    ) -> None:
        """Enqueue the stress stage's adjoint on buffers of the binding ``b``: F_bar, plastic_bar
        written, C_bar and param_bar accumulated into (see kernels_cl/mpm/adjoint/stress_adjoint.cl)."""
        bars = [tau_bar, F_bar_out, plastic_bar_out, F_bar, C_bar, plastic_bar, param_bar]
        launch_stress(self, b, dt, F, C, [param, *bars], [plastic, material, param, *bars])


__all__ = ["StateGrad", "SubstepAdjoint"]
