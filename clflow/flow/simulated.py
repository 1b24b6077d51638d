"""Simulated optical flow of moving Gaussians, differentiable.

The per-Gaussian part is pure torch; :func:`render_simulated_flow` blends it with the
OpenCL rasteriser (``clflow.splat.rasterize_gaussians``).

Between frames t and t+1 each Gaussian i moves its projected mean mu_i (px) by
dmu_i = mu_i(t+1) - mu_i(t) and changes its 2D covariance from Sigma_i(t) to Sigma_i(t+1).
Two per-Gaussian flow models, both rendered as feature channels of the rasteriser at
frame t's geometry and blended with the weights alpha_i T_i:

- ``"mean"``: flow_i(x) = dmu_i (the projected displacement);
- ``"affine"``: flow_i(x) = (A_i - I)(x - mu_i) + dmu_i, where A_i maps the 2D Gaussian
  of frame t onto that of frame t+1: A_i Sigma_i(t) A_i^T = Sigma_i(t+1).

Such an A is not unique (so is A S Q S^-1 for any orthogonal Q, S = Sigma(t)^1/2); clflow
takes the unique symmetric positive-definite one, the optimal-transport (Monge) map
between the two Gaussians, A = S^-1 (S Sigma(t+1) S)^1/2 S^-1 with S = Sigma(t)^1/2.
Covariances carry no rotation about the Gaussian's own axes, so a rotation-free A is the
least motion the data supports; A = L(t+1) L(t)^-1 with Cholesky factors L (one published
choice) adds a shear that depends on the image axes. The affine flow is affine in the pixel
x, so it renders exactly as 5 channels: the entries (a - 1, b, c - 1) of the symmetric
A_i - I and o_i = dmu_i - (A_i - I) mu_i; the pixel's flow is M(x) x + o(x) from the
blended M and o.

Pixels: continuous coordinates with pixel (i, j) centred at (j + 0.5, i + 0.5), as in the
rasteriser; flows in pixels per frame step.
"""

from __future__ import annotations

from typing import Literal

import torch

from clflow.errors import InputError
from clflow.splat.constants import EPS2D

#: Rendered opacity below which a pixel has no simulated flow when normalising by alpha.
MIN_ALPHA = 1e-2

FlowModel = Literal["mean", "affine"]


