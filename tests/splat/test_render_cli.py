"""High-level rasterize(gaussians, camera) and the `clflow render` command."""

import json
import math

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from clflow.errors import InputError
from clflow.fileio import WRITTEN_RECORD
from clflow.media import to_uint8
from clflow.splat import Gaussians, look_at, rgb_to_sh0, save_ply
from clflow.splat.render import rasterize
from clflow_cli.main import cli

F64 = torch.float64
W, H = 48, 32
RGB = torch.tensor([[0.9, 0.1, 0.1], [0.1, 0.8, 0.2], [0.2, 0.3, 0.95]], dtype=F64)
OPACITY = torch.tensor([0.8, 0.6, 0.95], dtype=F64)
SIGMA = 0.02  # m, isotropic
PIXELS = [(10, 12), (24, 16), (38, 20)]  # (column, row) each Gaussian's centre projects into
DEPTHS = [2.0, 2.5, 3.0]  # m


def camera():
    return look_at((0.3, -4.0, 1.0), (0.0, 0.0, 0.5), (0, 0, 1), fov_x=math.radians(40), width=W, height=H, name="cam")


def three_gaussians(cam, degree=0):
    """Three isotropic Gaussians whose centres project exactly onto pixel centres of PIXELS."""
    points = []
    for (col, row), z in zip(PIXELS, DEPTHS):
        x = (col + 0.5 - cam.cx) * z / cam.fx
        y = (row + 0.5 - cam.cy) * z / cam.fy
        points.append(cam.camtoworld() @ torch.tensor([x, y, z, 1.0], dtype=F64))
    means = torch.stack(points)[:, :3]
    sh = torch.zeros(3, (degree + 1) ** 2, 3, dtype=F64)
    sh[:, 0] = rgb_to_sh0(RGB)
    return Gaussians.from_activated(
        means, torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=F64), torch.full((3, 3), SIGMA, dtype=F64), OPACITY, sh=sh
    )


def expected_pixel(cam, i, dcol, drow, background):
    """Hand-computed colour of pixel PIXELS[i] + (dcol, drow): one Gaussian, EWA splat + 0.3 px^2 dilation."""
    col, row = PIXELS[i]
    z = DEPTHS[i]
    x, y = (col + 0.5 - cam.cx) * z / cam.fx, (row + 0.5 - cam.cy) * z / cam.fy
    J = torch.tensor([[cam.fx / z, 0, -cam.fx * x / z**2], [0, cam.fy / z, -cam.fy * y / z**2]], dtype=F64)
    cov2d = SIGMA**2 * J @ J.T + 0.3 * torch.eye(2, dtype=F64)
    d = torch.tensor([dcol, drow], dtype=F64)
    alpha = OPACITY[i] * torch.exp(-0.5 * d @ torch.linalg.solve(cov2d, d))
    return alpha * RGB[i] + (1 - alpha) * torch.as_tensor(background, dtype=F64), alpha


def test_three_gaussians_render_hand_computed_values():
    cam = camera()
    image, alpha, depth, meta = rasterize(three_gaussians(cam), cam, background=(0.1, 0.2, 0.3))
    assert image.shape == (H, W, 3) and alpha.shape == (H, W, 1) and depth.shape == (H, W, 1)
    for i, (col, row) in enumerate(PIXELS):
        for dcol, drow in [(0, 0), (1, 0), (0, -1), (1, 1)]:
            colour, a = expected_pixel(cam, i, dcol, drow, (0.1, 0.2, 0.3))
            assert torch.allclose(image[row + drow, col + dcol], colour, rtol=0, atol=1e-10), (i, dcol, drow)
            assert alpha[row + drow, col + dcol, 0].item() == pytest.approx(a.item(), abs=1e-10)
        assert depth[row, col, 0].item() == pytest.approx(DEPTHS[i], abs=1e-10)
    assert torch.allclose(image[0, -1], torch.tensor([0.1, 0.2, 0.3], dtype=F64))  # far from every splat
    assert alpha[0, -1, 0] == 0
    assert torch.allclose(meta["depths"], torch.tensor(DEPTHS, dtype=F64), atol=1e-12)


