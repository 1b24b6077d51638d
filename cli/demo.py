"""``clflow demo``: the bundled end-to-end example, made from scratch and run."""

from __future__ import annotations

import click


@click.command("demo")
@click.argument("folder", type=click.Path(file_okay=False), default="clflow-demo")
@click.option("--quick", is_flag=True, help="A smaller scene (for a first look or CI): about a minute.")
@click.option("--resume", is_flag=True, help="Continue an interrupted optimisation of an existing demo folder.")
@click.option("--views", type=click.IntRange(min=0), default=2, show_default=True,
              help="Fixed novel viewpoints of the 4D render.")  # fmt: skip
@click.option("--force", is_flag=True, help="Overwrite the demo's files (config.yaml, results/, ...) in FOLDER.")
def demo(folder, quick, resume, views, force):
    """Make the demo case in FOLDER (a jelly cube pushed sideways on a floor; its guidance
    video rendered from a ground-truth simulation, E = 20 kPa), then recover Young's
    modulus from a 10x too low guess (`clflow optimize`), simulate with the result
    (`clflow simulate`) and render it in 4D (`clflow render4d`)."""
    import time
    from pathlib import Path

    from clflow.pipeline.report import write_report
    from clflow.pipeline.runs import render_simulation_4d, run_optimization, simulate_scene
    from clflow_cli.progress import iteration_bar, note, progress
    from clflow_datasets.demo import QUICK, make_demo
    from clflow_datasets.synthetic import CASE_FILES, Resolution

    start = time.perf_counter()
    folder = Path(folder)
    config = folder / "config.yaml"
    resuming = resume and config.is_file()
    existing = [name for name in (*CASE_FILES, "results") if (folder / name).exists()]
    if existing and not resuming and not force:
        raise click.ClickException(
            f"{folder} already holds {', '.join(existing)}; the demo would overwrite "
            f"them: give another folder, --resume an interrupted demo, or --force"
        )
    if resuming:
        click.echo(f"resuming the demo in {folder}")
    else:
        click.echo(f"making the demo scene and its guidance video in {folder}")
        make_demo(folder, QUICK if quick else Resolution())
    run_optimization(config, resume, echo=click.echo, note=note, bar=iteration_bar)
    results = folder / "results"
    simulate_scene(config, results / "params.json", results / "simulation", "none", echo=click.echo)
    render_simulation_4d(results / "simulation", views=views, progress=progress, echo=click.echo)
    report = write_report(results)  # again, now with the 4D renders
    click.echo(f"demo finished in {time.perf_counter() - start:.0f} s: open {report}")
