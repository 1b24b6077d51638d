"""Differentiable MPM trajectories: :func:`simulate`, a torch autograd op whose backward runs
the hand-written adjoint kernels (clflow/mpm/adjoint.py) over the whole trajectory.

    sim = Simulator(x0, volume, MaterialSpec("elastic", {...}), grid, dtype=torch.float64)
    E = torch.tensor(2e5, dtype=torch.float64, requires_grad=True)
    frames = simulate(sim, 10, params={"youngs_modulus": E})   # frames.x [11, N, 3] (m)
    loss = ((frames.x[-1] - target) ** 2).sum()
    loss.backward()                                   # E.grad: exact trajectory gradient

Checkpointing: forward keeps one state per output frame; backward replays a frame's
substeps from its checkpoint (recording tau and the grids), then runs their adjoints in
reverse. Memory, in reals: (frames + 1) N 55 (checkpoints, outputs and their gradients)
+ substeps (34 N + 7 nodes) (one frame's replay) + adjoint scratch (memory_estimate,
docs/mpm_adjoint.md).

Checkpoints, replayed states, tapes and gradients stay on the device (DeviceArrays); the host
sees each frame's health (NaN/inf, the fastest speed: kernels_cl/mpm/health.cl), each frame's
x, v, F once (the op's outputs; with a reader, only when Frames is asked for them) and, in
backward, each frame's output gradients once and the gradients of the inputs that need them
at the end.

Parameter gradients are per particle; a global parameter (a 0-d tensor) is broadcast to
the particles with a backward that sums the rows in a fixed order
(clflow.runtime.reduction.sum_rows), so gradients are bit-identical across runs.

The op is a ``torch.autograd.Function`` rather than a ``torch.library.custom_op``: its
configuration (grid, boundary table, drivers, compiled kernels) is a :class:`Simulator`, not
a tensor.
"""

from __future__ import annotations

import dataclasses
import logging
import warnings
import weakref

import torch

from clflow.errors import InputError
from clflow.mpm.adjoint import StateGrad, SubstepAdjoint, g2p_adjoint_record_reals
from clflow.mpm.constants import PARAM_COUNT, grid_channels, velocity_channels
from clflow.mpm.material_model import KERNEL_PARAMETERS
from clflow.mpm.population import split_members
from clflow.mpm.run_inputs import (
    initial_state,
    masses,
    parameter_rows,
    per_particle,
    region_masses,
    stage_accelerations_of,
    stage_members,
)
from clflow.mpm.simulator import (
    FrameProgress,
    SimulationError,
    Simulator,
    StabilityWarning,
    state_health,
)
from clflow.mpm.substep import DriverAccelerations, State, SubstepInputs, SubstepTape, p2g_partial_reals
from clflow.runtime.arrays import DeviceArray, origin_device, to_cpu, to_origin
from clflow.runtime.reduction import sum_rows
from clflow.runtime.sort import counts_length


def read_states(states, name: str) -> torch.Tensor:
    """Field ``name`` ("x", "v" or "F") of each of ``states`` (device arrays), stacked on the host."""
    return torch.stack([getattr(state, name).read() for state in states])


