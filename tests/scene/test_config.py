"""Scene configs: a complete example parses; each bad config gets its own specific error."""

import copy
import dataclasses
import json
import math
import re
import time

import pytest

from clflow.errors import InputError
from clflow.scene.config import load_config, parse_config

GOOD = {
    "splats": "scene.ply",
    "scene": {"scale": 0.5, "up": "+z"},
    "object": {"select": {"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}, "fill": {"spacing": 0.02}},
    "material": {"type": "elastic", "parameters": {"youngs_modulus": 1e4}, "density": 500},
    "forces": [
        {"region": {"sphere": {"center": [0, 0.5, 0], "radius": 0.1}}, "force": [0, 0, 2], "start": 0, "end": 0.2}
    ],
    "boundaries": {
        "ground": {"height": 0.0, "mode": "slip", "friction": 0.3},
        "colliders": [{"point": [1, 0, 0], "normal": [-1, 0, 0], "mode": "sticky"}],
    },
    "simulation": {"grid_resolution": 32, "fps": 24, "frames": 12, "substep_dt": "auto"},
    "camera": {"position": [0, 1, 3], "look_at": [0, 0.5, 0], "width": 256, "height": 256},
    "optimize": {"parameters": ["youngs_modulus"], "learning_rates": {"youngs_modulus": 0.1}, "iterations": 5},
}


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "scene.ply").write_bytes(b"ply\n")
    return tmp_path


def parse(data, folder):
    return parse_config(data, "scene.yaml", folder)


def test_a_complete_config_parses_with_defaults(folder):
    cfg = parse(GOOD, folder)
    assert cfg.splats == folder / "scene.ply" and cfg.scale == 0.5 and cfg.up == "+z"
    assert cfg.objects[0].material.type == "elastic" and cfg.objects[0].material.density == 500.0
    assert cfg.objects[0].material.parameters == {"youngs_modulus": 1e4, "poissons_ratio": 0.3}
    assert cfg.forces[0].kind == "force" and cfg.forces[0].region.kind == "sphere"
    assert cfg.forces[0].end == 0.2 and cfg.colliders[0].normal == (0.0, 1.0, 0.0)
    assert cfg.colliders[1].mode == "sticky" and cfg.colliders[1].end == math.inf
    assert cfg.simulation.substep_dt is None and cfg.simulation.gravity == (0.0, -9.81, 0.0)
    assert cfg.flow.method == "dis" and cfg.optimize.iterations == 5
    assert cfg.output == (folder / "results").resolve()


def test_yaml_and_json_files(folder):
    import yaml

    (folder / "scene.yaml").write_text(yaml.safe_dump(GOOD))
    (folder / "scene.json").write_text(json.dumps(GOOD))
    from_json = load_config(folder / "scene.json")
    assert from_json.source == folder / "scene.json"
    assert load_config(folder / "scene.yaml") == dataclasses.replace(from_json, source=folder / "scene.yaml")
    (folder / "broken.yaml").write_text("material: [unclosed\n")
    with pytest.raises(InputError, match="broken.yaml: not valid YAML"):
        load_config(folder / "broken.yaml")
    with pytest.raises(InputError, match="config .*missing.yaml not found"):
        load_config(folder / "missing.yaml")


def edit(path, value):
    data = copy.deepcopy(GOOD)
    keys = path.split(".")
    node = data
    for key in keys[:-1]:
        node = node[int(key)] if isinstance(node, list) else node[key]
    if value is DELETE:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return data


DELETE = object()

BAD = [
    ("splats", "nope.ply", "scene.yaml: splats: file not found"),
    ("splats", DELETE, "splats: is required"),
    ("simulaton", {}, "simulaton: unknown key; known keys here: splats, scene"),
    ("simulation.frames", -3, "simulation.frames: must be an integer >= 1, got -3"),
    ("simulation.fps", "fast", "simulation.fps: must be a number, got 'fast'"),
    ("simulation.substep_dt", 0, r"simulation.substep_dt: must be >= 1e-09, got 0"),
    ("simulation.flip", 1.5, r"simulation.flip: must be in \[0, 1\], got 1.5"),
    ("simulation.flip", -0.1, r"simulation.flip: must be in \[0, 1\], got -0.1"),
    ("simulation.gravity", [0, -9.81], "simulation.gravity: must be a list of 3 finite numbers"),
    ("simulation.domain", {"min": [0, 0, 0], "max": [1, -1, 1]}, "simulation.domain: min .* must be below max"),
    ("scene.up", "up", "scene.up: must be one of"),
    ("scene.scale", 0, r"scene.scale: must be in \[1e-06, 1000\], got 0"),
    ("object.select", {}, "object.select: is required"),
    ("object.select", {"box": {"min": [0, 0, 0], "max": [1, 1, 1]}, "sphere": {}}, "object.select: give exactly one"),
    ("object.select", {"mask": "mask.npy"}, "object.select.mask: file not found"),
    ("object.fill.spacing", -0.1, r"object.fill.spacing: must be in \[1e-06, 10000\], got -0.1"),
    ("material.type", "lava", "material: unknown material 'lava'"),
    ("material.parameters", {"poissons_ratio": 0.5}, r"material: elastic: poissons_ratio \(nu\) = 0.5 is outside"),
    ("material.parameters", {"yield_stress": 10}, "material 'elastic' has no parameter 'yield_stress'"),
    ("material.density", -1, "material.density: must be > 0"),
    ("forces.0.force", [0, 0], "forces\\[0\\].force: must be a list of 3"),
    ("forces.0.end", -1, "forces\\[0\\].end: must be after start"),
    ("forces.0.acceleration", [0, 0, 1], "forces\\[0\\]: give exactly one of force"),
    ("forces.0.region", {"cube": 1}, "forces\\[0\\].region.cube: unknown key"),
    ("boundaries.ground.mode", "bouncy", "boundaries.ground.mode: must be one of sticky, slip, separate"),
    (
        "boundaries.colliders",
        [{"point": [0, 0, 0], "normal": [0, 0, 0]}],
        "boundaries.colliders\\[0\\].normal: must not be the zero",
    ),
    ("camera", {}, "camera: give a camera file"),
    ("camera.fov_y_deg", 200, r"camera.fov_y_deg: must be in \[1, 179\], got 200"),
    ("optimize.parameters", ["yield_stress"], "'yield_stress' is not a parameter of elastic"),
    ("optimize.learning_rates", {"poissons_ratio": 0.1}, "optimize.learning_rates.poissons_ratio: is not among"),
    ("video", "guide.mp4", "video: file or folder not found"),
    ("material.model", "stvk", "material.model: must be one of fixed_corotated, neo_hookean, got 'stvk'"),
    ("flow", {"preset": "slow"}, "flow.preset: must be one of ultrafast, fast, medium, fine, got 'slow'"),
    ("flow", {"confidence": "fb"}, "flow.confidence: must be one of none, forward_backward, got 'fb'"),
    ("flow", {"bias_correction": "yes"}, "flow.bias_correction: must be one of none, simulated, got 'yes'"),
    ("optimize.search", {"samples": 4, "starts": 5}, "optimize.search.starts: must not exceed search.samples"),
    ("optimize.search", {"samples": 4, "refine": -1}, "optimize.search.refine: must be an integer >= 0"),
    (
        "optimize.search",
        {"samples": 4, "starts": 2},
        "optimize.search.starts: several starts are polished by levenberg",
    ),
    ("flow", {"mask": "nope.png"}, "flow.mask: file not found"),
    ("scene.up", None, None),  # null takes the default
    ("camera.file", "scene.ply", "camera: with a camera file, position, look_at.* come from the file"),
    ("camera.index", 2, "camera.index: picks an entry of a camera file"),
    ("material.query", {"image": "x.png"}, "material.query: is only read with type: query"),
    (
        "material.parameters",
        {"youngs_modulus": "2e4"},
        "material.parameters.youngs_modulus: must be a number, got '2e4'",
    ),
    ("material.parameters", {"youngs_modulus": True}, "material.parameters.youngs_modulus: must be a number"),
    ("evaluation", {"ground_truth": {"density": -5.0}}, "evaluation.ground_truth: .*density"),
    ("simulation.grid_resolution", 9, r"simulation.grid_resolution: must be an integer in \[11, 100000\], got 9"),
    ("optimize.final_rate", 2, r"optimize.final_rate: must be in \[0, 1\], got 2"),
    (
        "material",
        {"type": "query", "query": {"image": "scene.ply", "backend": "gpt"}},
        "material.query.backend: must be one of offline, openai",
    ),
    ("object.velocity", [1.0, 2.0], r"object.velocity: must be a list of 3 finite numbers, got \[1.0, 2.0\]"),
    ("object.velocity", [float("nan"), 0, 0], "object.velocity: must be a list of 3 finite numbers, got \\[nan"),
    ("object.velocity", "fast", "object.velocity: must be a list of 3 finite numbers, got 'fast'"),
    ("object.velocity", ["1", "2", "3"], "object.velocity: must be a list of 3 finite numbers"),
    ("object.velocity", [True, 0, 0], "object.velocity: must be a list of 3 finite numbers"),
    ("optimize.parameters", ["speed"], "'speed' is not a parameter of elastic .*density, velocity"),
    (
        "optimize.learning_rates",
        {"velocity": 0.1},
        r"optimize.learning_rates.velocity: is not among optimize.parameters"
        r" \['youngs_modulus'\] \(nor estimated",
    ),
    (
        "optimize.estimate_velocity",
        {"frames": 13, "iterations": 5},
        r"optimize.estimate_velocity.frames: must be <= simulation.frames \(12\), got 13",
    ),
    ("optimize.estimate_velocity", {"frames": 3}, "optimize.estimate_velocity.iterations: is required"),
    (
        "optimize.estimate_velocity",
        {"frames": 0, "iterations": 5},
        "optimize.estimate_velocity.frames: must be an integer >= 1",
    ),
    (
        "optimize.estimate_velocity",
        {"frames": 3, "iterations": 5, "lr": 1},
        "optimize.estimate_velocity.lr: unknown key",
    ),
    (
        "optimize.estimate_velocity",
        {"frames": 3, "iterations": 5, "objects": ["jelly"]},
        "optimize.estimate_velocity.objects: names objects of a config of several: drop it",
    ),
    ("evaluation", {"ground_truth": {"velocity": 2.0}}, "evaluation.ground_truth.velocity: must be a list of 3 finite"),
    ("optimize.material", ["elastic", "lava"], "optimize.material: unknown material 'lava'"),
    ("optimize.material", "elastic", "optimize.material: must be a non-empty list of material names, got 'elastic'"),
    ("optimize.material", [], "optimize.material: must be a non-empty list"),
    ("optimize.material", ["elastic", "jelly"], r"optimize.material: names a material twice"),  # jelly: an alias
    ("optimize.material", ["elastic", "newtonian"], "optimize.material: newtonian has none of optimize.parameters"),
]


@pytest.mark.parametrize("path, value, message", BAD, ids=[f"{p}={v!r}"[:40] for p, v, _ in BAD])
def test_bad_configs_name_the_key_and_the_problem(folder, path, value, message):
    if message is None:
        parse(edit(path, value), folder)
        return
    with pytest.raises(InputError, match=message):
        parse(edit(path, value), folder)


def test_velocity_keys(folder):
    assert parse(GOOD, folder).objects[0].velocity == (0.0, 0.0, 0.0)  # at rest by default
    data = edit("object.velocity", [0.5, -1, 2])
    data["optimize"] = {
        "parameters": ["youngs_modulus", "velocity"],
        "learning_rates": {"velocity": 0.2},
        "estimate_velocity": {"frames": 4, "iterations": 10},
    }
    data["evaluation"] = {"ground_truth": {"youngs_modulus": 2e4, "velocity": [0.5, -1, 0]}}
    cfg = parse(data, folder)
    assert cfg.objects[0].velocity == (0.5, -1.0, 2.0)  # as written: m/s in the simulation frame
    opt = cfg.optimize
    assert opt.parameters == ("youngs_modulus", "velocity") and opt.learning_rates == {"velocity": 0.2}
    assert (opt.estimate_velocity_frames, opt.estimate_velocity_iterations) == (4, 10)
    assert cfg.ground_truth == {"youngs_modulus": 2e4, "velocity_x": 0.5, "velocity_y": -1.0, "velocity_z": 0.0}
    # a rate for the velocity phase alone
    data["optimize"] = {
        "parameters": ["youngs_modulus"],
        "learning_rates": {"velocity": 0.2},
        "estimate_velocity": {"frames": 4, "iterations": 10},
    }
    assert parse(data, folder).optimize.learning_rates == {"velocity": 0.2}
    assert parse(GOOD, folder).optimize.estimate_velocity_iterations == 0  # no velocity phase by default


def test_not_a_mapping(folder):
    with pytest.raises(InputError, match="must be a mapping"):
        parse(["splats"], folder)
    with pytest.raises(InputError, match="the config is empty"):
        parse({}, folder)


DUPLICATES = [
    ("scene.yaml", "splats: scene.ply\nsplats: other.ply\n", r"splats \(line 2\): duplicate key"),
    (
        "scene.yaml",
        "splats: scene.ply\nsimulation:\n  fps: 24\n  frames: 3\n  fps: 30\n",
        r"simulation.fps \(line 5\): duplicate key",
    ),
    (
        "scene.yaml",
        "splats: scene.ply\nforces:\n  - {force: [0, 0, 1], force: [0, 0, 2]}\n",
        r"forces\[0\].force \(line 3\): duplicate key",
    ),
    ("scene.json", '{"splats": "scene.ply", "splats": "other.ply"}', "splats: duplicate key"),
    (
        "scene.json",
        '{"splats": "scene.ply", "scene": {"scale": 1, "up": "+y", "scale": 2}}',
        "scene.scale: duplicate key",
    ),
    (
        "scene.json",
        '{"splats": "scene.ply", "forces": [{"start": 0, "start": 1}]}',
        r"forces\[0\].start: duplicate key",
    ),
]


@pytest.mark.parametrize("name, text, message", DUPLICATES, ids=[t[:30] for _, t, _ in DUPLICATES])
def test_a_duplicate_key_is_an_error_with_its_dotted_path(folder, name, text, message):
    (folder / name).write_text(text)
    with pytest.raises(InputError, match=f"{name}: {message}"):
        load_config(folder / name)


def alias_bomb(levels: int) -> str:
    """A "billion laughs" under an unknown key: ``levels`` lists of 9 aliases of the list
    before, 9^(levels + 1) values expanded."""
    lines = ["bomb:", "  a0: &a0 [x, x, x, x, x, x, x, x, x]"]
    lines += [f"  a{k}: &a{k} [{', '.join([f'*a{k - 1}'] * 9)}]" for k in range(1, levels + 1)]
    return "\n".join(lines) + "\n"


def test_an_alias_bomb_is_refused_at_once(scene_yaml):
    """Every walk of the document (the duplicate keys', then the checks') followed the
    aliases: 8 levels took 14 s, each level 9 times the one before."""
    bomb = scene_yaml.with_name("bomb.yaml")
    bomb.write_text(scene_yaml.read_text() + alias_bomb(8))
    start = time.perf_counter()
    with pytest.raises(
        InputError, match=r"^\S*bomb.yaml: bomb.a5: more than 100,000 nodes .* with its aliases expanded: too many"
    ):
        load_config(bomb)
    assert time.perf_counter() - start < 0.5


def test_aliases_within_the_bound_are_read(folder):
    import yaml

    text = yaml.safe_dump({k: v for k, v in GOOD.items() if k != "forces"}) + (
        "forces:\n"
        "- {region: &top {box: {min: [-1, 0.5, -1], max: [1, 1, 1]}}, force: &push [0, 0, 2], end: 0.1}\n"
        "- {region: *top, force: *push, start: 0.2}\n"
    )
    (folder / "aliases.yaml").write_text(text)
    first, second = load_config(folder / "aliases.yaml").forces
    assert first.region == second.region and first.vector == second.vector == (0.0, 0.0, 2.0)


def nested_block(levels: int, item: str) -> str:
    """``bomb:`` holding ``levels`` block lists (``item`` ``-``) or mappings (``k:``), one in the other."""
    return "bomb:\n" + "".join(f"{'  ' * (k + 1)}{item}\n" for k in range(levels))


STRUCTURES = [
    ("flow.yaml", "splats: " + "[" * 5000 + "]" * 5000, r"nested deeper than 100 levels \(line 1, column 108\)$"),
    ("list.yaml", "splats: scene.ply\n" + nested_block(5000, "-"), r"nested deeper than 100 levels \(line 102, "),
    ("map.yaml", "splats: scene.ply\n" + nested_block(5000, "k:"), r"nested deeper than 100 levels \(line 102, "),
    ("deep.json", '{"splats": ' + "[" * 100_000 + "]" * 100_000 + "}", r"nested deeper than 100 levels \(line 1, "),
    ("loop.yaml", "splats: scene.ply\nbomb: &b [1, *b]\n", r"bomb\[1\]: an alias to a node that holds it \(line 2, "),
    (
        "chain.yaml",
        "splats: scene.ply\nbomb:\n  a0: &a0 [1]\n" + "".join(f"  a{k}: &a{k} [*a{k - 1}]\n" for k in range(1, 150)),
        r"bomb.a98\[0\]: nested deeper than 100 levels with its aliases expanded$",
    ),
    ("100.yaml", "splats: scene.ply\nbomb: " + "[" * 99 + "]" * 99, r"bomb: unknown key"),  # deep enough
    ("100.json", '{"splats": "scene.ply", "bomb": ' + "[" * 99 + "]" * 99 + "}", r"bomb: unknown key"),
]


@pytest.mark.parametrize("name, text, message", STRUCTURES, ids=[name for name, _, _ in STRUCTURES])
def test_nesting_is_bounded_before_python_runs_out_of_recursion(folder, name, text, message):
    (folder / name).write_text(text)
    with pytest.raises(InputError, match=f"^{re.escape(str(folder / name))}: {message}"):
        load_config(folder / name)


UNREADABLE = [  # values PyYAML and json fail to build with a ValueError (or KeyError) of their own
    (
        "frames.yaml",
        "splats: scene.ply\nsimulation: {frames: " + "9" * 5000 + "}\n",
        r"not valid YAML: line 2, column 22: '9{20}'\.\.\. \(5,000 characters\) cannot be read as a YAML int "
        r"\(Exceeds the limit \(4300 digits\) for integer string conversion: value has 5000 digits\)$",
    ),
    (
        "date.yaml",
        "splats: scene.ply\noutput: 2001-13-45\n",
        r"not valid YAML: line 2, column 9: '2001-13-45' cannot be read as a YAML timestamp \(month must be in 1..12\)$",
    ),
    (
        "bool.yaml",
        "splats: scene.ply\nflow: {mask: !!bool maybe}\n",
        r"not valid YAML: line 2, column 14: 'maybe' cannot be read as a YAML bool$",
    ),
    (
        "frames.json",
        '{"splats": "scene.ply", "simulation": {"frames": ' + "9" * 5000 + "}}",
        r"not valid JSON: line 1, column 50: a number of 5,000 digits \(at most 4,300\)$",
    ),
]


@pytest.mark.parametrize("name, text, message", UNREADABLE, ids=[name for name, _, _ in UNREADABLE])
def test_a_value_the_parser_cannot_build_is_one_line(folder, name, text, message):
    (folder / name).write_text(text)
    with pytest.raises(InputError, match=f"^{re.escape(str(folder / name))}: {message}"):
        load_config(folder / name)


def test_a_set_value_nested_too_deep_or_unreadable_is_one_line(scene_yaml):
    item = "simulation.gravity=" + "[" * 200 + "]" * 200
    with pytest.raises(InputError, match=r"the value is not valid YAML \(nested deeper than 100 levels \(line 1, "):
        load_config(scene_yaml, [item])
    with pytest.raises(InputError, match=r"the value is not valid YAML \(.*\(5,000 characters\) cannot be read as"):
        load_config(scene_yaml, ["simulation.frames=" + "9" * 5000])


def test_material_hypotheses_check_parameters_against_all_of_them(folder):
    data = edit("optimize", {"parameters": ["youngs_modulus", "viscosity"], "material": ["Elastic", "newtonian"]})
    cfg = parse(data, folder)
    assert cfg.optimize.materials == {"object": ("elastic", "newtonian")}  # registry names, of the one object
    assert cfg.optimize.search is not None  # the search tells them apart: on by default
    with pytest.raises(
        InputError, match="optimize.parameters: 'yield_stress' is a parameter of none of the hypotheses"
    ):
        parse(edit("optimize", {"parameters": ["youngs_modulus", "yield_stress"], "material": ["elastic"]}), folder)
    # a ground truth may belong to any hypothesis
    truth = edit("evaluation", {"ground_truth": {"viscosity": 10.0}})
    truth["optimize"] = data["optimize"]
    assert parse(truth, folder).ground_truth == {"viscosity": 10.0}


def test_yaml_numbers_with_an_exponent_are_numbers(folder):
    import yaml

    text = yaml.safe_dump(GOOD).replace("youngs_modulus: 10000.0", "youngs_modulus: 2e4")
    assert "youngs_modulus: 2e4" in text
    (folder / "scene.yaml").write_text(text + "evaluation:\n  ground_truth: {youngs_modulus: 1.5E+5, density: 5e2}\n")
    cfg = load_config(folder / "scene.yaml")
    assert cfg.objects[0].material.parameters["youngs_modulus"] == 2e4
    assert cfg.ground_truth == {"youngs_modulus": 1.5e5, "density": 500.0}
    (folder / "quoted.yaml").write_text(text.replace("youngs_modulus: 2e4", "youngs_modulus: '2e4'"))
    with pytest.raises(InputError, match=r"youngs_modulus.*'2e4'"):  # a quoted string stays a string
        load_config(folder / "quoted.yaml")


@pytest.fixture
def scene_yaml(folder):
    import yaml

    (folder / "scene.yaml").write_text(yaml.safe_dump(GOOD))
    return folder / "scene.yaml"


def test_overrides_set_keys_before_validation(scene_yaml):
    cfg = load_config(
        scene_yaml,
        [
            "simulation.frames=20",
            "material.parameters.youngs_modulus=3e5",
            "object.velocity=[0, 1.5, 0]",
            "optimize.search.samples=4",
            "scene.up=+y",
        ],
    )
    assert cfg.simulation.frames == 20 and cfg.objects[0].material.parameters["youngs_modulus"] == 3e5
    assert cfg.objects[0].velocity == (0.0, 1.5, 0.0) and cfg.optimize.search.samples == 4 and cfg.up == "+y"
    assert load_config(scene_yaml, ["simulation.frames=20", "simulation.frames=8"]).simulation.frames == 8  # last wins
    assert load_config(scene_yaml).simulation.frames == 12


def test_overrides_index_list_items(scene_yaml):
    cfg = load_config(
        scene_yaml,
        ["forces.0.end=0.5", "forces.0.region.sphere.radius=0.2", "object.velocity=[0, 1, 0]", "object.velocity.1=2.5"],
    )
    assert cfg.forces[0].end == 0.5 and cfg.forces[0].region.radius == 0.2
    assert cfg.objects[0].velocity[1] == 2.5


@pytest.mark.parametrize(
    "item, message",
    [
        ("forces.3.end=1", r"^--set forces.3.end=1: forces has 1 item\(s\), so no item 3"),
        ("forces.0.end=-1", r"^--set forces.0.end=-1: forces\[0\].end: must be after start"),
        ("0.frames=1", r"^--set 0.frames=1: expected KEY.SUB=VALUE"),
        (
            "simulation.framez=3",
            r"^--set simulation.framez=3: simulation.framez: unknown key; known keys here: .*frames",
        ),
        (
            "simulation.frames=many",
            r"^--set simulation.frames=many: simulation.frames: must be an integer >= 1, got 'many'$",
        ),
        ("material.parameters.youngs_modulus=-5", r"^--set material.parameters.youngs_modulus=-5: .*youngs_modulus"),
        ("bogus.key=1", r"^--set bogus.key=1: bogus: unknown key"),
        ("scene.scale.x=1", r"^--set scene.scale.x=1: scene.scale is a float in the config, not a mapping of keys$"),
        ("simulation.frames", r"^--set simulation.frames: expected KEY.SUB=VALUE"),
        ("simulation..frames=2", r"^--set simulation..frames=2: expected KEY.SUB=VALUE"),
        ("object.velocity=[0, 1", r"^--set object.velocity=\[0, 1: the value is not valid YAML"),
    ],
)
def test_a_bad_override_is_one_line_naming_it(scene_yaml, item, message):
    with pytest.raises(InputError, match=message) as error:
        load_config(scene_yaml, [item])
    assert "\n" not in str(error.value)


def several(**changes):
    """GOOD with two objects (a list of entries with names) instead of object + material,
    without identification."""
    data = copy.deepcopy(GOOD)
    obj, material = data.pop("object"), data.pop("material")
    data["optimize"] = {"iterations": 5}
    data["objects"] = [
        {"name": "jelly", **obj, "velocity": [0, -1, 0], "material": material},
        {"name": "heap", "select": {"sphere": {"center": [0, 2, 0], "radius": 0.5}}, "material": {"type": "sand"}},
    ]
    data.update(changes)
    return data


def test_objects_as_a_list_or_a_mapping_and_one_object_in_either_form(folder):
    cfg = parse(several(), folder)
    jelly, heap = cfg.objects
    assert cfg.object_names == ("jelly", "heap") and (jelly.key, heap.material_key) == (
        "objects.jelly",
        "objects.heap.material",
    )
    assert jelly.material.parameters == {"youngs_modulus": 1e4, "poissons_ratio": 0.3} and jelly.fill.spacing == 0.02
    assert jelly.velocity == (0.0, -1.0, 0.0) and heap.velocity == (0.0, 0.0, 0.0)
    assert heap.material.type == "sand" and heap.material.density == 1600.0 and heap.selection.region.kind == "sphere"
    mapping = several(objects={o["name"]: {k: v for k, v in o.items() if k != "name"} for o in several()["objects"]})
    assert parse(mapping, folder) == cfg
    # the single-object form is one SceneObject named object, its material under material
    single = parse(GOOD, folder)
    (obj,) = single.objects
    assert (obj.name, obj.key, obj.material_key) == ("object", "object", "material")
    listed = parse(several(objects=[several()["objects"][0]], optimize=GOOD["optimize"]), folder)
    assert listed.objects[0].material == obj.material and listed.objects[0].selection == obj.selection
    assert (obj.own_file("material_query", ".json"), jelly.own_file("material_query", ".json")) == (
        "material_query.json",
        "material_query.jelly.json",
    )


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"objects": []}, "objects: is empty"),
        ({"objects": "jelly"}, "objects: must be a list of objects .* or a mapping"),
        ({"material": {"type": "elastic"}}, "material: give the scene's objects under objects .* not both"),
        ({"objects": [{"select": {"sphere": {"center": [0, 0, 0], "radius": 1}}}]}, r"objects\[0\].name: is required"),
        ({"objects": {"9lives": {}}}, "objects.9lives: an object's name is letters, digits and _"),
        ({"objects": [{"name": "a.b"}]}, r"objects\[0\].name: an object's name"),
        ({"objects": [{"name": "a", "colour": 1}]}, r"objects\[0\].colour: unknown key"),
        ({"objects": [{"name": "a", "select": {}}]}, "objects.a.select: is required"),
        (
            {"objects": [{"name": "a", "select": {"box": {"min": [0, 0, 0], "max": [1, 1, 1]}}}]},
            "objects.a.material.type: is required",
        ),
        ({"objects": {"a": {"name": "a"}}}, "objects.a.name: unknown key"),
        (
            {"evaluation": {"ground_truth": {"youngs_modulus": 1e4}}},
            r"evaluation.ground_truth: 'youngs_modulus': with several objects name each parameter's object, "
            r"OBJECT.PARAM \(e.g. jelly.",
        ),
        (
            {"evaluation": {"ground_truth": {"ghost.youngs_modulus": 1e4}}},
            r"evaluation.ground_truth: 'ghost.youngs_modulus': there is no object 'ghost' \(the objects: jelly, heap\)",
        ),
        (
            {"optimize": {"parameters": ["jelly.density"], "material": ["sand"]}},
            r"optimize.material: with several objects must map object names \(jelly, heap\) to lists of materials",
        ),
        (
            {"optimize": {"parameters": ["jelly.density"], "material": {"ghost": ["sand"]}}},
            r"optimize.material.ghost: there is no object 'ghost' \(the objects: jelly, heap\)",
        ),
        (
            {"optimize": {"parameters": ["heap.density"], "material": {"heap": ["sand", "lava"]}}},
            "optimize.material.heap: unknown material 'lava'",
        ),
        (
            {"optimize": {"parameters": ["heap.friction_angle"], "material": {"heap": ["sand", "newtonian"]}}},
            "optimize.material.heap: newtonian has none of optimize.parameters",
        ),
        (
            {"optimize": {"parameters": ["heap.viscosity", "heap.density"], "material": {"heap": ["sand", "snow"]}}},
            "optimize.parameters: 'heap.viscosity' is a parameter of none of the hypotheses sand, snow",
        ),
        (
            {
                "optimize": {
                    "parameters": ["jelly.density", "heap.density"],
                    "material": {
                        "jelly": ["elastic", "plasticine", "metal", "foam", "snow"],
                        "heap": ["sand", "snow", "newtonian", "elastic"],
                    },
                }
            },
            r"optimize.material: 20 combinations of materials \(5 of jelly x 4 of heap\); at most 16: name fewer",
        ),
        ({"optimize": {"parameters": ["youngs_modulus"]}}, r"optimize.parameters: 'youngs_modulus': with several"),
        (
            {"optimize": {"parameters": ["ghost.youngs_modulus"]}},
            r"^scene.yaml: optimize.parameters: 'ghost.youngs_modulus': there is no object 'ghost'",
        ),
        (
            {"optimize": {"parameters": ["heap.yield_stress"]}},
            r"'heap.yield_stress': 'yield_stress' is not a parameter of heap's material sand",
        ),
        (
            {"evaluation": {"ground_truth": {"jelly.velocity": 2.0}}},
            r"evaluation.ground_truth.jelly.velocity: must be a list of 3 finite numbers, got 2.0",
        ),
        (
            {"optimize": {"parameters": ["jelly.youngs_modulus"], "estimate_velocity": {"frames": 1, "iterations": 1}}},
            "optimize.estimate_velocity.objects: is required with several objects: a list of object names",
        ),
        (
            {
                "optimize": {
                    "parameters": ["jelly.youngs_modulus"],
                    "estimate_velocity": {"frames": 1, "iterations": 1, "objects": ["ghost"]},
                }
            },
            r"estimate_velocity.objects: 'ghost': there is no object 'ghost' \(the objects: jelly, heap\)",
        ),
        (
            {
                "optimize": {
                    "parameters": ["jelly.youngs_modulus"],
                    "estimate_velocity": {"frames": 1, "iterations": 1, "objects": ["jelly"]},
                    "learning_rates": {"heap.velocity": 0.2},  # the heap's velocity is not estimated
                }
            },
            r"optimize.learning_rates.heap.velocity: is not among optimize.parameters .* \(nor estimated",
        ),
    ],
)
def test_bad_objects(folder, changes, message):
    data = several(**changes)
    if "material" in changes:
        data["material"] = changes["material"]
    with pytest.raises(InputError, match=message):
        parse(data, folder)


