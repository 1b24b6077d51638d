"""Flow losses (the supervision of material identification) and the render-loss ablation.

All flows are [..., H, W, 2] tensors in pixels per frame step; masks are [..., H, W]
(bool, or weights >= 0 such as the loss mask times the observed flow's confidence)
broadcastable against the flows' leading shape. A loss is the weighted per-pixel mean
sum(w e) / sum(w): a pixel of weight 0 adds nothing to it or to its gradient, and uniform
weights give the plain masked mean.
"""

from __future__ import annotations

import torch

from clflow.errors import InputError

#: Weight of D-SSIM in the render loss, 3DGS's lambda_dssim.
SSIM_WEIGHT = 0.2
#: SSIM window size (pixels), the Gaussian window of Wang et al. 2004 and 3DGS.
SSIM_WINDOW = 11


def _finite(t: torch.Tensor, what: str) -> None:
    if not torch.isfinite(t).all():
        raise InputError(f"{what} contains NaN or infinite values")


def _masked_mean(per_pixel: torch.Tensor, mask: torch.Tensor | None, what: str) -> torch.Tensor:
    """sum(w v) / sum(w) of per-pixel values v [..., H, W] and mask weights w."""
    if mask is None:
        return per_pixel.mean()
    mask = torch.as_tensor(mask, device=per_pixel.device)
    try:
        weight = torch.broadcast_to(mask.to(per_pixel.dtype), per_pixel.shape)
    except RuntimeError:
        raise InputError(
            f"{what}: mask shape {tuple(mask.shape)} does not match flows of shape {tuple(per_pixel.shape)} + (2,)"
        ) from None
    _finite(weight, f"{what}: mask")
    if bool((weight < 0).any()):
        raise InputError(f"{what}: the mask has negative weights")
    total = weight.sum()
    if total <= 0:
        raise InputError(f"{what}: the mask is all zero, there is no pixel to compare")
    return (weight * per_pixel).sum() / total


def _difference(simulated: torch.Tensor, observed: torch.Tensor, what: str) -> torch.Tensor:
    if simulated.shape[-1] != 2 or simulated.shape != observed.shape:
        raise InputError(
            f"{what}: simulated and observed flows must have one [..., H, W, 2] shape, got "
            f"{tuple(simulated.shape)} and {tuple(observed.shape)}"
        )
    _finite(observed, f"{what}: observed flow")
    _finite(simulated.detach(), f"{what}: simulated flow")
    return simulated - observed.to(simulated.dtype)


def masked_flow_loss(simulated: torch.Tensor, observed: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """PhysFlow's flow loss: squared endpoint error |U_sim - U_obs|^2 (px^2), averaged over
    the masked pixels of all frames (the paper sums over frames; the mean makes the scale
    independent of frame count and image size, the optimum is the same)."""
    d = _difference(simulated, observed, "flow loss")
    return _masked_mean((d * d).sum(-1), mask, "flow loss")


def charbonnier_flow_loss(
    simulated: torch.Tensor, observed: torch.Tensor, mask: torch.Tensor | None = None, eps: float = 1e-3
) -> torch.Tensor:
    """Robust flow loss: sqrt(|U_sim - U_obs|^2 + eps^2) (px), averaged over the masked pixels.

    Quadratic for errors below ``eps`` pixels, linear above: outliers of the observed flow
    (occlusions, textureless areas) pull less than in the L2 loss."""
    d = _difference(simulated, observed, "Charbonnier flow loss")
    return _masked_mean(torch.sqrt((d * d).sum(-1) + eps * eps), mask, "Charbonnier flow loss")


def render_loss(rendered: torch.Tensor, target: torch.Tensor, ssim_weight: float = SSIM_WEIGHT) -> torch.Tensor:
    """Photometric loss of the paper's ablation (3DGS's): (1 - w) L1 + w (1 - SSIM).

    Args:
        rendered, target: [..., H, W, C] images with values in [0, 1] (C channels).
        ssim_weight: w, the weight of the D-SSIM term.

    SSIM is kornia's (11 px Gaussian window, sigma 1.5, max value 1); note that
    ``kornia.losses.ssim_loss`` would halve the D-SSIM term, so it is not used.
    """
    if rendered.shape != target.shape or rendered.dim() < 3:
        raise InputError(
            f"render loss: images must have one [..., H, W, C] shape, got {tuple(rendered.shape)} and {tuple(target.shape)}"
        )
    _finite(target, "render loss: target image")
    target = target.to(rendered.dtype)
    l1 = (rendered - target).abs().mean()
    return (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - ssim(rendered, target))


def ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM (kornia: SSIM_WINDOW px Gaussian window, sigma 1.5, max value 1) of images
    [..., H, W, C] of one shape; differentiable."""
    import kornia

    height, width, channels = image.shape[-3:]
    as_batch = lambda x: x.reshape(-1, height, width, channels).permute(0, 3, 1, 2)  # noqa: E731
    return kornia.metrics.ssim(as_batch(image), as_batch(target), SSIM_WINDOW, max_val=1.0).mean()
