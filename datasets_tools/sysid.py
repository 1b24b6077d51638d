"""The system-identification benchmark behind ``clflow eval sysid``.

PAC-NeRF's nine synthetic cases (materials, ground truths and initial guesses from its
configs), re-made with clflow's own geometry: a textured shape dropped onto a sticky floor,
seen by one guidance camera. Parameters are in clflow's SI conventions; for the Newtonian
cases that is viscosity = mu_PAC / 2 and bulk modulus = 7 kappa_PAC (docs/pipeline.md),
which leaves every relative error unchanged.

Every case's guidance video comes from a finer simulation and rendering than any the
optimiser runs (``truth_scale``: the grid and image refined 2x, its own particle sampling and
substep, area-downsampled frames; optional noise and video compression), so the optimiser
cannot reproduce it exactly. The optimiser searches on the base grid and runs its main phase
on one ``Resolution.main_grid_scale`` (1.5) times finer, still 1.33x coarser than the
truth's. Both the truth and the optimiser blend FLIP into APIC's transfer
(``Resolution.flip`` 0.99) so that neither one's damping depends on its substep count.
``floor_epe_px`` in a result is the flow error of the ground truth parameters at
the optimised resolution: the model error no optimiser can remove.

    results = evaluate(["torus"], Path("out"), QUICK, Settings())   # writes out/sysid.json, .md
"""

from __future__ import annotations

import glob
import json
import logging
import math
import statistics
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

from clflow.fileio.reading import parse_json
from clflow_datasets import per_class
from clflow_datasets.scene_cases import CaseObject, SceneCase, make_scene_case
from clflow_datasets.synthetic import GENERATOR_VERSION, Resolution, SyntheticCase, make_case

log = logging.getLogger(__name__)

# name -> case; shapes are clflow's own (cube, sphere, torus), sizes in metres, truths SI.
# Sizes make each case observable at 24 fps: the truth's slowest elastic period, about 4
# size / shear wave speed, spans 2-5 frames (a 0.2 m torus with E = 1e6 Pa rings at 6 ms,
# invisible between frames 42 ms apart); each shape falls about 0.3 of its size.
# a table, one case a row: kept as written
# fmt: off
CASES: dict[str, SyntheticCase] = {
    "droplet": SyntheticCase(shape="sphere", size=0.3, lift=0.1, spread=1.75, material="newtonian",
                             truth={"viscosity": 100.0, "bulk_modulus": 7.0e5},
                             guess={"viscosity": 0.5, "bulk_modulus": 7.0e3},
                             optimize=("viscosity", "bulk_modulus")),
    "letter": SyntheticCase(shape="cube", size=0.3, lift=0.1, spread=1.75, material="newtonian",
                            truth={"viscosity": 50.0, "bulk_modulus": 7.0e5},
                            guess={"viscosity": 0.5, "bulk_modulus": 7.0e6},
                            optimize=("viscosity", "bulk_modulus")),
    "cream": SyntheticCase(shape="sphere", size=0.4, lift=0.12, spread=1.25, material="non_newtonian",
                           truth={"shear_modulus": 1.0e4, "bulk_modulus": 1.0e6, "yield_stress": 3.0e3, "viscosity": 10.0},
                           guess={"shear_modulus": 100.0, "bulk_modulus": 1.0e4, "yield_stress": 10.0, "viscosity": 1.0},
                           optimize=("shear_modulus", "bulk_modulus", "yield_stress", "viscosity")),
    "toothpaste": SyntheticCase(shape="torus", size=0.4, lift=0.12, spread=1.25, material="non_newtonian",
                                truth={"shear_modulus": 5.0e3, "bulk_modulus": 1.0e5, "yield_stress": 200.0,
                                       "viscosity": 10.0},
                                guess={"shear_modulus": 100.0, "bulk_modulus": 1.0e4, "yield_stress": 10.0,
                                       "viscosity": 0.1},
                                optimize=("shear_modulus", "bulk_modulus", "yield_stress", "viscosity")),
    "torus": SyntheticCase(shape="torus", size=1.0, lift=0.3, spread=0.75, material="elastic",
                           truth={"youngs_modulus": 1.0e6, "poissons_ratio": 0.3},
                           guess={"youngs_modulus": 1.0e5, "poissons_ratio": 0.1},
                           optimize=("youngs_modulus", "poissons_ratio")),
    "bird": SyntheticCase(shape="sphere", size=0.6, lift=0.2, spread=0.75, material="elastic",
                          truth={"youngs_modulus": 3.0e5, "poissons_ratio": 0.3},
                          guess={"youngs_modulus": 1.0e3, "poissons_ratio": 0.1},
                          optimize=("youngs_modulus", "poissons_ratio")),
    "playdoh": SyntheticCase(shape="cube", size=1.0, lift=0.3, spread=0.75, material="plasticine",
                             truth={"youngs_modulus": 2.0e6, "poissons_ratio": 0.3, "yield_stress": 1.54e4},
                             guess={"youngs_modulus": 1.0e5, "poissons_ratio": 0.4, "yield_stress": 1.0e3},
                             optimize=("youngs_modulus", "poissons_ratio", "yield_stress")),
    "cat": SyntheticCase(shape="sphere", size=0.8, lift=0.25, spread=0.75, material="plasticine",
                         truth={"youngs_modulus": 1.0e6, "poissons_ratio": 0.3, "yield_stress": 3.85e3},
                         guess={"youngs_modulus": 1.0e3, "poissons_ratio": 0.2, "yield_stress": 100.0},
                         optimize=("youngs_modulus", "poissons_ratio", "yield_stress")),
    "trophy": SyntheticCase(shape="cube", size=0.5, lift=0.15, spread=1.25, material="sand",
                            truth={"friction_angle": 40.0, "youngs_modulus": 1.0e6, "poissons_ratio": 0.3},
                            guess={"friction_angle": 10.0}, optimize=("friction_angle",)),
}
# fmt: on


