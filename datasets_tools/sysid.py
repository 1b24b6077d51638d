"""The system-identification benchmark behind ``clflow eval sysid``.

PAC-NeRF's nine synthetic cases (materials, ground truths and initial guesses from its
configs), re-made with clflow's own geometry: a textured shape dropped onto a sticky floor,
seen by one guidance camera. Parameters are in clflow's SI conventions; for the Newtonian
cases that is viscosity = mu_PAC / 2 and bulk modulus = 7 kappa_PAC (docs/pipeline.md),
which leaves every relative error unchanged.

Every case's guidance video comes from a finer simulation and rendering than any the
optimiser runs (``truth_scale``: the grid and image refined 2x, its own particle sampling and
substep, area-downsampled frames; optional noise, video compression and the artefacts of a
generated or hand-held video: clflow_datasets.degradation), so the optimiser
cannot reproduce it exactly. The optimiser searches on the base grid and runs its main phase
on one ``Resolution.main_grid_scale`` (1.5) times finer, still 1.33x coarser than the
truth's. Both the truth and the optimiser blend FLIP into APIC's transfer
(``Resolution.flip`` 0.99) so that neither one's damping depends on its substep count.
``floor_epe_px`` in a result is the flow error of the ground truth parameters at
the optimised resolution: the model error no optimiser can remove.

    results = evaluate(["torus"], Path("out"), Settings(resolution=QUICK))   # writes out/sysid.json, .md

The cases (the nine of pacnerf_cases.yaml and case files) are :mod:`clflow_datasets.sysid_cases`; the
tables of the results, Markdown beside the published ones, :mod:`clflow_datasets.sysid_report`.
"""

from __future__ import annotations

import glob
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

from clflow.fileio.reading import parse_json
from clflow_datasets import per_class
from clflow_datasets.degradation import Degradation
from clflow_datasets.scene_cases import SceneCase
from clflow_datasets.synthetic import GENERATOR_VERSION, Resolution, SyntheticCase, make_case
from clflow_datasets.sysid_cases import CASES, check_case
from clflow_datasets.sysid_report import holds, markdown

log = logging.getLogger(__name__)

# PAC-NeRF's 14 frames at 24 fps; Levenberg-Marquardt iterations (each 1 + parameters forward
# runs) after the search, enough for the slowest case to stop by progress on the main grid;
# QUICK is small enough for CI. flip 0.99 for truth and optimiser: APIC's damping grows with
# the substeps, which the stiffness sets, so under APIC a fluid's bulk modulus would move the
# loss mostly through the substep count (docs/mpm.md, "Transfers and time step").
FULL = Resolution(
    object_detail=12, floor_side=32, image=160, grid=24, frames=14, iterations=16, main_grid_scale=1.5, flip=0.99
)
QUICK = Resolution(
    object_detail=8, floor_side=20, image=96, grid=24, frames=10, iterations=8, main_grid_scale=1.5, flip=0.99
)

#: --truth-transfer: the ground truth's PIC/FLIP blend (None: the optimiser's own)
TRUTH_FLIP = {"flip": None, "apic": 0.0}


@dataclass(frozen=True)
class Settings:
    """What a benchmark run depends on besides its cases (a rerun resumes only with equal settings)."""

    resolution: Resolution = FULL
    truth_scale: int = 2  # ground truth's grid and image refinement
    noise: float = 0.0  # sensor noise, 8-bit grey levels
    codec: str | None = None  # video suffix of a lossy guidance video, e.g. ".mp4"
    degradation: Degradation = Degradation()  # what a generated or hand-held video adds (flicker, shake, ...)
    seed: int = 0
    views: int = 1  # guidance views (clflow_datasets.synthetic.VIEW_AZIMUTHS_DEG)
    truth_transfer: str = "flip"  # the truth's transfer: "flip" (the optimiser's blend) or "apic" (a mismatch)
    # s of each case's optimisation (optimize.budget: the main grid from the device's speed; None: the resolution's)
    case_budget: float | None = None
    # the video's clock fitted too (optimize.parameters' time_scale; its truth the degradation's speed)
    fit_time_scale: bool = False
    # optimize.prior of every case: "knowledge", the material knowledge base decides what the
    # video leaves unresolved or implausible (within the video's ranges; clflow.pipeline.fit.prior)
    prior: str = "none"

    @classmethod
    def at(cls, quick: bool, iterations: int | None = None, **fields) -> Settings:
        """Settings at the QUICK or FULL resolution (``iterations``: its Levenberg-Marquardt
        iterations instead of the resolution's), the other ``fields`` as given."""
        resolution = QUICK if quick else FULL
        if iterations is not None:
            resolution = replace(resolution, iterations=iterations)
        return cls(resolution=resolution, **fields)

    def case_options(self) -> dict:
        """clflow_datasets.synthetic.make_case's keywords of these settings."""
        made = {key: getattr(self, key) for key in ("truth_scale", "noise", "codec", "views", "degradation")}
        return {**made, "truth_flip": TRUTH_FLIP[self.truth_transfer]}


