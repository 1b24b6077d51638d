"""Boundary conditions (grid side) and drivers (particle side) of a simulation, in SI units.

Grid side, evaluated in table order each substep where a node has mass:
  :class:`HalfSpace` colliders (sticky / slip / separate, Coulomb friction, time window),
  :class:`Box` velocity regions (fixed: velocity 0; moving: any velocity),
  :class:`RotatingCylinder` (propeller-like driver), and the domain walls.
Particle side: :class:`Force` stages on a region (a :class:`clflow.regions.Region` or a
boolean mask) in newtons or m/s^2, and layer release (:func:`layer_release_times`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence, Union

import torch

from clflow.errors import InputError
from clflow.mpm.constants import BC_BOX, BC_CYLINDER, BC_HALFSPACE, BC_STRIDE, COLLIDER_MODES
from clflow.regions import Region, vec3

Vec3 = Sequence[float]
INF = math.inf


def _unit(value, what: str) -> list[float]:
    v = vec3(value, what)
    norm = math.sqrt(sum(c * c for c in v))
    if norm == 0:
        raise InputError(f"{what} must not be the zero vector")
    return [c / norm for c in v]


def _window(start: float, end: float, what: str) -> list[float]:
    if math.isnan(start) or math.isnan(end) or end <= start:
        raise InputError(f"{what}: time window [{start}, {end}) is empty or not a number")
    return [float(start), float(end)]


def _record(kind: float, condition, what: str, *fields: list[float]) -> list[float]:
    """A boundary condition's kernel record: its ``kind``, its time window (``condition``'s
    start and end, checked as ``what``'s) and its ``fields`` in order."""
    return [kind] + _window(condition.start, condition.end, what) + [value for part in fields for value in part]


@dataclass(frozen=True)
class HalfSpace:
    """Collider filling {x : (x - point).normal < 0}; ``normal`` points into the free side.

    mode: "sticky" (v = 0), "slip" (normal velocity removed) or "separate" (removed only when
    moving into the collider); ``friction`` mu_f is Coulomb friction for slip/separate, acting
    while the node moves into the collider (it takes mu_f |v.n| off the tangential speed).
    Active for start <= t < end (s)."""

    point: Vec3
    normal: Vec3
    mode: str = "slip"
    friction: float = 0.0
    start: float = 0.0
    end: float = INF

    def record(self) -> list[float]:
        if self.mode not in COLLIDER_MODES:
            raise InputError(f"collider mode {self.mode!r} unknown; choose one of {', '.join(COLLIDER_MODES)}")
        if not (self.friction >= 0 and math.isfinite(self.friction)):
            raise InputError(f"collider friction must be a finite number >= 0, got {self.friction}")
        point, normal = vec3(self.point, "collider point"), _unit(self.normal, "collider normal")
        return _record(BC_HALFSPACE, self, "collider", point, normal, [COLLIDER_MODES[self.mode], float(self.friction)])


@dataclass(frozen=True)
class Box:
    """Grid nodes in the box [lower, upper] (m) move with ``velocity`` (m/s): a fixed region
    (velocity 0) or a moving one. Active for start <= t < end (s)."""

    lower: Vec3
    upper: Vec3
    velocity: Vec3 = (0.0, 0.0, 0.0)
    start: float = 0.0
    end: float = INF

    def record(self) -> list[float]:
        lo, hi = vec3(self.lower, "box lower"), vec3(self.upper, "box upper")
        if any(a > b for a, b in zip(lo, hi)):
            raise InputError(f"box lower {lo} is not below upper {hi}")
        return _record(BC_BOX, self, "box", lo, hi, vec3(self.velocity, "box velocity"))


@dataclass(frozen=True)
class RotatingCylinder:
    """Grid nodes in the cylinder (``center``, unit ``axis``, ``radius``, ``half_length``, m)
    rotate rigidly at ``angular_velocity`` (rad/s, right-handed about axis): a propeller
    driver. Active for start <= t < end (s)."""

    center: Vec3
    axis: Vec3
    radius: float
    half_length: float
    angular_velocity: float
    start: float = 0.0
    end: float = INF

    def record(self) -> list[float]:
        if not (self.radius > 0 and self.half_length > 0):
            raise InputError(f"cylinder radius and half_length must be > 0, got {self.radius}, {self.half_length}")
        if not math.isfinite(self.angular_velocity):
            raise InputError(f"cylinder angular_velocity must be finite, got {self.angular_velocity}")
        center, axis = vec3(self.center, "cylinder center"), _unit(self.axis, "cylinder axis")
        shape = [float(self.radius), float(self.half_length), float(self.angular_velocity)]
        return _record(BC_CYLINDER, self, "cylinder", center, axis, shape)


GridCondition = Union[HalfSpace, Box, RotatingCylinder]


