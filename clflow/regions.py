"""The one region type: a box, a sphere or everything, selecting points by position.

The scene config produces it (``object.select``, ``forces[].region``), the object selection
uses it on the splat file's centres (scene units) and the simulator's :class:`Force` stages
on the particles' initial positions (m, simulation frame)::

    Region.box((0, 0.5, 0), (1, 1, 1)).select(x)   # [N] bool of points x [N, 3]
    Region.sphere((0.5, 0.5, 0.5), 0.05)
    Region("all")

Points on the boundary are inside. Lengths are in the units of the points they select.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch

from clflow.errors import InputError

Vec3 = tuple[float, float, float]
KINDS = ("box", "sphere", "all")


def vec3(value, what: str) -> list[float]:
    """``value`` as 3 finite floats, else :class:`InputError` naming ``what``."""
    try:
        out = [float(c) for c in value]
    except (TypeError, ValueError):
        raise InputError(f"{what} must be 3 numbers, got {value!r}") from None
    if len(out) != 3 or not all(math.isfinite(c) for c in out):
        raise InputError(f"{what} must be 3 finite numbers, got {value!r}")
    return out


@dataclass(frozen=True)
class Region:
    """A box (``lower`` <= x <= ``upper`` on every axis), a sphere (|x - ``center``| <=
    ``radius``) or everything (kind "all"); the fields a kind does not use stay 0."""

    kind: str  # "box" | "sphere" | "all"
    lower: Vec3 = (0.0, 0.0, 0.0)
    upper: Vec3 = (0.0, 0.0, 0.0)
    center: Vec3 = (0.0, 0.0, 0.0)
    radius: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise InputError(f"region kind {self.kind!r} unknown; choose one of {', '.join(KINDS)}")
        for name in ("lower", "upper", "center"):
            object.__setattr__(self, name, tuple(vec3(getattr(self, name), f"region {name}")))
        object.__setattr__(self, "radius", float(self.radius))
        if self.kind == "box" and any(lo > hi for lo, hi in zip(self.lower, self.upper)):
            raise InputError(f"region lower {list(self.lower)} is not below upper {list(self.upper)}")
        if self.kind == "sphere" and not (math.isfinite(self.radius) and self.radius >= 0):
            raise InputError(f"region radius must be a finite number >= 0, got {self.radius}")

    @classmethod
    def box(cls, lower: Sequence[float], upper: Sequence[float]) -> "Region":
        return cls("box", lower=lower, upper=upper)

    @classmethod
    def sphere(cls, center: Sequence[float], radius: float) -> "Region":
        return cls("sphere", center=center, radius=radius)

    def select(self, points: torch.Tensor) -> torch.Tensor:
        """Bool [N]: which points [N, 3] lie in the region (the bounds cast to the points' dtype)."""
        if self.kind == "box":
            lo = torch.tensor(self.lower, dtype=points.dtype, device=points.device)
            hi = torch.tensor(self.upper, dtype=points.dtype, device=points.device)
            return ((points >= lo) & (points <= hi)).all(-1)
        if self.kind == "sphere":
            c = torch.tensor(self.center, dtype=points.dtype, device=points.device)
            return ((points - c) ** 2).sum(-1) <= self.radius**2
        return torch.ones(points.shape[0], dtype=torch.bool, device=points.device)
