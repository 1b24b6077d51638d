"""``clflow bench reconstruct``: training speed and held-out quality of ``clflow reconstruct``
on a procedural capture (datasets_tools.multiview)."""

import click

from clflow_cli.bench import bench_command
from clflow_cli.options import count_option

THRESHOLDS_DB = (25.0, 28.0)


@bench_command("reconstruct")
@click.option("--views", type=click.IntRange(min=2), default=60, show_default=True, help="Cameras around the shape.")
@click.option("--size", type=click.IntRange(min=16), default=128, show_default=True, help="Image side, pixels.")
@click.option("--shape", type=click.Choice(["sphere", "cube", "torus"]), default="sphere", show_default=True)
@click.option("--detail", type=click.IntRange(min=2), default=32, show_default=True,
              help="Ground-truth Gaussians per face side (6 detail^2 in all).")  # fmt: skip
@count_option("--iterations", default=3000)
@count_option("--init-points", default=5000)
@count_option('--eval-every', default=250, help="Held-out PSNR every N iterations (not timed).")  # fmt: skip
def reconstruct(views, size, shape, detail, iterations, init_points, eval_every) -> dict:
    """Iterations per second, held-out PSNR / SSIM and seconds to reach 25 and 28 dB.

    The schedule is 3DGS's scaled to the budget: densify from 10 % to 60 % of the
    iterations, SH degree up every third of them, no opacity reset.
    """
    import os
    import tempfile

    from clflow.benchmark import measure
    from clflow.recon import Settings, load_views
    from clflow.recon.train import reconstruct as train
    from clflow_datasets.multiview import make_multiview

    settings = Settings(
        iterations=iterations,
        densify_from=iterations // 10,
        densify_until=6 * iterations // 10,
        reset_every=iterations + 1,
        sh_every=max(1, iterations // 3),
        init_points=init_points,
    )
    with tempfile.TemporaryDirectory() as folder:
        make_multiview(folder, shape=shape, views=views, size=size, detail=detail)
        data = load_views(os.path.join(folder, "images"))
        timing = measure(
            lambda: train(
                data, os.path.join(folder, "out"), settings, checkpoint_every=iterations, eval_every=eval_every
            ),
            warmup=0,
        )
    metrics = timing.result.metrics
    test = metrics["test"]
    click.echo(
        f"{shape}, {views} views at {size}^2 ({test['views']} held out), {iterations} iterations, "
        f"load {timing.load_before} -> {timing.load_after}"
    )
    click.echo(
        f"  {metrics['iterations_per_second']:.1f} it/s, {metrics['seconds']:.0f} s, {metrics['gaussians']} Gaussians"
    )
    click.echo(f"  held-out PSNR {test['psnr']:.2f} dB, SSIM {test['ssim']:.4f}")
    reached_s = {}
    for threshold in THRESHOLDS_DB:
        reached = next((row for row in metrics["history"] if row[2] >= threshold), None)
        reached_s[f"{threshold:.0f}_db_s"] = reached[1] if reached else None
        click.echo(
            f"  {threshold:.0f} dB: " + (f"{reached[1]:.0f} s (iteration {reached[0]})" if reached else "not reached")
        )
    return {
        "run": timing.record(),
        "iterations_per_second": metrics["iterations_per_second"],
        "gaussians": metrics["gaussians"],
        "psnr_db": test["psnr"],
        "ssim": test["ssim"],
        **reached_s,
    }
