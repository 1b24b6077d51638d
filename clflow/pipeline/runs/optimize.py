"""``clflow optimize`` as a whole run: the config loaded, its folder held, the material
hypotheses, the optimisation, its results written as one step."""

from __future__ import annotations

import contextlib
import dataclasses
from pathlib import Path
from typing import Callable, ContextManager

from clflow.errors import InputError
from clflow.pipeline.runs.progress import _silent, format_row, iteration_lines
from clflow.pipeline.runs.records import input_files

#: what an interrupted optimisation leaves in its output folder for --resume: the main
#: checkpoint, the search starts' polishes, the material hypotheses' searches, the main grid
#: a budget chose (a new run times the device again)
RESUMABLE = ("checkpoint.json", "starts", "hypotheses", "budget.json")
#: an optimisation's results, written at its end as one step (all of them or none)
RESULTS = (
    "params.json",
    "metrics.json",
    "history.json",
    "search.json",
    "loss.png",
    "comparison*.mp4",
    "run.json",
    "index.html",
)
#: a run's own entries in its output folder (glob patterns), which a new run (no --resume)
#: removes as one step before it writes anything: the folder never mixes two runs
RUN_ENTRIES = (*RESUMABLE, "hypotheses.json", *RESULTS)
#: what an optimisation keeps in its folder across runs, each checked against the config
#: where it is read: the observed flow, the estimator's error, the material query's record
#: and the guidance frame it was asked about
CACHES = ("observed_flow*.npz", "estimator_error.npz", "material_query*.json", "guidance_frame0.png")


def run_optimization(
    config_path: str | Path,
    resume: bool = False,
    iterations: int | None = None,
    output: str | Path | None = None,
    overrides: tuple[str, ...] = (),
    max_substeps: int | None = None,
    force_video: bool = False,
    *,
    echo: Callable[[str], None] = _silent,
    note: Callable[[str], None] = _silent,
    bar: Callable[[int, int], ContextManager[Callable[[dict], None]]] | None = None,
    parallel: dict | None = None,
    resume_with: str | None = None,
) -> dict:
    """Load the config (``overrides``: ``KEY=VALUE``), generate its guidance video if it asks
    for one, choose among its material hypotheses, optimise (``bar(total, done)``: the
    iterations' progress, default :func:`iteration_lines`), write the results, run.json and
    the report; returns the metrics. ``resume`` continues from output/checkpoint.json.
    ``parallel``: the material hypotheses' searches and the search starts' polishes run as
    Ray tasks (clflow.parallel.map_on_ray's keywords: address, cpus_per_task, resources,
    device), with the serial path's results. ``resume_with``: the command an interruption
    says continues the run (default: the ``clflow optimize ... --resume`` that does; the
    demo's is ``clflow demo --resume``)."""
    from clflow.scene.config import load_config

    if parallel is not None:
        from clflow.parallel import require_ray

        require_ray("drop --parallel")
    cfg = load_config(config_path, overrides)
    with contextlib.ExitStack() as stack:
        search = cfg.optimize.search
        if parallel is not None and (cfg.optimize.materials or search is not None and search.starts > 1):
            from clflow.parallel import ray_session

            stack.enter_context(ray_session(parallel.get("address")))  # one Ray for all of the run's tasks
        again = resume_with or resume_command(
            config_path, output, overrides, iterations, max_substeps, force_video, parallel
        )
        return _optimize_config(
            cfg, again, resume, iterations, output, max_substeps, force_video, echo, note, bar, parallel
        )


def resume_command(config_path, output, overrides, iterations, max_substeps, force_video, parallel) -> str:
    """The command line that continues an interrupted ``clflow optimize`` with the options it
    was started with (shell-quoted)."""
    import shlex

    words = ["clflow", "optimize", str(config_path), "--resume"]
    words += ["-o", str(output)] if output is not None else []
    for item in overrides:
        words += ["--set", item]
    words += ["--iterations", str(iterations)] if iterations is not None else []
    words += ["--max-substeps", str(max_substeps)] if max_substeps is not None else []
    words += ["--force-video"] if force_video else []
    words += ["--parallel"] if parallel is not None else []
    return shlex.join(words)


def _optimize_config(
    cfg, again, resume, iterations, output, max_substeps, force_video, echo, note, bar, parallel
) -> dict:
    """run_optimization's work once its config is loaded (``again``: the command that resumes it)."""
    import torch

    from clflow.fileio import output_folder
    from clflow.limits import check_output
    from clflow.mpm.substep import check_device
    from clflow.runtime import get_device

    check_device(get_device(), torch.float32, differentiable=True)  # before any work
    if iterations is not None:
        cfg = dataclasses.replace(cfg, optimize=dataclasses.replace(cfg.optimize, iterations=iterations))
    if output is not None:
        cfg = dataclasses.replace(cfg, output=Path(output).resolve())
    check_output(cfg.output)
    created = not cfg.output.exists()
    with output_folder(cfg.output):  # this run's: other runs are refused, before any work
        return _optimize_held(cfg, again, resume, max_substeps, force_video, created, echo, note, bar, parallel)


