"""A tiny splat scene of two objects for the scene-config tests that need no demo: an
elastic cube above a low sand heap, each a solid lattice of Gaussians, plus a few static
Gaussians off to the side (scene units = metres, +y up)."""

from __future__ import annotations

import copy
from pathlib import Path

import torch
import yaml

from clflow.splat.gaussians import Gaussians
from clflow.splat.ply import save_ply

CUBE = ((-0.08, 0.22, -0.08), (0.08, 0.38, 0.08))  # the cube's box: 6^3 lattice, its surface
HEAP = ((-0.2, 0.02, -0.2), (0.2, 0.12, 0.2))  # the heap's box: 10 x 3 x 10 lattice, its surface
STATIC = ((0.5, 0.0, 0.5), (0.6, 0.1, 0.6))  # a few static Gaussians, outside both


def shell(lower, upper, counts) -> torch.Tensor:
    """The outer layer of a regular lattice of ``counts`` points per axis, cell-centred in
    [lower, upper]: Gaussians on the surface, as 3DGS places them (the fill adds the inside)."""
    index = torch.stack(torch.meshgrid(*[torch.arange(n) for n in counts], indexing="ij"), -1).reshape(-1, 3)
    top = torch.tensor(counts) - 1
    outer = ((index == 0) | (index == top)).any(-1)
    lo, hi = torch.tensor(lower, dtype=torch.float64), torch.tensor(upper, dtype=torch.float64)
    return lo + (hi - lo) * (0.5 + index[outer].double()) / torch.tensor(counts)


def write_scene(folder: Path) -> Path:
    """``folder/scene.ply``: the cube's, the heap's and the static Gaussians (in that order)."""
    parts = [shell(*CUBE, (6, 6, 6)), shell(*HEAP, (10, 3, 10)), shell(*STATIC, (2, 2, 2))]
    colours = [(0.9, 0.2, 0.2), (0.8, 0.7, 0.4), (0.3, 0.3, 0.3)]
    points = torch.cat(parts)
    colours = torch.cat([torch.tensor([c], dtype=torch.float64).expand(len(p), 3) for c, p in zip(colours, parts)])
    folder.mkdir(parents=True, exist_ok=True)
    save_ply(folder / "scene.ply", Gaussians.from_points(points, colours, scale=0.015, opacity=0.8))
    return folder / "scene.ply"


def box(lower, upper, margin: float = 0.01) -> dict:
    """A config's ``select: {box: ...}`` around [lower, upper], grown by ``margin``."""
    return {"box": {"min": [v - margin for v in lower], "max": [v + margin for v in upper]}}


ELASTIC = {"type": "elastic", "parameters": {"youngs_modulus": 2.0e4, "poissons_ratio": 0.3}, "density": 800.0}
FILL = {"spacing": 0.02}  # coarse: a few hundred particles per object
SAND = {"type": "sand", "parameters": {"friction_angle": 35.0}, "density": 1500.0}


def base_config(folder: Path, frames: int = 3) -> dict:
    """What every test config shares: the splats, a ground, a tiny grid, the camera."""
    return {
        "splats": str(write_scene(folder)),
        "boundaries": {"ground": {"height": 0.0, "mode": "sticky"}},
        "simulation": {"grid_resolution": 20, "fps": 24.0, "frames": frames},
        "camera": {"position": [0.0, 0.5, 1.5], "look_at": [0.0, 0.15, 0.0], "width": 32, "height": 32},
        "output": str(folder / "results"),
    }


def cube_config(folder: Path, frames: int = 3) -> dict:
    """The cube alone, in the single-object form (object + material). A copy each time: a
    test may change it without changing ELASTIC for the tests after it."""
    return copy.deepcopy(
        {
            **base_config(folder, frames),
            "object": {"select": box(*CUBE), "fill": FILL, "velocity": [0.0, -0.5, 0.0]},
            "material": ELASTIC,
        }
    )


def two_objects_config(folder: Path, frames: int = 3) -> dict:
    """The cube dropped on the heap, in the ``objects:`` form (a copy each time, as above)."""
    return copy.deepcopy(
        {
            **base_config(folder, frames),
            "objects": [
                {
                    "name": "jelly",
                    "select": box(*CUBE),
                    "fill": FILL,
                    "velocity": [0.0, -0.5, 0.0],
                    "material": ELASTIC,
                },
                {"name": "heap", "select": box(*HEAP), "fill": FILL, "material": SAND},
            ],
        }
    )


def write_config(folder: Path, data: dict, name: str = "scene.yaml") -> Path:
    path = folder / name
    path.write_text(yaml.safe_dump(data))
    return path