#: the ground truth's grid stays this many times finer (in cells) than any main grid a budget chooses
TRUTH_MARGIN = 4 / 3


def with_budget(cfg, seconds: float, truth_grid: int):
    """``cfg`` with ``optimize.budget`` of ``seconds``, its main grid at most 1 / TRUTH_MARGIN
    of the truth's ``truth_grid`` nodes (in cells): a budget refines the model, never to the
    truth's own grid."""
    from clflow.scene.config import BudgetSettings

    finest = math.floor((truth_grid - 1) / TRUTH_MARGIN) + 1
    return replace(cfg, optimize=replace(cfg.optimize, budget=BudgetSettings(seconds, finest)))


def run_case(
    name: str,
    folder: Path,
    settings: Settings,
    *,
    case: SyntheticCase | None = None,
    progress: Callable[[dict], None] | None = None,
) -> dict:
    """Make case ``name`` (``case``; default: the built-in one) in ``folder`` unless made, optimise
    it (resuming an interrupted optimisation) and return its result record (module docstring)."""
    import numpy as np

    from clflow.errors import ClflowError
    from clflow.fileio import atomic_write_text, remove_entries
    from clflow.pipeline.fit import Optimization
    from clflow.pipeline.fit.budget import BudgetTooSmall
    from clflow.pipeline.runs import write_results
    from clflow.scene.config import TIME_SCALE, load_config

    case = case or CASES[name]
    check_case(name, case)
    start = time.perf_counter()
    made = folder / "case.json"
    definition = case_definition(case)
    if made.exists() and json.loads(made.read_text()).get("definition") != definition:
        remove_entries(folder.parent, (glob.escape(folder.name),))  # made from another definition: make it anew
    if not made.exists():  # an interrupted generation leaves no case.json: make it again
        make_case(folder, case, settings.resolution, settings.seed, **settings.case_options())
        record = json.loads(made.read_text())
        record["definition"] = definition
        atomic_write_text(made, json.dumps(record, indent=2))
    generation = json.loads(made.read_text())
    generated = time.perf_counter()
    cfg = load_config(folder / "config.yaml")
    truth, overrides = dict(case.truth), (f"optimize.prior={settings.prior}",)
    if settings.fit_time_scale:
        truth[TIME_SCALE.name] = settings.degradation.speed
        fitted = json.dumps([*cfg.optimize.parameters, TIME_SCALE.name])
        overrides += (f"optimize.parameters={fitted}", f"evaluation.ground_truth.time_scale={truth[TIME_SCALE.name]!r}")
    cfg = load_config(folder / "config.yaml", overrides)
    if settings.case_budget is not None:
        cfg = with_budget(cfg, settings.case_budget, generation["truth_grid_resolution"])
    record = {"case": name, "material": case.material, "generation": generation, "status": "ok"}
    try:
        opt = Optimization(cfg, progress=progress)
        state = opt.run(resume=True)
        metrics = write_results(opt, state)
        record.update(grid=metrics["grid"], optimise_seconds=metrics["seconds"], budget=metrics.get("budget"))
        truth_z = {n: float(opt.problem.params[n].encode(truth[n])) for n in opt.problem.params}
        # at the truth's own stable time step: MPM's answer depends on dt (docs/history,
        # "MPM depends on the substep"), and the final run's may be finer
        floor = opt.objective.evaluate({**state.z, **truth_z}, opt.problem.frames, with_grad=False)
        floor_epe = opt.objective.endpoint_error(floor.flows, floor.more_flows)
        # both losses against the estimator's error measured at their own parameters (the final
        # point's targets hold its own): comparable, the truth's the floor of the optimiser's loss
        truth_loss = opt.objective.self_consistent_loss(floor, opt.problem.frames, opt.objective.final_shifts)
    except BudgetTooSmall:  # the settings', not the case's: every case would fail alike
        raise
    except ClflowError as exc:
        record.update(status=f"failed: {exc}", seconds=time.perf_counter() - start)
        return record
    # the result's values (the prior's where it moved the fit), as params.json gives them
    found = json.loads((cfg.output / "params.json").read_text())["optimized"]
    ranges = metrics["identifiability"]["ranges"]
    record["parameters"] = parameter_records(case, found, ranges)
    decisions = metrics.get("prior", {}).get("parameters", {})  # optimize.prior: who decided each
    if decisions:
        alone = parameter_records(case, {**found, **{n: d["video_fit"] for n, d in decisions.items()}}, ranges)
        for n, decision in decisions.items():
            if n in record["parameters"]:
                record["parameters"][n].update(
                    decided_by=decision["decided_by"], video_fit=decision["video_fit"], video_re=alone[n]["re"]
                )
    if settings.fit_time_scale:  # the clock's: apart from the material's mean RE
        speed = truth[TIME_SCALE.name]
        record["time_scale"] = {
            "found": found[TIME_SCALE.name],
            "truth": speed,
            "re": abs(found[TIME_SCALE.name] - speed) / speed,
            "range": [ranges[TIME_SCALE.name]["low"], ranges[TIME_SCALE.name]["high"]],
            "holds_truth": holds(ranges[TIME_SCALE.name], speed),
        }
    record.update(
        mean_re=float(np.mean([p["re"] for p in record["parameters"].values()])),
        epe_px=metrics["epe_px"],
        floor_epe_px=floor_epe,
        final_loss=metrics["flow_loss"],
        truth_loss=truth_loss,
        unexplained=metrics["unexplained_motion"]["fraction"],  # the share of the observed motion left unexplained
        identifiability=metrics["identifiability"],
        stabilisation=metrics.get("stabilisation"),  # per view: what flow.stabilise removed
        iterations=len(state.history),
        substeps=state.substeps,
        generation_seconds=generated - start,
        seconds=time.perf_counter() - start,
    )
    return record


