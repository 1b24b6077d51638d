"""One MLS-MPM substep on an OpenCL device: four stages with explicit inputs and outputs.

    trial_svd_simd: (F_n, C_n)                             -> U, s, V = svd3(F_tr)
    update_stress : (F_n, C_n, U, s, V, plastic_n, param)  -> F_n+1, plastic_n+1, tau
                    (update_stress_elastic_simd: both in one when all particles are elastic;
                    where P2G gathers in the GPU plan, update_stress[_elastic]_cells: the
                    SVD inline, and each particle keyed and counted by cell at x_n)
    p2g           : (x_n, v_n, C_n, tau, mass, volume)     -> grid [nodes, GRID_CH] (m, mv[, mv0])
                    (private grid copies, each zeroed and summed only in the box of nodes
                    its particles touch; a gather over blocks of cells, the particles sorted
                    by cell and each read once, whose sums the grid update adds; or atomics)
    grid_update   : (grid, boundary table, t)              -> grid_v [nodes, 3][, grid_dv]
    g2p           : (x_n[, v_n], grid_v[, grid_dv], release_time) -> x_n+1, v_n+1, C_n+1

(bracketed: with the PIC/FLIP blend, ``flip`` > 0; GRID_CH = constants.grid_channels).
State n is only read, so the adjoint can replay a substep from a checkpoint; tau, the grids
and the gather's cell sort go into a :class:`SubstepTape`, the caller's (to keep them for
the adjoint) or the kernels' own scratch one.

Everything a substep touches lives in device memory (:class:`~clflow.runtime.arrays.DeviceArray`):
the state, the particles' constant data, the boundary table, the driver accelerations and the
tape. A substep only enqueues kernels; it copies nothing between host and device and does not
wait for the device.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, fields

import numpy as np
import torch

from clflow.errors import DeviceError, InputError
from clflow.mpm.constants import (
    MATERIAL_IDS,
    SIMD_LANES,
    SVD_MATERIALS,
    grid_channels,
    kernel_defines,
    uses_flip,
    velocity_channels,
)
from clflow.runtime.arrays import DeviceArray, numpy_real, real_of
from clflow.runtime.binding import LaunchCache, Recording
from clflow.runtime.devices import Device
from clflow.runtime.plan import P2G_ENV, KernelPlan, P2GMode, kernel_plan
from clflow.runtime.profile import profiled_step
from clflow.runtime.sort import counting_sort, counts_length

MAX_GRID_COPIES = 16  # private P2G grids at most (memory: copies x nodes x 4 reals)
GRID_COPY_BUDGET = 1 << 30  # bytes all private grid copies may take together
#: Fixes the number of private P2G grid copies. The copies' sum order sets the last bits of a
#: CPU run, and their default number follows the device's compute units (PoCL's threads):
#: ``clflow sweep`` sets this in every task so a run limited to fewer threads than the machine
#: gives the same bits as the serial path (docs/sweep.md).
GRID_COPIES_ENV = "CLFLOW_P2G_COPIES"


def grid_copies(device: Device, copy_bytes: int, n: int) -> int:
    """Private grid copies (of ``copy_bytes`` each) for ``n`` particles, the same count for the
    forward P2G and the adjoint G2P scatter (and so the same summation order): the wanted
    count, at most MAX_GRID_COPIES, GRID_COPY_BUDGET bytes together and one per particle."""
    return max(1, min(wanted_grid_copies(device), MAX_GRID_COPIES, GRID_COPY_BUDGET // copy_bytes, n))


def wanted_grid_copies(device: Device) -> int:
    """Private P2G grid copies wanted on ``device``: $CLFLOW_P2G_COPIES, else 2 per compute unit."""
    fixed = os.environ.get(GRID_COPIES_ENV, "").strip()
    if fixed:
        if not fixed.isdigit() or int(fixed) < 1:
            raise InputError(f"${GRID_COPIES_ENV} must be a whole number >= 1, got {fixed!r}")
        return int(fixed)
    return max(2, 2 * device.info.compute_units)


@dataclass(frozen=True)
class Grid:
    """The background grid: ``resolution`` nodes per axis, spacing ``dx`` (m), node (0, 0, 0)
    at ``origin`` (m). The simulated domain is origin + [0, (resolution - 1) dx]."""

    resolution: tuple[int, int, int]
    dx: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def nodes(self) -> int:
        return int(np.prod(self.resolution))

    @property
    def upper(self) -> tuple[float, float, float]:
        return tuple(o + (n - 1) * self.dx for o, n in zip(self.origin, self.resolution))

    def kernel_args(self, real_t, members: int = 1) -> dict:
        """The grid's arguments of every MPM kernel (MPM_GRID_ARGS of kernels_cl/mpm/mpm.h):
        nodes per axis, the population's ``members`` (each on a grid like this one), dx and
        the origin (m)."""
        (nx, ny, nz), (ox, oy, oz) = (np.int32(n) for n in self.resolution), (real_t(o) for o in self.origin)
        return dict(nx=nx, ny=ny, nz=nz, members=np.int32(members), dx=real_t(self.dx), ox=ox, oy=oy, oz=oz)


def check_members(n: int, members: int) -> int:
    """``members`` (>= 1), checked to divide the ``n`` particles of a population into equal blocks."""
    if int(members) < 1 or n % int(members):
        raise InputError(f"a population of {members} members cannot split {n} particles into equal blocks")
    return int(members)


def p2g_path(device: Device, requested: P2GMode = "auto") -> str:
    """The P2G path a simulator on ``device`` takes when it asks for ``requested``: the
    plan's (clflow.runtime.plan.KernelPlan.with_p2g)."""
    return kernel_plan(device, requested).p2g


