"""Scans and sorts on the device (kernels_cl/common/scan.cl, sort.cl), each in the shape the
device's plan asks for (clflow.runtime.plan): one work-item or a few contiguous blocks on CPU
devices, work-groups cooperating in local memory on GPUs. Every result depends on the input
alone, so it repeats to the bit; the sorts are stable.

    scan_exclusive(device, counts, offsets, n)          # offsets[i] = sum(counts[:i]), offsets[n] the total
    swapped = radix_sort(device, (keys, values), (keys2, values2), n, key_bits, digit_bits)
    # the sorted pairs are in (keys2, values2) when swapped, else in (keys, values)
    counting_sort(device, keys, n, n_keys, counts, rank, order)   # keys < n_keys, one pass

The rasteriser sorts its tile entries by radix sort, the simulator its particles by grid cell
by counting sort. pyopencl's own scan and radix sort (``pyopencl.scan``,
``pyopencl.algorithm.RadixSort``) are not used: they need Mako at run time, generate their
kernels per call signature, and their radix sort scans every key once per bit (n x 2^bits
scan work per pass); these kernels take clflow's DeviceArrays and scratch, are checked by its
launch signatures, and count into its kernel profile.
"""

from __future__ import annotations

import numpy as np
import torch

from clflow.errors import InputError
from clflow.runtime.arrays import DeviceArray
from clflow.runtime.devices import Device, get_device
from clflow.runtime.plan import STAGE_KERNELS, kernel_plan

SORT_BLOCKS = 64  # blocks shape: contiguous blocks walked by one work-item each
DIGIT_BITS = 8  # blocks shape: bits per pass of 32-bit keys (4 passes)
SCAN_WG, SCAN_BLOCK = 256, 2048  # kernels_cl/common/scan.h: work-group size, elements per work-group
# blocks up to which a work-group adds the block sums before its block itself (each reads
# fewer than this many; all together fewer than its square, 4 M at most): beyond, the sums are
# scanned recursively
SCAN_SUMMED_BLOCKS = 2048
RADIX_BITS, RADIX_BLOCK = 4, 1024  # sort.cl: the work-group shape's digit bits and pairs per work-group


