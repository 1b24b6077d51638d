"""clflow optimize on the reduced demo: recovery, resume, rollback, results."""

import dataclasses
import json
import logging
import math
from types import SimpleNamespace

import pytest

from clflow.errors import ClflowError
from clflow.pipeline.fit import Optimization, OptimizerState
from clflow.pipeline.fit.checkpoint import Checkpoint
from clflow.pipeline.fit.results import UNEXPLAINED_WARNING, unexplained_warning
from clflow.pipeline.fit.steps import Steps, horizon, rate_schedule
from clflow.pipeline.runs import write_results
from clflow_datasets.demo import TRUTH


def test_demo_recovers_youngs_modulus_from_a_10x_low_guess(demo_config):
    cfg = demo_config()
    assert cfg.objects[0].material.parameters["youngs_modulus"] == pytest.approx(TRUTH["youngs_modulus"] / 10)
    opt = Optimization(cfg)
    state = opt.run()
    final = opt.problem.values(state.z)["youngs_modulus"]
    assert abs(final - TRUTH["youngs_modulus"]) / TRUTH["youngs_modulus"] < 0.10
    losses = [row["loss"] for row in state.history]
    assert losses[1] < losses[0]

    metrics = write_results(opt, state)  # its flow loss: at the final parameters, all frames
    initial = opt.objective.evaluate(opt.problem.initial_state().z, cfg.simulation.frames, with_grad=False).loss
    assert metrics["flow_loss"] < 0.2 * initial
    assert metrics["relative_error"]["youngs_modulus"] < 0.10
    assert metrics["unexplained_motion"]["fraction"] < UNEXPLAINED_WARNING and "warnings" not in metrics
    out = cfg.output
    for name in ("params.json", "metrics.json", "history.json", "loss.png", "comparison.mp4", "checkpoint.json"):
        assert (out / name).stat().st_size > 0, name
    record = json.loads((out / "params.json").read_text())
    assert record["material"] == "elastic" and record["units"] == {"youngs_modulus": "Pa"}
    assert record["parameters"]["youngs_modulus"] == pytest.approx(final)
    assert not list(out.glob("*.tmp*")), "temporary files left behind"


def test_a_video_playing_at_another_speed_leaves_its_motion_unexplained_and_is_warned_of(
    demo_config, monkeypatch, caplog
):
    """At the true material the demo's guidance is explained but for a trace; read as a
    video played at 0.8x (its motion stretched over 1.25x the frames' real time) no
    material explains it: the result says so in one line, with the likely causes."""
    fractions = []
    for speed in (1.0, 0.8):
        cfg = demo_config(name=f"speed_{speed}")
        cfg = dataclasses.replace(cfg, simulation=dataclasses.replace(cfg.simulation, fps=cfg.simulation.fps * speed))
        opt = Optimization(cfg)
        state = opt.problem.initial_state()
        state.z["youngs_modulus"] = float(opt.problem.params["youngs_modulus"].encode(TRUTH["youngs_modulus"]))
        result = opt.objective.evaluate(state.z, cfg.simulation.frames, with_grad=False)
        opt.objective.calibrate(state, result, cfg.simulation.frames)  # the estimator's error there, as a fit's end
        fractions.append(opt.objective.unexplained_motion(result)["fraction"])
    assert fractions[0] < 0.02 < UNEXPLAINED_WARNING < fractions[1], fractions
    nothing = {
        "ranges": {},
        "weakly_constrained": [],
        "unresolved": [],
        "grids": [0],
        "grid_sensitive": [],
        "trade_offs": [],
    }
    monkeypatch.setattr(opt.diagnostics, "identifiability", lambda *args: nothing)
    with caplog.at_level(logging.WARNING, logger="clflow"):
        metrics = opt.results().result_metrics(state, result)
    line = unexplained_warning(fractions[1])
    assert metrics["unexplained_motion"]["fraction"] == fractions[1] and metrics["warnings"] == [line]
    assert [r.getMessage() for r in caplog.records] == [line]
    assert f"leaves {100 * fractions[1]:.0f} % of the observed motion unexplained" in line
    assert all(cause in line for cause in ("simulation.fps", "flow.stabilise", "optimize.material"))


