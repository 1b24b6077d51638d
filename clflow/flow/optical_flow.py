"""Observed optical flow of a guidance video, masks of where it can be trusted.

    flows = observed_flow(video.frames)                         # DIS "fine": [T-1, H, W, 2] px
    confidence = flow_confidence(flows, backward_flow(video.frames))  # [T-1, H, W] in [0, 1]
    mask = mask_from_box((40, 30, 200, 180), video.width, video.height)

Flow convention (OpenCV's, Middlebury's): ``flow[t, i, j] = (du, dv)`` in pixels moves
pixel (i, j) of frame t to (j + du, i + dv) in frame t+1; u to the right, v down.
No backend downloads anything: DIS and Farneback are OpenCV's, RAFT runs only from a
weights file already on disk.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Literal, Sequence

import numpy as np

from clflow.errors import ClflowError, InputError

FlowMethod = Literal["dis", "farneback", "raft"]
#: DIS presets, fastest to most accurate: OpenCV's three, whose finest pyramid level is a
#: quarter (ultrafast, fast) or half (medium) of the image size, and ``fine``: medium
#: refined down to full resolution.
DIS_PRESETS = ("ultrafast", "fast", "medium", "fine")
#: The defaults: the least biased settings measured (docs/flow.md, "Observed-flow bias").
DEFAULT_PRESET = "fine"
#: Per-pixel confidence of the observed flow (:func:`observed_confidence`).
CONFIDENCES = ("none", "forward_backward")
DEFAULT_CONFIDENCE = "forward_backward"
#: What the optimiser does about the estimator's systematic error (clflow.pipeline.fit):
#: ``simulated`` measures it on the simulation's own rendered video and subtracts it.
BIAS_CORRECTIONS = ("none", "simulated")
DEFAULT_BIAS_CORRECTION = "simulated"


def _grey(frame: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY) if frame.ndim == 3 else frame


def _check_frames(frames: np.ndarray, source: str) -> None:
    if frames.ndim not in (3, 4) or frames.dtype != np.uint8:
        raise InputError(f"{source}: frames must be a [T, H, W(, 3)] uint8 array, got {frames.dtype} {frames.shape}")
    if frames.shape[0] < 2:
        raise InputError(f"{source}: optical flow needs at least 2 frames, the video has {frames.shape[0]}")


def _dis(preset: str):
    import cv2

    presets = {
        "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
        "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
        "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
        "fine": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
    }
    if preset not in presets:
        raise InputError(f"unknown DIS preset {preset!r}; choose one of {', '.join(DIS_PRESETS)}")
    dis = cv2.DISOpticalFlow.create(presets[preset])
    if preset == "fine":
        dis.setFinestScale(0)  # pyramid level 0: the full-resolution image
    return dis


def observed_flow(
    frames: np.ndarray,
    method: FlowMethod = "dis",
    *,
    preset: str = DEFAULT_PRESET,
    raft_weights: str | os.PathLike | None = None,
    source: str = "video",
    advance: Callable[[str], None] | None = None,
) -> np.ndarray:
    """Forward optical flow between consecutive frames.

    Args:
        frames: [T, H, W, 3] uint8 RGB (or [T, H, W] grey), T >= 2.
        method: ``dis`` (OpenCV DIS, default), ``farneback`` or ``raft`` (torchvision RAFT,
            only with ``raft_weights``, a state-dict file on disk).
        preset: DIS quality preset, one of :data:`DIS_PRESETS`.
        source: name of the video in error messages.
        advance: called with the method's name after each of the T-1 flow fields (progress).

    Returns:
        [T-1, H, W, 2] float32 flow in pixels (see the module docstring).
    """
    import cv2

    frames = np.asarray(frames)
    _check_frames(frames, source)
    if method == "raft":
        return raft_flow(frames, raft_weights, source=source, advance=advance)
    if raft_weights is not None:
        raise InputError(f"raft_weights given but method is {method!r}; use method='raft'")
    grey = [_grey(f) for f in frames]
    if method == "dis":
        pair_flow = _dis(preset).calc
    elif method == "farneback":
        # Pyramid of 5 levels (scale 0.5) reaches ~30 px motion; 15 px windows, 3 iterations.
        def pair_flow(a, b, _):
            return cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 5, 15, 3, 7, 1.5, cv2.OPTFLOW_FARNEBACK_GAUSSIAN)
    else:
        raise InputError(f"unknown optical flow method {method!r}; choose 'dis', 'farneback' or 'raft'")
    flows = []
    for a, b in zip(grey[:-1], grey[1:]):
        flows.append(pair_flow(a, b, None))
        if advance is not None:
            advance(method)
    return np.stack(flows).astype(np.float32)


def shift_mean_flow(
    wide: np.ndarray, margin: int, shifts: Sequence[tuple[int, int]], estimate: Callable[[np.ndarray], np.ndarray]
) -> np.ndarray:
    """The mean of a flow estimator's answers [T-1, H, W, 2] (px) over whole-pixel shifts of
    the camera: an estimate smoother in the motion than one (DIS's patch grid is fixed to the
    image corner, so its answer jumps as the content moves across it).

    ``wide``: [T, H + 2 margin, W + 2 margin(, 3)] frames, ``margin`` pixels more on each side
    than the images estimated. For each (dx, dy) of ``shifts`` (|dx|, |dy| <= margin) the
    estimator runs on the crop whose pixel (i, j) is pixel (i + dy, j + dx) of the central
    crop (the view moved by whole pixels: no resampling); its answer is moved back onto the
    central crop's pixels, and each pixel's mean is over the shifts that saw it, (0, 0)
    being one so that every pixel is seen. ``estimate``: frames -> [T-1, h, w, 2] flow."""
    wide = np.asarray(wide)
    height, width = wide.shape[1] - 2 * margin, wide.shape[2] - 2 * margin
    if height <= 0 or width <= 0:
        raise InputError(f"frames of {wide.shape[1]}x{wide.shape[2]} px have no room for a {margin} px margin")
    if (0, 0) not in shifts or any(max(abs(dx), abs(dy)) > margin for dx, dy in shifts):
        raise InputError(f"shifts {list(shifts)} must hold (0, 0) and stay within the {margin} px margin")
    total = np.zeros((wide.shape[0] - 1, height, width, 2))
    seen = np.zeros((height, width))
    for dx, dy in shifts:
        crop = wide[:, margin + dy : margin + dy + height, margin + dx : margin + dx + width]
        flow = estimate(np.ascontiguousarray(crop))
        # the crop's pixel (i, j) is the central crop's (i + dy, j + dx)
        rows = slice(max(0, dy), height + min(0, dy))
        cols = slice(max(0, dx), width + min(0, dx))
        total[:, rows, cols] += flow[:, max(0, -dy) : height - max(0, dy), max(0, -dx) : width - max(0, dx)]
        seen[rows, cols] += 1
    return total / seen[None, :, :, None]


def backward_flow(frames: np.ndarray, method: FlowMethod = "dis", **kwargs) -> np.ndarray:
    """Backward flow [T-1, H, W, 2] (px): entry t takes frame t+1 to frame t. The
    forward flow of the reversed video, reversed; ``kwargs`` as :func:`observed_flow`'s."""
    return observed_flow(np.ascontiguousarray(np.asarray(frames)[::-1]), method, **kwargs)[::-1].copy()


