"""Constitutive adjoints (update_stress_adjoint) at F = I, pure rotations and equal singular
values, against central differences of the float64 reference; float32 against float64."""

import math

import pytest
import torch

from clflow.mpm import reference
from clflow.mpm.adjoint import SubstepAdjoint
from clflow.mpm.constants import MATERIAL_IDS, PARAM_COUNT
from clflow.mpm.substep import Grid
from clflow.runtime.bridge import bind

MU, LAMBDA, TAU_Y, XI = 3.0e4, 5.0e4, 300.0, 2.0
HARDENING = 40.0  # metal's plastic state: the yield stress gained so far (Pa)
V_C = 0.02  # volume-corrected sand's plastic state: the log volume correction


def plastic_state(material):
    """The plastic state the tests start from: snow's J_P, sand's v_c, else the metal's hardening."""
    return {"snow": 0.98, "sand_volume_corrected": V_C}.get(material, HARDENING)


GRID = Grid((8, 8, 8), 0.1)
# kernel parameter rows (clflow.mpm.material_model.kernel_params) per material
PARAMS = {
    "elastic": (MU, LAMBDA),
    "neo_hookean": (MU, LAMBDA),
    "plasticine": (MU, LAMBDA, TAU_Y),
    "metal": (MU, LAMBDA, TAU_Y, XI),
    "foam": (MU, LAMBDA, TAU_Y, 50.0),
    "non_newtonian": (MU, LAMBDA, TAU_Y, 50.0),
    "sand": (MU, LAMBDA, 0.3, 0.01),
    "newtonian": (1.0, 1e4),  # sand: cohesion keeps F = I off the tip
    "sand_volume_corrected": (MU, LAMBDA, 0.3, 0.01),  # c > V_C/3: F = I stays inside the cone
    "snow": (MU, LAMBDA, 0.025, 0.0075, 10.0),
}
MATERIALS = list(PARAMS)


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
        "below_yield": R @ torch.diag(torch.tensor([1.001, 1.0, 0.999], dtype=torch.float64)) @ Q.T,
        "above_yield": R @ torch.diag(torch.tensor([1.02, 1.0, 0.98], dtype=torch.float64)) @ Q.T,
        "compressed": R @ torch.diag(torch.tensor([0.95, 0.93, 0.9], dtype=torch.float64)) @ Q.T,
        "sheared": R @ torch.diag(torch.tensor([1.1, 1.0, 0.88], dtype=torch.float64)) @ Q.T,
    }


def kernel_params(n, material, dtype=torch.float64):
    q = torch.zeros(n, PARAM_COUNT, dtype=dtype)
    q[:, : len(PARAMS[material])] = torch.tensor(PARAMS[material], dtype=dtype)
    return q


def stress_vjp(device, material, F, tau_bar, F_new_bar, plastic, plastic_new_bar, dtype):
    """(Fbar, plastic_bar, param_bar) of L = <tau_bar, tau> + <F_new_bar, F'> + <plastic_new_bar,
    plastic'> of (F, plastic) by the kernel (C = 0)."""
    n = F.shape[0]
    mat = torch.full((n,), MATERIAL_IDS[material], dtype=torch.int32)
    adjoint = SubstepAdjoint(device, dtype, n, GRID, mat)
    param = kernel_params(n, material, dtype)
    F_bar = torch.empty(n, 3, 3, dtype=dtype)
    plastic_bar = torch.empty(n, dtype=dtype)
    C_bar = torch.zeros(n, 3, 3, dtype=dtype)
    param_bar = torch.zeros(n, PARAM_COUNT, dtype=dtype)
    F_in, C_in = F.to(dtype).contiguous(), torch.zeros(n, 3, 3, dtype=dtype)
    with bind(device) as b:
        adjoint.launch_stress_adjoint(
            1e-3,
            b.input(F_in),
            b.input(C_in),
            b.input(plastic.to(dtype).contiguous()),
            b.input(mat),
            b.input(param),
            b.input(tau_bar.to(dtype).contiguous()),
            b.input(F_new_bar.to(dtype).contiguous()),
            b.input(plastic_new_bar.to(dtype).contiguous()),
            b.output(F_bar),
            b.inout(C_bar),
            b.output(plastic_bar),
            b.inout(param_bar),
        )
    return F_bar.double(), plastic_bar.double(), param_bar.double()


def reference_loss(material, F, plastic, q, tau_bar, F_new_bar, plastic_new_bar) -> float:
    """<tau_bar, tau> + <F_new_bar, F'> + plastic_new_bar plastic' of the float64 reference for
    one F [3, 3] and plastic state (a number)."""
    F_new, plastic_new, tau = reference.constitutive(
        MATERIAL_IDS[material],
        F[None],
        torch.zeros(1, 3, 3, dtype=F.dtype),
        q[None],
        torch.tensor([plastic], dtype=torch.float64),
        1e-3,
    )
    return float((tau_bar * tau[0]).sum() + (F_new_bar * F_new[0]).sum() + plastic_new_bar * plastic_new[0])


def returned(material, F, plastic=HARDENING):
    """F' of the reference for F (C = 0)."""
    F_new, _, _ = reference.constitutive(
        MATERIAL_IDS[material],
        F[None],
        torch.zeros(1, 3, 3, dtype=F.dtype),
        kernel_params(1, material),
        torch.full((1,), plastic, dtype=F.dtype),
        1e-3,
    )
    return F_new[0]


