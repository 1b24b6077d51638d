"""Pure-torch dense reference of the splat rasteriser (small images only: O(N H W)).

Same maths and the same decisions as the OpenCL kernels (projection with clamped J, radii,
tile boxes, (tile, depth) order, skip and stop rules), written plainly so that tests can
compare the kernels with it in float64 and differentiate it with torch autograd.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from clflow.splat.constants import (
    ALPHA_MAX,
    ALPHA_MIN,
    EPS2D,
    LIM_FOV,
    MAX_RADIUS,
    MIN_RADIUS_EIGEN,
    T_MIN,
    TILE_SIZE,
)
from clflow.splat.geometry import covariances_of, quat_to_rotmat
from clflow.splat.ops import assemble_channels, split_outputs


def covariances_from_quats_scales(quats: Tensor, scales: Tensor) -> Tensor:
    """Sigma = R(q) S S^T R(q)^T [N, 3, 3] (m^2) from quats [N, 4] (w, x, y, z; normalised
    here) and scales [N, 3] (standard deviations, m)."""
    return covariances_of(scales, quat_to_rotmat(quats))


def project_reference(
    means: Tensor, covars: Tensor, viewmat: Tensor, K: Tensor, width: int, height: int, near: float
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Torch version of ``clflow::splat_project``: means2d, conics, depths, radii, tiles_touched."""
    W, t = viewmat[:3, :3], viewmat[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    mc = means @ W.T + t
    x, y, z = mc.unbind(-1)
    u, v = x / z, y / z
    margin_u = (LIM_FOV - 1) * 0.5 * width / fx
    margin_v = (LIM_FOV - 1) * 0.5 * height / fy
    tu = torch.minimum(torch.maximum(u, -(cx / fx + margin_u)), (width - cx) / fx + margin_u)
    tv = torch.minimum(torch.maximum(v, -(cy / fy + margin_v)), (height - cy) / fy + margin_v)
    zeros = torch.zeros_like(z)
    J = torch.stack([fx / z, zeros, -fx * tu / z, zeros, fy / z, -fy * tv / z], dim=-1).reshape(-1, 2, 3)
    sym = 0.5 * (covars + covars.transpose(-1, -2))
    cov2d = J @ (W @ sym @ W.T) @ J.transpose(-1, -2)
    a, b, c = cov2d[:, 0, 0] + EPS2D, cov2d[:, 0, 1], cov2d[:, 1, 1] + EPS2D
    det = a * c - b * b
    visible = (z > near) & (det > 0)
    safe_det = torch.where(visible, det, torch.ones_like(det))
    conics = torch.stack([c / safe_det, -b / safe_det, a / safe_det], dim=-1)
    means2d = torch.stack([fx * u + cx, fy * v + cy], dim=-1)
    mid = 0.5 * (a + c)
    lambda_max = mid + torch.sqrt(torch.clamp_min(mid * mid - det, MIN_RADIUS_EIGEN))
    radii = torch.ceil(3 * torch.sqrt(lambda_max.detach().clamp_min(0))).clamp_max(MAX_RADIUS).to(torch.int32)
    tiles_x, tiles_y = math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)
    x0, y0, x1, y1 = tile_rect_reference(means2d.detach(), radii, tiles_x, tiles_y)
    touched = (x1 - x0).clamp_min(0) * (y1 - y0).clamp_min(0)
    visible = visible & (touched > 0)
    radii = torch.where(visible, radii, torch.zeros_like(radii))
    touched = torch.where(visible, touched, torch.zeros_like(touched)).to(torch.int32)
    keep = visible.unsqueeze(-1)
    return (torch.where(keep, means2d, 0.0), torch.where(keep, conics, 0.0), z, radii, touched)


def tile_rect_reference(means2d: Tensor, radii: Tensor, tiles_x: int, tiles_y: int):
    """Tile box [x0, x1) x [y0, y1) of each Gaussian (as kernels_cl/splat/common.h)."""
    r = radii.to(means2d.dtype)
    mx, my = means2d.unbind(-1)

    def cell(v, hi):
        return torch.floor(torch.clamp(v, 0, hi)).to(torch.int64)

    x0, y0 = cell((mx - r) / TILE_SIZE, tiles_x), cell((my - r) / TILE_SIZE, tiles_y)
    x1, y1 = cell((mx + r) / TILE_SIZE + 1, tiles_x), cell((my + r) / TILE_SIZE + 1, tiles_y)
    return x0, y0, x1, y1


def composite_reference(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    background: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Dense front-to-back compositing: out [H, W, C] and T_final [H, W]."""
    dtype = means2d.dtype
    tiles_x, tiles_y = math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)
    x0, y0, x1, y1 = tile_rect_reference(means2d.detach(), radii, tiles_x, tiles_y)
    py, px = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    tx, ty = px // TILE_SIZE, py // TILE_SIZE
    pcx, pcy = px.to(dtype) + 0.5, py.to(dtype) + 0.5
    T = torch.ones(height, width, dtype=dtype)
    acc = torch.zeros(height, width, features.shape[1], dtype=dtype)
    done = torch.zeros(height, width, dtype=torch.bool)
    # depth order as the kernels sort it: float32 depth, ties by index
    order = torch.sort(depths.detach().to(torch.float32), stable=True).indices
    for g in order.tolist():
        if radii[g] <= 0:
            continue
        in_box = (tx >= x0[g]) & (tx < x1[g]) & (ty >= y0[g]) & (ty < y1[g])
        dx, dy = means2d[g, 0] - pcx, means2d[g, 1] - pcy
        A, B, C = conics[g].unbind()
        sigma = 0.5 * (A * dx * dx + C * dy * dy) + B * dx * dy
        alpha = torch.clamp(opacities[g] * torch.exp(-sigma), max=ALPHA_MAX)
        valid = in_box & ~done & (sigma >= 0) & (alpha >= ALPHA_MIN)
        T_next = T * (1 - alpha)
        stop = valid & (T_next < T_MIN)
        done = done | stop
        take = valid & ~stop
        acc = acc + torch.where(take, alpha * T, 0.0).unsqueeze(-1) * features[g]
        T = torch.where(take, T_next, T)
    return acc + T.unsqueeze(-1) * background, T


def rasterize_reference(
    means,
    quats,
    scales,
    opacities,
    colors,
    viewmat,
    K,
    width,
    height,
    *,
    covars=None,
    sh_degree=None,
    sh_rotations=None,
    features=None,
    background=None,
    near=0.01,
    render_depth=True,
):
    """Same interface and outputs (image, alpha, depth, meta) as
    :func:`clflow.splat.ops.rasterize_gaussians`; meta holds means2d, conics, depths, radii."""
    dtype = means.dtype
    viewmat, K = viewmat.to(dtype), K.to(dtype)
    if covars is None:
        covars = covariances_from_quats_scales(quats, scales)
    means2d, conics, depths, radii, _ = project_reference(means, covars, viewmat, K, width, height, near)
    channels, background, c_out = assemble_channels(
        means, colors, viewmat, depths, sh_degree, sh_rotations, features, background, render_depth
    )
    out, T = composite_reference(means2d, conics, opacities, channels, background, depths, radii, width, height)
    image, alpha, depth = split_outputs(out, T, c_out, render_depth)
    return image, alpha, depth, {"means2d": means2d, "conics": conics, "depths": depths, "radii": radii}