class Frames:
    """Per-frame states of a differentiable run; frame 0 is the initial state.
    x, v [T+1, N, 3] (m, m/s), F [T+1, N, 3, 3] (deformation gradient), with the member axis
    after T for a population (x [T+1, K, N, 3]); ``substeps`` per frame that the run used
    (more than the simulator's after a NaN/CFL retry).

    ``states``: each frame's state on the device (the run's checkpoints and its last state),
    for readers that take the frames there (clflow.flow.scene_flow,
    clflow.pipeline.render.render_rgb_frames); None for a population or a run of tensors on
    another torch device. x, v or F given as None is read from the states when first asked
    for (a run with a reader: its gradient flows through the reader's tensors, not these)."""

    def __init__(
        self,
        x: torch.Tensor | None,
        v: torch.Tensor | None,
        F: torch.Tensor | None,
        substeps: int = 0,
        clamped: int = 0,
        cfl_violation: str | None = None,
        states: tuple[State, ...] | None = None,
    ):
        if states is None and (x is None or v is None or F is None):
            raise InputError("Frames: x, v and F are needed where there are no states to read them from")
        self._values = {"x": x, "v": v, "F": F}
        self.substeps = substeps
        # what makes the run untrustworthy though it finished: particles clamped at the grid's
        # edge (at least once in some frame) and the first CFL violation (a message; None: none)
        self.clamped, self.cfl_violation, self.states = clamped, cfl_violation, states

    def _value(self, name: str) -> torch.Tensor:
        value = self._values[name]
        if value is None:  # read once, from the device
            value = self._values[name] = read_states(self.states, name)
        return value

    x = property(lambda self: self._value("x"), doc="[T+1, N, 3] positions (m)")
    v = property(lambda self: self._value("v"), doc="[T+1, N, 3] velocities (m/s)")
    F = property(lambda self: self._value("F"), doc="[T+1, N, 3, 3] deformation gradients")

    def replace(self, x: torch.Tensor, v: torch.Tensor, F: torch.Tensor) -> Frames:
        """These frames with other values (a member's, or copies on another torch device) and
        no states on the device."""
        return Frames(x, v, F, self.substeps, self.clamped, self.cfl_violation)

    def __getstate__(self) -> dict:
        """A copy for another process (a Ray task, a pickle) keeps x, v, F (read now where they
        were not) and leaves the states on the device behind: device memory is this process's."""
        return {**self.__dict__, "_values": {name: self._value(name) for name in self._values}, "states": None}

    @property
    def unstable(self) -> str | None:
        """Why this run is not to be trusted (a CFL violation, particles clamped at the grid's
        edge), or None. A NaN/inf run raises SimulationError instead."""
        if self.cfl_violation:
            return self.cfl_violation
        if self.clamped:
            return f"{self.clamped} particles left the grid and were clamped to its boundary"
        return None


class _Engine:
    """Forward and adjoint kernels of one simulator (built once, reused by every run): the
    simulator's own substep kernels and their adjoint."""

    def __init__(self, sim: Simulator):
        self.forward = sim.kernels
        plan = sim.kernels.plan  # the forward's, with the P2G path it took
        materials = sim.particles.material
        self.adjoint = SubstepAdjoint(sim.device, sim.dtype, sim.n, sim.grid, materials, sim.flip, plan, sim.members)


log = logging.getLogger("clflow.mpm")
_ENGINES: "weakref.WeakKeyDictionary[Simulator, _Engine]" = weakref.WeakKeyDictionary()
#: share of a discrete device's memory a differentiable run may plan for (the rest: the
#: rasteriser's and the driver's own); beyond it backward replays frames in segments
DEVICE_MEMORY_SHARE = 0.8


def engine(sim: Simulator) -> _Engine:
    """The forward and adjoint kernels (with their buffers) that simulate() uses for ``sim``."""
    engine = _ENGINES.get(sim)
    if engine is None:
        engine = _ENGINES[sim] = _Engine(sim)
    return engine


