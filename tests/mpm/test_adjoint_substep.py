"""The hand-written substep adjoint against torch autograd of the float64 reference substep."""

import dataclasses

import pytest
import torch

from clflow.mpm import Grid, HalfSpace, MaterialSpec, Simulator, reference
from clflow.mpm.adjoint import StateGrad, SubstepAdjoint
from clflow.mpm.substep import Particles
from clflow.runtime.arrays import DeviceArray, to_device, to_host
from tests.mpm._helpers import MATERIAL_CASES, cube, poison, random_scene, two_blocks

GRAD_FIELDS = ("x", "v", "C", "F", "plastic")


def warmed_up(steps=5, materials=("elastic",), **kwargs):
    """A float64 scene after a few substeps: C != 0, F != I, and walls 5 cells thick that cut
    through the particles' stencils (so the boundary adjoints are exercised)."""
    kwargs.setdefault("wall_cells", 5)
    sim = random_scene({m: MATERIAL_CASES[m] for m in materials}, **kwargs)
    for _ in range(steps):
        sim.step()
    return sim


def clamp_flags(sim) -> DeviceArray:
    return DeviceArray.zeros(sim.device, (sim.n,), torch.uint8)


def kernel_vjp(sim, grad_after: StateGrad, adjoint: SubstepAdjoint | None = None):
    """(dL/d state, dL/d param, dL/d mass) of L = <grad_after, substep(state)> by the kernels
    (``adjoint``'s, default a new SubstepAdjoint)."""
    n, dtype, dev = sim.n, sim.dtype, sim.device
    tape = sim.kernels.empty_tape()
    state = sim.device_state
    after = state.empty_like()
    inputs = sim.substep_inputs()
    sim.kernels.run(state, after, inputs, clamp_flags(sim), tape=tape)
    adjoint = adjoint or SubstepAdjoint(dev, dtype, n, sim.grid, sim.particles.material, sim.flip, sim.kernels.plan)
    grad = StateGrad.zeros(dev, n, dtype)
    param_grad = DeviceArray.zeros(dev, sim.particles.param.shape, dtype)
    mass_grad = DeviceArray.zeros(dev, (n,), dtype)
    adjoint.run(state, after, tape, inputs, to_device(grad_after, dev), grad, param_grad, mass_grad)
    return to_host(grad), param_grad.read(), mass_grad.read()


def reference_vjp(sim, grad_after: StateGrad):
    s, p = sim.state, sim.particles
    leaves = {f: getattr(s, f).clone().requires_grad_() for f in GRAD_FIELDS}
    param = p.param.clone().requires_grad_()
    mass = p.mass.clone().requires_grad_()
    state = type(s)(*(leaves[f] for f in GRAD_FIELDS))
    particles = Particles(mass, p.volume, p.material, param, p.group, p.release_time, p.mass_eps)
    out, _ = reference.substep(
        state,
        particles,
        sim.grid,
        sim.time,
        sim.dt,
        sim.gravity,
        sim.boundaries,
        sim.drivers.accel(sim.time, sim.dtype),
        sim.flip,
    )
    loss = sum((getattr(grad_after, f) * getattr(out, f)).sum() for f in GRAD_FIELDS)
    grads = torch.autograd.grad(loss, [leaves[f] for f in GRAD_FIELDS] + [param, mass])
    return StateGrad(*grads[:5]), grads[5], grads[6]


def random_grad(n, seed=1):
    gen = torch.Generator().manual_seed(seed)
    return StateGrad(
        *(
            torch.randn(shape, generator=gen, dtype=torch.float64)
            for shape in ((n, 3), (n, 3), (n, 3, 3), (n, 3, 3), (n,))
        )
    )


def rel_err(a, b):
    return float((a - b).abs().max() / b.abs().max().clamp(min=1e-300))


