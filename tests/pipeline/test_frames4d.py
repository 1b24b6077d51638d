"""clflow simulate CONFIG, clflow render4d and clflow optimize through the CLI; per-frame
Gaussians written and read back; atomic output."""

import json

import numpy as np
import pytest
import torch
import yaml
from click.testing import CliRunner

from clflow.fileio import WRITTEN_RECORD
from clflow.pipeline.forward import simulate_config
from clflow.pipeline.frames4d import export_gaussians, load_frames
from clflow.splat.geometry import quat_to_rotmat, rotmat_to_quat
from clflow.splat.ply import load_ply
from clflow_cli.main import cli


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def test_export_round_trip(demo_config, tmp_path):
    result = simulate_config(demo_config())
    export_gaussians(result, tmp_path / "sim")
    frames = load_frames(tmp_path / "sim")
    T = result.x.shape[0]
    assert (
        frames.frame_count == T
        and sorted(p.name for p in (tmp_path / "sim").glob("*.ply"))[-1] == f"frame_{T - 1:03d}.ply"
    )
    for t in (0, T - 1):
        want, got = result.scene_at(t), frames.scene_at(t)
        torch.testing.assert_close(got.means, want.means.float(), rtol=0, atol=1e-6)
        torch.testing.assert_close(got.covariances, want.covariances.float(), rtol=1e-5, atol=1e-9)
        torch.testing.assert_close(got.sh_rotations, want.sh_rotations.float(), rtol=0, atol=1e-6)
    # the PLY frame holds the same Gaussians (file frame = simulation frame for the demo)
    ply = load_ply(tmp_path / "sim" / f"frame_{T - 1:03d}.ply")
    want = result.scene_at(T - 1)
    torch.testing.assert_close(ply.means.double(), want.means.double(), rtol=0, atol=1e-6)
    torch.testing.assert_close(ply.covariances.double(), want.covariances.double(), rtol=1e-4, atol=1e-9)


def test_rotmat_to_quat_inverts_quat_to_rotmat():
    q = torch.nn.functional.normalize(
        torch.randn(200, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1)), dim=-1
    )
    q2 = rotmat_to_quat(quat_to_rotmat(q))
    torch.testing.assert_close(quat_to_rotmat(q2), quat_to_rotmat(q), rtol=0, atol=1e-12)


def test_simulate_config_then_render4d(quick_demo, tmp_path):
    out = tmp_path / "sim"
    res = run("simulate", quick_demo / "config_truth.yaml", "-o", out)
    assert res.exit_code == 0, res.output
    T = 9  # QUICK: 8 frames + the initial state
    assert len(list(out.glob("frame_*.ply"))) == T and (out / "gaussians.npz").is_file()
    # progress off a terminal: a line per frame simulated (8 frames: a tenth is one)
    steps = [line for line in res.output.splitlines() if line.startswith("simulating: ")]
    assert steps == [f"simulating: {k}/8 frame {k}" for k in range(1, 9)]
    # clflow view's reading of the folder: each frame where that frame's PLY has it (file frame)
    from clflow.view import load_scene

    scene = load_scene(out)
    ply = load_ply(out / f"frame_{T - 1:03d}.ply")
    np.testing.assert_allclose(np.concatenate([scene.means[-1], scene.static_means]), ply.means.numpy(), atol=1e-5)
    np.testing.assert_allclose(
        np.concatenate([scene.covariances[-1], scene.static_covariances]), ply.covariances.numpy(), rtol=1e-3, atol=1e-8
    )
    assert scene.frame_count == T and scene.camera is not None
    assert len(list((out / "guidance").glob("*.png"))) == T and (out / "guidance.mp4").stat().st_size > 0
    res = run("render4d", out, "--views", 1, "--format", "gif")
    assert res.exit_code == 0, res.output
    for name in ("guidance", "orbit", "view_0"):
        assert (out / "render4d" / f"{name}.gif").stat().st_size > 0
        assert len(list((out / "render4d" / name).glob("*.png"))) == T
    # the orbit starts at the guidance camera and then moves away from it
    import cv2

    first = [cv2.imread(str(out / "render4d" / n / "000.png")).astype(float) for n in ("guidance", "orbit")]
    middle = [cv2.imread(str(out / "render4d" / n / "004.png")).astype(float) for n in ("guidance", "orbit")]
    assert np.abs(first[0] - first[1]).mean() < 1.0 < np.abs(middle[0] - middle[1]).mean()
    view = cv2.imread(str(out / "render4d" / "view_0" / "000.png")).astype(float)
    assert np.abs(view - first[0]).mean() > 1.0  # a novel view: the one fixed view looks from the other side
    assert not list(out.rglob("*.tmp*"))


