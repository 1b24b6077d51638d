"""Populations (clflow.mpm.population): K members in lockstep, each on its own grid, against
their own single runs, forward and adjoint, in the CPU plan (private P2G copies), the GPU
plan (the gather over particles sorted by cell) and the atomic path."""

import pytest
import torch

from clflow.errors import InputError
from clflow.mpm import Force, Grid, MaterialSpec, Region, Simulator
from clflow.mpm.autograd import simulate

GRID = Grid((16, 16, 16), dx=1 / 16)
N = 150


def block(dtype=torch.float32, seed=0) -> torch.Tensor:
    """[N, 3] positions (m) of a block above the floor, which it reaches within two frames."""
    g = torch.Generator().manual_seed(seed)
    x = 0.3 + 0.3 * torch.rand(N, 3, generator=g, dtype=torch.float64)
    x[:, 1] -= 0.17
    return x.to(dtype)


def falling(dtype=torch.float32, substeps=30):
    return dict(volume=1e-5, grid=GRID, frame_dt=1 / 24, substeps=substeps, dtype=dtype)


def member_velocities(k: int) -> torch.Tensor:
    """[k, N, 3] initial velocities (m/s): each member falls at its own speed."""
    return torch.tensor([0.0, -1.0, 0.2]).expand(k, N, 3) * torch.linspace(1.0, 2.0, k).view(k, 1, 1)


@pytest.fixture(params=["cpu", "gpu", "atomic"])
def plan(request, monkeypatch, copy_mode):
    """The kernel plan a simulator takes: the CPU plan, the GPU plan (forced, copy mode) or the CPU plan's atomic P2G."""
    monkeypatch.setenv("CLFLOW_KERNELS", "gpu" if request.param == "gpu" else "cpu")
    monkeypatch.delenv("CLFLOW_P2G", raising=False)  # the path is this fixture's (a device mode may set one)
    return request.param


def p2g(plan: str) -> str:
    return "atomic" if plan == "atomic" else "auto"


@pytest.mark.parametrize("k", [1, 3, 24])
def test_members_match_their_single_runs(plan, k):
    moduli = torch.logspace(4, 5, k)
    poisson = torch.linspace(0.2, 0.4, k)
    v = member_velocities(k)
    spec = MaterialSpec("elastic", {"youngs_modulus": moduli, "poissons_ratio": poisson})
    pop = Simulator(block(), materials=spec, velocities=v, p2g=p2g(plan), **falling())
    assert (pop.members, pop.batched, pop.n) == (k, True, k * N)
    traj = pop.run(2)
    assert traj.x.shape == (3, k, N, 3) and traj.F.shape == (3, k, N, 3, 3) and traj.plastic.shape == (3, k, N)
    for m in range(k):
        one_spec = MaterialSpec("elastic", {"youngs_modulus": float(moduli[m]), "poissons_ratio": float(poisson[m])})
        one = Simulator(block(), materials=one_spec, velocities=v[m], p2g=p2g(plan), **falling()).run(2)
        assert float((one.F[-1] - torch.eye(3)).abs().max()) > 1e-3  # the floor has deformed the block
        if plan == "gpu" or (k == 1 and plan == "cpu"):  # the same sums in the same order: the same bits
            assert torch.equal(traj.x[:, m], one.x) and torch.equal(traj.F[:, m], one.F)
        else:  # the private copies split the particles differently, atomics add in any order
            torch.testing.assert_close(traj.x[:, m], one.x, rtol=0, atol=2e-6)
            torch.testing.assert_close(traj.F[:, m], one.F, rtol=0, atol=2e-5)


