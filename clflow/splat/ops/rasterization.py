"""``rasterize_gaussians``: one view of N Gaussians, differentiably, put together from the
ops (covariances, projection, tile lists, compositing) after its inputs are checked."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from clflow.errors import InputError
from clflow.runtime.arrays import origin_device, to_cpu, to_origin
from clflow.runtime.devices import get_device
from clflow.splat.binning import build_tile_lists
from clflow.splat.constants import MIN_QUAT_NORM
from clflow.splat.ops.compositing import composite, entry_record_bytes
from clflow.splat.ops.covariance import covariances
from clflow.splat.ops.projection import project
from clflow.splat.sh import num_sh_bases, sh_to_rgb

ORTHONORMAL_TOL = 1e-4  # |W W^T - I| allowed in the viewmat's rotation


def view_directions(means: Tensor, viewmat: Tensor, sh_rotations: Tensor | None = None) -> Tensor:
    """Unit directions [N, 3] from the camera centre to each mean, in each Gaussian's rest
    frame when ``sh_rotations`` [N, 3, 3] are given (dir -> R^T dir)."""
    W, t = viewmat[:3, :3], viewmat[:3, 3]
    campos = -W.T @ t
    dirs = means - campos
    if sh_rotations is not None:
        dirs = torch.einsum("nji,nj->ni", sh_rotations, dirs)
    return dirs / dirs.norm(dim=-1, keepdim=True)


def _check(t: Tensor | None, name: str, shape: tuple, dtype: torch.dtype | None) -> None:
    """Shape ([-1] = any size), dtype and finiteness of one input."""
    if not isinstance(t, Tensor):
        raise InputError(f"rasterize: {name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() != len(shape) or any(s != -1 and s != d for s, d in zip(shape, t.shape)):
        want = "[" + ", ".join("*" if s == -1 else str(s) for s in shape) + "]"
        raise InputError(f"rasterize: {name} has shape {list(t.shape)}, expected {want}")
    if dtype is not None and t.dtype != dtype:
        raise InputError(f"rasterize: {name} is {t.dtype} but means are {dtype}; use one float dtype")
    # one reduction in the common case: a sum is finite unless some value is NaN or inf
    # (or the values are so large that they overflow, which the exact check then clears)
    if t.numel() and not bool(torch.isfinite(t.sum())):
        finite_rows = torch.isfinite(t.reshape(t.shape[0], -1)).all(dim=-1) if t.dim() else torch.isfinite(t)[None]
        if bool(finite_rows.all()):
            return
        bad = torch.nonzero(~finite_rows)[0].item()
        raise InputError(f"rasterize: {name} has NaN or infinite values (first at index {bad})")


def _validate_gaussians(means, quats, scales, opacities, colors, covars, sh_degree, sh_rotations, features) -> None:
    """InputError unless the Gaussians' tensors have the shapes, dtype and values rasterize needs."""
    if not isinstance(means, Tensor) or means.dtype not in (torch.float32, torch.float64):
        raise InputError("rasterize: means must be a float32 or float64 tensor [N, 3]")
    dtype = means.dtype
    _check(means, "means", (-1, 3), dtype)
    n = means.shape[0]
    if covars is not None:
        if quats is not None or scales is not None:
            raise InputError("rasterize: give either covars or quats and scales, not both")
        _check(covars, "covars", (n, 3, 3), dtype)
    else:
        if quats is None or scales is None:
            raise InputError("rasterize: quats and scales are required when covars is None")
        _check(quats, "quats", (n, 4), dtype)
        _check(scales, "scales", (n, 3), dtype)
        short = torch.linalg.vector_norm(quats, dim=-1) < MIN_QUAT_NORM
        if n and bool(short.any()):
            i = torch.nonzero(short)[0].item()
            raise InputError(
                f"rasterize: quats[{i}] is (nearly) zero (norm < {MIN_QUAT_NORM:g}): a degenerate rotation"
            )
        if n and float(scales.min()) <= 0:
            i = torch.nonzero((scales <= 0).any(dim=-1))[0].item()
            raise InputError(f"rasterize: scales[{i}] = {scales[i].tolist()} has a zero or negative standard deviation")
    _check(opacities, "opacities", (n,), dtype)
    if n and not 0 <= float(opacities.min()) <= float(opacities.max()) <= 1:
        i = torch.nonzero((opacities < 0) | (opacities > 1))[0].item()
        raise InputError(f"rasterize: opacities[{i}] = {opacities[i].item()} is outside [0, 1] (apply the sigmoid)")
    if sh_degree is None:
        _check(colors, "colors", (n, -1), dtype)
        if colors.shape[1] < 1:
            raise InputError("rasterize: colors need at least one channel")
    else:
        if sh_degree not in (0, 1, 2, 3):
            raise InputError(f"rasterize: sh_degree must be 0..3, got {sh_degree}")
        _check(colors, "colors (SH coefficients)", (n, -1, 3), dtype)
        if colors.shape[1] < num_sh_bases(sh_degree):
            raise InputError(
                f"rasterize: SH degree {sh_degree} needs {num_sh_bases(sh_degree)} coefficients per channel, "
                f"colors has {colors.shape[1]}"
            )
    if sh_rotations is not None:
        if sh_degree is None:
            raise InputError("rasterize: sh_rotations only apply with sh_degree")
        _check(sh_rotations, "sh_rotations", (n, 3, 3), dtype)
    if features is not None:
        _check(features, "features", (n, -1), dtype)


