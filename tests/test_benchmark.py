"""clflow.benchmark: the one timing helper of `clflow bench ...`, and `--json`."""

import json
import time

import pytest
import torch
from click.testing import CliRunner

from clflow.benchmark import Stopwatch, measure
from clflow.fileio import WRITTEN_RECORD
from clflow_cli.bench import BENCHMARKS
from clflow_cli.main import cli


def test_measure_warms_up_then_times_each_call_with_its_setup():
    calls = []
    timing = measure(lambda arg: calls.append(arg) or len(calls), repeats=3, warmup=2, setup=lambda: "x")
    assert calls == ["x"] * 5 and timing.result == 5  # 2 untimed, 3 timed; the last call's result
    assert len(timing.wall) == len(timing.cpu) == 3 and all(w >= 0 for w in timing.wall)
    assert timing.load_before is not None and timing.load_after is not None
    with pytest.raises(ValueError, match="repeats must be >= 1"):
        measure(lambda: None, repeats=0)


def test_wall_time_counts_sleep_and_cpu_time_counts_work():
    asleep = measure(lambda: time.sleep(0.05), repeats=2, warmup=0)
    assert min(asleep.wall) >= 0.05 and asleep.median_cpu < asleep.median_wall / 2

    def work():
        deadline = time.process_time() + 0.05
        while time.process_time() < deadline:
            pass

    busy = measure(work, warmup=0)
    assert busy.median_cpu >= 0.05
    record = busy.record()
    assert record["runs"] == 1 and record["median_wall_s"] == busy.wall[0] and record["cores"] >= 1


def test_stopwatch_skips_warm_ups_and_blocks_that_raise():
    watch = Stopwatch()
    for seconds in (0.03, 0.0, 0.0):
        with watch:
            time.sleep(seconds)
    with pytest.raises(RuntimeError), watch:
        raise RuntimeError
    timing = watch.timing(skip=1)
    assert len(timing.wall) == 2 and max(timing.wall) < 0.03


def test_every_bench_has_json_and_ply_writes_figures_with_the_environment(tmp_path):
    for name in BENCHMARKS:
        assert "--json PATH" in CliRunner().invoke(cli, ["bench", name, "--help"]).output, name
    out = tmp_path / "ply.json"
    res = CliRunner().invoke(
        cli,
        ["bench", "ply", "--gaussians", "200", "--points", "50", "--repeat", "2", "--json", str(out)],
        catch_exceptions=False,
    )
    assert res.exit_code == 0, res.output
    record = json.loads(out.read_text())
    assert record["benchmark"] == "ply" and record["parameters"] == {
        "count": 200,
        "sh_degree": 3,
        "points": 50,
        "repeat": 2,
    }
    results = record["results"]
    assert results["save_s"] > 0 and results["load_s"] > 0 and results["from_points_s"] > 0
    assert f"{results['save_s']:6.2f} s" in res.output  # the printed figure is the recorded one
    env = record["environment"]
    assert env["torch"] == torch.__version__ and env["device"] and "load" in env
    assert sorted(p.name for p in tmp_path.iterdir()) == [WRITTEN_RECORD, "ply.json"]  # no temporary left


def test_bench_mpm_adjoint_runs_a_small_block_and_records_both_passes(tmp_path):
    out = tmp_path / "adjoint.json"
    args = ["bench", "mpm-adjoint", "--particles", "128", "--grid", "16", "--frames", "1", "--substeps", "2"]
    res = CliRunner().invoke(cli, [*args, "--json", str(out)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    results = json.loads(out.read_text())["results"]
    assert results["particles"] == 128 and results["forward"]["median_wall_s"] > 0
    assert results["backward_over_forward"] > 0 and "backward" in res.output


def test_clflow_profile_records_every_kernel_of_any_command(tmp_path, device):
    """`clflow --profile PATH COMMAND`: the table of device time per kernel at the end and the
    summary as JSON (with the environment), whatever the command; here a small raster bench."""
    path = tmp_path / "profile.json"
    args = ["--profile", str(path), "bench", "raster", "-n", "300", "--size", "64", "--repeat", "1"]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert "kernel profile:" in res.output
    record = json.loads(path.read_text())
    assert record["parameters"]["command"] and record["environment"]["device"]
    kernels = {row["kernel"]: row for row in record["results"]["kernels"]}
    assert {"project_forward", "reduce_slots"} <= set(kernels)  # the rasteriser's first and last
    assert record["results"]["launches"] == sum(row["launches"] for row in kernels.values())
    assert all(row["device_s"] > 0 for row in kernels.values())


def test_bench_launch_times_the_substep_loop_and_each_launch_phase(tmp_path, device):
    out = tmp_path / "launch.json"
    res = CliRunner().invoke(cli, ["bench", "launch", "--substeps", "2", "--calls", "3", "--json", str(out)])
    assert res.exit_code == 0, res.output
    results = json.loads(out.read_text())["results"]
    assert set(results["sizes"]) == {"512", "4096", "32768"}
    assert all(0 < s["host_us_per_substep"] <= s["wall_us_per_substep"] for s in results["sizes"].values())
    assert all(0 < s["host_cpu_us_per_substep"] for s in results["sizes"].values())
    assert len(results["phases"]) == 2 and any(name.startswith("g2p") for name in results["phases"])
    assert all(p["enqueue_us"] > 0 and p["arguments"] > 5 for p in results["phases"].values())
    population = results["population"]
    assert (population["members"], population["particles_per_member"]) == (24, 512)
    share = population["host_us_per_member_substep"] / results["sizes"]["512"]["host_us_per_substep"]
    assert share == pytest.approx(population["host_share_of_single"]) and 0 < share
    assert "launch" not in vars(device)  # the recording stand-in is gone: launches enqueue again
