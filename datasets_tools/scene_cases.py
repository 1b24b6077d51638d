"""Identification cases of several objects for ``clflow eval sysid``: textured
shapes, each its own material, simulated together in one grid on a sticky floor and seen by
one guidance camera; every object's parameters are identified from the one video, named
OBJECT.PARAM (``jelly.youngs_modulus``).

A case is made as the single-object cases are (clflow_datasets.synthetic): the truth
simulated and rendered ``truth_scale`` times finer (grid and image; its own particle
sampling and substep), the frames area-averaged down to the guidance's size, so that the
optimiser cannot reproduce the video exactly (no inverse crime).

    case = SceneCase(objects=(CaseObject("jelly", ...), CaseObject("heap", ...)))
    make_case(Path("out/cases/drop"), case, QUICK, truth_scale=2)  # clflow_datasets.synthetic
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from clflow.scene.config import FlowSettings
from clflow_datasets.synthetic import SURFACES, Resolution, _rounded, add_optimization, floor, surface_gaussians


@dataclass(frozen=True)
class CaseObject:
    """One shape of a case: ``size`` (cube side, sphere diameter, torus outer diameter, m)
    centred at ``position`` (m, +y up; the floor is y = 0), its ``material`` with ``truth``
    (SI), ``guess`` the start of its ``optimize`` parameters, its initial ``velocity`` (m/s)."""

    name: str
    shape: str = "cube"
    size: float = 0.2
    position: tuple[float, float, float] = (0.0, 0.1, 0.0)
    material: str = "elastic"
    truth: dict[str, float] = field(default_factory=dict)
    guess: dict[str, float] = field(default_factory=dict)
    optimize: tuple[str, ...] = ()
    density: float = 1000.0
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def half_height(self) -> float:
        return self.size / (4 if self.shape == "torus" else 2)  # a torus lies flat

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) corners of its box at rest (m)."""
        half = np.array([self.size / 2, self.half_height, self.size / 2])
        c = np.asarray(self.position, dtype=float)
        return c - half, c + half


