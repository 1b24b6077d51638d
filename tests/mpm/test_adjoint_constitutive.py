"""Constitutive adjoints (update_stress_adjoint) at F = I, pure rotations and equal singular
values, against central differences of the float64 reference; float32 against float64."""

import math

import numpy as np
import pytest
import torch

from clflow.mpm import reference
from clflow.mpm.adjoint import SubstepAdjoint
from clflow.mpm.constants import MATERIAL_IDS, PARAM_COUNT
from clflow.mpm.substep import Grid

MU, LAMBDA = 3.0e4, 5.0e4
GRID = Grid((8, 8, 8), 0.1)


def rotation(axis, angle):
    axis = torch.tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    K = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def deformations():
    """name -> F: the rest state, rotations, equal and nearly equal singular values, generic."""
    R = rotation([1, 2, 3], 0.7)
    Q = rotation([-2, 1, 0.5], 1.1)
    gen = torch.Generator().manual_seed(3)
    return {
        "identity": torch.eye(3, dtype=torch.float64),
        "rotation": R,
        "rotation_pi_half": rotation([0, 0, 1], math.pi / 2),
        "uniform_scale": 1.2 * R,
        "two_equal": R @ torch.diag(torch.tensor([1.1, 1.1, 0.9], dtype=torch.float64)) @ Q.T,
        "nearly_equal": R @ torch.diag(torch.tensor([1.0, 1.0 + 1e-9, 0.95], dtype=torch.float64)) @ Q.T,
        "generic": torch.eye(3, dtype=torch.float64) + 0.2 * torch.randn(3, 3, generator=gen, dtype=torch.float64),
    }


def stress_vjp(device, material, F, tau_bar, dtype):
    """(Fbar, [mubar, lambdabar]) of L = <tau_bar, tau(F)> by the kernel (C = 0, F'bar = 0)."""
    n = F.shape[0]
    mat = torch.full((n,), MATERIAL_IDS[material], dtype=torch.int32)
    adjoint = SubstepAdjoint(device, dtype, n, GRID, mat)
    param = torch.zeros(n, PARAM_COUNT, dtype=dtype)
    param[:, 0], param[:, 1] = MU, LAMBDA
    F_bar = torch.empty(n, 3, 3, dtype=dtype)
    C_bar = torch.zeros(n, 3, 3, dtype=dtype)
    param_bar = torch.zeros(n, PARAM_COUNT, dtype=dtype)
    R = adjoint.real_t
    with device.bind() as b:
        device.launch(adjoint.k_stress, n, [
            np.int32(n), R(1e-3), b.input(F.to(dtype).contiguous()), b.input(torch.zeros(n, 3, 3, dtype=dtype)),
            b.input(mat), b.input(param), b.input(tau_bar.to(dtype).contiguous()),
            b.input(torch.zeros(n, 3, 3, dtype=dtype)), b.output(F_bar), b.inout(C_bar), b.inout(param_bar)])
    return F_bar.double(), param_bar[:, :2].double()


def reference_tau(material, F, mu, lam):
    q = torch.zeros(F.shape[0], PARAM_COUNT, dtype=torch.float64)
    q[:, 0], q[:, 1] = mu, lam
    _, _, tau = reference.constitutive(MATERIAL_IDS[material], F, None, q, torch.zeros(F.shape[0]), 1e-3)
    return tau


@pytest.mark.parametrize("material", ["elastic", "neo_hookean"])
def test_stress_adjoint_matches_central_differences(device, material):
    cases = deformations()
    F = torch.stack(list(cases.values()))
    gen = torch.Generator().manual_seed(5)
    tau_bar = torch.randn(F.shape, generator=gen, dtype=torch.float64)
    F_bar, q_bar = stress_vjp(device, material, F, tau_bar, torch.float64)
    h = 1e-6
    for idx, name in enumerate(cases):
        for k in range(9):
            dF = torch.zeros(1, 3, 3, dtype=torch.float64)
            dF.view(-1)[k] = h
            Fi = F[idx : idx + 1]
            diff = (reference_tau(material, Fi + dF, MU, LAMBDA) - reference_tau(material, Fi - dF, MU, LAMBDA)) / (2 * h)
            fd = float((tau_bar[idx] * diff[0]).sum())
            assert abs(F_bar[idx].view(-1)[k] - fd) < 1e-7 * (1 + F_bar[idx].abs().max()), (name, k)
        for j, (dmu, dlam) in enumerate(((1.0, 0.0), (0.0, 1.0))):
            diff = (reference_tau(material, Fi, MU + dmu, LAMBDA + dlam)
                    - reference_tau(material, Fi, MU - dmu, LAMBDA - dlam)) / 2
            assert abs(q_bar[idx, j] - float((tau_bar[idx] * diff[0]).sum())) < 1e-8 * (1 + q_bar[idx].abs().max())


def test_float32_adjoint_is_accurate_at_equal_singular_values(device):
    """The block form keeps float32 accurate at F = I and at rotations, where the generic SVD
    backward (1/(s_i^2 - s_j^2)) breaks down."""
    F = torch.stack(list(deformations().values()))
    tau_bar = torch.randn(F.shape, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    F64, q64 = stress_vjp(device, "elastic", F, tau_bar, torch.float64)
    F32, q32 = stress_vjp(device, "elastic", F, tau_bar, torch.float32)
    assert float((F32 - F64).abs().max() / F64.abs().max()) < 1e-5
    assert float((q32 - q64).abs().max() / q64.abs().max()) < 1e-5
