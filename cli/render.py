"""``clflow render``: images and an orbit video of a 3DGS PLY file."""

from __future__ import annotations

import math
import re

import click

from clflow_cli.options import (
    FiniteFloat,
    InputFile,
    Numbers,
    OutputPath,
    count_option,
    given_options,
    max_output_option,
    out_option,
)

VIDEO_SUFFIXES = (".mp4", ".gif")
#: what only makes new views; a camera file's views are the file's
NEW_VIEW_OPTIONS = ("eye", "target", "up", "n_orbit", "elevation", "azimuth", "fov", "width", "height")


@click.command()
@click.argument("splats", type=InputFile())
@out_option("output_dir", "Folder for the PNG images (one per view).", default="renders", show_default=True)
@click.option("--cameras", "cameras_json", type=InputFile(),
              help="3DGS cameras.json; render its cameras (all, or those picked by --camera).")  # fmt: skip
@click.option("--transforms", "transforms_json", type=InputFile(),
              help="NeRF-style transforms.json; render its frames (all, or those picked by --camera).")  # fmt: skip
@click.option("--camera", "camera_keys", multiple=True, metavar="NAME|INDEX",
              help="Pick a camera of --cameras/--transforms by image name, file_path or index (repeatable).")  # fmt: skip
@click.option("--box", type=Numbers(6), metavar="X0,Y0,Z0,X1,Y1,Z1",
              help="Render only the Gaussians whose centres lie in this box (m).")  # fmt: skip
@click.option("--sphere", type=Numbers(4), metavar="X,Y,Z,R",
              help="Render only the Gaussians whose centres lie within R m of X,Y,Z.")  # fmt: skip
@click.option("--eye", type=Numbers(3), help="Look-at camera position X,Y,Z (m).")
@click.option("--target", type=Numbers(3), help="Look-at target X,Y,Z (m); default: the scene centre.")
@click.option("--up", type=Numbers(3), default="0,1,0", show_default=True,
              help="World up direction (+y, as scene configs; NeRF synthetic and Blender scenes: 0,0,1).")  # fmt: skip
@count_option("--orbit", "n_orbit", help="Render N views on a circle around the target.")
@click.option("--elevation", type=FiniteFloat(), default=20.0, show_default=True,
              help="Orbit / default view elevation above the horizontal plane, degrees.")  # fmt: skip
@click.option("--azimuth", type=FiniteFloat(), default=0.0, show_default=True, help="First orbit / default view azimuth, degrees.")  # fmt: skip
@click.option("--fov", type=FiniteFloat(1, 179), default=50.0, show_default=True,
              help="Horizontal field of view of generated views, degrees.")  # fmt: skip
@count_option('--width', default=512, help="Image width of generated views, pixels.")  # fmt: skip
@count_option('--height', default=512, help="Image height of generated views, pixels.")  # fmt: skip
@click.option("--background", type=Numbers(3, within=(0, 1)), metavar="R,G,B", default="0,0,0", show_default=True,
              help="Background colour R,G,B in [0, 1].")  # fmt: skip
@click.option("--sh-degree", type=click.IntRange(0, 3), help="Evaluate SH only up to this degree (default: all).")
@click.option("--video", type=OutputPath(file=True), help="Also write the views as a video (.mp4 or .gif).")
@click.option("--fps", type=FiniteFloat(min=0, min_open=True), default=24.0, show_default=True, help="Video frame rate.")  # fmt: skip
@click.option("--precision", type=click.Choice(["float32", "float64"]), default="float32", show_default=True,
              help="Compute precision of the rasteriser.")  # fmt: skip
@max_output_option
@click.pass_context
def render(
    ctx, splats, output_dir, box, sphere, background, sh_degree, video, fps, precision, max_output_gb, **view_options
) -> None:
    """Render SPLATS (a 3DGS PLY file, or a plain x y z [r g b] point cloud) to PNG images.

    The views are the cameras of --cameras or --transforms, a look-at camera (--eye,
    --target), an orbit of --orbit N views around the target, or by default one view that
    frames the scene (the centres between the 1st and 99th percentiles on each axis).
    --box and --sphere render a selection (both: the intersection), e.g. to check the
    object region before simulating it. Positions are in the PLY's world units (m).
    """
    import glob
    import time
    from pathlib import Path

    import numpy as np
    import torch

    from clflow.errors import InputError
    from clflow.fileio import atomic_dir, check_output_folder
    from clflow.media import to_uint8, write_image, write_video
    from clflow.splat import load_ply
    from clflow.splat.ply import require_gaussians
    from clflow.splat.render import rasterize
    from clflow_cli.progress import progress

    from_file = view_options["cameras_json"] or view_options["transforms_json"]
    unused = given_options(ctx, lambda name: name in NEW_VIEW_OPTIONS) if from_file else []
    if unused:
        raise click.UsageError(f"{', '.join(unused)} make new views, --cameras/--transforms give theirs: drop them")
    if video is not None and Path(video).suffix.lower() not in VIDEO_SUFFIXES:
        raise InputError(f"--video {video}: the file name must end in {' or '.join(VIDEO_SUFFIXES)}")
    output_dir = Path(output_dir)
    if not from_file:  # the views' number and size are the options': checked before the scene is read
        count, pixels = view_options["n_orbit"] or 1, view_options["width"] * view_options["height"]
        _check_room(output_dir, video, count, 3 * pixels * count, max_output_gb)
    gaussians = require_gaussians(load_ply(splats), splats).to(getattr(torch, precision))
    total = len(gaussians)
    if box is not None:
        gaussians = gaussians.select_box(box[:3], box[3:])
    if sphere is not None:
        gaussians = gaussians.select_sphere(sphere[:3], sphere[3])
    if (box or sphere) and len(gaussians) == 0:
        raise InputError(f"--box/--sphere select none of the {total} Gaussians of {splats}")
    cameras = _views(gaussians, **view_options)
    sizes = {(c.width, c.height) for c in cameras}
    if video is not None and len(sizes) > 1:
        raise InputError(f"--video: the views have different sizes {sorted(sizes)}; a video needs one size")
    if from_file:
        _check_room(output_dir, video, len(cameras), sum(3 * c.width * c.height for c in cameras), max_output_gb)
    stems: list[str] = []
    for i, camera in enumerate(cameras):
        stem = _file_stem(camera.name)
        stems.append(stem if stem not in stems else f"{stem}_{i:04d}")  # e.g. train/r_0 and test/r_0
    names = tuple(glob.escape(f"{stem}.png") for stem in stems)
    check_output_folder(output_dir, names, [splats])  # replaces only clflow's images: before the work
    frames = []
    seconds = 0.0
    with atomic_dir(output_dir, names, [splats]) as tmp, progress(len(cameras), "rendering") as advance:
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
    click.echo(
        f"rendered {len(gaussians)} Gaussians: {len(frames)} view(s) -> {output_dir}/ "
        f"({1e3 * seconds / len(frames):.0f} ms per view, first includes kernel builds)"
    )
    if video is not None:
        click.echo(f"video: {video}")


