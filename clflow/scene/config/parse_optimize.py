"""The ``optimize`` and ``evaluation`` sections of a parsed config, checked against the
config's objects, simulation and flow."""

from __future__ import annotations

import math
from typing import Any

from clflow.errors import InputError
from clflow.materials import DENSITY, get_material, validate_params
from clflow.scene.config import schema
from clflow.scene.config.keys import SPEED
from clflow.scene.config.optimize_settings import (
    MAX_HYPOTHESES,
    TIME_SCALE,
    VELOCITY,
    VELOCITY_COMPONENTS,
    BudgetSettings,
    OptimizeSettings,
    SearchSettings,
)
from clflow.scene.config.reader import Reader
from clflow.scene.config.settings import (
    FlowSettings,
    MaterialConfig,
    SceneObject,
    SimulationSettings,
    main_grid_range,
    split_parameter,
    velocity_names,
)


def optimize_settings(r: Reader, data: Any, objects: tuple[SceneObject, ...], frames: int) -> OptimizeSettings:
    """``optimize``; with several objects each parameter is named OBJECT.PARAM."""
    p = "optimize"
    body = r.section(data, p, schema.OPTIMIZE.known)
    names = body.get("parameters", [])
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise r.fail(f"{p}.parameters", f"must be a list of parameter names, got {names!r}")
    hypotheses = _material_hypotheses(r, body.get("material"), names, objects)
    material = objects[0].material
    if len(objects) > 1:
        for name in names:
            if name != TIME_SCALE.name:  # the scene's, no object's
                _object_parameter(r, f"{p}.parameters", name, objects, hypotheses)
    elif material.type != "query" and not hypotheses:
        mat = get_material(material.type)
        for name in names:
            if name not in ("density", VELOCITY, TIME_SCALE.name) and name not in mat.param_names:
                raise r.fail(
                    f"{p}.parameters",
                    f"{name!r} is not a parameter of {mat.name} "
                    f"(its parameters: {', '.join(mat.param_names)}, density, velocity; and time_scale)",
                )
    phase = schema.ESTIMATE_VELOCITY
    estimate = r.section(body.get("estimate_velocity"), f"{p}.estimate_velocity", phase.known)
    if "objects" in estimate and len(objects) == 1:
        raise r.fail(f"{p}.estimate_velocity.objects", "names objects of a config of several: drop it")
    estimate_frames = estimate_iterations = 0
    estimated: tuple[str, ...] = ()  # velocity, or OBJECT.velocity of each object the phase estimates
    if estimate:
        estimate_frames, estimate_iterations = (
            r.read(estimate, f"{p}.estimate_velocity", phase[k]) for k in ("frames", "iterations")
        )
        if estimate_frames > frames:
            raise r.fail(
                f"{p}.estimate_velocity.frames", f"must be <= simulation.frames ({frames}), got {estimate_frames}"
            )
        estimated = (VELOCITY,) if len(objects) == 1 else _estimated_objects(r, estimate.get("objects"), objects)
    rates_in = r.mapping(body.get("learning_rates"), f"{p}.learning_rates")
    for name in rates_in:
        if name not in names and name not in estimated:
            velocity = name.rpartition(".")[2] == VELOCITY
            raise r.fail(
                f"{p}.learning_rates.{name}",
                f"is not among optimize.parameters {names}"
                + (" (nor estimated: optimize.estimate_velocity)" if velocity else ""),
            )
    rate = schema.OPTIMIZE["learning_rates"]  # each rate's range
    rates = {
        n: r.number(rates_in, n, f"{p}.learning_rates", low=rate.low, high=rate.high, strict_low=rate.strict_low)
        for n in rates_in
    }
    horizon = r.section(body.get("horizon"), f"{p}.horizon", schema.HORIZON.known)
    # hypotheses are told apart by the search
    search = _search(r, body["search"]) if body.get("search") is not None else SearchSettings() if hypotheses else None
    bounds = _bounds(r, body.get("bounds"), names, objects, hypotheses)
    settings = r.fields(  # iterations, final_rate, method: as they declare
        body,
        p,
        OptimizeSettings,
        parameters=tuple(names),
        learning_rates=rates,
        horizon_start=lambda: r.read(horizon, f"{p}.horizon", schema.HORIZON["start"]),
        horizon_step=lambda: r.read(horizon, f"{p}.horizon", schema.HORIZON["step"]),
        search=search,
        bounds=bounds,
        estimate_velocity_frames=estimate_frames,
        estimate_velocity_iterations=estimate_iterations,
        # the one object's name, or those of estimate_velocity.objects
        estimate_velocity_objects=(objects[0].name,) * bool(estimated)
        if len(objects) == 1
        else tuple(n.partition(".")[0] for n in estimated),
        materials=hypotheses,
        budget=lambda: _budget(r, body["budget"]) if body.get("budget") is not None else None,
    )
    return OptimizeSettings(**settings)