def test_cases_cover_every_branch_of_the_returns():
    cases = deformations()
    for material in ("plasticine", "metal", "foam", "non_newtonian"):
        assert torch.equal(returned(material, cases["below_yield"]), cases["below_yield"]), material
        assert torch.equal(returned(material, cases["identity"]), cases["identity"]), material
        assert not torch.equal(returned(material, cases["above_yield"]), cases["above_yield"]), material
        assert not torch.equal(returned(material, cases["two_equal"]), cases["two_equal"]), material
    # sand: inside the cone (compressed, at rest), onto the cone (sheared), past the tip
    # (stretched: F' = exp(c) R)
    assert torch.equal(returned("sand", cases["compressed"]), cases["compressed"])
    assert torch.equal(returned("sand", cases["identity"]), cases["identity"])
    sheared = returned("sand", cases["sheared"])
    assert not torch.equal(sheared, cases["sheared"]) and float(torch.linalg.det(sheared)) < 1
    # snow: singular values inside [1 - theta_c, 1 + theta_s] stay, outside are clamped
    # (F_E is rebuilt from the SVD: equal up to rounding when nothing is clamped)
    assert torch.allclose(returned("snow", cases["rotation"]), cases["rotation"], atol=1e-14)
    assert not torch.allclose(returned("snow", cases["uniform_scale"]), cases["uniform_scale"], atol=1e-3)
    assert not torch.allclose(returned("snow", cases["compressed"]), cases["compressed"], atol=1e-3)
    tip = cases["uniform_scale"] / 1.2 * math.exp(PARAMS["sand"][3])
    assert torch.allclose(returned("sand", cases["uniform_scale"]), tip, atol=1e-14)
    # volume-corrected sand with v_c = V_C: inside the cone F' = exp(v_c/3) F, past the tip the
    # same as without, onto the cone (a different F' than without: the trace is shifted)
    for name in ("compressed", "identity"):
        inside = returned("sand_volume_corrected", cases[name], V_C)
        assert torch.equal(inside, math.exp(V_C / 3) * cases[name]), name
    assert torch.allclose(returned("sand_volume_corrected", cases["uniform_scale"], V_C), tip, atol=1e-14)
    sheared = returned("sand_volume_corrected", cases["sheared"], V_C)
    assert not torch.allclose(sheared, returned("sand", cases["sheared"]), atol=1e-6)
    assert not torch.allclose(sheared, math.exp(V_C / 3) * cases["sheared"], atol=1e-6)


@pytest.mark.parametrize("material", MATERIALS)
def test_stress_adjoint_matches_central_differences(device, material):
    cases = deformations()
    F = torch.stack(list(cases.values()))
    gen = torch.Generator().manual_seed(5)
    tau_bar = torch.randn(F.shape, generator=gen, dtype=torch.float64)
    F_new_bar = 1e4 * torch.randn(F.shape, generator=gen, dtype=torch.float64)
    plastic = torch.full(F.shape[:1], plastic_state(material), dtype=torch.float64)
    plastic_new_bar = torch.randn(F.shape[:1], generator=gen, dtype=torch.float64)
    F_bar, plastic_bar, q_bar = stress_vjp(
        device, material, F, tau_bar, F_new_bar, plastic, plastic_new_bar, torch.float64
    )
    q = kernel_params(1, material)[0]
    for idx, name in enumerate(cases):

        def loss(Fi, qi, h=plastic_state(material)):
            return reference_loss(material, Fi, h, qi, tau_bar[idx], F_new_bar[idx], float(plastic_new_bar[idx]))

        h = 1e-7
        scale = 1 + float(F_bar[idx].abs().max())
        for k in range(9):
            dF = torch.zeros(3, 3, dtype=torch.float64)
            dF.view(-1)[k] = h
            fd = (loss(F[idx] + dF, q) - loss(F[idx] - dF, q)) / (2 * h)
            assert abs(float(F_bar[idx].view(-1)[k]) - fd) < 1e-6 * scale, (name, k)
        for j in range(len(PARAMS[material])):
            dq = torch.zeros(PARAM_COUNT, dtype=torch.float64)
            dq[j] = 1e-4 * float(q[j]) if q[j] != 0 else 1e-6
            fd = (loss(F[idx], q + dq) - loss(F[idx], q - dq)) / (2 * float(dq[j]))
            assert abs(float(q_bar[idx, j]) - fd) < 1e-6 * (1 + float(q_bar[idx].abs().max())), (name, j)
        h0, dh = plastic_state(material), 1e-5
        fd = (loss(F[idx], q, h0 + dh) - loss(F[idx], q, h0 - dh)) / (2 * dh)
        assert abs(float(plastic_bar[idx]) - fd) < 1e-6 * (1 + abs(fd)), (name, "plastic")


def test_float32_adjoint_is_accurate_at_equal_singular_values(device):
    """The block form keeps float32 accurate at F = I and at rotations, where the generic SVD
    backward (1/(s_i^2 - s_j^2)) breaks down."""
    F = torch.stack(list(deformations().values()))
    tau_bar = torch.randn(F.shape, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    zero, zero_n = torch.zeros_like(F), torch.zeros(F.shape[0], dtype=torch.float64)
    F64, _, q64 = stress_vjp(device, "elastic", F, tau_bar, zero, zero_n, zero_n, torch.float64)
    F32, _, q32 = stress_vjp(device, "elastic", F, tau_bar, zero, zero_n, zero_n, torch.float32)
    assert float((F32 - F64).abs().max() / F64.abs().max()) < 1e-5
    assert float((q32 - q64).abs().max() / q64.abs().max()) < 1e-5