def _check_room(output_dir, video: str | None, count: int, image_bytes: int, max_output_gb: float) -> None:
    """Refuse ``count`` views of ``image_bytes`` in all when they (and their video) would not
    fit the disk or --max-output-gb."""
    from pathlib import Path

    from clflow.limits import check_output

    what, less = f"{count:,} views", "render fewer views"
    check_output(output_dir, image_bytes, max_output_gb, what, less)
    if video is not None:
        check_output(Path(video).parent, image_bytes, max_output_gb, what, less)


def _views(
    gaussians,
    *,
    cameras_json,
    transforms_json,
    camera_keys,
    eye,
    target,
    up,
    n_orbit,
    elevation,
    azimuth,
    fov,
    width,
    height,
):
    """The cameras the view options ask for (the command's options of those names; angles in
    degrees, sizes in pixels; see the command's help)."""
    import torch

    from clflow.errors import InputError
    from clflow.splat import cameras as cams

    if cameras_json and transforms_json:
        raise InputError("give --cameras or --transforms, not both")
    if cameras_json or transforms_json:
        loaded = cams.load_cameras_json(cameras_json) if cameras_json else cams.load_transforms_json(transforms_json)
        return [_pick(loaded, key, cameras_json or transforms_json) for key in camera_keys] or loaded
    if camera_keys:
        raise InputError("--camera picks from --cameras or --transforms; give one of them")
    elevation, azimuth = math.radians(elevation), math.radians(azimuth)
    view = dict(fov_x=math.radians(fov), width=width, height=height)
    if eye is None:
        low, high = gaussians.bounds(quantile=0.01)
        if target is not None:  # keep the framing distance, centre the given target
            shift = torch.tensor(target, dtype=low.dtype) - 0.5 * (low + high)
            low, high = low + shift, high + shift
        return cams.frame_box(low, high, n_views=n_orbit or 1, elevation=elevation, azimuth=azimuth, up=up, **view)
    if target is None:
        low, high = gaussians.bounds(quantile=0.01)
        target = (0.5 * (low + high)).tolist()
    if not n_orbit:
        return [cams.look_at(eye, target, up, keys=("--eye", "--target", "--up"), **view)]
    # An orbit through the eye: its distance to the target and its elevation about up.
    offset = torch.tensor(eye, dtype=torch.float64) - torch.tensor(target, dtype=torch.float64)
    unit_up = torch.tensor(up, dtype=torch.float64) / torch.tensor(up, dtype=torch.float64).norm()
    radius = offset.norm().item()
    if radius == 0:
        raise InputError("--eye and --target are the same point")
    return cams.orbit(
        target,
        radius,
        n_views=n_orbit,
        elevation=math.asin((offset @ unit_up).item() / radius),
        up=up,
        azimuth=azimuth,
        **view,
    )


def _pick(cameras, key: str, source: str):
    """The camera named ``key``, or at index ``key``."""
    for camera in cameras:
        if camera.name == key or _file_stem(camera.name) == key:
            return camera
    if key.lstrip("-").isdigit() and -len(cameras) <= int(key) < len(cameras):
        return cameras[int(key)]
    from clflow.errors import InputError

    names = ", ".join(c.name for c in cameras[:5]) + (", ..." if len(cameras) > 5 else "")
    raise InputError(f"{source}: no camera named {key!r} and no index {key} among {len(cameras)} ({names})")


def _file_stem(name: str) -> str:
    """A camera name as a safe file name: its last path component, odd characters replaced."""
    stem = re.sub(r"[^A-Za-z0-9_.-]", "_", name.replace("\\", "/").rsplit("/", 1)[-1])
    stem = re.sub(r"\.(png|jpe?g)$", "", stem, flags=re.IGNORECASE)
    return stem.strip(".") or "view"