def assert_adjoint_matches_reference(sim, parameters=True, adjoint=None):
    """The kernel's state gradients (``adjoint``'s kernels, default new ones) and
    (``parameters``: where they are not round-off) the parameter and mass gradients agree
    with the reference's to 1e-9."""
    grad_after = random_grad(sim.n)
    grad, param_grad, mass_grad = kernel_vjp(sim, grad_after, adjoint)
    ref, ref_param, ref_mass = reference_vjp(sim, grad_after)
    for f in GRAD_FIELDS:
        assert rel_err(getattr(grad, f), getattr(ref, f)) < 1e-9, f
    if not parameters:
        return
    for k in range(param_grad.shape[1]):
        assert rel_err(param_grad[:, k], ref_param[:, k]) < 1e-9, k
    assert rel_err(mass_grad, ref_mass) < 1e-9


@pytest.mark.parametrize("walls,friction", [("separate", 0.0), ("slip", 0.3), ("sticky", 0.0)])
def test_substep_adjoint_matches_autograd_of_reference(walls, friction):
    assert_adjoint_matches_reference(warmed_up(walls=walls, wall_friction=friction))


@pytest.mark.parametrize("walls", ["separate", "sticky"])
@pytest.mark.parametrize("materials", [("elastic",), ("plasticine", "newtonian")])
def test_flip_blend_adjoint_matches_autograd_of_reference(walls, materials):
    """The PIC/FLIP blend's adjoint (flip = 0.7: both the FLIP and the PIC part) with the
    boundary conditions and the fused and per-particle stress adjoints."""
    sim = warmed_up(materials=materials, walls=walls, flip=0.7)
    assert sim.flip == 0.7
    assert_adjoint_matches_reference(sim)


@pytest.mark.parametrize("flip", [0.0, 0.99])
def test_adjoint_copies_are_zeroed_and_summed_only_in_their_boxes(flip, monkeypatch):
    """The G2P adjoint's private grid copies (the CPU plan), like P2G's, are zeroed and summed
    only in the box of nodes each particle chunk touches: copies full of NaN beforehand leave
    the adjoint of two separate moving blocks equal to the reference's."""
    monkeypatch.setenv("CLFLOW_KERNELS", "cpu")
    sim = two_blocks(("newtonian", "elastic"), flip=flip)
    for _ in range(5):
        sim.step()
    adjoint = SubstepAdjoint(sim.device, sim.dtype, sim.n, sim.grid, sim.particles.material, sim.flip)
    poison(sim.device, adjoint.grid_v_bar_copies)
    assert_adjoint_matches_reference(sim, adjoint=adjoint)
    boxes = adjoint.copy_boxes.read()
    volumes = (boxes[:, 3:] - boxes[:, :3]).prod(1)
    assert adjoint.copies >= 2 and int(volumes.max()) <= sim.grid.nodes // 4, boxes


@pytest.mark.parametrize("flip", [0.0, 0.99])
def test_the_gather_adjoint_writes_every_node_and_record(flip, monkeypatch):
    """The G2P adjoint as a gather per node (the GPU plan): with its records and grid_v_bar
    full of NaN beforehand, every node is written (empty ones with zeros), so the adjoint of
    two separate moving blocks equals the reference's; no private copies exist."""
    monkeypatch.setenv("CLFLOW_KERNELS", "gpu")
    sim = two_blocks(("newtonian", "elastic"), flip=flip, p2g="gather")
    for _ in range(5):
        sim.step()
    plan = sim.kernels.plan  # the adjoint's gather reads the forward's cell sort
    adjoint = SubstepAdjoint(sim.device, sim.dtype, sim.n, sim.grid, sim.particles.material, sim.flip, plan)
    poison(sim.device, adjoint.records.buffer)
    poison(sim.device, adjoint.grid_v_bar.buffer)
    assert_adjoint_matches_reference(sim, adjoint=adjoint)
    assert adjoint.gather and not hasattr(adjoint, "grid_v_bar_copies")


