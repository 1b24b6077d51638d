"""Synthetic cases: a textured shape on a checkered floor, a material with ground-truth
parameters, forces (or a drop), a camera, and the guidance video rendered by clflow.

``make_case(folder, case, resolution)`` writes

- ``scene.ply``: procedural 3DGS Gaussians (metres, +y up): the shape's surface (flat
  Gaussians tangent to it; the pipeline fills the inside) and a static floor;
- ``config_truth.yaml``: the scene with the ground-truth material;
- ``guidance/000.png ...`` and ``guidance.mp4``: the ground-truth simulation seen by the
  guidance camera (lossless PNG frames);
- ``config.yaml``: the same scene starting from ``case.guess`` with ``optimize`` set to
  recover ``case.optimize`` from the guidance video's optical flow.

The bundled demo (datasets_tools/demo.py) is one case; benchmarks make others.
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from clflow.scene.config import FlowSettings

SHAPES = ("cube", "sphere", "torus")


@dataclass(frozen=True)
class Resolution:
    """Detail knobs: ``object_detail`` sets the shape's Gaussian count (about
    6 x object_detail^2), ``floor_side`` floor Gaussians per side, image side (px), grid
    nodes along the domain's longest side, frames, optimisation iterations."""

    object_detail: int = 14
    floor_side: int = 40
    image: int = 160
    grid: int = 24
    frames: int = 12
    iterations: int = 20


@dataclass(frozen=True)
class SyntheticCase:
    """A shape (``size``: cube side, sphere diameter or torus outer diameter, m) resting on
    the floor or ``lift`` m above it, made of ``material`` with ``truth`` (SI), density in
    kg/m^3; ``guess`` is the optimisation's start for the ``optimize`` parameters.
    ``forces`` are config force stages (see docs/scene_config.md) in metres relative to the
    shape's centre; ``camera`` position and target likewise, in units of ``size``."""

    shape: str = "cube"
    size: float = 0.2
    lift: float = 0.0
    material: str = "elastic"
    truth: dict[str, float] = field(default_factory=lambda: {"youngs_modulus": 2.0e4, "poissons_ratio": 0.3})
    guess: dict[str, float] = field(default_factory=lambda: {"youngs_modulus": 2.0e3})
    density: float = 1000.0
    optimize: tuple[str, ...] = ("youngs_modulus",)
    learning_rate: float = 0.2  # per iteration, in the optimiser's z units (decades for moduli)
    horizon: tuple[int, int] = (4, 1)  # frames in the first iteration's loss, frames added per iteration
    forces: tuple[dict, ...] = ()
    ground: str = "sticky"
    camera_offset: tuple[float, float, float] = (1.25, 1.75, 3.75)  # camera - centre, in sizes
    fov_y_deg: float = 40.0

    @property
    def center(self) -> np.ndarray:
        """The shape's centre at rest (m)."""
        height = self.size * (0.25 if self.shape == "torus" else 0.5)  # a torus lies flat
        return np.array([0.0, self.lift + height, 0.0])


def _checker(u: np.ndarray, v: np.ndarray, cells: int, a, b) -> np.ndarray:
    """RGB [n, 3] of a checkerboard with ``cells`` squares per unit of (u, v) in [0, 1]."""
    odd = (np.floor(u * cells) + np.floor(v * cells)).astype(int) % 2 == 1
    return np.where(odd[:, None], np.asarray(b, float), np.asarray(a, float))


OBJECT_COLOURS = ((0.95, 0.35, 0.25), (0.98, 0.85, 0.3))


def cube_surface(side: float, centre, n: int, rng: np.random.Generator):
    """Gaussians on the 6 faces of a cube, n x n per face: means [6n^2, 3] m, scales
    [6n^2, 3] m, rotations [6n^2, 3, 3] (identity), rgb [6n^2, 3]."""
    means, scales, rgb = [], [], []
    grid = (np.arange(n) + 0.5) / n  # face coordinates in (0, 1)
    uu, vv = [a.ravel() for a in np.meshgrid(grid, grid, indexing="ij")]
    spacing = side / n
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = np.zeros((uu.size, 3))
            others = [a for a in range(3) if a != axis]
            p[:, others[0]] = (uu - 0.5) * side
            p[:, others[1]] = (vv - 0.5) * side
            p[:, axis] = sign * side / 2
            s = np.full((uu.size, 3), 0.6 * spacing)
            s[:, axis] = 0.1 * spacing  # flat along the face normal
            means.append(p + np.asarray(centre))
            scales.append(s)
            rgb.append(_checker(uu, vv, 4, *OBJECT_COLOURS))
    means, scales, rgb = np.concatenate(means), np.concatenate(scales), np.concatenate(rgb)
    rgb = rgb * (0.9 + 0.1 * rng.random((len(rgb), 1)))  # a little grain helps the flow
    return means, scales, np.broadcast_to(np.eye(3), (len(means), 3, 3)).copy(), rgb


