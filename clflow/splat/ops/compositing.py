"""``clflow::splat_composite``: front-to-back compositing of the sorted splats per tile, in the
shape the device's kernel plan picks (rasterize_tile_rows.cl for CPUs, rasterize_workgroup.cl for GPUs),
over per-entry records (entries.cl); and its adjoint, back to front, with the per-(tile,
Gaussian) gradient slots summed per Gaussian in a fixed order."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from clflow.errors import DeviceError
from clflow.runtime.bridge import bind
from clflow.runtime.devices import get_device
from clflow.runtime.plan import kernel_plan
from clflow.splat.binning import tile_grid
from clflow.splat.constants import TILE_SIZE
from clflow.splat.ops.kernels import grad_or_zeros, splat_kernel

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
    kernel = lambda name: splat_kernel("entries.cl", name, features.dtype, CHANNELS=channels)  # noqa: E731
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

    - "tile_rows" (rasterize_tile_rows.cl): a work-item per 16 x 16 tile, each its own work-group, so
      the busy tiles spread over the cores;
    - "workgroup" (rasterize_workgroup.cl): a work-group of TILE_PIXELS work-items per tile, one
      per pixel, entries staged in local memory in batches sized to LOCAL_MEM_BYTES.
    """
    tiles_x, tiles_y = tile_grid(width, height)
    n_tiles = tiles_x * tiles_y
    image = dict(width=np.int32(width), height=np.int32(height), tiles_x=np.int32(tiles_x))
    plan = kernel_plan(device)
    source, entry = plan.kernel("raster", direction)
    source = source.removeprefix("splat/")
    if plan.raster == "tile_rows":
        kern = splat_kernel(source, entry, dtype, CHANNELS=channels)
        return kern, n_tiles, image | dict(n_tiles=np.int32(n_tiles)), 1
    if device.info.max_work_group_size < TILE_PIXELS:
        raise DeviceError(
            f"{device.info.name}: work-groups of at most {device.info.max_work_group_size} work-items, the tiled "
            f"compositing kernels need {TILE_PIXELS}; run the CPU shape (CLFLOW_KERNELS=cpu)"
        )
    local_bytes = min(device.info.local_mem_size, MAX_RASTER_LOCAL_BYTES)
    kern = splat_kernel(source, entry, dtype, CHANNELS=channels, LOCAL_MEM_BYTES=local_bytes)
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
    out = features.new_empty(height, width, features.shape[1])
    T_final = features.new_empty(height, width)
    n_contrib = torch.empty(height, width, dtype=torch.int32)
    with bind(device) as b:
        splats = (means2d, conics, opacities, features, background)
        launch_composite(device, b, splats, (ranges, sorted_slots, slot_gaussian), (out, T_final, n_contrib))
    return out, T_final, n_contrib


def launch_composite(device, b, splats: tuple, tiles: tuple, outputs: tuple) -> None:
    """Enqueue the compositing on tensors or device arrays bound by ``b``: ``splats``
    (means2d, conics, opacities, features, background), ``tiles`` (ranges, sorted_slots,
    slot_gaussian of the tile lists), ``outputs`` (out [H, W, C], T_final [H, W], n_contrib
    [H, W] int32), as :func:`composite` documents them."""
    means2d, conics, opacities, features, background = splats
    ranges, sorted_slots, slot_gaussian = tiles
    out, T_final, n_contrib = outputs
    height, width = T_final.shape
    kern, global_size, size_args, local_size = _composite_launch(
        device, "forward", features.dtype, features.shape[1], width, height
    )
    entries = _sorted_entry_records(device, b, means2d, conics, opacities, features, sorted_slots, slot_gaussian)
    image = dict(ranges=b.input(ranges), entries=entries, background=b.input(background))
    image |= dict(out=b.output(out), T_final=b.output(T_final), n_contrib=b.output(n_contrib))
    device.launch(kern, global_size, image | size_args, local_size)


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
    v_means2d, v_conics = torch.empty_like(means2d), torch.empty_like(conics)
    v_opacities, v_features = torch.empty_like(opacities), torch.empty_like(features)
    outputs = (v_means2d, v_conics, v_opacities, v_features)
    with bind(device) as b:
        splats = (means2d, conics, opacities, features, background)
        tiles = (ranges, sorted_slots, slot_gaussian, first_slot, tiles_touched)
        launch_composite_backward(device, b, splats, tiles, (T_final, n_contrib, v_out, v_T_final), outputs)
    return outputs


