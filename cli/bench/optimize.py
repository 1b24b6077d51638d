"""``clflow bench optimize``: time per optimisation iteration of a demo-like scene."""

import click

from clflow_cli.bench import bench_command
from clflow_cli.options import count_option


@bench_command("optimize")
@click.option("--gaussians", type=click.IntRange(min=100), default=100_000, show_default=True,
              help="Gaussians in the scene (a fifth on the simulated object).")  # fmt: skip
@click.option("--image", type=click.IntRange(min=16), default=256, show_default=True, help="Guidance image side, px.")
@click.option("--frames", type=click.IntRange(min=2), default=12, show_default=True, help="Frames simulated.")
@click.option("--grid", type=click.IntRange(min=8), default=24, show_default=True, help="Grid nodes along the longest side.")  # fmt: skip
@count_option("--iterations", default=2, help="Iterations timed.")
def optimize(gaussians, image, frames, grid, iterations):
    """Make a demo-like scene (datasets_tools), then time full-horizon iterations of
    `clflow optimize`: simulate + adjoint, render simulated flow, loss and its backward."""
    import dataclasses
    import tempfile
    import warnings

    from clflow.benchmark import measure
    from clflow.mpm.simulator import StabilityWarning
    from clflow.pipeline.fit import Optimization
    from clflow.runtime import get_device
    from clflow.scene.config import load_config
    from clflow_datasets.demo import benchmark_size, make_demo

    warnings.simplefilter("ignore", StabilityWarning)
    size = benchmark_size(gaussians, image, grid, frames)
    with tempfile.TemporaryDirectory(prefix="clflow-bench-") as folder:
        make = measure(lambda: make_demo(folder, size), warmup=0)
        cfg = load_config(make.result)
        cfg = dataclasses.replace(
            cfg, optimize=dataclasses.replace(cfg.optimize, iterations=iterations, horizon_start=0)
        )
        load = measure(lambda: Optimization(cfg), warmup=0)
        opt = load.result
        setup = opt.problem.prepared.setup
        n_gauss = opt.problem.prepared.obj_rest.means.shape[0] + opt.problem.prepared.static.means.shape[0]
        click.echo(
            f"scene: {n_gauss:,} Gaussians ({setup.particles.n_gaussians:,} on the object, "
            f"{setup.particles.n_fill:,} fill particles), grid {setup.grid.resolution}, {frames} frames, "
            f"{image}x{image} px"
        )
        click.echo(
            f"  make scene + guidance video {make.median_wall:7.2f} s;  load, fill, video flow "
            f"{load.median_wall:7.2f} s"
        )
        rows, device = [], get_device()
        copied = []  # bytes moved between host and device by each iteration

        def record(row: dict) -> None:  # each row has the iteration's seconds, as the optimiser timed it
            rows.append(row)
            copied.append(device.transfers.since(marks[-1]))
            marks.append(device.transfers.mark())

        marks = [device.transfers.mark()]
        opt.progress = record
        run = measure(opt.run, warmup=0)
        for row, moved in zip(rows, copied):
            click.echo(
                f"  iteration {row['iteration']}: {row['seconds']:7.2f} s ({row['substeps']} substeps per frame; "
                f"copied {moved.to_device / 2**20:.1f} MiB to the device, {moved.to_host / 2**20:.1f} MiB to the host)"
            )
        best = min(r["seconds"] for r in rows)
        click.echo(f"  per iteration: {best:.2f} s best, {sum(r['seconds'] for r in rows) / len(rows):.2f} s mean")
        click.echo(f"  device: {device.info.label} ({'shared' if device.zero_copy else 'separate'} memory)")
    return {
        "make_scene": make.record(),
        "load": load.record(),
        "run": run.record(),
        "iterations": [
            {
                "seconds": r["seconds"],
                "substeps": r["substeps"],
                "bytes_to_device": m.to_device,
                "bytes_to_host": m.to_host,
            }
            for r, m in zip(rows, copied)
        ],
    }
