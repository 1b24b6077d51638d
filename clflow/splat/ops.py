"""Differentiable tile-based Gaussian splat rasteriser over OpenCL kernels (kernels_cl/splat/).

Pipeline of :func:`rasterize_gaussians`, one view:

1. ``clflow::splat_covariances``: Sigma = R(q) S S^T R(q)^T (covariance.cl), unless given;
   colours from SH in torch (sh.py);
2. ``clflow::splat_project``: EWA projection, culling, radii (project.cl);
3. tile lists sorted by (tile, depth) on the device (binning.py, binning.cl, sort.cl);
4. ``clflow::splat_composite``: per-tile front-to-back compositing of every channel
   (colours, extra features, depth) with early termination, in the shape the device's
   kernel plan picks (clflow.runtime.plan: rasterize.cl for CPUs, rasterize_tiles.cl for GPUs).

Both ops have OpenCL adjoints (back to front for compositing); per-Gaussian gradients are
summed from per-(tile, Gaussian) slots in a fixed order, so they are deterministic.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from clflow.errors import DeviceError, InputError
from clflow.runtime.arrays import origin_device, real_of, to_cpu, to_origin
from clflow.runtime.bridge import bind
from clflow.runtime.devices import get_device
from clflow.runtime.plan import kernel_plan
from clflow.splat.binning import build_tile_lists, tile_grid
from clflow.splat.constants import MIN_QUAT_NORM, SPLAT_DEFINES, SPLAT_LANES, TILE_SIZE
from clflow.splat.sh import num_sh_bases, sh_to_rgb

ORTHONORMAL_TOL = 1e-4  # |W W^T - I| allowed in the viewmat's rotation


def _kernel(source: str, name: str, dtype: torch.dtype, **defines):
    """The cached kernel ``name`` of ``kernels_cl/splat/<source>`` for ``dtype``."""
    return get_device().kernel(f"splat/{source}", name, real_of(dtype, name), {**SPLAT_DEFINES, **defines})


# -- covariance op ----------------------------------------------------------------------


@torch.library.custom_op("clflow::splat_covariances", mutates_args=())
def covariances(quats: Tensor, scales: Tensor) -> Tensor:
    """Sigma = R(q) S S^T R(q)^T [N, 3, 3] (m^2) from quats [N, 4] (w, x, y, z; normalised
    here) and scales [N, 3] (standard deviations, m), on the device."""
    device = get_device()
    n = quats.shape[0]
    covars = quats.new_empty(n, 3, 3)
    with bind(device) as b:
        device.launch(
            _kernel("covariance.cl", "covariance_forward", quats.dtype),
            -(-n // SPLAT_LANES),
            dict(quats=b.input(quats), scales=b.input(scales), covars=b.output(covars), n=np.int32(n)),
        )
    return covars


@covariances.register_fake
def _covariances_fake(quats, scales):
    return quats.new_empty(quats.shape[0], 3, 3)


@torch.library.custom_op("clflow::splat_covariances_backward", mutates_args=())
def covariances_backward(quats: Tensor, scales: Tensor, v_covars: Tensor) -> tuple[Tensor, Tensor]:
    """Adjoint of :func:`covariances`: (dL/dquats [N, 4], dL/dscales [N, 3])."""
    device = get_device()
    n = quats.shape[0]
    v_quats, v_scales = torch.empty_like(quats), torch.empty_like(scales)
    with bind(device) as b:
        grads = dict(v_covars=b.input(v_covars), v_quats=b.output(v_quats), v_scales=b.output(v_scales))
        gaussians = dict(quats=b.input(quats), scales=b.input(scales), n=np.int32(n))
        device.launch(_kernel("covariance.cl", "covariance_backward", quats.dtype), n, gaussians | grads)
    return v_quats, v_scales


@covariances_backward.register_fake
def _covariances_backward_fake(quats, scales, v_covars):
    return torch.empty_like(quats), torch.empty_like(scales)


def _covariances_setup(ctx, inputs, output) -> None:
    ctx.save_for_backward(*inputs)


def _covariances_grad(ctx, v_covars):
    return covariances_backward(*ctx.saved_tensors, v_covars.contiguous())


covariances.register_autograd(_covariances_grad, setup_context=_covariances_setup)


# -- projection op ----------------------------------------------------------------------


def _projection_args(b, means, covars, viewmat, K, width: int, height: int) -> dict:
    """The projection kernels' inputs (bound by ``b``), the count and the image size."""
    gaussians = dict(means=b.input(means), covars=b.input(covars), n=np.int32(means.shape[0]))
    return gaussians | dict(
        viewmat=b.input(viewmat), intrinsics=b.input(K), width=np.int32(width), height=np.int32(height)
    )


