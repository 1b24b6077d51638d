"""The MLS-MPM simulator: particles, materials, boundaries and time settings -> trajectories.

from clflow.mpm import Simulator, MaterialSpec, Grid, HalfSpace
sim = Simulator(positions, volume=1e-6, materials=MaterialSpec("elastic", {"youngs_modulus": 1e5}),
                grid=Grid((64, 64, 64), dx=1 / 64), frame_dt=1 / 24)
traj = sim.run(frames=24)          # traj.x [25, N, 3] (m), frame 0 is the initial state
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np
import torch

from clflow.errors import ClflowError, InputError
from clflow.mpm.boundaries import DriverGroups, Force, GridCondition, boundary_table, wall_colliders
from clflow.mpm.constants import (
    CLAMP_MARGIN,
    COLLIDER_MODES,
    HEALTH_GROUPS,
    HEALTH_WG,
    MASS_EPS_REL,
    WALL_CELLS,
    kernel_defines,
)
from clflow.mpm.inputs import (
    MaterialLimits,
    MaterialSpec,
    particle_inputs,
    population_materials,
    release_time_array,
)
from clflow.mpm.population import check_forces_shared_mass, population_size, split_members, tile
from clflow.mpm.substep import (
    DriverAccelerations,
    Grid,
    Particles,
    State,
    SubstepInputs,
    SubstepKernels,
)
from clflow.runtime import Device, get_device
from clflow.runtime.arrays import DeviceArray, arrays_of, origin_device, real_of, to_cpu, to_device, to_origin
from clflow.runtime.plan import P2GMode

CFL_NUMBER = 0.3  # dt <= CFL_NUMBER dx / max|v|
WAVE_NUMBER = 0.5  # dt <= WAVE_NUMBER dx / c, c the fastest elastic wave speed
# dt <= VISCOUS_NUMBER rho dx^2 / mu, mu the explicit viscosity (material_model.explicit_viscosity);
# a margin below where a Newtonian block blows up (docs/mpm.md, "Safety")
VISCOUS_NUMBER = 0.2
PROGRESS_SECONDS = 5.0  # a frame that takes longer logs its progress this often

log = logging.getLogger("clflow.mpm")


class FrameProgress:
    """Logs where a long run stands (frame, substep, seconds) at most every PROGRESS_SECONDS,
    so a run of many substeps per frame does not look like a hang. Substeps are only enqueued:
    before it logs, it waits for ``device`` (when given) so that the figures are the device's."""

    def __init__(
        self,
        what: str,
        frames: int,
        substeps: int,
        every: float | None = None,
        first: int = 0,
        device: Device | None = None,
    ):
        self.what, self.frames, self.substeps, self.first, self.device = what, frames, substeps, first, device
        self.every = PROGRESS_SECONDS if every is None else every
        self.start = self.last = time.perf_counter()

    def tick(self, frame: int, substep: int) -> None:
        """Called after substep ``substep`` (0-based) of frame ``frame`` (counted from ``first``)."""
        frame -= self.first
        now = time.perf_counter()
        if now - self.last >= self.every:
            if self.device is not None:
                self.device.finish()
                now = time.perf_counter()
            self.last = now
            done = frame * self.substeps + substep + 1
            total = self.frames * self.substeps
            log.info(
                "%s: frame %d/%d, substep %d/%d, %.0f s so far, about %.0f s left",
                self.what,
                frame + 1,
                self.frames,
                substep + 1,
                self.substeps,
                now - self.start,
                (now - self.start) * (total - done) / done,
            )


class SimulationError(ClflowError):
    """A run produced NaN/inf; the message names the frame and the likely cause."""


class StabilityWarning(UserWarning):
    """The time step exceeds a stability limit (CFL, elastic wave speed or viscous diffusion)."""


@dataclass
class Trajectory:
    """Per-frame states; frame 0 is the initial state. x, v [T, N, 3] (m, m/s),
    F [T, N, 3, 3], plastic [T, N], time [T] (s), clamped [T] (particles clamped back into
    the domain during the frame). A population's states have the member axis after T:
    x [T, K, N, 3] (clflow.mpm.population)."""

    x: torch.Tensor
    v: torch.Tensor
    F: torch.Tensor
    plastic: torch.Tensor
    time: torch.Tensor
    clamped: torch.Tensor


