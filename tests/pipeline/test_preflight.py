"""Probes of clflow optimize / simulate: stiff materials refused before any work
with the numbers and the ways out, progress within long frames, unstable iterations never
accepted, guidance videos that do not fit the scene refused, force stages that never act."""

import dataclasses
import json
import logging
import re

import numpy as np
import pytest
import torch
import yaml
from click.testing import CliRunner

from clflow.media import write_image
from clflow.pipeline.fit import Optimization
from clflow.pipeline.runs import write_results
from clflow_cli.main import cli


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def bad_config(quick_demo, tmp_path, name, **changes):
    """The demo's config with top-level ``changes`` (a dict merges into its section), next to
    scene.ply, its output in tmp_path."""
    data = yaml.safe_load((quick_demo / "config.yaml").read_text())
    for key, value in changes.items():
        data[key] = {**data[key], **value} if isinstance(value, dict) and isinstance(data.get(key), dict) else value
    data["output"] = str(tmp_path / "out")
    path = quick_demo / f"preflight_{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def one_line_error(res, pattern):
    assert res.exit_code == 1, res.output
    assert "Traceback" not in res.output
    errors = [line for line in res.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1 and re.search(pattern, errors[0]), res.output
    return errors[0]


# -- 1. stiff materials: substeps and predicted time, a limit the user can raise ----------------


@pytest.mark.parametrize("parameters", [{"poissons_ratio": 0.4999999}, {"youngs_modulus": 2e11}], ids=["nu", "steel"])
@pytest.mark.parametrize("command", ["optimize", "simulate"])
def test_a_stiff_material_is_refused_before_any_work(quick_demo, tmp_path, parameters, command):
    data = yaml.safe_load((quick_demo / "config.yaml").read_text())
    path = bad_config(
        quick_demo,
        tmp_path,
        f"stiff_{command}",
        material={"parameters": {**data["material"]["parameters"], **parameters}},
    )
    extra = ["--preview", "none"] if command == "simulate" else []
    line = one_line_error(
        run(command, path, *extra),
        r"the simulation needs \d+ substeps per frame \(dt = .* s, "
        r"limited by elastic wave speed .* m/s of elastic, about .* s per frame\), beyond the "
        r"limit of 2000; ways out: a softer proxy material .*a coarser grid .*--max-substeps N",
    )
    assert "simulation.substep_dt" not in line  # a fixed step above the stable one is refused: no way out


def test_the_substep_limit_is_the_users(quick_demo, tmp_path, caplog):
    path = bad_config(quick_demo, tmp_path, "limit")
    one_line_error(
        run("simulate", path, "--max-substeps", 4, "--preview", "none"),
        r"needs 5 substeps per frame .* beyond the limit of 4",
    )
    one_line_error(
        run("optimize", bad_config(quick_demo, tmp_path, "limit_key", simulation={"max_substeps": 4})),
        r"needs 5 substeps per frame .* beyond the limit of 4",
    )
    with caplog.at_level(logging.INFO):
        res = run("simulate", path, "--max-substeps", 5, "--preview", "none", "-o", tmp_path / "sim")
    assert re.search(
        r"simulation: 5 substeps per frame \(dt = 0.00833 s, limited by elastic wave speed .*\), "
        r"1,867 particles, 8 frames: about .* s",
        caplog.text,
    ), caplog.text
    # at 5 the push breaks the CFL limit, and 10 is beyond the limit: an error, not exit 0; it runs at 20
    one_line_error(res, r"breaks the CFL limit .* \(the limit is 5 substeps per frame: --max-substeps\)")
    assert run("simulate", path, "--max-substeps", 20, "--preview", "none", "-o", tmp_path / "sim").exit_code == 0


def test_the_particle_simulate_refuses_too_many_substeps(tmp_path):
    one_line_error(
        run(
            "simulate",
            "--grid",
            16,
            "--frames",
            1,
            "-p",
            "youngs_modulus=1e12",
            "--preview",
            "none",
            "-o",
            tmp_path / "sim",
        ),
        r"\d+ substeps per frame .* beyond the limit of 2000; ways out: a "
        r"softer material, a coarser --grid, .*--max-substeps N",
    )


def test_a_long_frame_logs_its_progress(monkeypatch, caplog):
    import clflow.mpm.simulator as simulator
    from clflow.mpm import Grid, MaterialSpec, Simulator
    from clflow.mpm.autograd import simulate

    monkeypatch.setattr(simulator, "PROGRESS_SECONDS", 0.0)
    x = torch.rand(64, 3, dtype=torch.float64) * 0.2 + 0.4
    sim = Simulator(
        x, 1e-5, MaterialSpec("elastic", {"youngs_modulus": 1e4}), Grid((16, 16, 16), 1 / 16), frame_dt=0.01, substeps=3
    )
    E = torch.tensor(1e4, dtype=torch.float64, requires_grad=True)
    with caplog.at_level(logging.INFO, logger="clflow.mpm"):
        sim.run(2)
        simulate(sim, 1, params={"youngs_modulus": E}).x.sum().backward()
    assert "simulation: frame 2/2, substep 3/3" in caplog.text
    assert "differentiable run: frame 1/1, substep 2/3" in caplog.text
    assert "adjoint: frame 1/1, substep 3/3" in caplog.text


# -- 2. an unstable iteration is never accepted -------------------------------------------------


def test_clamped_and_cfl_breaking_runs_are_flagged():
    from clflow.mpm import Grid, MaterialSpec, Simulator
    from clflow.mpm.autograd import simulate

    grid = Grid((16, 16, 16), 1 / 16)
    x = torch.stack(torch.meshgrid(*[torch.linspace(0.7, 0.85, 4)] * 3, indexing="ij"), -1).reshape(-1, 3)
    sim = Simulator(
        x,
        1e-5,
        MaterialSpec("elastic", {"youngs_modulus": 1e4}),
        grid,
        velocities=torch.tensor([[20.0, 0, 0]]).expand(64, 3),
        gravity=(0, 0, 0),
        walls=None,
        frame_dt=0.02,
        substeps=40,
    )
    with pytest.warns(RuntimeWarning):
        frames = simulate(sim, 1)
    assert frames.clamped > 0 and frames.unstable.endswith("particles left the grid and were clamped to its boundary")
    sim.use_substeps(1)  # 20 m/s x 0.02 s is 6 cells a substep
    with pytest.warns(Warning):
        frames = simulate(sim, 1)
    assert frames.cfl_violation and "breaks the CFL limit" in frames.unstable


def probe_config(demo_config, iterations=8):
    """The unstable-iteration probe: a fixed substep_dt (stable up to E = 4.7e4 Pa) and a rate of 1.5
    decades per iteration from E = 2e3 Pa (truth 2e4)."""
    cfg = demo_config(iterations=iterations)
    return dataclasses.replace(
        cfg,
        simulation=dataclasses.replace(cfg.simulation, substep_dt=1 / 24 / 20),
        optimize=dataclasses.replace(cfg.optimize, learning_rates={"youngs_modulus": 1.5}),
    )


def test_a_fixed_substep_and_a_large_rate_never_accept_an_unstable_iteration(demo_config):
    from clflow.pipeline.forward import scene_values
    from clflow.pipeline.simulation import build_simulator

    opt = Optimization(probe_config(demo_config))
    state = opt.run()
    assert state.rollbacks, "the 1.5-decade step to 6.3e4 Pa is beyond the fixed substep's stable range"
    first = state.rollbacks[0]
    assert first["iteration"] == 1 and first["params"]["youngs_modulus"] == pytest.approx(63245.55, rel=1e-4)
    assert "exceeds the stable step" in first["reason"]
    assert first["back_to"]["youngs_modulus"] == pytest.approx(2000.0)
    for row in state.history:  # every accepted iteration: stable at its own parameters
        sim = build_simulator(opt.cfg, opt.problem.prepared.setup, scene_values(opt.cfg, row["params"]))
        assert sim.stable_substeps() <= row["substeps"], row
        opt.objective.evaluate(row["z"], row["frames"], with_grad=False)  # raises UnstableRun on CFL / clamping / dt
    final = opt.problem.values(state.z)["youngs_modulus"]
    assert abs(final - 2e4) / 2e4 < 0.3
    metrics = write_results(opt, state)
    assert json.loads((opt.cfg.output / "metrics.json").read_text())["rollbacks"] == metrics["rollbacks"]
    assert metrics["rollbacks"][0]["reason"] == first["reason"]


def test_a_clamped_iteration_is_rolled_back(demo_config, monkeypatch):
    from clflow.pipeline.fit import population  # where the objective's runs are made (run_point)

    real, calls = population.run, []

    def clamping(*args, **kwargs):
        out = real(*args, **kwargs)  # Frames, or (Frames, what its reader read)
        calls.append(1)
        if len(calls) != 2:
            return out
        frames = out[0] if isinstance(out, tuple) else out
        frames.clamped = 7
        return out

    monkeypatch.setattr(population, "run", clamping)
    opt = Optimization(demo_config(iterations=2))
    calls.clear()  # the pre-flight's runs
    state = opt.run()
    assert state.iteration == 2 and state.step_scale == 0.5
    assert [r["reason"] for r in state.rollbacks] == ["7 particles left the grid and were clamped to its boundary"]


def test_an_iteration_beyond_the_substep_limit_is_rolled_back(demo_config):
    cfg = demo_config(iterations=2)
    cfg = dataclasses.replace(
        cfg,
        simulation=dataclasses.replace(cfg.simulation, max_substeps=22),
        optimize=dataclasses.replace(cfg.optimize, learning_rates={"youngs_modulus": 1.5}),
    )
    state = Optimization(cfg).run()  # the start needs 5 (20 after its CFL retries), the step to 6.3e4 Pa 24
    assert state.iteration == 2 and len(state.rollbacks) == 1
    reason = state.rollbacks[0]["reason"]
    assert re.search(r"needs 2\d substeps per frame .* beyond the limit of 22", reason) and "substep_dt" not in reason
    assert all(row["params"]["youngs_modulus"] == pytest.approx(2000.0) for row in state.history)


def test_a_fixed_substep_too_long_for_the_start_is_refused(quick_demo, tmp_path):
    one_line_error(
        run("optimize", bad_config(quick_demo, tmp_path, "long_dt", simulation={"substep_dt": 0.02})),
        r"simulation.substep_dt = 0.02 s is above the stable step 0.00833 s of the starting parameters "
        r"\(elastic wave speed .*\); the optimiser rejects unstable runs",
    )


# -- 3. guidance videos that do not fit the scene -----------------------------------------------


def video(tmp_path, name, frames):
    folder = tmp_path / name
    folder.mkdir()
    for t, frame in enumerate(frames):
        write_image(folder / f"{t:03d}.png", frame)
    return str(folder)


@pytest.mark.parametrize(
    "case, pattern",
    [
        ("grey", r"does not look like the scene .*correlation 0.00.*; the video shows no motion inside the loss mask"),
        ("noise", r"does not look like the scene .*the observed flow is unreliable inside the loss mask \(\d+ % of"),
        (
            "behind",
            r"the simulated motion at the starting parameters points against the video's over the first 3 "
            r"frames \(cosine -0.\d+; is the camera on the other side",
        ),
        ("inside", r"the object covers 100 % of the image \(more than 90 %: is the camera inside the object\?\)"),
    ],
)
def test_a_video_that_does_not_fit_the_scene_is_refused(quick_demo, tmp_path, case, pattern):
    data = yaml.safe_load((quick_demo / "config.yaml").read_text())
    shape = (data["simulation"]["frames"] + 1, data["camera"]["height"], data["camera"]["width"], 3)
    changes = {
        "grey": {"video": video(tmp_path, "grey", np.full(shape, 128, np.uint8))},
        "noise": {"video": video(tmp_path, "noise", np.random.default_rng(0).integers(0, 256, shape, np.uint8))},
        "behind": {"camera": {"position": [-0.25, 0.45, -0.75]}},  # the demo's camera mirrored through the cube
        "inside": {"camera": {"position": [0.0, 0.12, 0.01]}},
    }[case]
    one_line_error(
        run("optimize", bad_config(quick_demo, tmp_path, case, **changes)),
        r"the guidance video does not fit the scene: .*" + pattern + r".*optimise anyway with --force-video",
    )


def test_a_forced_bad_video_is_warned_about_and_recorded(quick_demo, tmp_path):
    data = yaml.safe_load((quick_demo / "config.yaml").read_text())
    shape = (data["simulation"]["frames"] + 1, data["camera"]["height"], data["camera"]["width"], 3)
    path = bad_config(quick_demo, tmp_path, "forced", video=video(tmp_path, "grey", np.full(shape, 128, np.uint8)))
    res = run("optimize", path, "--force-video", "--iterations", 1)
    assert res.exit_code == 0, res.output
    assert "WARNING: the video shows no motion inside the loss mask" in res.output
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert any("no motion" in w for w in metrics["warnings"]) and metrics["guidance_checks"][0]["motion_px"] == 0.0


def test_the_demo_passes_the_guidance_checks(demo_config):
    check = Optimization(demo_config()).guidance[0]
    assert check.problems() == []
    assert check.appearance > 0.99 and check.agreement > 0.5 and check.motion_px > 1.0 and check.confident > 0.8
    assert 0.05 < check.coverage < 0.5


# -- 4. force stages ----------------------------------------------------------------------------


def test_a_force_stage_after_the_simulated_time_is_refused(quick_demo, tmp_path):
    data = yaml.safe_load((quick_demo / "config.yaml").read_text())
    late = [{**data["forces"][0], "start": 5.0, "end": 6.0}]
    for command in ("optimize", "simulate"):
        one_line_error(
            run(command, bad_config(quick_demo, tmp_path, f"late_{command}", forces=late)),
            r"forces\[0\] starts at 5 s, after the simulated 0.3333 s \(8 frames at 24 fps\): it would "
            r"never act",
        )


def test_a_force_region_without_particles_is_one_setup_error(quick_demo, tmp_path):
    forces = [{"region": {"sphere": {"center": [3, 3, 3], "radius": 0.1}}, "acceleration": [1, 0, 0]}]
    line = one_line_error(
        run("optimize", bad_config(quick_demo, tmp_path, "empty_region", forces=forces)),
        r"forces\[0\].region holds no particle of the object \(the object spans \(.*\) .. \(.*\) m",
    )
    assert "optimisation stopped" not in line and "failed" not in line
    assert not re.search(r"\d\.\d{6,}", line), "coordinates in float32 digits"
