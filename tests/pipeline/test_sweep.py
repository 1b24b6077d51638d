"""``clflow sweep``: the spec's checks, a sweep on an embedded local Ray with a failing and a
timed-out run, reruns, and the serial path giving the same results."""

import json
import shutil
import sys

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from clflow.errors import InputError
from clflow.fileio import atomic_write_text
from clflow.sweep import load_spec
from clflow_cli.main import cli

# four runs of the quick demo's simulate: two good, one that raises (its output is over its
# own --max-output-gb), one that cannot finish in its time limit
FOUR_RUNS = {
    "command": "simulate",
    "base": "demo/config.yaml",
    "options": {"preview": "none"},
    "set": {"simulation.frames": 2},
    "timeout": 300,
    "grid": {"material.parameters.youngs_modulus": [2.0e3, 2.0e4]},
    "runs": [
        {"name": "fails", "config": "demo/config.yaml", "options": {"max_output_gb": 1.0e-9}},
        {"name": "slow", "config": "demo/config.yaml", "set": {"simulation.frames": 2000}, "timeout": 2},
    ],
}


@pytest.fixture
def spec_dir(quick_demo, tmp_path):
    """tmp_path with the quick demo in demo/ and a ``write(spec) -> path`` helper."""
    (tmp_path / "demo").symlink_to(quick_demo)

    def write(spec, name="spec.yaml"):
        path = tmp_path / name
        path.write_text(yaml.safe_dump(spec))
        return path

    return tmp_path, write


def _sweep(*args):
    return CliRunner().invoke(cli, ["sweep", *map(str, args)])


@pytest.mark.parametrize(
    "change, message",
    [
        ({"colour": 1}, "unknown key 'colour'"),
        ({"command": "render"}, "unknown command 'render'"),
        ({"base": "demo/nowhere.yaml"}, "config demo/nowhere.yaml not found"),
        ({"grid": {"simulation.framez": [1, 2]}}, "framez"),
        ({"grid": {"material.parameters.youngs_modulus": [-1.0]}}, "youngs_modulus"),
        ({"grid": {"simulation.frames": []}}, "non-empty list"),
        ({"options": {"preview": "gif"}}, "options.preview: must be one of mp4, png, none"),
        ({"options": {"iterations": 3}}, "unknown key 'iterations'"),
        ({"runs": [{"name": "x", "config": "demo/config.yaml", "case": "torus"}]}, "only sysid runs take a case"),
        ({"cases": ["torus"]}, "sysid cases need command: sysid"),
    ],
)
def test_a_bad_spec_is_one_line_before_any_work(spec_dir, change, message):
    folder, write = spec_dir
    spec = write({**FOUR_RUNS, **change})
    with pytest.raises(InputError, match=message):
        load_spec(spec)
    result = _sweep(spec, "-o", folder / "out", "--serial")
    assert result.exit_code == 1 and message.split("'")[0] in result.output
    assert len(result.output.strip().splitlines()) == 1  # the one error line: nothing ran
    assert not (folder / "out").exists()


def test_run_names_are_stable_and_readable(spec_dir):
    folder, write = spec_dir
    names = [r.name for r in load_spec(write(FOUR_RUNS)).runs]
    assert names == [r.name for r in load_spec(write(FOUR_RUNS, "again.yaml")).runs]
    assert names[0].startswith("simulate-config-youngs_modulus=2000.0-") and names[2].startswith("simulate-fails-")
    assert len(set(names)) == 4


def test_without_ray_it_says_which_extra_to_install(spec_dir, monkeypatch):
    folder, write = spec_dir
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails
    result = _sweep(write(FOUR_RUNS), "-o", folder / "out")
    assert result.exit_code == 1 and "pip install 'clflow[sweep]'" in result.output and "--serial" in result.output


