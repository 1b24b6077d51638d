"""The object's initial velocity: object.velocity in every forward run, its gradient, and its
estimation by clflow optimize (optimize.parameters: velocity; optimize.estimate_velocity)."""

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
import yaml

from clflow.mpm import Force, Grid, MaterialSpec, Simulator
from clflow.pipeline.fit import Optimization
from clflow.pipeline.forward import prepare, scene_values
from clflow.pipeline.runs import write_results
from clflow.pipeline.simulation import build_simulator, run
from clflow.scene.config import SINGLE_OBJECT, VELOCITY_COMPONENTS, load_config
from tests.mpm._helpers import cube
from tests.pipeline.test_frames4d import run as run_cli

# m/s, perpendicular to the view direction (1, 2, 3) of the camera of `thrown`: a single view
# sees the velocity along its line of sight only through perspective, barely
THROW = (1.0, 1.0, -1.0)


def test_gradient_of_the_initial_velocity_matches_central_differences():
    """A 3-vector broadcast to every particle, through the MPM adjoint: float64, 216
    particles of a block whose upper half is pushed (so it deforms), 3 frames."""
    x = cube(6, 0.38, 0.62)
    sim = Simulator(
        x,
        (0.24 / 6) ** 3,
        MaterialSpec("elastic", {"youngs_modulus": 2e4, "poissons_ratio": 0.3}, 800.0),
        Grid((16, 16, 16), 1 / 16),
        forces=[Force(x[:, 1] > 0.5, 0.0, 0.03, acceleration=(20.0, 0.0, 0.0))],
        frame_dt=1e-2,
        substeps=10,
        dtype=torch.float64,
    )
    gen = torch.Generator().manual_seed(0)
    w_x, w_v, w_F = (
        torch.randn(shape, generator=gen, dtype=torch.float64)
        for shape in ((4, sim.n, 3), (4, sim.n, 3), (4, sim.n, 3, 3))
    )

    def loss_at(velocity):
        out = run(sim, 3, {}, velocity=velocity)
        return (w_x * out.x).sum() + 0.1 * (w_v * out.v).sum() + (w_F * out.F).sum()

    velocity = torch.tensor([0.3, 0.5, -0.2], dtype=torch.float64, requires_grad=True)
    loss_at(velocity).backward()
    for axis in range(3):
        step = torch.zeros(3, dtype=torch.float64)
        step[axis] = 1e-3  # m/s
        with torch.no_grad():
            measured = float(loss_at(velocity.detach() + step) - loss_at(velocity.detach() - step)) / 2e-3
        assert abs(measured - float(velocity.grad[axis])) < 1e-5 * abs(measured), (axis, measured, velocity.grad)


@pytest.mark.parametrize("up", ["+x", "-x", "+y", "-y", "+z", "-z"])
def test_object_velocity_is_in_the_simulation_frame_whatever_the_files_up_axis(demo_config, up):
    """Like forces and gravity, the velocity is not turned by scene.up: (0, 2, 0) is up."""
    cfg = dataclasses.replace(demo_config(), up=up)
    cfg = cfg.with_objects([dataclasses.replace(cfg.objects[0], velocity=(0.5, 2.0, -1.0))])
    setup = prepare(demo_config()).setup
    sim = build_simulator(cfg, setup, scene_values(cfg))
    assert sim.state.v.double().unique(dim=0).tolist() == [[0.5, 2.0, -1.0]]


def test_the_simulator_starts_at_the_velocity_and_takes_substeps_for_it(demo_config):
    cfg = demo_config()
    setup = prepare(cfg).setup
    at_rest = build_simulator(cfg, setup, scene_values(cfg))
    moving = cfg.with_objects([dataclasses.replace(cfg.objects[0], velocity=(0.0, 0.0, 3.0))])
    thrown = build_simulator(moving, setup, scene_values(moving))
    assert bool((at_rest.state.v == 0).all())
    assert thrown.state.v.tolist() == [[0.0, 0.0, 3.0]] * thrown.n
    assert thrown.substeps > at_rest.substeps  # CFL: 3 m/s crosses a cell of 3.3 cm in 11 ms
    # an explicit velocity wins over the config's
    (values,) = scene_values(cfg)
    explicit = build_simulator(cfg, setup, (dataclasses.replace(values, velocity=torch.tensor([1.0, 0, 0])),))
    assert explicit.state.v[0].tolist() == [1.0, 0.0, 0.0]


def test_simulate_takes_the_velocity_of_a_params_file(quick_demo, tmp_path):
    truth = yaml.safe_load((quick_demo / "config_truth.yaml").read_text())
    truth["object"]["velocity"] = [0.5, 0.0, 0.0]
    moving = quick_demo / "config_truth_moving.yaml"  # next to scene.ply, which it names relatively
    moving.write_text(yaml.safe_dump(truth))
    assert run_cli("simulate", moving, "-o", tmp_path / "a", "--preview", "none").exit_code == 0
    params = tmp_path / "params.json"
    record = {
        "material": "elastic",
        "parameters": {"youngs_modulus": 2e4, "poissons_ratio": 0.3},
        "density": 1000.0,
        "velocity": [0.5, 0.0, 0.0],
    }
    params.write_text(json.dumps(record))
    res = run_cli(
        "simulate", quick_demo / "config.yaml", "--params-from", params, "-o", tmp_path / "b", "--preview", "none"
    )
    assert res.exit_code == 0, res.output
    means = [np.load(tmp_path / name / "gaussians.npz")["object_means"] for name in ("a", "b")]
    np.testing.assert_array_equal(means[0], means[1])
    params.write_text(json.dumps({**record, "velocity": [0.5, "fast", 0.0]}))
    res = run_cli("simulate", quick_demo / "config.yaml", "--params-from", params)
    assert res.exit_code == 1
    assert "velocity must be a list of 3 finite numbers (m/s), got [0.5, 'fast', 0.0]" in res.output