def parameter_records(case: SyntheticCase, found: dict[str, float], ranges: dict[str, dict]) -> dict[str, dict]:
    """Per optimised parameter: found, truth, guess, RE, its range [low, high] (None: open)
    and whether that holds the truth; a case of several objects' (OBJECT.PARAM) also its
    object's material and the parameter's own name (the per-class table's)."""
    records = {
        n: {
            "found": found[n],
            "truth": case.truth[n],
            "guess": case.guess.get(n, case.truth[n]),
            "re": abs(found[n] - case.truth[n]) / abs(case.truth[n]),
            "range": [ranges[n]["low"], ranges[n]["high"]],
            "holds_truth": holds(ranges[n], case.truth[n]),
        }
        for n in case.optimize
    }
    if isinstance(case, SceneCase):
        for n, record in records.items():
            obj, param = case.object_of(n)
            record.update(object=obj.name, material=obj.material, parameter=param)
    return records


def case_definition(case: SyntheticCase) -> dict:
    """A case's definition as JSON data, with the generator's version (a finished result
    counts only for an equal one)."""
    return json.loads(json.dumps({**asdict(case), "generator": GENERATOR_VERSION}))


def settings_record(settings: Settings) -> dict:
    return json.loads(json.dumps(asdict(settings)))


def _earlier_summary(out: Path, settings: Settings, force: bool) -> dict:
    """The summary to continue in ``out``: the earlier one when its settings are these, else a
    new one; results of other settings, or other files, are refused unless ``force`` (which
    clears the earlier cases)."""
    from clflow.errors import InputError
    from clflow.fileio import is_bookkeeping

    summary_path = out / "sysid.json"
    wanted = settings_record(settings)
    summary = {"settings": wanted, "cases": {}}
    if summary_path.exists():
        try:
            previous = parse_json(summary_path.read_text())
            earlier = previous.get("settings") if isinstance(previous, dict) else None
            if isinstance(earlier, dict):  # a setting added since those results were made takes its default there
                earlier = {**settings_record(Settings()), **earlier}
            same = earlier == wanted
        except (OSError, ValueError) as exc:
            raise InputError(
                f"{summary_path} is not a clflow sysid result ({exc}); use --force to start over"
            ) from None
        if same:
            summary = previous
        elif not force:
            raise InputError(
                f"{out} holds sysid results of other settings ({_difference(earlier, wanted)}); "
                f"use another -o folder, or --force to replace them"
            )
    elif out.exists() and any(not is_bookkeeping(p.name) for p in out.iterdir()) and not force:
        raise InputError(f"{out} exists and holds other files; use an empty or new -o folder, or --force")
    if force and summary["cases"] == {}:
        from clflow.fileio import remove_entries

        remove_entries(out, ("cases",))  # what clflow wrote there, as one step
    return summary


