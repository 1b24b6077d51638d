"""``clflow reconstruct``: 3D Gaussians trained from posed images (3DGS recipe, OpenCL rasteriser)."""

from __future__ import annotations

import click

from clflow_cli.main import Interrupted
from clflow_cli.options import InputFile, count_option, given_options, out_option
from clflow_cli.progress import progress

LOG_EVERY = 100  # iterations between progress lines when stderr is not a terminal
#: what only a photo and its depth map take (no training), and what every reconstruction takes
DEPTH_OPTIONS = ("depth_scale", "fov", "shell")
COMMON_OPTIONS = ("images", "output_dir", "depth")
#: what reconstruct writes into its folder
RECONSTRUCTION_ENTRIES = ("point_cloud.ply", "cameras.json", "metrics.json", "checkpoint.pt", "preview")


@click.command("reconstruct")
@click.argument("images", type=click.Path())
@out_option("output_dir", "Folder for point_cloud.ply, cameras.json, metrics.json, checkpoint.pt and preview/.",
            required=True)  # fmt: skip
@click.option("--transforms", type=InputFile(), help="NeRF-style transforms.json (OpenGL axes).")
@click.option("--colmap", type=click.Path(file_okay=False), help="COLMAP sparse model folder (.bin or .txt), e.g. sparse/0.")  # fmt: skip
@click.option("--cameras", "cameras_json", type=InputFile(), help="3DGS cameras.json.")
@click.option("--frame", type=int,
              help="IMAGES is a PAC-NeRF-style multi-camera sequence (a folder with all_data.json): train on "
                   "every camera's image of this frame.")  # fmt: skip
@click.option("--masks", type=click.Path(file_okay=False),
              help="Folder of masks named like the images (white = object); default: the images' alpha channel, if any.")  # fmt: skip
@click.option("--background", type=click.Choice(["black", "white"]), default="black", show_default=True,
              help="Colour behind the masked object, in the targets and the renders.")  # fmt: skip
@count_option("--iterations", help="Training iterations (default 7000).")
@click.option("--seed", type=int, help="Seeds the initial points, view order and splits (default 0).")
@click.option("--sh-degree", type=click.IntRange(0, 3), help="Highest SH degree (default 3).")
@count_option('--sh-every', help="Raise the SH degree by one every N iterations (default 1000).")  # fmt: skip
@click.option("--densify-from", type=click.IntRange(min=0), help="First densification after this iteration (default 500).")  # fmt: skip
@click.option("--densify-until", type=click.IntRange(min=0), help="Last densification at this iteration (default 3500).")  # fmt: skip
@count_option("--densify-every", help="Densify every N iterations (default 100).")
@count_option('--reset-every', help="Reset the opacities every N iterations while densifying (default 3000).")  # fmt: skip
@count_option('--init-points', help="Random initial Gaussians when the cameras bring no point cloud (COLMAP's points3D; default 10000).")  # fmt: skip
@click.option("--holdout-every", type=click.IntRange(min=0),
              help="Hold out views 0, N, 2N, ... for the metrics (0: none; default 8).")  # fmt: skip
@click.option("--preview-every", type=click.IntRange(min=0), default=500, show_default=True,
              help="Write preview/iter_N.png (render | target of a held-out view) every N iterations (0: never).")  # fmt: skip
@count_option("--checkpoint-every", default=1000)
@click.option("--resume", is_flag=True, help="Continue from OUT/checkpoint.pt with the same options.")
@click.option("--depth", type=InputFile(),
              help="Single image + depth: IMAGES is one image, this its depth map (.npy in m, or 16-bit PNG); no training.")  # fmt: skip
@click.option("--depth-scale", type=click.FloatRange(min=0, min_open=True),
              help="Metres per depth unit (default: 1 for .npy, 0.001 for PNG).")  # fmt: skip
@click.option("--fov", type=click.FloatRange(1, 179), default=50.0, show_default=True,
              help="With --depth: horizontal field of view of the photo, degrees.")  # fmt: skip
@click.option("--shell", type=click.Choice(["mirror", "extrude", "none"]), default="mirror", show_default=True,
              help="With --depth: how the hidden side is closed.")  # fmt: skip