@pytest.mark.parametrize("p2g,gather", [("private", False), ("gather", True), ("atomic", False)])
def test_the_adjoint_takes_the_p2g_path_taken(p2g, gather, monkeypatch):
    """A differentiable run's adjoint follows its simulator's plan, with the P2G path taken:
    a private or gather P2G's scatter shape, the CPU plan's own after the atomic one."""
    from clflow.mpm.autograd import engine

    monkeypatch.setenv("CLFLOW_KERNELS", "cpu")
    sim = two_blocks(p2g=p2g)
    adjoint = engine(sim).adjoint
    assert adjoint.plan == sim.kernels.plan and sim.kernels.plan.p2g == p2g and adjoint.gather == gather


@pytest.mark.parametrize("material", ["plasticine", "metal", "foam", "sand", "newtonian", "non_newtonian", "snow"])
def test_material_substep_adjoint_matches_autograd_of_reference(material):
    assert_adjoint_matches_reference(warmed_up(materials=(material,)))


@pytest.mark.parametrize("materials,fused", [(("elastic",), True), (("elastic", "plasticine"), False)])
def test_elastic_stress_adjoint_fused_and_per_particle(materials, fused):
    """Elastic-only scenes take the fused SIMD stress adjoint (300 particles: a partial last
    work-item), mixed scenes the per-particle one: both match the reference."""
    sim = warmed_up(materials=materials)
    assert SubstepAdjoint(sim.device, sim.dtype, sim.n, sim.grid, sim.particles.material).elastic_only == fused
    assert_adjoint_matches_reference(sim)


def kernel_loss(sim, grad_after: StateGrad, state, particles) -> float:
    """<grad_after, substep(state)> by the kernels, from a host ``state`` and ``particles``."""
    state = to_device(state, sim.device)
    out = state.empty_like()
    inputs = dataclasses.replace(sim.substep_inputs(), particles=to_device(particles, sim.device))
    sim.kernels.run(state, out, inputs, clamp_flags(sim))
    out = to_host(out)
    return float(sum((getattr(grad_after, f) * getattr(out, f)).sum() for f in GRAD_FIELDS))


FLOOR_Y, FLOOR_FRICTION = 0.45, 2.0


def over_a_floor(mode: str):
    """The warmed-up random scene cut by a floor collider (y < 0.45 m), no walls; mu_f = 2 so
    that some floor nodes stick."""
    return warmed_up(walls=None, boundaries=[HalfSpace((0, FLOOR_Y, 0), (0, 1, 0), mode, FLOOR_FRICTION)])


def floor_node_velocities(sim) -> torch.Tensor:
    """[k, 3] velocities (m/s) of the next substep's grid nodes below FLOOR_Y, before the
    boundary conditions."""
    state = sim.device_state
    sim.kernels.run(state, state.empty_like(), sim.substep_inputs(), clamp_flags(sim))
    grid = sim.kernels.scratch.grid_mv.read()
    m, mv = grid[:, 0], grid[:, 1:]
    node_y = sim.grid.dx * (torch.arange(sim.grid.nodes) // sim.grid.resolution[2] % sim.grid.resolution[1])
    on_floor = (m > sim.particles.mass_eps) & (node_y.double() < FLOOR_Y)
    return mv[on_floor] / m[on_floor, None] + sim.dt * torch.tensor(sim.gravity, dtype=torch.float64)


def floor_branches(sim) -> dict[str, int]:
    """How many floor nodes of the next substep move into the floor and slide (|vt| > mu_f
    |v.n|), move into it and stick (|vt| <= mu_f |v.n|), or move away (v.n >= 0)."""
    v = floor_node_velocities(sim)
    vn, vt = v[:, 1], v[:, [0, 2]].norm(dim=-1)
    friction = FLOOR_FRICTION * (-vn).clamp(min=0)
    return {
        "slide": int(((vn < 0) & (vt > friction)).sum()),
        "stick": int(((vn < 0) & (vt <= friction)).sum()),
        "away": int((vn >= 0).sum()),
    }


@pytest.mark.parametrize("mode", ["slip", "separate"])
def test_floor_friction_adjoint_matches_autograd_of_reference(mode):
    """Coulomb friction only while moving into the floor: every branch of the half-space
    adjoint is exercised (sliding, stuck and moving-away nodes) and matches the reference."""
    sim = over_a_floor(mode)
    assert min(floor_branches(sim).values()) > 0, floor_branches(sim)
    assert_adjoint_matches_reference(sim)


def falling_straight_onto_a_frictionless_floor():
    """Unstressed fluid particles (F = I, C = 0) falling at 1 m/s onto a slip floor without
    friction (the J-only fluid: the reference's SVD has no derivative at F = I)."""
    x = cube(6, 0.4, 0.6)
    v = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64).expand(x.shape[0], 3)
    return Simulator(
        x,
        1e-5,
        MaterialSpec("newtonian", MATERIAL_CASES["newtonian"]),
        Grid((16, 16, 16), 1 / 16),
        velocities=v,
        walls=None,
        boundaries=[HalfSpace((0, FLOOR_Y, 0), (0, 1, 0), "slip", 0.0)],
        frame_dt=1e-2,
        substeps=10,
        dtype=torch.float64,
    )


