"""Issue 46's probes, driven through the CLI as a user would: no retry loop that changes
nothing (a hang), no check that comes after the work it could have spared, no plan printed
that is not the plan run, and one error line that names the file or key and the problem."""

import re
import subprocess
import sys

import pytest

from tests.pipeline.test_bad_input import Case, Probe, assert_probe, simulation  # noqa: F401 (a fixture)


def run(*args, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "clflow_cli", *map(str, args)], capture_output=True, text=True, timeout=timeout
    )


def one_error(res: subprocess.CompletedProcess, pattern: str, exit_code: int = 1) -> str:
    """The one error line of ``res``, matching ``pattern``, no traceback; returns stderr."""
    errors = [line for line in res.stderr.splitlines() if line.startswith("Error")]
    assert res.returncode == exit_code and len(errors) == 1, res.stderr
    assert re.search(pattern, errors[0]), errors[0]
    assert "Traceback" not in res.stderr
    return res.stderr


def progress_past_total(stderr: str) -> list[str]:
    """The progress lines ("label: k/total ...") whose count ran past its total."""
    counts = re.findall(r"^\w[\w ]*: (\d+)/(\d+)", stderr, re.M)
    return [f"{k}/{total}" for k, total in counts if int(k) > int(total)]


# -- 1. no hang: every retry changes something or stops ---------------------------------------


def test_a_fixed_substep_that_breaks_the_cfl_limit_mid_run_stops(quick_demo, tmp_path):
    """substep_dt 0.005 s is stable at the demo's start and breaks the CFL limit at frame 4: a
    retry at "twice the substeps" would run the same fixed step forever."""
    res = run(
        "simulate", quick_demo / "config.yaml", "-o", tmp_path / "s", "--preview", "none",
        "--set", "simulation.substep_dt=0.005", timeout=120,
    )  # fmt: skip
    one_error(res, r"breaks the CFL limit .*simulation.substep_dt = 0.005 s is fixed: a shorter one, or auto")
    assert "simulating again" not in res.stderr and not progress_past_total(res.stderr)
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("dt", ["0.02", "10"])
def test_a_fixed_substep_above_the_stable_step_is_refused_before_the_run(quick_demo, tmp_path, dt):
    res = run(
        "simulate", quick_demo / "config.yaml", "-o", tmp_path / "s", "--preview", "none",
        "--set", f"simulation.substep_dt={dt}", timeout=120,
    )  # fmt: skip
    one_error(
        res,
        rf"simulation.substep_dt = {dt} s is above the stable step 0.00833 s of the starting parameters "
        r"\(elastic wave speed .*\); the run would blow up or break the CFL limit: use substep_dt: auto",
    )
    assert "simulating:" not in res.stderr and "StabilityWarning" not in res.stderr


def test_an_unstable_substep_count_of_particles_is_refused_before_the_run(tmp_path):
    res = run(
        "simulate", "--substeps", 1, "--frames", 4, "--grid", 16, "-p", "youngs_modulus=1e6", "-o", tmp_path / "p"
    )
    one_error(res, r"--substeps 1 \(dt = 0.0417 s\) is above the stable step .* \(elastic wave speed .*: 46 substeps")
    assert "simulating:" not in res.stderr and not (tmp_path / "p").exists()


def test_the_progress_never_runs_past_its_total_after_a_cfl_retry(quick_demo, tmp_path):
    res = run("-v", "simulate", quick_demo / "config.yaml", "-o", tmp_path / "s", "--preview", "none")
    assert res.returncode == 0, res.stderr
    assert "simulating again at 10 substeps per frame" in res.stderr  # the demo's start breaks the CFL limit
    assert not progress_past_total(res.stderr)
    assert res.stderr.count("simulating: 8/8") == 1


# -- 2. the plan printed is the plan run; checks before the work ------------------------------


def test_the_plan_printed_is_the_substeps_of_the_params_record(quick_demo, tmp_path):
    import json

    record = {"material": "elastic", "parameters": {"youngs_modulus": 2e4}, "density": 1000.0, "substeps": 20}
    (tmp_path / "params.json").write_text(json.dumps({**record, "fps": 24.0, "velocity": [0, 0, 0]}))
    res = run(
        "simulate", quick_demo / "config.yaml", "--params-from", tmp_path / "params.json", "-o", tmp_path / "s",
        "--preview", "none",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert re.search(r"simulation: 20 substeps per frame", res.stderr), res.stderr
