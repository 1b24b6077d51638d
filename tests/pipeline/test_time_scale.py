"""optimize.parameters' time_scale (simulated seconds per second of the guidance video): a
fit of a video played slower than it was filmed identifies its speed and the material with
it, and a scene that cannot tell the clock from the material is refused before the work."""

import dataclasses

import pytest
import yaml

from clflow.errors import InputError
from clflow.pipeline.fit import Optimization, parameter_unit
from clflow.pipeline.plots import _parameter_axis
from clflow.scene.config import TIME_SCALE, load_config, parse_config
from clflow_datasets.degradation import Degradation
from clflow_datasets.synthetic import Resolution, SyntheticCase, make_case

TINY = Resolution(object_detail=6, floor_side=8, image=48, grid=14, frames=6, iterations=8)
SPEED = 0.8  # the truth's frames lie 0.8 of the video's frame interval apart: a slow-motion video


@pytest.fixture(scope="module")
def slow_case(tmp_path_factory):
    """(config dict, its folder) of a falling elastic case filmed at SPEED, its optimiser Levenberg-Marquardt."""
    folder = tmp_path_factory.mktemp("slow")
    config = make_case(folder, SyntheticCase(spread=0.5), TINY, truth_scale=1, degradation=Degradation(speed=SPEED))
    data = yaml.safe_load(config.read_text())
    data["optimize"] = {"parameters": ["youngs_modulus"], "method": "levenberg_marquardt", "iterations": 8}
    return data, folder


def fitted(slow_case, tmp_path, parameters):
    data, folder = slow_case
    data = {**data, "optimize": {**data["optimize"], "parameters": parameters}, "output": str(tmp_path / "out")}
    data["evaluation"] = {"ground_truth": {**data["evaluation"]["ground_truth"], "time_scale": SPEED}}
    opt = Optimization(parse_config(data, str(folder / "config.yaml"), folder))
    return opt, opt.problem.values(opt.run().z)


def test_a_slow_motion_video_gives_its_speed_and_the_material_with_it(slow_case, tmp_path):
    opt, found = fitted(slow_case, tmp_path, ["youngs_modulus", "time_scale"])
    assert opt.problem.initial_state().z["time_scale"] == 0.0  # it starts at the video's clock
    assert found["time_scale"] == pytest.approx(SPEED, rel=0.05)
    assert found["youngs_modulus"] == pytest.approx(2e4, rel=0.1)
    sim = opt.problem.simulator_on(opt.problem.model_grid, {"youngs_modulus": 4.3, "time_scale": -0.1})
    assert sim.frame_dt == pytest.approx(10**-0.1 / 24, rel=1e-12)
    _, fixed_clock = fitted(slow_case, tmp_path, ["youngs_modulus"])
    assert abs(fixed_clock["youngs_modulus"] / 2e4 - 1) > 0.15  # the stated clock biases the material


def test_the_results_name_it_dimensionless_on_a_log_axis(quick_demo):
    cfg = load_config(quick_demo / "config.yaml")
    assert parameter_unit(cfg, "time_scale") == TIME_SCALE.unit == "1"
    assert _parameter_axis("time_scale") == ("time_scale (dimensionless)", True)


def demo_data(quick_demo, **optimize) -> dict:
    data = yaml.safe_load((quick_demo / "config.yaml").read_text())
    data["optimize"] = {"parameters": ["youngs_modulus", "time_scale"], "method": "levenberg_marquardt", **optimize}
    return data


@pytest.mark.parametrize(
    "change, message",
    [
        (
            lambda d: d.update(forces=[], simulation={**d["simulation"], "gravity": [0, 0, 0]}),
            "fixes the video's clock",
        ),
        (lambda d: d["optimize"].update(method="adam"), "levenberg_marquardt"),
        (
            lambda d: d["optimize"].update(estimate_velocity={"iterations": 2, "frames": 3}),
            "velocity among optimize.parameters",
        ),
        (lambda d: d.update(evaluation={"ground_truth": {"time_scale": 20.0}}), "time_scale"),
    ],
)
def test_a_scene_that_cannot_tell_the_clock_is_refused(quick_demo, change, message):
    data = demo_data(quick_demo)
    change(data)
    with pytest.raises(InputError, match=message):
        parse_config(data, str(quick_demo / "config.yaml"), quick_demo)


def test_the_demo_with_its_clock_parses_and_keeps_the_material_as_it_was(quick_demo):
    cfg = parse_config(demo_data(quick_demo), str(quick_demo / "config.yaml"), quick_demo)
    assert cfg.optimize.parameters == ("youngs_modulus", "time_scale")
    assert dataclasses.asdict(cfg.objects[0].material) == dataclasses.asdict(
        load_config(quick_demo / "config.yaml").objects[0].material
    )
