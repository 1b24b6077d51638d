"""``clflow flow`` as a whole run: the observed optical flow of a guidance video, written to a folder."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Callable, ContextManager

from clflow.pipeline.runs.progress import _silent


def export_flow(
    video: str | Path,
    out_dir: str | Path | None = None,
    method: str = "dis",
    preset: str = "fine",
    raft_weights: str | Path | None = None,
    fps: float | None = None,
    start: float = 0.0,
    end: float | None = None,
    stride: int = 1,
    sim_fps: float | None = None,
    mask_image: str | Path | None = None,
    box: tuple[int, int, int, int] | None = None,
    panels_video: bool = True,
    echo: Callable[[str], None] = _silent,
    progress: Callable[[int, str], ContextManager[Callable[[str], None]]] | None = None,
) -> Path:
    """The optical flow between consecutive frames of ``video`` (a file or an image folder;
    ``fps`` frames/s gives an image folder its times) from ``start`` to ``end`` (s), every
    ``stride``-th frame, resampled to ``sim_fps`` if given, by ``method`` ("dis" with DIS's
    ``preset``, "farneback", or "raft" with ``raft_weights``), kept inside the object mask
    (``mask_image``, or ``box`` x0, y0, x1, y1 in pixels). Written to ``out_dir`` (default:
    the video's name + "_flow") as the files of ``clflow.flow.export.write_flow_folder``
    (``panels_video``: flow.mp4 too), all or nothing. ``progress(total, label)`` yields
    ``advance(step)``. Returns the folder."""
    import numpy as np

    from clflow.fileio import atomic_dir, check_output_folder
    from clflow.flow.export import FLOW_ENTRIES, write_flow_folder
    from clflow.flow.optical_flow import mask_from_box, mask_from_image
    from clflow.flow.video import read_video

    out = Path(out_dir) if out_dir else Path(Path(video).stem + "_flow")
    inputs = [path for path in (video, mask_image, raft_weights) if path is not None]
    check_output_folder(out, FLOW_ENTRIES, inputs)  # replaces only clflow's: before the work
    clip = read_video(video, fps=fps)
    echo(clip.describe())
    if start > 0 or end is not None:
        clip = clip.window(start, end)
    if stride != 1:
        clip = clip.every(stride)
    if sim_fps is not None:
        clip = clip.resample_rate(sim_fps)
    object_mask = True
    if mask_image:
        object_mask = mask_from_image(mask_image, clip.width, clip.height)
    elif box:
        object_mask = mask_from_box(box, clip.width, clip.height)
    steps = 3 * max(len(clip.frames) - 1, 0)  # forward, backward, files
    shown = progress(steps, "optical flow") if progress else contextlib.nullcontext(_silent)
    with (
        shown as advance,
        atomic_dir(out, FLOW_ENTRIES, inputs) as staged,  # all or nothing: no earlier run's extra frames stay
    ):
        forward, valid = write_flow_folder(
            clip, staged, method, preset, object_mask, raft_weights, panels_video, advance
        )
    speed = np.linalg.norm(forward, axis=-1)
    echo(
        f"{method}{'/' + preset if method == 'dis' else ''}: {len(forward)} flow fields {clip.width}x{clip.height}, "
        f"mean speed {speed.mean():.3f} px/frame, max {max(float(speed.max()), 1e-6):.2f}, "
        f"consistent {valid.mean():.1%} -> {out}"
    )
    return out


__all__ = ["export_flow"]