def _outputs(out):
    summary = json.loads((out / "sweep.json").read_text())
    arrays = {}
    for name, record in summary["runs"].items():
        if record["status"] == "ok":
            with np.load(out / "runs" / name / "simulation" / "gaussians.npz") as g:
                arrays[name] = {k: g[k] for k in g.files}
    return summary, arrays


@pytest.mark.slow
def test_a_sweep_on_local_ray_records_failures_resumes_and_matches_the_serial_path(spec_dir):
    pytest.importorskip("ray")
    folder, write = spec_dir
    spec = write(FOUR_RUNS)
    out = folder / "ray"
    result = _sweep(spec, "-o", out)  # embedded local Ray, 2 CPUs: two tasks of one thread at a time
    assert result.exit_code == 1, result.output
    summary, arrays = _outputs(out)
    status = {name.split("-")[1]: r["status"] for name, r in summary["runs"].items()}
    assert status == {"config": "ok", "fails": "failed", "slow": "timeout"} and len(arrays) == 2
    assert list(status.values()).count("ok") == 1  # (the two good runs share the readable part)
    assert sum(r["status"] == "ok" for r in summary["runs"].values()) == 2
    failed = next(r for r in summary["runs"].values() if r["status"] == "failed")
    assert "more than --max-output-gb" in failed["reason"]
    timed = next(r for r in summary["runs"].values() if r["status"] == "timeout")
    assert timed["reason"] == "exceeded the time limit of 2 s" and timed["seconds"] < 30
    assert summary["finished"] == 4 and summary["mode"].startswith("ray (local")
    for record in summary["runs"].values():  # each run's own record, written as it finished
        assert json.loads((out / "runs" / record["name"] / "result.json").read_text())["status"] == record["status"]
    table = (out / "sweep.md").read_text()
    assert "2 ok, 1 failed, 1 timeout of 4 runs" in table and "exceeded the time limit" in table
    ok = [r for r in summary["runs"].values() if r["status"] == "ok"]
    assert all(r["result"]["frames"] == 3 for r in ok)

    again = _sweep(spec, "-o", out)  # all four finished: nothing runs, no Ray starts
    assert again.exit_code == 1 and "4 run(s) finished earlier, skipped" in again.output
    assert _outputs(out)[0]["runs"] == {n: {**r, "skipped": True} for n, r in summary["runs"].items()}

    # the serial path gives the same statuses and the same bits (its PoCL has two threads, each
    # task had one: CLFLOW_P2G_COPIES keeps the P2G sum order)
    serial = folder / "serial"
    result = _sweep(spec, "-o", serial, "--serial")
    assert result.exit_code == 1, result.output
    serial_summary, serial_arrays = _outputs(serial)
    assert {n: r["status"] for n, r in serial_summary["runs"].items()} == {
        n: r["status"] for n, r in summary["runs"].items()
    }
    assert serial_arrays.keys() == arrays.keys()
    for name in arrays:
        for key, value in arrays[name].items():
            np.testing.assert_array_equal(serial_arrays[name][key], value, err_msg=f"{name}: {key}")

    # --retry-failed runs the two failures again (serially here) and keeps the two good runs
    shutil.rmtree(serial / "runs" / next(n for n in arrays))  # and a run whose folder went is run again
    result = _sweep(spec, "-o", serial, "--serial", "--retry-failed")
    assert "1 run(s) finished earlier, skipped" in result.output
    assert sum(r["status"] == "ok" for r in _outputs(serial)[0]["runs"].values()) == 2