def test_sh_degree_features_and_background_channels():
    cam = camera()
    g = three_gaussians(cam, degree=1)
    g.sh[:, 1:] = 0.3  # view-dependent part
    flat = rasterize(g, cam, sh_degree=0).image
    degree0 = Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, sh=g.sh[:, :1].contiguous())
    assert torch.equal(flat, rasterize(degree0, cam).image)
    assert not torch.allclose(flat, rasterize(g, cam).image)
    with pytest.raises(InputError, match="sh_degree 2 is outside 0..1"):
        rasterize(g, cam, sh_degree=2)

    flow = torch.tensor([[1.0, -2.0], [0.5, 0.0], [3.0, 4.0]], dtype=F64)
    image = rasterize(g, cam, sh_degree=0, features=flow, background=(1, 1, 1)).image
    assert image.shape == (H, W, 5)
    col, row = PIXELS[2]
    assert torch.allclose(image[row, col, 3:], OPACITY[2] * flow[2], atol=1e-10)  # features get 0 background
    assert torch.allclose(image[0, 0], torch.tensor([1, 1, 1, 0, 0], dtype=F64))
    with pytest.raises(InputError, match="background must have 3 values"):
        rasterize(g, cam, background=(1, 1))


def test_gradients_reach_the_stored_parameters():
    cam = camera()
    g = three_gaussians(cam, degree=1)
    g.quats = torch.tensor([[0.9, 0.2, -0.3, 0.1]] * 3, dtype=F64)  # anisotropic, so rotation matters
    g.log_scales = torch.log(torch.tensor([[0.02, 0.05, 0.03]] * 3, dtype=F64))
    leaves = [g.means, g.quats, g.log_scales, g.opacity_logits, g.sh]
    for t in leaves:
        t.requires_grad_(True)
    image, alpha, depth, _ = rasterize(g, cam)
    (image.square().sum() + alpha.sum() + depth.sum()).backward()
    for name, t in zip(["means", "quats", "log_scales", "opacity_logits", "sh"], leaves):
        assert t.grad is not None and torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0, name


def test_gradcheck_through_the_activations():
    cam = look_at((0, -3, 0), (0, 0, 0), fov_x=0.5, width=12, height=10)
    base = three_gaussians(cam)
    means = torch.tensor([[0.02, 0.0, 0.01], [-0.03, 0.1, -0.02]], dtype=F64, requires_grad=True)
    log_scales = torch.log(torch.tensor([[0.05, 0.08, 0.06], [0.07, 0.05, 0.05]], dtype=F64)).requires_grad_()
    logits = torch.tensor([0.3, -0.2], dtype=F64, requires_grad=True)

    def f(means, log_scales, logits):
        g = Gaussians(means, base.quats[:2], log_scales, logits, sh=base.sh[:2])
        out = rasterize(g, cam)
        return out.image, out.alpha

    assert torch.autograd.gradcheck(f, (means, log_scales, logits), eps=1e-6, atol=1e-6)


def test_empty_and_culled_scenes_render_the_background():
    cam = camera()
    g = three_gaussians(cam)
    empty = g.select(torch.zeros(3, dtype=torch.bool))
    behind = g.select(torch.ones(3, dtype=torch.bool))
    behind.means = 2 * cam.position.to(F64) - behind.means  # mirrored behind the camera
    for scene in (empty, behind):
        image, alpha, _, _ = rasterize(scene, cam, background=(0.5, 0.5, 0.5))
        assert torch.allclose(image, torch.full((H, W, 3), 0.5, dtype=F64)) and (alpha == 0).all()


# -- the CLI -------------------------------------------------------------------------------


@pytest.fixture()
def scene(tmp_path):
    path = tmp_path / "scene.ply"
    save_ply(path, three_gaussians(camera()))
    return path


def run(*args):
    result = CliRunner().invoke(cli, [str(a) for a in args])
    return result


def read_png(path):
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, path
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def test_cli_cameras_json_view_matches_the_python_api(tmp_path, scene):
    cam = camera()
    entry = dict(
        id=0,
        img_name="front.png",
        width=W,
        height=H,
        position=cam.position.tolist(),
        rotation=cam.R.T.tolist(),
        fx=cam.fx,
        fy=cam.fy,
    )
    (tmp_path / "cameras.json").write_text(json.dumps([entry]))
    out = tmp_path / "out"
    result = run(
        "render", scene, "-o", out, "--cameras", tmp_path / "cameras.json", "--camera", "front", "--background", "0,0,1"
    )
    assert result.exit_code == 0, result.output
    from clflow.splat import load_ply

    expected = to_uint8(rasterize(load_ply(scene), cam, background=(0, 0, 1)).image)
    png = read_png(out / "front.png")
    assert png.shape == (H, W, 3)
    assert np.abs(png.astype(int) - expected.astype(int)).max() <= 1  # float32 path vs float32 API
    col, row = PIXELS[0]
    assert png[row, col, 0] > 150 and png[0, 0].tolist() == [0, 0, 255]  # red splat on blue