def test_resume_after_an_interruption_gives_the_uninterrupted_result(demo_config):
    whole = Optimization(demo_config(iterations=4, name="whole")).run()
    cfg = demo_config(iterations=4, name="split")
    Optimization(cfg).run(stop_after=2)
    saved = json.loads((cfg.output / "checkpoint.json").read_text())["state"]
    assert saved["iteration"] == 2
    resumed = Optimization(cfg).run(resume=True)  # a fresh process would build a new Optimization too
    assert resumed.iteration == whole.iteration == 4
    assert resumed.z == whole.z and resumed.m == whole.m and resumed.v == whole.v
    assert [r["loss"] for r in resumed.history] == [r["loss"] for r in whole.history]


def test_a_failed_iteration_rolls_back_and_halves_the_step(demo_config, monkeypatch):
    opt = Optimization(demo_config(iterations=3))
    real = opt.objective.evaluate
    calls = []

    def flaky(z, frames, **kw):
        calls.append(dict(z))
        if len(calls) == 2:  # the second evaluation "blows up"
            raise FloatingPointError("the flow loss is not finite")
        return real(z, frames, **kw)

    monkeypatch.setattr(opt.objective, "evaluate", flaky)
    state = opt.run()
    assert state.iteration == 3 and state.step_scale == 0.5
    assert calls[2] == calls[0], "the retry starts from the last good parameters"


def test_repeated_failures_stop_with_the_reason_and_keep_the_checkpoint(demo_config, monkeypatch):
    opt = Optimization(demo_config(iterations=5))
    opt.run(stop_after=1)
    before = opt.checkpoint.path.read_text()

    def broken(z, frames, **kw):
        raise FloatingPointError("the gradient is not finite")

    monkeypatch.setattr(opt.objective, "evaluate", broken)
    with pytest.raises(ClflowError, match="optimisation stopped at iteration 1: the gradient is not finite"):
        opt.run(resume=True)
    assert opt.checkpoint.path.read_text() == before, "the last good checkpoint survives"


def test_adam_restarts_its_momentum_after_an_overshoot(demo_config):
    steps = Steps.__new__(Steps)  # adam_step reads the config alone
    steps.problem = SimpleNamespace(cfg=demo_config())
    state = OptimizerState(
        5,
        {"youngs_modulus": 4.5},
        {"youngs_modulus": -0.3},
        {"youngs_modulus": 1.0},
        history=[{"z": {"youngs_modulus": 4.3}}],
        momentum_steps=5,
    )
    # the last step went up by 0.2 and the gradient is now positive: uphill, so restart
    after = steps.adam_step(state, {"youngs_modulus": 2.0})
    assert after.momentum_steps == 1 and after.z["youngs_modulus"] < 4.5
    # the same step with a negative gradient keeps the momentum
    kept = steps.adam_step(state, {"youngs_modulus": -2.0})
    assert kept.momentum_steps == 6 and kept.m["youngs_modulus"] < -0.3


def test_schedules(demo_config):
    opt = dataclasses.replace(demo_config().optimize, iterations=11, final_rate=0.1, horizon_start=4, horizon_step=1)
    assert rate_schedule(opt, 0) == 1.0 and rate_schedule(opt, 10) == pytest.approx(0.1)
    assert rate_schedule(opt, 5) == pytest.approx(0.55)
    cfg = dataclasses.replace(demo_config(), optimize=opt)
    assert [horizon(cfg, i) for i in (0, 1, 4, 10)] == [4, 5, 8, 8]
    assert math.isclose(sum(rate_schedule(opt, i) for i in range(11)), 6.05, rel_tol=1e-12)


