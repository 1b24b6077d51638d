"""The cases of the system-identification benchmark (``clflow eval sysid``): the built-in
table of PAC-NeRF's nine, each run with the benchmark's policy, the case files of
``--cases FILE`` and ``--set extra`` read and checked, and the check of any case's truth and
guess against its material."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Iterable

from clflow_datasets.scene_cases import CaseObject, SceneCase
from clflow_datasets.synthetic import SyntheticCase


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


#: PAC-NeRF's nine (the built-in set)
PAPER_CASES_FILE = Path(__file__).with_name("pacnerf_cases.yaml")
QUICK_CASES = ("torus", "playdoh", "droplet")  # elastic, plasticine, Newtonian: the CI subset
#: clflow's own second set (--set extra): every material type, so coverage is not tuned on the nine
EXTRA_CASES_FILE = Path(__file__).with_name("extra_cases.yaml")


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


def load_cases(path: Path, reserved: Iterable[str] | None = None) -> dict[str, SyntheticCase | SceneCase]:
    """The cases of a YAML or JSON file: a mapping of name -> {shape, size (m), lift (m),
    spread (sizes), material, density (kg/m^3), truth and guess (SI, by registry name),
    optimize (names; default: the truth's; guess gives each a start), velocity (m/s, 3
    numbers)}, each run with the benchmark's policy (search, starts, Levenberg-Marquardt).
    Values are checked as a scene config checks its own; InputError, one line naming the file
    and the case's key, for anything clflow cannot run; names must be new (not in
    ``reserved``, default the built-in CASES)."""
    from clflow.errors import InputError
    from clflow.scene.config.files import read_data_file
    from clflow.scene.config.reader import Reader

    data = read_data_file(path, "case file")
    if not isinstance(data, dict) or not data:
        raise InputError(f"{path}: expected a mapping of case names to cases")
    r = Reader(str(path), path.parent)
    r.no_huge_integers(data)
    reserved = set(CASES if reserved is None else reserved)
    cases = {}
    for name, body in data.items():
        if not isinstance(name, str) or not name.isidentifier() or name in reserved:
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


CASES = load_cases(PAPER_CASES_FILE, reserved=())  # name -> case, the benchmark's policy applied

__all__ = [
    "CASES",
    "EXTRA_CASES_FILE",
    "PAPER_CASES_FILE",
    "QUICK_CASES",
    "check_case",
    "load_cases",
]