def _walls(grid: Grid, walls: str, wall_cells: int, wall_friction: float) -> list[GridCondition]:
    """The domain's six walls as colliders, ``wall_cells`` cells in from the grid's faces."""
    if walls not in COLLIDER_MODES:
        raise InputError(f"walls {walls!r} unknown; choose one of {', '.join(COLLIDER_MODES)} or None")
    return wall_colliders(grid.origin, grid.upper, wall_cells, grid.dx, walls, wall_friction)


def _check_flip_and_dtype(flip: float, dtype: torch.dtype) -> None:
    if not (isinstance(flip, (int, float)) and 0.0 <= flip <= 1.0):
        raise InputError(f"flip (the PIC/FLIP blend) must be a number in [0, 1], got {flip!r}")
    if dtype not in (torch.float32, torch.float64):
        raise InputError(f"dtype must be torch.float32 or torch.float64, got {dtype}")


def _frame_dt(frame_dt: float) -> float:
    """The frame interval (s), checked positive and finite."""
    if not (frame_dt > 0 and math.isfinite(frame_dt)):
        raise InputError(f"frame_dt must be a positive number of seconds, got {frame_dt}")
    return float(frame_dt)


def _gravity(gravity: Sequence[float]) -> tuple[float, float, float]:
    """Gravity (m/s^2) as 3 finite floats."""
    g = tuple(float(c) for c in gravity)
    if len(g) != 3 or not all(math.isfinite(c) for c in g):
        raise InputError(f"gravity must be 3 finite numbers (m/s^2), got {gravity!r}")
    return g


@dataclass(frozen=True)
class SimulationSpec:
    """What a simulation is, apart from its evolving state; immutable (a changed substep
    count is a new spec) and shared by the plain and the differentiable runs: the particles'
    constant data, the grid, the boundary table [B, BC_STRIDE], the force drivers, gravity
    (m/s^2), the time between frames (s), the substeps per frame, the PIC/FLIP blend, the
    precision, each material's time-step limits and each particle's SI material values
    [N, PARAM_COUNT] (float64, in KERNEL_PARAMETERS order of its kernel material: what the
    kernel parameters were made from, and what a differentiable run's parameters replace)."""

    particles: Particles
    grid: Grid
    boundaries: torch.Tensor
    drivers: DriverGroups
    gravity: tuple[float, float, float]
    frame_dt: float
    substeps: int
    flip: float
    dtype: torch.dtype
    material_limits: tuple[MaterialLimits, ...]
    material_values: torch.Tensor

    @property
    def dt(self) -> float:
        """The substep (s)."""
        return self.frame_dt / self.substeps


def max_speed(v: torch.Tensor) -> float:
    """The fastest speed (m/s) of velocities ``v`` [N, 3] (m/s), 0 for none."""
    return float(v.double().norm(dim=-1).max()) if v.numel() else 0.0


@dataclass(frozen=True)
class StateHealth:
    """What a run checks of a state after each frame: whether every value of x, v, F is
    finite, and the fastest finite particle's speed (m/s)."""

    finite: bool
    max_speed: float

    def cfl_breach(self, dt: float, dx: float) -> float | None:
        """The fastest speed (m/s) when it moves more than CFL_NUMBER cells in ``dt`` (s) on a
        grid of spacing ``dx`` (m), else None."""
        return self.max_speed if self.max_speed * dt > CFL_NUMBER * dx else None


def state_health(device: Device, state: State) -> StateHealth:
    """The :class:`StateHealth` of ``state`` (DeviceArrays), reduced on the device: the host
    reads 2 HEALTH_GROUPS reals, not the state."""
    n, dtype = state.x.shape[0], state.x.dtype
    partial = DeviceArray.empty(device, (HEALTH_GROUPS, 2), dtype)
    kern = device.kernel("mpm/health.cl", "state_health", real_of(dtype), kernel_defines())
    args = dict(n=np.int32(n), x=state.x, v=state.v, F=state.F, partial=partial)
    device.launch(kern, HEALTH_GROUPS * HEALTH_WG, args, HEALTH_WG)
    speed2, bad = partial.read().double().unbind(-1)
    return StateHealth(not bool(bad.any()), math.sqrt(float(speed2.max())))


