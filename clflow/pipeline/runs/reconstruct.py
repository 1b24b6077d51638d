"""``clflow reconstruct`` as a whole run: 3D Gaussians trained from posed images, or
back-projected from one photo and its depth map, into an output folder clflow holds."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Callable, ContextManager

from clflow.pipeline.runs.progress import _silent

#: what reconstruct writes into its folder
RECONSTRUCTION_ENTRIES = ("point_cloud.ply", "cameras.json", "metrics.json", "checkpoint.pt", "preview")


def reconstruct_images(
    images: str | Path,
    out_dir: str | Path,
    settings=None,
    *,
    sources: dict | None = None,
    resume: bool = False,
    checkpoint_every: int = 1000,
    preview_every: int = 500,
    echo: Callable[[str], None] = _silent,
    note: Callable[[str], None] = _silent,
    progress: Callable[[int, str], ContextManager[Callable[..., None]]] | None = None,
) -> dict:
    """Train Gaussians (``settings``: a ``clflow.recon.Settings``, its background also the
    targets') on the posed ``images`` and write out_dir/point_cloud.ply, cameras.json, metrics.json, checkpoint.pt and preview/
    (``clflow.recon.train.reconstruct``). Refuses, before the work, a folder another run holds
    or that holds files clflow did not write. ``progress(total, label)`` yields
    ``advance(info, to=step)`` (info: running PSNR dB, Gaussians). ``sources``: the views'
    options of ``clflow.recon.load_views`` by name (``transforms``, ``colmap`` or
    ``cameras_json``, else the cameras found beside the images; ``masks``; ``frame``: frame N
    of a multi-camera sequence). Ctrl-C raises
    KeyboardInterrupt saying what was saved and how to resume. Returns the metrics."""
    from clflow.fileio import check_output_folder, output_folder
    from clflow.recon import Settings, load_views
    from clflow.recon.train import reconstruct

    settings = settings or Settings()
    sources = sources or {}
    files = [sources.get(name) for name in ("transforms", "colmap", "cameras_json", "masks")]
    inputs = [path for path in (images, *files) if path is not None]
    with output_folder(out_dir):  # this run's: other runs are refused, before any work
        check_output_folder(out_dir, RECONSTRUCTION_ENTRIES, inputs)  # replaces only clflow's
        views = load_views(images, background=settings.background, **sources)
        iterations = settings.iterations
        note(f"{len(views.views)} views; training {iterations} iterations -> {out_dir}")
        shown = progress(iterations, "reconstructing") if progress else contextlib.nullcontext(None)
        with shown as advance:
            try:
                result = reconstruct(
                    views,
                    out_dir,
                    settings,
                    resume=resume,
                    checkpoint_every=checkpoint_every,
                    preview_every=preview_every,
                    progress=(lambda step, info: advance(info, to=step)) if advance else None,
                )
            except KeyboardInterrupt:
                if not (Path(out_dir) / "checkpoint.pt").is_file():
                    raise KeyboardInterrupt("interrupted before the first checkpoint; nothing was saved") from None
                raise KeyboardInterrupt(
                    f"interrupted; the last checkpoint (every {checkpoint_every} iterations) is in "
                    f"{out_dir}/checkpoint.pt: continue with the same command and --resume"
                ) from None
        _echo_result(result.metrics, out_dir, echo)
    return result.metrics


def _echo_result(metrics: dict, out_dir: str | Path, echo: Callable[[str], None]) -> None:
    """One line: the Gaussians, the held-out views' PSNR and SSIM, the speed and the PLY."""
    test = metrics["test"]
    held_out = (
        f"held-out PSNR {test['psnr']:.2f} dB, SSIM {test['ssim']:.4f} ({test['views']} views)"
        if test["views"]
        else "no held-out views"
    )
    echo(
        f"{metrics['gaussians']} Gaussians, {held_out}, "
        f"{metrics['iterations_per_second'] or 0:.1f} it/s -> {out_dir}/point_cloud.ply"
    )


def reconstruct_photo(
    image: str | Path,
    depth: str | Path,
    out_dir: str | Path,
    depth_scale: float | None = None,
    fov: float = 50.0,
    shell: str = "mirror",
    echo: Callable[[str], None] = _silent,
) -> Path:
    """Back-project one photo along a camera at the origin (OpenCV axes, horizontal ``fov``
    degrees) by its ``depth`` map (.npy in m, or a 16-bit PNG; ``depth_scale`` m per unit)
    into Gaussians, the hidden side closed by ``shell`` ("mirror", "extrude" or "none"), and
    write out_dir/point_cloud.ply and cameras.json, no training. Returns the PLY's path."""
    import math

    import torch

    from clflow.errors import InputError
    from clflow.fileio import check_output_folder, output_folder
    from clflow.media import read_image
    from clflow.recon.depth import backproject, read_depth
    from clflow.splat.cameras import Camera, intrinsics, save_cameras_json
    from clflow.splat.ply import save_ply

    with output_folder(out_dir):  # this run's: other runs are refused, before any work
        check_output_folder(out_dir, RECONSTRUCTION_ENTRIES, [image, depth])  # replaces only clflow's
        if not Path(image).is_file():
            raise InputError(f"{image}: with --depth, IMAGES must be one image file")
        rgba = torch.from_numpy(read_image(Path(image)))
        height, width = rgba.shape[:2]
        camera = Camera(
            torch.eye(4, dtype=torch.float64),
            intrinsics(width, height, math.radians(fov)),
            width,
            height,
            Path(image).name,
        )
        mask = rgba[..., 3] > 0.5 if rgba.shape[2] == 4 else None
        gaussians = backproject(rgba[..., :3], read_depth(depth, depth_scale), camera, mask=mask, shell=shell)
        ply = Path(out_dir) / "point_cloud.ply"
        save_ply(ply, gaussians)
        save_cameras_json(Path(out_dir) / "cameras.json", [camera])
        echo(f"{len(gaussians)} Gaussians from {image} and {depth} -> {out_dir}/point_cloud.ply")
    return ply


__all__ = ["RECONSTRUCTION_ENTRIES", "reconstruct_images", "reconstruct_photo"]
