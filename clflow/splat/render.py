"""High-level rendering: :class:`Gaussians` seen by a :class:`Camera`, differentiably.

    from clflow.splat import load_ply, look_at, rasterize
    g = load_ply("point_cloud.ply")
    cam = look_at((2, 0, 1), (0, 0, 0), fov_x=0.9, width=512, height=512)
    image, alpha, depth, meta = rasterize(g, cam, background=(1, 1, 1))

The OpenCL rasteriser (:func:`clflow.splat.ops.rasterize_gaussians`) is imported on
the first call, so importing this module builds no kernels.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import torch

from clflow.errors import InputError
from clflow.splat.cameras import Camera
from clflow.splat.gaussians import Gaussians


class Render(NamedTuple):
    """One rendered view.

    image: [H, W, C] colour channels then feature channels, composited over the background.
    alpha: [H, W, 1] accumulated opacity 1 - T_final.
    depth: [H, W, 1] expected camera depth (m) of the visible Gaussians, or None.
    meta: the rasteriser's per-Gaussian projection data (means2d, radii, ...).
    """

    image: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor | None
    meta: dict


def rasterize(
    gaussians: Gaussians,
    camera: Camera,
    *,
    background: torch.Tensor | Sequence[float] | None = None,
    sh_degree: int | None = None,
    features: torch.Tensor | None = None,
    covariances: torch.Tensor | None = None,
    sh_rotations: torch.Tensor | None = None,
    near: float = 0.01,
    render_depth: bool = True,
) -> Render:
    """Render ``gaussians`` from ``camera``; differentiable w.r.t. every Gaussian tensor.

    Args:
        gaussians: N Gaussians; their dtype (float32 or float64) is the compute precision.
        camera: the view; its viewmat and K are cast to the Gaussians' dtype.
        background: colour of empty space, one value per colour channel (the feature
            channels get 0) or per output channel; default black.
        sh_degree: evaluate SH up to this degree (0..the Gaussians' degree); default all.
            Ignored for Gaussians with plain ``colors``.
        features: [N, F] extra channels to blend; default ``gaussians.features`` (if any).
        covariances: [N, 3, 3] world covariances (m^2) replacing quats and scales, e.g.
            of Gaussians deformed by the simulator.
        sh_rotations: [N, 3, 3] rotation of each Gaussian since its SH were fitted; SH are
            evaluated at R^T dir (a deformed Gaussian keeps its SH in the rest frame).
        near: Gaussians with camera depth <= near (m) are culled.
        render_depth: also return the expected depth.

    Returns:
        :class:`Render` (image [H, W, C], alpha [H, W, 1], depth [H, W, 1] or None, meta).
    """
    from clflow.splat.ops import rasterize_gaussians

    dtype = gaussians.dtype
    if gaussians.sh is not None:
        available = gaussians.sh_degree
        if sh_degree is None:
            sh_degree = available
        elif not 0 <= sh_degree <= available:
            raise InputError(f"sh_degree {sh_degree} is outside 0..{available}, the degree of these Gaussians")
        colors = gaussians.sh  # the rasteriser reads the first (sh_degree + 1)^2 coefficients
        n_colors = 3
    else:
        sh_degree = None
        colors = gaussians.colors
        n_colors = colors.shape[1]
    if features is None:
        features = gaussians.features
    n_out = n_colors + (0 if features is None else features.shape[1])
    image, alpha, depth, meta = rasterize_gaussians(
        gaussians.means,
        None if covariances is not None else gaussians.quats,
        None if covariances is not None else gaussians.scales,
        gaussians.opacities,
        colors,
        camera.viewmat.to(dtype),
        camera.K.to(dtype),
        camera.width,
        camera.height,
        covars=covariances,
        sh_degree=sh_degree,
        sh_rotations=sh_rotations,
        features=features,
        background=_background(background, n_colors, n_out, dtype),
        near=near,
        render_depth=render_depth,
    )
    return Render(image, alpha, depth, meta)


def _background(value, n_colors: int, n_out: int, dtype: torch.dtype) -> torch.Tensor | None:
    if value is None:
        return None
    value = torch.as_tensor(value, dtype=dtype)
    if value.dim() != 1 or len(value) not in (n_colors, n_out):
        raise InputError(
            f"background must have {n_colors} values (one per colour channel) or {n_out} (every output channel), "
            f"got shape {tuple(value.shape)}"
        )
    if not torch.isfinite(value).all():
        raise InputError(f"background has non-finite values: {value.tolist()}")
    return torch.cat([value, value.new_zeros(n_out - len(value))])