def _tangent_frames(normals: np.ndarray) -> np.ndarray:
    """Rotations [n, 3, 3] whose third column is the unit normal (first two: a tangent basis)."""
    helper = np.where(np.abs(normals[:, 1:2]) < 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(helper, normals)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    return np.stack([t1, t2, normals], axis=2)


def _flat_scales(count: int, area: float) -> np.ndarray:
    """Scales [count, 3] of flat Gaussians sharing ``area`` (m^2) evenly."""
    spacing = math.sqrt(area / count)
    return np.tile([0.7 * spacing, 0.7 * spacing, 0.1 * spacing], (count, 1))


def sphere_surface(diameter: float, centre, n: int, rng: np.random.Generator):
    """6 n^2 Gaussians on a sphere (Fibonacci lattice), flat along the normal."""
    count, r = 6 * n * n, diameter / 2
    k = np.arange(count) + 0.5
    polar, azimuth = np.arccos(1 - 2 * k / count), math.pi * (1 + 5**0.5) * k
    normals = np.stack([np.sin(polar) * np.cos(azimuth), np.cos(polar), np.sin(polar) * np.sin(azimuth)], 1)
    rgb = _checker((azimuth / (2 * math.pi)) % 1.0, polar / math.pi, 6, *OBJECT_COLOURS)
    rgb = rgb * (0.9 + 0.1 * rng.random((count, 1)))
    return (np.asarray(centre) + r * normals, _flat_scales(count, 4 * math.pi * r * r),
            _tangent_frames(normals), rgb)


def torus_surface(outer_diameter: float, centre, n: int, rng: np.random.Generator):
    """About 6 n^2 Gaussians on a torus lying flat (axis +y), tube radius = outer / 4."""
    a = outer_diameter / 4  # tube radius
    R = outer_diameter / 2 - a  # ring radius: R + a = outer / 2
    nu, nv = 3 * n, 2 * n
    u, v = [g.ravel() for g in np.meshgrid((np.arange(nu) + 0.5) / nu, (np.arange(nv) + 0.5) / nv, indexing="ij")]
    phi, theta = 2 * math.pi * u, 2 * math.pi * v
    ring = np.stack([np.cos(phi), np.zeros_like(phi), np.sin(phi)], 1)
    normals = np.cos(theta)[:, None] * ring + np.sin(theta)[:, None] * np.array([[0.0, 1.0, 0.0]])
    means = np.asarray(centre) + R * ring + a * normals
    # area element (R + a cos theta) dphi a dtheta: scale each Gaussian to its own patch
    patch = (2 * math.pi / nu) * (2 * math.pi * a / nv) * (R + a * np.cos(theta))
    spacing = np.sqrt(patch)[:, None]
    scales = np.concatenate([0.7 * spacing, 0.7 * spacing, 0.1 * spacing], 1)
    rgb = _checker(u, v, 6, *OBJECT_COLOURS) * (0.9 + 0.1 * rng.random((u.size, 1)))
    return means, scales, _tangent_frames(normals), rgb


SURFACES = {"cube": cube_surface, "sphere": sphere_surface, "torus": torus_surface}


def floor(size: float, n: int, height: float = 0.0):
    """Static floor Gaussians in the plane y = height: means, scales, rotations, rgb."""
    grid = (np.arange(n) + 0.5) / n
    uu, vv = [a.ravel() for a in np.meshgrid(grid, grid, indexing="ij")]
    means = np.stack([(uu - 0.5) * size, np.full(uu.size, height - 0.01), (vv - 0.5) * size], 1)
    spacing = size / n
    scales = np.tile([0.6 * spacing, 0.004, 0.6 * spacing], (uu.size, 1))
    rgb = _checker(uu, vv, 8, (0.85, 0.85, 0.85), (0.35, 0.4, 0.5))
    return means, scales, np.broadcast_to(np.eye(3), (uu.size, 3, 3)).copy(), rgb


def write_scene(folder: Path, case: SyntheticCase, resolution: Resolution, seed: int = 0) -> None:
    """Write the case's scene.ply: the shape's surface Gaussians, then the floor's."""
    from clflow.splat.gaussians import Gaussians, rgb_to_sh0, rotmat_to_quat
    from clflow.splat.ply import save_ply

    if case.shape not in SURFACES:
        raise ValueError(f"shape must be one of {', '.join(SHAPES)}, got {case.shape!r}")
    rng = np.random.default_rng(seed)
    parts = [SURFACES[case.shape](case.size, case.center, resolution.object_detail, rng),
             floor(6 * case.size, resolution.floor_side)]
    means, scales, rotations, rgb = (torch.from_numpy(np.concatenate(arrays)) for arrays in zip(*parts))
    g = Gaussians.from_activated(means.float(), rotmat_to_quat(rotations).float(), scales.float(),
                                 torch.full((means.shape[0],), 0.95), sh=rgb_to_sh0(rgb.float())[:, None, :])
    save_ply(folder / "scene.ply", g)


def push_upper_part(case_size: float = 0.2, acceleration: float = 12.0, duration: float = 0.12) -> dict:
    """A force stage that pushes the upper 40% of a shape resting on the floor along +x."""
    half = case_size
    return {"region": {"box": {"min": [-half, 0.1 * case_size, -half], "max": [half, half, half]}},
            "acceleration": [acceleration, 0.0, 0.0], "start": 0.0, "end": duration}


def _rounded(values) -> list[float]:
    return [round(float(v), 9) for v in values]


def case_config(case: SyntheticCase, resolution: Resolution, parameters: dict[str, float], optimize: bool) -> dict:
    """The case's scene config (as a dict; see clflow.scene.config)."""
    c, s = case.center, case.size
    margin = 0.025 * s
    half = s / 2 + margin
    height = (s / 4 if case.shape == "torus" else s / 2) + margin
    forces = []
    for stage in case.forces:  # regions relative to the centre -> absolute
        stage = copy.deepcopy(stage)
        box = stage["region"].get("box")
        if box is not None:
            box["min"], box["max"] = _rounded(np.add(box["min"], c)), _rounded(np.add(box["max"], c))
        forces.append(stage)
    config = {
        "splats": "scene.ply",
        "scene": {"scale": 1.0, "up": "+y"},
        "object": {"select": {"box": {"min": _rounded([c[0] - half, case.lift - margin, c[2] - half]),
                                      "max": _rounded([c[0] + half, c[1] + height, c[2] + half])}}},
        "material": {"type": case.material, "parameters": dict(parameters), "density": case.density},
        "forces": forces,
        "boundaries": {"ground": {"height": 0.0, "mode": case.ground}},
        "simulation": {"grid_resolution": resolution.grid, "fps": 24, "frames": resolution.frames},
        "camera": {"position": _rounded(c + s * np.asarray(case.camera_offset)),
                   "look_at": _rounded(c), "fov_y_deg": case.fov_y_deg,
                   "width": resolution.image, "height": resolution.image},
        "flow": asdict(FlowSettings()),  # the defaults, spelled out
        "output": "results",
    }
    if optimize:
        config["video"] = "guidance"
        config["optimize"] = {"parameters": list(case.optimize),
                              "learning_rates": {n: case.learning_rate for n in case.optimize},
                              "iterations": resolution.iterations,
                              "horizon": {"start": case.horizon[0], "step": case.horizon[1]}}
        config["evaluation"] = {"ground_truth": dict(case.truth)}
    return config


def make_case(folder: str | Path, case: SyntheticCase, resolution: Resolution = Resolution(), seed: int = 0) -> Path:
    """Write the case into ``folder`` (see module docstring); returns its ``config.yaml``."""
    import yaml

    from clflow.fileio import atomic_write_text
    from clflow.pipeline.forward import render_video, simulate_config
    from clflow.scene.config import parse_config

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_scene(folder, case, resolution, seed)
    truth = case_config(case, resolution, case.truth, optimize=False)
    atomic_write_text(folder / "config_truth.yaml", yaml.safe_dump(truth, sort_keys=False))
    result = simulate_config(parse_config(truth, str(folder / "config_truth.yaml"), folder))
    render_video(result, folder / "guidance", video=folder / "guidance.mp4")
    config = case_config(case, resolution, {**case.truth, **case.guess}, optimize=True)
    atomic_write_text(folder / "config.yaml", yaml.safe_dump(config, sort_keys=False))
    return folder / "config.yaml"


__all__ = ["Resolution", "SHAPES", "SyntheticCase", "case_config", "cube_surface", "floor", "make_case",
           "push_upper_part", "sphere_surface", "torus_surface", "write_scene"]
