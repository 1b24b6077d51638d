"""Material hypotheses (``optimize.material: [elastic, plasticine, ...]``; with several
objects ``{jelly: [elastic, plasticine], heap: [sand, snow]}``).

When the material type is uncertain (a query that hesitates, a user who does not know), each
hypothesis runs the global phase of ``clflow optimize`` alone: the same search design over
its own parameters, forward runs only, against the same guidance. The hypothesis whose best
sample has the lowest flow loss is kept and optimised to the end; the others' losses are
recorded in ``hypotheses.json`` and ``metrics.json``. Each hypothesis searches in
``output/hypotheses/<name>/`` (:func:`hypothesis_name`) with its own checkpoint, so
``--resume`` skips finished searches.

A hypothesis gives each object named in ``optimize.material`` one of its materials (all
combinations; the objects not named keep theirs). Each object starts from its config's
parameters where the names agree (``youngs_modulus`` of an elastic config carries over to
plasticine) and from the registry's defaults elsewhere; the hypothesis optimises the
entries of ``optimize.parameters`` its objects' materials have.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import logging
import time
from typing import Callable, Iterable, Iterator

from clflow.errors import ClflowError, InputError
from clflow.fileio import atomic_write_text, copy_file
from clflow.materials import get_material, validate_params
from clflow.pipeline.material import resolve_material
from clflow.scene.config import TIME_SCALE, VELOCITY, MaterialConfig, SceneConfig, object_name, split_parameter

log = logging.getLogger(__name__)


def hypotheses(cfg: SceneConfig) -> list[dict[str, str]]:
    """Every combination of ``optimize.material`` (object name -> material of each object it
    names), in the lists' order, the first object's slowest."""
    lists = cfg.optimize.materials
    return [dict(zip(lists, combination)) for combination in itertools.product(*lists.values())]


def hypothesis_name(cfg: SceneConfig, hypothesis: dict[str, str]) -> str:
    """The name of ``hypothesis`` (of :func:`hypotheses`) in records and as a folder: the
    material of a config of one object, else its OBJECT-MATERIAL pairs joined by ``+``
    (object and material names are letters, digits and ``_``)."""
    names = cfg.object_names
    return "+".join(object_name(cfg.objects, names.index(obj), material, "-") for obj, material in hypothesis.items())


def hypothesis_config(cfg: SceneConfig, hypothesis: dict[str, str]) -> SceneConfig:
    """``cfg`` (concrete materials) with each object named in ``hypothesis`` (object name ->
    material) of that material and the parameters it has, optimising the entries of
    optimize.parameters its object's material has (density and velocity always); its output
    is ``cfg.output/hypotheses/<hypothesis_name>``; no further hypotheses."""
    objects = [_with_material(obj, hypothesis.get(obj.name, obj.material.type)) for obj in cfg.objects]

    def kept(name: str) -> bool:
        if name == TIME_SCALE.name:  # the scene's, whatever its objects are
            return True
        k, param = split_parameter(cfg.objects, name)
        return param in ("density", VELOCITY) or param in get_material(objects[k].material.type).param_names

    names = tuple(n for n in cfg.optimize.parameters if kept(n))
    optimize = dataclasses.replace(
        cfg.optimize,
        parameters=names,
        materials={},
        learning_rates={
            k: v for k, v in cfg.optimize.learning_rates.items() if k in names or k.rpartition(".")[2] == VELOCITY
        },
        bounds={k: v for k, v in cfg.optimize.bounds.items() if k in names},
    )
    return dataclasses.replace(
        cfg.with_objects(objects),
        optimize=optimize,
        output=cfg.output / "hypotheses" / hypothesis_name(cfg, hypothesis),
    )


def _with_material(obj, material: str):
    """The SceneObject ``obj`` of ``material``: its parameters that material has, its density,
    and its material model only when the material is its own."""
    mat = get_material(material)
    params = validate_params(mat.name, {k: v for k, v in obj.material.parameters.items() if k in mat.param_names})
    model = obj.material.model if obj.material.type == mat.name else None
    return dataclasses.replace(obj, material=MaterialConfig(mat.name, params, obj.material.density, model=model))


def search_hypothesis(
    cfg: SceneConfig,
    hypothesis: dict[str, str],
    resume: bool = False,
    progress: Callable[[str, dict], None] | None = None,
    force_video: bool = False,
) -> dict:
    """The global search of ``hypothesis`` (of :func:`hypotheses`) of ``cfg`` (resolved; in
    its own folder, the observed flow copied from ``cfg.output`` when it is there;
    ``progress(name, row)``, name its :func:`hypothesis_name`). Returns {"record": its
    entry in hypotheses.json, "state": the optimiser state its search ended in (None when it
    failed), "config": its config}; a failure other than the user's config is recorded."""
    from clflow.pipeline.fit import Optimization
    from clflow.pipeline.fit.guidance import observed_flow_cache
    from clflow.pipeline.simulation import SubstepLimitError

    hyp, name = hypothesis_config(cfg, hypothesis), hypothesis_name(cfg, hypothesis)
    hyp.output.mkdir(parents=True, exist_ok=True)
    for view in range(1 + len(cfg.more_views)):  # the observed flow is computed once for all
        shared, own = observed_flow_cache(cfg, view), observed_flow_cache(hyp, view)
        if shared.exists() and not own.exists():
            copy_file(shared, own)
    start = time.perf_counter()
    try:
        opt = Optimization(
            hyp, progress=(lambda row: progress(name, row)) if progress else None, force_video=force_video
        )
        state = opt.load_state() if resume and opt.checkpoint.exists() else opt.problem.initial_state()
        if not state.searched:
            state = opt.search.global_search(state, opt.progress)
    except ClflowError as exc:  # no sample of this hypothesis ran: the others may
        if isinstance(exc, InputError) and not isinstance(exc, SubstepLimitError):
            raise  # the user's config: no hypothesis can fix that
        log.warning("hypothesis %s failed: %s", name, exc)
        return {
            "record": {"failed": str(exc), "seconds_this_run": time.perf_counter() - start},
            "state": None,
            "config": hyp,
        }
    finite = [r for r in state.search if r["loss"] is not None]
    best = min(finite, key=lambda r: r["loss"])
    log.info("hypothesis %s: best search loss %.4g at %s", name, best["loss"], best["params"])
    record = {
        "loss": best["loss"],
        "parameters": best["params"],
        "samples": len(state.search),
        "failed_samples": len(state.search) - len(finite),
        "seconds": sum(r["seconds"] for r in state.search),
        "seconds_this_run": time.perf_counter() - start,
    }
    return {"record": record, "state": state, "config": hyp}


