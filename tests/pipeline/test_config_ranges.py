"""Every numeric key of a scene config at the extremes (1e308, -1e308, 0, -1, 1e-308, 1e15,
10^400): refused by the reader in one line naming the key, or taken; 1e308 either way taken
only where it means something. The bulk through parse_config, a handful through the CLI."""

import copy
import re
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from clflow.errors import InputError
from clflow.scene.config import parse_config, schema
from clflow_cli.main import cli
from tests.pipeline._scenes import two_objects_config

EXTREMES = (1e308, -1e308, 0, -1, 1e-308, 1e15, 10**400)

#: keys that take +-1e308 besides the material parameters (and their ground truth and
#: bounds), whose registry ranges are open above (a yield stress of 1e308 never yields; the
#: pre-flight refuses a modulus that needs too many substeps): an end that never comes, a
#: friction that sticks, a budget without a limit, a search box of all the typical range, a
#: fixed substep above the stable step (the pre-flight refuses it, naming the stable step)
HUGE_TAKEN = re.compile(
    r"^(forces\[\d\]\.end|boundaries\.colliders\[0\]\.end|boundaries\.(ground|colliders\[0\])\.friction"
    r"|optimize\.budget\.seconds|optimize\.search\.decades|simulation\.substep_dt)$"
)


def one_object(demo: Path) -> dict:
    """The demo's config with every optional numeric key given: fill, velocity, a sphere
    stage, a slip ground and a collider, a fixed substep, the search, starts, budget, bounds,
    velocity phase and the ground truth's velocity."""
    data = yaml.safe_load((demo / "config.yaml").read_text())
    data["splats"] = str(demo / "scene.ply")
    data["video"] = str(demo / "guidance")
    data["object"].update(fill={"enabled": True, "spacing": 0.02, "per_axis": 1}, velocity=[0.0, 0.0, 0.0])
    data["forces"].append({"region": {"sphere": {"center": [0.0, 0.2, 0.0], "radius": 0.1}}, "force": [0, 1, 0]})
    data["boundaries"] = {
        "ground": {"height": 0.0, "mode": "slip", "friction": 0.3},
        "colliders": [{"point": [0.3, 0, 0], "normal": [-1, 0, 0], "friction": 0.1, "start": 0.0, "end": 0.5}],
    }
    data["simulation"].update(substep_dt=0.001, flip=0.5, gravity=[0.0, -9.81, 0.0], max_substeps=2000)
    data["camera"]["up"] = [0.0, 1.0, 0.0]
    data["optimize"] = {
        "parameters": ["youngs_modulus", "velocity"],
        "learning_rates": {"youngs_modulus": 0.2, "velocity": 0.1},
        "iterations": 5,
        "horizon": {"start": 2, "step": 1},
        "final_rate": 0.1,
        "method": "levenberg_marquardt",
        "search": {
            "samples": 8, "decades": 2.0, "frames": 4, "starts": 2, "start_iterations": 2, "refine": 2,
            "object_samples": 4, "grid_resolution": 11,
        },
        "bounds": {"youngs_modulus": [1.0e3, 1.0e5]},
        "estimate_velocity": {"frames": 3, "iterations": 2},
        "budget": {"seconds": 600.0, "max_grid_resolution": 0},
    }  # fmt: skip
    data["evaluation"]["ground_truth"].update(density=1000.0, velocity=[0.0, 0.0, 0.0])
    return data


def variants(demo: Path) -> list[dict]:
    """The keys the first config cannot hold besides its own: a sphere or PLY selection, a
    camera file's index; and a config of several objects (tests/pipeline/_scenes.py)."""
    base = one_object(demo)
    sphere, ply, camera = copy.deepcopy(base), copy.deepcopy(base), copy.deepcopy(base)
    sphere["object"]["select"] = {"sphere": {"center": [0.0, 0.1, 0.0], "radius": 0.15}}
    ply["object"]["select"] = {"ply": str(demo / "scene.ply"), "tolerance": 0.001}
    (demo / "cameras.json").write_text("[]")  # read when the scene is built
    camera["camera"] = {"file": str(demo / "cameras.json"), "index": 0}
    two = two_objects_config(demo / "two")
    two["optimize"] = {
        "parameters": ["jelly.youngs_modulus", "heap.friction_angle", "jelly.velocity"],
        "learning_rates": {"jelly.velocity": 0.1},
        "bounds": {"heap.friction_angle": [20, 45]},
    }
    two["evaluation"] = {"ground_truth": {"jelly.youngs_modulus": 2.0e4, "jelly.velocity": [0.0, -0.5, 0.0]}}
    return [base, sphere, ply, camera, two]


def numeric_leaves(node, parts: tuple = ()):
    """(the keys and indices down to it, the dotted key as messages write it) of each number."""
    if isinstance(node, dict):
        for key, value in node.items():
            yield from numeric_leaves(value, (*parts, key))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            yield from numeric_leaves(value, (*parts, i))
    elif isinstance(node, (int, float)) and not isinstance(node, bool):
        yield parts, "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in parts).lstrip(".")


def with_value(data: dict, parts: tuple, value) -> dict:
    data = copy.deepcopy(data)
    node = data
    for part in parts[:-1]:
        node = node[part]
    node[parts[-1]] = value
    return data


def name_of(parts: tuple) -> str:
    """The key's own name: ``velocity`` of ``object.velocity[1]``."""
    return next(p for p in reversed(parts) if isinstance(p, str)).rpartition(".")[2]