def test_each_objects_parameters_by_object_name(folder):
    """Several objects: optimize.parameters, bounds, learning rates and the ground truth name
    OBJECT.PARAM, each checked against that object's material."""
    optimize = {
        "parameters": ["jelly.youngs_modulus", "jelly.velocity", "heap.friction_angle", "heap.density"],
        "bounds": {"heap.friction_angle": [20, 45]},
        "learning_rates": {"jelly.youngs_modulus": 0.1, "jelly.velocity": 0.3},
    }
    truth = {"jelly.youngs_modulus": 2e4, "heap.friction_angle": 30, "heap.density": 1500, "jelly.velocity": [1, -2, 0]}
    cfg = parse(several(optimize=optimize, evaluation={"ground_truth": truth}), folder)
    assert cfg.optimize.parameters == ("jelly.youngs_modulus", "jelly.velocity", "heap.friction_angle", "heap.density")
    assert cfg.optimize.bounds == {"heap.friction_angle": (20.0, 45.0)}
    assert cfg.ground_truth == {
        "jelly.velocity_x": 1.0,
        "jelly.velocity_y": -2.0,
        "jelly.velocity_z": 0.0,
        "jelly.youngs_modulus": 2e4,
        "heap.friction_angle": 30.0,
        "heap.density": 1500.0,
    }
    # the search's object rounds look at material parameters: velocity is not searched
    assert cfg.optimize.parameters_by_object() == {
        "jelly": ("jelly.youngs_modulus",),
        "heap": ("heap.friction_angle", "heap.density"),
    }
    with pytest.raises(InputError, match=r"ground_truth: heap: .*friction_angle"):
        parse(several(evaluation={"ground_truth": {"heap.friction_angle": 95}}), folder)


