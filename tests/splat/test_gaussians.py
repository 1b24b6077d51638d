"""The Gaussians container: activations, rotations, selection, concatenation, dtype."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from clflow.errors import InputError
from clflow.splat.gaussians import Gaussians
from clflow.splat.geometry import nearest_neighbour_rms, quat_to_rotmat
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
    g = Gaussians.from_activated(
        torch.zeros(1, 3), torch.tensor([[2.0, 0, 0, 0]]), scales, opacities, colors=torch.ones(1, 3)
    )
    assert torch.allclose(g.scales, scales, rtol=1e-15) and torch.allclose(g.opacities, opacities, rtol=1e-15)
    assert g.sh_degree is None


def test_rotation_of_a_quarter_turn_about_z_and_covariance():
    # wxyz (cos 45deg, 0, 0, sin 45deg), stored unnormalised (x2): x -> y, y -> -x.
    q = torch.tensor([[2 * math.cos(math.pi / 4), 0, 0, 2 * math.sin(math.pi / 4)]], dtype=torch.float64)
    R = quat_to_rotmat(q)[0]
    assert torch.allclose(R, torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64), atol=1e-15)
    g = Gaussians.from_activated(
        torch.zeros(1, 3, dtype=torch.float64),
        q,
        torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64),
        torch.tensor([0.5], dtype=torch.float64),
        colors=torch.zeros(1, 3, dtype=torch.float64),
    )
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
    assert all(
        getattr(f32, k).dtype == torch.float32
        for k in ("means", "quats", "log_scales", "opacity_logits", "sh", "features")
    )
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
    args = dict(
        means=torch.zeros(1, 3),
        quats=torch.tensor([[1.0, 0, 0, 0]]),
        scales=torch.ones(1, 3),
        opacities=torch.tensor([0.5]),
    )
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
    """transformed(R, s): means s R x, covariances s^2 R Sigma R^T, sh_rotations R;
    select, cat and to(dtype) keep the fields together."""
    g = make(n=5, degree=2, dtype=torch.float32)
    R = rotations(1, seed=7)[0]
    c = g.transformed(R, 2.5)
    torch.testing.assert_close(c.means, 2.5 * g.means.double() @ R.T)
    torch.testing.assert_close(c.covariances, 6.25 * R @ g.covariances.double() @ R.T)
    torch.testing.assert_close(c.sh_rotations, R.expand(5, 3, 3))
    assert c.opacities is not None and torch.equal(c.opacities, g.opacities) and torch.equal(c.sh, g.sh)
    assert c.colors is None and c.sh_degree == 2 and len(c) == 5
    plain = g.transformed()
    torch.testing.assert_close(plain.covariances, g.covariances.double())
    torch.testing.assert_close(plain.sh_rotations, torch.eye(3, dtype=torch.float64).expand(5, 3, 3))
    parts = [c.select(torch.tensor([3, 0])), c.select(torch.tensor([False, True, False, False, True]))]
    joined = Gaussians.cat(parts).to(torch.float32)
    order = torch.tensor([3, 0, 1, 4])
    for name in ("means", "covariances", "opacities", "sh", "sh_rotations"):
        got = getattr(joined, name)
        assert got.dtype == torch.float32
        torch.testing.assert_close(got, getattr(c, name)[order].float())
    assert joined.colors is None


def reference_covariances(g):
    """Sigma = R diag(s^2) R^T in float64 numpy, from the quaternions' own formula (not quat_to_rotmat)."""
    q = torch.nn.functional.normalize(g.quats.double(), dim=-1).numpy()
    w, x, y, z = q.T
    R = np.stack(
        [
            np.stack([w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z], -1),
        ],
        1,
    )
    s2 = np.exp(2 * g.log_scales.double().numpy())
    return np.einsum("nij,nj,nkj->nik", R, s2, R)


