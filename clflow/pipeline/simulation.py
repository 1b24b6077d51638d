"""The objects' particles and the MPM simulator of a scene config, and differentiable runs.

The objects' Gaussians are the first particles (their centres, object by object), followed
by the particles that fill the inside (clflow.scene.filling), object by object; several
objects share one grid, where they collide, each particle with its object's material. Grid:
``simulation.grid_resolution`` nodes along the longest side of the configured domain or, by
default, of the box of all objects grown by 75% of its size (at least the wall cells + 1) on
every side. Either puts a ground collider GROUND_OFFSET cells above a node row: the default
domain reaches down below it, with as many more nodes as that takes; a configured domain
keeps its size and moves down by less than one cell (so a grid of any resolution over it
meets the ground alike).

Why the ground's place among the node rows matters: the boundary condition acts on the
nodes behind the plane, so how strongly the object's bottom layer couples to them depends on
where the plane cuts the cells. A 1 m elastic torus dropped 0.3 m rebounds 0.15 m higher at
frame 8 with the ground 0.1 cells above a node row than at 0.9 (32-node grid). Grids of 32
and 63 nodes agree far better at 0.75-0.9 cells than at 0.5 (flow difference at the truth:
torus 0.026-0.019 px against 0.068, plasticine block 0.021-0.017 against 0.047; a fluid
drop, 0.040-0.045 against 0.033, prefers 0.5 slightly); 0.75 keeps away from the plane on a
node row, where rounding decides (docs/history/benchmarks-2026-11.md, "Where the ground cuts the cells").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from clflow.errors import InputError
from clflow.materials import get_material
from clflow.mpm.constants import WALL_CELLS
from clflow.mpm.substep import Grid, check_grid_memory
from clflow.runtime import get_device
from clflow.scene.config import SceneConfig, split_parameter
from clflow.scene.filling import ObjectParticles, fill_object
from clflow.splat.gaussians import Gaussians

GROUND_OFFSET = 0.75  # cells between the ground plane and the node row below it


class SubstepLimitError(InputError):
    """A run would need more substeps per frame than ``simulation.max_substeps`` allows."""


def _fmt_point(values) -> str:
    return "(" + ", ".join(f"{float(v):.4g}" for v in values) + ")"


def check_forces(cfg: SceneConfig, positions: torch.Tensor, dtype: torch.dtype = torch.float32) -> list[torch.Tensor]:
    """Each force stage's particles, [N] bool masks (selected in the simulator's ``dtype``,
    as the simulator selects them); InputError for a stage whose region holds no particle or
    whose time window lies outside the simulated time (0 .. frames / fps)."""
    sim = cfg.simulation
    duration = sim.frames / sim.fps
    x = positions.to(dtype).double()  # as the simulator tests them (clflow.mpm.boundaries.DriverGroups)
    masks = []
    what = cfg.objects_word
    for i, stage in enumerate(cfg.forces):
        masks.append(stage.region.select(x))
        if not bool(masks[-1].any()):
            raise InputError(
                f"{cfg.source}: forces[{i}].region holds no particle of the {what} (the {what} spans "
                f"{_fmt_point(positions.min(0).values)} .. {_fmt_point(positions.max(0).values)} m "
                f"in the simulation frame, +y up)"
            )
        if stage.start >= duration:
            raise InputError(
                f"{cfg.source}: forces[{i}] starts at {stage.start:g} s, after the simulated "
                f"{duration:.4g} s ({sim.frames} frames at {sim.fps:g} fps): it would never act; "
                f"fix forces[{i}].start/end (seconds) or simulation.frames"
            )
    return masks


def substep_limit_message(
    cfg: SceneConfig,
    substeps: int,
    dt: float,
    limit: str,
    max_substeps: int,
    seconds_per_substep: float | None = None,
) -> str:
    """Why a run of ``substeps`` per frame is refused, and the ways out (a fixed substep beyond
    the stable one is none: plan_run refuses it)."""
    cost = ""
    if seconds_per_substep:
        frame = substeps * seconds_per_substep
        cost = f", about {frame:.3g} s per frame"
    return (
        f"{cfg.source}: the simulation needs {substeps} substeps per frame (dt = {dt:.3g} s, limited by "
        f"{limit}{cost}), beyond the limit of {max_substeps}; ways out: a softer proxy material (a lower "
        f"youngs_modulus or bulk_modulus, poissons_ratio <= 0.45), a coarser grid (a smaller "
        f"simulation.grid_resolution: dt grows with the cell size), or raise the limit "
        f"(--max-substeps N or simulation.max_substeps)"
    )


def check_substeps(cfg: SceneConfig, sim, max_substeps: int | None) -> None:
    """SubstepLimitError when ``sim`` takes more than ``max_substeps`` substeps per frame (the
    optimiser's check of each iteration: build_simulator(max_substeps=...))."""
    if max_substeps is not None and sim.substeps > max_substeps:
        raise SubstepLimitError(
            substep_limit_message(cfg, sim.substeps, sim.dt, sim.limit_reason(sim.state.v), max_substeps)
        )


def unstable_start(sim) -> str | None:
    """Why the substep of ``sim`` (a fixed one) is too long for its start: the stable step and
    what limits it; None when it is not (a run of such a step blows up or breaks the CFL limit)."""
    needed = sim.stable_substeps()
    if sim.substeps >= needed:
        return None
    return (
        f"above the stable step {sim.frame_dt / needed:.3g} s of the starting parameters "
        f"({sim.limit_reason(sim.state.v)}: {needed} substeps per frame)"
    )


@dataclass
class ObjectSetup:
    """Everything about the simulated objects that does not change between iterations.

    ``particles``: positions [M, 3] m, the objects' Gaussian centres first (object by object,
    in the config's order), then their fill particles (object by object); rest volume per
    particle [M] m^3 (each object its own).
    ``object_index``: [M] int64, each particle's object (an index into ``cfg.objects``)."""

    particles: ObjectParticles
    grid: Grid
    object_index: torch.Tensor


@dataclass(frozen=True)
class ObjectValues:
    """What a run gives one object: material parameters (SI, registry names), density
    (kg/m^3) and initial velocity ([3] m/s, simulation frame; a tuple or a tensor)."""

    params: dict[str, float]
    density: float
    velocity: tuple[float, float, float] | torch.Tensor


def simulation_grid(cfg: SceneConfig, lower: torch.Tensor, upper: torch.Tensor):
    """The background grid for an object spanning [lower, upper] (m, simulation frame)."""
    from clflow.mpm import Grid

    sim = cfg.simulation
    res = sim.grid_resolution
    if sim.domain_lower is not None:
        lo = torch.tensor(sim.domain_lower, dtype=torch.float64)
        hi = torch.tensor(sim.domain_upper, dtype=torch.float64)
        dx = float((hi - lo).max()) / (res - 1)
    else:
        # pad the object's box by 75 % of its size, and by at least the wall cells + 1
        size = float((upper - lower).max())
        inner = res - 1 - 2 * (WALL_CELLS + 1)
        if inner < 2:
            raise InputError(
                f"{cfg.source}: simulation.grid_resolution {res} is too small: the walls take "
                f"{2 * (WALL_CELLS + 1)} cells; use at least {2 * (WALL_CELLS + 1) + 3}"
            )
        dx = max(2.5 * size / (res - 1), size / inner)
        pad = max(0.75 * size, (WALL_CELLS + 1) * dx)
        lo, hi = lower - pad, upper + pad
    # a ground collider (normal +y) lies GROUND_OFFSET cells above a node row: the default
    # domain reaches down to that row (at least the wall cells + 1 below the ground); a
    # configured one keeps its size and is moved down by less than a cell
    grounds = [c.point[1] for c in cfg.colliders if c.normal[0] == c.normal[2] == 0.0 and c.normal[1] > 0]
    if grounds:
        ground = min(grounds)
        rows = math.ceil((ground - float(lo[1])) / dx - GROUND_OFFSET - 1e-6)
        below = ground - (rows + GROUND_OFFSET) * dx
        if sim.domain_lower is not None:
            hi[1] -= float(lo[1]) - below
        else:
            rows = max(WALL_CELLS + 1, rows)
            below = ground - (rows + GROUND_OFFSET) * dx
        lo[1] = below
    resolution = tuple(int(math.ceil(float(e) / dx - 1e-9)) + 1 for e in (hi - lo))
    return Grid(resolution, dx, tuple(float(v) for v in lo))


def setup_object(cfg: SceneConfig, obj: Gaussians, gaussian_objects: torch.Tensor | None = None) -> ObjectSetup:
    """Particles of the objects (their Gaussians ``obj`` in the simulation frame, object by
    object; ``gaussian_objects`` [n] each one's object, None: all the first's) and the grid,
    which holds all of them."""
    means = obj.means.detach().double()
    lower, upper = means.min(0).values, means.max(0).values
    grid = simulation_grid(cfg, lower, upper)
    check_grid_memory(get_device(), grid, itemsize=4)  # before the fill, whose own limit would blame its spacing
    covariances = obj.covariances.double()
    if gaussian_objects is None:
        gaussian_objects = torch.zeros(means.shape[0], dtype=torch.long)
    parts = []
    for k, o in enumerate(cfg.objects):
        mine = gaussian_objects == k
        parts.append(_particles(o.fill, grid, means[mine], covariances[mine], obj.opacities[mine]))
    # (object, rows): every object's Gaussian centres, then every object's fill particles
    pieces = [(k, p.positions[: p.n_gaussians]) for k, p in enumerate(parts)]
    pieces += [(k, p.positions[p.n_gaussians :]) for k, p in enumerate(parts)]
    particles = ObjectParticles(
        torch.cat([x for _, x in pieces]),
        sum(p.n_gaussians for p in parts),
        torch.cat([torch.full((len(x),), float(parts[k].volume), dtype=torch.float64) for k, x in pieces]),
    )
    object_index = torch.cat([torch.full((len(x),), k, dtype=torch.long) for k, x in pieces])
    inner_lo = torch.tensor(grid.origin, dtype=torch.float64) + (WALL_CELLS + 1) * grid.dx
    inner_hi = torch.tensor(grid.upper, dtype=torch.float64) - (WALL_CELLS + 1) * grid.dx
    x = particles.positions.double()
    if bool(((x < inner_lo) | (x > inner_hi)).any()):
        what = cfg.objects_word
        raise InputError(
            f"{cfg.source}: the {what} ({lower.tolist()} .. {upper.tolist()} m) does not fit inside "
            f"simulation.domain minus its walls ({inner_lo.tolist()} .. {inner_hi.tolist()} m)"
        )
    return ObjectSetup(particles, grid, object_index)


def _particles(fill, grid, means: torch.Tensor, covariances: torch.Tensor, opacities: torch.Tensor) -> ObjectParticles:
    """One object's particles: its Gaussians' centres, then (``fill`` enabled) the fill's."""
    if fill.enabled:
        spacing = fill.spacing or grid.dx / 2  # default: 8 particles per grid cell (per_axis 1)
        return fill_object(means, covariances, opacities, spacing, per_axis=fill.per_axis)
    lower, upper = means.min(0).values, means.max(0).values
    return ObjectParticles(means, means.shape[0], float(torch.prod(upper - lower)) / means.shape[0])


def build_simulator(
    cfg: SceneConfig,
    setup: ObjectSetup,
    values,
    *,
    dtype: torch.dtype = torch.float32,
    min_substeps: int = 1,
    max_substeps: int | None = None,
    time_scale: float = 1.0,
):
    """A :class:`clflow.mpm.Simulator` of the config's objects in one grid, each with its
    :class:`ObjectValues` (``values``, one per object in ``cfg.objects``' order; or, for a
    population of K runs in lockstep, clflow.mpm.population, K such lists); substeps from
    ``simulation.substep_dt``, else the stability limits of these values (the stiffest
    material and the fastest object decide) but at least ``min_substeps``; a frame
    ``time_scale`` / simulation.fps seconds (the video's clock, optimize.parameters'
    time_scale; 1: its stated frame rate). SubstepLimitError
    beyond ``max_substeps`` per frame (None: no limit); InputError for a force stage that
    holds no particle or never acts."""
    from clflow.mpm import Force, HalfSpace, MaterialSpec, Simulator

    single = isinstance(values[0], ObjectValues)
    members = [values] if single else list(values)
    for member in members:
        if len(member) != len(cfg.objects):
            raise ValueError(f"{len(member)} objects' values for the config's {len(cfg.objects)} objects")
    sim_cfg = cfg.simulation
    frame_dt = time_scale / sim_cfg.fps
    substeps = None if sim_cfg.substep_dt is None else max(1, math.ceil(frame_dt / sim_cfg.substep_dt - 1e-9))
    x = setup.particles.positions
    forces = []
    for stage, where in zip(cfg.forces, check_forces(cfg, x, dtype)):  # as the simulator would select them
        vec = list(stage.vector)
        forces.append(
            Force(
                where,
                stage.start,
                stage.end,
                force=vec if stage.kind == "force" else None,
                acceleration=vec if stage.kind == "acceleration" else None,
            )
        )
    colliders = [HalfSpace(c.point, c.normal, c.mode, c.friction, c.start, c.end) for c in cfg.colliders]

    def per_member(column: list[float]):  # one value where the members agree, else each member's
        return column[0] if all(c == column[0] for c in column) else column

    materials = []
    for k, o in enumerate(cfg.objects):
        params = {name: per_member([m[k].params[name] for m in members]) for name in members[0][k].params}
        density = per_member([m[k].density for m in members])
        materials.append(MaterialSpec(get_material(o.material.type).name, params, density, o.material.model))
    speeds = [torch.stack([torch.as_tensor(v.velocity, dtype=torch.float64).detach() for v in m]) for m in members]
    velocities = torch.stack([s[setup.object_index] for s in speeds])  # [K, M, 3]
    sim = Simulator(
        x,
        setup.particles.volume,
        materials,
        setup.grid,
        material_index=setup.object_index,
        velocities=velocities[0] if single else velocities,
        frame_dt=frame_dt,
        substeps=substeps,
        gravity=sim_cfg.gravity,
        boundaries=colliders,
        forces=forces,
        dtype=dtype,
        flip=sim_cfg.flip,
    )
    if substeps is None and sim.substeps < min_substeps:
        sim.use_substeps(min_substeps)
    check_substeps(cfg, sim, max_substeps)
    return sim


def run(simulator, frames: int, values: dict[str, torch.Tensor], velocity: torch.Tensor | None = None, reader=None):
    """Differentiable run (clflow.mpm.autograd.simulate) with the material parameters in
    ``values`` (registry name or "density" -> 0-d tensor, SI) and the initial velocity
    ``velocity`` ([3] m/s, simulation frame, given to every particle; default: the
    simulator's) as inputs; returns Frames (x, v [T+1, M, 3], F [T+1, M, 3, 3]), or (Frames,
    the reader's tensors) with a ``reader`` of the frames on the device (simulate's)."""
    from clflow.mpm.autograd import simulate

    params = {name: value for name, value in values.items() if name != "density"}
    velocities = None if velocity is None else particle_velocities(simulator, velocity)
    density = values.get("density")
    return simulate(
        simulator, frames, params=params or None, density=density, velocities=velocities, retries=2, reader=reader
    )


def particle_velocities(simulator, velocity: torch.Tensor) -> torch.Tensor:
    """[M, 3] initial velocities (m/s) of ``simulator``'s particles from ``velocity`` ([3], every
    particle's, or [M, 3]), with a fixed-order backward."""
    from clflow.mpm.run_inputs import per_particle

    return per_particle(velocity, simulator.n, "velocity", simulator.dtype, simulator.device, trailing=(3,))


def object_masks(setup: ObjectSetup, count: int) -> torch.Tensor:
    """[K, M] float64: 1 where particle m belongs to object k of ``count`` (a per-object value
    [K] times it, summed over k, is that value per particle with a fixed-order backward)."""
    return (setup.object_index[None, :] == torch.arange(count)[:, None]).double()


def scene_run_values(
    cfg: SceneConfig, setup: ObjectSetup, values, decoded: dict[str, torch.Tensor]
) -> dict[str, torch.Tensor]:
    """The inputs of :func:`run` for ``decoded`` (optimised name -> 0-d tensor, SI), by
    parameter: one that every object takes from the same tensor (the one object's) as it is;
    else per particle [M] (float64), every object's particles with its own value (``values``:
    the objects' ObjectValues for those not optimised), so that an object's parameter
    reaches only its own particles and its gradient comes from them alone (a masked sum: a
    fixed-order backward)."""
    by_param: dict[str, dict[int, torch.Tensor]] = {}
    for name, value in decoded.items():
        k, param = split_parameter(cfg.objects, name)
        by_param.setdefault(param, {})[k] = value
    count = len(cfg.objects)
    out = {}
    for param, given in by_param.items():
        if len(given) == count and len({id(v) for v in given.values()}) == 1:
            out[param] = next(iter(given.values()))
            continue
        fallback = float(next(iter(given.values())).detach())  # particles without the parameter ignore it
        fixed = [v.density if param == "density" else v.params.get(param, fallback) for v in values]
        per_object = torch.stack(
            [
                given[k].double() if k in given else torch.tensor(float(fixed[k]), dtype=torch.float64)
                for k in range(count)
            ]
        )
        out[param] = (per_object[:, None] * object_masks(setup, count)).sum(0)
    return out