def _optimize_held(cfg, again, resume, max_substeps, force_video, created, echo, note, bar, parallel) -> dict:
    """_optimize_config's work once this run holds the output folder (``created``: by this run)."""
    from clflow.fileio import check_output_folder, discard_written, remove_entries
    from clflow.pipeline.fit import resampled_guidance
    from clflow.pipeline.fit.state import check_resume

    if resume and not any((cfg.output / saved).exists() for saved in RESUMABLE):
        raise InputError(
            f"--resume: {cfg.output} holds no interrupted run to continue (no checkpoint.json); "
            f"run without --resume to start one"
        )
    if max_substeps is not None:
        cfg = dataclasses.replace(cfg, simulation=dataclasses.replace(cfg.simulation, max_substeps=max_substeps))
    generated = getattr(cfg, "generate", None) is not None  # video: {generate: ...}, made in the run
    for video in [cfg.video, *(view.video for view in cfg.more_views)]:
        if video is not None or not generated:  # none, unreadable, short or gapped: before the scene and kernels
            resampled_guidance(cfg, video, cfg.simulation.frames)
    query = any(o.material.type == "query" for o in cfg.objects)
    rewritten = query or cfg.optimize.materials or generated  # by the run's first steps
    if resume and not rewritten and (cfg.output / "checkpoint.json").exists():
        check_resume(cfg.output / "checkpoint.json", cfg)  # a changed --set or video: before the scene is loaded
    # what it removes (a new run: the earlier one), replaces at the end or keeps as a cache is clflow's
    check_output_folder(cfg.output, (*(RESULTS if resume else RUN_ENTRIES), *CACHES), input_files(cfg))
    if not resume:
        earlier = remove_entries(cfg.output, RUN_ENTRIES)  # as one step
        if earlier:
            note(f"a new run in {cfg.output}: removing the earlier run's {', '.join(earlier)}")
    try:
        return _optimize_prepared(cfg, again, resume, force_video, echo, note, bar, parallel)
    except BaseException:  # a first run that fails before it saved anything leaves no folder behind
        kept = (*RESUMABLE, "generated")  # what a rerun continues from, or an expensive generated video
        if created and not any((cfg.output / saved).exists() for saved in kept):
            discard_written(cfg.output)
        raise


def _chosen_material(cfg, again: str, resume: bool, force_video: bool, note, parallel):
    """optimize.material's hypotheses searched (serially or on Ray), the best chosen: its
    config, its start and the hypotheses' record (clflow.pipeline.hypotheses)."""
    from clflow.pipeline.hypotheses import choose_material

    search = cfg.optimize.search

    def searched(material: str, row: dict) -> None:
        note(f"{material}: search {row['iteration'] + 1}/{search.samples + search.refine}: {format_row(row)}")

    search_all = {}
    if parallel is not None:
        from clflow.pipeline.hypotheses import hypotheses_on_ray

        search_all = {"search_all": hypotheses_on_ray(**parallel)}
    try:
        cfg, start, hypotheses = choose_material(
            cfg, resume=resume, progress=searched, force_video=force_video, **search_all
        )
    except KeyboardInterrupt:
        raise KeyboardInterrupt(
            f"interrupted while searching the material hypotheses (each saves its samples "
            f"in {cfg.output / 'hypotheses'}); continue with `{again}`"
        ) from None
    note(
        f"material: {hypotheses['chosen']} fits best (best search loss: "
        + ", ".join(
            f"{m} {r['loss']:.4g}" if "loss" in r else f"{m} failed" for m, r in hypotheses["hypotheses"].items()
        )
        + ")"
    )
    return cfg, start, hypotheses


