"""Gaussian splats: 3DGS PLY files, the Gaussians container, cameras and the differentiable rasteriser.

    from clflow.splat import load_ply, look_at, rasterize
    gaussians = load_ply("point_cloud.ply")                  # 3DGS PLY or x y z [r g b] points
    camera = look_at((2, 0, 1), (0, 0, 0), fov_x=0.9, width=512, height=512)
    image, alpha, depth, meta = rasterize(gaussians, camera)  # differentiable

The torch ops over the kernels (``rasterize_gaussians`` on raw tensors, ``covariances``,
``project``, ``composite``) are in :mod:`clflow.splat.ops`. Importing this package builds no
OpenCL kernels.
"""

from clflow.splat.cameras import (
    Camera,
    frame_box,
    intrinsics,
    load_cameras_json,
    load_transforms_json,
    look_at,
    orbit,
    save_cameras_json,
    save_transforms_json,
)
from clflow.splat.gaussians import Gaussians
from clflow.splat.ply import load_ply, save_ply
from clflow.splat.render import Render, rasterize
from clflow.splat.sh import rgb_to_sh0, sh0_to_rgb

__all__ = [
    "Camera",
    "Gaussians",
    "frame_box",
    "intrinsics",
    "load_cameras_json",
    "load_transforms_json",
    "load_ply",
    "look_at",
    "orbit",
    "rasterize",
    "Render",
    "rgb_to_sh0",
    "save_cameras_json",
    "save_ply",
    "save_transforms_json",
    "sh0_to_rgb",
]