def test_members_of_different_materials_and_densities(monkeypatch):
    """A population may batch any parameter and the density of every material of a
    scene; each member is the run of its own values."""
    monkeypatch.setenv("CLFLOW_KERNELS", "cpu")
    monkeypatch.delenv("CLFLOW_P2G", raising=False)
    x = block(torch.float64)
    index = (x[:, 0] > 0.45).long()
    sand = MaterialSpec("sand", {"friction_angle": [25.0, 35.0]}, density=[1500.0, 2000.0])
    elastic = MaterialSpec("elastic", {"youngs_modulus": 3e4})
    pop = Simulator(x, materials=[sand, elastic], material_index=index, **falling(torch.float64)).run(2)
    for m, (angle, rho) in enumerate([(25.0, 1500.0), (35.0, 2000.0)]):
        sand_m = MaterialSpec("sand", {"friction_angle": angle}, density=rho)
        one = Simulator(x, materials=[sand_m, elastic], material_index=index, **falling(torch.float64)).run(2)
        torch.testing.assert_close(pop.x[:, m], one.x, rtol=0, atol=1e-12)
    assert not torch.allclose(pop.x[-1, 0], pop.x[-1, 1])


def test_substep_is_the_stiffest_members():
    def chosen(moduli) -> int:
        spec = MaterialSpec("elastic", {"youngs_modulus": moduli})
        return Simulator(block(), materials=spec, **falling(substeps=None)).substeps

    assert chosen([1e4, 1e6]) == chosen(1e6) > chosen(1e4)


@pytest.mark.parametrize("k", [1, 3])
@pytest.mark.parametrize("plan", ["cpu", "gpu"], indirect=True)  # after an atomic P2G, the plan's adjoint
def test_member_gradients_match_their_single_runs(plan, k):
    """simulate() of a population: per-member parameters [K] get each member's own gradient."""
    dtype = torch.float64
    moduli = torch.logspace(4, 5, k, dtype=dtype)
    v = member_velocities(k).to(dtype)
    pop = Simulator(block(dtype), materials=MaterialSpec("elastic", {"youngs_modulus": moduli}), **falling(dtype))
    E = moduli.clone().requires_grad_()
    out = simulate(pop, 2, params={"youngs_modulus": E}, velocities=v)
    assert out.x.shape == (3, k, N, 3)
    (out.x[-1] ** 2).sum().backward()
    for m in range(k):
        one = Simulator(block(dtype), materials=MaterialSpec("elastic", {"youngs_modulus": 1.0}), **falling(dtype))
        e = moduli[m].clone().requires_grad_()
        o = simulate(one, 2, params={"youngs_modulus": e}, velocities=v[m])
        (o.x[-1] ** 2).sum().backward()
        assert abs(float(e.grad)) > 0
        if plan == "gpu" or k == 1:
            assert torch.equal(out.x[:, m], o.x) and torch.equal(E.grad[m], e.grad)
        else:
            torch.testing.assert_close(out.x[:, m], o.x, rtol=0, atol=1e-12)
            torch.testing.assert_close(E.grad[m], e.grad, rtol=1e-9, atol=0)


def test_population_inputs_are_checked():
    with pytest.raises(InputError, match="disagree on the number of members"):
        Simulator(
            block(),
            materials=MaterialSpec("elastic", {"youngs_modulus": [1e4, 2e4], "poissons_ratio": [0.2, 0.3, 0.4]}),
            **falling(),
        )
    with pytest.raises(InputError, match="disagree on the number of members"):
        Simulator(
            block(),
            materials=MaterialSpec("elastic", {"youngs_modulus": [1e4, 2e4]}),
            velocities=member_velocities(3),
            **falling(),
        )
    with pytest.raises(InputError, match="one value per member"):
        Simulator(block(), materials=MaterialSpec("elastic", {"youngs_modulus": [[1e4]]}), **falling())
    push = Force(Region.box((0, 0, 0), (1, 1, 1)), 0.0, 1.0, force=(0.0, 1.0, 0.0))
    with pytest.raises(InputError, match="one density for all members"):
        Simulator(block(), materials=MaterialSpec("elastic", density=[900.0, 1000.0]), forces=[push], **falling())
