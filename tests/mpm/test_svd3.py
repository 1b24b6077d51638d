"""kernels_cl/common/svd3.h: F = U diag(s) V^T, U and V rotations, s sorted (s2 signed)."""

import math

import numpy as np
import pytest
import torch

from clflow.runtime.bridge import bind


def svd3(device, F: torch.Tensor):
    n = F.shape[0]
    real = "double" if F.dtype == torch.float64 else "float"
    kern = device.kernel("common/svd3.cl", "svd3_batch", real)
    U, V = torch.empty(n, 3, 3, dtype=F.dtype), torch.empty(n, 3, 3, dtype=F.dtype)
    s = torch.empty(n, 3, dtype=F.dtype)
    with bind(device) as b:
        device.launch(
            kern, n, dict(n=np.int32(n), F=b.input(F.contiguous()), U=b.output(U), s=b.output(s), V=b.output(V))
        )
    return U, s, V


def rotation(axis, angle):
    axis = torch.tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    K = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def hard_cases() -> torch.Tensor:
    """Identity, rotations, equal and near-equal singular values, rank deficiency,
    reflections, extreme scales, and random matrices."""
    gen = torch.Generator().manual_seed(3)
    R1, R2 = rotation((1, 2, 3), 0.7), rotation((-2, 0.5, 1), 2.9)
    cases = [
        torch.eye(3, dtype=torch.float64),
        R1,
        rotation((0, 0, 1), math.pi),
        R1 @ torch.diag(torch.tensor([2.0, 2.0, 2.0], dtype=torch.float64)) @ R2.T,
        R1 @ torch.diag(torch.tensor([1.5, 1.5, 0.5], dtype=torch.float64)) @ R2.T,
        R1 @ torch.diag(torch.tensor([1.0, 1.0 + 1e-9, 1.0 - 1e-9], dtype=torch.float64)) @ R2.T,
        R1 @ torch.diag(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)) @ R2.T,
        R1 @ torch.diag(torch.tensor([3.0, 1e-7, 0.0], dtype=torch.float64)) @ R2.T,
        torch.zeros(3, 3, dtype=torch.float64),
        torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)),
        R1 @ torch.diag(torch.tensor([2.0, 1.0, -0.5], dtype=torch.float64)) @ R2.T,
        1e-6 * R1,
        1e6 * (R1 @ torch.diag(torch.tensor([3.0, 2.0, 1.0], dtype=torch.float64)) @ R2.T),
        torch.tensor([[1.0, 1e-8, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64),
    ]
    near_identity = torch.eye(3, dtype=torch.float64) + 1e-3 * torch.randn(50, 3, 3, generator=gen, dtype=torch.float64)
    return torch.cat([torch.stack(cases), near_identity, torch.randn(200, 3, 3, generator=gen, dtype=torch.float64)])


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
def test_svd3_properties(device, dtype, tol):
    F = hard_cases()
    U, s, V = svd3(device, F.to(dtype))
    U, s, V = U.double(), s.double(), V.double()
    scale = torch.linalg.matrix_norm(F, ord=2).clamp(min=1e-30)[:, None, None]
    eye = torch.eye(3, dtype=torch.float64)
    assert ((U @ torch.diag_embed(s) @ V.transpose(1, 2) - F).abs() / scale).max() < 10 * tol
    assert (U.transpose(1, 2) @ U - eye).abs().max() < 10 * tol
    assert (V.transpose(1, 2) @ V - eye).abs().max() < 10 * tol
    assert (torch.linalg.det(U) - 1).abs().max() < 10 * tol
    assert (torch.linalg.det(V) - 1).abs().max() < 10 * tol
    rel = scale[:, 0]
    assert bool((s[:, 0] >= s[:, 1] - tol * rel[:, 0]).all() and (s[:, 1] >= s[:, 2].abs() - tol * rel[:, 0]).all())
    assert bool((s[:, :2] >= 0).all())
    # |s| are the singular values; s2 carries the sign of det F
    expected = torch.linalg.svdvals(F)
    assert ((s.abs() - expected).abs() / rel).max() < 10 * tol
    det = torch.linalg.det(F)
    flipped = det < -1e-6 * scale[:, 0, 0] ** 3
    assert bool((s[flipped, 2] < 0).all()) and bool((s[det > 1e-6 * scale[:, 0, 0] ** 3, 2] > 0).all())
