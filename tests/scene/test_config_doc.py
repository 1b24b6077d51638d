"""docs/scene_config.md stays true: its examples load, and its key tables are the schema's, which
the parser reads."""

import dataclasses
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from clflow.mpm.constants import COLLIDER_MODES
from clflow.scene.config import doc as config_doc
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
    assert cfg.objects[0].selection.region.kind == "box" and cfg.objects[0].fill.spacing == 0.01
    assert (
        cfg.objects[0].material.model == "fixed_corotated"
        and cfg.objects[0].material.parameters["youngs_modulus"] == 2000.0
    )
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
    assert cfg.objects[0].selection.region.kind == "sphere" and cfg.objects[0].selection.region.radius == 0.12
    assert (
        cfg.objects[0].material.type == "query"
        and cfg.objects[0].material.query_image == (folder / "object.png").resolve()
    )
    assert cfg.objects[0].material.density == 1100.0 and cfg.objects[0].material.parameters == {"poissons_ratio": 0.4}
    assert cfg.forces[0].region.kind == "all" and cfg.forces[0].kind == "force"
    assert math.isinf(cfg.forces[0].end)
    assert cfg.camera.cameras_file == (folder / "cameras.json").resolve() and cfg.simulation.substep_dt == 0.0005

    cfg = _load(folder, _merge(base, yaml.safe_load(BLOCKS[2])))
    assert cfg.objects[0].selection.mask == (folder / "object.npy").resolve()
    assert cfg.objects[0].material.query_result == (folder / "object.material.json").resolve()
    assert cfg.objects[0].material.query_image is None and cfg.objects[0].material.density is None


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


def test_the_key_tables_are_the_schema_s():
    """The tables between the markers are what clflow.scene.config.doc writes (run it after
    changing a key: python -m clflow.scene.config.doc)."""
    assert config_doc.written(DOC) == DOC


def test_every_section_has_one_table():
    tables = [config_doc.TOP if p == "" else p for p in schema.SECTIONS]
    assert sorted(config_doc.documented_sections(DOC)) == sorted(tables)


def _normal(path: str) -> str:
    """A section's path as the schema names it: any index [i], any object NAME (an object's
    select, fill and material: as the one object's), any camera's."""
    path = re.sub(r"\[\d+\]", "[i]", path)
    path = re.sub(r"^objects\.\w+", "objects.NAME", path)
    path = re.sub(r"^objects\.NAME\.(?=material)", "", path)  # an object's parts: as the one object's
    path = re.sub(r"^objects\.NAME\.", "object.", path)
    return re.sub(r"^camera\[i\]", "camera", path)


def test_every_key_the_reader_takes_is_in_the_doc(folder, monkeypatch):
    """The reader's allowed keys of each section it reads in the examples are the schema's, so
    the tables' (the examples read every section but video.generate's: tests/generate)."""
    from clflow.scene.config.reader import Reader

    seen = {}
    section = Reader.section

    def recorded(self, data, path, known):
        seen.setdefault(_normal(path), set()).add(tuple(known))
        return section(self, data, path, known)

    monkeypatch.setattr(Reader, "section", recorded)
    test_the_complete_example_loads_with_its_values(folder)
    test_the_alternative_forms_load(folder)
    test_the_objects_example_loads(folder)
    # the objects as a mapping, and a sphere for a force stage's region
    base = {k: v for k, v in yaml.safe_load(BLOCKS[0]).items() if k not in ("object", "material", "evaluation")}
    base["optimize"] = {}
    base["forces"][0]["region"] = {"sphere": {"center": [0.0, 0.2, 0.0], "radius": 0.1}}
    _load(folder, {**base, "objects": {o.pop("name"): o for o in yaml.safe_load(BLOCKS[3])["objects"]}})
    table_keys = _table_keys()
    for path, knowns in seen.items():
        if path == "object.select":  # a box or sphere is read as a region too, after its select's keys
            knowns -= {schema.REGION.known}
        assert knowns == {schema.SECTIONS[path].known}, path
        for key in schema.SECTIONS[path].known:
            dotted = f"{path}.{key}" if path else key
            assert dotted in table_keys or any(k.startswith(dotted + ".") for k in table_keys), dotted
    assert set(schema.SECTIONS) - set(seen) == {"video", "video.generate"}


def _table_keys() -> set[str]:
    """The keys of the tables between the markers, as their rows name them."""
    return {k for m in config_doc.TABLE.finditer(DOC) for k in re.findall(r"^\| `([^`]+)` \|", m.group(3), re.M)}


def test_every_documented_key_is_the_schema_s():
    keys = {f"{s.path}.{k.name}" if s.path else k.name for s in schema.SECTIONS.values() for k in s.keys}
    assert _table_keys() == {k for k in keys if k.count(".") == 0 or k.rpartition(".")[0] in schema.SECTIONS}


def test_every_option_is_documented():
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
