"""``clflow optimize --parallel``: the search starts' polishes and the material hypotheses'
searches as Ray tasks give the serial path's results to the last bit, a run resumes after
them, an interrupted polish resumes where it stopped, and without Ray it is one line."""

import dataclasses
import json
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from clflow.pipeline.fit import Optimization
from clflow.scene.config import SearchSettings
from clflow_cli.main import cli

# a 2-sample search, both samples polished for 2 Levenberg-Marquardt iterations each (with
# the estimator-bias calibration of the demo's config), then one more iteration from the best
TINY = (
    "--set",
    "optimize.method=levenberg_marquardt",
    "--set",
    "optimize.search={samples: 2, starts: 2, start_iterations: 2}",
    "--set",
    "optimize.horizon={start: 0, step: 0}",
    "--set",
    "optimize.iterations=3",
    "--set",
    "simulation.frames=4",
)
HYPOTHESES = ("--set", "optimize.material=[elastic, plasticine]")
RESULTS = (
    "params.json",
    "metrics.json",
    "history.json",
    "checkpoint.json",
    "hypotheses.json",
    "search.json",
    "starts/0/checkpoint.json",
    "starts/1/checkpoint.json",
)
ARRAYS = ("estimator_error.npz", "starts/0/estimator_error.npz", "starts/1/estimator_error.npz")


def _optimize(config, out, *args):
    result = CliRunner().invoke(cli, ["optimize", str(config), "-o", str(out), *TINY, *HYPOTHESES, *args])
    assert result.exit_code == 0, result.output
    return result


def _untimed(value):
    """``value`` (JSON data) without its timings."""
    if isinstance(value, dict):
        return {k: _untimed(v) for k, v in value.items() if "seconds" not in k}
    if isinstance(value, list):
        return [_untimed(v) for v in value]
    return value


def _results(out):
    files = {name: _untimed(json.loads((out / name).read_text())) for name in RESULTS}
    arrays = {}
    for name in ARRAYS:
        with np.load(out / name) as data:
            arrays.update({f"{name}:{k}": data[k] for k in data.files})
    return files, arrays


@pytest.mark.slow  # Ray's start and its workers' OpenCL builds: 25-85 s on the shared 2 cores
def test_polishes_and_hypotheses_on_ray_give_the_serial_results_and_resume(quick_demo, tmp_path):
    pytest.importorskip("ray")
    config = quick_demo / "config.yaml"
    _optimize(config, tmp_path / "serial")
    _optimize(config, tmp_path / "ray", "--parallel")
    serial, ray = _results(tmp_path / "serial"), _results(tmp_path / "ray")
    state = serial[0]["checkpoint.json"]["state"]
    # the work the tasks did: two hypotheses searched, two starts polished, each calibrated
    assert set(serial[0]["hypotheses.json"]["hypotheses"]) == {"elastic", "plasticine"}
    assert len(state["polished"]) == 2 and [r.get("start") for r in state["history"]] == [0, 0, 1, 1, None]
    assert all(state["history"][i].get("calibrated") for i in (0, 2))  # each start's first point
    assert serial[0] == ray[0]
    assert serial[1].keys() == ray[1].keys()
    for name, value in serial[1].items():
        np.testing.assert_array_equal(ray[1][name], value, err_msg=name)
    # a finished parallel run goes on with --resume as the serial one does
    for mode in ("serial", "ray"):
        _optimize(config, tmp_path / mode, "--resume", "--iterations", "4")
    assert _results(tmp_path / "serial")[0] == _results(tmp_path / "ray")[0]
    assert len(json.loads((tmp_path / "ray" / "history.json").read_text())) == 6


def test_an_interrupted_polish_resumes_to_the_uninterrupted_result(demo_config):
    def config(name):
        cfg = demo_config(iterations=3, name=name)
        return dataclasses.replace(
            cfg,
            simulation=dataclasses.replace(cfg.simulation, frames=4),
            optimize=dataclasses.replace(
                cfg.optimize,
                method="levenberg_marquardt",
                horizon_start=0,
                horizon_step=0,
                search=SearchSettings(samples=3, starts=2, start_iterations=2),
            ),
        )

    whole = Optimization(config("whole")).run()
    Optimization(config("parts")).run(stop_after=3)  # inside the second start's polish
    resumed = Optimization(config("parts"))
    begin = resumed.load_state()
    assert begin.searched and begin.polished == []  # the starts' progress is in their own checkpoints
    parts = resumed.run(resume=True)
    assert _untimed(dataclasses.asdict(parts)) == _untimed(dataclasses.asdict(whole))
    assert len(parts.polished) == 2 and parts.iteration == 5
    # the second start polished alone, in a fresh optimiser (as a Ray task does), is the same polish
    alone = Optimization(config("alone")).polish.polish(begin, 1)
    rows = [{k: v for k, v in r.items() if k != "iteration"} for r in _untimed(whole.history) if r.get("start") == 1]
    assert [{k: v for k, v in r.items() if k != "iteration"} for r in _untimed(alone["state"]["history"])] == rows
    assert alone["finished"] and alone["state"]["best"]["loss"] == whole.polished[1]["loss"]


def test_parallel_without_ray_is_one_line(quick_demo, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails
    result = CliRunner().invoke(
        cli, ["optimize", str(quick_demo / "config.yaml"), "-o", str(tmp_path / "out"), "--parallel"]
    )
    assert result.exit_code == 1 and len(result.output.strip().splitlines()) == 1, result.output
    assert "pip install 'clflow[sweep]'" in result.output and "drop --parallel" in result.output
    assert not (tmp_path / "out").exists()
    result = CliRunner().invoke(cli, ["optimize", str(quick_demo / "config.yaml"), "--address", "auto"])
    assert result.exit_code == 2 and "go with --parallel" in result.output


@pytest.mark.slow  # a local Ray's start
def test_map_on_ray_keeps_the_order_raises_a_tasks_error_and_refuses_what_cannot_run():
    pytest.importorskip("ray")
    from clflow.errors import InputError
    from clflow.parallel import map_on_ray, ray_session

    def sub(a, b):
        return a - b

    def div(a, b):
        return a / b

    with ray_session():
        seen = []
        assert map_on_ray(sub, [(5, 1), (9, 1), (1, 1)], done=lambda i, r: seen.append(i)) == [4, 8, 0]
        assert sorted(seen) == [0, 1, 2]
        with pytest.raises(ZeroDivisionError):  # the task's own exception, as in this process
            map_on_ray(div, [(1, 1), (1, 0)])
        with pytest.raises(InputError, match="no room for a task"):
            map_on_ray(sub, [(1, 1)], resources={"GPU": 1})