def test_material_hypotheses_of_several_objects(folder):
    """optimize.material of several objects maps objects to their lists; the hypotheses are
    every combination, each a config of those materials optimising the entries they have."""
    from clflow.pipeline.hypotheses import hypotheses, hypothesis_config, hypothesis_name

    optimize = {
        "parameters": [
            "jelly.youngs_modulus",
            "jelly.yield_stress",
            "jelly.velocity",
            "heap.friction_angle",
            "heap.youngs_modulus",
        ],
        "material": {"heap": ["sand", "snow"], "jelly": ["jelly", "plasticine"]},  # jelly: elastic's alias
        "learning_rates": {"jelly.yield_stress": 0.1, "jelly.velocity": 0.3},
        "bounds": {"jelly.yield_stress": [100, 1e4]},
    }
    truth = {"jelly.yield_stress": 500.0}  # of plasticine, one of the jelly's hypotheses
    cfg = parse(several(optimize=optimize, evaluation={"ground_truth": truth}), folder)
    assert cfg.optimize.materials == {"jelly": ("elastic", "plasticine"), "heap": ("sand", "snow")}  # objects' order
    assert cfg.optimize.search is not None  # hypotheses are told apart by the search
    combinations = hypotheses(cfg)
    assert combinations == [
        {"jelly": "elastic", "heap": "sand"},
        {"jelly": "elastic", "heap": "snow"},
        {"jelly": "plasticine", "heap": "sand"},
        {"jelly": "plasticine", "heap": "snow"},
    ]
    assert [hypothesis_name(cfg, h) for h in combinations][1] == "jelly-elastic+heap-snow"
    hyp = hypothesis_config(cfg, combinations[1])
    jelly, heap = hyp.objects
    assert (jelly.material.type, heap.material.type) == ("elastic", "snow")
    assert jelly.material.parameters == {"youngs_modulus": 1e4, "poissons_ratio": 0.3}  # the config's
    assert heap.material.density == cfg.objects[1].material.density and "friction_angle" not in heap.material.parameters
    assert heap.material.parameters["youngs_modulus"] == cfg.objects[1].material.parameters["youngs_modulus"]
    assert hyp.optimize.parameters == ("jelly.youngs_modulus", "jelly.velocity", "heap.youngs_modulus")  # no friction
    assert hyp.optimize.learning_rates == {"jelly.velocity": 0.3} and hyp.optimize.bounds == {}
    assert hyp.optimize.materials == {} and hyp.output == cfg.output / "hypotheses" / "jelly-elastic+heap-snow"
    hyp = hypothesis_config(cfg, combinations[2])
    assert hyp.optimize.parameters == cfg.optimize.parameters
    assert hyp.objects[1].material == cfg.objects[1].material  # sand: as configured
    # an object not named keeps its material; one object's list is a product of one list
    cfg = parse(several(optimize={"parameters": ["heap.density"], "material": {"heap": ["sand", "snow"]}}), folder)
    assert [hypothesis_name(cfg, h) for h in hypotheses(cfg)] == ["heap-sand", "heap-snow"]
    assert hypothesis_config(cfg, hypotheses(cfg)[1]).objects[0].material == cfg.objects[0].material