def evaluate(
    names: list[str],
    out: Path,
    settings: Settings,
    *,
    force: bool = False,
    progress: Callable[[str, dict], None] | None = None,
    run_cases: Callable | None = None,
    cases: dict[str, SyntheticCase] | None = None,
) -> dict:
    """Run the cases ``names`` into ``out`` (``out/cases/NAME``), writing ``sysid.json`` and
    ``sysid.md`` after each case. A rerun with the same settings skips finished cases and
    resumes an interrupted one; other results in ``out`` are refused unless ``force``.
    ``run_cases(names, out, settings, done, cases)`` runs the cases elsewhere
    (``clflow.sweep``: Ray), calling ``done(name, record)`` as each finishes; the summary is
    the serial path's. ``cases``: name -> case (default: the built-in CASES; load_cases)."""
    from clflow.errors import InputError
    from clflow.fileio import output_folder

    cases = cases or CASES
    unknown = [n for n in names if n not in cases]
    if unknown:
        raise InputError(f"unknown case(s) {', '.join(unknown)}; the cases are {', '.join(cases)}")
    for n in names:
        try:
            check_case(n, cases[n])
        except ValueError as exc:
            raise InputError(str(exc)) from None
    with output_folder(out):  # this benchmark's: other runs are refused
        return _evaluate(names, out, settings, force, progress, run_cases, cases)


def _evaluate(names, out: Path, settings: Settings, force: bool, progress, run_cases, cases) -> dict:
    """evaluate's work once ``out`` is held."""
    from clflow.fileio import atomic_write_text

    summary_path = out / "sysid.json"
    summary = _earlier_summary(out, settings, force)
    out.mkdir(parents=True, exist_ok=True)
    from clflow.environment import environment

    summary["environment"] = environment()
    atomic_write_text(summary_path, json.dumps(summary, indent=2))  # settings first: an interrupted run resumes
    todo = []
    for name in names:
        done = summary["cases"].get(name, {})
        if done.get("status") == "ok" and done["generation"].get("definition") == case_definition(cases[name]):
            log.info("%s: done earlier, skipped", name)
            continue
        todo.append(name)
    order = list(summary["cases"]) + [n for n in todo if n not in summary["cases"]]  # the serial path's

    def finished(name: str, record: dict) -> None:
        summary["cases"][name] = record
        summary["cases"] = {n: summary["cases"][n] for n in order if n in summary["cases"]}
        summary["per_class"] = per_class.per_class(summary["cases"])
        summary["bounded_ranges"] = per_class.bounded_ranges(summary["cases"])
        atomic_write_text(summary_path, json.dumps(summary, indent=2))
        atomic_write_text(out / "sysid.md", markdown(summary))

    if run_cases is not None:
        run_cases(todo, out, settings, finished, cases)
        return summary
    for name in todo:
        finished(
            name,
            run_case(
                name,
                out / "cases" / name,
                settings,
                case=cases[name],
                progress=(lambda row, n=name: progress(n, row)) if progress else None,
            ),
        )
    return summary


def _difference(old: dict | None, new: dict) -> str:
    if not isinstance(old, dict):
        return "no settings recorded"
    keys = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
    return ", ".join(f"{k}: {old.get(k)} -> {new.get(k)}" for k in keys)


__all__ = [
    "FULL",
    "QUICK",
    "Settings",
    "TRUTH_MARGIN",
    "evaluate",
    "run_case",
    "with_budget",
]