@pytest.mark.slow
def test_a_killed_task_is_recorded_and_the_others_go_on(spec_dir):
    pytest.importorskip("ray")
    import ray

    from clflow.parallel import serial_order, start_ray, task_env
    from clflow.sweep import execute, run_on_ray

    folder, write = spec_dir
    spec = load_spec(write({key: FOUR_RUNS[key] for key in ("command", "base", "options", "set", "grid")}))

    def task(run, where):  # the first run's worker dies as if killed (out of memory, kill -9)
        import os

        if "youngs_modulus=2000.0" in run.name:
            os._exit(9)
        return execute(run, where)

    records = []
    start_ray(None)
    try:
        run_on_ray(
            list(spec.runs),
            lambda run: folder / "out" / run.name,
            None,
            records.append,
            env=task_env(1, None, serial_order()),
            task=task,
        )
    finally:
        ray.shutdown()
    status = {r["name"].split("-")[2]: (r["status"], r["reason"]) for r in records}
    assert status["youngs_modulus=20000.0"] == ("ok", None)
    killed, reason = status["youngs_modulus=2000.0"]
    assert killed == "killed" and ("Worker" in reason or "died" in reason), reason


@pytest.mark.slow
def test_ctrl_c_stops_the_sweep_and_keeps_what_finished(spec_dir):
    pytest.importorskip("ray")
    import os
    import signal
    import subprocess
    import time

    from tests.pipeline.test_written_record import sigint_as_a_terminal_sends_it

    folder, write = spec_dir
    spec = write(
        {
            "command": "simulate",
            "base": "demo/config.yaml",
            "options": {"preview": "none"},
            "overrides": [{"simulation.frames": 2}, {"simulation.frames": 3000}],
        }
    )
    out = folder / "out"
    clflow = os.path.join(os.path.dirname(sys.executable), "clflow")
    proc = subprocess.Popen(
        [clflow, "sweep", str(spec), "-o", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=sigint_as_a_terminal_sends_it,
    )
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:  # until the short run is in
        summary = json.loads((out / "sweep.json").read_text()) if (out / "sweep.json").exists() else {}
        if summary.get("finished") == 1:
            break
        time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    output, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130, output
    assert "interrupted; finished runs are kept" in output
    summary = json.loads((out / "sweep.json").read_text())
    assert sorted(r["status"] for r in summary["runs"].values()) == ["ok", "pending"]
    again = _sweep(spec, "-o", out, "--serial", "--timeout", "1")  # the short run is not run again
    assert "1 run(s) finished earlier, skipped" in again.output


@pytest.mark.slow
def test_an_optimisation_on_ray_gives_the_serial_bits(spec_dir):
    """A one-thread task with the driver's P2G copies and torch threads (clflow.parallel.serial_order)
    ends where the serial path does, to the last bit of the loss and the parameters."""
    pytest.importorskip("ray")
    folder, write = spec_dir
    spec = write({"command": "optimize", "configs": ["demo/config.yaml"], "options": {"iterations": 2}})
    results = {}
    for mode in ("ray", "serial"):
        result = _sweep(spec, "-o", folder / mode, *(["--serial"] if mode == "serial" else []))
        assert result.exit_code == 0, result.output
        (record,) = json.loads((folder / mode / "sweep.json").read_text())["runs"].values()
        params = json.loads((folder / mode / "runs" / record["name"] / "results" / "params.json").read_text())
        results[mode] = (record["result"]["flow_loss"], params["parameters"])
    assert results["ray"] == results["serial"]


def test_resources_and_modes_are_checked_as_usage(spec_dir):
    from clflow_cli.sweep import parse_resources

    assert parse_resources(("GPU=1", "memory_gb=4.5")) == {"GPU": 1.0, "memory_gb": 4.5}
    folder, write = spec_dir
    spec = write(FOUR_RUNS)
    for args, message in (
        (["--resources", "GPU"], "expected NAME=AMOUNT"),
        (["--resources", "GPU=0"], "amount > 0"),
        (["--serial", "--address", "auto"], "drop --address"),
    ):
        result = _sweep(spec, "-o", folder / "out", *args)
        assert result.exit_code == 2 and message in result.output, result.output
    assert not (folder / "out").exists()


@pytest.fixture
def own_scene(quick_demo, tmp_path):
    """tmp_path with a copy of the quick demo in scene/ (the test edits it) and ``write(spec) -> path``."""
    shutil.copytree(quick_demo, tmp_path / "scene")

    def write(spec):
        path = tmp_path / "spec.yaml"
        path.write_text(yaml.safe_dump(spec))
        return path

    return tmp_path, write


def _records(out):
    return {name.split("-")[1]: record for name, record in json.loads((out / "sweep.json").read_text())["runs"].items()}


def test_a_run_whose_inputs_changed_runs_again_and_the_others_are_skipped(own_scene):
    folder, write = own_scene
    spec = write(
        {
            "command": "simulate",
            "configs": ["scene/config.yaml", "scene/config_truth.yaml"],  # config_truth names no guidance
            "options": {"preview": "none"},
            "set": {"simulation.frames": 2},
        }
    )
    out = folder / "out"
    assert _sweep(spec, "-o", out, "--serial").exit_code == 0
    first = _records(out)
    assert set(first["config"]["inputs"]) == {"run", "config.yaml", "guidance", "scene.ply"}
    name = first["config"]["name"]
    saved = out / "runs" / name / "simulation" / "gaussians.npz"

    def again(*changes):
        result = _sweep(spec, "-o", out, "--serial")
        assert result.exit_code == 0, result.output
        lines = [line for line in result.output.splitlines() if "running it again" in line]
        assert lines == [f"run {name}: {change}, running it again" for change in changes], result.output
        return result.output

    assert "2 run(s) finished earlier, skipped" in again()  # nothing changed: nothing runs
    written = saved.stat().st_mtime_ns

    config = folder / "scene" / "config.yaml"
    config.write_text(config.read_text().replace("density: 1000.0", "density: 1100.0"))
    assert "1 run(s) finished earlier, skipped" in again("its inputs changed since its result (config.yaml)")
    second = _records(out)
    assert second["config"]["inputs"]["config.yaml"] != first["config"]["inputs"]["config.yaml"]
    assert second["config"]["date"] >= first["config"]["date"] and saved.stat().st_mtime_ns != written
    assert json.loads((out / "runs" / name / "result.json").read_text()) == second["config"]
    assert second["config_truth"] == {**first["config_truth"], "skipped": True}  # its inputs are the same

    frame = sorted((folder / "scene" / "guidance").glob("*.png"))[0]  # a frame of the folder the config points at
    frame.write_bytes(frame.read_bytes() + b"\0")
    again("its inputs changed since its result (guidance)")

    record = json.loads((out / "runs" / name / "result.json").read_text())  # as an earlier clflow wrote it
    atomic_write_text(
        out / "runs" / name / "result.json", json.dumps({k: v for k, v in record.items() if k != "inputs"})
    )
    again("its result has no digest of its inputs (an earlier clflow's)")
    assert "2 run(s) finished earlier, skipped" in again()


def test_an_optimisation_whose_config_changed_starts_over_instead_of_resuming(own_scene):
    """Its checkpoint is of the other inputs: it runs from the start (and does not fail to resume)."""
    folder, write = own_scene
    spec = write(
        {
            "command": "optimize",
            "configs": ["scene/config.yaml"],
            "options": {"iterations": 1},
            "set": {"simulation.frames": 3, "optimize.horizon.start": 2},
        }
    )
    out = folder / "out"
    assert _sweep(spec, "-o", out, "--serial").exit_code == 0
    config = folder / "scene" / "config.yaml"
    config.write_text(config.read_text().replace("density: 1000.0", "density: 1100.0"))
    result = _sweep(spec, "-o", out, "--serial")
    assert result.exit_code == 0 and "(config.yaml), running it again" in result.output, result.output
    (record,) = _records(out).values()
    assert record["status"] == "ok" and "skipped" not in record
    log = (out / "runs" / record["name"] / "run.log").read_text()
    assert "removing the earlier run's" in log  # a new run, not a resumed one
    inputs = json.loads((out / "runs" / record["name"] / "inputs.json").read_text())
    assert inputs == record["inputs"]