def _budget(r: Reader, data: Any) -> BudgetSettings:
    """``optimize.budget``: seconds, and the finest main grid to consider."""
    p = "optimize.budget"
    return BudgetSettings(**r.fields(r.section(data, p, schema.BUDGET.known), p, BudgetSettings))


def _estimated_objects(r: Reader, data: Any, objects: tuple[SceneObject, ...]) -> tuple[str, ...]:
    """``optimize.estimate_velocity.objects`` of a config of several objects: the objects whose
    velocities the velocity phase estimates, as OBJECT.velocity (required: an object at rest
    has no velocity to estimate, and Adam's steps would move its weakly observed ones)."""
    where = "optimize.estimate_velocity.objects"
    names = [o.name for o in objects]
    if not isinstance(data, list) or not data or not all(isinstance(n, str) for n in data):
        raise r.fail(where, f"is required with several objects: a list of object names ({', '.join(names)})")
    for name in data:
        if name not in names:
            raise r.fail(where, f"{name!r}: there is no object {name!r} (the objects: {', '.join(names)})")
    if len(set(data)) < len(data):
        raise r.fail(where, f"names an object twice: {data!r}")
    return tuple(f"{n}.{VELOCITY}" for n in data)


def _search(r: Reader, data: Any) -> SearchSettings:
    """``optimize.search``: the global phase's samples, starts and grid."""
    p = "optimize.search"
    search = SearchSettings(**r.fields(r.section(data, p, schema.SEARCH.known), p, SearchSettings))
    finest = schema.SIMULATION["grid_resolution"].low  # as simulation.grid_resolution: walls take 4 cells a side
    if 0 < search.grid_resolution < finest:
        raise r.fail(
            f"{p}.grid_resolution", f"must be 0 (the simulation's) or >= {finest}, got {search.grid_resolution}"
        )
    if search.starts > search.samples:
        raise r.fail(f"{p}.starts", f"must not exceed search.samples ({search.samples}), got {search.starts}")
    return search


def _bounds(
    r: Reader, data: Any, names: list[str], objects: tuple[SceneObject, ...], hypotheses: dict[str, tuple[str, ...]]
) -> dict[str, tuple[float, float]]:
    """``optimize.bounds``: [lower, upper] in SI per optimised parameter, within the
    parameter's valid range where the config names its material."""
    bounds = {}
    for name, box in r.mapping(data, "optimize.bounds").items():
        where = f"optimize.bounds.{name}"
        if name not in names:
            raise r.fail(where, f"is not among optimize.parameters {names}")
        if (
            not isinstance(box, list)
            or len(box) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in box)
        ):
            raise r.fail(where, f"must be [lower, upper] (SI), got {box!r}")
        if not box[0] < box[1]:
            raise r.fail(where, f"is empty or inverted: lower {box[0]:g} must be below upper {box[1]:g}")
        param = _registry_param(name, objects, hypotheses)
        if param is not None:
            (lo, hi), (low_in, high_in) = param.valid, (param.low_inclusive, param.high_inclusive)
            if box[0] < lo or (box[0] == lo and not low_in) or box[1] > hi or (box[1] == hi and not high_in):
                valid = f"{'[' if low_in else '('}{lo:g}, {hi:g}{']' if high_in else ')'}"
                raise r.fail(where, f"[{box[0]:g}, {box[1]:g}] must lie in {param.name}'s valid range {valid}")
        bounds[name] = (float(box[0]), float(box[1]))
    return bounds


