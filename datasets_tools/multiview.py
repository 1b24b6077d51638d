"""A procedural multi-view capture for reconstruction tests and benchmarks.

``make_multiview(folder)`` renders a textured shape (datasets_tools.synthetic's checkered
surfaces: flat Gaussians tangent to it, detail^2 x 6 of them) with clflow's rasteriser from
``views`` cameras spread evenly over a sphere around it (a Fibonacci lattice of
directions), and writes

- ``images/r_000.png ...``: RGBA, alpha = the rendered coverage (so masks can be tested);
- ``transforms.json``: NeRF synthetic layout (OpenGL camera-to-world, ``camera_angle_x``);
- ``truth.ply``: the Gaussians that made the images.

The shape's size is 1 m (cube side, sphere diameter, torus outer diameter) at the origin;
cameras look at the origin from where the shape's bounding sphere fills ``fill`` of the
narrower field of view.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from clflow_datasets.synthetic import SURFACES, surface_gaussians

FOV_X = math.radians(40.0)


def sphere_directions(n: int) -> np.ndarray:
    """[n, 3] unit vectors evenly spread over the sphere (Fibonacci lattice, z from 1 to -1 exclusive)."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    azimuth = math.pi * (1 + 5**0.5) * k
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(azimuth), r * np.sin(azimuth), z], axis=1)


def make_multiview(
    folder: str | Path,
    *,
    shape: str = "sphere",
    views: int = 60,
    size: int = 128,
    detail: int = 24,
    fill: float = 0.8,
    seed: int = 0,
) -> Path:
    """Write the capture (see the module docstring) into ``folder``; returns transforms.json's path.

    Args:
        shape: one of datasets_tools.synthetic.SHAPES. views: number of cameras.
        size: image side (pixels). detail: Gaussians per face side (6 detail^2 in all).
        fill: fraction of the narrower field of view the bounding sphere spans.
    """
    from clflow.fileio import atomic_write_text
    from clflow.media import to_uint8, write_image
    from clflow.splat.cameras import OPENGL_TO_OPENCV, framing_distance, look_at
    from clflow.splat.ply import save_ply
    from clflow.splat.render import rasterize

    folder = Path(folder)
    gaussians = surface_gaussians([SURFACES[shape](1.0, (0.0, 0.0, 0.0), detail, np.random.default_rng(seed))])
    radius = 0.5 * math.sqrt(3) if shape == "cube" else 0.5
    distance = framing_distance(radius / fill, FOV_X, size, size)
    frames = []
    for i, direction in enumerate(sphere_directions(views)):
        camera = look_at(distance * direction, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), fov_x=FOV_X, width=size, height=size)
        with torch.no_grad():
            render = rasterize(gaussians, camera, render_depth=False)
        name = f"images/r_{i:03d}"
        rgba = torch.cat([render.image, render.alpha], dim=-1)
        write_image(folder / f"{name}.png", to_uint8(rgba))
        frames.append({"file_path": name, "transform_matrix": (camera.camtoworld() @ OPENGL_TO_OPENCV).tolist()})
    save_ply(folder / "truth.ply", gaussians)
    path = folder / "transforms.json"
    atomic_write_text(
        path, json.dumps({"camera_angle_x": FOV_X, "w": size, "h": size, "frames": frames}, indent=1) + "\n"
    )
    return path
