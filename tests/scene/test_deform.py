"""Deforming Gaussians by deformation gradients."""

import numpy as np
import torch

from clflow.scene.deform import polar_rotations
from clflow.splat.geometry import covariances_of, deformed_covariances


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
    torch.testing.assert_close(
        deformed_covariances(cov, stretch)[0], torch.diag(torch.tensor([4.0, 4.0, 2.25], dtype=torch.float64))
    )
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
    torch.testing.assert_close(
        polar_rotations(torch.eye(3, dtype=torch.float64).repeat(4, 1, 1)),
        torch.eye(3, dtype=torch.float64).repeat(4, 1, 1),
    )


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


def test_a_frame_moves_and_deforms_the_object_and_keeps_the_static_gaussians():
    """frame_gaussians: object covariances F Sigma F^T and sh_rotations R_polar(F) R_up against a
    float64 numpy reference (SVD), fill particles beyond the object ignored, static unchanged."""
    from clflow.pipeline.render import frame_gaussians
    from clflow.splat.gaussians import Gaussians

    gen = torch.Generator().manual_seed(5)
    up = random_rotations(1, seed=6)[0]
    scene = (
        Gaussians.from_activated(
            torch.randn(9, 3, generator=gen),
            torch.randn(9, 4, generator=gen),
            0.1 + torch.rand(9, 3, generator=gen),
            0.2 + 0.6 * torch.rand(9, generator=gen),
            sh=torch.randn(9, 4, 3, generator=gen),
        )
        .transformed(up, 2.0)
        .to(torch.float32)
    )
    obj, static = scene.select(torch.arange(6)), scene.select(torch.arange(6, 9))
    x = torch.randn(8, 3, generator=gen)  # 6 Gaussians + 2 fill particles
    F = torch.eye(3) + 0.3 * torch.randn(8, 3, 3, generator=gen)
    g = frame_gaussians(static, obj, x, F)
    U, _, Vt = np.linalg.svd(F[:6].double().numpy())
    polar = U @ Vt
    polar[np.linalg.det(polar) < 0] = (U * np.array([1, 1, -1]) @ Vt)[np.linalg.det(polar) < 0]
    Fd, rest = F[:6].double().numpy(), obj.covariances.double().numpy()
    np.testing.assert_allclose(g.covariances[:6].numpy(), Fd @ rest @ Fd.transpose(0, 2, 1), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(g.sh_rotations[:6].numpy(), polar @ up.numpy(), atol=1e-5)
    assert torch.equal(g.means[:6], x[:6]) and torch.equal(g.means[6:], static.means)
    assert torch.equal(g.covariances[6:], static.covariances) and torch.equal(g.sh_rotations[6:], static.sh_rotations)
    assert torch.equal(g.opacity_logits, scene.opacity_logits) and torch.equal(g.sh, scene.sh)
