"""``clflow eval sysid``: the nine-case system-identification benchmark (datasets_tools/sysid.py)."""

from __future__ import annotations

import sys

import click

from clflow_cli.main import Interrupted
from clflow_cli.options import InputFile, LazyHelpOption, budget_option, count_option, out_option
from clflow_cli.sweep import parse_resources, with_ray_options


def _case_help() -> str:
    from clflow_datasets.sysid_cases import CASES, QUICK_CASES

    return (
        f"Run only this case (repeatable): {', '.join(CASES)}. Default: all {len(CASES)}, or the "
        f"{len(QUICK_CASES)} of --quick ({', '.join(QUICK_CASES)})."
    )


def _catalogue(case_file: str | None, case_set: str, quick: bool) -> tuple[dict, list[str]]:
    """(name -> case, the names run by default) of --cases FILE, --set and --quick."""
    from pathlib import Path

    from clflow_datasets.sysid_cases import CASES, EXTRA_CASES_FILE, QUICK_CASES, load_cases

    if case_file and case_set != "paper":
        raise click.UsageError("--cases and --set extra both choose the cases: give one")
    own = case_file or (EXTRA_CASES_FILE if case_set == "extra" else None)
    if own:
        catalogue = load_cases(Path(own))
        return catalogue, list(catalogue)
    return CASES, list(QUICK_CASES if quick else CASES)


def _degradation(ctx, param, spec: str | None):
    """--degrade's SPEC as a clflow_datasets.degradation.Degradation (the default: none)."""
    from clflow_datasets.degradation import Degradation

    try:
        return Degradation() if spec is None else Degradation.parse(spec)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None


@click.command("sysid")
@out_option("output", "Results folder: sysid.json, sysid.md and cases/NAME/ (scene, guidance, results).",
            required=True)  # fmt: skip
@click.option("--case", "cases", multiple=True, metavar="NAME", cls=LazyHelpOption, help_fn=lambda: _case_help())
@click.option("--cases", "case_file", type=InputFile(), default=None, metavar="FILE",
              help="Your own cases (YAML or JSON: name -> shape, size, lift, spread, material, density, truth, guess, "
                   "optimize, velocity; docs/pipeline.md) instead of the built-in nine; --case picks among them.")  # fmt: skip
@click.option("--set", "case_set", type=click.Choice(["paper", "extra"]), default="paper", show_default=True,
              help="paper: PAC-NeRF's nine; extra: clflow's own nine (every material type, guesses above and "
                   "below the truth, one thrown), so the ranges' coverage is not tuned on the paper's.")  # fmt: skip
@click.option("--quick", is_flag=True,
              help="A small grid and image, and of the paper's set three cases (elastic torus, plasticine playdoh, "
                   "Newtonian droplet): minutes, for CI.")  # fmt: skip
@click.option("--iterations", type=click.IntRange(min=1), default=None, help="Override the iterations per case.")
@count_option('--truth-scale', default=2, help="Grid and image refinement of the ground truth (1 reproduces the optimiser's own forward: "
                   "an inverse crime, for diagnosis only).")  # fmt: skip
@click.option("--truth-transfer", type=click.Choice(["flip", "apic"]), default="flip", show_default=True,
              help="The ground truth's particle-grid transfer: flip, the optimiser's own blend (FLIP 0.99), or apic, "
                   "a model mismatch the optimiser does not share (nature is neither).")  # fmt: skip
@click.option("--noise", type=click.FloatRange(min=0.0), default=0.0, show_default=True,
              help="Sensor noise added to the guidance frames, 8-bit grey levels (standard deviation).")  # fmt: skip
@click.option("--codec", type=click.Choice([".mp4", ".webm", ".avi"]), default=None,
              help="Read the guidance through this lossy video encoding instead of lossless PNG frames.")  # fmt: skip
@click.option("--degrade", "degradation", callback=_degradation, default=None, metavar="SPEC",
              help="The guidance's artefacts, as a generated or hand-held video has them: a preset (realistic) "
                   "and/or name=value items, comma-separated: flicker (exposure gain's standard deviation, "
                   "relative), offset (exposure offset, grey levels), shake (px a frame), roll (deg a frame), "
                   "blur (px), jpeg (quality), speed (playback speed, e.g. 0.8). Drawn from --seed.")  # fmt: skip