def test_two_objects_of_one_name(folder):
    data = several()
    data["objects"][1]["name"] = "jelly"
    with pytest.raises(InputError, match=r"^scene.yaml: objects\[1\].name: 'jelly' names objects\[0\] too"):
        parse(data, folder)


def test_overrides_of_one_object_by_its_name(folder):
    import yaml

    for form, data in (
        ("list", several()),
        ("mapping", several(objects={"jelly": several()["objects"][0], "heap": several()["objects"][1]})),
    ):
        if form == "mapping":
            for o in data["objects"].values():
                o.pop("name")
        path = folder / f"{form}.yaml"
        path.write_text(yaml.safe_dump(data))
        cfg = load_config(
            path, ["objects.jelly.material.parameters.youngs_modulus=3e4", "objects.heap.velocity=[0, 1, 0]"]
        )
        named = {o.name: o for o in cfg.objects}  # a mapping keeps its order: safe_dump sorted it
        assert named["jelly"].material.parameters["youngs_modulus"] == 3e4 and named["heap"].velocity == (0, 1, 0)
        with pytest.raises(
            InputError,
            match=r"^--set objects.rock.velocity=\[0,1,0\]: the config has no object named 'rock' \(its objects: (jelly, heap|heap, jelly)\)$",
        ):
            load_config(path, ["objects.rock.velocity=[0,1,0]"])
        with pytest.raises(
            InputError, match=r"^--set objects.heap.material.density=-1: objects.heap.material.density: must be > 0"
        ):
            load_config(path, ["objects.heap.material.density=-1"])
        with pytest.raises(InputError, match=r"^--set objects.heap=1: set a key of the object"):
            load_config(path, ["objects.heap=1"])
    (folder / "one.yaml").write_text(yaml.safe_dump(GOOD))
    with pytest.raises(InputError, match="the config gives one object .*no object 'jelly' to set: set object"):
        load_config(folder / "one.yaml", ["objects.jelly.velocity=[0,1,0]"])
