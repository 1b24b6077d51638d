"""``clflow reconstruct``: 3D Gaussians trained from posed images (3DGS recipe, OpenCL rasteriser)."""

from __future__ import annotations

import click

from clflow_cli.options import InputFile, count_option, given_options, out_option
from clflow_cli.progress import note, progress

LOG_EVERY = 100  # iterations between progress lines when stderr is not a terminal
#: what only a photo and its depth map take (no training), and what every reconstruction takes
DEPTH_OPTIONS = ("depth_scale", "fov", "shell")
COMMON_OPTIONS = ("images", "output_dir", "depth")
#: where a training's views come from (clflow.recon.load_views' options of those names)
VIEW_SOURCES = ("transforms", "colmap", "cameras_json", "frame", "masks")


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
@count_option('--reset-every', help="Reset the opacities every N iterations while densifying, where N more follow (default 3000).")  # fmt: skip
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
    if photo:
        from clflow.pipeline.runs import reconstruct_photo

        reconstruct_photo(images, depth, output_dir, depth_scale, fov, shell, echo=click.echo)
        return
    from clflow.pipeline.runs import reconstruct_images
    from clflow.recon import Settings

    sources = {name: training.pop(name) for name in VIEW_SOURCES}
    rgb = (1.0, 1.0, 1.0) if background == "white" else (0.0, 0.0, 0.0)
    # training: --iterations, --seed, --sh-degree, ... --holdout-every, Settings' fields by name (None: its default)
    settings = Settings(background=rgb, **{k: v for k, v in training.items() if v is not None})
    show = lambda info: f"PSNR {info['psnr']:.2f} dB, {info['gaussians']} Gaussians"  # noqa: E731
    reconstruct_images(
        images,
        output_dir,
        settings,
        sources=sources,
        resume=resume,
        checkpoint_every=checkpoint_every,
        preview_every=preview_every,
        echo=click.echo,
        note=note,
        progress=lambda total, label: progress(total, label, show=show, every=LOG_EVERY),
    )
