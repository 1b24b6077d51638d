"""docs/scene_config.md stays true: its examples parse, and it names every key the parser takes."""

import re
from pathlib import Path

import pytest
import yaml

from clflow.scene.config import parse_config

ROOT = Path(__file__).resolve().parents[2]
DOC = (ROOT / "docs" / "scene_config.md").read_text()
BLOCKS = [yaml.safe_load(b) for b in re.findall(r"```yaml\n(.*?)```", DOC, re.S)]


@pytest.fixture
def folder(tmp_path):
    """The files the examples name: scene.ply, guidance/, object.png, cameras.json."""
    from clflow_datasets.demo import DEMO
    from clflow_datasets.synthetic import Resolution, write_scene

    write_scene(tmp_path, DEMO, Resolution(object_detail=3, floor_side=3))
    (tmp_path / "guidance").mkdir()
    (tmp_path / "object.png").write_bytes(b"")  # only its existence is checked when parsing
    (tmp_path / "cameras.json").write_text("[]")
    return tmp_path


def test_the_complete_example_parses_with_its_values(folder):
    cfg = parse_config(BLOCKS[0], "scene.yaml", folder)
    assert (cfg.simulation.frames, cfg.simulation.fps, cfg.simulation.grid_resolution) == (12, 24.0, 24)
    assert cfg.material.model == "fixed_corotated" and cfg.material.parameters["youngs_modulus"] == 2000.0
    assert cfg.optimize.horizon_start == 4 and cfg.optimize.learning_rates == {"youngs_modulus": 0.2}
    assert [c.mode for c in cfg.colliders] == ["sticky", "separate"] and cfg.colliders[1].end == 0.5
    assert cfg.forces[0].kind == "acceleration" and cfg.forces[0].end == 0.12


def test_the_alternative_forms_parse(folder):
    data = dict(BLOCKS[0])
    alt = BLOCKS[1]
    data["object"] = {**data["object"], "select": alt["object"]["select"]}
    data["material"], data["forces"], data["camera"] = alt["material"], alt["forces"], alt["camera"]
    data["simulation"] = {**data["simulation"], **alt["simulation"]}
    cfg = parse_config(data, "scene.yaml", folder)
    assert cfg.selection.region.kind == "sphere" and cfg.material.type == "query"
    assert cfg.material.density == 1100.0 and cfg.forces[0].region.kind == "all" and cfg.forces[0].kind == "force"
    assert cfg.camera.cameras_file == (folder / "cameras.json").resolve() and cfg.simulation.substep_dt == 0.0005
    # without a mask file the select block has only one shape: the mask form is a comment
    assert "mask: object.npy" in DOC


def test_every_key_of_the_parser_is_documented():
    source = (ROOT / "clflow" / "scene" / "config.py").read_text()
    keys = set()
    for line in source.splitlines():
        if "r.section(" in line:  # the known keys: a tuple of strings, the call's last argument
            for tuple_text in re.findall(r'\(("\w+"(?:, "\w+")*,?)\)', line):
                keys.update(re.findall(r'"(\w+)"', tuple_text))
    keys.update(re.findall(r'"(\w+)"', re.search(r"TOP_KEYS = \(([^)]*)\)", source).group(1)))
    assert len(keys) > 50
    missing = sorted(k for k in keys if not re.search(rf"\b{k}\b", DOC))
    assert not missing, f"docs/scene_config.md does not mention {missing}"
