"""flow.bias_correction: the flow estimator's error measured on the simulation's own rendered
video and subtracted from the observed flow (clflow.pipeline.fit.objective.Objective.calibrate)."""

import dataclasses
import json

import numpy as np
import pytest

from clflow.media import write_image
from clflow.pipeline.fit import Optimization
from clflow.pipeline.fit.objective import SUPERSAMPLE
from clflow.pipeline.forward import render_frames, simulate_config
from clflow_datasets.demo import TRUTH


def test_calibrated_at_the_parameters_that_made_the_video_the_residual_vanishes(demo_config, tmp_path):
    # guidance: the demo's simulation at the truth, rendered the way calibrate renders (pixels
    # area-averaged from SUPERSAMPLE^2 samples), so the estimator errs on both alike
    cfg = demo_config(iterations=1)
    truth = simulate_config(cfg, TRUTH)
    (tmp_path / "video").mkdir()
    for t, frame in enumerate(render_frames(truth, supersample=SUPERSAMPLE)):
        write_image(tmp_path / "video" / f"{t:03d}.png", frame)
    opt = Optimization(dataclasses.replace(cfg, video=tmp_path / "video"))
    state = opt.problem.initial_state()
    state.z = {n: float(p.encode(TRUTH[n])) for n, p in opt.problem.params.items()}
    at_truth = opt.objective.evaluate(state.z, opt.problem.frames, with_grad=False)
    raw = at_truth.loss
    assert raw > 1e-3  # DIS's own error on this video, px^2

    # the search's score of a sample: against the video's flow less the error at that sample
    assert (
        float(opt.objective.loss_of([at_truth.flows], opt.objective.estimator_errors(at_truth, opt.problem.frames)))
        < 1e-3 * raw
    )
    calibrated = opt.objective.calibrate(state, at_truth, opt.problem.frames)
    assert calibrated.calibrated_at == {"z": state.z, "frames": opt.problem.frames, "grid": opt.problem.model_grid}
    assert opt.objective.rescored(at_truth).loss < 1e-3 * raw  # the estimator's error cancels
    error = opt.objective.errors[0]
    assert error.shape == opt.problem.views[0].observed.shape and float(error.abs().max()) > 0.05
    # the loss of evaluate() itself fits the corrected target
    assert opt.objective.evaluate(state.z, opt.problem.frames, with_grad=False).loss == pytest.approx(
        opt.objective.rescored(at_truth).loss, abs=1e-9
    )


def test_the_default_corrects_and_none_leaves_the_observed_flow(demo_config):
    opt = Optimization(demo_config(iterations=2))
    assert opt.cfg.flow.bias_correction == "simulated"
    state = opt.run()
    assert state.calibrated_at is not None and any(row.get("calibrated") for row in state.history)
    assert (opt.cfg.output / "estimator_error.npz").exists()
    assert not bool((opt.objective.target(0) == opt.problem.views[0].observed).all())

    cfg = demo_config(iterations=2, name="plain")
    plain = Optimization(dataclasses.replace(cfg, flow=dataclasses.replace(cfg.flow, bias_correction="none")))
    state = plain.run()
    assert state.calibrated_at is None and plain.objective.target(0) is plain.problem.views[0].observed
    assert not (plain.cfg.output / "estimator_error.npz").exists()


@pytest.mark.parametrize("lose_the_file", [False, True])
def test_resume_restores_the_estimator_error(demo_config, lose_the_file):
    whole = Optimization(demo_config(iterations=3, name="whole")).run()
    cfg = demo_config(iterations=3, name="split")
    Optimization(cfg).run(stop_after=2)
    if lose_the_file:  # measured again at the checkpoint's calibration point
        (cfg.output / "estimator_error.npz").unlink()
    saved = json.loads((cfg.output / "checkpoint.json").read_text())["state"]
    assert saved["calibrated_at"] is not None
    resumed = Optimization(cfg).run(resume=True)
    assert resumed.z == whole.z
    assert [r["loss"] for r in resumed.history] == [r["loss"] for r in whole.history]


def test_a_lost_error_file_is_measured_again_at_the_calibration_point(demo_config):
    cfg = demo_config(iterations=2)
    state = Optimization(cfg).run()
    with np.load(cfg.output / "estimator_error.npz") as data:
        saved = data["view_0"]
    (cfg.output / "estimator_error.npz").unlink()
    at_point = dataclasses.replace(state, z=dict(state.calibrated_at["z"]))  # as after a rejected step
    fresh = Optimization(cfg)
    fresh.objective.restore_calibration(at_point)
    np.testing.assert_allclose(fresh.objective.errors[0].numpy(), saved, atol=1e-6)
    with np.load(cfg.output / "estimator_error.npz") as data:
        assert json.loads(str(data["key"])) == state.calibrated_at