# every case, one policy: a global search of the parameter box first (12 samples per free
# parameter, at least 24: a space-filling design grows with the dimension, as the 10 d rule of
# thumb for computer experiments; 24 samples in playdoh's 3-D box never came near its
# truth's yield stress, 36 did), a second round of half as many around the three best
# distinct samples (one design spacing wide: the cream's narrow yield-stress valley lies
# between the first round's samples), then Levenberg-Marquardt over all frames (a dropped
# object's first frames are free fall, where the material does nothing) from each
# neighbourhood's best for 3 iterations, then on from the best of those
def _with_policy(case: SyntheticCase) -> SyntheticCase:
    samples = max(24, 12 * len(case.optimize))
    return replace(case, search=samples, refine=samples // 2, starts=3, horizon=(0, 0), method="levenberg_marquardt")


CASES = {name: _with_policy(case) for name, case in CASES.items()}

QUICK_CASES = ("torus", "playdoh", "droplet")  # elastic, plasticine, Newtonian: the CI subset
#: clflow's own second set (--set extra): every material type, so coverage is not tuned on the nine
EXTRA_CASES_FILE = Path(__file__).with_name("extra_cases.yaml")

# PAC-NeRF's 14 frames at 24 fps; Levenberg-Marquardt iterations (each 1 + parameters forward
# runs) after the search (16: on the 1.5x main grid the cat's 9 main iterations of 12 were
# still climbing from its coarse start, loss 0.0079 against the truth's 0.0038); QUICK is
# small enough for CI. flip 0.99 for truth and optimiser: APIC's damping grows with the
# substeps, which the stiffness sets, so under APIC a fluid's bulk modulus moved the loss
# mostly through the substep count (quick droplet: bulk RE 0.72 with APIC, 0.17 with FLIP;
# docs/mpm.md, "Transfers and time step").
FULL = Resolution(
    object_detail=12, floor_side=32, image=160, grid=24, frames=14, iterations=16, main_grid_scale=1.5, flip=0.99
)
QUICK = Resolution(
    object_detail=8, floor_side=20, image=96, grid=24, frames=10, iterations=8, main_grid_scale=1.5, flip=0.99
)

# Table 3 of the PhysFlow paper (CVPR 2025): (mean RE, EPE px) per case and method; their
# images are 800 x 800 px, so their EPE is not comparable with ours in pixels.
# a table, one case a row: kept as written
# fmt: off
PUBLISHED: dict[str, dict[str, tuple[float, float]]] = {
    "droplet": {"PAC-NeRF": (0.06, 0.28), "GIC": (0.41, 0.42), "PhysFlow": (0.02, 0.08)},
    "letter": {"PAC-NeRF": (0.26, 0.11), "GIC": (0.02, 0.07), "PhysFlow": (0.46, 0.13)},
    "cream": {"PAC-NeRF": (3.04, 0.61), "GIC": (0.21, 0.20), "PhysFlow": (0.54, 0.64)},
    "toothpaste": {"PAC-NeRF": (0.42, 0.15), "GIC": (0.11, 0.07), "PhysFlow": (0.24, 0.16)},
    "torus": {"PAC-NeRF": (0.06, 0.52), "GIC": (0.01, 0.24), "PhysFlow": (0.51, 1.04)},
    "bird": {"PAC-NeRF": (0.08, 0.62), "GIC": (0.04, 0.36), "PhysFlow": (0.31, 0.69)},
    "playdoh": {"PAC-NeRF": (0.37, 0.55), "GIC": (0.10, 0.16), "PhysFlow": (0.15, 0.29)},
    "cat": {"PAC-NeRF": (0.31, 0.34), "GIC": (0.02, 0.08), "PhysFlow": (0.34, 0.24)},
    "trophy": {"PAC-NeRF": (0.10, 3.30), "GIC": (0.05, 1.85), "PhysFlow": (0.01, 1.33)},
}
# fmt: on
PUBLISHED_MEAN = {"PAC-NeRF": (0.52, 0.72), "GIC": (0.11, 0.38), "PhysFlow": (0.29, 0.51)}
METHODS = ("PAC-NeRF", "GIC", "PhysFlow")


#: --truth-transfer: the ground truth's PIC/FLIP blend (None: the optimiser's own)
TRUTH_FLIP = {"flip": None, "apic": 0.0}


@dataclass(frozen=True)
class Settings:
    """What a benchmark run depends on besides its cases (a rerun resumes only with equal settings)."""

    resolution: Resolution = FULL
    truth_scale: int = 2  # ground truth's grid and image refinement
    noise: float = 0.0  # sensor noise, 8-bit grey levels
    codec: str | None = None  # video suffix of a lossy guidance video, e.g. ".mp4"
    seed: int = 0
    views: int = 1  # guidance views (clflow_datasets.synthetic.VIEW_AZIMUTHS_DEG)
    truth_transfer: str = "flip"  # the truth's transfer: "flip" (the optimiser's blend) or "apic" (a mismatch)
    # s of each case's optimisation (optimize.budget: the main grid from the device's speed; None: the resolution's)
    case_budget: float | None = None


#: the ground truth's grid stays this many times finer (in cells) than any main grid a budget chooses
TRUTH_MARGIN = 4 / 3


def with_budget(cfg, seconds: float, truth_grid: int):
    """``cfg`` with ``optimize.budget`` of ``seconds``, its main grid at most 1 / TRUTH_MARGIN
    of the truth's ``truth_grid`` nodes (in cells): a budget refines the model, never to the
    truth's own grid."""
    from clflow.scene.config import BudgetSettings

    finest = math.floor((truth_grid - 1) / TRUTH_MARGIN) + 1
    return replace(cfg, optimize=replace(cfg.optimize, budget=BudgetSettings(seconds, finest)))


def check_case(name: str, case: SyntheticCase | SceneCase) -> None:
    """ValueError if a case's truth or guess is not a valid start for its material (a
    case of several objects: each object's for its own)."""
    from clflow.errors import InputError
    from clflow.materials import validate_params
    from clflow.mpm.parameterization import parameterization

    if isinstance(case, SceneCase):
        for obj in case.objects:
            check_case(f"{name}.{obj.name}", obj)
        return
    for label, values in (("truth", case.truth), ("guess", {**case.truth, **case.guess})):
        try:
            validate_params(case.material, values)
            for p in case.optimize:
                parameterization(case.material, p).encode(values[p])
        except InputError as exc:  # from the registry or the encoding
            raise ValueError(f"case {name!r}: its {label} is out of range: {exc}") from None


MAX_SPREAD = 1e3  # a case's room beside its shapes, in their sizes
#: what a case file may say of a case (clflow eval sysid --cases FILE), in the table's terms
CASE_KEYS = ("shape", "size", "lift", "spread", "material", "density", "truth", "guess", "optimize", "velocity")
#: a case of several objects: its objects (a list, each of OBJECT_KEYS) and the room beside them
SCENE_CASE_KEYS = ("objects", "spread")
OBJECT_KEYS = ("name", "shape", "size", "position", "material", "density", "truth", "guess", "optimize", "velocity")


def load_cases(path: Path) -> dict[str, SyntheticCase]:
    """The cases of a YAML or JSON file: a mapping of name -> {shape, size (m), lift (m),
    spread (sizes), material, density (kg/m^3), truth and guess (SI, by registry name),
    optimize (names; default: the truth's; guess gives each a start), velocity (m/s, 3
    numbers)}, each run with the benchmark's policy (search, starts, Levenberg-Marquardt).
    Values are checked as a scene config checks its own; InputError, one line naming the file
    and the case's key, for anything clflow cannot run."""
    from clflow.errors import InputError
    from clflow.scene.config.files import read_data_file
    from clflow.scene.config.reader import Reader

    data = read_data_file(path, "case file")
    if not isinstance(data, dict) or not data:
        raise InputError(f"{path}: expected a mapping of case names to cases")
    r = Reader(str(path), path.parent)
    r.no_huge_integers(data)
    cases = {}
    for name, body in data.items():
        if not isinstance(name, str) or not name.isidentifier() or name in CASES:
            raise InputError(f"{path}: case name {name!r}: use a new identifier (not one of the built-in cases)")
        several = isinstance(body, dict) and "objects" in body
        cases[name] = _with_policy(_scene_case_of(r, body, name) if several else _case_of(r, body, name))
        try:
            check_case(name, cases[name])
        except ValueError as exc:
            raise InputError(f"{path}: {exc}") from None
    return cases


def _scene_case_of(r, body, name: str) -> SceneCase:
    """A :class:`SceneCase` of case file entry ``name``: ``objects``, a list of shapes each
    with a name, shape, size (m), position (its centre, m, +y up), material, density, truth,
    guess, optimize and velocity as a single case's; ``spread``: room beside them (in their
    box's longest side)."""
    from clflow.scene.config.parse import LENGTH

    body = r.section(body, name, SCENE_CASE_KEYS)
    entries = body.get("objects")
    if not isinstance(entries, list) or len(entries) < 2:
        raise r.fail(f"{name}.objects", "must be a list of two or more shapes, each with a name")
    objects, names = [], set()
    for k, entry in enumerate(entries):
        where = f"{name}.objects[{k}]"
        entry = r.section(entry, where, OBJECT_KEYS)
        label = entry.get("name")
        if not isinstance(label, str) or not label.isidentifier() or label in names:
            raise r.fail(f"{where}.name", f"must be a new identifier for the object, got {label!r}")
        names.add(label)
        one = _case_of(r, {k: v for k, v in entry.items() if k not in ("name", "position")}, where)
        position = r.vec3(entry, "position", where, None, limit=LENGTH)
        if position is None:
            raise r.fail(f"{where}.position", "is required: the shape's centre (m, +y up; the floor is y = 0)")
        obj = CaseObject(
            label, one.shape, one.size, position, one.material, one.truth, one.guess, one.optimize, one.density,
            one.velocity,
        )  # fmt: skip
        if obj.bounds()[0][1] < 0:
            raise r.fail(
                f"{where}.position", f"puts the shape below the floor (its lowest point y = {obj.bounds()[0][1]:g} m)"
            )
        objects.append(obj)
    spread = r.number(body, "spread", name, SceneCase.spread, low=0.0, high=MAX_SPREAD)
    return SceneCase(objects=tuple(objects), spread=spread)


def _case_of(r, body, name: str) -> SyntheticCase:
    """A :class:`SyntheticCase` of case file entry ``name`` (parameter names made canonical),
    its values read by ``r`` (a clflow.scene.config Reader, errors naming ``name.key``)."""
    from clflow.errors import InputError
    from clflow.materials import DENSITY, get_material
    from clflow.scene.config.parse import LENGTH, SPEED
    from clflow_datasets.synthetic import SHAPES

    body = r.section(body, name, CASE_KEYS)
    missing = [key for key in ("material", "truth", "guess") if body.get(key) is None]
    if missing:
        raise r.fail(f"{name}.{missing[0]}", "is required (a case gives material, truth and guess)")
    truth_in, guess_in = r.mapping(body["truth"], f"{name}.truth"), r.mapping(body["guess"], f"{name}.guess")
    optimize_in = r.items(body, "optimize", name) if body.get("optimize") is not None else list(truth_in)
    try:
        material = get_material(str(body["material"]))
        name_of = lambda n: material.param(str(n)).name  # noqa: E731  (InputError for an unknown name)
        truth = {name_of(n): v for n, v in truth_in.items()}
        guess = {name_of(n): v for n, v in guess_in.items()}
        optimize = tuple(name_of(n) for n in optimize_in)
    except InputError as exc:
        raise r.fail(name, str(exc)) from None
    if not optimize or set(optimize) - set(truth) or set(guess) != set(optimize):
        raise r.fail(name, "optimize names parameters of the truth, and guess gives each a start")
    density = r.number(body, "density", name, SyntheticCase.density, low=0.0, strict_low=True)
    DENSITY.check(density, f"{r.source}: {name}.density")
    spread = body.get("spread")
    return SyntheticCase(
        shape=r.choice(body, "shape", name, SHAPES, "cube"),
        size=r.number(body, "size", name, SyntheticCase.size, low=0.0, high=LENGTH, strict_low=True),
        lift=r.number(body, "lift", name, SyntheticCase.lift, low=0.0, high=LENGTH),
        spread=None if spread is None else r.number(body, "spread", name, low=0.0, high=MAX_SPREAD),
        material=material.name,
        truth=truth,
        guess=guess,
        optimize=optimize,
        density=density,
        velocity=r.vec3(body, "velocity", name, (0.0, 0.0, 0.0), limit=SPEED),
    )


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
    from clflow.scene.config import load_config

    case = case or CASES[name]
    check_case(name, case)
    make = make_scene_case if isinstance(case, SceneCase) else make_case
    start = time.perf_counter()
    made = folder / "case.json"
    definition = case_definition(case)
    if made.exists() and json.loads(made.read_text()).get("definition") != definition:
        remove_entries(folder.parent, (glob.escape(folder.name),))  # made from another definition: make it anew
    if not made.exists():  # an interrupted generation leaves no case.json: make it again
        make(
            folder,
            case,
            settings.resolution,
            settings.seed,
            truth_scale=settings.truth_scale,
            noise=settings.noise,
            codec=settings.codec,
            views=settings.views,
            truth_flip=TRUTH_FLIP[settings.truth_transfer],
        )
        record = json.loads(made.read_text())
        record["definition"] = definition
        atomic_write_text(made, json.dumps(record, indent=2))
    generation = json.loads(made.read_text())
    generated = time.perf_counter()
    cfg = load_config(folder / "config.yaml")
    if settings.case_budget is not None:
        cfg = with_budget(cfg, settings.case_budget, generation["truth_grid_resolution"])
    record = {"case": name, "material": case.material, "generation": generation, "status": "ok"}
    try:
        opt = Optimization(cfg, progress=progress)
        state = opt.run(resume=True)
        metrics = opt.write_results(state)
        record.update(grid=metrics["grid"], optimise_seconds=metrics["seconds"], budget=metrics.get("budget"))
        truth_z = {n: float(opt.params[n].encode(case.truth[n])) for n in opt.params}
        # at the truth's own stable time step: MPM's answer depends on dt (quick playdoh at the
        # truth: 0.0057 at its 40 substeps per frame, 0.028 at 254), and the final run's may be finer
        floor = opt.evaluate({**state.z, **truth_z}, opt.frames, with_grad=False)
        floor_epe = opt.endpoint_error(floor.flows, floor.more_flows)
        # both losses against the estimator's error measured at their own parameters (the final
        # point's targets hold its own): comparable, the truth's the floor of the optimiser's loss
        truth_loss = opt.self_consistent_loss(floor, opt.frames, opt.final_shifts)
    except BudgetTooSmall:  # the settings', not the case's: every case would fail alike
        raise
    except ClflowError as exc:
        record.update(status=f"failed: {exc}", seconds=time.perf_counter() - start)
        return record
    record["parameters"] = parameter_records(case, opt.values(state.z), metrics["identifiability"]["ranges"])
    record.update(
        mean_re=float(np.mean([p["re"] for p in record["parameters"].values()])),
        epe_px=metrics["epe_px"],
        floor_epe_px=floor_epe,
        final_loss=metrics["flow_loss"],
        truth_loss=truth_loss,
        identifiability=metrics["identifiability"],
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


def holds(entry: dict, truth: float) -> bool:
    """Whether a parameter's range (Diagnostics.ranges: low, high; None for an open end) holds ``truth``."""
    return (entry["low"] is None or truth >= entry["low"]) and (entry["high"] is None or truth <= entry["high"])


def coverage(cases: dict) -> tuple[int, int]:
    """(parameters whose range holds the truth, parameters) over the finished cases."""
    params = [p for r in cases.values() if r.get("status") == "ok" for p in r["parameters"].values()]
    return sum(bool(p.get("holds_truth")) for p in params), sum("holds_truth" in p for p in params)


def range_shapes(cases: dict) -> tuple[int, int]:
    """(ranges bounded on both sides, ranges open on both) over the finished cases: an open
    range holds any truth, so coverage is read beside these."""
    ranges = [
        p["range"] for r in cases.values() if r.get("status") == "ok" for p in r["parameters"].values() if "range" in p
    ]
    return sum(None not in r for r in ranges), sum(r == [None, None] for r in ranges)


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


def _fmt(value: float) -> str:
    return f"{value:.3g}"


def _caveat(name: str, record: dict) -> str:
    """What a case's identifiability check says of a parameter, for the table."""
    ident = record.get("identifiability", {})
    if name in ident.get("unresolved", []):
        values = ident["profile"][name]["values"]
        return f" (loss flat from {_fmt(min(values))} to {_fmt(max(values))})"
    notes = ["weakly constrained"] if name in ident.get("weakly_constrained", []) else []
    if name in ident.get("grid_sensitive", []):
        notes.append(f"grid-sensitive, {ident['grid_shift_z'][name]:+.2f} on {ident['grids'][0]} nodes")
    return f" ({'; '.join(notes)})" if notes else ""


def markdown(summary: dict) -> str:
    """The results as a Markdown table in the layout of the paper's Table 3, with the
    published rows (RE / EPE) beside ours where the paper has the case, and each case's loss
    found against the loss at its ground truth (below it: the model's own minimum lies
    elsewhere; above: the optimiser stopped short)."""
    cases = summary["cases"]
    methods = METHODS if any(name in PUBLISHED for name in cases) else ()
    lines = [
        "| case | material | parameter: found (truth) | RE | EPE px (floor) | loss found / at truth | iterations, "
        "main grid | seconds |" + "".join(f" {m} RE/EPE |" for m in methods),
        "|---" * (8 + len(methods)) + "|",
    ]
    for name, r in cases.items():
        published = "".join(f" {_published(PUBLISHED.get(name, {}).get(m))} |" for m in methods)
        if r.get("status") != "ok":
            lines.append(
                f"| {name} | {r['material']} | {r['status']} | - | - | - | - | {r.get('seconds', 0):.0f} |{published}"
            )
            continue
        params = "<br>".join(
            f"{n}: {_fmt(p['found'])} {_range(p)} ({_fmt(p['truth'])}), RE {p['re']:.3f}{_caveat(n, r)}"
            for n, p in r["parameters"].items()
        )
        lines.append(
            f"| {name} | {r['material']} | {params} | {r['mean_re']:.3f} | {r['epe_px']:.3f} "
            f"({r['floor_epe_px']:.3f}) | {r['final_loss']:.3g} / {r['truth_loss']:.3g} | {r['iterations']}"
            f"{_grid(r)} | {r['seconds']:.0f} |{published}"
        )
    lines += _summary_rows(cases, methods)
    return "\n".join(lines + per_class.markdown(cases) + _closing(summary, methods)) + "\n"


def _grid(r: dict) -> str:
    """A case's main grid for the table's iterations column, " on N nodes" (empty for results
    made before it was recorded)."""
    return f" on {r['grid']['main']} nodes" if "grid" in r else ""


def _range(p: dict) -> str:
    """A parameter's range for the table, "[low, high]" ("-" for an open end), marked where
    it misses the truth; empty for results made before ranges."""
    if "range" not in p:
        return ""
    low, high = ("-" if v is None else _fmt(v) for v in p["range"])
    return f"[{low}, {high}]" + ("" if p["holds_truth"] else " **misses**")


def _published(row: tuple[float, float] | None) -> str:
    return "-" if row is None else f"{row[0]:.2f}/{row[1]:.2f}"


def _summary_rows(cases: dict, methods: tuple[str, ...]) -> list[str]:
    """The mean and median rows over the finished cases; the published means are the paper's
    for its nine, else the means of the rows shown (cases the paper lacks left out)."""
    ok = [r for r in cases.values() if r.get("status") == "ok"]
    if not ok:
        return []
    if set(cases) == set(PUBLISHED):
        means = {m: PUBLISHED_MEAN[m] for m in methods}
    else:
        rows = [PUBLISHED[name] for name in cases if name in PUBLISHED]
        means = {m: tuple(statistics.fmean(row[m][k] for row in rows) for k in (0, 1)) for m in methods}
    total = sum(r.get("seconds", 0.0) for r in cases.values())
    mean_re, mean_epe = sum(r["mean_re"] for r in ok) / len(ok), sum(r["epe_px"] for r in ok) / len(ok)
    bounded = per_class.bounded_ranges(cases)
    bounded_row = (
        [
            f"| mean over the {bounded['parameters']} ranges bounded on both sides | | median width "
            f"{bounded['median_width_decades']:.2f} decades | {bounded['mean_re']:.3f} | | | | |" + " |" * len(methods)
        ]
        if bounded["parameters"] and bounded["median_width_decades"] is not None
        else []
    )
    from clflow.pipeline.fit.diagnostics import RANGE_LEVEL

    held, counted = coverage(cases)
    bounded, unbounded = range_shapes(cases)
    ranges = [
        f"| {100 * RANGE_LEVEL:.0f} % ranges holding the truth | | {held} of {counted} ({100 * held / max(counted, 1):.0f} %; "
        f"{bounded} bounded on both sides, {unbounded} on neither) | | | | | |" + " |" * len(methods)
    ]
    return (ranges if counted else []) + [
        f"| **mean** ({len(ok)} of {len(cases)}) | | | **{mean_re:.3f}** | **{mean_epe:.3f}** | | | {total:.0f} |"
        + "".join(f" {_published(means[m])} |" for m in methods),
        f"| median | | | {statistics.median(r['mean_re'] for r in ok):.3f} | "
        f"{statistics.median(r['epe_px'] for r in ok):.3f} | | | |" + " |" * len(methods),
        *bounded_row,
    ]


def _main_phase(settings: dict) -> str:
    """The main phase's grid in the settings line: its scale, or the budget that chose it."""
    if settings.get("case_budget") is None:
        return f"{settings['resolution'].get('main_grid_scale', 1.0):g}x"
    return f"the finest a budget of {settings['case_budget']:g} s per case affords, timed on the device"


def _closing(summary: dict, methods: tuple[str, ...]) -> list[str]:
    """The settings and provenance lines under the table."""
    s = summary["settings"]
    res = s["resolution"]
    env = summary.get("environment", {})
    if not methods:
        published = "No published rows: the paper has none of these cases."
    elif set(summary["cases"]) == set(PUBLISHED):
        published = "Published rows: PhysFlow (CVPR 2025) Table 3, 800 x 800 px images."
    else:
        published = (
            "Published rows: PhysFlow (CVPR 2025) Table 3, 800 x 800 px images; their means over the cases shown."
        )
    return [
        "",
        f"Settings: grid {res['grid']} nodes (search; main phase {_main_phase(s)}), "
        f"PIC/FLIP blend {res.get('flip', 0.0):g}, "
        f"image {res['image']} px, {res['frames']} frames, "
        f"{res['iterations']} iterations; ground truth at {s['truth_scale']}x grid and image; noise "
        f"{s['noise']} grey levels; codec {s['codec'] or 'none (PNG)'}; seed {s['seed']}; "
        f"{s.get('views', 1)} guidance view{'s' if s.get('views', 1) > 1 else ''}"
        + (
            "; ground truth under APIC, a transfer the optimiser does not share."
            if s.get("truth_transfer") == "apic"
            else "."
        ),
        f"Made {env.get('date', '?')} with clflow {env.get('clflow', '?')} (commit {env.get('commit') or '?'}), "
        f"torch {env.get('torch', '?')}, "
        f"pyopencl {env.get('pyopencl', '?')} on {env.get('device', '?')} (load {env.get('load', '?')}). " + published,
    ]


__all__ = [
    "CASES",
    "EXTRA_CASES_FILE",
    "FULL",
    "METHODS",
    "PUBLISHED",
    "PUBLISHED_MEAN",
    "QUICK",
    "QUICK_CASES",
    "Settings",
    "TRUTH_MARGIN",
    "check_case",
    "coverage",
    "evaluate",
    "holds",
    "load_cases",
    "markdown",
    "run_case",
    "with_budget",
]
