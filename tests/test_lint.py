"""Lint: ruff's checks and ruff format (pyproject.toml) on the Python tree, clang-format (.clang-format) on the
kernels."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


PYTHON_TREE = ["clflow", "cli", "datasets_tools", "tests", "scripts", "experiments"]


def _ruff(*args: str) -> subprocess.CompletedProcess:
    """``ruff ARGS... clflow cli datasets_tools tests`` in the repository root."""
    ruff = shutil.which("ruff", path=str(Path(sys.executable).parent)) or shutil.which("ruff")
    if ruff is None:
        pytest.skip("ruff is not installed (the test extra installs it)")
    return subprocess.run(
        [ruff, *args, "--no-cache", *PYTHON_TREE], cwd=ROOT, capture_output=True, text=True, timeout=120
    )


def test_ruff_finds_nothing():
    done = _ruff("check")
    assert done.returncode == 0, done.stdout + done.stderr


def test_the_python_tree_is_ruff_formatted():
    done = _ruff("format", "--check")
    assert done.returncode == 0, (done.stdout + done.stderr)[-3000:] + "\nrun: ruff format " + " ".join(PYTHON_TREE)


def test_the_kernels_are_clang_formatted():
    clang_format = shutil.which("clang-format")
    if clang_format is None:
        pytest.skip("clang-format is not installed (CI installs it)")
    sources = sorted(str(p) for p in (ROOT / "kernels_cl").rglob("*") if p.suffix in (".cl", ".h"))
    done = subprocess.run(
        [clang_format, "--style=file", "--dry-run", "-Werror", *sources],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-3000:]