def _registry_param(name: str, objects: tuple[SceneObject, ...], hypotheses: dict[str, tuple[str, ...]]):
    """The registry's Param that ``name`` of optimize.parameters stands for; None for a
    velocity and for a material the query picks."""
    if name == TIME_SCALE.name:
        return TIME_SCALE
    k, param = split_parameter(objects, name)
    if param == "density":
        return DENSITY
    for material in hypotheses.get(objects[k].name, (objects[k].material.type,)):
        if material != "query" and param in get_material(material).param_names:
            return get_material(material).param(param)
    return None


def _material_hypotheses(
    r: Reader, data: Any, names: list[str], objects: tuple[SceneObject, ...]
) -> dict[str, tuple[str, ...]]:
    """``optimize.material``: object name -> its hypotheses (:func:`_hypotheses`), in the
    objects' order; of one object a list, of several a mapping OBJECT -> list (the objects
    not named keep their material), each list checked against its object's entries of
    optimize.parameters. The hypotheses are the lists' product: at most MAX_HYPOTHESES."""
    p = "optimize.material"
    if data is None:
        return {}
    if len(objects) == 1:
        return {objects[0].name: _hypotheses(r, p, data, names)}
    known = [o.name for o in objects]
    if not isinstance(data, dict) or not data:
        raise r.fail(
            p, f"with several objects must map object names ({', '.join(known)}) to lists of materials, got {data!r}"
        )
    for name in data:
        if name not in known:
            raise r.fail(f"{p}.{name}", f"there is no object {name!r} (the objects: {', '.join(known)})")
    lists = {
        o.name: _hypotheses(r, f"{p}.{o.name}", data[o.name], [n for n in names if n.partition(".")[0] == o.name])
        for o in objects
        if o.name in data
    }
    count = math.prod(len(materials) for materials in lists.values())
    if count > MAX_HYPOTHESES:
        sizes = " x ".join(f"{len(m)} of {name}" for name, m in lists.items())
        raise r.fail(p, f"{count} combinations of materials ({sizes}); at most {MAX_HYPOTHESES}: name fewer")
    return lists


def _hypotheses(r: Reader, p: str, data: Any, names: list[str]) -> tuple[str, ...]:
    """The list of materials at key ``p``: registry names (aliases resolved), each with at
    least one of ``names`` (its object's entries of optimize.parameters: PARAM, or
    OBJECT.PARAM with several objects); each of those belongs to at least one of them."""
    if not isinstance(data, list) or not data or not all(isinstance(n, str) for n in data):
        raise r.fail(p, f"must be a non-empty list of material names, got {data!r}")
    try:
        materials = [get_material(n) for n in data]
    except InputError as exc:
        raise r.fail(p, str(exc)) from None
    canonical = [m.name for m in materials]
    if len(set(canonical)) < len(canonical):
        raise r.fail(p, f"names a material twice: {data!r}")
    common = ("density", VELOCITY, TIME_SCALE.name)
    bare = {n: n.rpartition(".")[2] for n in names}  # OBJECT.PARAM -> PARAM
    for m in materials:
        if not any(b in common or b in m.param_names for b in bare.values()):
            raise r.fail(
                p,
                f"{m.name} has none of optimize.parameters {names} (its parameters: "
                f"{', '.join(m.param_names)}, density, velocity)",
            )
    for n, b in bare.items():
        if b not in common and not any(b in m.param_names for m in materials):
            raise r.fail(
                "optimize.parameters", f"{n!r} is a parameter of none of the hypotheses {', '.join(canonical)}"
            )
    return tuple(canonical)


def _object_parameter(
    r: Reader, where: str, name: str, objects: tuple[SceneObject, ...], hypotheses: dict[str, tuple[str, ...]]
) -> tuple[SceneObject, str]:
    """(object, parameter) of ``name`` (OBJECT.PARAM) of a config of several objects: the
    object is one of them and the parameter its material's (for an object of ``hypotheses``
    checked against those instead, by :func:`_hypotheses`), density or velocity."""
    names = ", ".join(o.name for o in objects)
    obj_name, dot, param = name.partition(".")
    example = f"{objects[0].name}.{next(iter(objects[0].material.parameters), 'density')}"
    if not dot or not param:
        raise r.fail(
            where, f"{name!r}: with several objects name each parameter's object, OBJECT.PARAM (e.g. {example})"
        )
    obj = next((o for o in objects if o.name == obj_name), None)
    if obj is None:
        raise r.fail(where, f"{name!r}: there is no object {obj_name!r} (the objects: {names})")
    if obj.material.type != "query" and obj.name not in hypotheses and param not in ("density", VELOCITY):
        mat = get_material(obj.material.type)
        if param not in mat.param_names:
            raise r.fail(
                where,
                f"{name!r}: {param!r} is not a parameter of {obj.name}'s material {mat.name} "
                f"(its parameters: {', '.join(mat.param_names)}, density, velocity)",
            )
    return obj, param