@click.option("--fit-time-scale", is_flag=True,
              help="Fit the video's clock too (optimize.parameters' time_scale; its truth --degrade's speed) and "
                   "report its error apart from the material's.")  # fmt: skip
@click.option("--prior", type=click.Choice(["none", "knowledge"]), default="none", show_default=True,
              help="optimize.prior of every case: knowledge, the material knowledge base decides what the video "
                   "leaves unresolved or implausible, within the video's ranges (docs/pipeline.md).")  # fmt: skip
@click.option("--seed", type=int, default=0, show_default=True,
              help="Seed of the scene's texture grain, the noise and the artefacts.")  # fmt: skip
@click.option("--views", type=click.IntRange(1, 4), default=1, show_default=True,
              help="Guidance views of each case (the first, then cameras turned 90, -90 and 180 deg about the "
                   "vertical); the loss is the mean over views.")  # fmt: skip
@budget_option("The cases' optimisation time (600, 10min, 1.5h), shared equally: each case's main grid is the finest "
               "whose predicted run fits its share, timed on this device, and at least 4/3 coarser than the ground "
               "truth's (raise --truth-scale for finer). The truths' making is not counted.")  # fmt: skip
@click.option("--force", is_flag=True, help="Replace sysid results of other settings in the output folder.")
@click.option("--parallel", is_flag=True,
              help="Run the cases as Ray tasks (clflow[sweep]; a local Ray on this machine's cores, or --address); "
                   "the results are the serial path's.")  # fmt: skip
@with_ray_options
@click.pass_context
def sysid(
    ctx,
    output,
    cases,
    case_file,
    case_set,
    quick,
    iterations,
    truth_scale,
    truth_transfer,
    noise,
    codec,
    degradation,
    fit_time_scale,
    prior,
    seed,
    views,
    budget,
    force,
    parallel,
    address,
    cpus_per_task,
    resources,
):
    """Identify the material parameters of PAC-NeRF's nine synthetic cases (re-made with
    clflow's geometry; guidance from a finer simulation and rendering than the optimiser's)
    from the published initial guesses, and print a table like Table 3 of the PhysFlow paper.

    A rerun with the same settings skips finished cases and resumes an interrupted one."""
    from pathlib import Path

    from clflow_datasets.sysid import Settings, evaluate, markdown

    catalogue, default_names = _catalogue(case_file, case_set, quick)
    names = list(dict.fromkeys(cases)) or default_names
    given = dict(truth_scale=truth_scale, noise=noise, codec=codec, degradation=degradation, seed=seed, views=views)
    budget_each = None if budget is None else budget / len(names)
    settings = Settings.at(
        quick,
        iterations,
        **given,
        truth_transfer=truth_transfer,
        case_budget=budget_each,
        fit_time_scale=fit_time_scale,
        prior=prior,
    )

    def progress(name: str, row: dict) -> None:
        from clflow.pipeline.runs import format_row

        step = "search sample" if row.get("phase") == "search" else "iteration"
        click.echo(f"{name}: {step} {row['iteration'] + 1}: {format_row(row)}", err=True)

    run_cases = None
    if parallel:
        from clflow.sweep import sysid_on_ray

        run_cases = sysid_on_ray(
            address=address,
            cpus_per_task=cpus_per_task,
            resources=parse_resources(resources),
            device=ctx.obj.device_spec if ctx.obj else None,
            echo=lambda line: click.echo(line, err=True),
        )
    elif address or resources:
        raise click.UsageError("--address and --resources go with --parallel")
    out = Path(output)
    try:
        summary = evaluate(names, out, settings, force=force, progress=progress, run_cases=run_cases, cases=catalogue)
    except KeyboardInterrupt:
        raise Interrupted(
            f"interrupted; finished cases are kept in {out / 'sysid.json'}; run the same command again to resume"
        ) from None
    click.echo(markdown(summary), nl=False)
    failed = [n for n, r in summary["cases"].items() if r.get("status") != "ok"]
    if failed:
        click.echo(f"failed: {', '.join(failed)} (see {out / 'sysid.json'})", err=True)
        sys.exit(1)
