"""Images in and frames out: the input image read and checked, fitted to the model's frame,
the generated frames cut back to the image's area, and the video and its record written."""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clflow.errors import InputError


def load_image(path: str | os.PathLike) -> np.ndarray:
    """[H, W, 3] uint8 RGB of an image file; transparency is laid over white (the renderer's
    background). A file that is not an image, or is too small, raises an InputError."""
    from clflow.media import read_image, to_uint8

    rgba = read_image(path)
    alpha = rgba[..., 3:] if rgba.shape[2] == 4 else np.float32(1)
    image = to_uint8(rgba[..., :3] * alpha + (1 - alpha))
    check_image(image, str(path))
    return image


def check_image(image: np.ndarray, where: str) -> None:
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(f"{where}: expected an RGB image, got an array of shape {image.shape}")
    h, w = image.shape[:2]
    if min(w, h) < 8:
        raise InputError(f"{where}: the image is {w}x{h} px; the model needs at least 8 px a side")
    if max(w, h) > 16 * min(w, h):
        raise InputError(
            f"{where}: the image is {w}x{h} px, too thin to fit a video model's frame (aspect ratio over 16)"
        )


@dataclass(frozen=True)
class Placement:
    """Where the image lies in the model's frame: ``box`` (x0, y0, x1, y1) px of the model frame
    holding image content, which is ``restored`` (w, h) px at the image's scale."""

    box: tuple[int, int, int, int]
    restored: tuple[int, int]


def fit_image(image: np.ndarray, size: tuple[int, int], fit: str = "pad") -> tuple[np.ndarray, Placement]:
    """Scale ``image`` [H, W, 3] to the model's ``size`` (w, h) keeping its aspect: ``pad``
    fits it inside and pads the rest with its edge pixels; ``crop`` fills the frame and cuts
    the overflow off, centred."""
    import cv2

    H, W = image.shape[:2]
    w, h = size
    scale = min(w / W, h / H) if fit == "pad" else max(w / W, h / H)
    sw, sh = max(1, round(W * scale)), max(1, round(H * scale))
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC
    scaled = cv2.resize(image, (sw, sh), interpolation=interp)
    if fit == "pad":
        x0, y0 = (w - sw) // 2, (h - sh) // 2
        out = cv2.copyMakeBorder(scaled, y0, h - sh - y0, x0, w - sw - x0, cv2.BORDER_REPLICATE)
        return out, Placement((x0, y0, x0 + sw, y0 + sh), (W, H))
    x0, y0 = (sw - w) // 2, (sh - h) // 2
    out = scaled[y0 : y0 + h, x0 : x0 + w]
    return np.ascontiguousarray(out), Placement((0, 0, w, h), (max(1, round(w / scale)), max(1, round(h / scale))))


def restore_frames(frames: np.ndarray, placement: Placement) -> np.ndarray:
    """The generated frames [T, h, w, 3] cut to the image's area and scaled back to its pixels."""
    import cv2

    x0, y0, x1, y1 = placement.box
    out_w, out_h = placement.restored
    interp = cv2.INTER_AREA if out_w < x1 - x0 else cv2.INTER_CUBIC
    return np.stack(
        [cv2.resize(np.ascontiguousarray(f[y0:y1, x0:x1]), (out_w, out_h), interpolation=interp) for f in frames]
    )


def write_generated(path: str | os.PathLike, frames: np.ndarray, record: dict, total_s: float | None = None) -> Path:
    """Write the frames as a video (clflow.media, at ``record['fps']``) and the record as
    ``<video>.json`` beside it; returns the JSON's path."""
    from clflow.fileio import atomic_write_text
    from clflow.media import write_video

    path = Path(path)
    start = time.perf_counter()
    write_video(path, frames, record["fps"])
    record = dict(record, video=str(path.resolve()))
    record["timings"] = dict(record.get("timings", {}), write_s=round(time.perf_counter() - start, 3))
    if total_s is not None:
        record["timings"]["total_s"] = round(total_s, 3)
    meta = path.with_suffix(".json")
    atomic_write_text(meta, json.dumps(record, indent=2) + "\n")
    return meta
