"""Helpers of tests in more than one folder."""

from __future__ import annotations

import subprocess
import sys


def run_python(code: str, timeout: float = 120, **options) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter (``options``: subprocess.run's, e.g. env); its
    output captured as text; asserts that it exited 0, with its stderr."""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout, **options)
    assert res.returncode == 0, res.stderr
    return res
