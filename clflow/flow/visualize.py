"""Flow visualisation: the Middlebury colour wheel, comparison panels, image and video files.

Images are [H, W, 3] uint8 RGB; files are written atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from clflow.errors import ClflowError, InputError
from clflow.fileio import atomic_path
from clflow.limits import why_not_written

#: Hue segments of the Middlebury colour wheel (Baker et al. 2011): red-yellow, yellow-green,
#: green-cyan, cyan-blue, blue-magenta, magenta-red; more steps where the eye sees more hues.
WHEEL_SEGMENTS = (15, 6, 4, 11, 13, 6)
#: fourcc of the codec each video suffix is written with (all in opencv-python's FFmpeg).
VIDEO_FOURCC = {".mp4": "mp4v", ".avi": "MJPG", ".webm": "VP90", ".mkv": "FFV1", ".mov": "mp4v"}


def colour_wheel() -> np.ndarray:
    """[55, 3] float64 RGB in [0, 1]: the wheel's colours in order of flow angle."""
    rows = []
    for segment, n in enumerate(WHEEL_SEGMENTS):
        ramp = np.floor(255.0 * np.arange(n) / n) / 255.0
        # Each segment holds one primary at 1 and ramps another up or down between primaries.
        primary, ramped, rising = [(0, 1, True), (1, 0, False), (1, 2, True), (2, 1, False), (2, 0, True), (0, 2, False)][segment]
        colour = np.zeros((n, 3))
        colour[:, primary] = 1.0
        colour[:, ramped] = ramp if rising else 1.0 - ramp
        rows.append(colour)
    return np.concatenate(rows)


def flow_to_color(flow: np.ndarray, max_flow: float | None = None) -> np.ndarray:
    """Middlebury colouring of a [H, W, 2] flow: hue = direction, saturation = speed
    relative to ``max_flow`` (px; default: the largest speed in the field). Speeds above
    ``max_flow`` are darkened. Returns [H, W, 3] uint8 RGB."""
    flow = np.asarray(flow, np.float64)
    if flow.ndim != 3 or flow.shape[-1] != 2:
        raise InputError(f"flow to colour: expected a [H, W, 2] flow, got shape {flow.shape}")
    if not np.isfinite(flow).all():
        raise InputError("flow to colour: the flow contains NaN or infinite values")
    speed = np.linalg.norm(flow, axis=-1)
    if max_flow is None:
        max_flow = float(speed.max())
    radius = speed / max(max_flow, 1e-12)
    wheel = colour_wheel()
    n = len(wheel)
    angle = np.arctan2(-flow[..., 1], -flow[..., 0]) / np.pi  # (-1, 1]
    position = (angle + 1.0) / 2.0 * (n - 1)
    k0 = np.floor(position).astype(int)
    k1 = (k0 + 1) % n
    f = (position - k0)[..., None]
    colour = (1.0 - f) * wheel[k0] + f * wheel[k1]
    r = radius[..., None]
    colour = np.where(r <= 1.0, 1.0 - r * (1.0 - colour), 0.75 * colour)
    return np.floor(255.0 * colour).astype(np.uint8)


def _label(image: np.ndarray, text: str) -> np.ndarray:
    import cv2

    out = image.copy()
    scale = max(0.35, image.shape[0] / 500.0)
    for colour, thickness in (((0, 0, 0), 3), ((255, 255, 255), 1)):
        cv2.putText(out, text, (6, int(22 * scale) + 4), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, thickness, cv2.LINE_AA)
    return out


def error_to_color(error: np.ndarray, max_error: float) -> np.ndarray:
    """[H, W] end-point error (px) to [H, W, 3] uint8 RGB (inferno, 0 .. max_error)."""
    import cv2

    scaled = np.clip(255.0 * np.asarray(error) / max(max_error, 1e-12), 0, 255).astype(np.uint8)
    return cv2.cvtColor(cv2.applyColorMap(scaled, cv2.COLORMAP_INFERNO), cv2.COLOR_BGR2RGB)


def comparison_panel(
    frame: np.ndarray, observed: np.ndarray, simulated: np.ndarray | None = None, max_flow: float | None = None
) -> np.ndarray:
    """Side by side: guidance frame | guidance flow | simulated flow | end-point error.

    Without ``simulated`` only the first two panels. Both flows share one colour scale
    (``max_flow`` px, default the largest observed speed); the error panel spans 0 to it.
    Returns [H, k W, 3] uint8 RGB.
    """
    if max_flow is None:
        max_flow = max(float(np.linalg.norm(observed, axis=-1).max()), 1e-6)
    panels = [_label(np.asarray(frame, np.uint8), "guidance"), _label(flow_to_color(observed, max_flow), "guidance flow")]
    if simulated is not None:
        simulated = np.asarray(simulated)
        error = np.linalg.norm(simulated - observed, axis=-1)
        panels += [
            _label(flow_to_color(simulated, max_flow), "simulated flow"),
            _label(error_to_color(error, max_flow), f"EPE {error.mean():.2f} px"),
        ]
    return np.concatenate(panels, axis=1)


def _write_failed(path, what: str) -> ClflowError:
    """The error of an OpenCV writer that reported only failure: a full disk or unwritable
    folder if either is the cause, else ``what``."""
    return ClflowError(f"{path}: {why_not_written(path) or what}")


def write_image(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write a [H, W, 3] uint8 RGB image (PNG, JPEG, ... by suffix) atomically."""
    import cv2

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(np.asarray(image, np.uint8), cv2.COLOR_RGB2BGR)):
            raise _write_failed(path, "OpenCV cannot write an image of this type")


def write_video(path: str | os.PathLike, frames: np.ndarray, fps: float) -> None:
    """Write [T, H, W, 3] uint8 RGB frames as a video atomically; the suffix picks the codec
    (:data:`VIDEO_FOURCC`, or ``.gif`` through OpenCV's animation writer)."""
    import cv2

    path = Path(path)
    frames = np.asarray(frames, np.uint8)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] < 1:
        raise InputError(f"{path}: video frames must be [T, H, W, 3] with T >= 1, got shape {frames.shape}")
    if not fps > 0:
        raise InputError(f"{path}: frame rate must be positive, got {fps!r}")
    suffix = path.suffix.lower()
    bgr = [cv2.cvtColor(f, cv2.COLOR_RGB2BGR) for f in frames]
    with atomic_path(path) as tmp:
        if suffix == ".gif":
            animation = cv2.Animation()
            animation.frames = bgr
            animation.durations = [int(round(1000.0 / fps))] * len(bgr)
            if not cv2.imwriteanimation(str(tmp), animation):
                raise _write_failed(path, "OpenCV could not write the GIF")
            return
        if suffix not in VIDEO_FOURCC:
            raise InputError(f"{path}: unsupported video suffix {suffix!r}; use .gif or one of {', '.join(VIDEO_FOURCC)}")
        height, width = frames.shape[1:3]
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*VIDEO_FOURCC[suffix]), float(fps), (width, height))
        if not writer.isOpened():
            raise _write_failed(path, f"OpenCV's FFmpeg cannot encode {VIDEO_FOURCC[suffix]!r} video here")
        try:
            for f in bgr:
                writer.write(f)
        finally:
            writer.release()
        if why_not_written(tmp):  # FFmpeg does not report failed writes: a full disk truncates silently
            raise _write_failed(path, "")
