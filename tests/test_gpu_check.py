"""scripts/gpu_check.py, the one-command GPU check, works end to end (a dry run on the test
device at small sizes), so that a GPU lease is not spent finding its bugs."""

import json
import subprocess
import sys

import pytest

from tests.conftest import REPO


def test_the_gpu_check_writes_one_record_of_device_tests_and_benchmarks(device, tmp_path):
    out = tmp_path / "check.json"
    cmd = [sys.executable, "scripts/gpu_check.py", "--device", device.info.label, "--small", "--suite", "none"]
    cmd += ["--bench", "mpm-262k", "--bench", "raster-100k-512", "--out", str(out), "--logs", str(tmp_path / "logs")]
    res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    record = json.loads(out.read_text())
    assert record["passed"] and record["finished"] and record["device"]["name"] == device.info.name
    mpm = record["benchmarks"]["mpm-262k"]["results"]["elastic"]
    assert mpm["particle_substeps_per_s"] > 0 and mpm["bytes_to_device_per_substep"] == 0
    # every bench runs with its kernel profile: per kernel launches and device time, per substep launches
    profile = record["benchmarks"]["mpm-262k"]["results"]["profile"]
    kernels = {row["kernel"]: row for row in profile["kernels"]}
    assert "g2p" in kernels or "g2p_sorted" in kernels
    assert all(row["launches"] > 0 and row["device_s"] > 0 for row in kernels.values())
    assert abs(sum(row["share"] for row in kernels.values()) - 1) < 1e-9
    substep = profile["steps"]["substep"]
    assert substep["count"] > 1 and 3 <= substep["launches_per_step"] <= 12 and substep["host_s_per_step"] > 0
    assert "kernel profile:" in record["benchmarks"]["mpm-262k"]["output"]
    raster = record["benchmarks"]["raster-100k-512"]["results"]
    assert raster["forward"]["median_wall_s"] > 0 and "bytes_to_host_per_call" in raster["forward"]
    assert record["environment"]["torch"] and record["environment"]["pyopencl"]


def test_without_a_gpu_the_check_says_so_in_one_line(device):
    if device.info.type == "GPU":
        pytest.skip("the selected device is a GPU: the check runs on it")
    res = subprocess.run(
        [sys.executable, "scripts/gpu_check.py"], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 1 and "no GPU among the OpenCL devices" in res.stderr and "Traceback" not in res.stderr
