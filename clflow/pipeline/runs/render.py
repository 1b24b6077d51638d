"""``clflow render`` as a whole run: PNG images (and a video) of a 3DGS PLY from chosen views."""

from __future__ import annotations

import contextlib
import dataclasses
import math
import re
from pathlib import Path
from typing import Callable, ContextManager

from clflow.errors import InputError
from clflow.limits import DEFAULT_MAX_OUTPUT_GB
from clflow.pipeline.runs.progress import _silent

VIDEO_SUFFIXES = (".mp4", ".gif")


@dataclasses.dataclass(frozen=True)
class Views:
    """Which views to render: the cameras of a 3DGS ``cameras_json`` or a NeRF-style
    ``transforms_json`` (all, or those ``camera_keys`` pick by image name, file path or
    index), else new ones: a look-at camera at ``eye`` (m), ``n_orbit`` views on a circle
    around ``target`` (m; default the scene's centre) or one view that frames the scene.
    ``up``: world up (+y as in scene configs); angles in degrees, sizes in pixels."""

    cameras_json: str | Path | None = None
    transforms_json: str | Path | None = None
    camera_keys: tuple[str, ...] = ()
    eye: tuple[float, float, float] | None = None
    target: tuple[float, float, float] | None = None
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    n_orbit: int | None = None
    elevation: float = 20.0
    azimuth: float = 0.0
    fov: float = 50.0
    width: int = 512
    height: int = 512

    @property
    def from_file(self) -> str | Path | None:
        """The camera file the views come from, or None for new views."""
        return self.cameras_json or self.transforms_json

    def cameras(self, gaussians) -> list:
        """The cameras (``clflow.splat.Camera``) of these views of ``gaussians``: new views
        frame the centres between the 1st and 99th percentiles on each axis."""
        import torch

        from clflow.splat import cameras as cams

        if self.cameras_json and self.transforms_json:
            raise InputError("give --cameras or --transforms, not both")
        if self.from_file:
            if self.cameras_json:
                loaded = cams.load_cameras_json(self.cameras_json)
            else:
                loaded = cams.load_transforms_json(self.transforms_json)
            return [_pick(loaded, key, self.from_file) for key in self.camera_keys] or loaded
        if self.camera_keys:
            raise InputError("--camera picks from --cameras or --transforms; give one of them")
        elevation, azimuth, up, target = math.radians(self.elevation), math.radians(self.azimuth), self.up, self.target
        view = dict(fov_x=math.radians(self.fov), width=self.width, height=self.height)
        if self.eye is None:
            low, high = gaussians.bounds(quantile=0.01)
            if target is not None:  # keep the framing distance, centre the given target
                shift = torch.tensor(target, dtype=low.dtype) - 0.5 * (low + high)
                low, high = low + shift, high + shift
            n_views = self.n_orbit or 1
            return cams.frame_box(low, high, n_views=n_views, elevation=elevation, azimuth=azimuth, up=up, **view)
        if target is None:
            low, high = gaussians.bounds(quantile=0.01)
            target = (0.5 * (low + high)).tolist()
        if not self.n_orbit:
            return [cams.look_at(self.eye, target, up, keys=("--eye", "--target", "--up"), **view)]
        # An orbit through the eye: its distance to the target and its elevation about up.
        offset = torch.tensor(self.eye, dtype=torch.float64) - torch.tensor(target, dtype=torch.float64)
        unit_up = torch.tensor(up, dtype=torch.float64) / torch.tensor(up, dtype=torch.float64).norm()
        radius = offset.norm().item()
        if radius == 0:
            raise InputError("--eye and --target are the same point")
        return cams.orbit(
            target,
            radius,
            n_views=self.n_orbit,
            elevation=math.asin((offset @ unit_up).item() / radius),
            up=up,
            azimuth=azimuth,
            **view,
        )


