"""Per-Gaussian simulated flow: projection, 2D covariances, transport map, features."""

import math

import pytest
import torch

from clflow.errors import InputError
from clflow.flow.simulated import (
    covariance_2d,
    flow_features,
    flow_from_features,
    gaussian_transport_map,
    pixel_centres,
    project_means,
    sqrtm_spd_2x2,
)

torch.manual_seed(0)
D = torch.float64


def camera():
    """A camera 4 m from the origin looking at it, rotated about all axes; 200x150 px."""
    angles = torch.tensor([0.3, -0.2, 0.1], dtype=D)
    R = torch.linalg.matrix_exp(
        torch.tensor([[0, -angles[2], angles[1]], [angles[2], 0, -angles[0]], [-angles[1], angles[0], 0]], dtype=D)
    )
    viewmat = torch.eye(4, dtype=D)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = torch.tensor([0.1, -0.05, 4.0], dtype=D)
    K = torch.tensor([[180.0, 0.0, 100.0], [0.0, 190.0, 75.0], [0.0, 0.0, 1.0]], dtype=D)
    return viewmat, K


def random_spd(n, scale=0.05):
    L = torch.randn(n, 3, 3, dtype=D) * scale
    return L @ L.transpose(-1, -2) + 1e-3 * torch.eye(3, dtype=D)


def test_projection_matches_pinhole_by_hand():
    viewmat, K = camera()
    means = torch.randn(5, 3, dtype=D) * 0.3
    pc = means @ viewmat[:3, :3].T + viewmat[:3, 3]
    expected = torch.stack([K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2], K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]], -1)
    torch.testing.assert_close(project_means(means, viewmat, K), expected, rtol=1e-14, atol=1e-12)


def test_covariance_2d_is_the_linearised_projection():
    """J Sigma J^T against finite differences of the projection (central, float64)."""
    viewmat, K = camera()
    means = torch.randn(4, 3, dtype=D) * 0.3
    covars = random_spd(4)
    h = 1e-6
    J = torch.stack(
        [
            (project_means(means + h * e, viewmat, K) - project_means(means - h * e, viewmat, K)) / (2 * h)
            for e in torch.eye(3, dtype=D)
        ],
        -1,
    )  # [N, 2, 3] d pixel / d world
    expected = J @ covars @ J.transpose(-1, -2)
    torch.testing.assert_close(covariance_2d(means, covars, viewmat, K, eps2d=0.0), expected, rtol=1e-7, atol=1e-7)
    dilated = covariance_2d(means, covars, viewmat, K, eps2d=0.3) - covariance_2d(means, covars, viewmat, K, eps2d=0.0)
    torch.testing.assert_close(dilated, 0.3 * torch.eye(2, dtype=D).expand(4, 2, 2))


def test_sqrtm_and_transport_map():
    A = torch.randn(20, 2, 2, dtype=D)
    sigma0 = A @ A.transpose(-1, -2) + 0.1 * torch.eye(2, dtype=D)
    B = torch.randn(20, 2, 2, dtype=D)
    sigma1 = B @ B.transpose(-1, -2) + 0.1 * torch.eye(2, dtype=D)
    S = sqrtm_spd_2x2(sigma0)
    torch.testing.assert_close(S @ S, sigma0)
    torch.testing.assert_close(S, S.transpose(-1, -2))
    T = gaussian_transport_map(sigma0, sigma1)
    torch.testing.assert_close(T @ sigma0 @ T.transpose(-1, -2), sigma1)
    torch.testing.assert_close(T, T.transpose(-1, -2))
    assert (torch.linalg.eigvalsh(T) > 0).all()
    torch.testing.assert_close(gaussian_transport_map(sigma0, sigma0), torch.eye(2, dtype=D).expand(20, 2, 2))
    # The map of sigma0 -> P sigma0 P with P symmetric positive-definite is P itself.
    P = torch.tensor([[1.2, 0.1], [0.1, 0.9]], dtype=D)
    torch.testing.assert_close(gaussian_transport_map(sigma0, P @ sigma0 @ P), P.expand(20, 2, 2))


def test_features_gradcheck():
    viewmat, K = camera()
    n = 3
    means_t = (torch.randn(n, 3, dtype=D) * 0.3).requires_grad_()
    means_t1 = (means_t.detach() + 0.02 * torch.randn(n, 3, dtype=D)).requires_grad_()
    covars_t = random_spd(n).requires_grad_()
    covars_t1 = random_spd(n).requires_grad_()

    def mean_model(a, b):
        return flow_features(a, b, viewmat, K, model="mean")

    def affine_model(a, b, c0, c1):
        sym = lambda c: 0.5 * (c + c.transpose(-1, -2))  # noqa: E731 (perturb within symmetric matrices)
        return flow_features(a, b, viewmat, K, model="affine", covars_t=sym(c0), covars_t1=sym(c1))

    assert torch.autograd.gradcheck(mean_model, (means_t, means_t1))
    assert torch.autograd.gradcheck(affine_model, (means_t, means_t1, covars_t, covars_t1))


def sample_gaussian_points(mean, covar, n):
    z = torch.randn(n, 3, dtype=D).clamp(-2, 2)
    return mean + z @ torch.linalg.cholesky(covar).T