def check_device(device: Device, dtype: torch.dtype, p2g: P2GMode = "auto", differentiable: bool = False) -> None:
    """DeviceError, one line naming the device and what it lacks, unless ``device`` can run
    the simulator in ``dtype`` on the P2G path that asking for ``p2g`` takes and, when
    ``differentiable``, the adjoint (whose deterministic reductions accumulate in float64)."""
    info = device.info
    if not info.fp64 and (dtype == torch.float64 or differentiable):
        needs = "float64 simulation (--double)" if dtype == torch.float64 else "the adjoint's float64 reductions"
        raise DeviceError(
            f"{info.label} has no double precision (cl_khr_fp64), which {needs} needs; choose another device (--device)"
        )
    if dtype == torch.float64 and p2g_path(device, p2g) == "atomic" and not info.int64_atomics:
        raise DeviceError(
            f"{info.label} has no 64-bit atomics (cl_khr_int64_base_atomics), which the atomic P2G path needs in "
            f"float64; simulate in float32, or take the private path ({P2G_ENV}=private)"
        )


@dataclass
class State:
    """Particle state at one instant (SI): x, v [N, 3] (m, m/s), C, F [N, 3, 3] (affine velocity
    1/s, deformation gradient), plastic [N] (metal: yield stress gained, Pa; snow: J_P).
    Fields are torch tensors on the host, or DeviceArrays (``to_device(state, device)``) for
    the kernels."""

    x: torch.Tensor | DeviceArray
    v: torch.Tensor | DeviceArray
    C: torch.Tensor | DeviceArray
    F: torch.Tensor | DeviceArray
    plastic: torch.Tensor | DeviceArray

    def clone(self) -> "State":
        return State(*(getattr(self, f.name).clone() for f in fields(self)))

    def empty_like(self) -> "State":
        return State(*(_empty_like(getattr(self, f.name)) for f in fields(self)))


def _empty_like(t: torch.Tensor | DeviceArray) -> torch.Tensor | DeviceArray:
    return t.empty_like() if isinstance(t, DeviceArray) else torch.empty_like(t)


@dataclass
class Particles:
    """What stays constant during a run: mass, volume [N] (kg, m^3), material [N] int32
    (kernel ids), param [N, PARAM_COUNT] kernel parameters, group [N] int32 (driver group or
    -1), release_time [N] (s; a particle moves only from then on) and mass_eps (kg): grid
    nodes lighter than this are empty (MASS_EPS_REL x the lightest particle). Host tensors,
    or DeviceArrays for the kernels."""

    mass: torch.Tensor | DeviceArray
    volume: torch.Tensor | DeviceArray
    material: torch.Tensor | DeviceArray
    param: torch.Tensor | DeviceArray
    group: torch.Tensor | DeviceArray
    release_time: torch.Tensor | DeviceArray
    mass_eps: float