def raft_flow(
    frames: np.ndarray,
    weights: str | os.PathLike | None,
    *,
    source: str = "video",
    advance: Callable[[str], None] | None = None,
) -> np.ndarray:
    """Forward flow by torchvision's RAFT (large) from a state-dict file already on disk;
    ``advance("raft")`` after each flow field.

    torchvision is not a dependency of clflow and nothing is downloaded: a missing
    torchvision or weights file is a clear :class:`ClflowError`.
    """
    _check_frames(frames, source)
    if weights is None:
        raise InputError("the RAFT backend needs a weights file on disk (raft_weights=PATH / --raft-weights PATH)")
    weights = Path(weights)
    if not weights.is_file():
        raise InputError(f"{weights}: RAFT weights file not found")
    try:
        from torchvision.models.optical_flow import raft_large
    except Exception as exc:  # ImportError, or a torchvision built for another torch
        raise ClflowError(f"the RAFT backend needs torchvision, which cannot be imported here ({exc})") from None
    import torch

    try:
        state = torch.load(weights, map_location="cpu", weights_only=True)
        model = raft_large(weights=None)
        model.load_state_dict(state)
    except Exception as exc:
        raise InputError(f"{weights}: not a torchvision RAFT-large state dict ({exc})") from None
    model.eval()
    if frames.ndim == 3:
        frames = np.repeat(frames[..., None], 3, axis=-1)
    height, width = frames.shape[1:3]
    if height % 8 or width % 8:
        raise InputError(f"{source}: RAFT needs frame sizes divisible by 8, got {width}x{height}")
    images = torch.from_numpy(frames).permute(0, 3, 1, 2).float() / 127.5 - 1.0  # RAFT expects [-1, 1]
    flows = []
    with torch.no_grad():
        for t in range(len(frames) - 1):
            flows.append(model(images[t : t + 1], images[t + 1 : t + 2])[-1][0])
            if advance is not None:
                advance("raft")
    return torch.stack(flows).permute(0, 2, 3, 1).numpy().astype(np.float32)