class Simulator:
    """MLS-MPM simulation of particles with per-particle materials on one OpenCL device: a
    :class:`SimulationSpec` (``spec``), the state it advances, and the substep kernels with
    their buffers (``kernels``, also used by the differentiable runs of clflow.mpm.autograd).

    The state, the particles' constant data and the boundary table live on the device
    (``device_state``, ``device_particles``); ``state`` is the host's view of the state, read
    when asked (in place on devices that share the host's memory), and in-place edits of
    it reach the device before the next substep.

    Args:
        positions: [N, 3] initial positions (m), inside the grid. The tensors given may live
            on any one torch device: they are copied to the host once, and run() returns
            the trajectory on that device.
        volume: rest volume per particle (m^3), a number or [N].
        materials: one :class:`MaterialSpec` or a list of them (then ``material_index`` [N]
            picks each particle's entry). A parameter or density given as K values makes a
            population of K members in lockstep (clflow.mpm.population).
        grid: the background :class:`Grid`.
        velocities: [N, 3] initial velocities (m/s), default 0; [K, N, 3]: each member's.
        frame_dt: time between output frames (s).
        substeps: substeps per frame; None chooses the smallest stable count.
        gravity: (m/s^2).
        walls: domain-wall mode ("separate", "slip", "sticky") or None for no walls;
            ``wall_cells`` thick, with Coulomb ``wall_friction``.
        boundaries: further grid conditions (HalfSpace, Box, RotatingCylinder).
        forces: :class:`~clflow.mpm.boundaries.Force` stages.
        release_times: [N] time (s) each particle is released (see layer_release_times).
        dtype: torch.float32 (default) or torch.float64.
        device: OpenCL device (default: clflow.runtime.get_device()).
        p2g: "auto" (the device's kernel plan: private grid copies on CPUs, the gather per
            node on GPUs; $CLFLOW_P2G overrides), "private", "gather" or "atomic".
        flip: PIC/FLIP blend in [0, 1]: the share of each particle's velocity that keeps its
            own value plus the grid's change (FLIP), the rest taken from the grid (APIC).
            0 is plain APIC, whose numerical dissipation grows with the substeps per frame
            (docs/mpm.md, "Transfers and time step").
    """

    def __init__(
        self,
        positions: torch.Tensor,
        volume: float | torch.Tensor,
        materials: MaterialSpec | Sequence[MaterialSpec],
        grid: Grid,
        *,
        material_index: torch.Tensor | None = None,
        velocities: torch.Tensor | None = None,
        frame_dt: float = 1.0 / 24.0,
        substeps: int | None = None,
        gravity: Sequence[float] = (0.0, -9.81, 0.0),
        walls: str | None = "separate",
        wall_friction: float = 0.0,
        wall_cells: int = WALL_CELLS,
        boundaries: Sequence[GridCondition] = (),
        forces: Sequence[Force] = (),
        release_times: torch.Tensor | None = None,
        dtype: torch.dtype = torch.float32,
        device: Device | None = None,
        p2g: P2GMode = "auto",
        flip: float = 0.0,
    ):
        _check_flip_and_dtype(flip, dtype)
        self.device = device or get_device()
        self._check_grid(grid)
        #: the torch device of the tensors given: where run() returns its trajectory
        self.origin = origin_device(
            positions, volume, velocities, material_index, release_times, what="Simulator: the tensors"
        )
        host = lambda t: to_cpu(t, self.device)  # noqa: E731
        positions, volume, velocities = host(torch.as_tensor(positions)), host(volume), host(velocities)
        material_index, release_times = host(material_index), host(release_times)
        batch = population_size(materials, velocities)
        #: the population's members (clflow.mpm.population; 1: a single run), and whether the
        #: inputs had a batch dimension (then the outputs have one)
        self.members, self.batched = batch or 1, batch is not None
        check_forces_shared_mass(forces, materials)
        x, v, vol = particle_inputs(positions, volume, velocities, grid, dtype, self.members)
        n, n_member = x.shape[0], positions.shape[0]
        material, param, si_values, density, plastic0, material_limits = population_materials(
            materials, material_index, n_member, dtype, self.members
        )
        mass = vol * density

        drivers = DriverGroups(forces, x[:n_member].double(), mass[:n_member])  # a member's; every member alike
        particles = Particles(
            mass=mass.to(dtype).contiguous(),
            volume=vol.to(dtype).contiguous(),
            material=material,
            param=param,
            group=tile(drivers.group, self.members).contiguous(),
            release_time=tile(release_time_array(release_times, n_member, dtype), self.members),
            mass_eps=MASS_EPS_REL * float(mass.min()),
        )
        eye = torch.eye(3, dtype=dtype).expand(n, 3, 3).contiguous()
        host_state = State(x, v, torch.zeros(n, 3, 3, dtype=dtype), eye, plastic0)

        walls_ = [] if walls is None else _walls(grid, walls, wall_cells, wall_friction)
        self.spec = SimulationSpec(
            particles,
            grid,
            boundary_table(walls_ + list(boundaries), dtype),
            drivers,
            _gravity(gravity),
            _frame_dt(frame_dt),
            1,
            float(flip),
            dtype,
            tuple(material_limits),
            si_values,
        )
        self.use_substeps(self._checked_substeps(substeps, v))
        self.time = 0.0
        self.frame = 0
        self.kernels = SubstepKernels(self.device, dtype, n, grid, particles.material, p2g, float(flip), self.members)
        # constant data: on zero-copy devices the host tensors' own memory
        self.device_particles = to_device(particles, self.device, alias=True)
        self.device_boundaries = DeviceArray.alias(self.device, self.spec.boundaries, "boundaries")
        self.accelerations = DriverAccelerations(self.device, drivers, dtype)
        self._state = to_device(host_state, self.device, alias=True)  # fresh tensors: their memory is the state's
        self._next = self._state.empty_like()
        self._clamped = DeviceArray.zeros(self.device, (n,), torch.uint8)
        self._progress: FrameProgress | None = None  # set while run() runs

    # -- validation -------------------------------------------------------------------------

    def _checked_substeps(self, substeps: int | None, v: torch.Tensor) -> int:
        """``substeps`` per frame (None: the stable number), warning when fewer than stable."""
        auto = self._stable_substeps(max_speed(v))
        if substeps is None:
            return auto
        if int(substeps) < 1:
            raise InputError(f"substeps must be >= 1, got {substeps}")
        if int(substeps) < auto:
            warnings.warn(
                f"dt = {self.frame_dt / int(substeps):.3g} s exceeds the stable limit {self.frame_dt / auto:.3g} s "
                f"({self.limit_reason(v)}); use substeps >= {auto} per frame (or substeps=None to choose it)",
                StabilityWarning,
                stacklevel=3,
            )
        return int(substeps)

    @staticmethod
    def _check_grid(grid: Grid) -> None:
        if len(grid.resolution) != 3 or any(int(r) < 2 * CLAMP_MARGIN + 3 for r in grid.resolution):
            raise InputError(f"grid resolution {grid.resolution} too small: need >= {2 * CLAMP_MARGIN + 3} per axis")
        if not (grid.dx > 0 and math.isfinite(grid.dx)):
            raise InputError(f"grid dx must be a positive length (m), got {grid.dx}")

    def _dt_limits(self, vmax: float) -> list[tuple[float, str]]:
        """(the largest stable dt (s), why) of each limit at the fastest speed ``vmax`` (m/s)."""
        dx = self.grid.dx
        limits = []
        for m in self.material_limits:
            if m.wave_speed > 0:
                limits.append(
                    (WAVE_NUMBER * dx / m.wave_speed, f"elastic wave speed {m.wave_speed:.3g} m/s of {m.name}")
                )
            if m.viscosity > 0:
                reason = f"viscous diffusion of {m.name}, viscosity {m.viscosity:.3g} Pa s at {m.density:.3g} kg/m^3"
                limits.append((VISCOUS_NUMBER * m.density * dx**2 / m.viscosity, reason))
        if vmax > 0:
            limits.append((CFL_NUMBER * dx / vmax, f"CFL with max speed {vmax:.3g} m/s"))
        return limits

    def stable_substeps(self, v: torch.Tensor | None = None) -> int:
        """Smallest substep count per frame meeting the CFL, elastic-wave and viscous limits at
        velocities ``v`` [N, 3] (m/s; None: the current state's, its fastest speed found on the
        device; a state not finite has no stable substep)."""
        if v is None:
            health = state_health(self.device, self.device_state)
            return self._stable_substeps(health.max_speed if health.finite else math.inf)
        return self._stable_substeps(max_speed(v))

    def _stable_substeps(self, vmax: float) -> int:
        limits = self._dt_limits(vmax)
        dt_max, reason = min(limits, default=(self.frame_dt, ""))
        if not dt_max > 0:  # a speed so large its square overflows: the run has blown up
            raise SimulationError(
                f"no stable time step is left ({reason}): the simulation blew up; use smaller "
                f"substeps (simulation.substep_dt) or check the material parameters and forces"
            )
        return max(1, math.ceil(self.frame_dt / dt_max * (1 - 1e-12)))

    def use_substeps(self, substeps: int) -> None:
        """Take ``substeps`` per frame from now on (>= 1; no stability check)."""
        if int(substeps) < 1:
            raise InputError(f"substeps must be >= 1, got {substeps}")
        self.spec = replace(self.spec, substeps=int(substeps))

    # the spec's fields, read through the simulator
    particles = property(lambda self: self.spec.particles, doc="Particles: the constant per-particle data")
    grid = property(lambda self: self.spec.grid, doc="Grid")
    boundaries = property(lambda self: self.spec.boundaries, doc="[B, BC_STRIDE] boundary table")
    drivers = property(lambda self: self.spec.drivers, doc="DriverGroups of the force stages")
    gravity = property(lambda self: self.spec.gravity, doc="(m/s^2)")
    frame_dt = property(lambda self: self.spec.frame_dt, doc="time between frames (s)")
    substeps = property(lambda self: self.spec.substeps, doc="substeps per frame")
    dt = property(lambda self: self.spec.dt, doc="the substep (s)")
    flip = property(lambda self: self.spec.flip, doc="PIC/FLIP blend")
    dtype = property(lambda self: self.spec.dtype, doc="torch.float32 or torch.float64")
    material_limits = property(lambda self: self.spec.material_limits, doc="MaterialLimits per material spec")

    def limit_reason(self, v: torch.Tensor) -> str:
        """What limits the substep at velocities ``v`` [N, 3] (m/s), in words."""
        return min(self._dt_limits(max_speed(v)), default=(0.0, "no limit"))[1]

    # -- stepping ---------------------------------------------------------------------------

    @property
    def n(self) -> int:
        return self._state.x.shape[0]

    @property
    def state(self) -> State:
        """The current state as host tensors (see the class docstring): edit it in place to
        change what the next substep starts from."""
        return State(*(a.host_view() for a in arrays_of(self._state)))

    @property
    def device_state(self) -> State:
        """The current state as DeviceArrays, with the host view's edits sent to the device."""
        for array in arrays_of(self._state):
            array.push_host_edits()
        return self._state

    def particle_arrays(self) -> list[DeviceArray]:
        """Every per-particle array the simulator keeps on its device (what its memory per
        particle counts): the current and the next state, the constant particle data, the
        kernels' per-particle scratch (tau, and U, s, V where an SVD kernel writes them) and
        the clamp flags [N] uint8."""
        arrays = arrays_of(self._state) + arrays_of(self._next) + arrays_of(self.device_particles)
        svd = [a for a in (self.kernels.U, self.kernels.s, self.kernels.V) if a.shape[0]]
        return arrays + [self.kernels.scratch.tau, *svd, self._clamped]

    def substep_inputs(self) -> SubstepInputs:
        """What the next substep reads besides the state (at the current time), on the device."""
        return SubstepInputs(
            self.device_particles,
            self.time,
            self.dt,
            self.gravity,
            self.device_boundaries,
            self.accelerations.at(self.time),
        )

    def step(self) -> None:
        """Advance one substep (dt seconds); the kernels are enqueued, not waited for."""
        self.kernels.run(self.device_state, self._next, self.substep_inputs(), self._clamped)
        for array in arrays_of(self._next):
            array.device_wrote()
        self._state, self._next = self._next, self._state
        self.time += self.dt

    def advance_frame(self, strict_cfl: bool = False) -> int:
        """Run one frame of substeps; returns how many particles were clamped into the domain
        at least once.

        Raises :class:`SimulationError` if the state became NaN/inf, or (``strict_cfl``) when
        it ends faster than the CFL limit allows (otherwise a StabilityWarning)."""
        self._clamped.zero_()
        v_before = self.device_state.v.clone()  # on the device; read only to explain a blow-up
        for s in range(self.substeps):
            self.step()
            if self._progress is not None:
                self._progress.tick(self.frame, s)
        self.frame += 1
        health = state_health(self.device, self.device_state)
        if not health.finite:
            v_before = v_before.read()
            raise SimulationError(
                f"the simulation became NaN/inf during frame {self.frame} (t = {self.time:.4g} s); likely cause: "
                f"dt = {self.dt:.3g} s is too large ({self.limit_reason(v_before)}; stable substeps per frame now: "
                f"{self.stable_substeps(v_before)}), or extreme material parameters / forces"
            )
        count = int(self._clamped.read().sum(dtype=torch.int64))
        if count:
            warnings.warn(
                f"frame {self.frame}: {count} particles left the grid and were clamped to "
                f"its boundary (enlarge the grid or add walls)",
                RuntimeWarning,
                stacklevel=2,
            )
        vmax = health.cfl_breach(self.dt, self.grid.dx)
        if vmax is not None:
            message = (
                f"frame {self.frame}: max speed {vmax:.3g} m/s breaks the CFL limit at dt = {self.dt:.3g} s; "
                f"use substeps >= {self.stable_substeps()}"
            )
            if strict_cfl:
                raise SimulationError(message)
            warnings.warn(message, StabilityWarning, stacklevel=2)
        return count

    def run(self, frames: int, on_frame: Callable[[int], None] | None = None, strict_cfl: bool = False) -> Trajectory:
        """Simulate ``frames`` frames, calling ``on_frame(k)`` after frame k (1-based); returns
        the :class:`Trajectory` (frames + 1 states). ``strict_cfl``: a frame that ends
        breaking the CFL limit raises SimulationError instead of warning."""
        if int(frames) < 0:
            raise InputError(f"frames must be >= 0, got {frames}")
        snaps = [self._snapshot(0)]
        self._progress = FrameProgress("simulation", int(frames), self.substeps, first=self.frame, device=self.device)
        try:
            for k in range(int(frames)):
                snaps.append(self._snapshot(self.advance_frame(strict_cfl)))
                if on_frame is not None:
                    on_frame(k + 1)
        finally:
            self._progress = None
        back = lambda t: to_origin(t, self.origin, self.device)  # noqa: E731
        states = lambda i: back(self._batch(torch.stack([s[i] for s in snaps])))  # noqa: E731
        return Trajectory(
            x=states(0),
            v=states(1),
            F=states(2),
            plastic=states(3),
            time=back(torch.tensor([s[4] for s in snaps], dtype=torch.float64)),
            clamped=back(torch.tensor([s[5] for s in snaps], dtype=torch.int64)),
        )

    def _batch(self, t: torch.Tensor) -> torch.Tensor:
        """[T, K N, ...] -> [T, K, N, ...] for a population given a batch dimension."""
        return split_members(t, self.members) if self.batched else t

    def _snapshot(self, clamped: int):
        s = self.state
        return s.x.clone(), s.v.clone(), s.F.clone(), s.plastic.clone(), self.time, clamped