@dataclass(frozen=True)
class StressStage:
    """How the stress stage runs for a set of kernel material ids, for the forward and the
    adjoint alike: only the constitutive models present are compiled in (``mask``, the
    MATERIALS_PRESENT define); all fixed-corotated elastic takes one fused kernel (SVD
    included); otherwise the SVD of F_tr runs when a model needs it (``needs_svd``), then the
    models one particle per work-item. The fused and SVD kernels take the plan's stress shape
    (clflow.runtime.plan: SIMD lanes on CPU devices, a particle a work-item on GPUs)."""

    mask: int
    elastic_only: bool
    needs_svd: bool

    @staticmethod
    def of(materials: torch.Tensor) -> "StressStage":
        mask = sum(1 << int(m) for m in torch.unique(materials))
        elastic_only = mask == 1 << MATERIAL_IDS["elastic"]
        return StressStage(mask, elastic_only, not elastic_only and bool(mask & SVD_MATERIALS))

    def defines(self, flip: float) -> dict[str, object]:
        return {**kernel_defines(flip), "MATERIALS_PRESENT": self.mask}

    def kernels(self, device: Device, real: str, plan: KernelPlan, adjoint: bool = False):
        """(stress kernel, SVD kernel or None) of the forward or the ``adjoint`` stress stage on
        ``device`` in precision ``real``, in the shape of ``plan`` (SIMD lanes or a particle a
        work-item; a forward that also keys the particles by cell, the SVD inline, where the
        plan says so: KernelPlan.stress_keys_cells); built without the PIC/FLIP switch, which
        only the transfer kernels read, so blended and plain simulators share these programs."""
        defines = self.defines(0.0)
        stage = "stress_adjoint" if adjoint else "stress"
        build = lambda role: device.kernel(*plan.kernel(stage, role), real, defines)  # noqa: E731
        if plan.stress_keys_cells and not adjoint:
            return build("elastic_cells" if self.elastic_only else "models_cells"), None
        svd = build("svd") if self.needs_svd else None
        return build("elastic" if self.elastic_only else "models"), svd

    @staticmethod
    def svd_buffers(device: Device, n: int, dtype: torch.dtype) -> tuple[DeviceArray, DeviceArray, DeviceArray]:
        """U [n, 3, 3], s [n, 3], V [n, 3, 3] of svd3(F_tr) on ``device`` (n = 0 where no SVD
        kernel writes them)."""
        return tuple(DeviceArray.empty(device, shape, dtype) for shape in ((n, 3, 3), (n, 3), (n, 3, 3)))


class DriverAccelerations:
    """The driver groups' accelerations [groups, 3] (m/s^2) on the device: one array per set of
    active force stages, uploaded the first time that set is active, so that stepping copies
    nothing. ``stage_accel`` [stages, 3] (default: the stages' own) is this run's."""

    def __init__(self, device: Device, drivers, dtype: torch.dtype, stage_accel: torch.Tensor | None = None):
        self.device, self.drivers, self.dtype = device, drivers, dtype
        self.stage_accel = stage_accel
        self._tables: dict[tuple[bool, ...], DeviceArray] = {}

    def at(self, t: float) -> DeviceArray:
        """The accelerations at time ``t`` (s)."""
        key = tuple(bool(f.start <= t < f.end) for f in self.drivers.forces)  # the stages active (DriverGroups.active)
        table = self._tables.get(key)
        if table is None:
            accel = self.drivers.accel(t, self.dtype, self.stage_accel)
            table = self._tables[key] = DeviceArray.of(self.device, accel, "driver accelerations")
        return table


