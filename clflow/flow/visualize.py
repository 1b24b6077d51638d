"""Flow visualisation: the Middlebury colour wheel and comparison panels.

Images are [H, W, 3] uint8 RGB; clflow.media writes them.
"""

from __future__ import annotations

import numpy as np

from clflow.errors import InputError

#: Hue segments of the Middlebury colour wheel (Baker et al. 2011): red-yellow, yellow-green,
#: green-cyan, cyan-blue, blue-magenta, magenta-red; more steps where the eye sees more hues.
WHEEL_SEGMENTS = (15, 6, 4, 11, 13, 6)


def colour_wheel() -> np.ndarray:
    """[55, 3] float64 RGB in [0, 1]: the wheel's colours in order of flow angle."""
    rows = []
    for segment, n in enumerate(WHEEL_SEGMENTS):
        ramp = np.floor(255.0 * np.arange(n) / n) / 255.0
        # Each segment holds one primary at 1 and ramps another up or down between primaries.
        primary, ramped, rising = [
            (0, 1, True),
            (1, 0, False),
            (1, 2, True),
            (2, 1, False),
            (2, 0, True),
            (0, 2, False),
        ][segment]
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


def wheel_legend(size: int, max_flow: float) -> np.ndarray:
    """[size, size, 3] uint8 RGB key of :func:`flow_to_color`: each pixel of the disc has the
    colour of a flow pointing from the centre to it (image axes: x right, y down), the rim
    standing for ``max_flow`` px, which the label below the disc gives. Black outside it."""
    import cv2

    radius = 0.5 * size - 1.0
    label_height = max(8, size // 5)
    centre = np.array([0.5 * size, 0.5 * (size - label_height)])
    y, x = np.mgrid[0 : size - label_height, 0:size] + 0.5
    offset = np.stack([x - centre[0], y - centre[1]], axis=-1)
    scale = (size - label_height) / size
    inside = np.linalg.norm(offset, axis=-1) <= radius * scale
    disc = flow_to_color(offset * (max_flow / (radius * scale)), max_flow) * inside[..., None]
    key = np.zeros((size, size, 3), np.uint8)
    key[: size - label_height] = disc
    text, font = f"{max_flow:.3g} px", cv2.FONT_HERSHEY_SIMPLEX
    font_scale = 0.3 * label_height / 8
    width = cv2.getTextSize(text, font, font_scale, 1)[0][0]
    cv2.putText(key, text, (max(0, (size - width) // 2), size - 2), font, font_scale, (255, 255, 255), 1, cv2.LINE_AA)
    return key


def _with_legend(image: np.ndarray, max_flow: float) -> np.ndarray:
    """``image`` with a :func:`wheel_legend` in its bottom-right corner (none below 32 px)."""
    size = min(image.shape[:2]) // 4
    if size < 32:
        return image
    out = image.copy()
    out[-size - 2 : -2, -size - 2 : -2] = wheel_legend(size, max_flow)
    return out


def _label(image: np.ndarray, text: str) -> np.ndarray:
    import cv2

    out = image.copy()
    scale = max(0.35, image.shape[0] / 500.0)
    for colour, thickness in (((0, 0, 0), 3), ((255, 255, 255), 1)):
        cv2.putText(
            out, text, (6, int(22 * scale) + 4), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, thickness, cv2.LINE_AA
        )
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
    (``max_flow`` px, default the largest observed speed), keyed by a colour wheel in the
    guidance flow's corner (panels of 128 px and more); the error panel spans 0 to it.
    Returns [H, k W, 3] uint8 RGB.
    """
    if max_flow is None:
        max_flow = max(float(np.linalg.norm(observed, axis=-1).max()), 1e-6)
    panels = [
        _label(np.asarray(frame, np.uint8), "guidance"),
        _label(_with_legend(flow_to_color(observed, max_flow), max_flow), "guidance flow"),
    ]
    if simulated is not None:
        simulated = np.asarray(simulated)
        error = np.linalg.norm(simulated - observed, axis=-1)
        panels += [
            _label(flow_to_color(simulated, max_flow), "simulated flow"),
            _label(error_to_color(error, max_flow), f"EPE {error.mean():.2f} px"),
        ]
    return np.concatenate(panels, axis=1)