@torch.library.custom_op("clflow::splat_project", mutates_args=())
def project(
    means: Tensor, covars: Tensor, viewmat: Tensor, K: Tensor, width: int, height: int, near: float
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """EWA projection of N Gaussians (OpenCL).

    Args:
        means: [N, 3] world positions (m). covars: [N, 3, 3] world covariances (m^2).
        viewmat: [4, 4] world-to-camera (OpenCV axes). K: [3, 3] intrinsics (pixels).
        width, height: image size (pixels). near: culling distance (m).

    Returns:
        means2d [N, 2] (pixels), conics [N, 3] (A, B, C of the inverse 2D covariance,
        1/pixel^2), depths [N] (camera z, m), radii [N] int32 (pixels, 0 = culled),
        tiles_touched [N] int32.
    """
    device = get_device()
    n = means.shape[0]
    means2d = means.new_empty(n, 2)
    conics = means.new_empty(n, 3)
    depths = means.new_empty(n)
    radii = torch.empty(n, dtype=torch.int32)
    tiles_touched = torch.empty(n, dtype=torch.int32)
    kern = _kernel("project.cl", "project_forward", means.dtype)
    near_real = np.float64(near) if means.dtype == torch.float64 else np.float32(near)
    with bind(device) as b:
        splats = _projection_args(b, means, covars, viewmat, K, width, height) | dict(near_plane=near_real)
        outputs = dict(means2d=b.output(means2d), conics=b.output(conics), depths=b.output(depths))
        outputs |= dict(radii=b.output(radii), tiles_touched=b.output(tiles_touched))
        device.launch(kern, -(-n // SPLAT_LANES), splats | outputs)
    return means2d, conics, depths, radii, tiles_touched


@project.register_fake
def _project_fake(means, covars, viewmat, K, width, height, near):
    n = means.shape[0]
    i32 = dict(dtype=torch.int32)
    return (
        means.new_empty(n, 2),
        means.new_empty(n, 3),
        means.new_empty(n),
        means.new_empty(n, **i32),
        means.new_empty(n, **i32),
    )


@torch.library.custom_op("clflow::splat_project_backward", mutates_args=())
def project_backward(
    means: Tensor,
    covars: Tensor,
    viewmat: Tensor,
    K: Tensor,
    radii: Tensor,
    v_means2d: Tensor,
    v_conics: Tensor,
    v_depths: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Adjoint of :func:`project`: (dL/dmeans [N, 3], dL/dcovars [N, 3, 3])."""
    device = get_device()
    n = means.shape[0]
    v_means = torch.empty_like(means)
    v_covars = torch.empty_like(covars)
    kern = _kernel("project.cl", "project_backward", means.dtype)
    with bind(device) as b:
        splats = _projection_args(b, means, covars, viewmat, K, width, height) | dict(radii=b.input(radii))
        grads = dict(v_means2d=b.input(v_means2d), v_conics=b.input(v_conics), v_depths=b.input(v_depths))
        grads |= dict(v_means=b.output(v_means), v_covars=b.output(v_covars))
        device.launch(kern, n, splats | grads)
    return v_means, v_covars


@project_backward.register_fake
def _project_backward_fake(means, covars, viewmat, K, radii, v_means2d, v_conics, v_depths, width, height):
    return torch.empty_like(means), torch.empty_like(covars)


def _project_setup(ctx, inputs, output) -> None:
    means, covars, viewmat, K, width, height, _near = inputs
    ctx.save_for_backward(means, covars, viewmat, K, output[3])
    ctx.size = (width, height)


def _grad_or_zeros(grad: Tensor | None, like: Tensor) -> Tensor:
    return torch.zeros_like(like) if grad is None else grad.contiguous()


def _project_backward(ctx, v_means2d, v_conics, v_depths, _v_radii, _v_tiles):
    means, covars, viewmat, K, radii = ctx.saved_tensors
    grads = (
        _grad_or_zeros(v_means2d, means.new_empty(means.shape[0], 2)),
        _grad_or_zeros(v_conics, means.new_empty(means.shape[0], 3)),
        _grad_or_zeros(v_depths, means.new_empty(means.shape[0])),
    )
    v_means, v_covars = project_backward(means, covars, viewmat, K, radii, *grads, *ctx.size)
    return v_means, v_covars, None, None, None, None, None


project.register_autograd(_project_backward, setup_context=_project_setup)


# -- compositing op ---------------------------------------------------------------------


ENTRY_FIELDS = 9  # per-Gaussian record of the compositing kernels (splat/composite.h, entries.cl: entry_records)


def entry_record_bytes(n: int, m: int, channels: int, dtype: torch.dtype) -> int:
    """Scratch the compositing kernels take for N Gaussians, M tile entries and C channels:
    the per-Gaussian records and the records of the sorted entries (with the features)."""
    itemsize = torch.tensor([], dtype=dtype).element_size()
    return itemsize * (n * ENTRY_FIELDS + m * (ENTRY_FIELDS + channels))


def _sorted_entry_records(device, b, means2d, conics, opacities, features, sorted_slots, slot_gaussian):
    """Scratch buffer [M, ENTRY_FIELDS + C] of binding ``b``: per sorted tile entry, what the
    compositing kernels read (mean2d, conic, opacity, the row cull's cut, slope and reach,
    then the features), in entry order (entries.cl: entry_records, sort_entry_records)."""
    n, channels = features.shape
    m = sorted_slots.shape[0]
    itemsize = features.dtype.itemsize
    records = b.scratch(n * ENTRY_FIELDS * itemsize)
    entries = b.scratch(m * (ENTRY_FIELDS + channels) * itemsize)
    kernel = lambda name: _kernel("entries.cl", name, features.dtype, CHANNELS=channels)  # noqa: E731
    device.launch(
        kernel("entry_records"),
        n,
        dict(
            means2d=b.input(means2d),
            conics=b.input(conics),
            opacities=b.input(opacities),
            records=records,
            n=np.int32(n),
        ),
    )
    device.launch(
        kernel("sort_entry_records"),
        m,
        dict(sorted_slots=b.input(sorted_slots), slot_gaussian=b.input(slot_gaussian), records=records)
        | dict(features=b.input(features), entries=entries, m=np.int32(m)),
    )
    return entries


TILE_PIXELS = TILE_SIZE * TILE_SIZE  # work-items of a tile's work-group in the "workgroup" shape
MAX_RASTER_LOCAL_BYTES = 48 * 1024  # local memory the "workgroup" kernels may take (sizes their batches)


def _composite_launch(device, direction: str, dtype: torch.dtype, channels: int, width: int, height: int):
    """(kernel, global size, image-size args, local size) of the compositing kernel of
    ``direction`` ("forward" or "backward") in the shape the device's plan picks
    (clflow.runtime.plan):

    - "tile_rows" (rasterize.cl): a work-item per 16 x 16 tile, each its own work-group, so
      the busy tiles spread over the cores;
    - "workgroup" (rasterize_tiles.cl): a work-group of TILE_PIXELS work-items per tile, one
      per pixel, entries staged in local memory in batches sized to LOCAL_MEM_BYTES.
    """
    tiles_x, tiles_y = tile_grid(width, height)
    n_tiles = tiles_x * tiles_y
    image = dict(width=np.int32(width), height=np.int32(height), tiles_x=np.int32(tiles_x))
    if kernel_plan(device).raster == "tile_rows":
        kern = _kernel("rasterize.cl", f"rasterize_{direction}", dtype, CHANNELS=channels)
        return kern, n_tiles, image | dict(n_tiles=np.int32(n_tiles)), 1
    if device.info.max_work_group_size < TILE_PIXELS:
        raise DeviceError(
            f"{device.info.name}: work-groups of at most {device.info.max_work_group_size} work-items, the tiled "
            f"compositing kernels need {TILE_PIXELS}; run the CPU shape (CLFLOW_KERNELS=cpu)"
        )
    local_bytes = min(device.info.local_mem_size, MAX_RASTER_LOCAL_BYTES)
    kern = _kernel(
        "rasterize_tiles.cl", f"rasterize_tiles_{direction}", dtype, CHANNELS=channels, LOCAL_MEM_BYTES=local_bytes
    )
    return kern, n_tiles * TILE_PIXELS, image, TILE_PIXELS


@torch.library.custom_op("clflow::splat_composite", mutates_args=())
def composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    background: Tensor,
    ranges: Tensor,
    sorted_slots: Tensor,
    slot_gaussian: Tensor,
    first_slot: Tensor,
    tiles_touched: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """Front-to-back compositing of sorted splats (OpenCL), per 16 x 16 tile.

    Args:
        means2d [N, 2], conics [N, 3], opacities [N], features [N, C], background [C];
        the tile lists of :class:`~clflow.splat.binning.TileLists`; image size (pixels).

    Returns:
        out [H, W, C] = sum_i f_i alpha_i T_i + T_final background, T_final [H, W]
        (transmittance left), n_contrib [H, W] int32 (entries walked up to the last
        contributor, for the adjoint).
    """
    device = get_device()
    channels = features.shape[1]
    out = features.new_empty(height, width, channels)
    T_final = features.new_empty(height, width)
    n_contrib = torch.empty(height, width, dtype=torch.int32)
    kern, global_size, size_args, local_size = _composite_launch(
        device, "forward", features.dtype, channels, width, height
    )
    with bind(device) as b:
        entries = _sorted_entry_records(device, b, means2d, conics, opacities, features, sorted_slots, slot_gaussian)
        image = dict(ranges=b.input(ranges), entries=entries, background=b.input(background))
        image |= dict(out=b.output(out), T_final=b.output(T_final), n_contrib=b.output(n_contrib))
        device.launch(kern, global_size, image | size_args, local_size)
    return out, T_final, n_contrib


@composite.register_fake
def _composite_fake(
    means2d,
    conics,
    opacities,
    features,
    background,
    ranges,
    sorted_slots,
    slot_gaussian,
    first_slot,
    tiles_touched,
    width,
    height,
):
    out = features.new_empty(height, width, features.shape[1])
    return out, features.new_empty(height, width), features.new_empty(height, width, dtype=torch.int32)


@torch.library.custom_op("clflow::splat_composite_backward", mutates_args=())
def composite_backward(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    background: Tensor,
    ranges: Tensor,
    sorted_slots: Tensor,
    slot_gaussian: Tensor,
    first_slot: Tensor,
    tiles_touched: Tensor,
    T_final: Tensor,
    n_contrib: Tensor,
    v_out: Tensor,
    v_T_final: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Adjoint of :func:`composite`: dL/d(means2d, conics, opacities, features)."""
    device = get_device()
    n, channels = features.shape
    m = sorted_slots.shape[0]
    v_means2d, v_conics = torch.empty_like(means2d), torch.empty_like(conics)
    v_opacities, v_features = torch.empty_like(opacities), torch.empty_like(features)
    backward, global_size, size_args, local_size = _composite_launch(
        device, "backward", features.dtype, channels, width, height
    )
    reduce = _kernel("entries.cl", "reduce_slots", features.dtype, CHANNELS=channels)
    with bind(device) as b:
        entries = _sorted_entry_records(device, b, means2d, conics, opacities, features, sorted_slots, slot_gaussian)
        # [M, 6 + C]: one gradient row per (tile, Gaussian) pair, written once by its tile
        slots = b.scratch(m * (6 + channels) * features.dtype.itemsize)
        image = dict(ranges=b.input(ranges), sorted_slots=b.input(sorted_slots), entries=entries)
        image |= dict(background=b.input(background), T_final=b.input(T_final), n_contrib=b.input(n_contrib))
        grads = dict(v_out=b.input(v_out), v_T=b.input(v_T_final), slot_grads=slots)
        device.launch(backward, global_size, image | grads | size_args, local_size)
        device.launch(
            reduce,
            n,
            dict(slot_grads=slots, first_slot=b.input(first_slot), tiles_touched=b.input(tiles_touched), n=np.int32(n))
            | dict(v_means2d=b.output(v_means2d), v_conics=b.output(v_conics))
            | dict(v_opacities=b.output(v_opacities), v_features=b.output(v_features)),
        )
    return v_means2d, v_conics, v_opacities, v_features


@composite_backward.register_fake
def _composite_backward_fake(means2d, conics, opacities, features, *rest):
    return torch.empty_like(means2d), torch.empty_like(conics), torch.empty_like(opacities), torch.empty_like(features)


def _composite_setup(ctx, inputs, output) -> None:
    *tensors, width, height = inputs
    ctx.save_for_backward(*tensors, output[1], output[2])
    ctx.size = (width, height)


def _composite_backward(ctx, v_out, v_T_final, _v_n_contrib):
    *tensors, T_final, n_contrib = ctx.saved_tensors
    v_out = _grad_or_zeros(v_out, tensors[3].new_empty(T_final.shape + (tensors[3].shape[1],)))
    v_T_final = _grad_or_zeros(v_T_final, T_final)
    v_means2d, v_conics, v_opacities, v_features = composite_backward(
        *tensors, T_final, n_contrib, v_out, v_T_final, *ctx.size
    )
    v_background = (T_final.unsqueeze(-1) * v_out).sum(dim=(0, 1))
    return (v_means2d, v_conics, v_opacities, v_features, v_background) + (None,) * 7


composite.register_autograd(_composite_backward, setup_context=_composite_setup)


# -- public function --------------------------------------------------------------------


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