def test_a_video_file_keeps_its_own_frame_rate(demo_config, quick_demo, tmp_path):
    """The guidance frames as a 48 fps video (each frame twice) give the flow of the 24 fps
    image folder, not half of it."""
    import cv2
    import numpy as np

    from clflow.media import write_video
    from clflow.pipeline.forward import prepare

    frames = [
        cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB) for p in sorted((quick_demo / "guidance").glob("*.png"))
    ]
    write_video(tmp_path / "guidance48.mp4", np.stack([f for f in frames for _ in range(2)]), 48.0)
    folder_cfg = demo_config(name="folder")
    video_cfg = dataclasses.replace(demo_config(name="video"), video=tmp_path / "guidance48.mp4")
    T = folder_cfg.simulation.frames
    _, from_folder, _ = observed_flow_of(folder_cfg, prepare(folder_cfg), T)
    _, from_video, _ = observed_flow_of(video_cfg, prepare(video_cfg), T)
    speed = lambda flow: float(np.linalg.norm(flow, axis=-1).mean())  # noqa: E731
    assert speed(from_video) == pytest.approx(speed(from_folder), rel=0.15)


def test_the_guidance_is_stabilised_over_the_static_pixels_and_a_clean_one_left_as_it_is(
    demo_config, quick_demo, tmp_path
):
    """The demo's guidance seen by a camera drifting 0.6 px a frame with a flickering
    exposure: the optimiser's view of it shows a still floor and says what it removed; the
    clean guidance gives the flow of ``flow.stabilise: none`` to the bit."""
    import cv2
    import numpy as np
    import torch

    from clflow.media import write_image
    from clflow.pipeline.fit.guidance import guidance_views_of, static_pixels
    from clflow.pipeline.forward import prepare

    clean = demo_config(name="clean")
    prepared, T = prepare(clean), clean.simulation.frames
    static = static_pixels(prepared, prepared.camera)
    paths = sorted((quick_demo / "guidance").glob("*.png"))
    rng = np.random.default_rng(5)
    for k, path in enumerate(paths):
        frame = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB).astype(np.float64)
        shift = np.array([0.5, 0.3]) * k + rng.normal(0, 0.2, 2) * (k > 0)
        warp = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
        frame = cv2.warpAffine(frame, warp, frame.shape[1::-1], flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT101)
        gain = 1.0 + (0.05 if k % 2 else -0.04) * (k > 0)
        write_image(tmp_path / "shaken" / path.name, np.clip(gain * frame + 0.5, 0, 255).astype(np.uint8))
    shaken = dataclasses.replace(demo_config(name="shaken"), video=tmp_path / "shaken")
    (view,) = guidance_views_of(shaken, prepared, T)
    record = view.stabilisation
    assert (
        record["frames_changed"] == len(paths) - 1
        and record["motion_removed_px"]["max"] > 0.8 * math.hypot(0.5, 0.3) * T
    )
    assert record["exposure_removed_grey_levels"] > 3.0
    inner = static.copy()
    margin = math.ceil(record["motion_removed_px"]["max"]) + 4  # the warp's replicated border
    inner[:margin], inner[-margin:], inner[:, :margin], inner[:, -margin:] = False, False, False, False
    (steady,) = guidance_views_of(clean, prepared, T)
    raw = dataclasses.replace(demo_config(name="raw"), flow=dataclasses.replace(clean.flow, stabilise="none"))
    (unstabilised,) = guidance_views_of(raw, prepared, T)
    assert steady.stabilisation["frames_changed"] == 0 and unstabilised.stabilisation is None
    assert torch.equal(steady.observed, unstabilised.observed)
    # the shaken video's flow outside the object, stabilised, is the steady camera's
    shaken_raw = dataclasses.replace(shaken, output=tmp_path / "shaken_raw", flow=raw.flow)
    (drifting,) = guidance_views_of(shaken_raw, prepared, T)
    off = lambda v: float((v.observed - steady.observed).norm(dim=-1)[:, torch.from_numpy(inner)].mean())  # noqa: E731
    assert off(view) < 0.3 and off(view) < 0.4 * off(drifting)  # 0.22 against 0.75 px when written


