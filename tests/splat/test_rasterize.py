"""Forward of the OpenCL splat rasteriser against the dense torch reference and hand values."""

import math

import pytest
import torch

from clflow.splat.ops import covariances, rasterize_gaussians
from clflow.splat.reference import covariances_from_quats_scales, rasterize_reference
from tests.splat._helpers import camera, random_scene, rotations

W, H = 40, 36  # 3 x 3 tiles, the last row and column partial


def both(*args, **kwargs):
    return rasterize_gaussians(*args, **kwargs), rasterize_reference(*args, **kwargs)


def assert_close(a, b, tol):
    assert a.shape == b.shape
    err = (a - b).abs().max().item() if a.numel() else 0.0
    assert err <= tol, f"max abs error {err:.3g} > {tol:.3g}"


@pytest.mark.parametrize(
    "scene",
    [
        dict(n=30, seed=0),
        # opaque and overlapping: exercises the ALPHA_MAX clamp and the T_MIN stop
        dict(n=60, seed=1, opacity=(0.9, 1.0), spread=0.15),
        # Gaussians near and beyond the image border, where J's x/z, y/z are clamped
        dict(n=40, seed=2, spread=2.6),
        # some Gaussians behind the camera or the near plane, some in front
        dict(n=40, seed=3, spread=1.0, depth_shift=-2.5),
    ],
)
def test_forward_matches_reference_float64(scene):
    scene = dict(scene)
    shift = scene.pop("depth_shift", 0.0)
    means, quats, scales, opacities, colors = random_scene(**scene)
    means[:, 2] += shift
    viewmat, K = camera(W, H, 30.0)
    flow = torch.randn(means.shape[0], 2, dtype=torch.float64)
    background = torch.tensor([0.2, 0.3, 0.4, -1.0, 0.5], dtype=torch.float64)
    (img, alpha, depth, meta), (r_img, r_alpha, r_depth, r_meta) = both(
        means, quats, scales, opacities, colors, viewmat, K, W, H, features=flow, background=background
    )
    assert img.shape == (H, W, 5) and alpha.shape == (H, W, 1) and depth.shape == (H, W, 1)
    assert torch.equal(meta["radii"], r_meta["radii"])
    visible = meta["radii"] > 0
    assert_close(meta["means2d"][visible], r_meta["means2d"][visible], 1e-9)
    assert_close(meta["conics"][visible], r_meta["conics"][visible], 1e-9)
    assert_close(img, r_img, 1e-9)
    assert_close(alpha, r_alpha, 1e-9)
    assert_close(depth, r_depth, 1e-9)
    assert alpha.max() > 0.5  # the scene is really seen
    if shift:
        assert 0 < int((meta["radii"] == 0).sum()) < means.shape[0]  # some culled, some seen
    if scene["seed"] == 1:
        assert alpha.max() > 1 - 2e-4  # some pixel stopped at T_MIN


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_colours_match_reference(degree):
    means, quats, scales, opacities, _ = random_scene(20, seed=3)
    g = torch.Generator().manual_seed(4)
    sh = torch.randn(20, 16, 3, generator=g, dtype=torch.float64) * 0.5  # more bases than used
    viewmat, K = camera(W, H, 30.0)
    viewmat[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    kwargs = dict(sh_degree=degree, sh_rotations=rotations(20, seed=5) if degree else None)
    (img, alpha, depth, _), (r_img, r_alpha, r_depth, _) = both(
        means, quats, scales, opacities, sh, viewmat, K, W, H, **kwargs
    )
    assert img.shape == (H, W, 3)
    assert_close(img, r_img, 1e-9)
    assert_close(depth, r_depth, 1e-9)


def test_covariances_give_the_same_image_as_quats_and_scales():
    means, quats, scales, opacities, colors = random_scene(25, seed=6)
    viewmat, K = camera(W, H, 30.0)
    a = rasterize_gaussians(means, quats, scales, opacities, colors, viewmat, K, W, H)
    covars = covariances(quats, scales)
    assert_close(covars, covariances_from_quats_scales(quats, scales), 1e-14)
    b = rasterize_gaussians(means, None, None, opacities, colors, viewmat, K, W, H, covars=covars)
    for x, y in zip(a[:3], b[:3]):
        assert_close(x, y, 1e-12)


def test_rotation_and_scale_give_the_expected_covariance():
    quats = torch.tensor([[math.cos(math.pi / 8), 0.0, 0.0, math.sin(math.pi / 8)]], dtype=torch.float64) * 3
    scales = torch.tensor([[2.0, 1.0, 0.5]], dtype=torch.float64)
    c = s = math.sqrt(0.5)  # 45 degrees about z
    R = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float64)
    expected = R @ torch.diag(scales[0] ** 2) @ R.T
    assert_close(covariances(quats, scales)[0], expected, 1e-12)
    assert_close(covariances_from_quats_scales(quats, scales)[0], expected, 1e-12)


