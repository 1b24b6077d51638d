"""Flow metrics: end-point error and ECMS, the paper's motion score.

Flows (velocity fields) are [T, H, W, 2] (or [H, W, 2]) arrays in pixels per frame step;
masks are bool [H, W] or [T, H, W].
"""

from __future__ import annotations

import numpy as np

from clflow.errors import InputError

#: ECMS weight of the inverse-motion term (the paper's alpha).
ECMS_ALPHA = 0.1


def _as_array(x, what: str) -> np.ndarray:
    x = np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=np.float64)
    if x.ndim < 3 or x.shape[-1] != 2:
        raise InputError(f"{what}: a flow must be [..., H, W, 2], got shape {x.shape}")
    if not np.isfinite(x).all():
        raise InputError(f"{what}: the flow contains NaN or infinite values")
    return x


def _mask(mask, shape: tuple[int, ...], what: str) -> np.ndarray:
    if mask is None:
        return np.ones(shape, bool)
    mask = np.asarray(mask.detach().cpu() if hasattr(mask, "detach") else mask).astype(bool)
    try:
        mask = np.broadcast_to(mask, shape)
    except ValueError:
        raise InputError(f"{what}: mask shape {mask.shape} does not match flows of shape {shape} + (2,)") from None
    if not mask.any():
        raise InputError(f"{what}: the mask is all zero")
    return mask


def endpoint_error(flow, reference, mask=None) -> float:
    """Mean end-point error |flow - reference| in pixels over the masked pixels."""
    flow, reference = _as_array(flow, "EPE"), _as_array(reference, "EPE reference")
    if flow.shape != reference.shape:
        raise InputError(f"EPE: flow shapes differ, {flow.shape} and {reference.shape}")
    error = np.linalg.norm(flow - reference, axis=-1)
    return float(error[_mask(mask, error.shape, "EPE")].mean())


def ecms(velocity, mask=None, alpha: float = ECMS_ALPHA) -> float:
    """ECMS motion score of a flow sequence (lower: smoother motion that still moves).

    The velocity field v_t is the optical flow of frame t (px per frame step), as in the
    paper's E = sum_t ||v_t+1 - v_t||^2 + ||lap v_t||^2 + alpha / sum_t ||v_t||. clflow
    takes each norm as a per-pixel mean over the mask M so that the score does not grow
    with the image size:

        E = sum_{t=0}^{T-2} mean_{x in M} |v_{t+1}(x) - v_t(x)|^2            (temporal)
          + sum_{t=0}^{T-1} mean_{x in M'} |lap v_t(x)|^2                     (spatial)
          + alpha / sum_{t=0}^{T-1} mean_{x in M} |v_t(x)|                    (motion)

    lap is the 5-point Laplacian (px^-1 per frame) and M' the pixels of M whose four
    neighbours are in M too (the Laplacian is not taken across the mask edge or the
    frame border). The motion term is inf for a flow that is zero everywhere.

    Args:
        velocity: [T, H, W, 2] flows, T >= 1.
        mask: bool [H, W] (or [T, H, W]) pixels to score; None: all pixels.
    """
    v = _as_array(velocity, "ECMS")
    if v.ndim == 3:
        v = v[None]
    if v.ndim != 4:
        raise InputError(f"ECMS: velocity must be [T, H, W, 2], got shape {v.shape}")
    m = _mask(mask, v.shape[:-1], "ECMS")
    temporal = sum(
        float(np.sum((v[t + 1] - v[t]) ** 2, axis=-1)[m[t] & m[t + 1]].mean()) if (m[t] & m[t + 1]).any() else 0.0
        for t in range(v.shape[0] - 1)
    )
    interior = m[:, 1:-1, 1:-1] & m[:, :-2, 1:-1] & m[:, 2:, 1:-1] & m[:, 1:-1, :-2] & m[:, 1:-1, 2:]
    lap = v[:, :-2, 1:-1] + v[:, 2:, 1:-1] + v[:, 1:-1, :-2] + v[:, 1:-1, 2:] - 4.0 * v[:, 1:-1, 1:-1]
    lap2 = np.sum(lap**2, axis=-1)
    spatial = sum(float(lap2[t][interior[t]].mean()) for t in range(v.shape[0]) if interior[t].any())
    motion = sum(float(np.linalg.norm(v[t], axis=-1)[m[t]].mean()) for t in range(v.shape[0]) if m[t].any())
    return temporal + spatial + (alpha / motion if motion > 0 else float("inf"))