def objects_truth(
    r: Reader, data: Any, objects: tuple[SceneObject, ...], hypotheses: dict[str, tuple[str, ...]]
) -> dict[str, float]:
    """``evaluation.ground_truth`` of a config of several objects: OBJECT.PARAM -> SI value,
    each checked against its object's material (of its ``hypotheses``, the first that has
    all its names; density: kg/m^3; OBJECT.velocity: [3] m/s, as its components
    OBJECT.velocity_x, ...)."""
    p = "evaluation.ground_truth"
    evaluation = r.section(data, "evaluation", schema.EVALUATION.known)
    given = dict(r.mapping(evaluation.get("ground_truth"), p))
    per_object: dict[str, dict] = {}
    truth = {}
    for name, value in given.items():
        if name == TIME_SCALE.name:  # the scene's, no object's
            truth[name] = _time_scale_truth(r, value)
            continue
        obj, param = _object_parameter(r, p, name, objects, hypotheses)
        if param == VELOCITY:
            value = r.vec3(given, name, p, limit=SPEED)
        elif isinstance(value, bool) or not isinstance(value, (int, float)):
            raise r.fail(f"{p}.{name}", f"must be a number, got {value!r}")
        per_object.setdefault(obj.name, {})[param] = value
    for k, obj in enumerate(objects):
        values = per_object.get(obj.name, {})
        truth.update(zip(velocity_names(objects, k)[1], values.pop(VELOCITY, ())))
        density = values.pop("density", None)
        try:
            if density is not None:
                DENSITY.check(density)
            if values and obj.material.type != "query":
                material = _fitting(hypotheses.get(obj.name, (obj.material.type,)), values)
                values = {k: v for k, v in validate_params(material, values).items() if k in values}
        except InputError as exc:
            raise r.fail(p, f"{obj.name}: {exc}") from None
        truth.update({f"{obj.name}.{k}": float(v) for k, v in values.items()})
        if density is not None:
            truth[f"{obj.name}.density"] = float(density)
    return truth


def given_truth(r: Reader, data: Any) -> tuple[dict, float | None, tuple]:
    """``evaluation.ground_truth`` as given: the material's values (numbers, checked against
    the material later), the density (kg/m^3, checked) and the velocity (m/s; () if absent)."""
    evaluation = r.section(data, "evaluation", schema.EVALUATION.known)
    truth = dict(r.mapping(evaluation.get("ground_truth"), "evaluation.ground_truth"))
    true_velocity = r.vec3(truth, VELOCITY, "evaluation.ground_truth", (), limit=SPEED)  # () when not given
    truth.pop(VELOCITY, None)
    for name, value in truth.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise r.fail(f"evaluation.ground_truth.{name}", f"must be a number, got {value!r}")
    true_density = truth.pop("density", None)
    if true_density is not None:
        try:
            DENSITY.check(true_density)
        except InputError as exc:
            raise r.fail("evaluation.ground_truth", str(exc)) from None
    return truth, true_density, true_velocity


def ground_truth(
    r: Reader,
    truth: dict,
    true_density: float | None,
    true_velocity: tuple,
    material: MaterialConfig,
    optimize: OptimizeSettings,
) -> dict[str, float]:
    """The ground truth's material values validated for the material (with hypotheses: the
    first that has all its names), its density and velocity components, SI; the video's
    time_scale."""
    truth = dict(truth)  # the caller's is left as it is
    time_scale = truth.pop(TIME_SCALE.name, None)
    if truth and (optimize.materials or material.type != "query"):
        candidates = next(iter(optimize.materials.values()), (material.type,))
        try:
            truth = {k: v for k, v in validate_params(_fitting(candidates, truth), truth).items() if k in truth}
        except InputError as exc:
            raise r.fail("evaluation.ground_truth", str(exc)) from None
    if true_density is not None:
        truth["density"] = float(true_density)
    truth.update(zip(VELOCITY_COMPONENTS, true_velocity))
    if time_scale is not None:
        truth[TIME_SCALE.name] = _time_scale_truth(r, time_scale)
    return truth