@pytest.fixture(scope="module")
def thrown(tmp_path_factory):
    """A 0.2 m jelly cube thrown at THROW from 0.25 m above the floor, 4 frames at 24 fps,
    seen from above and in front, with room for its flight (``spread``); its config starts
    from the truth's material."""
    from clflow_datasets.synthetic import Resolution, SyntheticCase, make_case

    folder = tmp_path_factory.mktemp("thrown")
    case = SyntheticCase(lift=0.25, velocity=THROW, forces=(), camera_offset=(1.5, 3.0, 4.5), spread=1.0)
    make_case(folder, case, Resolution(object_detail=8, floor_side=24, image=128, grid=24, frames=4))
    data = yaml.safe_load((folder / "config.yaml").read_text())
    data["flow"]["loss"] = "charbonnier"  # robust to the optical flow's errors at the cube's edges
    (folder / "config.yaml").write_text(yaml.safe_dump(data))
    return folder


def thrown_config(folder, output, **optimize):
    """The thrown case's config starting at rest, with the true velocity as ground truth."""
    cfg = load_config(folder / "config.yaml")
    assert cfg.objects[0].velocity == THROW  # written by the generator
    optimize = {"learning_rates": {}, "horizon_start": 0, **optimize}
    return dataclasses.replace(
        cfg.with_objects([dataclasses.replace(cfg.objects[0], velocity=(0.0, 0.0, 0.0))]),
        output=output,
        optimize=dataclasses.replace(cfg.optimize, **optimize),
        ground_truth={**cfg.ground_truth, **dict(zip(VELOCITY_COMPONENTS, THROW))},
    )


def test_the_velocity_alone_is_recovered_from_the_video(thrown, tmp_path):
    opt = Optimization(thrown_config(thrown, tmp_path / "out", parameters=("velocity",), iterations=20))
    state = opt.run()
    assert sorted(state.z) == sorted(VELOCITY_COMPONENTS)
    losses = [row["loss"] for row in state.history]
    assert losses[-1] < 0.3 * losses[0]
    metrics = write_results(opt, state)
    estimate = opt.problem.velocities(state.z)[0]
    assert metrics["velocity_error_m_s"] == pytest.approx(math.dist(estimate, THROW))
    assert metrics["relative_error"]["velocity"] == pytest.approx(math.dist(estimate, THROW) / math.sqrt(3))
    assert metrics["relative_error"]["velocity"] < 0.05
    record = json.loads((tmp_path / "out" / "params.json").read_text())
    assert record["velocity"] == list(estimate) and record["units"] == {n: "m/s" for n in VELOCITY_COMPONENTS}


def test_the_velocity_phase_runs_first_and_resumes_across_the_phases(thrown, tmp_path):
    settings = dict(
        parameters=("youngs_modulus",),
        learning_rates={"velocity": 0.25},
        iterations=2,
        estimate_velocity_frames=3,
        estimate_velocity_iterations=12,
        estimate_velocity_objects=(SINGLE_OBJECT,),
    )
    whole_opt = Optimization(thrown_config(thrown, tmp_path / "whole", **settings))
    whole = whole_opt.run()
    rows = whole.history
    assert [r["phase"] for r in rows] == ["velocity"] * 12 + ["main"] * 2
    assert [r["frames"] for r in rows] == [3] * 12 + [4] * 2
    # the velocity phase leaves the material at its guess, the main phase the velocity at its estimate
    assert len({r["z"]["youngs_modulus"] for r in rows[:13]}) == 1 < len({r["z"]["velocity_x"] for r in rows[:13]})
    assert len({tuple(r["z"][n] for n in VELOCITY_COMPONENTS) for r in rows[12:]}) == 1
    estimate = whole_opt.problem.velocities(whole.z)[0]
    assert math.dist(estimate, THROW) < 0.1 * math.dist((0, 0, 0), THROW), estimate

    cfg = thrown_config(thrown, tmp_path / "split", **settings)
    Optimization(cfg).run(stop_after=5)  # in the velocity phase
    Optimization(cfg).run(resume=True, stop_after=8)  # into the main phase
    assert json.loads((cfg.output / "checkpoint.json").read_text())["state"]["iteration"] == 13
    resumed = Optimization(cfg).run(resume=True)
    assert resumed.iteration == whole.iteration == 14
    assert resumed.z == whole.z and resumed.m == whole.m and resumed.v == whole.v
    assert [r["loss"] for r in resumed.history] == [r["loss"] for r in rows]