def test_frictionless_slip_passes_tangential_adjoints_at_zero_tangential_velocity():
    """A floor node moving straight into a frictionless slip floor (vt = 0 exactly) keeps the
    tangential part of a perturbation (v' = P v, so vbar = P v'bar), not zero. (Unstressed
    and moving as one, the particles' parameter and mass gradients vanish: only round-off.)"""
    sim = falling_straight_onto_a_frictionless_floor()
    v = floor_node_velocities(sim)
    assert v.shape[0] > 0 and bool((v[:, [0, 2]] == 0).all()) and bool((v[:, 1] < 0).all())
    assert_adjoint_matches_reference(sim, parameters=False)
    assert_dot_product_matches_central_differences(sim)


@pytest.mark.parametrize(
    "sim",
    [lambda: warmed_up(walls="slip", wall_friction=0.2), lambda: over_a_floor("slip")],
    ids=["slip_walls", "slip_floor"],
)
def test_substep_adjoint_dot_product_with_central_differences(sim):
    assert_dot_product_matches_central_differences(sim())


def assert_dot_product_matches_central_differences(sim):
    """<J^T ybar, xdot> = d/dh <ybar, f(x + h xdot)> for a random direction of every input."""
    grad_after = random_grad(sim.n)
    grad, param_grad, mass_grad = kernel_vjp(sim, grad_after)
    gen = torch.Generator().manual_seed(7)
    s, p = sim.state, sim.particles
    # small directions (x by ~1e-4 cells at h = 1): the friction and separation branches of
    # the walls are kinks, and a step across one is no test of the derivative
    dirs = {f: 1e-3 * torch.randn(getattr(s, f).shape, generator=gen, dtype=torch.float64) for f in GRAD_FIELDS}
    dirs["x"] *= 0.1 * sim.grid.dx
    dparam = torch.zeros_like(p.param)
    dparam[:, :2] = 1e-3 * p.param[:, :2] * torch.randn(sim.n, 2, generator=gen, dtype=torch.float64)
    dmass = 1e-3 * p.mass * torch.randn(sim.n, generator=gen, dtype=torch.float64)
    predicted = float(
        sum((getattr(grad, f) * dirs[f]).sum() for f in GRAD_FIELDS)
        + (param_grad * dparam).sum()
        + (mass_grad * dmass).sum()
    )

    def loss_at(h):
        state = type(s)(*(getattr(s, f) + h * dirs[f] for f in GRAD_FIELDS))
        particles = Particles(
            p.mass + h * dmass, p.volume, p.material, p.param + h * dparam, p.group, p.release_time, p.mass_eps
        )
        return kernel_loss(sim, grad_after, state, particles)

    h = 1e-3
    measured = (loss_at(h) - loss_at(-h)) / (2 * h)
    assert abs(measured - predicted) < 1e-6 * abs(predicted)