def test_deformations_compose_like_f_sigma_ft_and_sh_rotations_multiply():
    """transformed then deformed twice: covariances F2 F1 sR Sigma (F2 F1 sR)^T, deformations
    F2 F1 sR, sh_rotations R2 R1 R, against a float64 reference; the cached covariances equal
    the ones recomputed from the parameters and deformations."""
    g = make(n=7, degree=1, dtype=torch.float32)
    R, R1, R2 = rotations(1, seed=1)[0], rotations(7, seed=2), rotations(7, seed=3)
    gen = torch.Generator().manual_seed(4)
    F1, F2 = (torch.eye(3) + 0.4 * torch.randn(2, 7, 3, 3, generator=gen, dtype=torch.float64)).unbind(0)
    x1, x2 = torch.randn(2, 7, 3, generator=gen, dtype=torch.float64).unbind(0)
    moved = g.transformed(R, 1.5).deformed(x1, F1, R1).deformed(x2, F2, R2)
    D = (F2 @ F1 @ (1.5 * R)).numpy()
    want = np.einsum("nij,njk,nlk->nil", D, reference_covariances(g), D)
    np.testing.assert_allclose(moved.covariances.numpy(), want, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(moved.deformations.numpy(), D, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(moved.sh_rotations.numpy(), (R2 @ R1 @ R).numpy(), rtol=1e-12, atol=1e-14)
    assert torch.equal(moved.means, x2) and torch.equal(moved.opacity_logits, g.opacity_logits)
    uncached = dataclasses.replace(moved, covariance_cache=None)
    torch.testing.assert_close(uncached.covariances, moved.covariances, rtol=1e-6, atol=1e-12)
    with pytest.raises(InputError, match=r"Gaussians.deformations must have shape \[7, 3, 3\], got \[6, 3, 3\]"):
        dataclasses.replace(moved, deformations=moved.deformations[:6])


def test_deformed_covariances_are_differentiable_in_f_and_the_means():
    """d sum(W * F Sigma F^T) / dF = (W + W^T) F Sigma; the means pass through unchanged."""
    g = make(n=5, degree=0)
    gen = torch.Generator().manual_seed(2)
    W = torch.randn(5, 3, 3, generator=gen, dtype=torch.float64)
    F = (torch.eye(3) + 0.3 * torch.randn(5, 3, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    x = torch.randn(5, 3, generator=gen, dtype=torch.float64).requires_grad_()
    moved = g.deformed(x, F, rotations(5, seed=6))
    ((moved.covariances * W).sum() + moved.means.sum()).backward()
    torch.testing.assert_close(F.grad, (W + W.transpose(1, 2)) @ F.detach() @ g.covariances)
    torch.testing.assert_close(x.grad, torch.ones(5, 3, dtype=torch.float64))


def test_cat_of_deformed_and_plain_parts_fills_identity_and_keeps_covariances():
    """A plain part next to a deformed one: identity deformations and sh_rotations, its own
    covariances; select, to and detach keep the optional fields; plain parts alone stay plain."""
    plain, other = make(n=3, seed=1), make(n=4, seed=2)
    gen = torch.Generator().manual_seed(3)
    F = torch.eye(3) + 0.3 * torch.randn(4, 3, 3, generator=gen, dtype=torch.float64)
    moved = other.deformed(other.means + 1, F, rotations(4, seed=5))
    joined = Gaussians.cat([plain, moved])
    eye = torch.eye(3, dtype=torch.float64).expand(3, 3, 3)
    assert torch.equal(joined.deformations, torch.cat([eye, F])) and torch.equal(joined.sh_rotations[:3], eye)
    torch.testing.assert_close(
        joined.covariances, torch.cat([plain.covariances, F @ other.covariances @ F.transpose(1, 2)])
    )
    torch.testing.assert_close(dataclasses.replace(joined, covariance_cache=None).covariances, joined.covariances)
    part = joined.select(torch.tensor([4, 0])).to(torch.float32).detach()
    for name in ("deformations", "sh_rotations", "covariance_cache"):
        value = getattr(part, name)
        assert value.dtype == torch.float32 and torch.equal(value, getattr(joined, name)[[4, 0]].float())
    both = Gaussians.cat([plain, make(n=2, seed=4)])
    assert both.deformations is None and both.sh_rotations is None and both.covariance_cache is None


def test_from_covariances_keeps_them_as_unit_gaussians_deformed_by_a_factor():
    R = rotations(4, seed=8)
    variances = torch.tensor(
        [[1e-4, 4e-4, 9e-4], [1e-2, 1e-2, 1e-2], [2e-3, 1e-3, 0.0], [5e-3, 1e-5, 2e-4]], dtype=torch.float64
    )
    covs = R @ torch.diag_embed(variances) @ R.transpose(1, 2)
    covs[2] = torch.diag(variances[2])  # exactly singular: no Cholesky factor
    opacities = torch.tensor([0.3, 1.0, 0.9, 0.0], dtype=torch.float64)
    g = Gaussians.from_covariances(
        torch.zeros(4, 3, dtype=torch.float64), covs, opacities, colors=torch.ones(4, 3, dtype=torch.float64)
    )
    assert g.covariances is covs and g.sh_rotations is None
    assert torch.equal(g.scales, torch.ones(4, 3, dtype=torch.float64)) and torch.equal(
        g.rotations, torch.eye(3, dtype=torch.float64).expand(4, 3, 3)
    )
    # the factors alone give the same covariances, the singular one (a zero variance) too
    torch.testing.assert_close(g.deformations @ g.deformations.transpose(1, 2), covs, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(dataclasses.replace(g, covariance_cache=None).covariances, covs, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(g.opacities, opacities.clamp(1e-6, 1 - 1e-6))


def test_deformed_gaussians_are_refused_by_the_file_writers(tmp_path):
    from clflow.splat.compressed_ply import save_compressed_ply
    from clflow.splat.ply import save_ply

    g = make(n=3)
    for turned in (g.transformed(), dataclasses.replace(g, sh_rotations=rotations(3, seed=1))):
        for save, name in ((save_ply, "a.ply"), (save_compressed_ply, "a.compressed.ply")):
            with pytest.raises(InputError, match=f"{name}: these Gaussians are deformed or turned"):
                save(tmp_path / name, turned)
    assert not list(tmp_path.iterdir())
