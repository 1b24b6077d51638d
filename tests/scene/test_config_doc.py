"""docs/scene_config.md stays true: its examples load, and it names every key the parser takes."""

import dataclasses
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from clflow.mpm.constants import COLLIDER_MODES
from clflow.scene.config import load_config, schema
from clflow.scene.config import settings as config_settings

ROOT = Path(__file__).resolve().parents[2]
DOC = (ROOT / "docs" / "scene_config.md").read_text()
BLOCKS = re.findall(r"```yaml\n(.*?)```", DOC, re.S)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """The files the examples name: scene.ply, guidance/, object.png, object.npy,
    object.material.json, cameras.json (parsing checks only that they exist)."""
    from clflow_datasets.demo import DEMO, QUICK
    from clflow_datasets.synthetic import write_scene

    path = tmp_path_factory.mktemp("scene_config_doc")
    write_scene(path, DEMO, QUICK)
    (path / "guidance").mkdir()
    (path / "object.png").write_bytes(b"")
    np.save(path / "object.npy", np.arange(4))
    (path / "object.material.json").write_text("{}")
    (path / "cameras.json").write_text("[]")
    return path


def _load(folder: Path, data, name: str = "scene.yaml"):
    path = folder / name
    path.write_text(json.dumps(data) if name.endswith(".json") else yaml.safe_dump(data))
    return load_config(path)


def _merge(base: dict, alt: dict) -> dict:
    """``base`` with the sections of ``alt``: object.select and camera replaced, material and
    forces replaced, simulation keys updated."""
    out = dict(base)
    for key, value in alt.items():
        if key == "object":
            out["object"] = {**base["object"], "select": value["select"]}
        elif key == "simulation":
            out["simulation"] = {**base["simulation"], **value}
        else:
            out[key] = value
    return out


def test_the_doc_has_the_complete_example_and_the_alternatives():
    assert len(BLOCKS) == 5  # the complete example, two of alternatives, several objects and their identification


def test_the_complete_example_loads_with_its_values(folder):
    (folder / "scene.yaml").write_text(BLOCKS[0])
    cfg = load_config(folder / "scene.yaml")
    sim = cfg.simulation
    assert (sim.frames, sim.fps, sim.grid_resolution, sim.substep_dt) == (12, 24.0, 24, None)
    assert sim.domain_lower == (-0.5, -0.2, -0.5) and sim.gravity == (0.0, -9.81, 0.0)
    assert cfg.splats == (folder / "scene.ply").resolve() and cfg.video == (folder / "guidance").resolve()
    assert cfg.selection.region.kind == "box" and cfg.fill.spacing == 0.01
    assert cfg.material.model == "fixed_corotated" and cfg.material.parameters["youngs_modulus"] == 2000.0
    assert cfg.forces[0].kind == "acceleration" and cfg.forces[0].end == 0.12
    assert [c.mode for c in cfg.colliders] == ["sticky", "separate"] and cfg.colliders[1].end == 0.5
    assert cfg.camera.position == (0.25, 0.45, 0.75) and cfg.camera.width == 96
    assert cfg.optimize.horizon_start == 4 and cfg.optimize.learning_rates == {"youngs_modulus": 0.2}
    assert cfg.ground_truth["youngs_modulus"] == 20000.0 and cfg.output == (folder / "results").resolve()
    # the same as JSON
    assert _load(folder, yaml.safe_load(BLOCKS[0]), "scene.json") == dataclasses.replace(
        cfg, source=folder / "scene.json"
    )


def test_the_alternative_forms_load(folder):
    base = yaml.safe_load(BLOCKS[0])
    cfg = _load(folder, _merge(base, yaml.safe_load(BLOCKS[1])))
    assert cfg.selection.region.kind == "sphere" and cfg.selection.region.radius == 0.12
    assert cfg.material.type == "query" and cfg.material.query_image == (folder / "object.png").resolve()
    assert cfg.material.density == 1100.0 and cfg.material.parameters == {"poissons_ratio": 0.4}
    assert cfg.forces[0].region.kind == "all" and cfg.forces[0].kind == "force"
    assert math.isinf(cfg.forces[0].end)
    assert cfg.camera.cameras_file == (folder / "cameras.json").resolve() and cfg.simulation.substep_dt == 0.0005

    cfg = _load(folder, _merge(base, yaml.safe_load(BLOCKS[2])))
    assert cfg.selection.mask == (folder / "object.npy").resolve()
    assert cfg.material.query_result == (folder / "object.material.json").resolve()
    assert cfg.material.query_image is None and cfg.material.density is None


def test_the_objects_example_loads(folder):
    base = yaml.safe_load(BLOCKS[0])
    for key in ("object", "material", "evaluation"):  # objects replace them; their parameters are OBJECT.PARAM
        base.pop(key)
    base["optimize"].pop("parameters")
    base["optimize"].pop("learning_rates")
    base["optimize"].pop("bounds")
    base["optimize"].pop("estimate_velocity", None)
    cfg = _load(folder, {**base, **yaml.safe_load(BLOCKS[3])})
    jelly, heap = cfg.objects
    assert cfg.object_names == ("jelly", "heap") and jelly.key == "objects.jelly"
    assert jelly.velocity == (0.0, -0.5, 0.0) and jelly.material.density == 800.0
    assert heap.material.type == "sand" and heap.material.parameters["friction_angle"] == 35.0
    assert heap.fill.spacing == 0.01 and jelly.fill.spacing is None
    identify = yaml.safe_load(BLOCKS[4])  # each object's parameters, OBJECT.PARAM
    cfg = _load(folder, {**base, **yaml.safe_load(BLOCKS[3]), **identify})
    assert cfg.optimize.parameters == ("jelly.youngs_modulus", "heap.friction_angle")
    assert cfg.optimize.bounds == {"heap.friction_angle": (20.0, 45.0)}
    assert cfg.ground_truth == {"jelly.youngs_modulus": 6.0e4, "heap.friction_angle": 35.0}


def test_every_key_and_option_of_the_parser_is_documented():
    keys = {k.name.rpartition(".")[2] for section in schema.SECTIONS.values() for k in section.keys}
    assert {"splats", "grid_resolution", "per_axis", "fov_y_deg", "result", "final_rate"} <= keys
    missing = sorted(k for k in keys if not re.search(rf"`[^`\n]*\b{k}\b[^`\n]*`|^\s*-?\s*{k}:", DOC, re.M))
    assert not missing, f"docs/scene_config.md does not mention the keys {missing}"
    options = [
        *config_settings.UP_AXES,
        *COLLIDER_MODES,
        *config_settings.FLOW_METHODS,
        *config_settings.FLOW_LOSSES,
        *(m for ms in config_settings.MATERIAL_MODELS.values() for m in ms),
        "auto",
        "all",
        "query",
        "alpha",
        "none",
        "offline",
        "openai",
    ]
    assert not [o for o in options if o not in DOC], "an option value is missing from the doc"
