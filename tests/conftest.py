"""Shared fixtures: every test runs on the device clflow selects ($CLFLOW_DEVICE or default,
PoCL's CPU device on CI)."""

from pathlib import Path

import pytest

REPO = str(Path(__file__).resolve().parents[1])  # the repository: scripts run under oclgrind import tests.*


@pytest.fixture(scope="session")
def device():
    from clflow.runtime import get_device

    return get_device()


@pytest.fixture
def copy_mode(monkeypatch):
    """The bridge's copy mode for the test: separate device buffers and explicit, counted
    copies on any device (what a discrete GPU does)."""
    from clflow.runtime import devices

    monkeypatch.setattr(devices, "_BRIDGE_MODE", "copy")


@pytest.fixture
def oclgrind(tmp_path):
    """Run a Python snippet under oclgrind (out-of-bounds, data-race and, unless
    ``uninitialized=False``, uninitialised-value checks) and return ``(stdout, log)``; skips
    when oclgrind is not installed. The snippet can import the ``tests`` package's helpers.

    Oclgrind replaces the OpenCL runtime for the child process, so inside it the only
    device is the Oclgrind simulator (a non-unified device: the bridge's copy path runs).
    """
    import os
    import shutil
    import subprocess
    import sys

    exe = shutil.which("oclgrind")
    if exe is None:
        pytest.skip("oclgrind is not installed (apt-get install oclgrind)")

    def run(code: str, timeout: float = 300, uninitialized: bool = True):
        script, log = tmp_path / "under_oclgrind.py", tmp_path / "oclgrind.log"
        script.write_text(code)
        env = {k: v for k, v in os.environ.items() if k != "CLFLOW_DEVICE"}
        env["PYTHONPATH"] = os.pathsep.join([REPO, *filter(None, [env.get("PYTHONPATH")])])  # tests.* helpers
        res = subprocess.run(
            [
                exe,
                "--data-races",
                *(["--uninitialized"] if uninitialized else []),
                "--log",
                str(log),
                sys.executable,
                str(script),
            ],
            capture_output=True,
            text=True,
            timeout=timeout,
            env=env,
        )
        assert res.returncode == 0, res.stderr
        return res.stdout, (log.read_text() if log.exists() else "")

    return run


@pytest.fixture(params=["cpu", "gpu"])
def plan_kind(request, monkeypatch):
    """Each parallel stage in the CPU and in the GPU shape (clflow.runtime.plan), on the
    test's device: CLFLOW_KERNELS forced for the test."""
    from clflow.runtime.plan import KERNELS_ENV

    monkeypatch.setenv(KERNELS_ENV, request.param)
    return request.param
