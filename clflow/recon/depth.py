"""Single image + depth: pixel-aligned Gaussians back-projected from a user-given depth map
(any monocular depth model's output; nothing is downloaded), with the hidden side closed.

    g = backproject(rgb, depth, camera, shell="mirror")      # Gaussians, metres

Each pixel with depth z > 0 (and inside the mask) becomes a flat Gaussian facing the camera
at X = z K^-1 (u + 0.5, v + 0.5, 1), as wide as its pixel footprint (std 0.6 z / f) and a
tenth of that thick, with the pixel's colour. The hidden side (``shell``):

- ``mirror``: a second Gaussian per pixel at depth 2 z_max - z, the visible surface mirrored
  about the plane of the object's farthest depth z_max (exact for a sphere seen from outside);
- ``extrude``: at depth z + t, a shell of constant thickness t (default z_max - z_min);
- ``none``: the visible surface only.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from clflow.errors import InputError
from clflow.splat.cameras import Camera
from clflow.splat.gaussians import Gaussians
from clflow.splat.geometry import rotmat_to_quat
from clflow.splat.sh import rgb_to_sh0

SHELLS = ("mirror", "extrude", "none")
FOOTPRINT = 0.6  # in-plane std of a pixel's Gaussian, in pixel footprints (z / f)
FLATNESS = 0.1  # thickness / width
PNG_METRES_PER_UNIT = 1e-3  # 16-bit depth PNGs store millimetres unless told otherwise


def read_depth(path: str | os.PathLike, metres_per_unit: float | None = None) -> torch.Tensor:
    """[H, W] float32 depth (m) of a ``.npy`` (values x ``metres_per_unit``, default 1) or a
    16-bit PNG (default 1e-3: millimetres); 0 marks pixels without depth."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        try:
            depth = np.load(path)
        except (OSError, ValueError) as exc:
            raise InputError(f"{path}: cannot read the depth map ({exc})") from None
        scale = 1.0 if metres_per_unit is None else metres_per_unit
    elif path.suffix.lower() == ".png":
        import cv2

        depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if depth is None or depth.dtype != np.uint16 or depth.ndim != 2:
            raise InputError(f"{path}: a depth PNG must be a single-channel 16-bit image")
        scale = PNG_METRES_PER_UNIT if metres_per_unit is None else metres_per_unit
    else:
        raise InputError(f"{path}: depth maps are .npy or 16-bit .png files")
    depth = np.squeeze(np.asarray(depth, dtype=np.float64))
    if depth.ndim != 2:
        raise InputError(f"{path}: a depth map is [H, W], got shape {list(depth.shape)}")
    if not np.isfinite(depth).all() or (depth < 0).any():
        raise InputError(f"{path}: depth must be finite and >= 0 (0 = no depth)")
    return torch.from_numpy(depth * scale).float()


def backproject(
    rgb: torch.Tensor,
    depth: torch.Tensor,
    camera: Camera,
    *,
    mask: torch.Tensor | None = None,
    shell: str = "mirror",
    thickness: float | None = None,
    opacity: float = 0.95,
) -> Gaussians:
    """Degree-0 Gaussians of one view (see the module docstring).

    Args:
        rgb: [H, W, 3] colours in [0, 1]. depth: [H, W] camera z (m), 0 where unknown.
        camera: the view (its size must be W x H). mask: [H, W] bool, optional.
        shell: "mirror", "extrude" or "none". thickness: extrusion depth (m).
    """
    if shell not in SHELLS:
        raise InputError(f"shell must be one of {', '.join(SHELLS)}, got {shell!r}")
    if tuple(depth.shape) != (camera.height, camera.width) or tuple(rgb.shape[:2]) != (camera.height, camera.width):
        raise InputError(
            f"the depth map is {depth.shape[-1]}x{depth.shape[0]} px and the image {rgb.shape[1]}x{rgb.shape[0]} px, "
            f"but the camera is {camera.width}x{camera.height} px: they must match"
        )
    keep = depth > 0 if mask is None else (depth > 0) & mask
    if not bool(keep.any()):
        raise InputError("the depth map has no pixel with depth > 0 (inside the mask)")
    v, u = torch.nonzero(keep, as_tuple=True)
    z = depth[keep].double()
    if shell == "mirror":
        z = torch.cat([z, 2 * z.max() - z])
    elif shell == "extrude":
        t = float(z.max() - z.min()) if thickness is None else thickness
        if not t > 0:
            raise InputError(f"extrusion thickness must be > 0 m, got {t} (a flat depth map: give thickness)")
        z = torch.cat([z, z + t])
    copies = len(z) // len(u)
    u, v = u.repeat(copies).double() + 0.5, v.repeat(copies).double() + 0.5
    local = torch.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], dim=1)
    means = local @ camera.R + camera.position  # camera to world: R^T x + C
    width = FOOTPRINT * z / camera.fx
    scales = torch.stack([width, width, FLATNESS * width], dim=1)
    quats = rotmat_to_quat(camera.R.T[None])[0].expand(len(z), 4)  # local z along the viewing axis
    colours = rgb[keep].double().repeat(copies, 1)
    return Gaussians.from_activated(
        means.float(),
        quats.float().contiguous(),
        scales.float(),
        torch.full((len(z),), opacity),
        sh=rgb_to_sh0(colours.float())[:, None, :],
    )
