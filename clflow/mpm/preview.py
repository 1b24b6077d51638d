"""A quick point renderer for previews of simulated particles (numpy, no GPU)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from clflow.media import write_image, write_video


def _view_rotation(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Rotation taking simulation coordinates (y up) to camera coordinates (x right, y up,
    z towards the viewer): turn by the azimuth about y, then tilt by the elevation about x."""
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    tilt = np.array([[1, 0, 0], [0, np.cos(e), -np.sin(e)], [0, np.sin(e), np.cos(e)]])
    return tilt @ turn


def render_points(
    x: torch.Tensor, lower, upper, size: int = 512, azimuth: float = 30.0, elevation: float = 20.0
) -> np.ndarray:
    """[size, size, 3] uint8 RGB image of positions x [N, 3] (m) from an orthographic camera
    looking at the box [lower, upper] from ``azimuth`` / ``elevation`` (degrees, y up);
    nearer points are brighter and drawn over farther ones."""
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    rot = _view_rotation(azimuth, elevation)
    center = (lo + hi) / 2
    corners = np.array([[hx, hy, hz] for hx in (lo[0], hi[0]) for hy in (lo[1], hi[1]) for hz in (lo[2], hi[2])])
    frame = (corners - center) @ rot.T
    extent = (frame.max(0) - frame.min(0)).max()
    p = (x.detach().double().numpy() - center) @ rot.T  # camera coordinates
    scale = (size - 1) / extent
    px = np.clip(((p[:, 0] - frame[:, 0].min()) * scale).astype(np.int64), 0, size - 1)
    py = np.clip(((frame[:, 1].max() - p[:, 1]) * scale).astype(np.int64), 0, size - 1)
    depth = np.clip((p[:, 2] - frame[:, 2].min()) / max(np.ptp(frame[:, 2]), 1e-12), 0.0, 1.0)
    order = np.argsort(depth, kind="stable")  # far first, near last (painter's order)
    shade = (80 + 175 * depth[order]).astype(np.uint8)
    img = np.full((size, size, 3), 24, dtype=np.uint8)
    for dy in (0, 1):  # 2x2 pixel dots
        for dx in (0, 1):
            yy, xx = np.clip(py[order] + dy, 0, size - 1), np.clip(px[order] + dx, 0, size - 1)
            img[yy, xx, 0] = 255 - shade // 2
            img[yy, xx, 1] = shade
            img[yy, xx, 2] = shade // 2
    return img


PREVIEW_SIZE = 512  # px, side of the square preview frames


def write_preview(frames: torch.Tensor, lower, upper, out: Path, fps: float, size: int = PREVIEW_SIZE) -> Path:
    """Write frames [T, N, 3] as ``out``: an .mp4/.avi video, or a folder of PNG images."""
    out = Path(out)
    if out.suffix.lower() in (".mp4", ".avi"):
        write_video(out, np.stack([render_points(x, lower, upper, size) for x in frames]), fps)
        return out
    out.mkdir(parents=True, exist_ok=True)
    for k, x in enumerate(frames):
        write_image(out / f"frame_{k:04d}.png", render_points(x, lower, upper, size))
    return out
