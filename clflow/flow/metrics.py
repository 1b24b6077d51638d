"""Flow metrics: end-point error, the least-squares slope of one flow on another (the
observed flow's scale bias) and ECMS, the paper's motion score.

Flows (velocity fields) are [T, H, W, 2] (or [H, W, 2]) arrays in pixels per frame step;
masks are [H, W] or [T, H, W], bool or weights >= 0 (ECMS uses the pixels of weight > 0).
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


def _weights(mask, shape: tuple[int, ...], what: str) -> np.ndarray:
    """float64 weights of shape ``shape`` from a bool or weight mask (None: ones)."""
    if mask is None:
        return np.ones(shape)
    mask = np.asarray(mask.detach().cpu() if hasattr(mask, "detach") else mask, dtype=np.float64)
    try:
        mask = np.broadcast_to(mask, shape)
    except ValueError:
        raise InputError(f"{what}: mask shape {mask.shape} does not match flows of shape {shape} + (2,)") from None
    if not np.isfinite(mask).all() or (mask < 0).any():
        raise InputError(f"{what}: mask weights must be finite and >= 0")
    if not mask.any():
        raise InputError(f"{what}: the mask is all zero")
    return mask


def _pair(flow, reference, what: str) -> tuple[np.ndarray, np.ndarray]:
    flow, reference = _as_array(flow, what), _as_array(reference, f"{what} reference")
    if flow.shape != reference.shape:
        raise InputError(f"{what}: flow shapes differ, {flow.shape} and {reference.shape}")
    return flow, reference


def endpoint_error(flow, reference, mask=None) -> float:
    """Mean end-point error |flow - reference| in pixels over the masked pixels (weighted
    mean for a weight mask)."""
    flow, reference = _pair(flow, reference, "EPE")
    error = np.linalg.norm(flow - reference, axis=-1)
    weight = _weights(mask, error.shape, "EPE")
    return float((weight * error).sum() / weight.sum())


def flow_slope(flow, reference, mask=None) -> float:
    """Least-squares scale s of ``flow`` on ``reference`` over the masked pixels:
    s = sum w flow.reference / sum w |reference|^2, the minimiser of sum w |flow - s reference|^2.
    1 is unbiased; below 1 ``flow`` underestimates the motion of ``reference``."""
    flow, reference = _pair(flow, reference, "flow slope")
    weight = _weights(mask, flow.shape[:-1], "flow slope")
    motion = (weight * np.sum(reference * reference, axis=-1)).sum()
    if motion <= 0:
        raise InputError("flow slope: the reference flow is zero wherever the mask is set")
    return float((weight * np.sum(flow * reference, axis=-1)).sum() / motion)


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
        mask: bool [H, W] (or [T, H, W]) pixels to score (or weights: those > 0); None: all pixels.
    """
    v = _as_array(velocity, "ECMS")
    if v.ndim == 3:
        v = v[None]
    if v.ndim != 4:
        raise InputError(f"ECMS: velocity must be [T, H, W, 2], got shape {v.shape}")
    m = _weights(mask, v.shape[:-1], "ECMS") > 0
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