def digit_width(key_bits: int, digit_bits: int) -> int:
    """Bits of each pass's digit: ``key_bits`` cut into equal passes of at most ``digit_bits``."""
    passes = -(-key_bits // digit_bits)
    return -(-key_bits // passes)


def _blocks(n: int, per_block: int) -> int:
    return max(1, -(-n // per_block))


def scan_exclusive(device: Device, src, dst, n: int, block_sums: tuple | None = None) -> None:
    """dst[i] = sum of src[:i] for i = 0..n (int32; dst holds n + 1, dst[n] the total). ``src``
    and ``dst`` may be the same buffer. ``block_sums`` (buffer, first index): where the sums
    of src's blocks of SCAN_BLOCK elements already lie (counted with the elements: the
    counting sort's), which spares the work-group shape its reduce pass."""
    if kernel_plan(device).scan == "serial" or n <= 0:  # nothing to scan: the one work-item writes the 0
        scan = device.kernel(*STAGE_KERNELS["scan"]["serial"]["scan"])
        device.launch(scan, 1, {"in": src, "out": dst, "n": np.int32(n)}, 1)
        return
    _scan_workgroups(device, src, dst, n, block_sums)


def _scan_workgroups(device: Device, src, dst, n: int, block_sums: tuple | None = None) -> None:
    """Reduce-then-scan: the block sums (unless ``block_sums`` holds them), then each block
    offset by the sums before it (which its work-group adds up; up to SCAN_SUMMED_BLOCKS
    blocks), else by the sums scanned the same way (recursively)."""
    blocks = _blocks(n, SCAN_BLOCK)
    kernels = STAGE_KERNELS["scan"]["workgroup"]
    scan_blocks = device.kernel(*kernels["blocks"])
    args = {"in": src, "out": dst, "n": np.int32(n)}
    if blocks == 1:
        device.launch(scan_blocks, SCAN_WG, args | dict(offsets=dst, has_offsets=np.int32(0)), SCAN_WG)
        return
    summed = blocks <= SCAN_SUMMED_BLOCKS  # each block adds the sums before it: one launch after the sums
    given = summed and block_sums is not None
    if given:
        sums, first = block_sums
    else:
        sums, first = device.take_scratch(4 * blocks), 0
        device.launch(
            device.kernel(*kernels["block_sums"]),
            blocks * SCAN_WG,
            {"in": src, "n": np.int32(n), "sums": sums},
            SCAN_WG,
        )
    if summed:
        summed_args = args | dict(sums=sums, sums_at=np.int32(first))
        device.launch(device.kernel(*kernels["summed"]), blocks * SCAN_WG, summed_args, SCAN_WG)
        if not given:
            device.give_back_scratch(sums)
        return
    offsets = device.take_scratch(4 * (blocks + 1))
    _scan_workgroups(device, sums, offsets, blocks)
    device.launch(scan_blocks, blocks * SCAN_WG, args | dict(offsets=offsets, has_offsets=np.int32(1)), SCAN_WG)
    # the in-order queue runs every later use of these buffers after the commands above
    device.give_back_scratch(sums)
    device.give_back_scratch(offsets)


def radix_sort(device: Device, pair, spare, n: int, key_bits: int, digit_bits: int = DIGIT_BITS) -> bool:
    """Stable sort of the first ``n`` (uint32 key, int32 value) pairs of device buffers
    ``pair`` by the low ``key_bits`` of the key, ping-ponging with ``spare``. ``digit_bits``
    is the blocks shape's digit (a CPU's cache holds its 2^digit_bits x 64 counters); the
    work-group shape takes RADIX_BITS, what its local memory holds. Returns True when the
    result ends in ``spare``."""
    if n == 0:
        return False
    plan = kernel_plan(device)
    workgroups = plan.sort == "workgroup"
    width = digit_width(key_bits, RADIX_BITS if workgroups else digit_bits)
    passes = -(-key_bits // width)
    blocks = _blocks(n, RADIX_BLOCK) if workgroups else SORT_BLOCKS
    hist = device.take_scratch(4 * ((1 << width) * blocks + 1))
    histogram, scatter = (
        device.kernel(*plan.kernel("sort", "histogram")),
        device.kernel(*plan.kernel("sort", "scatter")),
    )
    src, dst = pair, spare
    for p in range(passes):
        shift = np.int32(p * width)
        mask = np.uint32((1 << min(width, key_bits - p * width)) - 1)
        digit = dict(n=np.int32(n), shift=shift, mask=mask, nblocks=np.int32(blocks))
        pairs = dict(keys_in=src[0], values_in=src[1], keys_out=dst[0], values_out=dst[1])
        if workgroups:
            device.launch(histogram, blocks * SCAN_WG, digit | dict(keys=src[0], hist=hist), SCAN_WG)
            scan_exclusive(device, hist, hist, (int(mask) + 1) * blocks)
            device.launch(scatter, blocks * SCAN_WG, digit | pairs | dict(starts=hist), SCAN_WG)
        else:
            # local size 1: the blocks are independent work-groups, spread over all cores
            block_len = dict(block_len=np.int32(-(-n // SORT_BLOCKS)))
            device.launch(histogram, SORT_BLOCKS, digit | block_len | dict(keys=src[0], hist=hist), 1)
            scan_exclusive(device, hist, hist, (int(mask) + 1) * SORT_BLOCKS)
            device.launch(scatter, SORT_BLOCKS, digit | block_len | pairs | dict(starts=hist), 1)
        src, dst = dst, src
    device.give_back_scratch(hist)
    return passes % 2 == 1


def counts_length(n_keys: int) -> int:
    """Length of a counting sort's ``counts`` for keys in [0, n_keys): a count per key, the
    total, then a count per block of SCAN_BLOCK keys (the scan's block sums)."""
    return n_keys + 1 + _blocks(n_keys, SCAN_BLOCK)


def counting_sort(
    device: Device,
    keys,
    n: int,
    n_keys: int,
    counts,
    rank,
    order,
    starts=None,
    counted: bool = False,
    order_runs: bool = True,
) -> None:
    """``order`` [n] int32: the indices 0..n-1 sorted by ``keys`` [n] (uint32, each < n_keys),
    equal keys in index order; ``starts`` [n_keys + 1] int32 (default: ``counts``, scanned in
    place): where each key's run begins (starts[n_keys] = n). ``counts``
    [counts_length(n_keys)] and ``rank`` [n] int32: scratch. ``counted``: the caller has
    already zeroed ``counts``, counted the keys and their blocks into it and written each
    one's rank (common/sort.cl count_keys, or a kernel that computes the keys and counts
    them at once: mpm/cells.h count_cell). ``order_runs`` False: each run is left in the order
    the atomics placed it, for the caller to put in index order (common/runs.h) as it reads it."""
    if not counted:
        counts.zero_()
        device.launch(
            device.kernel("common/sort.cl", "count_keys"),
            n,
            dict(keys=keys, n=np.int32(n), n_keys=np.int32(n_keys), counts=counts, rank=rank),
        )
    starts = counts if starts is None else starts
    scan_exclusive(device, counts, starts, n_keys, block_sums=(counts, n_keys + 1))
    placed = dict(keys=keys, rank=rank, starts=starts, n=np.int32(n), order=order)
    device.launch(device.kernel("common/sort.cl", "place_keys"), n, placed)
    if order_runs:
        runs = dict(starts=starts, n_keys=np.int32(n_keys), order=order)
        device.launch(device.kernel("common/sort.cl", "order_runs"), n_keys, runs)


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
    swapped = radix_sort(device, arrays[:2], arrays[2:], n, key_bits)
    result = arrays[2:] if swapped else arrays[:2]
    return result[0].read(), result[1].read()


def sort_by_key(keys: torch.Tensor, n_keys: int, device: Device | None = None):
    """The counting sort of int ``keys`` [n] (each in [0, n_keys)): returns (order [n], the
    indices by key, equal keys in index order; starts [n_keys + 1], each key's first position)."""
    device = device or get_device()
    if keys.dim() != 1:
        raise InputError(f"sort_by_key: keys must be 1-D, got {tuple(keys.shape)}")
    n = keys.shape[0]
    if n and (int(keys.min()) < 0 or int(keys.max()) >= n_keys):
        raise InputError(f"sort_by_key: keys must lie in [0, {n_keys})")
    key_array = DeviceArray.of(device, keys.to(torch.int32))
    counts = DeviceArray.empty(device, (counts_length(n_keys),), torch.int32)
    rank, order = (DeviceArray.empty(device, (max(n, 1),), torch.int32) for _ in range(2))
    counting_sort(device, key_array, n, n_keys, counts, rank, order)
    return order.read()[:n], counts.read()[: n_keys + 1]
