"""``clflow::splat_covariances``: Sigma = R(q) S S^T R(q)^T from quaternions and scales
(covariance.cl), and its adjoint."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from clflow.runtime.bridge import bind
from clflow.runtime.devices import get_device
from clflow.splat.constants import SPLAT_LANES
from clflow.splat.ops.kernels import splat_kernel


@torch.library.custom_op("clflow::splat_covariances", mutates_args=())
def covariances(quats: Tensor, scales: Tensor) -> Tensor:
    """Sigma = R(q) S S^T R(q)^T [N, 3, 3] (m^2) from quats [N, 4] (w, x, y, z; normalised
    here) and scales [N, 3] (standard deviations, m), on the device."""
    device = get_device()
    n = quats.shape[0]
    covars = quats.new_empty(n, 3, 3)
    with bind(device) as b:
        device.launch(
            splat_kernel("covariance.cl", "covariance_forward", quats.dtype),
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
        device.launch(splat_kernel("covariance.cl", "covariance_backward", quats.dtype), n, gaussians | grads)
    return v_quats, v_scales


@covariances_backward.register_fake
def _covariances_backward_fake(quats, scales, v_covars):
    return torch.empty_like(quats), torch.empty_like(scales)


def _covariances_setup(ctx, inputs, output) -> None:
    ctx.save_for_backward(*inputs)


def _covariances_grad(ctx, v_covars):
    return covariances_backward(*ctx.saved_tensors, v_covars.contiguous())


covariances.register_autograd(_covariances_grad, setup_context=_covariances_setup)