def test_simulate_with_optimised_parameters_and_bad_params_file(quick_demo, tmp_path):
    params = tmp_path / "params.json"
    params.write_text(
        json.dumps(
            {"material": "elastic", "parameters": {"youngs_modulus": 2e4, "poissons_ratio": 0.3}, "density": 1000.0}
        )
    )
    res = run(
        "simulate", quick_demo / "config.yaml", "--params-from", params, "-o", tmp_path / "a", "--preview", "none"
    )
    assert res.exit_code == 0, res.output
    truth = np.load(tmp_path / "a" / "gaussians.npz")["object_means"]
    run("simulate", quick_demo / "config_truth.yaml", "-o", tmp_path / "b", "--preview", "none")
    np.testing.assert_array_equal(truth, np.load(tmp_path / "b" / "gaussians.npz")["object_means"])
    params.write_text(json.dumps({"material": "sand", "parameters": {}, "density": 1.0}))
    res = run("simulate", quick_demo / "config.yaml", "--params-from", params)
    assert res.exit_code == 1 and "is for 'sand', the config simulates 'elastic'" in res.output
    res = run("simulate", quick_demo / "config.yaml", "--grid", 32)
    assert res.exit_code == 2 and "drop --grid" in res.output


def test_failed_export_leaves_no_partial_file(demo_config, tmp_path, monkeypatch):
    import clflow.splat.ply as ply

    result = simulate_config(demo_config())
    real, calls = ply.save_ply, []

    def failing(path, g, **kw):
        calls.append(path)
        if len(calls) == 3:
            raise OSError("disk full")
        return real(path, g, **kw)

    monkeypatch.setattr(ply, "save_ply", failing)
    with pytest.raises(OSError, match="disk full"):
        export_gaussians(result, tmp_path / "sim")
    names = sorted(p.name for p in (tmp_path / "sim").iterdir())
    assert names == [WRITTEN_RECORD, "frame_000.ply", "frame_001.ply", "gaussians.npz"]  # complete files only
    assert sorted(json.loads((tmp_path / "sim" / WRITTEN_RECORD).read_text())["files"]) == names[1:]
    for name in names[1:3]:
        load_ply(tmp_path / "sim" / name)


def test_render4d_without_a_simulation(tmp_path):
    res = run("render4d", tmp_path)
    assert res.exit_code == 1 and "gaussians.npz not found: run `clflow simulate CONFIG" in res.output


def test_optimize_cli_writes_results_and_resumes(quick_demo, tmp_path):
    out = tmp_path / "opt"
    res = run("optimize", quick_demo / "config.yaml", "--iterations", 1, "-o", out)
    assert res.exit_code == 0, res.output
    assert "optimised: youngs_modulus = " in res.output and "relative error vs ground truth" in res.output
    assert json.loads((out / "checkpoint.json").read_text())["state"]["iteration"] == 1
    res = run("optimize", quick_demo / "config.yaml", "--iterations", 2, "-o", out, "--resume")
    assert res.exit_code == 0, res.output
    assert len(json.loads((out / "history.json").read_text())) == 2


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("splats", "nope.ply", "splats: file not found"),
        ("object", {"select": {"sphere": {"center": [5, 5, 5], "radius": 0.1}}}, "object.select selects no Gaussian"),
        (
            "forces",
            [{"region": {"sphere": {"center": [3, 3, 3], "radius": 0.1}}, "acceleration": [1, 0, 0]}],
            r"forces\[0\].region holds no particle of the object",
        ),
        (
            "camera",
            {"position": [0, 0.1, -3], "look_at": [0, 0.1, -4], "width": 96, "height": 96},
            "the object is not visible from the guidance camera",
        ),
    ],
)
def test_optimize_cli_bad_config(quick_demo, tmp_path, key, value, message):
    import re

    data = yaml.safe_load((quick_demo / "config.yaml").read_text())
    data[key] = value
    data["output"] = str(tmp_path / "out")
    bad = quick_demo / f"bad_{key}.yaml"  # next to scene.ply, which it names relatively
    bad.write_text(yaml.safe_dump(data))
    res = run("optimize", bad)
    assert res.exit_code == 1 and re.search(message, res.output), res.output
    assert "Traceback" not in res.output


def test_set_overrides_config_keys_on_simulate_and_optimize(quick_demo, tmp_path):
    out = tmp_path / "short"
    res = run(
        "simulate",
        quick_demo / "config_truth.yaml",
        "--set",
        "simulation.frames=2",
        "--set",
        "material.parameters.youngs_modulus=3e4",
        "-o",
        out,
        "--preview",
        "none",
    )
    assert res.exit_code == 0, res.output
    assert len(list(out.glob("frame_*.ply"))) == 3  # 2 frames + the initial state, not the config's 8
    for command, item, message in [
        ("simulate", "simulation.framez=3", "simulation.framez: unknown key; known keys here:"),
        ("optimize", "material.parameters.youngs_modulus=soft", "youngs_modulus"),
        ("optimize", "optimize.iterations=2.5", "optimize.iterations: must be an integer >= 1, got 2.5"),
    ]:
        res = run(command, quick_demo / "config.yaml", "--set", item, "-o", tmp_path / "bad")
        assert res.exit_code == 1, res.output
        assert res.output.startswith(f"Error: --set {item}: ") and message in res.output
        assert res.output.count("\n") == 1
    assert not (tmp_path / "bad").exists()
    res = run("simulate", "--set", "simulation.frames=2", "-o", tmp_path / "shape")
    assert res.exit_code == 2 and "--set needs a scene CONFIG" in res.output