@click.pass_context
def reconstruct(
    ctx,
    images,
    output_dir,
    transforms,
    colmap,
    cameras_json,
    frame,
    masks,
    background,
    preview_every,
    checkpoint_every,
    resume,
    depth,
    depth_scale,
    fov,
    shell,
    **training,
) -> None:
    """Train 3D Gaussians on the posed IMAGES and write a standard 3DGS PLY.

    Cameras come from --transforms, --colmap or --cameras, or are found next to IMAGES
    (transforms.json, cameras.json or sparse/0 in it or its parent). With --frame N,
    IMAGES is a multi-camera sequence laid out as PAC-NeRF's data (all_data.json and
    r_CAMERA_FRAME.png images) and the views are frame N of every camera. Every input is
    checked before training: missing images, images whose size differs from their
    camera's, non-orthonormal rotations and empty masks end with a one-line error. The
    held-out views' PSNR and SSIM go to metrics.json. Units are the cameras' (m).

    With --depth, IMAGES is a single photo: its pixels are back-projected along a camera at
    the origin (OpenCV axes, --fov) into Gaussians, the hidden side closed by --shell, and
    point_cloud.ply and cameras.json are written without training.
    """
    photo = depth is not None
    unused = given_options(
        ctx, lambda name: name not in DEPTH_OPTIONS + COMMON_OPTIONS if photo else name in DEPTH_OPTIONS
    )
    if unused:
        why = "with --depth nothing is trained" if photo else "they go with --depth (a photo and its depth map)"
        raise click.UsageError(f"{why}: drop {', '.join(unused)}")
    from clflow.fileio import check_output_folder, output_folder

    inputs = [path for path in (images, depth, transforms, colmap, cameras_json, masks) if path is not None]
    with output_folder(output_dir):  # this run's: other runs are refused, before any work
        check_output_folder(output_dir, RECONSTRUCTION_ENTRIES, inputs)  # replaces only clflow's
        if depth is not None:
            return _from_depth(images, depth, depth_scale, fov, shell, output_dir)
        _train(images, output_dir, background, training, transforms, colmap, cameras_json, masks, frame, resume,
               checkpoint_every, preview_every)  # fmt: skip


def _train(images, output_dir, background, training, transforms, colmap, cameras_json, masks, frame, resume,
           checkpoint_every, preview_every) -> None:  # fmt: skip
    """reconstruct's training, once the output folder is held and checked."""
    from clflow.recon import Settings, load_views
    from clflow.recon.train import reconstruct as train

    rgb = (1.0, 1.0, 1.0) if background == "white" else (0.0, 0.0, 0.0)
    # training: --iterations, --seed, --sh-degree, ... --holdout-every, Settings' fields by name (None: its default)
    settings = Settings(background=rgb, **{k: v for k, v in training.items() if v is not None})
    iterations = settings.iterations
    views = load_views(
        images,
        transforms=transforms,
        colmap=colmap,
        cameras_json=cameras_json,
        masks=masks,
        background=rgb,
        frame=frame,
    )
    click.echo(f"{len(views.views)} views; training {iterations} iterations -> {output_dir}", err=True)
    show = lambda info: f"PSNR {info['psnr']:.2f} dB, {info['gaussians']} Gaussians"  # noqa: E731
    with progress(iterations, "reconstructing", show=show, every=LOG_EVERY) as advance:
        try:
            result = train(
                views,
                output_dir,
                settings,
                resume=resume,
                checkpoint_every=checkpoint_every,
                preview_every=preview_every,
                progress=lambda step, info: advance(info, to=step),
            )
        except KeyboardInterrupt:
            from pathlib import Path

            if not (Path(output_dir) / "checkpoint.pt").is_file():
                raise Interrupted("interrupted before the first checkpoint; nothing was saved") from None
            raise Interrupted(
                f"interrupted; the last checkpoint (every {checkpoint_every} iterations) is in "
                f"{output_dir}/checkpoint.pt: continue with the same command and --resume"
            ) from None
    _echo_result(result.metrics, output_dir)


def _echo_result(metrics: dict, output_dir) -> None:
    """One line: the Gaussians, the held-out views' PSNR and SSIM, the speed and the PLY."""
    test = metrics["test"]
    held_out = (
        f"held-out PSNR {test['psnr']:.2f} dB, SSIM {test['ssim']:.4f} ({test['views']} views)"
        if test["views"]
        else "no held-out views"
    )
    click.echo(
        f"{metrics['gaussians']} Gaussians, {held_out}, "
        f"{metrics['iterations_per_second'] or 0:.1f} it/s -> {output_dir}/point_cloud.ply"
    )


def _from_depth(image_path, depth_path, depth_scale, fov, shell, output_dir) -> None:
    """Write the back-projected Gaussians of one photo and its camera."""
    import math
    from pathlib import Path

    import torch

    from clflow.errors import InputError
    from clflow.media import read_image
    from clflow.recon.depth import backproject, read_depth
    from clflow.splat.cameras import Camera, intrinsics, save_cameras_json
    from clflow.splat.ply import save_ply

    if not Path(image_path).is_file():
        raise InputError(f"{image_path}: with --depth, IMAGES must be one image file")
    rgba = torch.from_numpy(read_image(Path(image_path)))
    height, width = rgba.shape[:2]
    camera = Camera(
        torch.eye(4, dtype=torch.float64),
        intrinsics(width, height, math.radians(fov)),
        width,
        height,
        Path(image_path).name,
    )
    mask = rgba[..., 3] > 0.5 if rgba.shape[2] == 4 else None
    gaussians = backproject(rgba[..., :3], read_depth(depth_path, depth_scale), camera, mask=mask, shell=shell)
    save_ply(Path(output_dir) / "point_cloud.ply", gaussians)
    save_cameras_json(Path(output_dir) / "cameras.json", [camera])
    click.echo(f"{len(gaussians)} Gaussians from {image_path} and {depth_path} -> {output_dir}/point_cloud.ply")
