"""Deterministic column sums and atomic scatter-add, as torch ops over OpenCL kernels.

:func:`column_sum` is also the worked example of how clflow defines a torch op from OpenCL
kernels (see docs/architecture.md, "Writing a torch op").
"""

from __future__ import annotations

import numpy as np
import torch

from clflow.errors import InputError
from clflow.runtime.arrays import real_of
from clflow.runtime.bridge import bind, check_tensor
from clflow.runtime.devices import Device, get_device

REDUCE_WG = 64  # work-group size of the reduction: part of its fixed summation order
ROWS_PER_ITEM = 16  # rows each work-item adds before the in-group halving
_REDUCE_DEFINES = {"REDUCE_WG": REDUCE_WG, "ROWS_PER_ITEM": ROWS_PER_ITEM}


def sum_rows(x: torch.Tensor, device: Device | None = None) -> torch.Tensor:
    """Sum ``x`` [N, K] (float32/float64) over rows into [K] float64, in a fixed order.

    Bit-identical across runs on a device (see kernels_cl/common/reduce.cl); no autograd.
    """
    device = device or get_device()
    if x.dim() != 2:
        raise InputError(f"sum_rows: expected a 2-D [N, K] tensor, got shape {tuple(x.shape)}")
    real = real_of(x.dtype, "sum_rows")
    check_tensor(x, "sum_rows input")
    n, k = x.shape
    out = torch.zeros(k, dtype=torch.float64)
    if n == 0 or k == 0:
        return out
    device.require_real("double")  # the accumulator is double whatever the input
    chunk = REDUCE_WG * ROWS_PER_ITEM
    first = device.kernel("common/reduce.cl", "sum_rows_partial", real, _REDUCE_DEFINES)
    rest = device.kernel("common/reduce.cl", "sum_rows_partial_acc", real, _REDUCE_DEFINES)
    with bind(device) as b:
        src, kernel, rows = b.input(x), first, n
        while True:
            groups = -(-rows // chunk)
            dst = b.output(out) if groups == 1 else b.scratch(groups * k * 8)
            device.launch(
                kernel,
                (groups * REDUCE_WG, k),
                dict(x=src, partial=dst, n=np.int32(rows), k=np.int32(k)),
                (REDUCE_WG, 1),
            )
            if groups == 1:
                break
            src, kernel, rows = dst, rest, groups
    return out


def scatter_add(values: torch.Tensor, index: torch.Tensor, size: int, device: Device | None = None) -> torch.Tensor:
    """``out[index[i]] += values[i]`` with atomic adds; values [N] or [N, W], index [N] int.

    Returns out [size] or [size, W] of the values' dtype. The addition order is not fixed:
    use for GPU paths; CPU paths in clflow reduce private copies in a fixed order instead.
    """
    device = device or get_device()
    real = real_of(values.dtype, "scatter_add values")
    if index.dim() != 1 or values.shape[:1] != index.shape:
        raise InputError(f"scatter_add: values {tuple(values.shape)} and index {tuple(index.shape)} disagree")
    width = 1 if values.dim() == 1 else int(np.prod(values.shape[1:]))
    idx = index.to(torch.int32).contiguous()
    if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= size):
        raise InputError(f"scatter_add: index out of range [0, {size})")
    values = values.contiguous()
    out = values.new_zeros((size,) + tuple(values.shape[1:]))
    n = idx.numel()
    if n == 0:
        return out
    kernel = device.kernel("common/scatter_add.cl", "scatter_add", real)
    with bind(device) as b:
        args = dict(values=b.input(values), index=b.input(idx), out=b.inout(out), n=np.int32(n), width=np.int32(width))
        device.launch(kernel, n, args)
    return out


@torch.library.custom_op("clflow::column_sum", mutates_args=())
def column_sum(x: torch.Tensor) -> torch.Tensor:
    """Differentiable deterministic column sum: x [N, K] float32/64 -> [K] float64."""
    return sum_rows(x.contiguous())


@column_sum.register_fake
def _column_sum_fake(x: torch.Tensor) -> torch.Tensor:
    return x.new_empty((x.shape[1],), dtype=torch.float64)


def _column_sum_setup(ctx, inputs, output) -> None:
    (x,) = inputs
    ctx.rows, ctx.dtype = x.shape[0], x.dtype


def _column_sum_backward(ctx, grad: torch.Tensor):
    return grad.to(ctx.dtype).unsqueeze(0).expand(ctx.rows, -1).contiguous()


column_sum.register_autograd(_column_sum_backward, setup_context=_column_sum_setup)
