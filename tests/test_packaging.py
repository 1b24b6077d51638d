"""Packaging: every sub-package ships, kernels are found from an installed wheel, and CI
runs exactly the README's test command."""

import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import tomllib

ROOT = Path(__file__).resolve().parent.parent
PACKAGE_DIRS = {"clflow": "clflow", "clflow_cli": "cli", "clflow_datasets": "datasets_tools"}


def declared_packages() -> set[str]:
    return set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])


def test_every_python_package_is_declared():
    found = {"clflow.kernels_cl"}
    for name, folder in PACKAGE_DIRS.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            found.add(".".join((name, *rel)))
    assert found == declared_packages()


def test_ci_runs_exactly_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    commands = re.findall(r"^    (bash scripts/setup\.sh && .+)$", readme, flags=re.M)
    test_command = next(c for c in commands if "pytest" in c)
    ci_lines = [
        line
        for line in (ROOT / ".ci" / "run").read_text().splitlines()
        if line and not line.startswith(("#", "set ", "cd "))
    ]
    assert ci_lines == [test_command]


@pytest.mark.slow
def test_installed_wheel_finds_its_kernels(tmp_path):
    """Build the wheel, install it (no deps) into a fresh target and run from /tmp."""
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(tmp_path / "wheel"),
            str(ROOT),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    (wheel,) = (tmp_path / "wheel").glob("clflow-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert "clflow/kernels_cl/common/reduce.cl" in names and "clflow/kernels_cl/common/real.h" in names
    assert "clflow_cli/main.py" in names
    target = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target), str(wheel)],
        check=True,
        capture_output=True,
        timeout=300,
    )
    code = (
        "import clflow, torch\n"
        "from clflow.runtime.programs import kernels_dir\n"
        "from clflow.runtime.reduction import sum_rows\n"
        "print(clflow.__file__); print(kernels_dir())\n"
        "print(float(sum_rows(torch.ones(10, 2))[0]))\n"
    )
    env = dict(os.environ, PYTHONPATH=str(target))
    res = subprocess.run([sys.executable, "-c", code], cwd="/tmp", capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr
    module_file, kdir, total = res.stdout.split()
    assert module_file.startswith(str(target)) and kdir == str(target / "clflow" / "kernels_cl")
    assert float(total) == 10.0
    res = subprocess.run(
        [sys.executable, "-m", "clflow_cli", "devices"],
        cwd="/tmp",
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert res.returncode == 0 and "Portable Computing Language" in res.stdout, res.stderr
