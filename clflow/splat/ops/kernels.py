"""What every splat op shares: its kernels by name, built for the tensors' dtype, and the
zero gradient of an output that backward was not given."""

from __future__ import annotations

import torch
from torch import Tensor

from clflow.runtime.arrays import real_of
from clflow.runtime.devices import get_device
from clflow.splat.constants import SPLAT_DEFINES


def splat_kernel(source: str, name: str, dtype: torch.dtype, **defines):
    """The cached kernel ``name`` of ``kernels_cl/splat/<source>`` for ``dtype``."""
    return get_device().kernel(f"splat/{source}", name, real_of(dtype, name), {**SPLAT_DEFINES, **defines})


def grad_or_zeros(grad: Tensor | None, like: Tensor) -> Tensor:
    """``grad`` made contiguous, or zeros shaped like ``like`` where autograd gave None (an
    output nothing used)."""
    return torch.zeros_like(like) if grad is None else grad.contiguous()
