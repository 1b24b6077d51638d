"""``clflow::splat_project``: EWA projection of the Gaussians into one view, culling and
radii (project.cl), and its adjoint."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from clflow.runtime.bridge import bind
from clflow.runtime.devices import get_device
from clflow.splat.constants import SPLAT_LANES
from clflow.splat.ops.kernels import grad_or_zeros, splat_kernel


def _projection_args(b, means, covars, viewmat, K, width: int, height: int) -> dict:
    """The projection kernels' inputs (bound by ``b``), the count and the image size."""
    gaussians = dict(means=b.input(means), covars=b.input(covars), n=np.int32(means.shape[0]))
    return gaussians | dict(
        viewmat=b.input(viewmat), intrinsics=b.input(K), width=np.int32(width), height=np.int32(height)
    )


def launch_project(device, b, gaussians: tuple, view: tuple, outputs: tuple) -> None:
    """Enqueue the projection (project.cl) on tensors or device arrays bound by ``b``:
    ``gaussians`` (means [N, 3], covars [N, 3, 3], viewmat [4, 4], K [3, 3]), ``view``
    (width, height, near) and ``outputs`` (means2d [N, 2], conics [N, 3], depths [N], radii
    [N] int32, tiles_touched [N] int32), as :func:`project` documents them."""
    means, covars, viewmat, K = gaussians
    width, height, near = view
    n = means.shape[0]
    kern = splat_kernel("project.cl", "project_forward", means.dtype)
    near_real = np.float64(near) if means.dtype == torch.float64 else np.float32(near)
    splats = _projection_args(b, means, covars, viewmat, K, width, height) | dict(near_plane=near_real)
    names = ("means2d", "conics", "depths", "radii", "tiles_touched")
    outputs = {name: b.output(out) for name, out in zip(names, outputs)}
    device.launch(kern, -(-n // SPLAT_LANES), splats | outputs)


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
    i32 = dict(dtype=torch.int32)
    outputs = (
        means.new_empty(n, 2),
        means.new_empty(n, 3),
        means.new_empty(n),
        torch.empty(n, **i32),
        torch.empty(n, **i32),
    )
    with bind(device) as b:
        launch_project(device, b, (means, covars, viewmat, K), (width, height, near), outputs)
    return outputs


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
    v_means = torch.empty_like(means)
    v_covars = torch.empty_like(covars)
    with bind(device) as b:
        launch_project_backward(
            device,
            b,
            (means, covars, viewmat, K, radii),
            (v_means2d, v_conics, v_depths),
            (v_means, v_covars),
            width,
            height,
        )
    return v_means, v_covars


def launch_project_backward(device, b, gaussians: tuple, grads: tuple, outputs: tuple, width: int, height: int, n=None):
    """Enqueue the projection's adjoint on tensors or device arrays bound by ``b``:
    ``gaussians`` (means, covars, viewmat, K, radii), ``grads`` (v_means2d, v_conics,
    v_depths), ``outputs`` (v_means [N, 3], v_covars [N, 3, 3]) of the first ``n`` Gaussians
    (default all N)."""
    means, covars, viewmat, K, radii = gaussians
    n = means.shape[0] if n is None else n
    kern = splat_kernel("project.cl", "project_backward", means.dtype)
    splats = _projection_args(b, means, covars, viewmat, K, width, height) | dict(radii=b.input(radii), n=np.int32(n))
    v_means2d, v_conics, v_depths = grads
    args = dict(v_means2d=b.input(v_means2d), v_conics=b.input(v_conics), v_depths=b.input(v_depths))
    args |= dict(v_means=b.output(outputs[0]), v_covars=b.output(outputs[1]))
    device.launch(kern, n, splats | args)


@project_backward.register_fake
def _project_backward_fake(means, covars, viewmat, K, radii, v_means2d, v_conics, v_depths, width, height):
    return torch.empty_like(means), torch.empty_like(covars)


def _project_setup(ctx, inputs, output) -> None:
    means, covars, viewmat, K, width, height, _near = inputs
    ctx.save_for_backward(means, covars, viewmat, K, output[3])
    ctx.size = (width, height)


def _project_backward(ctx, v_means2d, v_conics, v_depths, _v_radii, _v_tiles):
    means, covars, viewmat, K, radii = ctx.saved_tensors
    grads = (
        grad_or_zeros(v_means2d, means.new_empty(means.shape[0], 2)),
        grad_or_zeros(v_conics, means.new_empty(means.shape[0], 3)),
        grad_or_zeros(v_depths, means.new_empty(means.shape[0])),
    )
    v_means, v_covars = project_backward(means, covars, viewmat, K, radii, *grads, *ctx.size)
    return v_means, v_covars, None, None, None, None, None


project.register_autograd(_project_backward, setup_context=_project_setup)