def render_splats(
    splats: str | Path,
    out_dir: str | Path,
    views: Views = Views(),
    box: tuple[float, ...] | None = None,
    sphere: tuple[float, ...] | None = None,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    sh_degree: int | None = None,
    video: str | Path | None = None,
    fps: float = 24.0,
    precision: str = "float32",
    max_output_gb: float = DEFAULT_MAX_OUTPUT_GB,
    echo: Callable[[str], None] = _silent,
    progress: Callable[[int, str], ContextManager[Callable[[str], None]]] | None = None,
) -> Path:
    """Render ``splats`` (a 3DGS PLY, or a plain x y z [r g b] point cloud) from ``views`` to
    one PNG per view in ``out_dir``, all or nothing, and to a ``video`` (.mp4 or .gif at
    ``fps``) if given. ``box`` (x0, y0, z0, x1, y1, z1, m) and ``sphere`` (x, y, z, r, m)
    keep the Gaussians whose centres lie inside (both: the intersection); ``background``
    R, G, B in [0, 1]; ``precision`` "float32" or "float64". The output is checked against
    the disk and ``max_output_gb`` before the work. ``progress(total, label)`` yields
    ``advance(name)``, called after each view. Returns the folder."""
    import glob
    import time

    import numpy as np
    import torch

    from clflow.fileio import atomic_dir, check_output_folder
    from clflow.media import to_uint8, write_image, write_video
    from clflow.splat import load_ply
    from clflow.splat.ply import require_gaussians
    from clflow.splat.render import rasterize

    if video is not None and Path(video).suffix.lower() not in VIDEO_SUFFIXES:
        raise InputError(f"--video {video}: the file name must end in {' or '.join(VIDEO_SUFFIXES)}")
    out_dir = Path(out_dir)
    if not views.from_file:  # the views' number and size are known: checked before the scene is read
        count, pixels = views.n_orbit or 1, views.width * views.height
        _check_room(out_dir, video, count, 3 * pixels * count, max_output_gb)
    gaussians = require_gaussians(load_ply(splats), splats).to(getattr(torch, precision))
    gaussians = dataclasses.replace(gaussians, features=None, feature_names=())  # colours only (not `object`, ...)
    total = len(gaussians)
    if box is not None:
        gaussians = gaussians.select_box(box[:3], box[3:])
    if sphere is not None:
        gaussians = gaussians.select_sphere(sphere[:3], sphere[3])
    if (box or sphere) and len(gaussians) == 0:
        raise InputError(f"--box/--sphere select none of the {total} Gaussians of {splats}")
    cameras = views.cameras(gaussians)
    sizes = {(c.width, c.height) for c in cameras}
    if video is not None and len(sizes) > 1:
        raise InputError(f"--video: the views have different sizes {sorted(sizes)}; a video needs one size")
    if views.from_file:
        _check_room(out_dir, video, len(cameras), sum(3 * c.width * c.height for c in cameras), max_output_gb)
    stems: list[str] = []
    for i, camera in enumerate(cameras):
        stem = _file_stem(camera.name)
        stems.append(stem if stem not in stems else f"{stem}_{i:04d}")  # e.g. train/r_0 and test/r_0
    names = tuple(glob.escape(f"{stem}.png") for stem in stems)
    check_output_folder(out_dir, names, [splats])  # replaces only clflow's images: before the work
    frames = []
    seconds = 0.0
    shown = progress(len(cameras), "rendering") if progress else contextlib.nullcontext(_silent)
    with atomic_dir(out_dir, names, [splats]) as tmp, shown as advance:
        for camera, stem in zip(cameras, stems):  # all or nothing
            start = time.perf_counter()
            with torch.no_grad():
                image = rasterize(
                    gaussians, camera, background=background, sh_degree=sh_degree, render_depth=False
                ).image
            seconds += time.perf_counter() - start
            frame = to_uint8(image)
            write_image(tmp / f"{stem}.png", frame)
            frames.append(frame)
            advance(stem)
        if video is not None:
            write_video(video, np.stack(frames), fps)
    echo(
        f"rendered {len(gaussians)} Gaussians: {len(frames)} view(s) -> {out_dir}/ "
        f"({1e3 * seconds / len(frames):.0f} ms per view, first includes kernel builds)"
    )
    if video is not None:
        echo(f"video: {video}")
    return out_dir


def _check_room(out_dir: Path, video: str | Path | None, count: int, image_bytes: int, max_output_gb: float) -> None:
    """Refuse ``count`` views of ``image_bytes`` in all when they (and their video) would not
    fit the disk or ``max_output_gb``."""
    from clflow.limits import check_output

    what, less = f"{count:,} views", "render fewer views"
    check_output(out_dir, image_bytes, max_output_gb, what, less)
    if video is not None:
        check_output(Path(video).parent, image_bytes, max_output_gb, what, less)


def _pick(cameras: list, key: str, source: str | Path):
    """The camera named ``key``, or at index ``key``."""
    for camera in cameras:
        if camera.name == key or _file_stem(camera.name) == key:
            return camera
    if key.lstrip("-").isdigit() and -len(cameras) <= int(key) < len(cameras):
        return cameras[int(key)]
    names = ", ".join(c.name for c in cameras[:5]) + (", ..." if len(cameras) > 5 else "")
    raise InputError(f"{source}: no camera named {key!r} and no index {key} among {len(cameras)} ({names})")


def _file_stem(name: str) -> str:
    """A camera name as a safe file name: its last path component, odd characters replaced."""
    stem = re.sub(r"[^A-Za-z0-9_.-]", "_", name.replace("\\", "/").rsplit("/", 1)[-1])
    stem = re.sub(r"\.(png|jpe?g)$", "", stem, flags=re.IGNORECASE)
    return stem.strip(".") or "view"


__all__ = ["VIDEO_SUFFIXES", "Views", "render_splats"]
