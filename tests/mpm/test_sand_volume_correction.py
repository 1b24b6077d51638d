"""Sand's volume correction (Tampubolon et al. 2017): the forward kernel against the float64
reference, the substep and trajectory adjoints, and what the correction does to a column of
sand that is thrown apart and falls back together."""

import pytest
import torch

from clflow.errors import InputError
from clflow.mpm import Grid, MaterialSpec, Simulator, reference
from clflow.mpm.autograd import simulate
from clflow.mpm.constants import MATERIAL_IDS
from tests.mpm._helpers import MATERIAL_CASES, VOLUME_CORRECTED_SAND, loss_rounding, random_scene
from tests.mpm.test_adjoint_substep import GRAD_FIELDS, kernel_vjp, random_grad, reference_vjp, rel_err
from tests.mpm.test_adjoint_trajectory import FRAMES, loss_of, swirling_block, weights
from tests.mpm.test_material_physics import lattice
from tests.mpm.test_substep import run_both

PLAIN_SAND = MaterialSpec("sand", MATERIAL_CASES["sand"])


def test_model_option_selects_the_kernel_material():
    assert int(random_scene([PLAIN_SAND]).particles.material[0]) == MATERIAL_IDS["sand"]
    sim = random_scene([VOLUME_CORRECTED_SAND])
    assert int(sim.particles.material[0]) == MATERIAL_IDS["sand_volume_corrected"]
    assert float(sim.state.plastic.abs().max()) == 0  # v_c starts at 0
    with pytest.raises(InputError, match="sand model 'cap' unknown; choose one of drucker_prager, volume_corrected"):
        random_scene([MaterialSpec("sand", model="cap")])


@pytest.mark.parametrize("substeps", [1, 20])
def test_matches_reference_float64(substeps):
    sim = random_scene([VOLUME_CORRECTED_SAND])
    assert run_both(sim, substeps) < 1e-9


def test_mixed_with_plain_sand_matches_reference():
    """Both sand kernels in one build; the plain one leaves its (unused) plastic state at 0."""
    sim = random_scene([PLAIN_SAND, VOLUME_CORRECTED_SAND])
    assert run_both(sim, 20) < 1e-9
    plain = sim.particles.material == MATERIAL_IDS["sand"]
    assert float(sim.state.plastic[plain].abs().max()) == 0
    assert float(sim.state.plastic[~plain].max()) > 0


def branches(sim) -> list[int]:
    """Counts of the particles whose next substep goes past the tip, onto the cone, stays
    inside it, and gives a correction back (v_c > 0, not past the tip), by the reference."""
    s, q = sim.state, sim.particles.param
    F_tr = (torch.eye(3, dtype=s.F.dtype) + sim.dt * s.C) @ s.F
    _, sv, _ = reference.signed_svd(F_tr)
    F_new, v_c_new, _ = reference.constitutive(MATERIAL_IDS["sand_volume_corrected"], F_tr, s.C, q, s.plastic, sim.dt)
    assert float(sv.abs().min()) > 1e-3  # no strain floor in play: the counts mean what they say
    tip = v_c_new > 1e-12
    inside = ~tip & (F_new - torch.exp(s.plastic / 3)[:, None, None] * F_tr).abs().amax((1, 2)).le(1e-12)
    return [int(tip.sum()), int((~tip & ~inside).sum()), int(inside.sum()), int((~tip & (s.plastic > 0)).sum())]


def branches_seen(sim, substeps: int) -> list[int]:
    """branches() summed over the next ``substeps`` substeps."""
    seen = [0, 0, 0, 0]
    for _ in range(substeps):
        seen = [a + b for a, b in zip(seen, branches(sim))]
        sim.step()
    return seen


def test_scene_exercises_every_branch_with_a_correction():
    assert min(branches_seen(random_scene([VOLUME_CORRECTED_SAND]), 20)) > 0


def test_substep_adjoint_matches_autograd_of_reference():
    """After 20 substeps some particles carry v_c > 0: its gradient is part of the state's."""
    sim = random_scene([VOLUME_CORRECTED_SAND], wall_cells=5)
    for _ in range(20):
        sim.step()
    assert float(sim.state.plastic.max()) > 0
    grad_after = random_grad(sim.n)
    grad, param_grad, mass_grad = kernel_vjp(sim, grad_after)
    ref, ref_param, ref_mass = reference_vjp(sim, grad_after)
    for f in GRAD_FIELDS:
        assert rel_err(getattr(grad, f), getattr(ref, f)) < 1e-9, f
    for k in range(4):
        assert rel_err(param_grad[:, k], ref_param[:, k]) < 1e-9, k
    assert rel_err(mass_grad, ref_mass) < 1e-9
    assert float(grad.plastic[sim.state.plastic > 0].abs().min()) > 0


