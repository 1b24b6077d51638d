"""An installed GPU driver without an ICD entry is found, used for the process, and named."""

import glob
import os
import subprocess
import sys
from pathlib import Path

import pytest

from clflow.runtime import drivers


def pocl_library() -> Path:
    """The PoCL library the system's ICD entry names: it stands in for a vendor's driver."""
    for icd in glob.glob("/etc/OpenCL/vendors/*.icd"):
        name = Path(icd).read_text().strip()
        if "pocl" in name:
            hits = [Path(d) / name for d in ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64")]
            hits = [h for h in hits if h.is_file()] + ([Path(name)] if Path(name).is_absolute() else [])
            if hits:
                return hits[0]
    pytest.skip("PoCL's ICD entry is not installed here")


@pytest.fixture
def unregistered(tmp_path):
    """A vendors folder without entries and an 'NVIDIA' driver (PoCL under NVIDIA's name) in a
    searched folder: the environment of a GPU container whose driver has no ICD entry."""
    (tmp_path / "vendors").mkdir()
    (tmp_path / "driver").mkdir()
    (tmp_path / "driver" / "libnvidia-opencl.so.1").symlink_to(pocl_library())
    env = {k: v for k, v in os.environ.items() if k not in ("POCL_CACHE_DIR", "CLFLOW_DEVICE")}
    env.update(
        OCL_ICD_VENDORS=str(tmp_path / "vendors"),
        CLFLOW_OPENCL_SEARCH_PATH=str(tmp_path / "driver"),
        XDG_CACHE_HOME=str(tmp_path / "cache"),
    )
    return env, tmp_path / "driver" / "libnvidia-opencl.so.1"


def clflow(env, *args):
    return subprocess.run(
        [sys.executable, "-m", "clflow_cli", *args], capture_output=True, text=True, env=env, timeout=120
    )


def test_an_unregistered_driver_is_used_and_named(unregistered):
    env, library = unregistered
    res = clflow(env, "devices")
    assert res.returncode == 0, res.stderr
    assert "Portable Computing Language" in res.stdout  # the device behind the adopted driver
    assert f"the nvidia OpenCL driver {library} has no ICD entry; used for this process" in res.stdout
    assert f"echo {library} | sudo tee /etc/OpenCL/vendors/nvidia.icd" in res.stdout


def test_processes_starting_together_all_adopt_the_driver(unregistered):
    """pytest-xdist workers and Ray tasks start at once and write the same entries folder:
    each must see the driver (on the first GPU, three of eight workers saw only PoCL)."""
    env, _ = unregistered
    code = (
        "from clflow.runtime import discovery, drivers\n"
        "a = drivers.adopt_unregistered(discovery.configure_kernel_cache().parent)\n"
        "print(a.used)"
    )
    procs = [
        subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, text=True) for _ in range(12)
    ]
    assert [p.communicate(timeout=120)[0].strip() for p in procs] == ["True"] * 12


def test_an_unwritable_cache_is_said_with_the_line_that_registers_the_driver(unregistered, tmp_path):
    env, library = unregistered
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / "clflow").write_text("a file where the cache folder should be")
    res = clflow(env, "devices")
    assert "cannot write" in res.stderr and f"echo {library} | sudo tee" in res.stderr


def test_without_adoption_the_error_says_which_file_to_add(unregistered):
    env, library = unregistered
    res = clflow({**env, "CLFLOW_ADOPT_DRIVERS": "0"}, "devices")
    assert res.returncode == 1 and "Traceback" not in res.stderr
    assert f"the nvidia driver {library} is installed without an ICD entry" in res.stderr
    assert "/etc/OpenCL/vendors/nvidia.icd" in res.stderr


def test_a_registered_driver_is_not_reported(tmp_path, monkeypatch):
    (tmp_path / "vendors").mkdir()
    (tmp_path / "driver").mkdir()
    (tmp_path / "driver" / "libamdocl64.so").write_bytes(b"")
    monkeypatch.setenv("OCL_ICD_VENDORS", str(tmp_path / "vendors"))
    monkeypatch.setenv(drivers.ENV_SEARCH_PATH, str(tmp_path / "driver"))
    assert [d.vendor for d in drivers.unregistered_drivers()] == ["amd"]
    (tmp_path / "vendors" / "amdocl64.icd").write_text("libamdocl64.so\n")
    assert drivers.unregistered_drivers() == []