def test_the_cached_observed_flow_is_reused_only_with_the_same_confidence_setting(demo_config, monkeypatch):
    import numpy as np

    import clflow.flow.optical_flow
    from clflow.pipeline.forward import prepare

    cfg = demo_config()
    with_confidence = dataclasses.replace(cfg, flow=dataclasses.replace(cfg.flow, confidence="forward_backward"))
    without = dataclasses.replace(cfg, flow=dataclasses.replace(cfg.flow, confidence="none"))
    prepared, T = prepare(cfg), cfg.simulation.frames
    _, flow, confidence = observed_flow_of(with_confidence, prepared, T)
    assert confidence.shape == flow.shape[:-1] == (T, cfg.camera.height, cfg.camera.width)
    assert 0.0 <= confidence.min() < 0.5 and confidence.max() <= 1.0  # the cube's edges occlude the floor
    _, flow_again, ones = observed_flow_of(without, prepared, T)  # same folder, other setting: recomputed
    assert np.array_equal(flow_again, flow) and np.all(ones == 1.0)

    def no_estimator(*args, **kwargs):
        raise AssertionError("the cache should have been used")

    observed_flow_of(with_confidence, prepared, T)  # recomputed and cached again
    monkeypatch.setattr(clflow.flow.optical_flow, "observed_flow", no_estimator)
    _, cached_flow, cached = observed_flow_of(with_confidence, prepared, T)
    assert np.array_equal(cached_flow, flow) and np.array_equal(cached, confidence)


def test_resume_refuses_a_changed_config_and_names_what_changed(tmp_path):
    import dataclasses

    from clflow.errors import InputError
    from clflow.pipeline.fit import OptimizerState
    from clflow.scene.config import parse_config

    (tmp_path / "scene.ply").write_bytes(b"ply\n")
    data = {
        "splats": "scene.ply",
        "object": {"select": {"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}},
        "material": {"type": "elastic", "parameters": {"youngs_modulus": 1e4}},
        "camera": {"position": [0, 1, 3], "look_at": [0, 0, 0]},
        "optimize": {"parameters": ["youngs_modulus"]},
    }
    cfg = parse_config(data, "scene.yaml", tmp_path)

    def checkpointing(cfg):  # just what a checkpoint reads of its problem, without the scene's preparation
        return Checkpoint(tmp_path / "checkpoint.json", SimpleNamespace(cfg=cfg, variables=("youngs_modulus",)))

    state = OptimizerState(3, {"youngs_modulus": 1.0}, {"youngs_modulus": 0.0}, {"youngs_modulus": 0.0})
    checkpointing(cfg).save(state)
    assert checkpointing(dataclasses.replace(cfg, output=tmp_path / "elsewhere")).load().iteration == 3
    longer = dataclasses.replace(cfg, optimize=dataclasses.replace(cfg.optimize, iterations=60))
    assert checkpointing(longer).load().iteration == 3  # --resume --iterations N extends a run
    changed = dataclasses.replace(cfg, scale=2.0, simulation=dataclasses.replace(cfg.simulation, frames=99))
    with pytest.raises(
        InputError,
        match=r"config changed since it was saved \(scale, simulation\); "
        r"give another -o/--out, or delete the checkpoint",
    ):
        checkpointing(changed).load()


def observed_flow_of(cfg, prepared, frames):
    """View 0's guidance frames at the simulation's frame times (stabilised as the config
    asks), their flow and its confidence, cached in output/observed_flow.npz, as the optimiser
    reads them."""
    from clflow.pipeline.fit.guidance import cached_observed_flow, guidance_video, observed_flow_cache, static_pixels

    video = guidance_video(cfg, cfg.video, prepared.camera, frames)
    static = static_pixels(prepared, prepared.camera)
    return cached_observed_flow(cfg, cfg.video, video.frames, static, observed_flow_cache(cfg, 0))[:3]
