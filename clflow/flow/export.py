"""A video's optical flow as files (``clflow flow``): flow.npz, a .flo and a panel PNG per
frame pair, and a panels video; every file atomically."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from clflow.flow.video import Video

#: what write_flow_folder writes into its folder
FLOW_ENTRIES = ("flow.npz", "flo", "png", "flow.mp4")


def write_flow_folder(
    clip: Video,
    out: Path,
    method: str,
    preset: str,
    object_mask: np.ndarray | bool = True,
    raft_weights: str | None = None,
    panels_video: bool = True,
    advance: Callable[[str], None] = lambda step: None,
) -> tuple[np.ndarray, np.ndarray]:
    """The forward flow of ``clip``'s frame pairs and where it is valid (forward-backward
    consistent and inside ``object_mask`` [H, W]), written to ``out``: flow.npz (flow
    [T-1, H, W, 2] px, valid [T-1, H, W], times [T] s, fps, method, preset), flo/flow_NNNN.flo,
    png/flow_NNNN.png (frame | flow) and flow.mp4 (``panels_video``). ``advance`` is called
    3 times per pair (forward, backward, files). Returns (flow, valid)."""
    from clflow.fileio import atomic_path
    from clflow.flow.flo import write_flo
    from clflow.flow.optical_flow import backward_flow, forward_backward_mask, observed_flow
    from clflow.flow.visualize import comparison_panel
    from clflow.media import write_image, write_video

    frames = clip.frames
    options = dict(preset=preset, raft_weights=raft_weights, source=clip.source, advance=advance)
    forward = observed_flow(frames, method, **options)
    backward = backward_flow(frames, method, **options)
    valid = forward_backward_mask(forward, backward) & object_mask
    with atomic_path(out / "flow.npz") as tmp:
        np.savez_compressed(
            tmp,
            flow=forward,
            valid=valid,
            times=np.asarray([] if clip.times is None else clip.times),
            fps=np.float64(clip.fps or np.nan),
            method=method,
            preset=preset,
        )
    max_flow = max(float(np.linalg.norm(forward, axis=-1).max()), 1e-6)
    panels = []
    for t, f in enumerate(forward):
        write_flo(out / "flo" / f"flow_{t:04d}.flo", f)
        panels.append(comparison_panel(frames[t], f, max_flow=max_flow))
        write_image(out / "png" / f"flow_{t:04d}.png", panels[-1])
        advance(f"flow_{t:04d}")
    if panels_video:
        write_video(out / "flow.mp4", np.stack(panels), clip.fps or 24.0)
    return forward, valid