@pytest.mark.parametrize("angle", [0.0, 0.7])
def test_affine_flow_matches_point_motion(angle):
    """Points of a small Gaussian under a known 3D stretch + translation: their projected
    displacements (finite differences of point projections) match the affine flow at their
    projected positions, and the plain mean flow is far worse for a stretch."""
    viewmat = torch.eye(4, dtype=D)
    viewmat[:3, 3] = torch.tensor([0.0, 0.0, 5.0], dtype=D)
    K = torch.tensor([[400.0, 0.0, 160.0], [0.0, 400.0, 120.0], [0.0, 0.0, 1.0]], dtype=D)
    c, s = math.cos(angle), math.sin(angle)
    Rz = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=D)
    F = Rz @ torch.diag(torch.tensor([1.08, 0.95, 1.0], dtype=D)) @ Rz.T  # symmetric in-plane stretch
    mean = torch.tensor([[0.05, -0.03, 0.0]], dtype=D)
    covar = (Rz @ torch.diag(torch.tensor([0.02, 0.008, 0.01], dtype=D)) ** 2 @ Rz.T).unsqueeze(0)
    shift = torch.tensor([[0.01, 0.004, 0.0]], dtype=D)
    points = sample_gaussian_points(mean[0], covar[0], 200)
    moved = mean + shift + (points - mean) @ F.T
    true = project_means(moved, viewmat, K) - project_means(points, viewmat, K)
    x = project_means(points, viewmat, K)
    feat = flow_features(
        mean, mean + shift, viewmat, K, model="affine", covars_t=covar, covars_t1=F @ covar @ F.T, eps2d=0.0
    )
    (m_xx, m_xy, m_yy), b = feat[0, :3], feat[0, 3:]
    M = torch.stack([torch.stack([m_xx, m_xy]), torch.stack([m_xy, m_yy])])
    affine = x @ M.T + b
    plain = flow_features(mean, mean + shift, viewmat, K, model="mean").expand_as(true)
    err_affine = (affine - true).norm(dim=-1).max()
    err_plain = (plain - true).norm(dim=-1).max()
    assert err_affine < 0.02 * err_plain  # measured: 0.002 px against 0.26 px
    assert err_affine < 5e-3  # px; perspective makes the true map only locally affine


def test_static_gaussians_have_no_flow_and_mean_features_render_as_constants():
    viewmat, K = camera()
    means = torch.randn(6, 3, dtype=D) * 0.2
    covars = random_spd(6)
    moved = means + torch.tensor([0.03, -0.01, 0.0], dtype=D)
    feat = flow_features(means, means, viewmat, K, model="affine", covars_t=covars, covars_t1=covars)
    torch.testing.assert_close(feat, torch.zeros_like(feat), atol=1e-10, rtol=0)
    mean_flow = flow_features(means, moved, viewmat, K, model="mean")
    image = torch.zeros(3, 4, 5, dtype=D)
    image[..., 3:] = mean_flow[0]
    torch.testing.assert_close(flow_from_features(image), mean_flow[0].expand(3, 4, 2))


def test_flow_from_features_affine_and_alpha():
    height, width = 5, 7
    M = torch.tensor([[0.1, -0.2], [-0.2, 0.3]], dtype=D)
    b = torch.tensor([1.5, -2.0], dtype=D)
    features = torch.tensor([0.1, -0.2, 0.3, 1.5, -2.0], dtype=D).expand(height, width, 5)
    x = pixel_centres(height, width)
    assert x[2, 3].tolist() == [3.5, 2.5]
    torch.testing.assert_close(flow_from_features(features), x @ M.T + b)
    alpha = torch.full((height, width, 1), 0.5, dtype=D)
    torch.testing.assert_close(flow_from_features(0.5 * features, alpha), x @ M.T + b)


def test_bad_input():
    viewmat, K = camera()
    means = torch.zeros(2, 3, dtype=D)
    with pytest.raises(InputError, match="covars_t"):
        flow_features(means, means, viewmat, K, model="affine")
    with pytest.raises(InputError, match="unknown simulated-flow model"):
        flow_features(means, means, viewmat, K, model="rigid")
    with pytest.raises(InputError, match=r"\[N, 3\]"):
        flow_features(means, means[:1], viewmat, K)
    with pytest.raises(InputError, match=r"\[H, W, 2\]"):
        flow_from_features(torch.zeros(4, 4, 6))


@pytest.mark.parametrize("model", ["mean", "affine"])
def test_a_gaussian_at_or_behind_the_camera_has_finite_flow_and_gradient(model):
    """A camera inside the object: one Gaussian exactly at the camera centre, one behind it,
    one crossing the near plane. Their features are 0 (the rasteriser culls them at frame t
    anyway) instead of NaN, which used to end the run as "rasterize: colors has NaN"."""
    from clflow.flow.simulated import render_simulated_flow

    viewmat, K = camera()
    W, t = viewmat[:3, :3], viewmat[:3, 3]
    centre = -W.T @ t  # the camera centre in world coordinates
    to_world = lambda p: (torch.tensor(p, dtype=D) - t) @ W  # noqa: E731 (camera -> world)
    means = torch.stack([centre, to_world([0.0, 0.0, -1.0]), to_world([0.1, 0.0, 0.5]), to_world([0.0, 0.0, 4.0])])
    moved = means.clone()
    moved[2] = to_world([0.1, 0.0, -0.2])  # in front at t, behind the camera at t+1
    moved[3] = to_world([0.05, 0.0, 4.0])  # an ordinary Gaussian: flow
    means, moved = means.clone().requires_grad_(), moved.clone().requires_grad_()
    covars = random_spd(4)
    flow, alpha = render_simulated_flow(
        means, moved, covars, torch.full((4,), 0.9, dtype=D), viewmat, K, 200, 150, model=model, covars_t1=covars
    )
    flow.sum().backward()
    assert bool(torch.isfinite(flow).all()) and float(flow.abs().max()) > 0  # the ordinary one moves
    assert bool(torch.isfinite(means.grad).all()) and bool(torch.isfinite(moved.grad).all())
    assert float(moved.grad[:3].abs().max()) == 0.0  # the dropped ones carry no gradient
