"""``clflow simulate`` end to end on tiny scenes."""

import numpy as np
import pytest
from click.testing import CliRunner

from clflow_cli.main import cli

GRID = ["--grid", "16", "--frames", "2", "-p", "youngs_modulus=1e4"]
FAST = [*GRID, "--size", "0.3"]  # a built-in shape's (a particle file's --size is refused)


def run(args):
    return CliRunner().invoke(cli, ["simulate", *args], catch_exceptions=False)


@pytest.mark.parametrize("shape", ["box", "sphere", "torus"])
def test_builtin_shape_writes_positions_and_png_preview(tmp_path, shape):
    res = run([*FAST, "--shape", shape, "--preview", "png", "-o", str(tmp_path)])
    assert res.exit_code == 0, res.output
    data = np.load(tmp_path / "positions.npz")
    assert data["x"].shape[0] == 3 and data["x"].shape[2] == 3
    assert data["time"].tolist() == pytest.approx([0, 1 / 24, 2 / 24])
    assert data["x"][-1, :, 1].mean() < data["x"][0, :, 1].mean()  # it falls
    assert "simulating: 2/2 frame 2" in res.output  # progress, a line per frame off a terminal
    assert sorted(p.name for p in (tmp_path / "preview").iterdir()) == [f"frame_{k:04d}.png" for k in range(3)]


def test_npz_particles_and_mp4_preview(tmp_path):
    x = 0.4 + 0.2 * np.random.default_rng(0).random((100, 3))
    np.savez(tmp_path / "in.npz", positions=x, volume=np.full(100, 1e-5))
    res = run([str(tmp_path / "in.npz"), *GRID, "-m", "plasticine", "-o", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    assert np.load(tmp_path / "out" / "positions.npz")["x"].shape == (3, 100, 3)
    assert (tmp_path / "out" / "preview.mp4").stat().st_size > 0


def test_ply_particles(tmp_path):
    x = 0.4 + 0.2 * np.random.default_rng(1).random((50, 3))
    header = (
        "ply\nformat ascii 1.0\nelement vertex 50\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    (tmp_path / "in.ply").write_text(header + "\n".join(" ".join(f"{c:.6f}" for c in p) for p in x) + "\n")
    res = run([str(tmp_path / "in.ply"), *GRID, "--preview", "none", "-o", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    assert np.allclose(np.load(tmp_path / "out" / "positions.npz")["x"][0], x, atol=1e-6)


@pytest.mark.parametrize(
    "args,message",
    [
        (["-m", "honey"], "unknown material 'honey'"),
        (["-p", "poissons_ratio=0.5"], "poissons_ratio (nu) = 0.5"),
        (["missing.npz"], "particle file not found: missing.npz"),
        (["-p", "youngs_modulus"], "--param takes NAME=VALUE"),
        (["-m", "sand", "--model", "cap"], "sand model 'cap' unknown; choose one of drucker_prager, volume_corrected"),
    ],
)
def test_bad_input_is_one_clear_line(tmp_path, args, message):
    res = CliRunner().invoke(cli, ["simulate", *GRID, "--preview", "none", "-o", str(tmp_path), *args])
    assert res.exit_code != 0
    assert message in res.output
    assert not (tmp_path / "positions.npz").exists()


def test_volume_corrected_sand(tmp_path):
    res = run([*FAST, "-m", "sand", "--model", "volume_corrected", "--preview", "none", "-o", str(tmp_path)])
    assert res.exit_code == 0, res.output
    x = np.load(tmp_path / "positions.npz")["x"]
    assert x[-1, :, 1].mean() < x[0, :, 1].mean()  # it falls


def test_bench_mpm_runs_on_a_small_scene():
    res = CliRunner().invoke(
        cli,
        [
            "bench",
            "mpm",
            "--substeps",
            "1",
            "--particles-per-axis",
            "8",
            "--grid",
            "16",
            "--material",
            "elastic",
            "--material",
            "sand",
        ],
        catch_exceptions=False,
    )
    assert res.exit_code == 0, res.output
    assert "512 particles" in res.output
    rows = [line for line in res.output.splitlines() if "M particle-substeps/s" in line]
    assert [r.split()[0] for r in rows] == ["elastic", "sand"]
    assert "B/particle" in rows[0]


def test_binary_ply_and_bad_particle_files(tmp_path):
    from clflow.errors import InputError
    from clflow.mpm.shapes import load_particles

    x = np.random.default_rng(2).random((7, 3))
    rows = np.zeros(7, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("opacity", "<f4")])
    rows["x"], rows["y"], rows["z"] = x.T
    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 7\nproperty float x\nproperty float y\n"
        "property float z\nproperty float opacity\nend_header\n"
    )
    (tmp_path / "b.ply").write_bytes(header.encode() + rows.tobytes())
    loaded, volume = load_particles(tmp_path / "b.ply")
    assert volume is None and np.allclose(loaded.numpy(), x, atol=1e-6)
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a numpy .npz"):
        load_particles(tmp_path / "bad.npz")
    np.savez(tmp_path / "nokey.npz", points=x)
    with pytest.raises(InputError, match="no 'positions'"):
        load_particles(tmp_path / "nokey.npz")
    (tmp_path / "short.ply").write_bytes(header.encode() + rows.tobytes()[:40])
    with pytest.raises(InputError, match="truncated PLY"):
        load_particles(tmp_path / "short.ply")
