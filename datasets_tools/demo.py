"""The bundled demo: a jelly cube on a checkered floor, pushed sideways and released.

``make_demo(folder)`` writes a complete, self-made case:

- ``scene.ply``: procedural, textured 3DGS Gaussians (scene units are metres, +y up): the
  cube's surface (the simulator fills its inside) and a static floor;
- ``config_truth.yaml``: the scene with the ground-truth material;
- ``guidance/000.png ...``: the guidance video, rendered by clflow from the ground-truth
  simulation seen by the guidance camera (lossless PNG frames; also ``guidance.mp4``);
- ``config.yaml``: the same scene whose initial guess of Young's modulus is 10x too low,
  with ``optimize`` set to recover it from the guidance video's optical flow.

The same path (config -> simulate -> render) makes benchmark scenes of other sizes.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

TRUTH = {"youngs_modulus": 2.0e4, "poissons_ratio": 0.3}  # a soft jelly, Pa
DENSITY = 1000.0  # kg/m^3


@dataclass(frozen=True)
class DemoSize:
    """Resolution knobs: Gaussians per cube edge, floor Gaussians per side, image size,
    grid nodes, frames."""

    cube_edge: int = 14
    floor_side: int = 40
    image: int = 160
    grid: int = 24
    frames: int = 12
    iterations: int = 20


QUICK = DemoSize(cube_edge=8, floor_side=24, image=96, grid=16, frames=8, iterations=14)


def benchmark_size(gaussians: int, image: int = 256, grid: int = 24, frames: int = 12) -> DemoSize:
    """A demo-like scene of about ``gaussians`` Gaussians, a fifth of them on the object."""
    cube_edge = max(2, round((gaussians / 5 / 6) ** 0.5))
    floor_side = max(2, round(max(0, gaussians - 6 * cube_edge**2) ** 0.5))
    return DemoSize(cube_edge=cube_edge, floor_side=floor_side, image=image, grid=grid, frames=frames)


def _checker(u: np.ndarray, v: np.ndarray, cells: int, a, b) -> np.ndarray:
    """RGB [n, 3] of a checkerboard with ``cells`` squares per unit of (u, v) in [0, 1]."""
    odd = (np.floor(u * cells) + np.floor(v * cells)).astype(int) % 2 == 1
    return np.where(odd[:, None], np.asarray(b, float), np.asarray(a, float))


def cube_surface(side: float, centre, n: int, rng: np.random.Generator):
    """Gaussians on the 6 faces of a cube: means [6n^2, 3], scales [6n^2, 3], rgb."""
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
            colour = _checker(uu, vv, 4, (0.95, 0.35, 0.25), (0.98, 0.85, 0.3))
            colour = colour * (0.9 + 0.1 * rng.random((uu.size, 1)))  # a little grain helps the flow
            means.append(p + np.asarray(centre))
            scales.append(s)
            rgb.append(colour)
    return np.concatenate(means), np.concatenate(scales), np.concatenate(rgb)


def floor(size: float, n: int, height: float = 0.0):
    """Static floor Gaussians in the plane y = height: means, scales, rgb."""
    grid = (np.arange(n) + 0.5) / n
    uu, vv = [a.ravel() for a in np.meshgrid(grid, grid, indexing="ij")]
    means = np.stack([(uu - 0.5) * size, np.full(uu.size, height - 0.01), (vv - 0.5) * size], 1)
    spacing = size / n
    scales = np.tile([0.6 * spacing, 0.004, 0.6 * spacing], (uu.size, 1))
    rgb = _checker(uu, vv, 8, (0.85, 0.85, 0.85), (0.35, 0.4, 0.5))
    return means, scales, rgb


def demo_config(size: DemoSize, parameters: dict[str, float], optimize: bool) -> dict:
    """The demo's scene config (as a dict; see clflow.scene.config)."""
    side = 0.2
    config = {
        "splats": "scene.ply",
        "scene": {"scale": 1.0, "up": "+y"},
        "object": {"select": {"box": {"min": [-0.15, -0.005, -0.15], "max": [0.15, 0.3, 0.15]}}},
        "material": {"type": "elastic", "parameters": dict(parameters), "density": DENSITY},
        "forces": [{"region": {"box": {"min": [-0.2, 0.6 * side, -0.2], "max": [0.2, 0.4, 0.2]}},
                    "acceleration": [12.0, 0.0, 0.0], "start": 0.0, "end": 0.12}],
        "boundaries": {"ground": {"height": 0.0, "mode": "sticky"}},
        "simulation": {"grid_resolution": size.grid, "fps": 24, "frames": size.frames},
        "camera": {"position": [0.25, 0.45, 0.75], "look_at": [0.0, 0.1, 0.0], "fov_y_deg": 40.0,
                   "width": size.image, "height": size.image},
        "flow": {"method": "dis", "preset": "medium", "loss": "l2", "mask": "alpha"},
        "output": "results",
    }
    if optimize:
        config["video"] = "guidance"
        # a 4-frame horizon first: its loss falls monotonically towards the truth from far
        # below, where the full horizon's has a local minimum (docs/pipeline.md)
        config["optimize"] = {"parameters": ["youngs_modulus"], "learning_rates": {"youngs_modulus": 0.2},
                              "iterations": size.iterations, "horizon": {"start": 4, "step": 1}}
        config["evaluation"] = {"ground_truth": dict(TRUTH)}
    return config


def write_scene(folder: Path, size: DemoSize, seed: int = 0) -> None:
    """Write the demo's scene.ply."""
    from clflow.splat.gaussians import Gaussians, rgb_to_sh0
    from clflow.splat.ply import save_ply

    rng = np.random.default_rng(seed)
    cm, cs, crgb = cube_surface(0.2, (0.0, 0.1, 0.0), size.cube_edge, rng)
    fm, fs, frgb = floor(1.2, size.floor_side)
    means = torch.from_numpy(np.concatenate([cm, fm])).float()
    scales = torch.from_numpy(np.concatenate([cs, fs])).float()
    rgb = torch.from_numpy(np.concatenate([crgb, frgb])).float()
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(means.shape[0], 1)
    opacities = torch.full((means.shape[0],), 0.95)
    g = Gaussians.from_activated(means, quats, scales, opacities, sh=rgb_to_sh0(rgb)[:, None, :])
    save_ply(folder / "scene.ply", g)


def make_demo(folder: str | Path, size: DemoSize = DemoSize(), seed: int = 0) -> Path:
    """Write the demo case into ``folder``; returns the path of its ``config.yaml``."""
    import yaml

    from clflow.fileio import atomic_write_text
    from clflow.pipeline.forward import render_video, simulate_config
    from clflow.scene.config import parse_config

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_scene(folder, size, seed)
    truth = demo_config(size, TRUTH, optimize=False)
    atomic_write_text(folder / "config_truth.yaml", yaml.safe_dump(truth, sort_keys=False))
    result = simulate_config(parse_config(truth, str(folder / "config_truth.yaml"), folder))
    render_video(result, folder / "guidance", video=folder / "guidance.mp4")
    guess = {name: value for name, value in TRUTH.items()}
    guess["youngs_modulus"] = TRUTH["youngs_modulus"] / 10.0  # 10x off
    config = demo_config(size, guess, optimize=True)
    atomic_write_text(folder / "config.yaml", yaml.safe_dump(copy.deepcopy(config), sort_keys=False))
    return folder / "config.yaml"


__all__ = ["DemoSize", "QUICK", "TRUTH", "benchmark_size", "demo_config", "make_demo", "write_scene"]
