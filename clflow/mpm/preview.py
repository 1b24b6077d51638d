"""A quick point renderer for previews of simulated particles (OpenCV, no GPU)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from clflow.fileio import atomic_path


def render_points(x: torch.Tensor, lower, upper, size: int = 512) -> np.ndarray:
    """[size, size, 3] uint8 BGR image of positions x [N, 3] (m) seen along -z with an
    orthographic camera framing the box [lower, upper]; nearer points are brighter and
    drawn over farther ones."""
    p = x.detach().double().numpy()
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    scale = (size - 1) / max(hi[0] - lo[0], hi[1] - lo[1])
    px = np.clip(((p[:, 0] - lo[0]) * scale).astype(np.int64), 0, size - 1)
    py = np.clip((size - 1 - (p[:, 1] - lo[1]) * scale).astype(np.int64), 0, size - 1)
    depth = np.clip((p[:, 2] - lo[2]) / max(hi[2] - lo[2], 1e-12), 0.0, 1.0)
    order = np.argsort(depth, kind="stable")  # far first, near last (painter's order)
    shade = (80 + 175 * depth[order]).astype(np.uint8)
    img = np.full((size, size, 3), 24, dtype=np.uint8)
    for dy in (0, 1):  # 2x2 pixel dots
        for dx in (0, 1):
            yy, xx = np.clip(py[order] + dy, 0, size - 1), np.clip(px[order] + dx, 0, size - 1)
            img[yy, xx, 0] = shade // 2
            img[yy, xx, 1] = shade
            img[yy, xx, 2] = 255 - shade // 2
    return img


def write_preview(frames: torch.Tensor, lower, upper, out: Path, fps: float, size: int = 512) -> Path:
    """Write frames [T, N, 3] as ``out``: an .mp4/.avi video, or a folder of PNG images."""
    import cv2

    out = Path(out)
    if out.suffix.lower() in (".mp4", ".avi"):
        with atomic_path(out) as tmp:
            fourcc = cv2.VideoWriter_fourcc(*("mp4v" if out.suffix.lower() == ".mp4" else "MJPG"))
            writer = cv2.VideoWriter(str(tmp), fourcc, float(fps), (size, size))
            try:
                for x in frames:
                    writer.write(render_points(x, lower, upper, size))
            finally:
                writer.release()
        return out
    out.mkdir(parents=True, exist_ok=True)
    for k, x in enumerate(frames):
        with atomic_path(out / f"frame_{k:04d}.png") as tmp:
            cv2.imwrite(str(tmp), render_points(x, lower, upper, size))
    return out
