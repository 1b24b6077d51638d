"""SH rotation (clflow.splat.sh.rotate_sh): rotated coefficients seen along d equal the
originals seen along R^T d, the rasteriser's ``sh_rotations`` convention."""

import pytest
import torch

from clflow.splat.sh import rotate_sh, sh_basis
from tests.splat._helpers import rotations


def evaluate(degree, coeffs, dirs):
    """[N, 3] values of coefficients [N, K, 3] along unit directions [N, 3] (no offset, no clamp)."""
    return torch.einsum("nk,nkc->nc", sh_basis(degree, dirs), coeffs)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_rotated_coefficients_equal_the_originals_seen_along_rotated_directions(degree):
    g = torch.Generator().manual_seed(degree)
    n = 300
    coeffs = torch.randn(n, (degree + 1) ** 2, 3, dtype=torch.float64, generator=g)
    R = rotations(n, seed=10 + degree)
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, dtype=torch.float64, generator=g), dim=-1)
    turned = rotate_sh(coeffs, R, chunk=64)  # several chunks
    want = evaluate(degree, coeffs, torch.einsum("nji,nj->ni", R, dirs))  # R^T d
    torch.testing.assert_close(evaluate(degree, turned, dirs), want, rtol=0, atol=1e-12)
    torch.testing.assert_close(turned[:, 0], coeffs[:, 0], rtol=0, atol=1e-12)  # degree 0 does not turn
    if degree:  # the test can fail: unrotated coefficients do not match, nor do ones rotated by R^T
        assert (evaluate(degree, coeffs, dirs) - want).abs().max() > 0.1
        wrong = rotate_sh(coeffs, R.transpose(1, 2))
        assert (evaluate(degree, wrong, dirs) - want).abs().max() > 0.1


def test_rotation_keeps_each_band_and_composes():
    g = torch.Generator().manual_seed(7)
    coeffs = torch.randn(50, 16, 3, dtype=torch.float64, generator=g)
    A, B = rotations(50, seed=1), rotations(50, seed=2)
    torch.testing.assert_close(rotate_sh(rotate_sh(coeffs, A), B), rotate_sh(coeffs, B @ A), rtol=0, atol=1e-12)
    for lo, hi in ((1, 4), (4, 9), (9, 16)):  # a band rotates into itself, energy kept
        only = torch.zeros_like(coeffs)
        only[:, lo:hi] = coeffs[:, lo:hi]
        turned = rotate_sh(only, A)
        assert torch.cat([turned[:, :lo], turned[:, hi:]], 1).abs().max() < 1e-12
        torch.testing.assert_close(turned.square().sum(1), only.square().sum(1), rtol=1e-12, atol=1e-12)
    assert rotate_sh(coeffs.float(), A.float()).dtype == torch.float32