def _validate_view(viewmat, K, width, height, near) -> None:
    """InputError unless the camera (world-to-camera viewmat, intrinsics K, image size, near plane) is valid."""
    _check(viewmat, "viewmat", (4, 4), None)
    _check(K, "K", (3, 3), None)
    W = viewmat[:3, :3].double()
    err = (W @ W.T - torch.eye(3, dtype=torch.float64)).abs().max().item()
    if err > ORTHONORMAL_TOL:
        raise InputError(f"rasterize: the rotation of viewmat is not orthonormal (|W W^T - I| = {err:.2g})")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise InputError(f"rasterize: focal lengths must be positive, K has fx={K[0, 0].item()}, fy={K[1, 1].item()}")
    for name, v in (("width", width), ("height", height)):
        if not isinstance(v, (int, np.integer)) or v <= 0:
            raise InputError(f"rasterize: {name} must be a positive int, got {v!r}")
    if not near > 0:
        raise InputError(f"rasterize: near must be > 0 (m), got {near}")


def _validate_background(background, colors, sh_degree, features, dtype) -> None:
    """InputError unless ``background`` (or None) has one value per output channel."""
    if background is not None:
        c_out = (3 if sh_degree is not None else colors.shape[1]) + (0 if features is None else features.shape[1])
        _check(background, "background", (c_out,), dtype)


def assemble_channels(means, colors, viewmat, depths, sh_degree, sh_rotations, features, background, render_depth):
    """Per-Gaussian channels [N, C_total] = colours (RGB from SH when sh_degree is set),
    extra features, then depth when render_depth; their background [C_total] (0 for depth);
    and C_out, the number of colour + feature channels."""
    if sh_degree is not None:
        colors = sh_to_rgb(sh_degree, colors, view_directions(means, viewmat, sh_rotations))
    channels = [colors] + ([features] if features is not None else [])
    c_out = sum(c.shape[1] for c in channels)
    if background is None:
        background = means.new_zeros(c_out)
    if render_depth:
        channels.append(depths.unsqueeze(-1))
        background = torch.cat([background, background.new_zeros(1)])
    return torch.cat(channels, dim=1).contiguous(), background.contiguous(), c_out


def split_outputs(out: Tensor, T_final: Tensor, c_out: int, render_depth: bool):
    """(image [H, W, C_out], alpha [H, W, 1], expected depth [H, W, 1] or None)."""
    alpha = (1 - T_final).unsqueeze(-1)
    depth = None
    if render_depth:
        # pixels that nothing covers have alpha = 0 and a blended depth of 0: depth 0
        depth = out[..., c_out:] / torch.where(alpha > 0, alpha, torch.ones_like(alpha))
    return out[..., :c_out], alpha, depth


def _validate(means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree, near, **optional):
    """Every input of :func:`rasterize_gaussians` checked: InputError on the first bad one."""
    with torch.no_grad():
        covars, sh_rotations, features = optional["covars"], optional["sh_rotations"], optional["features"]
        _validate_gaussians(means, quats, scales, opacities, colors, covars, sh_degree, sh_rotations, features)
        _validate_view(viewmat, K, width, height, near)
        _validate_background(optional["background"], colors, sh_degree, features, means.dtype)


def _rasterize_via_host(origin: torch.device, given: tuple, size: tuple, optional: dict, options: dict):
    """:func:`rasterize_gaussians` of tensors on torch device ``origin`` (not the CPU): drawn
    from their host copies, results on ``origin``; gradients flow back through the copies."""
    device = get_device()
    host = [to_cpu(t, device) for t in given]
    host_optional = {name: to_cpu(t, device) for name, t in optional.items()}
    *images, meta = rasterize_gaussians(*host, *size, **host_optional, **options)
    meta = {k: to_origin(v, origin, device) for k, v in meta.items()}
    return (*(to_origin(t, origin, device) for t in images), meta)


