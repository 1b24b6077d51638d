"""Rendered simulated flow (through the OpenCL rasteriser) against analytic motion."""

import math

import pytest
import torch

from clflow.flow.losses import masked_flow_loss
from clflow.flow.simulated import render_simulated_flow

D = torch.float64
FX, FY, CX, CY = 120.0, 110.0, 40.0, 30.0
WIDTH, HEIGHT = 80, 60


def camera():
    viewmat = torch.eye(4, dtype=D)
    viewmat[2, 3] = 3.0  # the world origin lies 3 m in front of the camera
    K = torch.tensor([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]], dtype=D)
    return viewmat, K


def pinhole(p):
    """Pixel of world point(s) [..., 3] for camera(): by hand, not through clflow."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2] + 3.0
    return torch.stack([FX * x / z + CX, FY * y / z + CY], -1)


def isotropic(n, sigma):
    return (sigma**2) * torch.eye(3, dtype=D).expand(n, 3, 3).clone()


def test_separate_gaussians_render_their_projected_displacement():
    """Four non-overlapping Gaussians at different depths, each moved by its own 3D
    displacement: wherever one covers a pixel, the rendered flow is its projected
    displacement pinhole(mu + d) - pinhole(mu), exactly."""
    means = torch.tensor([[-0.5, -0.4, 0.0], [0.5, -0.4, 0.5], [-0.5, 0.4, -0.5], [0.5, 0.4, 0.2]], dtype=D)
    moves = torch.tensor([[0.03, 0.0, 0.0], [0.0, -0.02, 0.1], [-0.01, 0.02, -0.2], [0.02, 0.02, 0.05]], dtype=D)
    viewmat, K = camera()
    flow, alpha = render_simulated_flow(
        means, means + moves, isotropic(4, 0.05), torch.full((4,), 0.9, dtype=D), viewmat, K, WIDTH, HEIGHT
    )
    assert flow.shape == (HEIGHT, WIDTH, 2) and alpha.shape == (HEIGHT, WIDTH, 1)
    expected = pinhole(means + moves) - pinhole(means)
    centres = pinhole(means)
    for g in range(4):
        j, i = int(centres[g, 0]), int(centres[g, 1])
        patch = flow[i - 2 : i + 3, j - 2 : j + 3].reshape(-1, 2)
        assert alpha[i, j, 0] > 0.5
        torch.testing.assert_close(patch, expected[g].expand_as(patch), rtol=0, atol=1e-12)
    assert (flow[alpha[..., 0] < 1e-2] == 0).all()


def test_overlapping_gaussians_moving_together_render_one_flow():
    """A layer of overlapping Gaussians at one depth moved parallel to the image plane:
    every Gaussian has the same projected displacement, so the alpha-normalised flow is
    that displacement everywhere the layer covers, and the raw flow is it times alpha."""
    g = torch.Generator().manual_seed(0)
    n = 40
    means = torch.cat([(torch.rand(n, 2, generator=g, dtype=D) - 0.5) * 1.2, torch.zeros(n, 1, dtype=D)], 1)
    move = torch.tensor([0.02, -0.015, 0.0], dtype=D)
    viewmat, K = camera()
    opacities = torch.rand(n, generator=g, dtype=D) * 0.5 + 0.3
    args = (means, means + move, isotropic(n, 0.08), opacities, viewmat, K, WIDTH, HEIGHT)
    flow, alpha = render_simulated_flow(*args)
    expected = torch.tensor([FX * 0.02 / 3.0, FY * -0.015 / 3.0], dtype=D)
    covered = alpha[..., 0] > 0.05
    assert covered.float().mean() > 0.3
    torch.testing.assert_close(flow[covered], expected.expand(int(covered.sum()), 2), rtol=0, atol=1e-10)
    raw, _ = render_simulated_flow(*args, normalize=False)
    torch.testing.assert_close(raw, alpha * expected, rtol=0, atol=1e-12)


def test_affine_flow_of_a_growing_gaussian():
    """An isotropic Gaussian on the optical axis grows by s in 3D: its 2D covariances are
    sigma_p^2 I + eps2d I before and s^2 sigma_p^2 I + eps2d I after, so the affine flow is
    (a - 1)(x - mu) with a = sqrt((s^2 sigma_p^2 + eps2d) / (sigma_p^2 + eps2d)); the mean
    model sees no motion at all."""
    from clflow.splat.constants import EPS2D

    sigma, s = 0.1, 1.05
    means = torch.zeros(1, 3, dtype=D)
    viewmat, K = camera()
    width, height = 2 * int(CX), 2 * int(CY)  # the mean at (CX, CY) is the image centre
    K_iso = K.clone()
    K_iso[1, 1] = FX
    args = (means, means, isotropic(1, sigma), torch.tensor([0.8], dtype=D), viewmat, K_iso, width, height)
    flow, alpha = render_simulated_flow(*args, model="affine", covars_t1=isotropic(1, s * sigma))
    sigma_p = FX * sigma / 3.0
    a = math.sqrt((s**2 * sigma_p**2 + EPS2D) / (sigma_p**2 + EPS2D))
    v, u = torch.meshgrid(torch.arange(height, dtype=D) + 0.5, torch.arange(width, dtype=D) + 0.5, indexing="ij")
    expected = (a - 1.0) * torch.stack([u - CX, v - CY], -1)
    covered = alpha[..., 0] > 0.05
    torch.testing.assert_close(flow[covered], expected[covered], rtol=0, atol=1e-10)
    still, _ = render_simulated_flow(*args)
    assert still.abs().max() == 0


@pytest.mark.parametrize("model", ["mean", "affine"])
def test_flow_loss_gradcheck_wrt_positions(model):
    """d(flow loss)/d(Gaussian positions at t and t+1) through features and rasteriser."""
    g = torch.Generator().manual_seed(1)
    n, width, height = 3, 20, 16
    viewmat = torch.eye(4, dtype=D)
    viewmat[2, 3] = 3.0
    K = torch.tensor([[30.0, 0.0, 10.0], [0.0, 30.0, 8.0], [0.0, 0.0, 1.0]], dtype=D)
    means_t = torch.tensor([[-0.3, -0.2, 0.0], [0.25, 0.1, 0.2], [0.0, 0.25, -0.3]], dtype=D)
    means_t1 = means_t + 0.05 * torch.randn(n, 3, generator=g, dtype=D)
    covars_t = isotropic(n, 0.25)
    covars_t1 = isotropic(n, 0.27)
    opacities = torch.tensor([0.7, 0.6, 0.8], dtype=D)
    observed = 0.5 * torch.randn(height, width, 2, generator=g, dtype=D)
    mask = torch.zeros(height, width, dtype=torch.bool)
    mask[2:-2, 2:-2] = True
    covars_t1_arg = covars_t1 if model == "affine" else None

    def loss(m0, m1):
        flow, _ = render_simulated_flow(
            m0, m1, covars_t, opacities, viewmat, K, width, height, model=model, covars_t1=covars_t1_arg
        )
        return masked_flow_loss(flow, observed, mask)

    assert torch.autograd.gradcheck(loss, (means_t.requires_grad_(), means_t1.requires_grad_()), atol=1e-7, rtol=1e-5)
