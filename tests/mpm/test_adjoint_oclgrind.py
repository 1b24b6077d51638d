"""Every MPM adjoint kernel under oclgrind: no out-of-bounds access, no data race (tiny scene
with every material, colliders, velocity regions, a force stage and a clamped particle; and an
elastic-only scene, which takes the fused SIMD stress adjoint; a PIC/FLIP blend; a population
of three on the private and the gather paths)."""

import textwrap

import pytest

from tests.mpm._helpers import assert_clean_under_oclgrind

pytestmark = [pytest.mark.oclgrind, pytest.mark.slow]

SCRIPT = textwrap.dedent(
    """
    import warnings
    import torch
    from clflow.mpm import Box, Force, HalfSpace, MaterialSpec, RotatingCylinder
    from clflow.mpm.autograd import simulate
    from tests.mpm._helpers import MATERIAL_CASES, VOLUME_CORRECTED_SAND, assert_velocity_gradient, random_scene, tiny_plasticine
    warnings.simplefilter("ignore")
    n = 18
    specs = [MaterialSpec(name, params) for name, params in MATERIAL_CASES.items()] + [VOLUME_CORRECTED_SAND]
    sim = random_scene(specs, n=n, substeps=2, frame_dt=2e-4, walls=None, p2g="private",
                       forces=[Force(torch.arange(n) % 2 == 0, 0, 1, force=(1, 0, 0))],
                       boundaries=[HalfSpace((0, 0.35, 0), (0, 1, 0), "separate", 0.3),
                                   Box((0.4,) * 3, (0.5,) * 3), RotatingCylinder((0.5,) * 3, (0, 1, 0), 0.2, 0.1, 2.0)])
    positions = sim.state.x.clone()
    positions[0, 0] = 0.87  # at the upper end of the grid's interior, pushed out: clamped back
    positions.requires_grad_()
    velocities = sim.state.v.clone()
    velocities[0] = torch.tensor([100.0, 0.0, 0.0])
    out = simulate(sim, 1, positions=positions, velocities=velocities)
    (out.x.sum() + out.F.sum()).backward()
    assert float(out.x[1, 0, 0]) == 0.875  # clamped to the interior's upper bound
    assert bool(torch.isfinite(positions.grad).all())
    # elastic only: the fused SIMD stress adjoint, 13 particles (a partial second work-item)
    solo = random_scene({"elastic": MATERIAL_CASES["elastic"]}, n=13, substeps=2, frame_dt=2e-4, walls=None,
                        p2g="private")
    E = torch.tensor(1e4, dtype=torch.float64, requires_grad=True)
    (simulate(solo, 1, params={"youngs_modulus": E}).x ** 2).sum().backward()
    assert bool(torch.isfinite(E.grad)) and float(E.grad) != 0
    # the PIC/FLIP blend's kernels (7-channel grid, dv, p2g_flip_adjoint), forward and adjoint
    assert_velocity_gradient(tiny_plasticine(flip=0.9, p2g="private"))
    # a population of three, each member on its own grid, on the private and the gather paths
    for path in ("private", "gather"):
        pop = random_scene({"elastic": dict(MATERIAL_CASES["elastic"], youngs_modulus=[1e4, 2e4, 3e4])}, n=13,
                           substeps=2, frame_dt=2e-4, walls=None, p2g=path)
        E = torch.tensor([1e4, 2e4, 3e4], dtype=torch.float64, requires_grad=True)
        (simulate(pop, 1, params={"youngs_modulus": E}).x ** 2).sum().backward()
        assert bool(torch.isfinite(E.grad).all()) and bool((E.grad != 0).all())
    print("done on", sim.device.info.label)
    """
)


def test_adjoint_kernels_are_clean_under_oclgrind(oclgrind):
    assert_clean_under_oclgrind(oclgrind, SCRIPT)
