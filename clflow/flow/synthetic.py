"""Synthetic guidance videos with known optical flow (for tests and benchmarks).

A textured image moves by a known 2D similarity per frame (translation, rotation about
the frame centre, scale); the true forward flow of frame t is x' - x with x' = M x the
frame-to-frame map, in pixel units. The texture is drawn larger than the frame so that
every frame is made of real texture (no border fill).
"""

from __future__ import annotations

import dataclasses

import numpy as np


def textured_image(height: int, width: int, seed: int = 0) -> np.ndarray:
    """[H, W, 3] uint8 RGB band-limited multi-scale noise (texture optical flow can track)."""
    import cv2

    rng = np.random.default_rng(seed)
    image = np.zeros((height, width, 3), np.float64)
    for sigma in (1.5, 3.0, 6.0, 12.0):
        noise = rng.standard_normal((height, width, 3))
        image += sigma * cv2.GaussianBlur(noise, (0, 0), sigma)
    image -= image.min()
    return (255.0 * image / image.max()).astype(np.uint8)


@dataclasses.dataclass(frozen=True)
class Motion:
    """Per-frame 2D similarity about the frame centre: ``shift`` (px, x then y), ``angle``
    (rad, counter-clockwise in the image as displayed, i.e. with y down), ``scale``."""

    shift: tuple[float, float] = (0.0, 0.0)
    angle: float = 0.0
    scale: float = 1.0

    def matrix(self, width: int, height: int) -> np.ndarray:
        """3x3 map of pixel-index coordinates of frame t to those of frame t+1."""
        cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
        c, s = self.scale * np.cos(self.angle), self.scale * np.sin(self.angle)
        A = np.array([[c, s], [-s, c]])  # y points down: positive angle turns counter-clockwise on screen
        t = np.array([cx, cy]) - A @ np.array([cx, cy]) + np.asarray(self.shift, np.float64)
        return np.array([[A[0, 0], A[0, 1], t[0]], [A[1, 0], A[1, 1], t[1]], [0.0, 0.0, 1.0]])


def moving_texture(
    frame_count: int, height: int, width: int, motion: Motion, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """A textured image moved by ``motion`` every frame.

    Returns:
        frames [T, H, W, 3] uint8 RGB and the true forward flows [T-1, H, W, 2] float64 px
        (flow[t, i, j] = displacement of pixel (i, j) of frame t into frame t+1).
    """
    import cv2

    M = motion.matrix(width, height)
    margin = 3 * max(height, width)
    texture = textured_image(height + 2 * margin, width + 2 * margin, seed)
    offset = np.array([[1.0, 0.0, -margin], [0.0, 1.0, -margin], [0.0, 0.0, 1.0]])  # texture -> frame 0
    frames, to_frame = [], offset
    for _ in range(frame_count):
        frames.append(
            cv2.warpAffine(texture, to_frame[:2], (width, height), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        )
        to_frame = M @ to_frame
    jj, ii = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    x = np.stack([jj, ii], axis=-1)
    flow = x @ M[:2, :2].T + M[:2, 2] - x
    return np.stack(frames), np.broadcast_to(flow, (frame_count - 1, height, width, 2)).copy()