def test_cli_renders_a_selection(tmp_path, scene):
    cam = camera()
    means = three_gaussians(cam).means
    entry = dict(
        img_name="v", width=W, height=H, position=cam.position.tolist(), rotation=cam.R.T.tolist(), fx=cam.fx, fy=cam.fy
    )
    (tmp_path / "cameras.json").write_text(json.dumps([entry]))
    sphere = ",".join(map(str, means[0].tolist() + [0.05]))
    result = run("render", scene, "-o", tmp_path / "s", "--cameras", tmp_path / "cameras.json", "--sphere", sphere)
    assert result.exit_code == 0, result.output
    png = read_png(tmp_path / "s" / "v.png")
    (c0, r0), (c1, r1) = PIXELS[:2]
    assert png[r0, c0, 0] > 150 and png[r1, c1].max() == 0  # Gaussian 0 kept, Gaussian 1 not
    low, high = (means[1] - 0.01).tolist(), (means[1] + 0.01).tolist()
    result = run(
        "render",
        scene,
        "-o",
        tmp_path / "b",
        "--cameras",
        tmp_path / "cameras.json",
        "--box",
        ",".join(map(str, low + high)),
    )
    assert result.exit_code == 0, result.output
    png = read_png(tmp_path / "b" / "v.png")
    assert png[r1, c1, 1] > 100 and png[r0, c0].max() == 0
    result = run("render", scene, "--sphere", "9,9,9,0.1")
    assert result.exit_code == 1 and "select none of the 3 Gaussians" in result.output


def test_cli_default_view_and_orbit_video(tmp_path, scene):
    result = run("render", scene, "-o", tmp_path / "one", "--width", 40, "--height", 30)
    assert result.exit_code == 0, result.output
    png = read_png(tmp_path / "one" / "orbit_0000.png")
    assert png.shape == (30, 40, 3) and png.max() > 50  # the framed scene is visible

    for video in ("orbit.gif", "orbit.mp4"):
        result = run(
            "render",
            scene,
            "-o",
            tmp_path / "orbit",
            "--orbit",
            4,
            "--width",
            32,
            "--height",
            32,
            "--video",
            tmp_path / video,
            "--fps",
            8,
        )
        assert result.exit_code == 0, result.output
        assert sorted(p.name for p in (tmp_path / "orbit").iterdir()) == [
            WRITTEN_RECORD,
            *(f"orbit_{i:04d}.png" for i in range(4)),
        ]
    ok, animation = cv2.imreadanimation(str(tmp_path / "orbit.gif"))
    assert ok and len(animation.frames) == 4
    capture = cv2.VideoCapture(str(tmp_path / "orbit.mp4"))
    frames = 0
    while capture.read()[0]:
        frames += 1
    assert frames == 4


def test_cli_look_at_and_transforms_frame(tmp_path, scene):
    cam = camera()
    result = run(
        "render",
        scene,
        "-o",
        tmp_path / "a",
        "--eye",
        ",".join(map(str, cam.position.tolist())),
        "--target",
        "0,0,0.5",
        "--up",
        "0,0,1",
        "--fov",
        40,
        "--width",
        W,
        "--height",
        H,
    )
    assert result.exit_code == 0, result.output
    look = read_png(tmp_path / "a" / "look_at.png")

    c2w_gl = cam.camtoworld() @ torch.diag(torch.tensor([1.0, -1, -1, 1], dtype=F64))
    frames = [dict(file_path="./train/r_7", transform_matrix=c2w_gl.tolist())]
    (tmp_path / "transforms.json").write_text(
        json.dumps(dict(camera_angle_x=math.radians(40), w=W, h=H, frames=frames))
    )
    result = run("render", scene, "-o", tmp_path / "b", "--transforms", tmp_path / "transforms.json", "--camera", 0)
    assert result.exit_code == 0, result.output
    assert np.array_equal(read_png(tmp_path / "b" / "r_7.png"), look)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--video", "x.avi"], "must end in .mp4 or .gif"),
        (["--eye", "1,2"], "expected 3 comma-separated finite numbers"),
        (["--camera", "a"], "--camera picks from --cameras or --transforms"),
        (["--eye", "0,0,0.5", "--target", "0,0,0.5"], "same point"),
    ],
)
def test_cli_bad_options(tmp_path, scene, args, message):
    result = run("render", scene, "-o", tmp_path / "o", *args)
    assert result.exit_code != 0 and message in result.output, result.output


