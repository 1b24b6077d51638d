"""`clflow demo --quick`: the README's main job, end to end in a temporary folder."""

import json

from click.testing import CliRunner

from clflow_cli.main import cli


def test_quick_demo_end_to_end(tmp_path):
    res = CliRunner().invoke(cli, ["demo", str(tmp_path / "demo"), "--quick", "--views", "1"], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    results = tmp_path / "demo" / "results"
    metrics = json.loads((results / "metrics.json").read_text())
    assert metrics["relative_error"]["youngs_modulus"] < 0.10
    assert "relative error vs ground truth: youngs_modulus" in res.output
    for video in ("guidance", "orbit", "view_0"):
        assert (results / "simulation" / "render4d" / f"{video}.mp4").stat().st_size > 0
    assert (results / "simulation" / "frame_008.ply").is_file()
