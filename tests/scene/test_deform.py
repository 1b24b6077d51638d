"""Deforming Gaussians by deformation gradients."""

import torch

from clflow.scene.deform import deformed_covariances, polar_rotations
from clflow.splat.gaussians import covariances_of


def random_rotations(n, seed=0):
    q, _ = torch.linalg.qr(torch.randn(n, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(seed)))
    return q * torch.sign(torch.det(q))[:, None, None]


def test_rest_covariance_has_the_scales_as_principal_std():
    R = random_rotations(5)
    s = torch.rand(5, 3, dtype=torch.float64) + 0.1
    cov = covariances_of(s, R)
    eig = torch.linalg.eigvalsh(cov)
    torch.testing.assert_close(eig, (s**2).sort(dim=1).values)


def test_a_stretch_scales_the_covariance_and_a_rotation_turns_it():
    cov = covariances_of(torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64), torch.eye(3, dtype=torch.float64)[None])
    stretch = torch.diag(torch.tensor([2.0, 1.0, 0.5], dtype=torch.float64))[None]
    torch.testing.assert_close(deformed_covariances(cov, stretch)[0], torch.diag(torch.tensor([4.0, 4.0, 2.25], dtype=torch.float64)))
    R = random_rotations(1, seed=3)
    torch.testing.assert_close(deformed_covariances(cov, R), R @ cov @ R.transpose(1, 2))


def test_polar_rotation_is_proper_and_recovers_the_rotation():
    R = random_rotations(20, seed=1)
    S = torch.diag_embed(torch.rand(20, 3, dtype=torch.float64) + 0.5)  # symmetric stretch in a rotated frame
    Q = random_rotations(20, seed=2)
    F = R @ (Q @ S @ Q.transpose(1, 2))
    torch.testing.assert_close(polar_rotations(F), R)
    inverted = F.clone()
    inverted[:, :, 2] *= -1  # det F < 0: still a proper rotation out
    assert torch.allclose(torch.det(polar_rotations(inverted)), torch.ones(20, dtype=torch.float64))
    torch.testing.assert_close(polar_rotations(torch.eye(3, dtype=torch.float64).repeat(4, 1, 1)), torch.eye(3, dtype=torch.float64).repeat(4, 1, 1))


def test_polar_rotation_in_float32_and_of_singular_matrices():
    R = random_rotations(13, seed=4)
    F = R @ torch.diag_embed(torch.rand(13, 3, dtype=torch.float64) + 0.5)
    torch.testing.assert_close(polar_rotations(F.float()), R.float(), atol=1e-5, rtol=0)
    flat = F.clone()
    flat[:, :, 1] = 0  # det F = 0 (a flattened element): still a rotation
    Rf = polar_rotations(flat)
    torch.testing.assert_close(Rf @ Rf.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(13, 3, 3))
    assert torch.allclose(torch.det(Rf), torch.ones(13, dtype=torch.float64))
    assert polar_rotations(torch.empty(0, 3, 3)).shape == (0, 3, 3)
