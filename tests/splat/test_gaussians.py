"""The Gaussians container: activations, rotations, selection, concatenation, dtype."""

import math

import pytest
import torch

from clflow.errors import InputError
from clflow.splat.gaussians import CovarianceGaussians, Gaussians, nearest_neighbour_rms, quat_to_rotmat
from tests.splat._helpers import rotations


def make(n=6, degree=1, seed=0, dtype=torch.float64, **extra):
    gen = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=torch.randn(n, 3, generator=gen, dtype=dtype),
        quats=torch.randn(n, 4, generator=gen, dtype=dtype),
        log_scales=torch.randn(n, 3, generator=gen, dtype=dtype) - 2,
        opacity_logits=torch.randn(n, generator=gen, dtype=dtype),
        sh=torch.randn(n, (degree + 1) ** 2, 3, generator=gen, dtype=dtype),
        **extra,
    )


def test_activations_are_exp_sigmoid_and_normalise():
    g = make()
    assert torch.equal(g.scales, torch.exp(g.log_scales))
    assert torch.equal(g.opacities, 1 / (1 + torch.exp(-g.opacity_logits)))
    assert torch.allclose(g.unit_quats.norm(dim=1), torch.ones(6, dtype=torch.float64))
    assert g.sh_degree == 1 and len(g) == 6


def test_from_activated_inverts_the_activations():
    scales = torch.tensor([[0.01, 0.2, 3.0]], dtype=torch.float64)
    opacities = torch.tensor([0.37], dtype=torch.float64)
    g = Gaussians.from_activated(torch.zeros(1, 3), torch.tensor([[2.0, 0, 0, 0]]), scales, opacities, colors=torch.ones(1, 3))
    assert torch.allclose(g.scales, scales, rtol=1e-15) and torch.allclose(g.opacities, opacities, rtol=1e-15)
    assert g.sh_degree is None


def test_rotation_of_a_quarter_turn_about_z_and_covariance():
    # wxyz (cos 45deg, 0, 0, sin 45deg), stored unnormalised (x2): x -> y, y -> -x.
    q = torch.tensor([[2 * math.cos(math.pi / 4), 0, 0, 2 * math.sin(math.pi / 4)]], dtype=torch.float64)
    R = quat_to_rotmat(q)[0]
    assert torch.allclose(R, torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64), atol=1e-15)
    g = Gaussians.from_activated(torch.zeros(1, 3, dtype=torch.float64), q, torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64),
                                 torch.tensor([0.5], dtype=torch.float64), colors=torch.zeros(1, 3, dtype=torch.float64))
    # The local x axis (sigma 0.1) now lies along world y.
    expected = torch.diag(torch.tensor([0.2**2, 0.1**2, 0.3**2], dtype=torch.float64))
    assert torch.allclose(g.covariances[0], expected, atol=1e-15)


def test_random_rotations_are_proper():
    R = quat_to_rotmat(torch.randn(50, 4, dtype=torch.float64))
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(50, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(50, dtype=torch.float64))


def test_box_sphere_and_mask_selection():
    means = torch.tensor([[0.0, 0, 0], [1, 1, 1], [0.5, -0.5, 0.2], [3, 0, 0]], dtype=torch.float64)
    g = make(n=4)
    g.means = means
    assert g.box_mask((-0.1, -1, -1), (1, 1, 1)).tolist() == [True, True, True, False]
    assert g.sphere_mask((0, 0, 0), 0.75).tolist() == [True, False, True, False]  # |m2| = 0.735
    box = g.select_box((0.4, -1, 0), (1, 1, 1))
    assert torch.equal(box.means, means[[1, 2]]) and torch.equal(box.sh, g.sh[[1, 2]])
    sphere = g.select_sphere((3, 0, 0.1), 0.2)
    assert torch.equal(sphere.opacity_logits, g.opacity_logits[[3]])
    picked = g.select(torch.tensor([3, 0]))
    assert torch.equal(picked.quats, g.quats[[3, 0]])
    empty = g.select_sphere((10, 10, 10), 1.0)
    assert len(empty) == 0 and empty.sh.shape == (0, 4, 3)


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda g: g.select(torch.ones(3, dtype=torch.bool)), "mask has shape"),
        (lambda g: g.select(torch.tensor([0, 9])), "out of range"),
        (lambda g: g.select(torch.ones(6)), "bool mask or a 1-D integer index"),
        (lambda g: g.select_box((1, 1, 1), (0, 0, 0)), "is not <= high"),
        (lambda g: g.select_box((0, 0), (1, 1)), "box low must be 3 numbers"),
        (lambda g: g.select_sphere((0, 0, 0), -1), "radius must be >= 0"),
        (lambda g: g.bounds(0.7), "quantile"),
        (lambda g: g.select(torch.zeros(6, dtype=torch.bool)).bounds(), "empty"),
    ],
)
def test_bad_selections_raise(call, message):
    with pytest.raises(InputError, match=message):
        call(make())


