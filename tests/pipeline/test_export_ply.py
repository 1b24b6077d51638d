"""Per-frame PLY exports of a deformed scene: the object's SH rotated into each frame, so the
PLY rendered without ``sh_rotations`` shows what clflow renders; --object-only frames with
static.ply once."""

import dataclasses

import pytest
import torch
from click.testing import CliRunner

from clflow.pipeline.forward import Prepared, SimulationResult
from clflow.pipeline.frames4d import export_gaussians, file_gaussians
from clflow.pipeline.render import render_rgb
from clflow.scene.load import to_file_camera, up_rotation
from clflow.splat.cameras import look_at
from clflow.splat.gaussians import Gaussians
from clflow.splat.ply import load_ply
from clflow.splat.render import rasterize
from clflow_cli.main import cli
from tests.splat._helpers import rotations


def random_gaussians(n, seed, center, up):
    """n Gaussians of SH degree 3 with strong view-dependent colour, simulation frame."""
    g = torch.Generator().manual_seed(seed)
    means = torch.tensor(center) + 0.4 * (torch.rand(n, 3, generator=g) - 0.5)
    quats = torch.randn(n, 4, generator=g)
    scales = 0.03 + 0.04 * torch.rand(n, 3, generator=g)
    sh = torch.randn(n, 16, 3, generator=g) * 0.6
    rest = Gaussians.from_activated(means, quats, scales, 0.5 + 0.4 * torch.rand(n, generator=g), sh=sh)
    return dataclasses.replace(rest, sh_rotations=up_rotation(up).float().expand(n, 3, 3).contiguous())


@pytest.fixture
def deformed(demo_config):
    """A two-frame result (rest, then each object Gaussian moved, turned and stretched) of a
    scene with a non-trivial file frame (+z up, 2.5 m per scene unit), and its camera."""
    cfg = dataclasses.replace(demo_config(), up="+z", scale=2.5)
    obj, static = random_gaussians(60, 1, (0.0, 0.3, 0.0), cfg.up), random_gaussians(40, 2, (0.0, -0.2, 0.0), cfg.up)
    camera = look_at((0.3, 0.4, 1.2), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), fov_x=0.8, width=96, height=80)
    turn = rotations(60, seed=3).float()
    stretch = torch.diag_embed(1 + 0.3 * torch.rand(60, 3, generator=torch.Generator().manual_seed(4)))
    x = torch.stack([obj.means, obj.means + torch.tensor([0.1, -0.05, 0.02])])
    F = torch.stack([torch.eye(3).expand(60, 3, 3), turn @ stretch])
    return SimulationResult(Prepared(cfg, static, obj, None, camera), x, F), camera


def test_exported_frame_renders_like_clflow(deformed, tmp_path):
    result, camera = deformed
    cfg = result.prepared.cfg
    export_gaussians(result, tmp_path / "all")
    export_gaussians(result, tmp_path / "split", object_only=True)
    with torch.no_grad():
        want = render_rgb(result.scene_at(1), camera)
        cam = to_file_camera(camera, up_rotation(cfg.up), cfg.scale)
        colours = lambda g: dataclasses.replace(g, features=None, feature_names=())  # noqa: E731
        show = lambda g: rasterize(colours(g), cam, background=(1.0, 1.0, 1.0), render_depth=False).image  # noqa: E731
        whole = show(load_ply(tmp_path / "all" / "frame_001.ply"))
        parts = show(
            Gaussians.cat([load_ply(tmp_path / "split" / "frame_001.ply"), load_ply(tmp_path / "split" / "static.ply")])
        )
        unturned = show(file_gaussians(result.scene_at(1), cfg.scale, cfg.up, turned=0).to(torch.float32))
    assert (want - 1).abs().mean() > 0.1  # the scene is in view
    torch.testing.assert_close(whole, want, rtol=0, atol=1e-4)
    torch.testing.assert_close(parts, want, rtol=0, atol=1e-4)
    assert (unturned - want).abs().max() > 0.1  # without the SH rotation the colours differ
    assert len(load_ply(tmp_path / "split" / "frame_000.ply")) == 60
    assert len(load_ply(tmp_path / "split" / "static.ply")) == 40 and not (tmp_path / "all" / "static.ply").exists()
    # each Gaussian's object: the one object's index 0, -1 static
    objects = lambda name: load_ply(tmp_path / name).features[:, 0].tolist()  # noqa: E731
    assert objects("all/frame_001.ply") == [0] * 60 + [-1] * 40 and objects("split/static.ply") == [-1] * 40


def test_simulate_object_only_and_compressed(quick_demo, tmp_path):
    simulate = lambda out, *flags: CliRunner().invoke(  # noqa: E731
        cli,
        ["simulate", str(quick_demo / "config_truth.yaml"), "-o", str(out), "--preview", "none", *flags],
        catch_exceptions=False,
    )
    res = simulate(tmp_path / "sim", "--object-only")
    assert res.exit_code == 0, res.output
    whole = load_ply(quick_demo / "scene.ply")
    frames = sorted((tmp_path / "sim").glob("frame_*.ply"))
    static, last = load_ply(tmp_path / "sim" / "static.ply"), load_ply(frames[-1])
    assert len(frames) == 9 and len(static) + len(last) == len(whole) and len(static) and len(last)
    res = simulate(tmp_path / "small", "--object-only", "--compressed-ply")
    assert res.exit_code == 0, res.output
    packed = sorted((tmp_path / "small").glob("frame_*.compressed.ply"))
    assert len(packed) == 9 and not list((tmp_path / "small").glob("frame_???.ply"))
    for standard, small in (
        (last, load_ply(packed[-1])),
        (static, load_ply(tmp_path / "small" / "static.compressed.ply")),
    ):
        assert len(small) == len(standard)
        extent = float((standard.means.max(0).values - standard.means.min(0).values).max())
        distance = torch.cdist(small.means, standard.means).min(1).values  # the compressed file is in Morton order
        assert float(distance.max()) < extent / 1000  # within a quantisation step (11 bits per chunk)
        assert small.feature_names == standard.feature_names == ("object",)
        assert sorted(small.features[:, 0].tolist()) == sorted(standard.features[:, 0].tolist())
    assert set(last.features[:, 0].tolist()) == {0} and set(static.features[:, 0].tolist()) == {-1}
    for flag in ("--object-only", "--compressed-ply"):
        res = CliRunner().invoke(cli, ["simulate", flag, "-o", str(tmp_path / "p")])
        assert res.exit_code == 2 and f"{flag} needs a scene CONFIG" in res.output