def launch_composite_backward(device, b, splats: tuple, tiles: tuple, grads: tuple, outputs: tuple, n=None) -> None:
    """Enqueue the compositing's adjoint on tensors or device arrays bound by ``b``:
    ``splats`` and ``tiles`` (all five lists) as :func:`composite_backward` takes them,
    ``grads`` (T_final, n_contrib, v_out, v_T_final), ``outputs`` (v_means2d, v_conics,
    v_opacities, v_features) of the first ``n`` Gaussians (default all N)."""
    means2d, conics, opacities, features, background = splats
    ranges, sorted_slots, slot_gaussian, first_slot, tiles_touched = tiles
    T_final, n_contrib, v_out, v_T_final = grads
    height, width = T_final.shape
    n = features.shape[0] if n is None else n
    channels, m = features.shape[1], sorted_slots.shape[0]
    backward, global_size, size_args, local_size = _composite_launch(
        device, "backward", features.dtype, channels, width, height
    )
    reduce = splat_kernel("entries.cl", "reduce_slots", features.dtype, CHANNELS=channels)
    entries = _sorted_entry_records(device, b, means2d, conics, opacities, features, sorted_slots, slot_gaussian)
    # [M, 6 + C]: one gradient row per (tile, Gaussian) pair, written once by its tile
    slots = b.scratch(m * (6 + channels) * features.dtype.itemsize)
    image = dict(ranges=b.input(ranges), sorted_slots=b.input(sorted_slots), entries=entries)
    image |= dict(background=b.input(background), T_final=b.input(T_final), n_contrib=b.input(n_contrib))
    device.launch(
        backward,
        global_size,
        image | dict(v_out=b.input(v_out), v_T=b.input(v_T_final), slot_grads=slots) | size_args,
        local_size,
    )
    v_means2d, v_conics, v_opacities, v_features = (b.output(out) for out in outputs)
    device.launch(
        reduce,
        n,
        dict(slot_grads=slots, first_slot=b.input(first_slot), tiles_touched=b.input(tiles_touched), n=np.int32(n))
        | dict(v_means2d=v_means2d, v_conics=v_conics, v_opacities=v_opacities, v_features=v_features),
    )


@composite_backward.register_fake
def _composite_backward_fake(means2d, conics, opacities, features, *rest):
    return torch.empty_like(means2d), torch.empty_like(conics), torch.empty_like(opacities), torch.empty_like(features)


def _composite_setup(ctx, inputs, output) -> None:
    *tensors, width, height = inputs
    ctx.save_for_backward(*tensors, output[1], output[2])
    ctx.size = (width, height)


def _composite_backward(ctx, v_out, v_T_final, _v_n_contrib):
    *tensors, T_final, n_contrib = ctx.saved_tensors
    v_out = grad_or_zeros(v_out, tensors[3].new_empty(T_final.shape + (tensors[3].shape[1],)))
    v_T_final = grad_or_zeros(v_T_final, T_final)
    v_means2d, v_conics, v_opacities, v_features = composite_backward(
        *tensors, T_final, n_contrib, v_out, v_T_final, *ctx.size
    )
    v_background = (T_final.unsqueeze(-1) * v_out).sum(dim=(0, 1))
    return (v_means2d, v_conics, v_opacities, v_features, v_background) + (None,) * 7


composite.register_autograd(_composite_backward, setup_context=_composite_setup)
