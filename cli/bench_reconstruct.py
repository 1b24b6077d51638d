"""``clflow bench reconstruct``: training speed and held-out quality of ``clflow reconstruct``
on a procedural capture (datasets_tools.multiview)."""

import click

THRESHOLDS_DB = (25.0, 28.0)


@click.command()
@click.option("--views", type=click.IntRange(min=2), default=60, show_default=True, help="Cameras around the shape.")
@click.option("--size", type=click.IntRange(min=16), default=128, show_default=True, help="Image side, pixels.")
@click.option("--shape", type=click.Choice(["sphere", "cube", "torus"]), default="sphere", show_default=True)
@click.option("--detail", type=click.IntRange(min=2), default=32, show_default=True,
              help="Ground-truth Gaussians per face side (6 detail^2 in all).")
@click.option("--iterations", type=click.IntRange(min=1), default=3000, show_default=True)
@click.option("--init-points", type=click.IntRange(min=1), default=5000, show_default=True)
@click.option("--eval-every", type=click.IntRange(min=1), default=250, show_default=True,
              help="Held-out PSNR every N iterations (not timed).")
def reconstruct(views, size, shape, detail, iterations, init_points, eval_every) -> None:
    """Iterations per second, held-out PSNR / SSIM and seconds to reach 25 and 28 dB.

    The schedule is 3DGS's scaled to the budget: densify from 10 % to 60 % of the
    iterations, SH degree up every third of them, no opacity reset.
    """
    import os
    import tempfile

    from clflow.recon import Settings, load_views
    from clflow.recon.train import reconstruct as train
    from clflow_datasets.multiview import make_multiview

    settings = Settings(iterations=iterations, densify_from=iterations // 10, densify_until=6 * iterations // 10,
                        reset_every=iterations + 1, sh_every=max(1, iterations // 3), init_points=init_points)
    with tempfile.TemporaryDirectory() as folder:
        make_multiview(folder, shape=shape, views=views, size=size, detail=detail)
        data = load_views(os.path.join(folder, "images"))
        load = os.getloadavg()[0]
        metrics = train(data, os.path.join(folder, "out"), settings, checkpoint_every=iterations, eval_every=eval_every).metrics
    test = metrics["test"]
    click.echo(f"{shape}, {views} views at {size}^2 ({test['views']} held out), {iterations} iterations, "
               f"load {load:.1f} -> {os.getloadavg()[0]:.1f}")
    click.echo(f"  {metrics['iterations_per_second']:.1f} it/s, {metrics['seconds']:.0f} s, {metrics['gaussians']} Gaussians")
    click.echo(f"  held-out PSNR {test['psnr']:.2f} dB, SSIM {test['ssim']:.4f}")
    for threshold in THRESHOLDS_DB:
        reached = next((row for row in metrics["history"] if row[2] >= threshold), None)
        click.echo(f"  {threshold:.0f} dB: " + (f"{reached[1]:.0f} s (iteration {reached[0]})" if reached else "not reached"))