def _time_scale_truth(r: Reader, value) -> float:
    """``evaluation.ground_truth.time_scale``, checked against its valid range."""
    try:
        return TIME_SCALE.check(value)
    except InputError as exc:
        raise r.fail("evaluation.ground_truth", str(exc)) from None


def check_time_scale(r: Reader, optimize: OptimizeSettings, simulation: SimulationSettings, objects, forces) -> None:
    """optimize.parameters' time_scale is identified only where the scene fixes the clock:
    gravity, a force stage or an initial velocity the optimiser is given (a faster clock
    and a stiffer or runnier material look alike otherwise); by Levenberg-Marquardt, whose
    finite differences take its derivative (the time step has no adjoint); and an estimated
    velocity is optimised beside it (the velocity phase assumes the video's clock)."""
    if TIME_SCALE.name not in optimize.parameters:
        return
    where = "optimize.parameters"
    named = (split_parameter(objects, n) for n in optimize.parameters if n != TIME_SCALE.name)
    optimised = [objects[k].name for k, param in named if param == VELOCITY]  # objects whose velocity is fitted
    known_motion = any(
        any(o.velocity) and o.name not in optimised and o.name not in optimize.estimate_velocity_objects
        for o in objects
    )
    if not (any(simulation.gravity) or forces or known_motion):
        raise r.fail(
            where,
            "time_scale: nothing in this scene fixes the video's clock (simulation.gravity is zero, no force "
            "stage, no known initial velocity): a faster clock and a stiffer material look alike. Drop "
            "time_scale and set simulation.fps to the video's frame rate divided by its playback speed",
        )
    if optimize.method != "levenberg_marquardt":
        raise r.fail(
            where,
            "time_scale needs optimize.method: levenberg_marquardt (its derivative is a finite difference; "
            "the simulation's time step has no adjoint)",
        )
    unfitted = [o for o in optimize.estimate_velocity_objects if o not in optimised]
    if unfitted:
        name = VELOCITY if len(objects) == 1 else f"{unfitted[0]}.{VELOCITY}"
        raise r.fail(
            where,
            f"time_scale with optimize.estimate_velocity needs {name} among optimize.parameters too: the "
            "velocity phase reads the video at its stated clock, so the main phase must refit it with the clock",
        )


def _fitting(materials: tuple[str, ...], truth: dict) -> str:
    """The first of ``materials`` that has every name of ``truth``, else the first."""
    return next((m for m in materials if set(truth) <= set(get_material(m).param_names)), materials[0])


def check_optimize_fits(r: Reader, optimize: OptimizeSettings, simulation: SimulationSettings, flow: FlowSettings):
    """The optimiser's settings that depend on other sections: several starts need
    Levenberg-Marquardt, the search's grid is the coarser one, LM needs the l2 loss."""
    if optimize.search is not None and optimize.search.starts > 1 and optimize.method != "levenberg_marquardt":
        raise r.fail(
            "optimize.search.starts",
            "several starts are polished by levenberg_marquardt: set "
            "optimize.method: levenberg_marquardt, or starts: 1",
        )
    if optimize.search is not None and optimize.search.grid_resolution > simulation.grid_resolution:
        raise r.fail(
            "optimize.search.grid_resolution",
            f"must not exceed simulation.grid_resolution ({simulation.grid_resolution}): the search's "
            f"grid is the coarse one, got {optimize.search.grid_resolution}",
        )
    budget = optimize.budget
    if budget is not None and 0 < budget.max_grid_resolution < main_grid_range(optimize, simulation)[0]:
        raise r.fail(
            "optimize.budget.max_grid_resolution",
            f"must be 0 or at least the search's grid ({main_grid_range(optimize, simulation)[0]}), the coarsest "
            f"the budget chooses from, got {budget.max_grid_resolution}",
        )
    if optimize.method == "levenberg_marquardt" and flow.loss != "l2":
        raise r.fail(
            "optimize.method", f"levenberg_marquardt minimises a sum of squares: it needs flow.loss l2, not {flow.loss}"
        )
