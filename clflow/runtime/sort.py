"""A stable radix sort of (uint32 key, int32 value) pairs on the device, and an exclusive
prefix sum and each key's range in the sorted keys (kernels_cl/common/sort.cl): every position depends on the keys alone, so the
result is deterministic and equal keys keep their order. The rasteriser sorts its tile
entries with it, the simulator its particles by grid cell.

    swapped = radix_sort(device, (keys, values), (keys2, values2), n, key_bits, digit_bits, hist)
    # the sorted pairs are in (keys2, values2) when swapped, else in (keys, values)
"""

from __future__ import annotations

import numpy as np
import torch

from clflow.errors import InputError
from clflow.runtime.arrays import DeviceArray
from clflow.runtime.devices import Device, get_device

SORT_BLOCKS = 64  # contiguous blocks walked by one work-item each
DIGIT_BITS = 8  # bits per pass of 32-bit keys: 4 passes


def digit_width(key_bits: int, digit_bits: int) -> int:
    """Bits of each pass's digit: ``key_bits`` cut into equal passes of at most ``digit_bits``."""
    passes = -(-key_bits // digit_bits)
    return -(-key_bits // passes)


def histogram_bytes(key_bits: int, digit_bits: int) -> int:
    """Bytes of the histogram buffer :func:`radix_sort` needs."""
    return 4 * ((1 << digit_width(key_bits, digit_bits)) * SORT_BLOCKS + 1)


def radix_sort(device: Device, pair, spare, n: int, key_bits: int, digit_bits: int, hist) -> bool:
    """Sort the first ``n`` (key, value) pairs of device buffers ``pair`` by the low
    ``key_bits`` of the key, ping-ponging with ``spare``; ``hist`` holds at least
    :func:`histogram_bytes`. Returns True when the result ends in ``spare``."""
    if n == 0:
        return False
    passes = -(-key_bits // digit_bits)
    width = digit_width(key_bits, digit_bits)
    block_len = np.int32(-(-n // SORT_BLOCKS))
    histogram = device.kernel("common/sort.cl", "radix_histogram")
    scan = device.kernel("common/sort.cl", "scan_exclusive")
    scatter = device.kernel("common/sort.cl", "radix_scatter")
    blocks = np.int32(SORT_BLOCKS)
    src, dst = pair, spare
    for p in range(passes):
        shift = np.int32(p * width)
        mask = np.uint32((1 << min(width, key_bits - p * width)) - 1)
        n_hist = np.int32((int(mask) + 1) * SORT_BLOCKS)
        # local size 1: the blocks are independent work-groups, spread over all cores
        digit = dict(n=np.int32(n), shift=shift, mask=mask, nblocks=blocks, block_len=block_len)
        device.launch(histogram, SORT_BLOCKS, digit | dict(keys=src[0], hist=hist), 1)
        device.launch(scan, 1, {"in": hist, "out": hist, "n": n_hist}, 1)
        pairs = dict(keys_in=src[0], values_in=src[1], keys_out=dst[0], values_out=dst[1])
        device.launch(scatter, SORT_BLOCKS, digit | pairs | dict(starts=hist), 1)
        src, dst = dst, src
    return passes % 2 == 1


def scan_exclusive(device: Device, src, dst, n: int) -> None:
    """dst[i] = sum of src[:i] for i = 0..n (dst holds n + 1 int32; dst[n] the total)."""
    device.launch(device.kernel("common/sort.cl", "scan_exclusive"), 1, {"in": src, "out": dst, "n": np.int32(n)}, 1)


def key_ranges(device: Device, keys, ranges, n: int) -> None:
    """ranges[k] = [start, end) of key k in the first ``n`` sorted ``keys`` (ranges [K, 2]
    int32, filled with zeros beforehand for the keys that do not occur)."""
    device.launch(device.kernel("common/sort.cl", "key_ranges"), n, dict(keys=keys, ranges=ranges, n=np.int32(n)))


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
    arrays = [DeviceArray.of(device, keys.to(torch.int32)), DeviceArray.of(device, values.to(torch.int32))]
    arrays += [DeviceArray.empty(device, (n,), torch.int32) for _ in range(2)]
    hist = DeviceArray.empty(device, (histogram_bytes(key_bits, DIGIT_BITS) // 4,), torch.int32)
    swapped = radix_sort(device, arrays[:2], arrays[2:], n, key_bits, DIGIT_BITS, hist)
    result = arrays[2:] if swapped else arrays[:2]
    return result[0].read(), result[1].read()