@dataclass(frozen=True)
class SubstepInputs:
    """What one substep reads besides the state, on the device: the particles' constant data
    (DeviceArrays), the time at its start ``t`` (s), its length ``dt`` (s), ``gravity``
    (m/s^2), the boundary table [B, BC_STRIDE] and the driver accelerations ``accel``
    [groups, 3] (m/s^2) during it."""

    particles: Particles
    t: float
    dt: float
    gravity: tuple[float, float, float]
    boundaries: DeviceArray
    accel: DeviceArray

    def grid_update_args(self, real_t) -> dict:
        """The grid update's (and its adjoint's) scalars: dt, t (s), gravity (m/s^2), mass_eps
        (kg), and the boundary table with its row count."""
        gx, gy, gz = (real_t(g) for g in self.gravity)
        scalars = dict(
            dt=real_t(self.dt), t=real_t(self.t), gx=gx, gy=gy, gz=gz, mass_eps=real_t(self.particles.mass_eps)
        )
        return scalars | dict(bc=self.boundaries, n_bc=np.int32(self.boundaries.shape[0]))


@dataclass
class SubstepTape:
    """What a substep writes besides the next state, and its adjoint reads (DeviceArrays):
    tau [N, 3, 3] (Kirchhoff stress, Pa), the grid [nodes, GRID_CH] (m, mv[, mv0]; kg,
    kg m/s), the grid velocities [nodes, 3] (m/s) and, with a PIC/FLIP blend, their change in
    the substep grid_dv [nodes, 3] (else [1, 3], unused); where P2G gathers, the particles
    sorted by cell (:class:`CellSort`): ``order`` [N] and ``starts`` [nodes + 1] int32 (else
    [1], unused), which the adjoint's gather reads instead of sorting again."""

    tau: DeviceArray
    grid_mv: DeviceArray
    grid_v: DeviceArray
    grid_dv: DeviceArray
    order: DeviceArray
    starts: DeviceArray

    @staticmethod
    def empty(
        device: Device, n: int, nodes: int, dtype: torch.dtype, flip: float = 0.0, sorted_by_cell: bool = False
    ) -> "SubstepTape":
        shapes = ((n, 3, 3), (nodes, grid_channels(flip)), (nodes, 3), (nodes if uses_flip(flip) else 1, 3))
        reals = [DeviceArray.empty(device, shape, dtype) for shape in shapes]
        sort_shapes = ((max(n, 1),), (nodes + 1,)) if sorted_by_cell else ((1,), (1,))
        return SubstepTape(*reals, *(DeviceArray.empty(device, shape, torch.int32) for shape in sort_shapes))

    @property
    def sorted_by_cell(self) -> bool:
        """Whether the tape holds a cell sort (the gather path's tapes)."""
        return self.starts.shape[0] > 1


def check_grid_memory(
    device: Device, grid: Grid, itemsize: int, flip: float = 0.0, plan: KernelPlan | None = None, members: int = 1
) -> None:
    """Refuse a grid whose node arrays do not fit ``device``: (m, mv[, mv0]) and v[, dv] per
    node (bracketed: PIC/FLIP blend ``flip`` > 0) of each of a population's ``members``, and
    where the P2G path taken (``plan``'s, default the device's) is the private one at least
    one copy of the first, where it is the gather its blocks' tiles of sums (p2g_partial_reals)."""
    from clflow.limits import format_bytes

    info, nodes, channels = device.info, members * grid.nodes, grid_channels(flip)
    path = (plan or kernel_plan(device)).p2g
    own = {"private": nodes * channels, "gather": p2g_partial_reals(nodes, flip)}.get(path, 0)
    total = itemsize * (nodes * (channels + velocity_channels(flip)) + own)
    largest = itemsize * max(nodes * channels, own)
    if total > info.global_mem_size or largest > info.max_mem_alloc_size:
        size = "x".join(str(int(r)) for r in grid.resolution)
        size += f" grid for each of {members} members" if members > 1 else " grid"
        raise InputError(
            f"a {size} ({nodes:,} nodes) needs {format_bytes(total)} of device memory, buffers up to "
            f"{format_bytes(largest)}; {info.name} has {format_bytes(info.global_mem_size)}, buffers up to "
            f"{format_bytes(info.max_mem_alloc_size)}: use a coarser grid (simulation.grid_resolution or "
            f"--grid) or a smaller simulation.domain"
        )


