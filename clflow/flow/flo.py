"""Middlebury ``.flo`` optical-flow files (Baker et al., "A Database and Evaluation
Methodology for Optical Flow", 2011).

Layout, little-endian: float32 202021.25 (the bytes "PIEH"), int32 width, int32 height,
then height x width x 2 float32 (u, v) row-major. Values >= 1e9 mark unknown flow.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from clflow.errors import InputError
from clflow.fileio import atomic_path

FLO_MAGIC = 202021.25
#: |u| or |v| at or above this marks an unknown flow vector in a .flo file.
UNKNOWN_FLOW = 1e9


def write_flo(path: str | os.PathLike, flow: np.ndarray) -> None:
    """Write a [H, W, 2] flow (px) atomically. NaN or infinite values are an error
    (mark unknown vectors with :data:`UNKNOWN_FLOW` instead)."""
    flow = np.asarray(flow)
    if flow.ndim != 3 or flow.shape[-1] != 2 or min(flow.shape[:2]) < 1:
        raise InputError(f"{path}: a .flo file holds one [H, W, 2] flow field, got shape {flow.shape}")
    if not np.isfinite(flow).all():
        raise InputError(f"{path}: the flow contains NaN or infinite values")
    height, width = flow.shape[:2]
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.array([FLO_MAGIC], "<f4").tofile(f)
        np.array([width, height], "<i4").tofile(f)
        flow.astype("<f4").tofile(f)


def read_flo(path: str | os.PathLike) -> np.ndarray:
    """Read a .flo file as a [H, W, 2] float32 flow (px)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the flow file ({exc.strerror})") from None
    if len(data) < 12 or np.frombuffer(data[:4], "<f4")[0] != FLO_MAGIC:
        raise InputError(f"{path}: not a Middlebury .flo file (wrong magic number)")
    width, height = (int(v) for v in np.frombuffer(data[4:12], "<i4"))
    expected = 12 + 8 * width * height
    if width < 1 or height < 1 or len(data) != expected:
        raise InputError(f"{path}: header says {width}x{height} ({expected} bytes) but the file has {len(data)} bytes")
    flow = np.frombuffer(data[12:], "<f4").reshape(height, width, 2).astype(np.float32)
    if np.isnan(flow).any():
        raise InputError(f"{path}: the flow contains NaN values")
    return flow