def test_cat_and_dtype_conversion():
    a = make(n=2, seed=1, features=torch.ones(2, 1, dtype=torch.float64), feature_names=("label",))
    b = make(n=3, seed=2, features=torch.zeros(3, 1, dtype=torch.float64), feature_names=("label",))
    c = Gaussians.cat([a, b])
    assert len(c) == 5 and torch.equal(c.means, torch.cat([a.means, b.means]))
    assert c.features[:, 0].tolist() == [1, 1, 0, 0, 0] and c.feature_names == ("label",)
    f32 = c.to(torch.float32)
    assert all(getattr(f32, k).dtype == torch.float32 for k in ("means", "quats", "log_scales", "opacity_logits", "sh", "features"))
    with pytest.raises(InputError, match="SH degree"):
        Gaussians.cat([make(degree=0), make(degree=2)])
    with pytest.raises(InputError, match="dtype"):
        Gaussians.cat([make(), make().to(torch.float32)])
    with pytest.raises(InputError, match="at least one"):
        Gaussians.cat([])


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(scales=torch.tensor([[0.1, 0.0, 0.1]])), "scales are <= 0 .*axis 1"),
        (dict(scales=torch.tensor([[0.1, -2.0, 0.1]])), "scales are <= 0"),
        (dict(opacities=torch.tensor([1.0])), "outside \\(0, 1\\)"),
        (dict(opacities=torch.tensor([0.0])), "outside \\(0, 1\\)"),
        (dict(means=torch.tensor([[0.0, float("nan"), 0]])), "non-finite values in means"),
        (dict(quats=torch.zeros(1, 4)), "degenerate quaternions"),
    ],
)
def test_from_activated_rejects_values_no_renderer_can_use(kwargs, message):
    args = dict(means=torch.zeros(1, 3), quats=torch.tensor([[1.0, 0, 0, 0]]), scales=torch.ones(1, 3), opacities=torch.tensor([0.5]))
    args.update(kwargs)
    with pytest.raises(InputError, match=message):
        Gaussians.from_activated(**args, colors=torch.zeros(1, 3))


def test_shapes_are_checked():
    with pytest.raises(InputError, match="quats must have shape \\[2, 4\\]"):
        Gaussians(torch.zeros(2, 3), torch.zeros(3, 4), torch.zeros(2, 3), torch.zeros(2), colors=torch.zeros(2, 3))
    with pytest.raises(InputError, match="means must have shape \\[N, 3\\], got list"):
        Gaussians([[0.0, 0, 0]], torch.zeros(1, 4), torch.zeros(1, 3), torch.zeros(1), colors=torch.zeros(1, 3))
    with pytest.raises(InputError, match="exactly one of sh"):
        Gaussians(torch.zeros(2, 3), torch.zeros(2, 4), torch.zeros(2, 3), torch.zeros(2))
    with pytest.raises(InputError, match="not \\(d\\+1\\)\\^2"):
        Gaussians(torch.zeros(2, 3), torch.zeros(2, 4), torch.zeros(2, 3), torch.zeros(2), sh=torch.zeros(2, 5, 3))
    with pytest.raises(InputError, match="feature_names"):
        make(features=torch.zeros(6, 2), feature_names=("a",))


def test_nearest_neighbour_rms_matches_brute_force():
    points = torch.randn(300, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    d2 = torch.cdist(points, points).square()
    d2.fill_diagonal_(float("inf"))
    expected = d2.topk(3, largest=False).values.mean(1).sqrt()
    assert torch.allclose(nearest_neighbour_rms(points), expected, rtol=1e-12)


def test_bounds_with_outlier_quantile():
    g = make(n=101)
    g.means = torch.zeros(101, 3, dtype=torch.float64)
    g.means[:, 0] = torch.arange(101, dtype=torch.float64)
    low, high = g.bounds()
    assert low[0] == 0 and high[0] == 100
    low, high = g.bounds(0.1)
    assert low[0].item() == pytest.approx(10) and high[0].item() == pytest.approx(90)


def test_the_covariance_form_moves_into_a_frame_and_keeps_the_rest():
    """from_gaussians(g, R, s): means s R x, covariances s^2 R Sigma R^T, sh_rotations R;
    select, cat and to(dtype) keep the fields together."""
    g = make(n=5, degree=2, dtype=torch.float32)
    R = rotations(1, seed=7)[0]
    c = CovarianceGaussians.from_gaussians(g, R, 2.5)
    torch.testing.assert_close(c.means, 2.5 * g.means.double() @ R.T)
    torch.testing.assert_close(c.covariances, 6.25 * R @ g.covariances.double() @ R.T)
    torch.testing.assert_close(c.sh_rotations, R.expand(5, 3, 3))
    assert c.opacities is not None and torch.equal(c.opacities, g.opacities) and torch.equal(c.sh, g.sh)
    assert c.colors is None and c.sh_degree == 2 and len(c) == 5
    plain = CovarianceGaussians.from_gaussians(g)
    torch.testing.assert_close(plain.covariances, g.covariances.double())
    torch.testing.assert_close(plain.sh_rotations, torch.eye(3, dtype=torch.float64).expand(5, 3, 3))
    parts = [c.select(torch.tensor([3, 0])), c.select(torch.tensor([False, True, False, False, True]))]
    joined = CovarianceGaussians.cat(parts).to(torch.float32)
    order = torch.tensor([3, 0, 1, 4])
    for name in ("means", "covariances", "opacities", "sh", "sh_rotations"):
        got = getattr(joined, name)
        assert got.dtype == torch.float32
        torch.testing.assert_close(got, getattr(c, name)[order].float())
    assert joined.colors is None

