"""``clflow flow VIDEO``."""

import numpy as np
from click.testing import CliRunner

from clflow.fileio import WRITTEN_RECORD
from clflow.flow.flo import read_flo
from clflow.flow.video import read_video
from clflow.media import write_video
from clflow_cli.main import cli


def test_flow_command_writes_fields_and_visualisation(tmp_path, translating):
    frames, truth = translating
    path = tmp_path / "guide.mkv"
    write_video(path, frames, 10.0)
    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ["flow", str(path), "-o", str(out), "--box", "8,8,72,56", "--stride", "1"])
    assert result.exit_code == 0, result.output
    assert "6 frames, 80x64, 10 fps" in result.output and "5 flow fields" in result.output
    # progress off a terminal: a line per step (forward flows, backward flows, files)
    steps = [line for line in result.output.splitlines() if line.startswith("optical flow: ")]
    assert steps[0] == "optical flow: 1/15 dis" and steps[9] == "optical flow: 10/15 dis"
    assert steps[-1] == "optical flow: 15/15 flow_0004" and len(steps) == 15
    data = np.load(out / "flow.npz")
    assert data["flow"].shape == (5, 64, 80, 2) and data["valid"].shape == (5, 64, 80)
    np.testing.assert_allclose(data["times"], np.arange(6) / 10.0)
    assert str(data["method"]) == "dis" and float(data["fps"]) == 10.0
    valid = data["valid"]
    assert valid.mean() > 0.5 and not valid[:, :4].any()  # outside the box
    assert np.abs(data["flow"] - truth)[valid].mean() < 0.2
    for t in range(5):
        assert np.array_equal(read_flo(out / "flo" / f"flow_{t:04d}.flo"), data["flow"][t])
    assert len(list((out / "png").glob("flow_*.png"))) == 5
    panels = read_video(out / "flow.mp4")
    assert panels.frames.shape == (5, 64, 160, 3)
    assert [p.name for p in out.rglob(".*")] == [WRITTEN_RECORD]  # one record, no temporary file left behind
    # again on the first 3 frames: the earlier run's frames 2-4 go with it, none left to mix in;
    # a file of the user's beside them stays as it was, byte for byte
    (out / "notes.txt").write_text("mine")
    result = CliRunner().invoke(cli, ["flow", str(path), "-o", str(out), "--end", "0.25"])
    assert (out / "notes.txt").read_bytes() == b"mine" and path.is_file()
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (out / "flo").iterdir()) == ["flow_0000.flo", "flow_0001.flo"]
    assert len(list((out / "png").iterdir())) == 2 and np.load(out / "flow.npz")["flow"].shape[0] == 2


def test_flow_command_window_and_errors(tmp_path, translating):
    path = tmp_path / "guide.mkv"
    write_video(path, translating[0], 10.0)
    runner = CliRunner()
    result = runner.invoke(
        cli, ["flow", str(path), "-o", str(tmp_path / "w"), "--start", "0.1", "--end", "0.4", "--no-video"]
    )
    assert result.exit_code == 0, result.output
    assert np.load(tmp_path / "w" / "flow.npz")["flow"].shape[0] == 2
    assert not (tmp_path / "w" / "flow.mp4").exists()
    result = runner.invoke(cli, ["flow", str(path), "-o", str(tmp_path / "r"), "--sim-fps", "20", "--no-video"])
    assert result.exit_code == 0, result.output
    data = np.load(tmp_path / "r" / "flow.npz")
    np.testing.assert_allclose(data["times"], np.arange(11) / 20.0)  # 0 .. 0.5 s at 20 frames/s
    assert data["flow"].shape[0] == 10 and float(data["fps"]) == 20.0
    result = runner.invoke(cli, ["flow", str(path), "-o", str(tmp_path / "x"), "--start", "0.5"])
    assert result.exit_code == 1 and "optical flow needs at least 2 frames, the video has 1" in result.output
    assert "Traceback" not in result.output and not (tmp_path / "x").exists()
    result = runner.invoke(cli, ["flow", str(tmp_path / "nope.mp4")])
    assert result.exit_code == 1 and "nope.mp4: no such video file or image folder" in result.output
    result = runner.invoke(cli, ["flow", str(path), "-o", str(tmp_path / "m"), "--mask", str(tmp_path / "none.png")])
    assert result.exit_code == 1 and "none.png: not a readable mask image" in result.output
    result = runner.invoke(cli, ["flow", str(path), "--box", "1,2,3"])
    assert result.exit_code == 2 and "expected x0,y0,x1,y1" in result.output


def test_bench_flow_runs_small():
    result = CliRunner().invoke(
        cli, ["bench", "flow", "--frames", "3", "--size", "64", "-n", "300", "--sim-frames", "1"]
    )
    assert result.exit_code == 0, result.output
    assert "dis medium" in result.output and "affine render + loss + backward" in result.output