def wall_colliders(lower: Vec3, upper: Vec3, cells: int, dx: float, mode: str, friction: float) -> list[HalfSpace]:
    """The six domain walls: nodes within ``cells`` cells of a face are inside a collider."""
    walls = []
    for axis in range(3):
        for sign, face in ((1.0, lower[axis] + cells * dx), (-1.0, upper[axis] - cells * dx)):
            point = [0.0, 0.0, 0.0]
            normal = [0.0, 0.0, 0.0]
            point[axis], normal[axis] = face, sign
            walls.append(HalfSpace(point, normal, mode, friction))
    return walls


def boundary_table(conditions: Sequence[GridCondition], dtype: torch.dtype) -> torch.Tensor:
    """[B, BC_STRIDE] table of the kernels (kernels_cl/mpm/grid.cl)."""
    table = torch.zeros(len(conditions), BC_STRIDE, dtype=torch.float64)
    for row, cond in enumerate(conditions):
        rec = cond.record()
        table[row, : len(rec)] = torch.tensor(rec, dtype=torch.float64)
    # inf time bounds stay inf in float32 too
    return table.to(dtype)


@dataclass(frozen=True)
class Force:
    """A driver stage: for start <= t < end (s) the particles of ``region`` are pushed by a
    total ``force`` (N, shared in proportion to mass: every particle gets F / M_region) or by
    an ``acceleration`` (m/s^2). Chain stages by giving consecutive time windows."""

    region: Region | torch.Tensor
    start: float
    end: float
    force: Vec3 | None = None
    acceleration: Vec3 | None = None

    def mask(self, x0: torch.Tensor) -> torch.Tensor:
        region = self.region
        if isinstance(region, torch.Tensor):
            if region.dtype != torch.bool or region.shape != x0.shape[:1]:
                raise InputError(
                    f"force region mask must be a bool tensor of shape [{x0.shape[0]}], "
                    f"got {region.dtype} {tuple(region.shape)}"
                )
            mask = region
        else:
            mask = region.select(x0)
        if not bool(mask.any()):
            raise InputError(f"force region {region!r} contains no particle")
        return mask

    def acceleration_of(self, region_mass: float) -> list[float]:
        """The stage's acceleration (m/s^2) given the region's total mass (kg)."""
        _window(self.start, self.end, "force")
        if (self.force is None) == (self.acceleration is None):
            raise InputError("a force stage needs exactly one of force (N) or acceleration (m/s^2)")
        if self.force is not None:
            return [f / region_mass for f in vec3(self.force, "force")]
        return vec3(self.acceleration, "acceleration")


class DriverGroups:
    """Particles grouped by which force stages act on them: group [N] int32 (-1: none) and,
    per substep, the acceleration table [groups, 3] (the sum of the active stages)."""

    def __init__(self, forces: Sequence[Force], x0: torch.Tensor, mass: torch.Tensor):
        n = x0.shape[0]
        self.forces = list(forces)
        if not self.forces:
            self.group = torch.full((n,), -1, dtype=torch.int32)
            self.members = torch.zeros(0, 0, dtype=torch.bool)
            self.stage_accel = torch.zeros(0, 3, dtype=torch.float64)
            return
        masks = torch.stack([f.mask(x0) for f in self.forces], 1)  # [N, S]
        self.stage_accel = torch.tensor(
            [f.acceleration_of(float(mass[m].double().sum())) for f, m in zip(self.forces, masks.T)],
            dtype=torch.float64,
        )
        members, inverse = torch.unique(masks, dim=0, return_inverse=True)  # [G, S], [N]
        inside = members.any(1)
        # group ids only for combinations that contain at least one stage
        ids = torch.cumsum(inside.long(), 0) - 1
        self.group = torch.where(inside[inverse], ids[inverse], -1).to(torch.int32)
        self.members = members[inside]

    def active(self, t: float) -> torch.Tensor:
        """[stages] 1.0 for each force stage acting at time t (s), else 0.0."""
        return torch.tensor([f.start <= t < f.end for f in self.forces], dtype=torch.float64)

    def accel(self, t: float, dtype: torch.dtype, stage_accel: torch.Tensor | None = None) -> torch.Tensor:
        """[groups, 3] acceleration (m/s^2) at time t: the sum of the active stages' accelerations
        ``stage_accel`` [stages, 3] (default: the stages' own) over each group's stages."""
        stage_accel = self.stage_accel if stage_accel is None else stage_accel.double()
        return ((self.members.double() * self.active(t)) @ stage_accel).to(dtype).contiguous()


def layer_release_times(
    x: torch.Tensor, layers: int, interval: float, axis: int = 1, top_first: bool = True
) -> torch.Tensor:
    """Release times [N] (s) that free the particles in ``layers`` equal slabs along ``axis``,
    one slab every ``interval`` seconds (the top slab at t = 0 when ``top_first``)."""
    if layers < 1 or not interval >= 0:
        raise InputError(f"layer release needs layers >= 1 and interval >= 0, got {layers}, {interval}")
    h = x[:, axis].double()
    lo, hi = float(h.min()), float(h.max())
    frac = (h - lo) / max(hi - lo, 1e-30)
    layer = torch.clamp((frac * layers).long(), max=layers - 1)
    order = (layers - 1 - layer) if top_first else layer
    return (order.double() * interval).to(x.dtype)