def compressed_block() -> Simulator:
    """The swirling block of test_adjoint_trajectory squeezed along x (-4 (x - 0.5) m/s) and
    stretched along z, its particles carrying corrections v_c in [0, 0.05) from an earlier
    expansion: within 3 frames x 10 substeps particles go past the tip and give corrections
    back on the cone and inside it."""
    x, v = swirling_block()
    v[:, 0] -= 4.0 * (x[:, 0] - 0.5)
    sim = Simulator(
        x,
        (0.24 / 6) ** 3,
        VOLUME_CORRECTED_SAND,
        Grid((16, 16, 16), 1 / 16),
        velocities=v,
        frame_dt=1e-2,
        substeps=10,
        dtype=torch.float64,
    )
    sim.state.plastic.copy_(0.05 * torch.rand(sim.n, generator=torch.Generator().manual_seed(4), dtype=torch.float64))
    return sim


def test_trajectory_gradient_matches_central_differences():
    """d loss / d (E, nu, phi, c, initial velocities) through the compressed block: the
    gradient crosses substeps through v_c."""
    assert min(branches_seen(compressed_block(), FRAMES * 10)) > 0
    sim = compressed_block()
    inputs = {
        name: torch.tensor(value, dtype=torch.float64, requires_grad=True)
        for name, value in MATERIAL_CASES["sand"].items()
    }
    velocities = sim.state.v.clone().requires_grad_()
    w = weights(sim, FRAMES)
    loss = loss_of(simulate(sim, FRAMES, params=inputs, velocities=velocities), w)
    loss.backward()
    resolution = loss_rounding(sim) * abs(float(loss.detach()))  # rounding of the loss over a step
    gen = torch.Generator().manual_seed(3)
    directions = {name: 1e-5 * max(abs(value), 1e-3) for name, value in MATERIAL_CASES["sand"].items()}
    directions["velocities"] = 1e-5 * torch.randn(velocities.shape, generator=gen, dtype=torch.float64)
    for name, direction in directions.items():
        grad = velocities.grad if name == "velocities" else inputs[name].grad
        predicted = float((grad * direction).sum())

        def loss_at(h):
            shifted = {k: val.detach() + (h * direction if k == name else 0.0) for k, val in inputs.items()}
            moved = velocities.detach() + (h * direction if name == "velocities" else 0.0)
            with torch.no_grad():
                return float(loss_of(simulate(sim, FRAMES, params=shifted, velocities=moved), w))

        measured = (loss_at(1.0) - loss_at(-1.0)) / 2
        assert abs(measured - predicted) < 1e-5 * abs(measured) + resolution, (name, measured, predicted)


def settled_height(model, throw: float) -> float:
    """Height (m, 2nd to 98th percentile of y) of a sand column between slip walls after it
    is thrown upwards with v_y = throw (y - floor) (1/s) and falls back (mean of the last
    6 of 16 frames of 0.05 s)."""
    dx, wall = 1 / 32, 3
    h = dx / 2
    x = lattice((10, 20, 10), (wall * dx,) * 3, h)  # fills the 5 x 5 cells between the walls
    v = torch.zeros_like(x)
    v[:, 1] = throw * (x[:, 1] - wall * dx)
    sim = Simulator(
        x,
        h**3,
        MaterialSpec("sand", {"youngs_modulus": 1e5}, density=1500, model=model),
        Grid((12, 48, 12), dx),
        velocities=v,
        walls="slip",
        wall_cells=wall,
        frame_dt=0.05,
    )
    y = sim.run(16).x[-6:, :, 1].double()
    return float((torch.quantile(y, 0.98, dim=1) - torch.quantile(y, 0.02, dim=1)).mean())


def test_thrown_column_keeps_its_volume_only_with_the_correction():
    """Thrown apart, the sand goes past the cone's tip and forgets the expansion; without the
    correction it piles up from the expanded state and keeps the gained volume (the column
    settles ~20 % higher than one left at rest); with it, v_c gives the expansion back and the
    column settles as high as the undisturbed one."""
    at_rest = settled_height(None, 0.0)
    plain = settled_height(None, 3.0)
    corrected = settled_height("volume_corrected", 3.0)
    assert plain > 1.12 * at_rest
    assert corrected == pytest.approx(at_rest, rel=0.05)