def _echo_results(opt, state, metrics: dict, report: Path, echo, note) -> None:
    """The optimised values, the errors against the ground truth, rollbacks, warnings and where the results are."""
    from clflow.pipeline.fit import parameter_unit

    cfg = opt.cfg
    final = opt.problem.values(state.z)
    units = {n: parameter_unit(cfg, n) for n in final}
    echo(
        "optimised: "
        + ", ".join(f"{n} = {v:.6g}" + ("" if units[n] == "1" else f" {units[n]}") for n, v in final.items())
    )
    if "relative_error" in metrics:
        echo(
            "relative error vs ground truth: "
            + ", ".join(f"{n} {100 * e:.2f}%" for n, e in metrics["relative_error"].items())
        )
    errors = metrics.get("velocity_error_m_s")  # m/s: a number, or one per OBJECT.velocity
    if errors is not None:
        for name, error in (errors if isinstance(errors, dict) else {"initial velocity": errors}).items():
            echo(f"{name} off by {error:.3g} m/s")
    if metrics.get("rollbacks"):
        note(f"{len(metrics['rollbacks'])} unstable or failed iterations were rolled back (metrics.json: rollbacks)")
    for warning in metrics.get("warnings", []):
        note(f"WARNING: {warning}; the result is likely wrong")
    echo(
        f"flow loss {metrics['flow_loss']:.4g}, end-point error {metrics['epe_px']:.3g} px, "
        f"{metrics['seconds_per_iteration']:.2f} s per iteration; results in {cfg.output} (open {report.name})"
    )


def _optimize_prepared(cfg, again, resume, force_video, echo, note, bar, parallel) -> dict:
    """_optimize_config's work once the output folder is checked and cleared of an earlier run."""
    from clflow.pipeline.fit import Optimization

    if getattr(cfg, "generate", None) is not None:  # video: {generate: ...}: the guidance video first
        from clflow.pipeline.generated_video import ensure_guidance_video

        cfg = ensure_guidance_video(
            cfg, progress=lambda step, total: note(f"generating the guidance video: step {step}/{total}")
        )
    start, hypotheses, search = None, None, cfg.optimize.search
    if cfg.optimize.materials:  # material hypotheses: search each, optimise the best
        cfg, start, hypotheses = _chosen_material(cfg, again, resume, force_video, note, parallel)
    opt = Optimization(
        cfg, hypotheses=hypotheses, force_video=force_video
    )  # loads the scene, runs the material query, computes the video's flow
    if parallel is not None:
        from clflow.pipeline.fit import starts_on_ray

        opt.map_starts = starts_on_ray(**parallel)
    total = opt.problem.total_iterations  # the velocity phase's (optimize.estimate_velocity) and the main phase's
    done = opt.load_state().iteration if resume and opt.checkpoint.exists() else 0
    with (bar or (lambda t, d: iteration_lines(t, d, note)))(total, done) as advance:

        def progress(row: dict) -> None:
            if row.get("phase") == "search":  # the global phase: one line per sample
                note(f"search {row['iteration'] + 1}/{search.samples + search.refine}: {format_row(row)}")
            else:
                advance(row)

        opt.progress = progress
        try:
            state = opt.run(resume=resume, start=start)
        except KeyboardInterrupt:  # (a new run cleared the earlier run's checkpoint before it began)
            if not opt.checkpoint.exists():
                raise KeyboardInterrupt("interrupted before the first iteration finished; nothing was saved") from None
            raise KeyboardInterrupt(
                f"interrupted after {opt.load_state().iteration} iterations (saved in {opt.checkpoint.path}); "
                f"continue with `{again}`"
            ) from None
    metrics = _write_results(opt, state, again, note)
    _echo_results(opt, state, metrics, cfg.output / "index.html", echo, note)
    return metrics


def write_results(opt, state) -> dict:
    """The final evaluation (grid check, identifiability) and every result of RESULTS
    (params.json, metrics.json, history, plot, comparison videos, run.json, index.html) of
    the optimisation ``opt`` ended in ``state``, into its output folder as one step: an
    interruption or failure leaves the folder as it was. The one writer of an optimisation's
    results, for ``clflow optimize``, ``eval sysid``'s cases and sweeps; returns the metrics."""
    from clflow.fileio import atomic_dir
    from clflow.pipeline.report import write_report, write_run_record

    output = opt.cfg.output
    with atomic_dir(output, replaces=RESULTS, inputs=input_files(opt.cfg)) as staged:
        metrics = opt.write_result_files(state, staged)
        write_run_record(opt.cfg, staged)
        write_report(output, staged)
    return metrics


def _write_results(opt, state, again: str, note) -> dict:
    """:func:`write_results`, an interruption answered with how to write them (``again``:
    the checkpoint holds every iteration)."""
    try:
        note("checking the result and writing it")
        return write_results(opt, state)
    except KeyboardInterrupt:
        raise KeyboardInterrupt(
            f"interrupted while checking and writing the results, none of which were written; the "
            f"{state.iteration} iterations are saved in {opt.checkpoint.path}: write them with `{again}`"
        ) from None


__all__ = ["CACHES", "RESULTS", "RESUMABLE", "RUN_ENTRIES", "resume_command", "run_optimization", "write_results"]
