"""The peers the benchmarks run beside clflow (clflow.peers): they must compute what they
claim, or the ratio printed against them means nothing."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

pytest.importorskip("taichi")

from clflow.peers.taichi_mpm import run_taichi_mpm  # noqa: E402
from clflow_cli.main import cli  # noqa: E402


def test_taichi_peer_falls_freely_as_symplectic_euler_says():
    """A stress-free block in free fall: after k substeps of dt its centre has dropped
    g dt^2 k (k + 1) / 2 (velocity first, then position), and it stays a block."""
    grid, per_axis = 16, 8
    dx, h = 1.0 / grid, 0.5 / grid
    axis = 0.5 - per_axis * h / 2 + h * (0.5 + np.arange(per_axis))
    x = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    dt, substeps = 1e-3, 9
    timing = run_taichi_mpm(
        x, grid, dx, dt, substeps, youngs_modulus=1e5, poissons_ratio=0.3, density=1000.0, particle_volume=h**3
    )
    k = substeps + 1  # the untimed warm-up substep moves it too
    assert timing.centre_drop == pytest.approx(9.81 * dt**2 * k * (k + 1) / 2, rel=1e-3)
    assert timing.particles == 512 and timing.particle_substeps_per_s > 0


def test_bench_mpm_runs_the_peer_on_the_same_lattice_and_records_the_ratio(tmp_path):
    out = tmp_path / "mpm.json"
    args = ["bench", "mpm", "--material", "elastic", "--particles-per-axis", "8", "--grid", "16", "--substeps", "3"]
    res = CliRunner().invoke(cli, [*args, "--peer", "taichi", "--json", str(out)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    results = json.loads(out.read_text())["results"]
    peer = results["peer"]
    assert peer["name"] == "taichi" and peer["arch"] == "cpu" and peer["particle_substeps_per_s"] > 0
    ratio = results["elastic"]["particle_substeps_per_s"] / peer["particle_substeps_per_s"]
    assert peer["clflow_elastic_over_peer"] == pytest.approx(ratio)
    assert "clflow elastic / taichi" in res.output
