"""What a run ran on: versions, the OpenCL device, the git commit, the date and the machine's
load. One record for every file that reports it (run.json, sysid.json, generate's record,
``clflow bench --json``)."""

from __future__ import annotations

import os
import platform
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path


def load_average() -> float | None:
    """The machine's 1-minute load average (None where the system gives none)."""
    try:
        return round(os.getloadavg()[0], 2)
    except OSError:
        return None


def environment(packages: tuple[str, ...] = (), opencl: bool = True) -> dict:
    """clflow, Python and torch versions, the git commit, the UTC date and the 1-minute load
    average; with ``opencl`` the pyopencl version and the selected OpenCL device (platform,
    driver); the installed version of each of ``packages`` (those not installed are left out)."""
    import torch

    import clflow

    record = {"clflow": clflow.__version__, "commit": _commit(Path(clflow.__file__).parent), "torch": torch.__version__}
    if opencl:
        import pyopencl

        from clflow.runtime import get_device

        device = get_device()
        info = getattr(device, "info", None)
        record.update(
            {
                "pyopencl": pyopencl.VERSION_TEXT,
                "device": str(getattr(device, "name", device)),
                "opencl_platform": getattr(info, "platform", None),
                "opencl_driver": getattr(info, "driver_version", None),
            }
        )
    for name in packages:
        try:
            record[name] = version(name)
        except PackageNotFoundError:
            pass
    record.update(
        {
            "python": platform.python_version(),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "load": load_average(),
        }
    )
    return record


def _commit(folder: Path) -> str | None:
    """The git commit clflow runs from (an editable install in a checkout), "-dirty" added when
    the checkout's tracked files differ from it (a copied tree whose git metadata lags, local
    edits), else None."""
    import subprocess

    try:
        done = subprocess.run(
            ["git", "-C", str(folder), "describe", "--always", "--dirty", "--abbrev=7", "--exclude=*"],
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() or None if done.returncode == 0 else None


__all__ = ["environment", "load_average"]
