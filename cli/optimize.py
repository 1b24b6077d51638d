"""``clflow optimize``: material parameters of a scene config from its guidance video."""

from __future__ import annotations

import sys

import click

from clflow_cli.main import Interrupted


def _format_row(row: dict | None) -> str:
    if not row:
        return ""
    params = " ".join(f"{name}={value:.4g}" for name, value in row["params"].items())
    loss = "failed" if row["loss"] is None else f"{row['loss']:.4g}"
    return f"loss {loss}  {params}  {row['seconds']:.1f} s/it"


def _modified(path) -> int | None:
    """``path``'s modification time in ns, None if it does not exist."""
    try:
        return path.stat().st_mtime_ns
    except FileNotFoundError:
        return None


def run_optimization(config_path: str, resume: bool, iterations: int | None, output: str | None,
                     overrides: tuple[str, ...] = (), max_substeps: int | None = None,
                     force_video: bool = False) -> dict:
    """Load the config (``overrides``: ``--set KEY=VALUE``), optimise with a progress bar,
    write the results; returns the metrics."""
    import dataclasses
    from pathlib import Path

    from clflow.limits import check_output
    from clflow.pipeline.optimize import Optimization, parameter_unit
    from clflow.scene.config import load_config

    cfg = load_config(config_path, overrides)
    if iterations is not None:
        cfg = dataclasses.replace(cfg, optimize=dataclasses.replace(cfg.optimize, iterations=iterations))
    if output is not None:
        cfg = dataclasses.replace(cfg, output=Path(output).resolve())
    check_output(cfg.output)
    if max_substeps is not None:
        cfg = dataclasses.replace(cfg, simulation=dataclasses.replace(cfg.simulation, max_substeps=max_substeps))
    if getattr(cfg, "generate", None) is not None:  # video: {generate: ...}: the guidance video first
        from clflow.pipeline.generated_video import ensure_guidance_video

        cfg = ensure_guidance_video(cfg, progress=lambda step, total: click.echo(
            f"generating the guidance video: step {step}/{total}", err=True))
    start, hypotheses, search = None, None, cfg.optimize.search
    if cfg.optimize.materials:  # material hypotheses: search each, optimise the best
        from clflow.pipeline.hypotheses import choose_material

        def searched(material: str, row: dict) -> None:
            click.echo(f"{material}: search {row['iteration'] + 1}/{search.samples}: {_format_row(row)}", err=True)

        try:
            cfg, start, hypotheses = choose_material(cfg, resume=resume, progress=searched, force_video=force_video)
        except KeyboardInterrupt:
            raise Interrupted(f"interrupted while searching the material hypotheses (each saves its samples in "
                              f"{cfg.output / 'hypotheses'}); continue with `clflow optimize {config_path} "
                              f"--resume`") from None
        click.echo(f"material: {hypotheses['chosen']} fits best (best search loss: " + ", ".join(
            f"{m} {r['loss']:.4g}" if "loss" in r else f"{m} failed" for m, r in hypotheses["hypotheses"].items())
            + ")", err=True)
    opt = Optimization(cfg, hypotheses=hypotheses, force_video=force_video)  # loads the scene, runs the material query, computes the video's flow
    total = opt.total_iterations  # the velocity phase's (optimize.estimate_velocity) and the main phase's
    with click.progressbar(length=total, label="optimising", show_pos=True,
                           item_show_func=_format_row, file=sys.stderr) as bar:
        def progress(row: dict) -> None:
            if row.get("phase") == "search":  # the global phase: one line per sample
                click.echo(f"search {row['iteration'] + 1}/{search.samples}: {_format_row(row)}", err=True)
            elif sys.stderr.isatty():
                bar.update(1, row)
            else:  # a log file or CI: one line per iteration instead of a redrawn bar
                click.echo(f"iteration {row['iteration'] + 1}/{total}: {_format_row(row)}", err=True)

        opt.progress = progress
        if resume and opt.checkpoint.exists():
            bar.update(opt.load_state().iteration)
        earlier_checkpoint = _modified(opt.checkpoint)
        try:
            state = opt.run(resume=resume, start=start)
        except KeyboardInterrupt:
            # without --resume, a checkpoint.json untouched since the start is an earlier run's
            if _modified(opt.checkpoint) is None or (not resume and _modified(opt.checkpoint) == earlier_checkpoint):
                raise Interrupted("interrupted before the first iteration finished; nothing was saved") from None
            raise Interrupted(
                f"interrupted after {opt.load_state().iteration} iterations (saved in {opt.checkpoint}); "
                f"continue with `clflow optimize {config_path} --resume`") from None
    metrics = opt.write_results(state)
    from clflow.pipeline.report import write_report, write_run_record

    write_run_record(opt.cfg, cfg.output)
    report = write_report(cfg.output)
    final = opt.values(state.z)
    click.echo("optimised: " + ", ".join(f"{n} = {v:.6g} {parameter_unit(opt.cfg, n)}" for n, v in final.items()))
    if "relative_error" in metrics:
        click.echo("relative error vs ground truth: " +
                   ", ".join(f"{n} {100 * e:.2f}%" for n, e in metrics["relative_error"].items()))
    if "velocity_error_m_s" in metrics:
        click.echo(f"initial velocity off by {metrics['velocity_error_m_s']:.3g} m/s")
    if metrics.get("rollbacks"):
        click.echo(f"{len(metrics['rollbacks'])} unstable or failed iterations were rolled back "
                   f"(metrics.json: rollbacks)", err=True)
    for warning in metrics.get("warnings", []):
        click.echo(f"WARNING: {warning}; the result is likely wrong", err=True)
    click.echo(f"flow loss {metrics['flow_loss']:.4g}, end-point error {metrics['epe_px']:.3g} px, "
               f"{metrics['seconds_per_iteration']:.2f} s per iteration; results in {cfg.output} (open {report.name})")
    return metrics


@click.command("optimize")
@click.argument("config", type=click.Path(dir_okay=False))
@click.option("--resume", is_flag=True, help="Continue from OUTPUT/checkpoint.json (after Ctrl-C or a kill).")
@click.option("--iterations", type=click.IntRange(min=1), default=None,
              help="Override optimize.iterations of the config.")
@click.option("--output", "-o", type=click.Path(file_okay=False), default=None,
              help="Results folder (default: the config's output).")
@click.option("--set", "overrides", multiple=True, metavar="KEY.SUB=VALUE",
              help="Set a config key, the value read as YAML, e.g. --set material.parameters.youngs_modulus=2e4 "
                   "(repeatable; checked like the file). --resume needs the same --set as the run it continues.")
@click.option("--max-substeps", type=click.IntRange(min=1), default=None,
              help="Refuse a run needing more substeps per frame (default: simulation.max_substeps, 2000).")
@click.option("--force-video", is_flag=True,
              help="Optimise even when the guidance checks fail (no motion, noise, a camera that does not fit); "
                   "the failures are warned about and recorded in metrics.json.")
def optimize(config, resume, iterations, output, overrides, max_substeps, force_video):
    """Optimise the material parameters of CONFIG (YAML/JSON scene config) so that the
    simulated optical flow matches the guidance video's.

    Writes into the output folder: params.json (final parameters, SI), metrics.json,
    history.json, loss.png, comparison.mp4 and checkpoint.json (after every iteration)."""
    run_optimization(config, resume, iterations, output, overrides, max_substeps, force_video)
