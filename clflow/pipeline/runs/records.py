"""What a run reads besides its config: an optimisation's params.json applied to a config,
and every file a config names."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from clflow.errors import InputError


def read_params_record(path: str | Path, cfg):
    """The material parameters, density and initial velocity of an optimisation's
    ``params.json`` applied to ``cfg`` (a SceneConfig of the same material): returns the
    config with that velocity (m/s), the parameter overrides (SI; ``density`` in kg/m^3) and
    the substeps per frame the optimiser's final evaluation needed (1 where the record,
    older or of another frame rate, does not say). A record of several objects (its
    ``objects`` by name) goes into each object's material and velocity; no overrides then."""
    from clflow.fileio import read_json

    record = read_json(path, "params file", "expected the params.json clflow optimize writes")
    several = isinstance(record, dict) and "objects" in record
    if several != (len(cfg.objects) > 1):
        what = "several objects" if several else "one object"
        raise InputError(f"{path} holds the parameters of {what}; {cfg.source} simulates {len(cfg.objects)}")
    if several:
        objects = [_object_from_record(path, record["objects"], obj) for obj in cfg.objects]
        return cfg.with_objects(objects), {}, _record_substeps(path, record, cfg)
    missing = [key for key in ("parameters", "density") if not isinstance(record, dict) or key not in record]
    if missing:
        raise InputError(
            f"{path} lacks {' and '.join(repr(k) for k in missing)}: not a params.json of clflow optimize "
            f"(it writes parameters, density and velocity)"
        )
    velocity = _checked_material(path, record, cfg.object)
    overrides = {**record["parameters"], "density": record["density"]}
    return cfg.with_object(velocity=velocity), overrides, _record_substeps(path, record, cfg)


def _checked_material(path, record: dict, obj) -> tuple[float, float, float]:
    """Check one object's entry of a params.json (``record``: material, parameters, density,
    velocity) against the config's object ``obj`` before any work; returns its velocity (m/s)."""
    from clflow.materials import DENSITY, validate_params
    from clflow.scene.config.settings import SINGLE_OBJECT

    where = str(path) if obj.key == SINGLE_OBJECT else f"{path}: object {obj.name!r}"
    if not isinstance(record.get("parameters"), dict):
        raise InputError(f"{where}: 'parameters' is not a table of numbers")
    if record.get("material") != obj.material.type:
        raise InputError(f"{where} is for {record.get('material')!r}, the config simulates {obj.material.type!r}")
    validate_params(obj.material.type, record["parameters"], where)  # as the config's, before any work
    DENSITY.check(record["density"], where)
    velocity = record.get("velocity", list(obj.velocity))  # older records have none
    if not (
        isinstance(velocity, list)
        and len(velocity) == 3
        and all(isinstance(v, (int, float)) and math.isfinite(v) for v in velocity)
    ):
        raise InputError(f"{where}: velocity must be a list of 3 finite numbers (m/s), got {velocity!r}")
    return tuple(float(v) for v in velocity)


def _object_from_record(path, records, obj):
    """The config's object ``obj`` (a SceneObject) with its material parameters, density and
    velocity from ``records`` (params.json's ``objects``: name -> entry)."""
    record = records.get(obj.name) if isinstance(records, dict) else None
    if not isinstance(record, dict) or "density" not in record:
        listed = ", ".join(records) if isinstance(records, dict) else "none"
        raise InputError(f"{path} lacks the object {obj.name!r} of the config, or its density (it lists {listed})")
    velocity = _checked_material(path, record, obj)
    parameters = {**obj.material.parameters, **record["parameters"]}
    material = dataclasses.replace(obj.material, parameters=parameters, density=float(record["density"]))
    return dataclasses.replace(obj, material=material, velocity=velocity)


def _record_substeps(path, record: dict, cfg) -> int:
    """The substeps per frame of a params.json at the config's frame rate (1 if it does not say)."""
    substeps = record.get("substeps", 1)
    if not (isinstance(substeps, int) and substeps >= 1):
        raise InputError(f"{path}: substeps must be a whole number >= 1, got {substeps!r}")
    if record.get("fps", cfg.simulation.fps) != cfg.simulation.fps:  # the same time step at another frame rate
        substeps = max(1, math.ceil(substeps * record["fps"] / cfg.simulation.fps - 1e-9))
    return substeps


def input_files(cfg) -> list[Path]:
    """Every file or folder a scene config ``cfg`` reads (the config itself, the splats, the
    videos, masks, camera files ...): the Path values of its settings, at any depth, but its
    output folder."""
    found: list[Path] = []

    def visit(value, name: str = "") -> None:
        if isinstance(value, Path) and name != "output":
            found.append(value)
        elif dataclasses.is_dataclass(value):
            for field in dataclasses.fields(value):
                visit(getattr(value, field.name), field.name)
        elif isinstance(value, (list, tuple)):
            for item in value:
                visit(item, name)

    visit(cfg)
    return found


__all__ = ["input_files", "read_params_record"]