@dataclass(frozen=True)
class SceneCase:
    """Several :class:`CaseObject` in one scene; ``spread``: room on each horizontal side of
    their common box, in units of its longest side. The optimiser's settings as
    clflow_datasets.synthetic.SyntheticCase's. ``truth``, ``guess`` and ``optimize`` are
    the objects' by OBJECT.PARAM; ``material`` names the objects' materials."""

    objects: tuple[CaseObject, ...]
    spread: float = 0.5
    learning_rate: float = 0.2
    horizon: tuple[int, int] = (0, 0)
    search: int = 0
    starts: int = 1
    refine: int = 0
    method: str = "adam"
    ground: str = "sticky"
    camera_offset: tuple[float, float, float] = (0.6, 0.9, 1.9)  # camera - centre, in extents
    fov_y_deg: float = 40.0

    @property
    def truth(self) -> dict[str, float]:
        return {f"{o.name}.{n}": v for o in self.objects for n, v in o.truth.items()}

    @property
    def guess(self) -> dict[str, float]:
        return {f"{o.name}.{n}": v for o in self.objects for n, v in o.guess.items()}

    @property
    def optimize(self) -> tuple[str, ...]:
        return tuple(f"{o.name}.{n}" for o in self.objects for n in o.optimize)

    @property
    def material(self) -> str:
        return " + ".join(o.material for o in self.objects)

    def object_of(self, name: str) -> tuple[CaseObject, str]:
        """(object, parameter) of OBJECT.PARAM."""
        obj, _, param = name.partition(".")
        return next(o for o in self.objects if o.name == obj), param

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lows, highs = zip(*(o.bounds() for o in self.objects))
        return np.min(lows, 0), np.max(highs, 0)

    ROOM: ClassVar[str] = "SceneCase.spread"  # what gives a case more room

    def make_scene(self, folder: Path, resolution: Resolution, seed: int = 0) -> None:
        """Write its scene.ply into ``folder``: each object's surface Gaussians (the second and later tinted
        otherwise), then the floor's."""
        from clflow.splat.ply import save_ply

        rng = np.random.default_rng(seed)
        parts = []
        for k, o in enumerate(self.objects):
            means, scales, rotations, rgb = SURFACES[o.shape](
                o.size, np.asarray(o.position), resolution.object_detail, rng
            )
            parts.append((means, scales, rotations, rgb if k % 2 == 0 else rgb[:, [2, 0, 1]]))
        lower, upper = self.bounds()
        parts.append(floor(3 * float((upper - lower).max()), resolution.floor_side))
        save_ply(folder / "scene.ply", surface_gaussians(parts))

    def make_config(
        self, resolution: Resolution, values: dict[str, float], optimize: bool, scale: int = 1, views: int = 1
    ) -> dict:
        """Its scene config (a dict) with ``values`` (OBJECT.PARAM -> SI, over the
        truth's); ``scale`` multiplies the grid (nodes - 1) and the image size; one guidance view
        (``views``: ValueError for more)."""
        if views != 1:
            raise ValueError("a case of several objects has one guidance view")
        lower, upper, nodes = scene_domain(self, resolution, scale)
        simulation = {
            "grid_resolution": nodes,
            "fps": 24,
            "frames": resolution.frames,
            "domain": {"min": lower, "max": upper},
        }
        if resolution.flip:
            simulation["flip"] = resolution.flip
        objects = []
        for o in self.objects:
            low, high = o.bounds()
            margin = 0.025 * o.size
            params = {**o.truth, **{n.partition(".")[2]: v for n, v in values.items() if n.startswith(f"{o.name}.")}}
            entry = {
                "name": o.name,
                "select": {
                    "box": {
                        "min": _rounded([low[0] - margin, low[1] - min(margin, 0.005), low[2] - margin]),
                        "max": _rounded(high + margin),
                    }
                },
                "material": {"type": o.material, "parameters": params, "density": o.density},
            }
            if any(o.velocity):
                entry["velocity"] = _rounded(o.velocity)
            objects.append(entry)
        config = {
            "splats": "scene.ply",
            "scene": {"scale": 1.0, "up": "+y"},
            "objects": objects,
            "boundaries": {"ground": {"height": 0.0, "mode": self.ground}},
            "simulation": simulation,
            "camera": scene_camera(self, resolution.image * scale),
            "flow": asdict(FlowSettings()),
            "output": "results",
        }
        if optimize:
            add_optimization(config, self, resolution, "guidance")
        return config


def scene_domain(case: SceneCase, resolution: Resolution, scale: int = 1) -> tuple[list[float], list[float], int]:
    """(domain min, domain max (m), grid nodes along its longest side): ``spread`` of room
    beside the objects' box, a quarter of its extent above, at the spacing the single-object cases'
    default domain (2.5 sizes across ``resolution.grid`` nodes) gives the objects' mean
    size, refined ``scale`` times."""
    from clflow.mpm.constants import WALL_CELLS
    from clflow.pipeline.simulation import GROUND_OFFSET

    lower, upper = case.bounds()
    extent = float((upper - lower).max())
    dx = 2.5 * float(np.mean([o.size for o in case.objects])) / (resolution.grid - 1)
    walls = (WALL_CELLS + 1) * dx
    room = case.spread * extent + walls
    lo = [lower[0] - room, -walls - GROUND_OFFSET * dx, lower[2] - room]
    hi = [upper[0] + room, upper[1] + 0.25 * extent + walls, upper[2] + room]
    longest = max(u - v for v, u in zip(lo, hi))
    nodes = int(math.ceil(longest / dx - 1e-9)) + 1
    return _rounded(lo), _rounded(hi), (nodes - 1) * scale + 1


def scene_camera(case: SceneCase, image: int) -> dict:
    """The guidance camera: looking at the objects' box centre from ``camera_offset`` extents."""
    lower, upper = case.bounds()
    c, extent = (lower + upper) / 2, float((upper - lower).max())
    return {
        "position": _rounded(c + extent * np.asarray(case.camera_offset)),
        "look_at": _rounded(c),
        "fov_y_deg": case.fov_y_deg,
        "width": image,
        "height": image,
    }


__all__ = ["CaseObject", "SceneCase", "scene_domain"]
