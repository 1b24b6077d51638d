"""`clflow bench optimize` on your own config or a benchmark case: timed iterations, the
scene's shape (particles a cell), and the config's own output folder left alone."""

import hashlib
import json

import pytest
import yaml
from click.testing import CliRunner

from clflow.scene.config import load_config
from clflow_cli.main import cli


def _files(folder):
    """Every path under ``folder`` with its content's hash and its modification time."""
    return sorted(
        (
            p.relative_to(folder),
            hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else None,
            p.stat().st_mtime_ns,
        )
        for p in folder.rglob("*")
    )


def test_a_config_is_timed_with_its_shape_and_its_output_left_alone(quick_demo, tmp_path):
    before = _files(quick_demo)
    record = tmp_path / "bench.json"
    config = quick_demo / "config.yaml"
    args = [
        "bench",
        "optimize",
        "--config",
        str(config),
        "--at-truth",
        "--iterations",
        "1",
        "--profile",
        "--json",
        str(record),
    ]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert "at rest:" in result.output and "particles a cell: median" in result.output
    scene = json.loads(record.read_text())["results"]["scene"]
    shape = scene["occupancy"]
    assert scene["particles"] == shape["particles"] > 0 and scene["method"] == "adam"
    results = json.loads(record.read_text())["results"]
    profile = results["profile"]  # the iteration's alone, not making and loading the scene
    assert profile["steps"]["adjoint substep"]["count"] > 0
    assert profile["wall_s"] <= results["run"]["wall_s"][0] + 0.5
    truth = load_config(config).ground_truth
    assert truth and all(scene["start"][n] == v for n, v in truth.items())  # --at-truth: from the truth
    assert 0 < shape["occupied_cells"] <= shape["cells"] and 1 <= shape["run_median"] <= shape["run_max"]
    assert _files(quick_demo) == before  # nothing written beside or inside the config's folder


def test_at_the_truth_needs_one(quick_demo, tmp_path):
    config = yaml.safe_load((quick_demo / "config.yaml").read_text())
    del config["evaluation"]
    for key in ("splats", "video"):  # the copy lies elsewhere: its files by absolute path
        config[key] = str(quick_demo / config[key])
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(config))
    result = CliRunner().invoke(cli, ["bench", "optimize", "--config", str(tmp_path / "config.yaml"), "--at-truth"])
    assert result.exit_code == 2 and "has no evaluation.ground_truth" in result.output, result.output


@pytest.mark.parametrize(
    "args, message",
    [
        (["--config", "{cfg}", "--case", "torus"], "--config and --case both choose the scene"),
        (["--config", "{cfg}", "--grid", "16"], "--grid size the demo-like scene"),
        (["--quick"], "--quick sizes a --case"),
        (["--case", "no_such_case"], "'no_such_case' is no case; the cases: droplet"),
    ],
)
def test_what_cannot_be_timed_is_refused_in_one_line(quick_demo, args, message):
    args = [a.format(cfg=quick_demo / "config.yaml") for a in args]
    result = CliRunner().invoke(cli, ["bench", "optimize", *args])
    assert result.exit_code == 2 and message in result.output, result.output
    assert "Traceback" not in result.output
