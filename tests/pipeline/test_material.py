"""material.type: query -> the material query decides type, density and initial parameters."""

import json

import numpy as np
import pytest
import yaml

from clflow.errors import InputError
from clflow.pipeline.material import resolve_material
from clflow.scene.config import load_config


def query_config(quick_demo, tmp_path, material, optimize=("youngs_modulus",)):
    import cv2

    cv2.imwrite(str(tmp_path / "jelly.png"), np.full((32, 32, 3), 128, np.uint8))
    data = yaml.safe_load((quick_demo / "config.yaml").read_text())
    data["splats"] = str(quick_demo / "scene.ply")
    data["video"] = str(quick_demo / "guidance")
    data["material"] = material
    data["optimize"] = {"parameters": list(optimize)}
    data["evaluation"] = {}
    data["output"] = str(tmp_path / "out")
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(data))
    return load_config(path)


def test_query_fills_in_the_material_and_config_values_win(quick_demo, tmp_path):
    cfg = query_config(
        quick_demo, tmp_path, {"type": "query", "query": {"image": "jelly.png"}, "parameters": {"poissons_ratio": 0.4}}
    )
    assert cfg.objects[0].material.density is None
    resolved = resolve_material(cfg)
    record = json.loads((tmp_path / "out" / "material_query.json").read_text())
    assert resolved.objects[0].material.type == record["material"] == "elastic"
    assert resolved.objects[0].material.density == record["density"] > 0
    assert resolved.objects[0].material.parameters["youngs_modulus"] == record["parameters"]["youngs_modulus"]
    assert resolved.objects[0].material.parameters["poissons_ratio"] == 0.4  # the config's value, not the query's


def test_a_saved_query_record_is_the_initial_guess(quick_demo, tmp_path):
    from clflow.query.backends import query_material

    query_material(object_name="steel spoon").save(tmp_path / "spoon.material.json")
    cfg = query_config(
        quick_demo,
        tmp_path,
        {"type": "query", "query": {"result": "spoon.material.json"}},
        optimize=("youngs_modulus",),
    )
    resolved = resolve_material(cfg)
    assert resolved.objects[0].material.type == "metal" and resolved.objects[0].material.density > 7000


def test_query_takes_an_image_or_a_record_not_both(quick_demo, tmp_path):
    with pytest.raises(InputError, match="material.query: give at most one of image"):
        query_config(quick_demo, tmp_path, {"type": "query", "query": {"image": "jelly.png", "result": "a.json"}})


def test_query_without_an_image_looks_at_the_object_in_the_guidance_view(quick_demo, tmp_path):
    """No image: the guidance video's first frame, cut to the object's screen box."""
    cfg = query_config(quick_demo, tmp_path, {"type": "query", "query": {"prompt": "a jelly cube"}})
    resolve_material(cfg)
    record = json.loads((tmp_path / "out" / "material_query.json").read_text())
    assert record["image"] == str(tmp_path / "out" / "guidance_frame0.png")
    x0, y0, x1, y1 = record["crop_box"]
    width, height = cfg.camera.width, cfg.camera.height
    assert 0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height
    assert (x1 - x0) * (y1 - y0) < 0.5 * width * height  # the cube, not the whole frame with its floor


def test_query_result_without_the_optimised_parameter(quick_demo, tmp_path):
    cfg = query_config(
        quick_demo,
        tmp_path,
        {"type": "query", "query": {"image": "jelly.png"}, "density": 900},
        optimize=("friction_angle",),
    )
    with pytest.raises(InputError, match="the query chose elastic, which has no parameter 'friction_angle'"):
        resolve_material(cfg)


def test_concrete_material_is_unchanged(demo_config):
    cfg = demo_config()
    assert resolve_material(cfg) is cfg


@pytest.mark.parametrize(
    "material, model, kernel_material",
    [
        ("sand", "volume_corrected", "sand_volume_corrected"),
        ("sand", None, "sand"),
        ("elastic", "neo_hookean", "neo_hookean"),
        ("elastic", None, "elastic"),
    ],
)
def test_material_model_reaches_the_simulator(demo_config, material, model, kernel_material):
    import dataclasses

    from clflow.materials import validate_params
    from clflow.mpm.constants import MATERIAL_IDS
    from clflow.pipeline.forward import prepare
    from clflow.pipeline.simulation import ObjectValues, build_simulator

    cfg = demo_config()
    params = validate_params(material, {})
    material_cfg = dataclasses.replace(cfg.objects[0].material, type=material, parameters=params, model=model)
    cfg = cfg.with_objects([dataclasses.replace(cfg.objects[0], material=material_cfg)])
    sim = build_simulator(cfg, prepare(cfg).setup, (ObjectValues(params, 1500.0, cfg.objects[0].velocity),))
    assert set(sim.particles.material.tolist()) == {MATERIAL_IDS[kernel_material]}
