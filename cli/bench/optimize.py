"""``clflow bench optimize``: time per optimisation iteration of a demo-like scene, of a
benchmark case, or of your own config, with the scene's shape (particles a cell)."""

import click

from clflow_cli.bench import bench_command
from clflow_cli.options import InputFile, count_option

DEMO_SIZES = ("gaussians", "image", "frames", "grid")


@bench_command("optimize")
@click.option("--gaussians", type=click.IntRange(min=100), default=100_000, show_default=True,
              help="Gaussians in the demo-like scene (a fifth on the simulated object).")  # fmt: skip
@click.option("--image", type=click.IntRange(min=16), default=256, show_default=True, help="Guidance image side, px.")
@click.option("--frames", type=click.IntRange(min=2), default=12, show_default=True, help="Frames simulated.")
@click.option("--grid", type=click.IntRange(min=8), default=24, show_default=True, help="Grid nodes along the longest side.")  # fmt: skip
@click.option("--config", "config_path", type=InputFile(), default=None, metavar="FILE",
              help="Time this scene config instead of the demo-like scene (a trained 3DGS object, say): its own "
                   "scene, guidance, grid and method; its output folder is left alone.")  # fmt: skip
@click.option("--case", default=None, metavar="NAME",
              help="Time a case of `clflow eval sysid` (the paper's nine or the extra set's) instead, its guidance "
                   "made at the optimiser's own resolution.")  # fmt: skip
@click.option("--quick", is_flag=True, help="With --case: the quick resolution of `clflow eval sysid --quick`.")
@click.option("--at-truth", is_flag=True,
              help="Start from the config's evaluation.ground_truth (a case's truth) instead of its initial guess: "
                   "iterations near a fit (a published guess may be unstable without the search).")  # fmt: skip
@count_option("--iterations", default=2, help="Iterations timed.")
def optimize(gaussians, image, frames, grid, config_path, case, quick, at_truth, iterations):
    """Make a demo-like scene (datasets_tools), or take a benchmark case or your config, then
    time full-horizon iterations of `clflow optimize` (no search; the config's method: Adam's
    simulate + adjoint, render simulated flow, loss and its backward, or Levenberg-Marquardt's
    runs), and say how the particles fill the grid (particles a cell: what the cell-sorted GPU
    kernels' time follows). --profile profiles the timed iterations alone."""
    import dataclasses
    import tempfile
    import warnings
    from pathlib import Path

    from click.core import ParameterSource

    from clflow.benchmark import measure
    from clflow.mpm.simulator import StabilityWarning
    from clflow.mpm.substep import cell_occupancy
    from clflow.pipeline.fit import Optimization
    from clflow.runtime import get_device
    from clflow.scene.config import load_config

    ctx = click.get_current_context()
    given = [f"--{n}" for n in DEMO_SIZES if ctx.get_parameter_source(n) is not ParameterSource.DEFAULT]
    if config_path and case:
        raise click.UsageError("--config and --case both choose the scene: give one")
    if (config_path or case) and given:
        raise click.UsageError(f"{', '.join(given)} size the demo-like scene; --config and --case bring their own")
    if quick and not case:
        raise click.UsageError("--quick sizes a --case")
    warnings.simplefilter("ignore", StabilityWarning)
    with tempfile.TemporaryDirectory(prefix="clflow-bench-") as folder:
        make = measure(
            lambda: _scene(Path(folder), config_path, case, quick, (gaussians, image, grid, frames)), warmup=0
        )
        cfg = load_config(make.result)
        cfg = dataclasses.replace(
            cfg,
            output=Path(folder) / "output",  # never the config's own
            optimize=dataclasses.replace(
                cfg.optimize,
                iterations=iterations,
                horizon_start=0,
                search=None,
                materials={},
                estimate_velocity_iterations=0,
                estimate_velocity_frames=0,
                budget=None,
            ),
        )
        if at_truth:
            cfg = _at_truth(cfg)
        load = measure(lambda: Optimization(cfg), warmup=0)
        opt = load.result
        setup = opt.problem.prepared.setup
        n_gauss = opt.problem.prepared.obj_rest.means.shape[0] + opt.problem.prepared.static.means.shape[0]
        occupancy = cell_occupancy(setup.grid, setup.particles.positions)
        click.echo(
            f"scene: {n_gauss:,} Gaussians ({setup.particles.n_gaussians:,} on the simulated objects, "
            f"{setup.particles.n_fill:,} fill particles), grid {setup.grid.resolution}, "
            f"{cfg.simulation.frames} frames, {cfg.optimize.method}"
        )
        click.echo(f"  at rest: {occupancy.summary()}")
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
        if device.profile is not None:  # --profile: the timed iterations', not making and loading the scene
            device.stop_profile()
            device.start_profile()
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
        "scene": {
            "source": str(config_path) if config_path else f"case {case}{' (quick)' * quick}" if case else "demo",
            "gaussians": n_gauss,
            "particles": setup.particles.positions.shape[0],
            "grid": list(setup.grid.resolution),
            "frames": cfg.simulation.frames,
            "method": cfg.optimize.method,
            "start": {  # the material parameters the iterations start from (SI)
                (f"{o.name}.{n}" if len(cfg.objects) > 1 else n): v
                for o in cfg.objects
                for n, v in o.material.parameters.items()
            },
            "occupancy": dataclasses.asdict(occupancy),
        },
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


def _at_truth(cfg):
    """``cfg`` with each object's material parameters at its evaluation.ground_truth."""
    import dataclasses

    from clflow.scene.config import split_parameter

    if not cfg.ground_truth:
        raise click.UsageError(f"--at-truth: {cfg.source} has no evaluation.ground_truth")
    truths = [{} for _ in cfg.objects]
    for name, value in cfg.ground_truth.items():
        k, param = split_parameter(cfg.objects, name)
        if param in cfg.objects[k].material.parameters:
            truths[k][param] = value
    return cfg.with_objects(
        dataclasses.replace(o, material=dataclasses.replace(o.material, parameters={**o.material.parameters, **t}))
        for o, t in zip(cfg.objects, truths)
    )


def _scene(folder, config_path, case: str | None, quick: bool, demo_size: tuple[int, int, int, int]):
    """The config file to time: ``config_path`` itself, ``case`` made in ``folder``, or the
    demo-like scene of ``demo_size`` (Gaussians, image side, grid nodes, frames) made there."""
    if config_path:
        return config_path
    if case:
        from clflow_datasets.synthetic import make_case
        from clflow_datasets.sysid import FULL, QUICK
        from clflow_datasets.sysid_cases import CASES, EXTRA_CASES_FILE, load_cases

        catalogue = {**CASES, **load_cases(EXTRA_CASES_FILE)}
        if case not in catalogue:
            raise click.BadParameter(f"{case!r} is no case; the cases: {', '.join(catalogue)}", param_hint="--case")
        return make_case(folder / case, catalogue[case], QUICK if quick else FULL)
    from clflow_datasets.demo import benchmark_size, make_demo

    return make_demo(folder, benchmark_size(*demo_size))