class _Run:
    """One differentiable run: its spec (the simulator's at this run's substeps), and the
    checkpoints (on the device) its forward leaves for backward."""

    def __init__(
        self, sim: Simulator, frames: int, substeps: int, memory_budget: int | None = None, strict_cfl: bool = False
    ):
        self.sim, self.frames, self.engine, self.strict_cfl = sim, frames, engine(sim), strict_cfl
        self.device = sim.device
        self.spec = spec = dataclasses.replace(sim.spec, substeps=substeps)
        self.t0, self.substeps, self.dt = sim.time, substeps, spec.dt
        info = sim.device.info
        if memory_budget is None and not sim.device.zero_copy:  # a discrete device: its own memory bounds the run
            memory_budget, what = int(DEVICE_MEMORY_SHARE * info.global_mem_size), f"{info.label}'s memory"
        else:
            what = "memory_budget"
        self.segment = replay_segment(
            sim.n, sim.members * spec.grid.nodes, frames, substeps, spec.dtype, memory_budget, spec.flip, what=what
        )

    def time(self, frame: int, substep: int) -> float:
        return self.t0 + (frame * self.substeps + substep) * self.dt

    def inputs(self, frame: int, s: int) -> SubstepInputs:
        """What substep ``s`` of frame ``frame`` reads besides the state (this run's particles
        and stage accelerations)."""
        t = self.time(frame, s)
        spec = self.spec
        return SubstepInputs(self.particles, t, self.dt, spec.gravity, self.sim.device_boundaries, self.accel.at(t))

    def substep(self, state: State, out: State, frame: int, s: int, tape: SubstepTape | None = None) -> None:
        self.engine.forward.run(state, out, self.inputs(frame, s), self.clamped, tape=tape)

    def forward(self, param, mass, x0, v0, stage_accel) -> None:
        """Run the frames, keeping each frame's state on the device (``frame_states``); the host
        reads each frame's health (NaN/inf, the fastest speed), not the frame. x0, v0: None
        for the simulator's own state."""
        sim, T, n, dev = self.sim, self.frames, self.sim.n, self.device
        self.accel = DriverAccelerations(dev, self.spec.drivers, self.spec.dtype, stage_accel.detach().double())
        self.particles = dataclasses.replace(
            sim.device_particles,
            param=DeviceArray.alias(dev, param.detach(), "material parameters"),
            mass=DeviceArray.alias(dev, mass.detach(), "masses"),
        )
        self.clamped = DeviceArray.zeros(dev, (n,), torch.uint8)
        s0 = sim.device_state
        first = State(
            s0.x.clone() if x0 is None else DeviceArray.of(dev, x0.detach(), "positions"),
            s0.v.clone() if v0 is None else DeviceArray.of(dev, v0.detach(), "velocities"),
            s0.C.clone(),
            s0.F.clone(),
            s0.plastic.clone(),
        )
        self.checkpoints = [first]
        a, b = first.clone(), first.empty_like()
        self.cfl_violation, breaches = None, []
        progress = FrameProgress("differentiable run", T, self.substeps, device=dev)
        for f in range(T):
            for s in range(self.substeps):
                self.substep(a, b, f, s)
                a, b = b, a
                progress.tick(f, s)
            health = state_health(dev, a)
            if not health.finite:
                raise SimulationError(
                    f"the differentiable run became NaN/inf during frame {f + 1} "
                    f"(t = {self.time(f + 1, 0):.4g} s); reduce dt (substeps per frame now {self.substeps}) "
                    f"or the material stiffness / forces"
                )
            vmax = health.cfl_breach(self.dt, self.spec.grid.dx)
            if vmax is not None:
                message = (
                    f"differentiable run, frame {f + 1}: max speed {vmax:.3g} m/s breaks the CFL limit "
                    f"at dt = {self.dt:.3g} s ({self.substeps} substeps per frame)"
                )
                if self.strict_cfl:
                    raise SimulationError(message)
                breaches.append((f + 1, vmax))
                self.cfl_violation = self.cfl_violation or message
            if f + 1 < T:  # the last frame's state is never replayed from
                self.checkpoints.append(a.clone())
        self.frame_states = (*self.checkpoints, a)
        if breaches:  # one warning a run, not one a frame
            frames_text = (
                f"frame {breaches[0][0]}" if len(breaches) == 1 else f"{len(breaches)} frames from {breaches[0][0]}"
            )
            warnings.warn(
                f"{self.cfl_violation}; {frames_text} break it, at most {max(v for _, v in breaches):.3g} m/s",
                StabilityWarning,
                stacklevel=4,
            )
        clamped = self.clamped_count = int(self.clamped.read().sum(dtype=torch.int64))
        if clamped:
            warnings.warn(
                f"differentiable run: {clamped} particles left the grid and were clamped to its "
                f"boundary (no gradient flows along a clamped axis); enlarge the grid or add walls",
                RuntimeWarning,
                stacklevel=4,
            )

    def read_frames(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """x, v [T+1, N, 3] and F [T+1, N, 3, 3] of the run, read from its frame states."""
        return tuple(read_states(self.frame_states, name) for name in "xvF")

    def backward(self, grad_x, grad_v, grad_F, device_grads=None, needed=(True,) * 5):
        """The inputs' gradients (param, mass, x0, v0, stage accelerations; None for an input
        not ``needed``, whose gradient is not read from the device) from the frames' (host
        tensors [T+1, ...] or None) and, where given, ``device_grads(frame)``: (dL/dx [N, 3],
        dL/dF [N, 3, 3]) of a frame as device arrays of the run's dtype (or None), what a reader
        of the frames on the device gives."""
        sim, spec, n, S, dtype, dev = self.sim, self.spec, self.sim.n, self.substeps, self.spec.dtype, self.device
        k = self.segment
        adjoint = self.engine.adjoint
        grad, spare = StateGrad.zeros(dev, n, dtype), StateGrad.zeros(dev, n, dtype)
        param_grad = DeviceArray.zeros(dev, self.particles.param.shape, dtype)
        mass_grad = DeviceArray.zeros(dev, (n,), dtype)
        # driver stages: dt vbar summed per stage over the substeps it is active (P2G adds
        # m dt a to the momentum, so abar_p = dt vbar_p), reduced over its particles at the end
        stage_rows = [DeviceArray.zeros(dev, (n, 3), dtype) for _ in spec.drivers.forces]
        first = self.checkpoints[0]
        states = [None] + [first.empty_like() for _ in range(k)]
        tapes = [self.engine.forward.empty_tape() for _ in range(k)]
        starts = list(range(0, S, k))  # first substep of each segment
        # second level (only when a frame's replay exceeds the budget): segment start states
        segment_states = [first.empty_like() for _ in starts[1:]]
        scratch = [states[1], first.empty_like()] if segment_states else []

        def add_output_grads(frame: int) -> None:
            for g, acc in ((grad_x, grad.x), (grad_v, grad.v), (grad_F, grad.F)):
                if g is not None:
                    acc.add_(g[frame])
            for g, acc in zip(device_grads(frame) if device_grads else (), (grad.x, grad.F)):
                if g is not None:
                    acc.add_(g)

        progress = FrameProgress("adjoint", self.frames, S, device=dev)
        for f in reversed(range(self.frames)):
            add_output_grads(f + 1)
            if segment_states:  # replay the frame once, keeping each later segment's first state
                src = self.checkpoints[f]
                for s in range(starts[-1]):
                    dst = segment_states[(s + 1) // k - 1] if (s + 1) % k == 0 else scratch[s % 2]
                    self.substep(src, dst, f, s)
                    src = dst
            for j in reversed(range(len(starts))):
                states[0] = self.checkpoints[f] if j == 0 else segment_states[j - 1]
                steps = range(starts[j], min(starts[j] + k, S))
                for i, s in enumerate(steps):
                    self.substep(states[i], states[i + 1], f, s, tapes[i])
                for i, s in reversed(list(enumerate(steps))):
                    inputs = self.inputs(f, s)
                    adjoint.run(states[i], states[i + 1], tapes[i], inputs, grad, spare, param_grad, mass_grad)
                    grad, spare = spare, grad
                    for stage in torch.nonzero(spec.drivers.active(inputs.t)).flatten().tolist():
                        stage_rows[stage].add_(grad.v, alpha=self.dt)
                    progress.tick(self.frames - 1 - f, S - 1 - s)  # counted in the order the adjoint runs
        add_output_grads(0)
        stage_grad = torch.zeros(len(spec.drivers.forces), 3, dtype=dtype)
        for stage, rows in enumerate(stage_rows if needed[4] else ()):
            members = rows.read()[stage_members(sim, stage)].contiguous()
            stage_grad[stage] = sum_rows(members, dev).to(dtype)
        grads = (param_grad, mass_grad, grad.x, grad.v)
        return (*(g.read() if need else None for g, need in zip(grads, needed)), stage_grad if needed[4] else None)


def memory_estimate(
    n: int,
    nodes: int,
    frames: int,
    substeps: int,
    dtype: torch.dtype,
    segment: int | None = None,
    grid_copies: int = 0,
    flip: float = 0.0,
) -> int:
    """Bytes a differentiable run of n particles on ``nodes`` grid nodes holds at its peak:
    per frame + 1, the checkpoint, the returned x, v, F and their gradients (25 + 15 + 15
    reals per particle); the replay of ``segment`` substeps at once (default: a whole frame),
    each a state of 25 reals and tau of 9 per particle and grids of g = 7 reals per node
    (13 with a PIC/FLIP blend ``flip`` > 0), plus, when segment < substeps, the first state
    of every later segment and a scratch state (two-level checkpointing); the kernels'
    working buffers (two forward states, tau, grids; two state gradients, taubar, U s V,
    parameter and mass gradients, the grid adjoint and the sum of its copies: g per node; the
    GPU plan's cell sort, 2 ints per particle and about 1 per node, each tape's order and
    cell starts, 1 per particle and per node, the P2G blocks' tiles of sums, about 3.4 g per
    node, and the adjoint's records, counted in either plan); and ``grid_copies`` private grid copies of g
    reals per node (CPU path: P2G and its adjoint)."""
    itemsize = torch.tensor([], dtype=dtype).element_size()
    k = substeps if segment is None else segment
    g = grid_channels(flip) + velocity_channels(flip)  # reals per node: P2G grid, grid_v[, grid_dv]
    checkpoints = (frames + 1) * n * (25 + 15 + 15)
    replay = k * (n * (25 + 9) + g * nodes) + (n * 25 * (-(-substeps // k)) if k < substeps else 0)
    working = n * (2 * 25 + 9) + g * nodes + n * (2 * 25 + 9 + 21 + PARAM_COUNT + 1) + g * nodes
    records = p2g_partial_reals(nodes, flip) + n * g2p_adjoint_record_reals(flip)
    # bytes: the cell sort's int32 keys, ranks and counts, and each tape's order and cell starts
    # (the replay's k and the kernels' own)
    cell_sorts = 4 * (2 * n + counts_length(nodes) + (k + 1) * (n + nodes + 1))
    return itemsize * (checkpoints + replay + working + records + grid_copies * g * nodes) + cell_sorts


def replay_segment(
    n: int,
    nodes: int,
    frames: int,
    substeps: int,
    dtype: torch.dtype,
    memory_budget: int | None,
    flip: float = 0.0,
    what: str = "memory_budget",
) -> int:
    """Substeps replayed at once in backward: a whole frame when that fits ``memory_budget``
    (bytes; None: no limit), else the longest segment that does (two-level checkpointing).
    InputError when not even one substep at a time fits (``what`` names the budget)."""
    if memory_budget is None or memory_estimate(n, nodes, frames, substeps, dtype, flip=flip) <= memory_budget:
        return substeps
    for k in range(substeps - 1, 0, -1):
        if memory_estimate(n, nodes, frames, substeps, dtype, k, flip=flip) <= memory_budget:
            return k
    need = memory_estimate(n, nodes, frames, substeps, dtype, 1, flip=flip)
    raise InputError(
        f"{what} {memory_budget / 2**20:.1f} MiB is too small for {frames} frames of {n} "
        f"particles: the checkpoints and a one-substep replay need {need / 2**20:.1f} MiB; "
        f"simulate fewer frames or particles"
    )


class _Simulate(torch.autograd.Function):
    """A run as an op: outputs x, v, F, or, with a reader of its frames on the device (see
    :func:`simulate`'s ``reader``), the reader's tensors instead."""

    @staticmethod
    def forward(ctx, run: _Run, reader, param, mass, x0, v0, stage_accel):
        run.forward(param, mass, x0, v0, stage_accel)
        ctx.run, ctx.reader = run, reader
        ctx.set_materialize_grads(False)  # an output nothing used gives None: no zeros uploaded
        return run.read_frames() if reader is None else tuple(reader.forward(run.frame_states))

    @staticmethod
    def backward(ctx, *grads):
        run, reader = ctx.run, ctx.reader
        if reader is None:
            host_grads, device_grads = [None if g is None else g.contiguous() for g in grads], None
        else:
            host_grads = (None, None, None)
            device_grads = reader.backward(grads) if any(g is not None for g in grads) else None
            ctx.reader = None  # its device memory is given back
        needed = tuple(ctx.needs_input_grad[2:])
        return (None, None, *run.backward(*host_grads, device_grads=device_grads, needed=needed))


def simulate(
    simulator: Simulator,
    frames: int,
    *,
    params=None,
    density=None,
    positions=None,
    velocities=None,
    stage_accelerations=None,
    kernel_params=None,
    retries: int = 0,
    memory_budget: int | None = None,
    reader=None,
) -> Frames | tuple[Frames, tuple[torch.Tensor, ...]]:
    """Differentiable run of ``frames`` frames from the simulator's current state.

    Every keyword may be a tensor that requires grad; None keeps the simulator's value.

    Args:
        simulator: the :class:`Simulator` (any materials, boundaries, drivers); it is not advanced.
        frames: number of output frames (each ``simulator.substeps`` substeps).
        params: material parameters by registry name (clflow/materials.py, SI units: e.g.
            "youngs_modulus" Pa, "poissons_ratio", "yield_stress" Pa, "friction_angle" deg,
            "viscosity" Pa s), each global (0-d) or per particle [N]; a name applies to every
            particle whose material has it (KERNEL_PARAMETERS); the rest keep their values.
            For a population (clflow.mpm.population) N counts every member's particles, and
            a value may also be given per member [K].
        density: rho (kg/m^3), global, per member [K] or [N]: particle mass = rho x rest volume.
        positions, velocities: initial x [N, 3] (m) and v [N, 3] (m/s); for a population
            [K, N / K, 3] (each member's) or [N / K, 3] (shared).
        stage_accelerations: [S, 3] acceleration (m/s^2) of each driver stage (the simulator's
            ``forces``, in order). A stage given as a force F (N) on a region of mass M
            accelerates it by F / M: pass ``force / region_masses(simulator)[s]`` to
            differentiate with respect to the force.
        kernel_params: [N, PARAM_COUNT] kernel parameters (clflow.mpm.material_model.kernel_params),
            an alternative to params.
        retries: NaN/CFL guard: when a frame turns NaN/inf or breaks the CFL limit, halve dt
            (double the substeps per frame) and run again, at most this many times (logged
            at INFO: routine). The last attempt raises :class:`SimulationError` on
            NaN/inf and only warns on a CFL violation; Frames.cfl_violation and Frames.clamped
            (particles clamped at the grid's edge) record what it warned about.
        memory_budget: bytes the run may hold (see :func:`memory_estimate`); when a whole
            frame's replay does not fit, backward replays it in shorter segments from
            intermediate states (two-level checkpointing: one more forward pass per frame).

        reader: what reads the run's frames on the device in the same op (a renderer of its
            flow, clflow.flow.scene_flow.FlowReader): ``reader.forward(states)`` (one State
            of device arrays a frame) returns tensors; ``reader.backward(grads)`` (theirs)
            returns ``frame -> (dL/dx [N, 3], dL/dF [N, 3, 3])`` as device arrays of the
            run's dtype (or None), added to the frames' own gradients on the device. Then
            the result is (Frames, the reader's tensors); not for a population or tensors on
            another torch device.

    Returns:
        :class:`Frames` with x, v [frames + 1, N, 3] and F [frames + 1, N, 3, 3] (a population:
        [frames + 1, K, N / K, ...]), on the torch
        device of the tensors given (any one device: copied to the host once, gradients flow
        back, the copies counted in ``simulator.device.transfers``).
    """
    sim = simulator
    if int(frames) < 1:
        raise InputError(f"frames must be >= 1, got {frames}")
    tensors = dict(
        density=density,
        positions=positions,
        velocities=velocities,
        stage_accelerations=stage_accelerations,
        kernel_params=kernel_params,
    )
    origin = origin_device(*(params or {}).values(), *tensors.values(), what="simulate: the tensors")
    if reader is not None and (origin.type != "cpu" or sim.batched):
        raise InputError("simulate: a reader of the frames on the device takes one run of CPU tensors")
    if origin.type != "cpu":
        return _simulate_via_host(sim, frames, origin, params, tensors, retries=retries, memory_budget=memory_budget)
    param = parameter_rows(sim, params, kernel_params)
    mass = sim.particles.mass if density is None else masses(sim, density)
    x0, v0 = initial_state(sim, positions, velocities)
    stage_accel = stage_accelerations_of(sim, stage_accelerations)
    substeps = sim.substeps
    inputs = (param, mass, x0, v0, stage_accel)
    for _ in range(int(retries)):
        try:
            return _apply(_Run(sim, int(frames), substeps, memory_budget, strict_cfl=True), inputs, reader)
        except SimulationError as err:
            log.info("%s; retrying with %d substeps per frame", err, 2 * substeps)  # routine: the guard at work
            substeps *= 2
    return _apply(_Run(sim, int(frames), substeps, memory_budget), inputs, reader)


def _apply(run: _Run, inputs: tuple, reader):
    """The op of ``run`` on ``inputs`` (param, mass, x0, v0, stage accelerations): its Frames,
    and the reader's tensors where a reader is given (then the Frames read x, v, F from the
    device only when asked for)."""
    outputs = _Simulate.apply(run, reader, *inputs)
    values = outputs if reader is None else (None, None, None)
    out = Frames(
        *values,
        substeps=run.substeps,
        clamped=run.clamped_count,
        cfl_violation=run.cfl_violation,
        states=run.frame_states,
    )
    out = _member_axis(run.sim, out)
    return out if reader is None else (out, tuple(outputs))


def _member_axis(sim: Simulator, frames: Frames) -> Frames:
    """A batched simulator's frames with the member axis: x, v [T+1, K, N / K, 3], F [T+1, K, N / K, 3, 3]."""
    if not sim.batched:
        return frames
    k = sim.members
    return frames.replace(split_members(frames.x, k), split_members(frames.v, k), split_members(frames.F, k))


def _simulate_via_host(sim: Simulator, frames: int, origin: torch.device, params, tensors: dict, **options) -> Frames:
    """:func:`simulate` of tensors on torch device ``origin`` (not the CPU): run on their host
    copies, frames back on ``origin``; gradients flow back through the copies."""
    on_host = {name: to_cpu(t, sim.device) for name, t in tensors.items()}
    host_params = {name: to_cpu(value, sim.device) for name, value in (params or {}).items()} or None
    out = simulate(sim, frames, params=host_params, **on_host, **options)
    back = lambda t: to_origin(t, origin, sim.device)  # noqa: E731
    return out.replace(back(out.x), back(out.v), back(out.F))


__all__ = [
    "KERNEL_PARAMETERS",
    "Frames",
    "engine",
    "memory_estimate",
    "per_particle",
    "region_masses",
    "replay_segment",
    "simulate",
]
