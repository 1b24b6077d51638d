"""Tile lists of projected splats, built and sorted on the device (kernels_cl/splat/).

Every visible Gaussian gets one entry per 16x16 tile its 3-sigma box touches; entries are
ordered by (tile, depth) with the device's stable radix sort (clflow.runtime.sort), so the
order, and everything computed from it, is deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from clflow.errors import InputError
from clflow.runtime.arrays import DeviceArray, real_of
from clflow.runtime.bridge import bind
from clflow.runtime.devices import Device, get_device
from clflow.runtime.sort import key_ranges, radix_sort, scan_exclusive
from clflow.splat.constants import SPLAT_DEFINES, TILE_SIZE

DEPTH_DIGIT_BITS = 8  # CPU devices (the sort's blocks shape): 32-bit depth keys in 4 passes of 8 bits
TILE_DIGIT_BITS = 12  # and tile keys in ceil(bits / 12) passes (one pass up to 4096 tiles)
MAX_TILE_ENTRIES = 1 << 26  # bound on (tile, Gaussian) entries: 1.3 GB of lists, + (9 + C) reals of records each
BYTES_PER_ENTRY = 20  # tile key + slot, double-buffered for the sort, + slot's Gaussian id


def tile_grid(width: int, height: int) -> tuple[int, int]:
    """Tiles along x and y covering a width x height image."""
    return -(-width // TILE_SIZE), -(-height // TILE_SIZE)


@dataclass(frozen=True)
class TileLists:
    """The (tile, depth)-sorted entries of one view.

    Attributes:
        ranges: [T, 2] int32, entries [start, end) of tile t (T = tiles_x * tiles_y,
            tile t = ty * tiles_x + tx).
        sorted_slots: [M] int32, slot of each sorted entry.
        slot_gaussian: [M] int32, Gaussian of each slot.
        first_slot: [N] int32, first slot of each Gaussian (its slots are contiguous).
        tiles_touched: [N] int32, number of slots of each Gaussian.
    """

    ranges: torch.Tensor
    sorted_slots: torch.Tensor
    slot_gaussian: torch.Tensor
    first_slot: torch.Tensor
    tiles_touched: torch.Tensor

    @property
    def num_entries(self) -> int:
        return int(self.sorted_slots.shape[0])

    @property
    def nbytes(self) -> int:
        """Device memory the lists take while they are built (sort buffers included)."""
        return self.num_entries * BYTES_PER_ENTRY + self.ranges.numel() * 4 + self.first_slot.numel() * 4


def build_tile_lists(
    means2d: torch.Tensor,
    depths: torch.Tensor,
    radii: torch.Tensor,
    tiles_touched: torch.Tensor,
    width: int,
    height: int,
    device: Device | None = None,
) -> TileLists:
    """(tile, depth)-sorted entries of the projected Gaussians (no autograd).

    Args:
        means2d: [N, 2] pixel positions; depths: [N] camera z (m); radii: [N] int32 pixel
            radii (0: culled); tiles_touched: [N] int32 tiles per Gaussian, from projection.
            Torch tensors give lists of tensors; device arrays
            (:class:`~clflow.runtime.arrays.DeviceArray`) lists of device arrays, nothing
            copied to the host but the entry count.
        width, height: image size (pixels).
    """
    device = device or get_device()
    real = real_of(means2d.dtype, "means2d")
    n = means2d.shape[0]
    tiles_x, tiles_y = tile_grid(width, height)
    n_tiles = tiles_x * tiles_y
    on_device = isinstance(means2d, DeviceArray)

    def kern(name):
        return device.kernel("splat/binning.cl", name, real, SPLAT_DEFINES)

    # checked before the device's int32 scan of the counts can overflow (device arrays: only
    # where the scan could overflow, else its total, below)
    if not on_device or n * n_tiles > np.iinfo(np.int32).max:
        touched = tiles_touched.read() if on_device else tiles_touched
        _check_entries(int(touched.sum(dtype=torch.int64)))
    # the sort's buffers live on the device for this call only; the host reads the entry
    # count and the lists the compositing op takes
    with bind(device) as b:
        # 1. Gaussians by depth; entry offsets in that order
        depth_pairs = [b.scratch(4 * n) for _ in range(4)]
        keys, values = depth_pairs[:2]
        gaussians = dict(depths=b.input(depths), radii=b.input(radii), n=np.int32(n))
        device.launch(kern("depth_keys"), n, gaussians | dict(keys=keys, values=values))
        tile_bits = max(1, (n_tiles - 1).bit_length())
        swapped = radix_sort(device, depth_pairs[:2], depth_pairs[2:], n, 32, DEPTH_DIGIT_BITS)
        order = depth_pairs[3] if swapped else depth_pairs[1]
        counts, offsets = b.scratch(4 * n), b.scratch(4 * (n + 1))
        touched = dict(order=order, tiles_touched=b.input(tiles_touched), counts=counts, n=np.int32(n))
        device.launch(kern("gather_counts"), n, touched)
        scan_exclusive(device, counts, offsets, n)
        m = b.read_element(offsets, n, np.int32)
        _check_entries(m)
        # 2. entries in depth order, 3. stable sort by tile, 4. per-tile ranges
        tile_pairs = [b.scratch(4 * m) for _ in range(4)]
        empty = (lambda *shape: DeviceArray.empty(device, shape, torch.int32)) if on_device else _int32_tensor
        slot_gaussian = empty(m)
        first_slot = empty(n)  # every Gaussian's is written
        ranges = empty(n_tiles, 2)
        ranges.zero_()  # empty tiles stay (0, 0)
        entries = dict(order=order, offsets=offsets, means2d=b.input(means2d), radii=b.input(radii))
        entries |= dict(tile_keys=tile_pairs[0], slots=tile_pairs[1])
        entries |= dict(slot_gaussian=b.output(slot_gaussian), first_slot=b.output(first_slot))
        tiles = dict(n=np.int32(n), tiles_x=np.int32(tiles_x), tiles_y=np.int32(tiles_y))
        device.launch(kern("emit_entries"), n, entries | tiles)
        swapped = radix_sort(device, tile_pairs[:2], tile_pairs[2:], m, tile_bits, TILE_DIGIT_BITS)
        keys, slots = (tile_pairs[2], tile_pairs[3]) if swapped else (tile_pairs[0], tile_pairs[1])
        key_ranges(device, keys, b.inout(ranges), m)
        sorted_slots = empty(m)
        if on_device:
            sorted_slots.copy_from_buffer(slots)
        else:
            b.copy_to(sorted_slots, slots)
    return TileLists(ranges, sorted_slots, slot_gaussian, first_slot, tiles_touched)


def _int32_tensor(*shape: int) -> torch.Tensor:
    return torch.empty(shape, dtype=torch.int32)


def _check_entries(total: int) -> None:
    """InputError when the Gaussians touch more (tile, Gaussian) pairs than MAX_TILE_ENTRIES
    (or so many that the int32 count wrapped)."""
    if total > MAX_TILE_ENTRIES or total < 0:
        raise InputError(
            f"rasterize: the Gaussians touch {total} (tile, Gaussian) pairs, more than the bound "
            f"{MAX_TILE_ENTRIES} ({MAX_TILE_ENTRIES * BYTES_PER_ENTRY / 2**30:.1f} GiB of tile lists, and compositing "
            "records of 9 + channels reals per entry); "
            "render fewer or smaller Gaussians, or a smaller image"
        )