def rasterize_gaussians(
    means: Tensor,
    quats: Tensor | None,
    scales: Tensor | None,
    opacities: Tensor,
    colors: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    *,
    covars: Tensor | None = None,
    sh_degree: int | None = None,
    sh_rotations: Tensor | None = None,
    features: Tensor | None = None,
    background: Tensor | None = None,
    near: float = 0.01,
    render_depth: bool = True,
) -> tuple[Tensor, Tensor, Tensor | None, dict]:
    """Render N 3D Gaussians into one pinhole view, differentiably.

    Args:
        means: [N, 3] world positions (m), float32 or float64 (every float input the same).
        quats: [N, 4] rotations (w, x, y, z; normalised here), or None with ``covars``.
        scales: [N, 3] standard deviations (m), already activated; or None with ``covars``.
        opacities: [N] in [0, 1], already activated.
        colors: [N, C] features (any C >= 1), or SH coefficients [N, K, 3] with
            K >= (sh_degree + 1)^2 when ``sh_degree`` is set.
        viewmat: [4, 4] world-to-camera, OpenCV axes (+x right, +y down, +z forward).
        K: [3, 3] pinhole intrinsics (pixels; pixel centres at i + 0.5).
        width, height: image size (pixels).
        covars: [N, 3, 3] world covariances (m^2) instead of quats and scales.
        sh_degree: 0..3: colours are SH coefficients, RGB = SH(dir) + 0.5 clamped at 0,
            dir the unit vector from the camera centre to the mean.
        sh_rotations: [N, 3, 3] per-Gaussian rotation R; SH are evaluated at R^T dir.
        features: [N, F] extra channels appended after the colour channels.
        background: [C_out] (C_out = colour channels + F) composited behind; default zeros.
        near: Gaussians with camera z <= near (m) are culled.
        render_depth: also render the expected depth sum z a T / sum a T.

    Returns:
        image [H, W, C_out], alpha [H, W, 1] (= 1 - T_final), depth [H, W, 1] (m; 0 where
        alpha is 0) or None, and meta: means2d [N, 2], conics [N, 3], depths [N], radii [N]
        (int32, 0 = culled), tiles_touched [N], num_tile_entries, tile_list_bytes and
        entry_record_bytes (device memory of the tile lists, and of the per-entry records
        the compositing kernels read, while they run).
        Differentiable w.r.t. means, quats, scales, covars, opacities, colors, sh_rotations,
        features and background.

    Tensors may live on any torch device (all on one): they are copied to the host once, the
    results come back on their device, and gradients flow back there (copies counted in
    ``get_device().transfers``).
    """
    given = (means, quats, scales, opacities, colors, viewmat, K)
    optional = dict(covars=covars, sh_rotations=sh_rotations, features=features, background=background)
    origin = origin_device(*given, *optional.values(), what="rasterize: the tensors")
    if origin.type != "cpu":
        options = dict(sh_degree=sh_degree, near=near, render_depth=render_depth)
        return _rasterize_via_host(origin, given, (width, height), optional, options)
    _validate(means, quats, scales, opacities, colors, viewmat, K, width, height, sh_degree, near, **optional)
    dtype = means.dtype
    viewmat = viewmat.to(dtype).contiguous()
    K = K.to(dtype).contiguous()
    if covars is None:
        covars = covariances(quats.contiguous(), scales.contiguous())
    means2d, conics, depths, radii, tiles_touched = project(
        means.contiguous(), covars.contiguous(), viewmat, K, int(width), int(height), float(near)
    )
    channels, background, c_out = assemble_channels(
        means, colors, viewmat, depths, sh_degree, sh_rotations, features, background, render_depth
    )
    lists = build_tile_lists(means2d.detach(), depths.detach(), radii, tiles_touched, int(width), int(height))
    splats = (means2d, conics, opacities.contiguous(), channels, background)
    tiles = (lists.ranges, lists.sorted_slots, lists.slot_gaussian, lists.first_slot, lists.tiles_touched)
    out, T_final, _ = composite(*splats, *tiles, int(width), int(height))
    image, alpha, depth = split_outputs(out, T_final, c_out, render_depth)
    meta = dict(means2d=means2d, conics=conics, depths=depths, radii=radii, tiles_touched=tiles_touched)
    meta.update(num_tile_entries=lists.num_entries, tile_list_bytes=lists.nbytes)
    meta["entry_record_bytes"] = entry_record_bytes(means.shape[0], lists.num_entries, channels.shape[1], dtype)
    return image, alpha, depth, meta
