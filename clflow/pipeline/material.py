"""Stage 2 of the pipeline: a config whose ``material.type`` is ``query`` gets its material
type, density and initial parameters from the material query (clflow.query)."""

from __future__ import annotations

import dataclasses
import logging

from clflow.errors import InputError
from clflow.materials import get_material, validate_params
from clflow.scene.config import VELOCITY, VELOCITY_COMPONENTS, SceneConfig

log = logging.getLogger(__name__)


def resolve_material(cfg: SceneConfig) -> SceneConfig:
    """The config with concrete materials.

    For ``type: query`` the query (offline knowledge base or a foundation model), or the
    record of an earlier ``clflow query`` (``material.query.result``), decides the type,
    density and parameters; parameters and density written in the config override the
    query's. The record is saved as ``output/material_query.json`` (with several objects one
    per object that asks: ``output/material_query.NAME.json``). Other configs are returned
    unchanged."""
    if not any(o.material.type == "query" for o in cfg.objects):
        return cfg
    if len(cfg.objects) == 1:
        return cfg.with_object(material=_resolved(cfg, cfg.object, "material_query.json"))
    return cfg.with_objects(
        dataclasses.replace(o, material=_resolved(cfg, o, f"material_query.{o.name}.json"))
        if o.material.type == "query"
        else o
        for o in cfg.objects
    )


def _resolved(cfg: SceneConfig, obj, record: str):
    """The MaterialConfig the query gives ``obj`` (a SceneObject of ``type: query``), its
    record saved as ``output/record``."""
    mat, key = obj.material, obj.material_key
    if mat.query_result is not None:
        from clflow.query.result import load_query_result

        result = load_query_result(mat.query_result)
    else:
        from clflow.query import ModelConfig
        from clflow.query.backends import query_material

        asked_by = f"{cfg.source}: {key}.query.backend: openai"  # the config has no --llm-url and --model
        model_config = ModelConfig.resolve(asked_by=asked_by) if mat.query_backend == "openai" else None
        result = query_material(
            mat.query_image, prompt=mat.query_prompt, backend=mat.query_backend, model_config=model_config
        )
    for warning in result.warnings:
        log.warning("material query%s: %s", "" if len(cfg.objects) == 1 else f" of {obj.name}", warning)
    cfg.output.mkdir(parents=True, exist_ok=True)
    result.save(cfg.output / record)
    where = f"{cfg.source}: {key}.parameters (material {result.material} from the query)"
    params = validate_params(result.material, {**result.parameters, **mat.parameters}, where)
    known = set(get_material(result.material).param_names) | {"density", VELOCITY, *VELOCITY_COMPONENTS}
    if len(cfg.objects) == 1:
        named = [*cfg.optimize.parameters, *cfg.ground_truth]
    else:  # this object's: OBJECT.PARAM
        prefix = f"{obj.name}."
        named = [n[len(prefix) :] for n in (*cfg.optimize.parameters, *cfg.ground_truth) if n.startswith(prefix)]
    wrong = [n for n in named if n not in known]
    if wrong and not cfg.optimize.materials:  # hypotheses: checked against them (scene config)
        raise InputError(
            f"{cfg.source}: the query chose {result.material}, which has no parameter "
            f"{', '.join(map(repr, wrong))} (optimize.parameters / evaluation.ground_truth)"
        )
    density = mat.density if mat.density is not None else result.density
    log.info(
        "material query%s: %s, density %g kg/m^3, %s",
        "" if len(cfg.objects) == 1 else f" of {obj.name}",
        result.material,
        density,
        params,
    )
    return dataclasses.replace(mat, type=result.material, parameters=params, density=density)


__all__ = ["resolve_material"]
