"""Tile lists of projected splats, built and sorted on the device (kernels_cl/splat/).

Every visible Gaussian gets one entry per 16x16 tile its 3-sigma box touches; entries are
ordered by (tile, depth) with a stable radix sort of our own (kernels_cl/splat/sort.cl), so
the order, and everything computed from it, is deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from clflow.errors import InputError
from clflow.runtime.bridge import real_of
from clflow.runtime.devices import Device, get_device
from clflow.splat.constants import SPLAT_DEFINES, TILE_SIZE

SORT_BLOCKS = 64  # radix sort: contiguous blocks walked by one work-item each
DEPTH_DIGIT_BITS = 8  # 32-bit depth keys: 4 passes of 8 bits
TILE_DIGIT_BITS = 12  # tile keys: ceil(bits / 12) passes (one pass up to 4096 tiles)
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


def _radix_sort(device: Device, b, pair, spare, n: int, key_bits: int, digit_bits: int) -> bool:
    """Sort the first n (key, value) pairs of bound buffers by the low key_bits of the key.

    ``pair`` and ``spare`` are (keys, values) buffers; the passes ping-pong between them.
    Returns True when the result ends in ``spare``. Stable: equal keys keep their order.
    """
    if n == 0:
        return False
    passes = -(-key_bits // digit_bits)
    width = -(-key_bits // passes)  # equal digits: 10 bits -> one pass of 10, not 8 + 2
    hist = b.scratch(4 * ((1 << width) * SORT_BLOCKS + 1))
    block_len = np.int32(-(-n // SORT_BLOCKS))
    histogram = device.kernel("splat/sort.cl", "radix_histogram")
    scan = device.kernel("splat/sort.cl", "scan_exclusive")
    scatter = device.kernel("splat/sort.cl", "radix_scatter")
    blocks = np.int32(SORT_BLOCKS)
    src, dst = pair, spare
    for p in range(passes):
        shift = np.int32(p * width)
        mask = np.uint32((1 << min(width, key_bits - p * width)) - 1)
        n_hist = np.int32((int(mask) + 1) * SORT_BLOCKS)
        # local size 1: the blocks are independent work-groups, spread over all cores
        device.launch(histogram, SORT_BLOCKS, [src[0], np.int32(n), shift, mask, hist, blocks, block_len], 1)
        device.launch(scan, 1, [hist, hist, n_hist], 1)
        device.launch(scatter, SORT_BLOCKS, [*src, *dst, np.int32(n), shift, mask, hist, blocks, block_len], 1)
        src, dst = dst, src
    return passes % 2 == 1


def sort_pairs(keys: torch.Tensor, values: torch.Tensor, key_bits: int = 32, device: Device | None = None):
    """Stable sort of int32 ``values`` by the low ``key_bits`` of ``keys`` read as uint32.

    Returns (sorted keys, sorted values), both [n] int32: the device's radix sort.
    """
    device = device or get_device()
    if keys.shape != values.shape or keys.dim() != 1:
        raise InputError(f"sort_pairs: keys {tuple(keys.shape)} and values {tuple(values.shape)} must be equal 1-D")
    if not 1 <= key_bits <= 32:
        raise InputError(f"sort_pairs: key_bits must be in 1..32, got {key_bits}")
    n = keys.shape[0]
    tensors = [keys.to(torch.int32).clone(), values.to(torch.int32).clone()]
    tensors += [torch.empty(n, dtype=torch.int32) for _ in range(2)]
    with device.bind() as b:
        bufs = [b.inout(t) for t in tensors]
        swapped = _radix_sort(device, b, bufs[:2], bufs[2:], n, key_bits, DEPTH_DIGIT_BITS)
    return tuple(tensors[2:]) if swapped else tuple(tensors[:2])


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
        width, height: image size (pixels).
    """
    device = device or get_device()
    real = real_of(means2d.dtype, "means2d")
    n = means2d.shape[0]
    tiles_x, tiles_y = tile_grid(width, height)
    n_tiles = tiles_x * tiles_y

    def kern(name):
        return device.kernel("splat/binning.cl", name, real, SPLAT_DEFINES)

    # checked before the device's int32 scan of the counts can overflow
    total = int(tiles_touched.sum(dtype=torch.int64))
    if total > MAX_TILE_ENTRIES:
        raise InputError(
            f"rasterize: the Gaussians touch {total} (tile, Gaussian) pairs, more than the bound "
            f"{MAX_TILE_ENTRIES} ({MAX_TILE_ENTRIES * BYTES_PER_ENTRY / 2**30:.1f} GiB of tile lists, and compositing "
            "records of 9 + channels reals per entry); "
            "render fewer or smaller Gaussians, or a smaller image"
        )
    scan = device.kernel("splat/sort.cl", "scan_exclusive")
    # the sort's buffers live on the device for this call only; the host reads the entry
    # count and the lists the compositing op takes
    with device.bind() as b:
        # 1. Gaussians by depth; entry offsets in that order
        depth_pairs = [b.scratch(4 * n) for _ in range(4)]
        device.launch(kern("depth_keys"), n, [b.input(depths), b.input(radii), *depth_pairs[:2], np.int32(n)])
        swapped = _radix_sort(device, b, depth_pairs[:2], depth_pairs[2:], n, 32, DEPTH_DIGIT_BITS)
        order = depth_pairs[3] if swapped else depth_pairs[1]
        counts, offsets = b.scratch(4 * n), b.scratch(4 * (n + 1))
        device.launch(kern("gather_counts"), n, [order, b.input(tiles_touched), counts, np.int32(n)])
        device.launch(scan, 1, [counts, offsets, np.int32(n)], 1)
        m = b.read_element(offsets, n, np.int32)
        # 2. entries in depth order, 3. stable sort by tile, 4. per-tile ranges
        tile_pairs = [b.scratch(4 * m) for _ in range(4)]
        slot_gaussian = torch.empty(m, dtype=torch.int32)
        first_slot = torch.empty(n, dtype=torch.int32)  # every Gaussian's is written
        ranges = torch.zeros(n_tiles, 2, dtype=torch.int32)  # empty tiles stay (0, 0)
        device.launch(
            kern("emit_entries"),
            n,
            [
                order,
                offsets,
                b.input(means2d),
                b.input(radii),
                *tile_pairs[:2],
                b.output(slot_gaussian),
                b.output(first_slot),
                np.int32(n),
                np.int32(tiles_x),
                np.int32(tiles_y),
            ],
        )
        tile_bits = max(1, (n_tiles - 1).bit_length())
        swapped = _radix_sort(device, b, tile_pairs[:2], tile_pairs[2:], m, tile_bits, TILE_DIGIT_BITS)
        keys, slots = (tile_pairs[2], tile_pairs[3]) if swapped else (tile_pairs[0], tile_pairs[1])
        device.launch(kern("tile_ranges"), m, [keys, b.inout(ranges), np.int32(m)])
        sorted_slots = torch.empty(m, dtype=torch.int32)
        b.copy_to(sorted_slots, slots)
    return TileLists(ranges, sorted_slots, slot_gaussian, first_slot, tiles_touched)