def serial_hypotheses(
    cfg: SceneConfig,
    resume: bool = False,
    progress: Callable[[str, dict], None] | None = None,
    force_video: bool = False,
) -> Iterator[dict]:
    """:func:`search_hypothesis` of each of :func:`hypotheses` in turn, in this process."""
    for hypothesis in hypotheses(cfg):
        yield search_hypothesis(cfg, hypothesis, resume, progress, force_video)


def choose_material(
    cfg: SceneConfig,
    *,
    resume: bool = False,
    progress: Callable[[str, dict], None] | None = None,
    force_video: bool = False,
    search_all: Callable[..., Iterable[dict]] = serial_hypotheses,
):
    """Search each of ``optimize.material``'s hypotheses and keep the best.

    Returns (the chosen hypothesis' config with output ``cfg.output``, the optimiser state
    its search ended in (the main run starts from it), the record written to
    ``output/hypotheses.json``: per hypothesis (:func:`hypothesis_name`) its best loss,
    parameters, samples and seconds, and the chosen one). ``progress(name, row)`` sees every
    search sample; a hypothesis whose start needs more substeps than allowed is recorded as
    failed. ``search_all(cfg, resume, progress, force_video)``: the results of
    :func:`search_hypothesis` for each of :func:`hypotheses` in order
    (:func:`serial_hypotheses`, or as Ray tasks: :func:`hypotheses_on_ray`)."""
    from clflow.pipeline.fit.guidance import observed_flow_cache

    cfg = resolve_material(cfg)
    cfg.output.mkdir(parents=True, exist_ok=True)
    record, states, configs = {}, {}, {}
    names = [hypothesis_name(cfg, h) for h in hypotheses(cfg)]
    for name, found in zip(names, search_all(cfg, resume, progress, force_video)):
        record[name] = found["record"]
        if found["state"] is None:
            continue
        for view in range(1 + len(cfg.more_views)):
            if not observed_flow_cache(cfg, view).exists():
                copy_file(observed_flow_cache(found["config"], view), observed_flow_cache(cfg, view))
        states[name], configs[name] = found["state"], found["config"]
    ran = [m for m in record if "loss" in record[m]]
    if not ran:
        raise ClflowError(
            "no material hypothesis could be simulated: " + "; ".join(f"{m}: {r['failed']}" for m, r in record.items())
        )
    chosen = min(ran, key=lambda m: record[m]["loss"])
    summary = {"chosen": chosen, "hypotheses": record}
    atomic_write_text(cfg.output / "hypotheses.json", json.dumps(summary, indent=2))
    log.info("material hypotheses: %s fits best (%s)", chosen, ", ".join(f"{m} {record[m]['loss']:.4g}" for m in ran))
    return dataclasses.replace(configs[chosen], output=cfg.output), states[chosen], summary


__all__ = [
    "choose_material",
    "hypotheses",
    "hypothesis_config",
    "hypothesis_name",
    "search_hypothesis",
    "serial_hypotheses",
]


def hypotheses_on_ray(**ray_options) -> Callable:
    """A ``search_all`` of clflow.pipeline.hypotheses.choose_material (``clflow optimize
    --parallel``): each hypothesis' search a Ray task (clflow.parallel.map_on_ray), its
    samples shown as it finishes."""
    from clflow.parallel import map_on_ray

    def search_all(
        cfg, resume: bool = False, progress: Callable[[str, dict], None] | None = None, force_video: bool = False
    ) -> list[dict]:
        combinations = hypotheses(cfg)
        materials = [hypothesis_name(cfg, h) for h in combinations]

        def finished(index: int, found: dict) -> None:
            for i, row in enumerate(found["state"].search if found["state"] is not None and progress else []):
                progress(materials[index], {**row, "phase": "search", "iteration": i})

        return map_on_ray(
            search_hypothesis, [(cfg, h, resume, None, force_video) for h in combinations], done=finished, **ray_options
        )

    return search_all