def warp_flow(flow_b: np.ndarray, flow_f: np.ndarray) -> np.ndarray:
    """Sample ``flow_b`` [H, W, 2] at x + flow_f(x) (bilinear, border replicated)."""
    import cv2

    height, width = flow_f.shape[:2]
    jj, ii = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    map_x, map_y = jj + flow_f[..., 0], ii + flow_f[..., 1]
    return cv2.remap(
        flow_b.astype(np.float32),
        map_x.astype(np.float32),
        map_y.astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )


def _consistency(forward: np.ndarray, backward: np.ndarray, alpha1: float, alpha2: float):
    """Forward-backward consistency of each pixel x: the ratio |w + w_b|^2 / (alpha1 (|w|^2 +
    |w_b|^2) + alpha2) with w = forward(x), w_b = backward(x + w) (float [..., H, W]), and
    whether x + w lies in the frame (bool [..., H, W])."""
    forward, backward = np.asarray(forward), np.asarray(backward)
    if forward.shape != backward.shape or forward.shape[-1] != 2:
        raise InputError(
            f"forward and backward flows must have one [..., H, W, 2] shape, got {forward.shape} and {backward.shape}"
        )
    lead = forward.shape[:-3]
    f = forward.reshape(-1, *forward.shape[-3:])
    b = backward.reshape(-1, *backward.shape[-3:])
    height, width = f.shape[1:3]
    jj, ii = np.meshgrid(np.arange(width), np.arange(height))
    ratio = np.empty(f.shape[:-1], np.float32)
    inside = np.empty(f.shape[:-1], bool)
    for k in range(f.shape[0]):
        wb = warp_flow(b[k], f[k])
        err = np.sum((f[k] + wb) ** 2, axis=-1)
        ratio[k] = err / (alpha1 * (np.sum(f[k] ** 2, axis=-1) + np.sum(wb**2, axis=-1)) + alpha2)
        x, y = jj + f[k][..., 0], ii + f[k][..., 1]
        inside[k] = (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
    return ratio.reshape(*lead, height, width), inside.reshape(*lead, height, width)


def forward_backward_mask(
    forward: np.ndarray, backward: np.ndarray, alpha1: float = 0.01, alpha2: float = 0.5
) -> np.ndarray:
    """Forward-backward consistency (Sundaram, Brox and Keutzer 2010).

    A pixel x of frame t is valid when w = forward(x) and w_b = backward(x + w) nearly
    cancel: |w + w_b|^2 < alpha1 (|w|^2 + |w_b|^2) + alpha2 (alpha2 in px^2), and x + w
    lies inside the frame.

    Args:
        forward: [..., H, W, 2] flow t -> t+1 (px).
        backward: [..., H, W, 2] flow t+1 -> t (px), same shape.

    Returns:
        bool [..., H, W], True where the flow is consistent.
    """
    ratio, inside = _consistency(forward, backward, alpha1, alpha2)
    return (ratio < 1.0) & inside


def flow_confidence(forward: np.ndarray, backward: np.ndarray, alpha1: float = 0.01, alpha2: float = 0.5) -> np.ndarray:
    """Soft form of :func:`forward_backward_mask`: exp(-|w + w_b|^2 / (alpha1 (|w|^2 + |w_b|^2)
    + alpha2)), 1 where the two flows cancel exactly, e^-1 on the mask's threshold, and 0
    where x + w leaves the frame (occluded by the border).

    Args and shapes as :func:`forward_backward_mask`'s; returns float32 [..., H, W] in [0, 1].
    """
    ratio, inside = _consistency(forward, backward, alpha1, alpha2)
    return np.where(inside, np.exp(-ratio), 0.0).astype(np.float32)


def observed_confidence(
    frames: np.ndarray, flow: np.ndarray, setting: str, method: FlowMethod = "dis", **kwargs
) -> np.ndarray:
    """Confidence [T-1, H, W] float32 in [0, 1] of ``flow``, the forward flow of ``frames``.

    ``setting`` is one of :data:`CONFIDENCES`: ``none`` gives ones; ``forward_backward``
    computes the backward flow (same ``method`` and ``kwargs`` as :func:`observed_flow`)
    and returns :func:`flow_confidence`."""
    if setting == "none":
        return np.ones(flow.shape[:-1], np.float32)
    if setting == "forward_backward":
        return flow_confidence(flow, backward_flow(frames, method, **kwargs))
    raise InputError(f"unknown flow confidence {setting!r}; choose one of {', '.join(CONFIDENCES)}")


def _nonempty(mask: np.ndarray, what: str) -> np.ndarray:
    if not mask.any():
        raise InputError(f"{what}: the object mask is empty (all zero)")
    return mask


def mask_from_image(path: str | os.PathLike, width: int, height: int, threshold: int = 127) -> np.ndarray:
    """bool [H, W] object mask from a mask image (object where grey value > threshold).

    The image must be ``width`` x ``height`` pixels (the video's size)."""
    import cv2

    path = Path(path)
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
    if image is None:
        raise InputError(f"{path}: not a readable mask image")
    if image.shape != (height, width):
        raise InputError(f"{path}: mask is {image.shape[1]}x{image.shape[0]} but the video is {width}x{height}")
    return _nonempty(image > threshold, str(path))


def mask_from_box(box: tuple[float, float, float, float], width: int, height: int) -> np.ndarray:
    """bool [H, W] mask of the pixels whose centres (j + 0.5, i + 0.5) lie in the box
    (x0, y0, x1, y1) (pixels)."""
    x0, y0, x1, y1 = (float(v) for v in box)
    if not (x0 < x1 and y0 < y1):
        raise InputError(f"object box {box} must have x0 < x1 and y0 < y1")
    u = np.arange(width) + 0.5
    v = np.arange(height) + 0.5
    mask = ((v >= y0) & (v <= y1))[:, None] & ((u >= x0) & (u <= x1))[None, :]
    return _nonempty(mask, f"object box {box} in a {width}x{height} frame")


def mask_from_alpha(alpha, threshold: float = 0.5) -> np.ndarray:
    """bool [H, W] mask where the rendered alpha ([H, W] or [H, W, 1], e.g. of the selected
    Gaussians at the first frame) exceeds ``threshold``."""
    alpha = np.asarray(alpha.detach().cpu() if hasattr(alpha, "detach") else alpha, dtype=np.float64)
    if alpha.ndim == 3 and alpha.shape[-1] == 1:
        alpha = alpha[..., 0]
    if alpha.ndim != 2:
        raise InputError(f"rendered alpha must be [H, W] or [H, W, 1], got shape {alpha.shape}")
    if not np.isfinite(alpha).all():
        raise InputError("rendered alpha contains NaN or infinite values")
    return _nonempty(alpha > threshold, f"rendered alpha above {threshold}")
