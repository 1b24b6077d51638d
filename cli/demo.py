"""``clflow demo``: the bundled end-to-end example, made from scratch and run."""

from __future__ import annotations

import click


@click.command("demo")
@click.argument("folder", type=click.Path(file_okay=False), default="clflow-demo")
@click.option("--quick", is_flag=True, help="A smaller scene (for a first look or CI): about a minute.")
@click.option("--scene", type=click.Choice(["jelly", "pair"]), default="jelly", show_default=True,
              help="jelly: one cube pushed sideways; pair: two cubes of two stiffnesses dropped side by side, "
              "each one's E identified from the one video.")  # fmt: skip
@click.option("--resume", is_flag=True, help="Continue an interrupted optimisation of an existing demo folder.")
@click.option("--views", type=click.IntRange(min=0), default=2, show_default=True,
              help="Fixed novel viewpoints of the 4D render.")  # fmt: skip
@click.option("--force", is_flag=True, help="Replace an earlier demo's files (config.yaml, results/, ...) in FOLDER "
              "(files clflow did not write are never replaced).")  # fmt: skip
def demo(folder, quick, scene, resume, views, force):
    """Make the demo case in FOLDER (a jelly cube pushed sideways on a floor; its guidance
    video rendered from a ground-truth simulation, E = 20 kPa), then recover Young's
    modulus from a 10x too low guess (`clflow optimize`), simulate with the result
    (`clflow simulate`) and render it in 4D (`clflow render4d`). `--scene pair`: two cubes
    (E = 20 and 100 kPa) dropped side by side, both moduli recovered from one video."""
    import shlex
    import time
    from pathlib import Path

    from clflow.fileio import output_folder
    from clflow.pipeline.report import write_report
    from clflow.pipeline.runs import render_simulation_4d, run_optimization, simulate_scene
    from clflow_cli.progress import iteration_bar, note, progress
    from clflow_datasets import demo as demos
    from clflow_datasets.synthetic import CASE_FILES, Resolution

    start = time.perf_counter()
    folder = Path(folder)
    config = folder / "config.yaml"
    with output_folder(folder):  # this demo's: other runs are refused
        resuming = resume and config.is_file()
        existing = [name for name in (*CASE_FILES, "results") if (folder / name).exists()]
        options = [*(["--quick"] if quick else []), *(["--scene", scene] if scene != "jelly" else [])]
        again = shlex.join(["clflow", "demo", "--resume", *options, str(folder)])
        again += f" --views {views}" if views != 2 else ""
        if resume and not existing:
            raise click.ClickException(
                f"{folder} holds no demo to resume; make one with `clflow demo {shlex.quote(str(folder))}`"
            )
        if existing and not resume and not force:
            raise click.ClickException(
                f"{folder} already holds {', '.join(existing)}; the demo would overwrite "
                f"them: give another folder, --resume an interrupted demo, or --force"
            )
        if resuming:
            click.echo(f"resuming the demo in {folder}")
        else:  # a new demo, or one interrupted while its scene was made: (again) from scratch
            click.echo(f"making the demo scene and its guidance video in {folder}")
            try:
                make = demos.make_pair_demo if scene == "pair" else demos.make_demo
                make(folder, demos.QUICK if quick else Resolution())
            except KeyboardInterrupt:
                raise KeyboardInterrupt(
                    f"interrupted while making the demo's scene; make it again with `{again}`"
                ) from None
        results = folder / "results"
        checkpointed = resuming and (results / "checkpoint.json").is_file()  # else the optimisation had not begun
        run_optimization(config, checkpointed, echo=click.echo, note=note, bar=iteration_bar, resume_with=again)
        simulate_scene(config, results / "params.json", results / "simulation", "none", echo=click.echo)
        render_simulation_4d(results / "simulation", views=views, progress=progress, echo=click.echo)
        report = write_report(results)  # again, now with the 4D renders
        click.echo(f"demo finished in {time.perf_counter() - start:.0f} s: open {report}")