def test_three_coloured_gaussians_match_hand_computed_values():
    """Isotropic Gaussians whose 2D centres sit on pixel centres; sigma_px = f s / z = 1 px."""
    f = 100.0
    viewmat = torch.eye(4, dtype=torch.float64)
    K = torch.tensor([[f, 0, 16.5], [0, f, 16.5], [0, 0, 1]], dtype=torch.float64)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 4.0], [0.2, 0.0, 2.0]], dtype=torch.float64)
    scales = torch.tensor([[0.02] * 3, [0.04] * 3, [0.02] * 3], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=torch.float64)
    opacities = torch.tensor([0.8, 0.5, 0.6], dtype=torch.float64)
    colors = torch.eye(3, dtype=torch.float64)  # red, green, blue
    background = torch.ones(3, dtype=torch.float64)
    img, alpha, depth, meta = rasterize_gaussians(
        means, quats, scales, opacities, colors, viewmat, K, 48, 32, background=background
    )
    # red over green on the optical axis, pixel (16, 16): Sigma_2D = (1 + 0.3) I
    assert meta["radii"].tolist() == [4, 4, 4]  # ceil(3 sqrt(1.3 + sqrt(0.1)))
    T = 0.2 * 0.5
    assert_close(img[16, 16], torch.tensor([0.8, 0.2 * 0.5, 0.0], dtype=torch.float64) + T, 1e-12)
    assert_close(alpha[16, 16, 0], torch.tensor(0.9, dtype=torch.float64), 1e-12)
    assert_close(depth[16, 16, 0], torch.tensor((0.8 * 2 + 0.1 * 4) / 0.9, dtype=torch.float64), 1e-12)
    # one pixel to the right: sigma = 0.5 / 1.3 for both
    a1, a2 = 0.8 * math.exp(-0.5 / 1.3), 0.5 * math.exp(-0.5 / 1.3)
    want = torch.tensor([a1, (1 - a1) * a2, 0.0], dtype=torch.float64) + (1 - a1) * (1 - a2)
    assert_close(img[16, 17], want, 1e-12)
    # blue at x = 0.2 m: u = 0.1, mean2d x = 26.5; J02 = -f x / z^2 = -5 adds
    # s^2 J02^2 = 0.0004 * 25 = 0.01 to the x variance: Sigma_2D = diag(1.31, 1.3)
    assert_close(img[16, 26], torch.tensor([0.4, 0.4, 1.0], dtype=torch.float64), 1e-12)
    a3 = 0.6 * math.exp(-0.5 / 1.31)
    assert_close(img[16, 27], torch.tensor([1 - a3, 1 - a3, 1.0], dtype=torch.float64), 1e-12)
    a3y = 0.6 * math.exp(-0.5 / 1.3)
    assert_close(img[17, 26], torch.tensor([1 - a3y, 1 - a3y, 1.0], dtype=torch.float64), 1e-12)
    # far from every Gaussian: background, alpha 0, depth 0
    assert_close(img[2, 40], background, 0.0)
    assert alpha[2, 40, 0] == 0 and depth[2, 40, 0] == 0


@pytest.mark.parametrize("case", ["empty", "behind", "outside"])
def test_scenes_with_nothing_visible_give_background(case):
    viewmat, K = camera(W, H, 30.0)
    n = 0 if case == "empty" else 5
    means, quats, scales, opacities, colors = random_scene(n, seed=7)
    if case == "behind":
        means[:, 2] = -means[:, 2]
    if case == "outside":
        means[:, 0] += 100.0
    leaves = [t.requires_grad_() for t in (means, quats, scales, opacities, colors)]
    background = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    img, alpha, depth, meta = rasterize_gaussians(*leaves, viewmat, K, W, H, background=background)
    assert meta["num_tile_entries"] == 0 and int(meta["radii"].sum()) == 0
    assert torch.equal(img, background.expand(H, W, 3))
    assert torch.equal(alpha, torch.zeros(H, W, 1, dtype=torch.float64))
    assert torch.equal(depth, torch.zeros(H, W, 1, dtype=torch.float64))
    (img.sum() + alpha.sum() + depth.sum()).backward()
    for leaf in leaves:
        assert torch.equal(leaf.grad, torch.zeros_like(leaf))


def test_float32_matches_float64():
    scene = random_scene(40, seed=8)
    viewmat, K = camera(W, H, 30.0)
    out64 = rasterize_gaussians(*scene, viewmat, K, W, H)
    out32 = rasterize_gaussians(*(t.float() for t in scene), viewmat.float(), K.float(), W, H)
    for a, b in zip(out32[:3], out64[:3]):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a.double(), b, rtol=1e-5, atol=1e-5)


def test_meta_reports_tile_lists():
    scene = random_scene(30, seed=9)
    viewmat, K = camera(W, H, 30.0)
    _, _, depth, meta = rasterize_gaussians(*scene, viewmat, K, W, H, render_depth=False)
    assert depth is None
    assert meta["num_tile_entries"] == int(meta["tiles_touched"].sum()) > 0
    assert meta["tile_list_bytes"] >= 20 * meta["num_tile_entries"]
    # float64 records: 9 per Gaussian, 9 + 3 colour channels per entry (no depth channel)
    assert meta["entry_record_bytes"] == 8 * (9 * 30 + 12 * meta["num_tile_entries"])


def test_a_camera_widened_by_whole_pixels_renders_the_same_pixels_inside():
    # the bias correction's shifted crops (clflow.pipeline.fit.objective.JITTER_SHIFTS) are
    # cut from one wider rendering: its central crop must be the plain rendering
    means, quats, scales, opacities, colors = random_scene(30, seed=6)
    viewmat, K = camera(W, H, 30.0)
    wide_K = K.clone()
    wide_K[:2, 2] += 3
    img = rasterize_gaussians(means, quats, scales, opacities, colors, viewmat, K, W, H)[0]
    wide = rasterize_gaussians(means, quats, scales, opacities, colors, viewmat, wide_K, W + 6, H + 6)[0]
    assert wide.shape == (H + 6, W + 6, 3) and float(img.max()) > 0.1
    assert_close(wide[3:-3, 3:-3], img, 1e-6)
