"""What a run reads besides its config: an optimisation's params.json applied to a config,
and every file a config names."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from clflow.errors import InputError


def read_params_record(path: str | Path, cfg):
    """An optimisation's ``params.json`` applied to ``cfg`` (a SceneConfig of the same
    objects and materials): returns the config with each object's material parameters,
    density (kg/m^3) and initial velocity (m/s) from the record, and the substeps per frame
    the optimiser's final evaluation needed (1 where the record, older or of another frame
    rate, does not say). The record has the config's form: one object's entry at the top,
    several objects' under ``objects`` by name."""
    from clflow.fileio import read_json
    from clflow.scene.config import object_entries

    record = read_json(path, "params file", "expected the params.json clflow optimize writes")
    try:
        entries = object_entries(cfg.objects, record)
    except ValueError as exc:
        raise InputError(f"{path} {exc}") from None
    objects = [_object_from_entry(path, entry, obj) for entry, obj in zip(entries, cfg.objects)]
    return cfg.with_objects(objects), _record_substeps(path, record, cfg)


def _object_from_entry(path, entry, obj):
    """The config's object ``obj`` (a SceneObject) with the material parameters, density and
    velocity of its ``entry`` of a params.json (what the record holds there, checked before
    any work against the config's material)."""
    from clflow.materials import DENSITY, validate_params
    from clflow.scene.config.settings import SINGLE_OBJECT

    where = str(path) if obj.key == SINGLE_OBJECT else f"{path}: object {obj.name!r}"
    missing = [key for key in ("parameters", "density") if not isinstance(entry, dict) or key not in entry]
    if missing:
        raise InputError(
            f"{where} lacks {' and '.join(repr(k) for k in missing)}: not a params.json of clflow optimize "
            f"(it writes parameters, density and velocity)"
        )
    if not isinstance(entry["parameters"], dict):
        raise InputError(f"{where}: 'parameters' is not a table of numbers")
    if entry.get("material") != obj.material.type:
        raise InputError(f"{where} is for {entry.get('material')!r}, the config simulates {obj.material.type!r}")
    validate_params(obj.material.type, entry["parameters"], where)  # as the config's, before any work
    DENSITY.check(entry["density"], where)
    velocity = entry.get("velocity", list(obj.velocity))  # older records have none
    if not (
        isinstance(velocity, list)
        and len(velocity) == 3
        and all(isinstance(v, (int, float)) and math.isfinite(v) for v in velocity)
    ):
        raise InputError(f"{where}: velocity must be a list of 3 finite numbers (m/s), got {velocity!r}")
    parameters = {**obj.material.parameters, **{k: float(v) for k, v in entry["parameters"].items()}}
    material = dataclasses.replace(obj.material, parameters=parameters, density=float(entry["density"]))
    return dataclasses.replace(obj, material=material, velocity=tuple(float(v) for v in velocity))


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
