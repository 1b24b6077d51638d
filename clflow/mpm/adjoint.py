"""Hand-written adjoint of one MLS-MPM substep (kernels in kernels_cl/mpm/adjoint/).

The substep (clflow/mpm/substep.py) maps state n to state n+1 through tau, the grid (m, mv)
and the grid velocities. Its adjoint maps dL/d(state n+1) to dL/d(state n) and accumulates
the gradients of the per-particle kernel parameters and masses, in reverse kernel order:

    g2p_adjoint_private              : (xbar', vbar', Cbar', grid_v[, grid_dv]) -> grid_vbar copies, xbar (part)
    sum_grid_copies                  : (grid_vbar copies)            -> grid_vbar (vbar_i[, dvbar_i])
      or, where the P2G took the gather (the GPU plan, clflow.runtime.plan), over the
      particles the forward sorted by cell (kept in its SubstepTape):
    g2p_adjoint_records              : (xbar', vbar', Cbar', grid_v[, grid_dv]) -> slot records, xbar (part)
    g2p_adjoint_gather_update        : (slot records)                -> grid_vbar, a work-item per node,
                                       and grid_update_adjoint's work on that node
    grid_update_adjoint              : (grid_vbar, grid, boundaries) -> grid_bar (mbar_i, pbar_i[, p0bar_i])
      (a launch of its own after sum_grid_copies)
    p2g_adjoint                      : (grid_bar, x, v, C, tau)      -> xbar, vbar, Cbar (part), taubar, massbar
    p2g_flip_adjoint (flip > 0)      : (grid_bar, vbar', x, v, C)    -> xbar, vbar, Cbar, massbar (parts)
    trial_svd[_simd] + update_stress_adjoint : (taubar, Fbar', F, C, param) -> Fbar, Cbar, parambar
      (update_stress_elastic_adjoint[_simd] when every particle is fixed-corotated elastic;
      _simd: SIMD lanes, the plan's CPU shape)

Every sum has a fixed order (private grid copies reduced in order, per-node and per-particle
gathers), so gradients are bit-identical across runs. States, gradients and the tape are
DeviceArrays: a substep's adjoint only enqueues kernels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from clflow.mpm.constants import SIMD_LANES, grid_channels, uses_flip, velocity_channels
from clflow.mpm.substep import (
    Grid,
    State,
    StressStage,
    SubstepInputs,
    SubstepTape,
    check_members,
    grid_copies,
    launch_stress,
    p2g_particle_args,
)
from clflow.runtime.arrays import DeviceArray, numpy_real, real_of
from clflow.runtime.binding import LaunchCache
from clflow.runtime.plan import KernelPlan, kernel_plan
from clflow.runtime.profile import profiled_step


@dataclass
class StateGrad:
    """dL/d(state) of one instant: x, v [N, 3], C, F [N, 3, 3], plastic [N] (units: 1/State's);
    host tensors, or DeviceArrays for the kernels."""

    x: torch.Tensor | DeviceArray
    v: torch.Tensor | DeviceArray
    C: torch.Tensor | DeviceArray
    F: torch.Tensor | DeviceArray
    plastic: torch.Tensor | DeviceArray

    @staticmethod
    def zeros(device, n: int, dtype: torch.dtype) -> "StateGrad":
        """Zero gradients on ``device``."""
        shapes = ((n, 3), (n, 3), (n, 3, 3), (n, 3, 3), (n,))
        return StateGrad(*(DeviceArray.zeros(device, shape, dtype) for shape in shapes))


def g2p_adjoint_record_reals(flip: float) -> int:
    """Reals per particle slot of the gather adjoint's records (mpm/adjoint/g2p_adjoint.h G2P_ADJ_REC)."""
    return 18 if uses_flip(flip) else 15


class SubstepAdjoint:
    """The adjoint kernels of one device, precision, particle count, grid, material set and
    PIC/FLIP blend, in the shapes of ``plan`` (the forward's, with the P2G path it took;
    default the device's), for a population of ``members`` (SubstepKernels), with their scratch buffers (grid adjoint, taubar, U s V,
    grid_v_bar, and the private grid copies with their boxes, or the gather's slot records)."""

    def __init__(
        self,
        device,
        dtype: torch.dtype,
        n: int,
        grid: Grid,
        materials: torch.Tensor,
        flip: float = 0.0,
        plan: KernelPlan | None = None,
        members: int = 1,
    ):
        import pyopencl as cl

        self.device, self.dtype, self.n, self.grid, self.flip = device, dtype, n, grid, float(flip)
        self.members, self.nodes = check_members(n, members), members * grid.nodes  # nodes: all members'
        real, self.real_t = real_of(dtype, "simulation"), numpy_real(dtype, "simulation")
        stage = StressStage.of(materials)  # as the forward: a fused adjoint for all-elastic scenes
        defines = stage.defines(self.flip)
        self.plan = plan = plan or kernel_plan(device)
        k = lambda src, name: device.kernel(src, name, real, defines)  # noqa: E731
        scatter = lambda role: device.kernel(*plan.kernel("adjoint_scatter", role), real, defines)  # noqa: E731
        self.elastic_only = stage.elastic_only
        self.k_stress, self.k_svd = stage.kernels(device, real, plan, adjoint=True)
        self.U, self.s, self.V = stage.svd_buffers(device, n if self.k_svd is not None else 0, dtype)
        self.gather = plan.adjoint_scatter == "gather"  # its launch also takes the grid update's adjoint
        self.k_grid = None if self.gather else k("mpm/adjoint/grid_adjoint.cl", "grid_update_adjoint")
        self.k_p2g = k("mpm/adjoint/p2g_adjoint.cl", "p2g_adjoint")
        self.k_flip = k("mpm/adjoint/p2g_adjoint.cl", "p2g_flip_adjoint") if uses_flip(self.flip) else None
        self.k_g2p = scatter("g2p")
        if self.gather:
            self.k_gather = scatter("gather")
            self.records = DeviceArray.empty(device, (n, g2p_adjoint_record_reals(self.flip)), dtype)
        else:
            self.k_sum = scatter("sum")
            itemsize = torch.tensor([], dtype=dtype).element_size()
            copy_bytes = velocity_channels(self.flip) * self.nodes * itemsize  # vbar[, dvbar] per node
            self.copies = grid_copies(device, copy_bytes, n)
            self.chunk = -(-n // self.copies)
            self.grid_v_bar_copies = cl.Buffer(device.context, cl.mem_flags.READ_WRITE, self.copies * copy_bytes)
            self.copy_boxes = DeviceArray.empty(device, (self.copies, 6), torch.int32)  # each copy's node box
        self.grid_v_bar = DeviceArray.empty(device, (self.nodes, velocity_channels(self.flip)), dtype)
        self.grid_bar = DeviceArray.empty(device, (self.nodes, grid_channels(self.flip)), dtype)
        self.grid_args = grid.kernel_args(self.real_t, members)
        self.tau_bar = DeviceArray.empty(device, (n, 3, 3), dtype)
        self.bound = LaunchCache()  # run()'s launches, bound per set of arrays

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
        parameter and mass gradients into ``param_grad`` [N, PARAM_COUNT] and ``mass_grad`` [N].
        Every argument but ``inputs``' scalars is a DeviceArray (or a dataclass of them). Its
        launches are bound on the first call with these arrays (clflow.runtime.binding)."""
        with profiled_step(self.device, "adjoint substep"):
            objects = (state, after, tape, inputs.particles, inputs.boundaries, inputs.accel, grad_after, grad)
            objects += (param_grad, mass_grad)
            args = (state, after, tape, inputs, grad_after, grad, param_grad, mass_grad)
            enqueue = lambda: self._enqueue(*args)  # noqa: E731
            recording = self.bound.recording(self.device, objects, (inputs.dt, inputs.gravity), enqueue)
            self.device.replay(recording, self.real_t(inputs.t))

    def _enqueue(self, state, after, tape, inputs, grad_after, grad, param_grad, mass_grad) -> None:
        """The launches of :meth:`run`, in order."""
        dev, R = self.device, self.real_t
        grid_args = self.grid_args
        particles = inputs.particles
        grids = dict(grid=tape.grid_mv, grid_v_bar=self.grid_v_bar, grid_bar=self.grid_bar)
        self._launch_g2p_adjoint(state, after, tape, inputs, grad_after, grad, grids)
        # p2g_adjoint writes v_bar, which p2g_flip_adjoint then reads and adds to
        bars = dict(grid_bar=self.grid_bar, x_bar=grad.x, v_bar=grad.v, C_bar=grad.C, tau_bar=self.tau_bar)
        particle_args = p2g_particle_args(R, state, tape, inputs)
        dev.launch(self.k_p2g, -(-self.n // SIMD_LANES), grid_args | particle_args | bars | dict(mass_bar=mass_grad))
        if self.k_flip is not None:
            self._launch_flip_adjoint(state, inputs, grad_after, grad, mass_grad)
        self.launch_stress_adjoint(
            inputs.dt,
            state.F,
            state.C,
            state.plastic,
            particles.material,
            particles.param,
            self.tau_bar,
            grad_after.F,
            grad_after.plastic,
            grad.F,
            grad.C,
            grad.plastic,
            param_grad,
        )

    def _launch_g2p_adjoint(self, state, after, tape, inputs, grad_after, grad, grids: dict) -> None:
        """G2P's adjoint: dL/dx into ``grad.x``, dL/d(grid v) into ``grid_v_bar`` (through the
        private grid copies and their column sum, or the slot records and a gather per node),
        then the grid update's adjoint into ``grid_bar`` (``grids``: the grid arrays it takes;
        in the gather's launch)."""
        R, grid_args = self.real_t, self.grid_args
        # v' read back as v_pic; with FLIP the kernel sums v_pic itself (any buffer will do)
        v_out = tape.grid_v if uses_flip(self.flip) else after.v
        args = dict(n=np.int32(self.n), dt=R(inputs.dt), t=R(inputs.t), flip=R(self.flip), x_in=state.x, v_out=v_out)
        args |= dict(release_time=inputs.particles.release_time, grid_v=tape.grid_v, grid_dv=tape.grid_dv)
        args |= dict(x_bar_out=grad_after.x, v_bar_out=grad_after.v, C_bar_out=grad_after.C, x_bar=grad.x)
        if self.gather:  # over the particles the forward sorted by cell
            if not tape.sorted_by_cell:
                raise ValueError("the gather adjoint needs a tape with the cell sort (SubstepKernels.empty_tape)")
            self.device.launch(self.k_g2p, self.n, grid_args | args | dict(order=tape.order, records=self.records))
            update = grid_args | inputs.grid_update_args(R) | grids
            self.device.launch(self.k_gather, self.nodes, update | dict(records=self.records, starts=tape.starts))
            return
        args |= dict(copies=np.int32(self.copies), chunk=np.int32(self.chunk))
        args |= dict(grid_v_bar_copies=self.grid_v_bar_copies, boxes=self.copy_boxes)
        self.device.launch(self.k_g2p, self.copies, grid_args | args, local_size=1)
        # the column sum of the copies into grid_v_bar, a row of nodes of the stacked grid (every
        # member's, mpm.h) a work-item, each copy inside its box
        nx, ny, nz = self.grid.resolution
        nx *= self.members
        rows = dict(nx=np.int32(nx), ny=np.int32(ny), nz=np.int32(nz), channels=np.int32(velocity_channels(self.flip)))
        copies = dict(copies=np.int32(self.copies), boxes=self.copy_boxes, grid_copies=self.grid_v_bar_copies)
        self.device.launch(self.k_sum, nx * ny, rows | copies | dict(grid=self.grid_v_bar))
        self.device.launch(self.k_grid, self.nodes, grid_args | inputs.grid_update_args(R) | grids)

    def _launch_flip_adjoint(self, state, inputs, grad_after, grad, mass_grad) -> None:
        """The PIC/FLIP blend's P2G adjoint: adds to ``grad``'s x, v, C and ``mass_grad``."""
        R, particles = self.real_t, inputs.particles
        args = dict(n=np.int32(self.n), t=R(inputs.t), flip=R(self.flip), x=state.x, v=state.v, C=state.C)
        args |= dict(mass=particles.mass, release_time=particles.release_time)
        args |= dict(v_bar_out=grad_after.v, grid_bar=self.grid_bar, x_bar=grad.x, v_bar=grad.v, C_bar=grad.C)
        self.device.launch(self.k_flip, self.n, self.grid_args | args | dict(mass_bar=mass_grad))

    def launch_stress_adjoint(
        self,
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
        """Enqueue the stress stage's adjoint on device arrays (or buffers): F_bar, plastic_bar
        written, C_bar and param_bar accumulated into (see kernels_cl/mpm/adjoint/stress_adjoint.cl)."""
        bars = dict(tau_bar=tau_bar, F_bar_out=F_bar_out, plastic_bar_out=plastic_bar_out, F_bar=F_bar, C_bar=C_bar)
        args = dict(plastic_in=plastic, material=material, param=param) | bars
        launch_stress(
            self, dt, F, C, args | dict(plastic_bar=plastic_bar, param_bar=param_bar), ("plastic_in", "material")
        )


__all__ = ["StateGrad", "SubstepAdjoint"]