def _camera_points(means: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    """[..., N, 3] world points (m) to camera coordinates (OpenCV axes, m)."""
    viewmat = viewmat.to(means.dtype)
    return means @ viewmat[:3, :3].T + viewmat[:3, 3]


def project_means(means: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Pinhole projection of [..., N, 3] world points (m) to [..., N, 2] pixels.

    viewmat: [4, 4] world-to-camera (OpenCV axes); K: [3, 3] intrinsics (px)."""
    p = _camera_points(means, viewmat) @ K.to(means.dtype).T
    return p[..., :2] / p[..., 2:3]


# Symmetric 2x2 matrices [[a, b], [b, c]] as component triples: closed forms beat batched
# torch.linalg calls on millions of tiny matrices by an order of magnitude.


def _sym(M: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return M[..., 0, 0], 0.5 * (M[..., 0, 1] + M[..., 1, 0]), M[..., 1, 1]


def _mat(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    return torch.stack([torch.stack([a, b], -1), torch.stack([b, c], -1)], -2)


def _sqrt_sym(a, b, c):
    """Principal square root of an SPD matrix: (M + sqrt(det M) I) / sqrt(tr M + 2 sqrt(det M))
    (Cayley-Hamilton)."""
    s = torch.sqrt(a * c - b * b)
    t = torch.sqrt(a + c + 2.0 * s)
    return (a + s) / t, b / t, (c + s) / t


def _inv_sym(a, b, c):
    det = a * c - b * b
    return c / det, -b / det, a / det


def _sandwich(p, q, r, x, y, z):
    """P X P for symmetric P = (p, q, r) and X = (x, y, z); symmetric again."""
    u, v = p * x + q * y, p * y + q * z  # first row of P X
    w, k = q * x + r * y, q * y + r * z  # second row
    return p * u + q * v, q * u + r * v, q * w + r * k


def covariance_2d(
    means: torch.Tensor, covars: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, eps2d: float = EPS2D
) -> torch.Tensor:
    """[..., N, 2, 2] image-plane covariances (px^2) of Gaussians with [..., N, 3] means (m)
    and [..., N, 3, 3] symmetric world covariances (m^2): J W Sigma W^T J^T + eps2d I (EWA
    splatting, J the projection's Jacobian at the mean). Unlike the rasteriser, J is not
    clamped to 1.3x the field of view: that only differs for Gaussians far outside the image."""
    dtype = means.dtype
    K, viewmat = K.to(dtype), viewmat.to(dtype)
    x, y, z = _camera_points(means, viewmat).unbind(-1)
    zero = torch.zeros_like(z)
    fx, fy, skew = K[0, 0], K[1, 1], K[0, 1]
    J = torch.stack(
        [
            torch.stack([fx / z, skew / z, -(fx * x + skew * y) / z**2], -1),
            torch.stack([zero, fy / z, -fy * y / z**2], -1),
        ],
        -2,
    )  # [..., N, 2, 3]
    T = J @ viewmat[:3, :3]
    return T @ covars @ T.transpose(-1, -2) + eps2d * torch.eye(2, dtype=dtype, device=means.device)


def _transport_sym(sigma0, sigma1):
    S = _sqrt_sym(*sigma0)
    return _sandwich(*_inv_sym(*S), *_sqrt_sym(*_sandwich(*S, *sigma1)))


def sqrtm_spd_2x2(M: torch.Tensor) -> torch.Tensor:
    """Principal square root of symmetric positive-definite [..., 2, 2] matrices, differentiable."""
    return _mat(*_sqrt_sym(*_sym(M)))


def gaussian_transport_map(sigma0: torch.Tensor, sigma1: torch.Tensor) -> torch.Tensor:
    """The symmetric positive-definite A with A sigma0 A^T = sigma1 ([..., 2, 2] SPD
    covariances): A = S^-1 (S sigma1 S)^1/2 S^-1, S = sigma0^1/2."""
    return _mat(*_transport_sym(_sym(sigma0), _sym(sigma1)))


def flow_features(
    means_t: torch.Tensor,
    means_t1: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    *,
    model: FlowModel = "mean",
    covars_t: torch.Tensor | None = None,
    covars_t1: torch.Tensor | None = None,
    eps2d: float = EPS2D,
) -> torch.Tensor:
    """Per-Gaussian flow features for the rasteriser, from the Gaussians at frames t, t+1.

    Args:
        means_t, means_t1: [N, 3] world positions (m) at frames t and t+1.
        viewmat: [4, 4] world-to-camera (OpenCV axes); K: [3, 3] intrinsics (px).
        model: ``"mean"`` (projected displacement) or ``"affine"`` (also the change of the
            2D covariance; needs ``covars_t``, ``covars_t1`` [N, 3, 3] in m^2).

    Returns:
        [N, 2] dmu (px) for ``"mean"``; [N, 5] for ``"affine"``: the symmetric A - I as
        (a - 1, b, c - 1), then o = dmu - (A - I) mu (px).
    """
    if means_t.shape != means_t1.shape or means_t.shape[-1] != 3:
        raise InputError(
            f"simulated flow: means at t and t+1 must both be [N, 3], got {tuple(means_t.shape)} and {tuple(means_t1.shape)}"
        )
    mu_t = project_means(means_t, viewmat, K)
    dmu = project_means(means_t1, viewmat, K) - mu_t
    if model == "mean":
        return dmu
    if model != "affine":
        raise InputError(f"unknown simulated-flow model {model!r}; choose 'mean' or 'affine'")
    if covars_t is None or covars_t1 is None:
        raise InputError("the 'affine' simulated-flow model needs covars_t and covars_t1 ([N, 3, 3] world covariances)")
    a, b, c = _transport_sym(
        _sym(covariance_2d(means_t, covars_t, viewmat, K, eps2d)),
        _sym(covariance_2d(means_t1, covars_t1, viewmat, K, eps2d)),
    )
    u, v = mu_t.unbind(-1)
    offset = dmu - torch.stack([(a - 1.0) * u + b * v, b * u + (c - 1.0) * v], -1)  # dmu - (A - I) mu
    return torch.cat([torch.stack([a - 1.0, b, c - 1.0], -1), offset], -1)


def pixel_centres(height: int, width: int, dtype=torch.float64, device=None) -> torch.Tensor:
    """[H, W, 2] continuous coordinates (x, y) of the pixel centres (j + 0.5, i + 0.5)."""
    v = torch.arange(height, dtype=dtype, device=device) + 0.5
    u = torch.arange(width, dtype=dtype, device=device) + 0.5
    return torch.stack(torch.meshgrid(u, v, indexing="xy"), -1)


def flow_from_features(
    features: torch.Tensor, alpha: torch.Tensor | None = None, min_alpha: float = MIN_ALPHA
) -> torch.Tensor:
    """Per-pixel flow [H, W, 2] (px) from rendered flow features [H, W, 2 | 5].

    Two channels are the flow itself; five are an affine field M x + o with M symmetric,
    stored as (M_xx, M_xy, M_yy, o_x, o_y) (see :func:`flow_features`).

    With ``alpha`` ([H, W, 1], the rendered opacity) the flow is divided by alpha: the
    blended flow of the Gaussians alone, not pulled towards zero at soft edges. Pixels
    with alpha below ``min_alpha`` get zero flow (their flow is undefined and 1/alpha
    would blow up the gradient).
    """
    if features.dim() != 3 or features.shape[-1] not in (2, 5):
        raise InputError(f"flow features must be [H, W, 2] or [H, W, 5], got {tuple(features.shape)}")
    if features.shape[-1] == 2:
        flow = features
    else:
        height, width = features.shape[:2]
        x = pixel_centres(height, width, features.dtype, features.device)
        m_xx, m_xy, m_yy, o_x, o_y = features.unbind(-1)
        u, v = x.unbind(-1)
        flow = torch.stack([m_xx * u + m_xy * v + o_x, m_xy * u + m_yy * v + o_y], -1)
    if alpha is not None:
        alpha = alpha.to(flow.dtype)
        covered = alpha >= min_alpha
        flow = torch.where(covered, flow / torch.where(covered, alpha, torch.ones_like(alpha)), torch.zeros_like(flow))
    return flow


def render_simulated_flow(
    means_t: torch.Tensor,
    means_t1: torch.Tensor,
    covars_t: torch.Tensor,
    opacities: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    *,
    model: FlowModel = "mean",
    covars_t1: torch.Tensor | None = None,
    normalize: bool = True,
    near: float = 0.01,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Render the simulated optical flow from frame t to t+1, differentiably.

    The per-Gaussian flow features (:func:`flow_features`) are rasterised as colour
    channels at frame t's geometry (means_t, covars_t), then turned into a per-pixel flow.

    Args:
        means_t, means_t1: [N, 3] world positions (m) at frames t and t+1.
        covars_t: [N, 3, 3] world covariances (m^2) at frame t.
        opacities: [N] in [0, 1].
        viewmat: [4, 4] world-to-camera (OpenCV axes); K: [3, 3] intrinsics (px).
        width, height: image size (px).
        model: ``"mean"`` or ``"affine"`` (needs ``covars_t1`` [N, 3, 3], m^2).
        normalize: divide by the rendered alpha (see :func:`flow_from_features`).

    Returns:
        flow [H, W, 2] (px per frame step) and alpha [H, W, 1].

    A Gaussian that is not in front of the near plane at both frames (a camera inside or
    passing through the object) has no projected motion: its features are 0 (finite, and
    with a zero gradient) instead of the NaN of a projection through the camera centre; it is
    drawn where it is at frame t (culled there when not in front of the near plane).
    """
    from clflow.splat.ops import rasterize_gaussians

    depth_t, depth_t1 = _camera_points(means_t, viewmat)[..., 2], _camera_points(means_t1, viewmat)[..., 2]
    ahead = (depth_t > near) & (depth_t1 > near)
    moving_t, moving_t1 = means_t, means_t1
    if not bool(ahead.all()):
        # their features from a point in front of the camera instead, then dropped; each is
        # still drawn where it is at frame t (culled there when behind the near plane)
        W, t = viewmat[:3, :3].to(means_t.dtype), viewmat[:3, 3].to(means_t.dtype)
        in_front = (torch.tensor([0.0, 0.0, 1.0], dtype=means_t.dtype, device=means_t.device) - t) @ W
        moving_t = torch.where(ahead[:, None], means_t, in_front)
        moving_t1 = torch.where(ahead[:, None], means_t1, in_front)
    features = flow_features(moving_t, moving_t1, viewmat, K, model=model, covars_t=covars_t, covars_t1=covars_t1)
    if not bool(ahead.all()):
        features = torch.where(ahead[:, None], features, torch.zeros_like(features))
    image, alpha, _, _ = rasterize_gaussians(
        means_t,
        None,
        None,
        opacities,
        features,
        viewmat,
        K,
        width,
        height,
        covars=covars_t,
        near=near,
        render_depth=False,
    )
    return flow_from_features(image, alpha if normalize else None), alpha