def launch_stress(owner, dt: float, F, C, args: dict, elastic_omits: tuple[str, ...], svd_inline: bool = False) -> None:
    """Enqueue a stress stage, forward or adjoint, of ``owner`` (:class:`SubstepKernels` or its
    adjoint: device, n, plan, k_stress, k_svd, U/s/V) from F and C: the per-particle kernel
    takes ``args`` after the SVD of the trial F (when k_svd), or computes the SVD itself
    (``svd_inline``: the forward's _cells kernels); an elastic-only kernel (SVD included)
    takes ``args`` less ``elastic_omits``. The SVD and elastic-only kernels run on SIMD lanes
    in the plan's "simd_lanes" shape, a particle a work-item in "plain"."""
    dev, n = owner.device, owner.n
    common = dict(n=np.int32(n), dt=owner.real_t(dt), F_in=F, C_in=C)
    lanes = -(-n // SIMD_LANES) if owner.plan.stress == "simd_lanes" else n
    if owner.elastic_only:
        dev.launch(owner.k_stress, lanes, common | {k: v for k, v in args.items() if k not in elastic_omits})
        return
    if owner.k_svd is not None:
        dev.launch(owner.k_svd, lanes, common | dict(U_out=owner.U, s_out=owner.s, V_out=owner.V))
    svd = {} if svd_inline else dict(U_in=owner.U, s_in=owner.s, V_in=owner.V)  # unread where no model needs it
    dev.launch(owner.k_stress, n, common | svd | args)


def p2g_particle_args(real_t, state: State, tape: SubstepTape, inputs: SubstepInputs) -> dict:
    """The particle arguments of the P2G kernels and of their adjoint (P2G_PARTICLE_ARGS of
    kernels_cl/mpm/mpm.h): n, dt, x, v, C, tau, mass, volume, group, accel."""
    p, n = inputs.particles, np.int32(state.x.shape[0])
    arrays = dict(x=state.x, v=state.v, C=state.C, tau=tape.tau, mass=p.mass, volume=p.volume, group=p.group)
    return dict(n=n, dt=real_t(inputs.dt)) | arrays | dict(accel=inputs.accel)


#: The gather P2G's blocks: P2G_BLOCK base cells a side, each block's tile of sums P2G_TILE
#: nodes a side, one work-item a tile node (mpm/p2g_gather.cl).
P2G_BLOCK = 4
P2G_TILE = P2G_BLOCK + 2


def p2g_blocks(grid: Grid, members: int = 1) -> int:
    """Blocks of the gather P2G (mpm/p2g_gather.cl blocks_along): a grid's base cells (its
    nodes less 2 a side) in P2G_BLOCK^3 blocks, for each of ``members`` grids."""
    return members * math.prod(-(-(int(r) - 2) // P2G_BLOCK) for r in grid.resolution)


@dataclass(frozen=True)
class CellOccupancy:
    """How particles fill a grid, the shape the cell-sorted kernels' time follows: the base
    cells (a stencil's lowest node, as mpm/cells.h keys them) that hold a particle, of
    ``cells``; the P2G_BLOCK^3 blocks that do, of ``blocks`` (the gather skips the others);
    the particles in an occupied cell (its run, which one work-item puts in order):
    median, 99th percentile and the longest."""

    particles: int
    cells: int
    occupied_cells: int
    blocks: int
    occupied_blocks: int
    run_median: float
    run_p99: float
    run_max: int

    def summary(self) -> str:
        return (
            f"{self.particles:,} particles in {self.occupied_cells:,} of {self.cells:,} cells "
            f"({self.occupied_blocks:,} of {self.blocks:,} blocks of {P2G_BLOCK}^3); particles a cell: median "
            f"{self.run_median:g}, 99th percentile {self.run_p99:g}, most {self.run_max:,}"
        )


def cell_occupancy(grid: Grid, x: torch.Tensor) -> CellOccupancy:
    """The :class:`CellOccupancy` of particles at ``x`` [N, 3] (m) in ``grid``: each counted in
    its stencil's base cell, floor((x - origin) / dx - 1/2) clamped to [0, resolution - 3] per
    axis as the kernels' make_stencil does."""
    extent = torch.tensor([int(r) - 2 for r in grid.resolution])
    xi = (x.double() - torch.tensor(grid.origin, dtype=torch.float64)) / grid.dx
    base = torch.minimum(torch.floor(xi - 0.5).long().clamp(min=0), extent - 1)
    cell = (base[:, 0] * extent[1] + base[:, 1]) * extent[2] + base[:, 2]
    runs = torch.unique(cell, return_counts=True)[1].double()  # the occupied cells' counts
    blocks_along = -(-extent // P2G_BLOCK)
    block = base // P2G_BLOCK
    block_id = (block[:, 0] * blocks_along[1] + block[:, 1]) * blocks_along[2] + block[:, 2]
    occupied = len(runs)
    runs = runs if occupied else torch.zeros(1, dtype=torch.float64)
    return CellOccupancy(
        particles=int(x.shape[0]),
        cells=int(extent.prod()),
        occupied_cells=occupied,
        blocks=p2g_blocks(grid),
        occupied_blocks=int(torch.unique(block_id).numel()),
        run_median=float(runs.median()),
        run_p99=float(torch.quantile(runs, 0.99)),
        run_max=int(runs.max()),
    )


def p2g_partial_reals(nodes: int, flip: float = 0.0) -> int:
    """Reals of the gather P2G's tiles of sums over a grid of ``nodes`` nodes: at most
    (P2G_TILE / P2G_BLOCK)^3 tile nodes a grid node (3.4), grid_channels(flip) reals each."""
    return -(-nodes * P2G_TILE**3 // P2G_BLOCK**3) * grid_channels(flip)


class CellSort:
    """The particles of a substep sorted by the cell of their stencil's base node, on the
    device, by counting sort (one pass; clflow.runtime.sort) into a tape's ``order`` [n]
    int32, the particles cell by cell, and ``starts`` [cells + 1] int32, the first slot of
    each of the ``cells`` (every member's grid nodes; mpm/cells.h), each cell's run left for the P2G's blocks to put in index
    order. The particles are keyed and counted by ``k_cells`` (particle_cells), or, when it
    is None, by the stress kernel (:meth:`key_args`); ``keys``, ``rank`` and ``counts`` are
    its scratch."""

    def __init__(self, device: Device, n: int, cells: int, k_cells=None):
        self.device, self.n, self.cells, self.k_cells = device, n, cells, k_cells
        self.keys, self.rank = (DeviceArray.empty(device, (max(n, 1),), torch.int32) for _ in range(2))
        self.counts = DeviceArray.empty(device, (counts_length(cells),), torch.int32)

    def key_args(self, x: DeviceArray) -> dict:
        """The arguments of a kernel that keys and counts the particles at ``x`` [n, 3] (m)
        (CELL_KEY_ARGS of mpm/cells.h, and x)."""
        return dict(x=x, key=self.keys, counts=self.counts, rank=self.rank)

    def sort(self, x: DeviceArray, grid_args: dict, tape: SubstepTape) -> None:
        """Enqueue the sort of the particles at ``x`` into ``tape``'s order and starts, after
        the zeroing of ``counts`` and, when k_cells is None, the kernel that counted them."""
        if self.k_cells is not None:
            self.device.launch(self.k_cells, self.n, grid_args | dict(n=np.int32(self.n)) | self.key_args(x))
        counting_sort(
            self.device, self.keys, self.n, self.cells, self.counts, self.rank, tape.order, tape.starts,
            counted=True, order_runs=False,
        )  # fmt: skip


class SubstepKernels:
    """The substep kernels of one device, precision, particle count, grid, set of material ids
    (``materials``: the kernel ids of the particles), P2G path asked for (``p2g``; ``plan``:
    the device's kernel plan with the path taken), PIC/FLIP blend ``flip`` (0: APIC) and
    population size (``members``: the n particles are ``members`` equal blocks in lockstep,
    each on its own copy of ``grid``; kernels_cl/mpm/mpm.h), with their scratch buffers (U, s,
    V of F_tr, the private P2G grid copies or the gather's tiles of sums, and a
    :class:`SubstepTape` for runs that keep none). ``count_reads``: the gather P2G counts the
    particles it reads from global memory into ``p2g_reads`` [1] int32 (tests check its
    design, one read a particle)."""

    def __init__(
        self,
        device: Device,
        dtype: torch.dtype,
        n: int,
        grid: Grid,
        materials: torch.Tensor,
        p2g: P2GMode = "auto",
        flip: float = 0.0,
        members: int = 1,
        count_reads: bool = False,
    ):
        import pyopencl as cl

        self.device, self.dtype, self.n, self.grid, self.flip = device, dtype, n, grid, float(flip)
        self.members, self.nodes = check_members(n, members), members * grid.nodes  # nodes: all members'
        channels = grid_channels(self.flip)
        self.real, self.real_t = real_of(dtype, "simulation"), numpy_real(dtype, "simulation")
        self.grid_args = grid.kernel_args(self.real_t, members)
        check_device(device, dtype, p2g)
        self.plan = plan = kernel_plan(device, p2g)
        self.p2g = p2g = plan.p2g
        stage = StressStage.of(materials)
        self.defines = defines = stage.defines(self.flip)  # the -D switches of its programs
        counting = defines | {"CLFLOW_COUNT_READS": 1} if count_reads and p2g == "gather" else defines
        k = lambda role: device.kernel(*plan.kernel("p2g", role), self.real, counting if role == "p2g" else defines)  # noqa: E731
        self.elastic_only = stage.elastic_only
        self.k_stress, self.k_svd = stage.kernels(device, self.real, plan)
        self.U, self.s, self.V = stage.svd_buffers(device, n if self.k_svd is not None else 0, dtype)
        # the private path's grid update sums the P2G copies too, a row of nodes a work-item;
        # the gather's the tiles of its blocks
        self.k_grid = k("grid")
        # the gather path runs G2P in slot order: neighbouring work-items read neighbouring nodes
        self.k_g2p = k("g2p")
        self.k_p2g = k("p2g")
        itemsize = torch.tensor([], dtype=dtype).element_size()
        check_grid_memory(device, grid, itemsize, self.flip, plan, members)
        grid_bytes = channels * self.nodes * itemsize
        self.p2g_reads = None
        if p2g == "private":
            self.copies = grid_copies(device, grid_bytes, n)
            self.chunk = -(-n // self.copies)
            self.grid_copies = cl.Buffer(device.context, cl.mem_flags.READ_WRITE, self.copies * grid_bytes)
            self.copy_boxes = DeviceArray.empty(device, (self.copies, 6), torch.int32)  # each copy's node box
        elif p2g == "gather":
            k_cells = None if plan.stress_keys_cells else k("cells")  # else the stress kernel keys them
            self.cells = CellSort(device, n, self.nodes, k_cells)
            self.blocks = p2g_blocks(grid, members)
            self.block_partials = DeviceArray.empty(device, (self.blocks * P2G_TILE**3, channels), dtype)
            self.block_counts = DeviceArray.empty(device, (self.blocks,), torch.int32)
            if count_reads:
                self.p2g_reads = DeviceArray.zeros(device, (1,), torch.int32)
        self.scratch = self.empty_tape()
        self.bound = LaunchCache()  # run()'s launches, bound per set of arrays

    def empty_tape(self) -> SubstepTape:
        """A tape for this kernels' substeps (with the cell sort where P2G gathers)."""
        return SubstepTape.empty(self.device, self.n, self.nodes, self.dtype, self.flip, self.p2g == "gather")

    def run(
        self,
        state: State,
        out: State,
        inputs: SubstepInputs,
        clamped: DeviceArray,
        tape: SubstepTape | None = None,
    ) -> None:
        """Enqueue the substep from ``state`` (time inputs.t) by inputs.dt into ``out`` (States
        of DeviceArrays); ``clamped`` uint8 [N] flags that G2P sets to 1 for particles it
        clamps; tau and the grids go into ``tape`` (default: ``self.scratch``). Its launches
        are bound on the first call with these arrays (clflow.runtime.binding); later calls
        set the time and enqueue them."""
        tape = tape or self.scratch
        with profiled_step(self.device, "substep"):
            objects = (state, out, tape, inputs.particles, inputs.boundaries, inputs.accel, clamped)
            enqueue = lambda: self._enqueue(state, out, inputs, clamped, tape)  # noqa: E731
            recording = self.bound.recording(self.device, objects, (inputs.dt, inputs.gravity), enqueue)
            self.device.replay(recording, self.real_t(inputs.t))

    def record(
        self, state: State, out: State, inputs: SubstepInputs, clamped: DeviceArray, tape: SubstepTape | None = None
    ) -> Recording:
        """The launches of :meth:`run` with these arguments, bound and not enqueued
        (clflow.runtime.binding): what a replay enqueues, and how many launches a substep makes."""
        with self.device.recording() as recording:
            self._enqueue(state, out, inputs, clamped, tape or self.scratch)
        return recording

    def _enqueue(self, state: State, out: State, inputs: SubstepInputs, clamped: DeviceArray, tape: SubstepTape):
        """The launches of :meth:`run`, in order."""
        dev, R, n = self.device, self.real_t, np.int32(self.n)
        grid_args = self.grid_args
        particles = inputs.particles
        gather = self.p2g == "gather"
        if gather:
            self.cells.counts.zero_()  # the counts the cell keys add to
        outputs = dict(F_out=out.F, plastic_out=out.plastic, tau_out=tape.tau)
        stress_args = dict(plastic_in=state.plastic, material=particles.material, param=particles.param) | outputs
        keys_cells = self.plan.stress_keys_cells  # the gather's keys counted by the stress kernel
        if keys_cells:
            stress_args |= grid_args | self.cells.key_args(state.x)
        launch_stress(self, inputs.dt, state.F, state.C, stress_args, ("material",), svd_inline=keys_cells)
        p2g_args = grid_args | p2g_particle_args(R, state, tape, inputs)
        grids = dict(grid=tape.grid_mv, grid_v=tape.grid_v, grid_dv=tape.grid_dv)
        grid_update_args = grid_args | inputs.grid_update_args(R) | grids
        if self.p2g == "private":
            copies = dict(copies=np.int32(self.copies), grid_copies=self.grid_copies, boxes=self.copy_boxes)
            dev.launch(self.k_p2g, self.copies, p2g_args | copies | dict(chunk=np.int32(self.chunk)), local_size=1)
            nx, ny, _ = self.grid.resolution
            dev.launch(self.k_grid, self.members * nx * ny, grid_update_args | copies)  # rows of the stacked grid
        elif gather:
            self.cells.sort(state.x, grid_args, tape)
            blocks = dict(partials=self.block_partials, block_counts=self.block_counts)
            reads = {} if self.p2g_reads is None else dict(reads=self.p2g_reads)
            cells = dict(starts=tape.starts, order=tape.order)
            dev.launch(self.k_p2g, self.blocks * P2G_TILE**3, p2g_args | cells | blocks | reads, local_size=P2G_TILE**3)
            dev.launch(self.k_grid, self.nodes, grid_update_args | blocks)
        else:
            tape.grid_mv.zero_()  # on the device, in queue order: the atomics add onto zeros
            dev.launch(self.k_p2g, self.n, p2g_args | dict(grid=tape.grid_mv))
            dev.launch(self.k_grid, self.nodes, grid_update_args)
        g2p = dict(n=n, dt=R(inputs.dt), t=R(inputs.t), flip=R(self.flip), x_in=state.x, v_in=state.v)
        if gather:
            g2p["order"] = tape.order
        g2p |= dict(grid_v=tape.grid_v, grid_dv=tape.grid_dv, release_time=particles.release_time)
        g2p |= dict(x_out=out.x, v_out=out.v, C_out=out.C, clamped=clamped)
        dev.launch(self.k_g2p, self.n, grid_args | g2p)