def test_cli_cameras_with_one_file_name_and_two_sizes(tmp_path, scene):
    cams = [look_at((0, -4, 1), (0, 0, 0.5), fov_x=0.7, width=w, height=16) for w in (16, 20)]
    frames = [
        dict(
            file_path=f"./{split}/r_0",
            transform_matrix=(c.camtoworld() @ torch.diag(torch.tensor([1.0, -1, -1, 1], dtype=F64))).tolist(),
            w=c.width,
            h=c.height,
        )
        for split, c in zip(("train", "test"), cams)
    ]
    (tmp_path / "t.json").write_text(json.dumps(dict(camera_angle_x=0.7, frames=frames)))
    result = run("render", scene, "-o", tmp_path / "o", "--transforms", tmp_path / "t.json")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == [WRITTEN_RECORD, "r_0.png", "r_0_0001.png"]
    assert read_png(tmp_path / "o" / "r_0_0001.png").shape == (16, 20, 3)
    result = run(
        "render", scene, "-o", tmp_path / "o", "--transforms", tmp_path / "t.json", "--video", tmp_path / "v.mp4"
    )
    assert result.exit_code == 1 and "different sizes" in result.output


def test_cli_bad_files(tmp_path, scene):
    result = run("render", tmp_path / "missing.ply")
    assert result.exit_code == 1 and "missing.ply: cannot read PLY file" in result.output
    (tmp_path / "cameras.json").write_text(
        json.dumps([dict(width=4, height=4, position=[0, 0, 0], rotation=np.eye(3).tolist(), fx=1, fy=1)])
    )
    result = run("render", scene, "--cameras", tmp_path / "cameras.json", "--camera", "nope")
    assert result.exit_code == 1 and "no camera named 'nope'" in result.output
    result = run("render", scene, "--cameras", tmp_path / "cameras.json", "--orbit", 3)
    assert result.exit_code == 2 and "--orbit make new views, --cameras/--transforms give theirs" in result.output


def test_cli_renders_a_plain_point_cloud(tmp_path):
    table = np.zeros(4, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    table["x"] = [0, 0.1, 0, 0.1]
    table["y"] = [0, 0, 0.1, 0.1]
    table["red"] = 255
    from clflow.splat.ply_format import write_ply_vertices

    write_ply_vertices(tmp_path / "points.ply", table)
    result = run("render", tmp_path / "points.ply", "-o", tmp_path / "o", "--width", 16, "--height", 16)
    assert result.exit_code == 0, result.output
    png = read_png(tmp_path / "o" / "orbit_0000.png")
    assert png[..., 0].max() > 0 and png[..., 1:].max() == 0  # red points on black


def test_the_package_exports_the_rasterize_function_even_after_the_ops_module_is_imported():
    import clflow.splat
    import clflow.splat.ops  # noqa: F401  (used to replace clflow.splat.rasterize by a module)
    from clflow.splat import rasterize as exported

    assert exported is rasterize and callable(clflow.splat.rasterize)


def test_cli_renders_the_colours_of_an_export_with_objects(tmp_path, scene):
    """A PLY of `clflow simulate` has each Gaussian's object as a property: an RGB image as
    without it (the property is no colour channel)."""
    import dataclasses

    g = three_gaussians(camera())
    save_ply(
        tmp_path / "labelled.ply",
        dataclasses.replace(g, features=torch.zeros(3, 1, dtype=F64), feature_names=("object",)),
    )
    for name, path in (("plain", scene), ("labelled", tmp_path / "labelled.ply")):
        assert run("render", path, "-o", tmp_path / name, "--width", 40, "--height", 30).exit_code == 0
    labelled, plain = (read_png(tmp_path / name / "orbit_0000.png") for name in ("labelled", "plain"))
    assert cv2.imread(str(tmp_path / "labelled" / "orbit_0000.png"), cv2.IMREAD_UNCHANGED).shape == (30, 40, 3)
    assert np.array_equal(labelled, plain)  # not RGBA with the objects as alpha
