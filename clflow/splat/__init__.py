"""Gaussian splats: 3DGS PLY files, the Gaussians container, cameras and the differentiable rasteriser.

    from clflow.splat import load_ply, look_at
    from clflow.splat.render import rasterize
    gaussians = load_ply("point_cloud.ply")                  # 3DGS PLY or x y z [r g b] points
    camera = look_at((2, 0, 1), (0, 0, 0), fov_x=0.9, width=512, height=512)
    image, alpha, depth, meta = rasterize(gaussians, camera)  # differentiable

``rasterize`` is not re-exported here: the name would be replaced by the submodule
``clflow.splat.rasterize`` (the low-level op) as soon as that is imported. Importing this
package builds no OpenCL kernels.
"""

from clflow.splat.cameras import (
    Camera,
    frame_box,
    intrinsics,
    load_cameras_json,
    load_transforms_json,
    look_at,
    orbit,
)
from clflow.splat.gaussians import Gaussians, rgb_to_sh0, sh0_to_rgb
from clflow.splat.ply import load_ply, save_ply

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
    "rgb_to_sh0",
    "save_ply",
    "sh0_to_rgb",
]