@pytest.fixture(scope="module")
def configs(quick_demo):
    return variants(quick_demo)


def test_the_configs_hold_every_numeric_key_of_the_reader(configs):
    """The keys the schema declares numbers (integer, number, vec3), but video.generate's
    (tests/generate/test_config.py: they need a model folder)."""
    read = {
        key.name.rpartition(".")[2]
        for section in schema.SECTIONS.values()
        if section is not schema.GENERATE
        for key in section.keys
        if key.kind in ("integer", "number", "vec3")
    }
    given = {name_of(parts) for data in configs for parts, _ in numeric_leaves(data)}
    assert read - given == set()


def test_every_numeric_key_at_the_extremes_is_refused_in_one_line_or_means_something(configs, quick_demo):
    taken_huge = set()
    for data in configs:
        for parts, key in numeric_leaves(data):
            for value in EXTREMES:
                try:
                    parse_config(with_value(data, parts, value), "scene.yaml", quick_demo)
                except InputError as exc:
                    message = str(exc)
                    assert "\n" not in message and message.startswith("scene.yaml: "), (key, value, message)
                    assert name_of(parts) in message, (key, value, message)
                    continue
                if value in (1e308, -1e308, 10**400):
                    taken_huge.add(key)
    material = re.compile(r"^((objects\[\d\]\.)?material\.parameters|evaluation\.ground_truth|optimize\.bounds)\.")
    unexpected = sorted(k for k in taken_huge if not HUGE_TAKEN.match(k) and not material.match(k))
    assert not unexpected, f"keys that take 1e308 or -1e308: {unexpected}"


def one_error_line(args, pattern: str) -> str:
    """``clflow ARGS`` in-process: exit 1, one error line matching ``pattern``, no traceback."""
    res = CliRunner().invoke(cli, [str(a) for a in args])
    errors = [line for line in res.output.splitlines() if line.startswith("Error")]
    assert res.exit_code == 1 and len(errors) == 1, res.output
    assert re.search(pattern, errors[0]), errors[0]
    assert "Traceback" not in res.output
    return res.output


# the CLI's part: the three keys first found, then what the fuzz found (each a traceback before); refused
# before the scene is loaded
REFUSED = [
    ("scene.scale=1e308", r"scene.scale: must be in \[1e-06, 1000\], got 1e\+308$"),
    ("boundaries.ground.height=1e308", r"boundaries.ground.height: must be in \[-10000, 10000\], got 1e\+308$"),
    ("simulation.domain.max=[1e308,1e308,1e308]", r"simulation.domain.max: must be 3 numbers in \[-10000, 10000\]"),
    ("object.fill.spacing=1e308", r"object.fill.spacing: must be in \[1e-06, 10000\], got 1e\+308$"),
    ("object.fill.spacing=1e-308", r"object.fill.spacing: must be in \[1e-06, 10000\], got 1e-308$"),
    ("object.fill.per_axis=1000000000000000", r"object.fill.per_axis: must be an integer in \[1, 16\]"),
    ("simulation.grid_resolution=1000000000000000", r"simulation.grid_resolution: must be an integer in \[11, 100000\]"),
    ("simulation.fps=1e-308", r"simulation.fps: must be in \[0.001, 1e\+06\], got 1e-308$"),
    ("simulation.gravity=[0,1e15,0]", r"simulation.gravity: must be 3 numbers in \[-1e\+06, 1e\+06\]"),
    ("forces.0.acceleration=[0,1e15,0]", r"forces\[0\].acceleration: must be 3 numbers in \[-1e\+06, 1e\+06\]"),
    ("simulation.substep_dt=1e-308", r"simulation.substep_dt: must be >= 1e-09, got 1e-308$"),
    ("material.density=1e-308", r"material.density: density \(rho\) = 1e-308 kg/m\^3 is outside the valid range"),
    ("object.velocity=[1e308,0,0]", r"object.velocity: must be 3 numbers in \[-10000, 10000\]"),
    ("object.velocity=[1" + "0" * 400 + ",0,0]", r"object.velocity\[0\]: an integer of 401 digits is beyond any"),
]  # fmt: skip


@pytest.mark.parametrize("item, message", REFUSED, ids=[item.partition("=")[0] for item, _ in REFUSED])
def test_extremes_through_the_cli_are_one_line_before_the_scene(quick_demo, tmp_path, monkeypatch, item, message):
    def loaded(*args, **kwargs):
        raise AssertionError("the scene was loaded before the refusal")

    monkeypatch.setattr("clflow.pipeline.forward.load_scene_objects", loaded)
    args = ["simulate", quick_demo / "config.yaml", "--set", "simulation.frames=1", "--preview", "none"]
    output = one_error_line(
        [*args, "-o", tmp_path / "s", "--set", item], rf"^Error: --set {re.escape(item)}: {message}"
    )
    assert len(output.strip().splitlines()) == 1 and not (tmp_path / "s").exists()


@pytest.mark.parametrize(
    "item", ["forces.0.end=1e308", "boundaries.ground.friction=1e308", "object.velocity=[1e-308,0,0]"]
)
def test_extremes_that_mean_something_run(quick_demo, tmp_path, item):
    args = ["simulate", quick_demo / "config.yaml", "--set", "simulation.frames=1", "--preview", "none"]
    res = CliRunner().invoke(cli, [str(a) for a in [*args, "-o", tmp_path / "s", "--set", item]])
    assert res.exit_code == 0, res.output
