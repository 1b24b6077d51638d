"""``clflow reconstruct``: 3D Gaussians trained from posed images (3DGS recipe, OpenCL rasteriser)."""

from __future__ import annotations

import sys

import click

from clflow_cli.main import Interrupted

LOG_EVERY = 100  # iterations between progress lines when stderr is not a terminal


@click.command("reconstruct")
@click.argument("images", type=click.Path(file_okay=False))
@click.option("-o", "--output-dir", required=True, type=click.Path(file_okay=False),
              help="Folder for point_cloud.ply, cameras.json, metrics.json, checkpoint.pt and preview/.")
@click.option("--transforms", type=click.Path(dir_okay=False), help="NeRF-style transforms.json (OpenGL axes).")
@click.option("--colmap", type=click.Path(file_okay=False), help="COLMAP sparse model folder (.bin or .txt), e.g. sparse/0.")
@click.option("--cameras", "cameras_json", type=click.Path(dir_okay=False), help="3DGS cameras.json.")
@click.option("--masks", type=click.Path(file_okay=False),
              help="Folder of masks named like the images (white = object); default: the images' alpha channel, if any.")
@click.option("--background", type=click.Choice(["black", "white"]), default="black", show_default=True,
              help="Colour behind the masked object, in the targets and the renders.")
@click.option("--iterations", type=click.IntRange(min=1), help="Training iterations (default 7000).")
@click.option("--seed", type=int, help="Seeds the initial points, view order and splits (default 0).")
@click.option("--sh-degree", type=click.IntRange(0, 3), help="Highest SH degree (default 3).")
@click.option("--sh-every", type=click.IntRange(min=1), help="Raise the SH degree by one every N iterations (default 1000).")
@click.option("--densify-from", type=click.IntRange(min=0), help="First densification after this iteration (default 500).")
@click.option("--densify-until", type=click.IntRange(min=0), help="Last densification at this iteration (default 3500).")
@click.option("--densify-every", type=click.IntRange(min=1), help="Densify every N iterations (default 100).")
@click.option("--reset-every", type=click.IntRange(min=1),
              help="Reset the opacities every N iterations while densifying (default 3000).")
@click.option("--init-points", type=click.IntRange(min=1),
              help="Random initial Gaussians when the cameras bring no point cloud (COLMAP's points3D; default 10000).")
@click.option("--holdout-every", type=click.IntRange(min=0),
              help="Hold out views 0, N, 2N, ... for the metrics (0: none; default 8).")
@click.option("--preview-every", type=click.IntRange(min=0), default=500, show_default=True,
              help="Write preview/iter_N.png (render | target of a held-out view) every N iterations (0: never).")
@click.option("--checkpoint-every", type=click.IntRange(min=1), default=1000, show_default=True)
@click.option("--resume", is_flag=True, help="Continue from OUTPUT_DIR/checkpoint.pt with the same options.")
def reconstruct(images, output_dir, transforms, colmap, cameras_json, masks, background, iterations, seed, sh_degree,
                sh_every, densify_from, densify_until, densify_every, reset_every, init_points, holdout_every,
                preview_every, checkpoint_every, resume) -> None:
    """Train 3D Gaussians on the posed IMAGES and write a standard 3DGS PLY.

    Cameras come from --transforms, --colmap or --cameras, or are found next to IMAGES
    (transforms.json, cameras.json or sparse/0 in it or its parent). Every input is
    checked before training: missing images, images whose size differs from their
    camera's, non-orthonormal rotations and empty masks end with a one-line error. The
    held-out views' PSNR and SSIM go to metrics.json. Units are the cameras' (m).
    """
    from clflow.recon import Settings, load_views
    from clflow.recon.train import reconstruct as train

    rgb = (1.0, 1.0, 1.0) if background == "white" else (0.0, 0.0, 0.0)
    given = dict(iterations=iterations, seed=seed, sh_degree=sh_degree, sh_every=sh_every, densify_from=densify_from,
                 densify_until=densify_until, densify_every=densify_every, reset_every=reset_every,
                 init_points=init_points, holdout_every=holdout_every)
    settings = Settings(background=rgb, **{k: v for k, v in given.items() if v is not None})
    iterations = settings.iterations
    views = load_views(images, transforms=transforms, colmap=colmap, cameras_json=cameras_json, masks=masks,
                       background=rgb)
    click.echo(f"{len(views.views)} views; training {iterations} iterations -> {output_dir}", err=True)
    show = lambda info: "" if info is None else f"PSNR {info['psnr']:.2f} dB, {info['gaussians']} Gaussians"  # noqa: E731
    with click.progressbar(length=iterations, label="reconstructing", show_pos=True, item_show_func=show,
                           file=sys.stderr) as bar:
        def progress(step: int, info: dict) -> None:
            if sys.stderr.isatty():
                bar.update(step - bar.pos, info)
            elif step % LOG_EVERY == 0 or step == iterations:
                click.echo(f"iteration {step}/{iterations}: {show(info)}", err=True)

        try:
            result = train(views, output_dir, settings, resume=resume, checkpoint_every=checkpoint_every,
                           preview_every=preview_every, progress=progress)
        except KeyboardInterrupt:
            raise Interrupted(f"interrupted; the last checkpoint (every {checkpoint_every} iterations) is in "
                              f"{output_dir}/checkpoint.pt: continue with the same command and --resume") from None
    test = result.metrics["test"]
    held_out = (f"held-out PSNR {test['psnr']:.2f} dB, SSIM {test['ssim']:.4f} ({test['views']} views)"
                if test["views"] else "no held-out views")
    click.echo(f"{result.metrics['gaussians']} Gaussians, {held_out}, "
               f"{result.metrics['iterations_per_second'] or 0:.1f} it/s -> {output_dir}/point_cloud.ply")
