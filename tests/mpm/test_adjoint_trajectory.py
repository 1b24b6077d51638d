"""Whole-trajectory gradients of clflow.mpm.autograd.simulate: central differences in
float64, float32 smoke, determinism, parameter identification."""

import pytest
import torch

from clflow.errors import InputError
from clflow.materials import get_material
from clflow.mpm import Force, Grid, MaterialSpec, Simulator
from clflow.mpm.autograd import memory_estimate, region_masses, replay_segment, simulate
from clflow.mpm.constants import MATERIAL_IDS
from clflow.mpm.material_model import KERNEL_PARAMETERS
from clflow.mpm.parameterization import parameterization
from tests.mpm._helpers import MATERIAL_CASES, assert_repeats, cube, loss_rounding

E_TRUE, NU_TRUE, RHO_TRUE, TAU_Y_TRUE = 2e4, 0.3, 800.0, 500.0


def swirling_block():
    """216 particles in a cube (m) and a smooth swirling velocity field (m/s)."""
    x = cube(6, 0.38, 0.62)
    c = x - 0.5
    return x, torch.stack([-c[:, 1], c[:, 0], 0.5 * c[:, 2]], 1) * 4.0


def scene(dtype=torch.float64, substeps=10, model=None, seed=0, material="elastic", flip=0.0):
    """216 particles in a cube with a smooth swirling velocity field, far from the walls for
    the few frames simulated (no contact kinks), 16^3 grid of 1/16 m."""
    x, v = swirling_block()
    v = v + torch.tensor([0.2, 0.0, -0.1])
    v += 0.05 * torch.randn(x.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    params = {"youngs_modulus": E_TRUE, "poissons_ratio": NU_TRUE}
    if material == "plasticine":
        params["yield_stress"] = TAU_Y_TRUE
    spec = MaterialSpec(material, params, density=RHO_TRUE, model=model)
    return Simulator(
        x,
        (0.24 / 6) ** 3,
        spec,
        Grid((16, 16, 16), 1 / 16),
        velocities=v,
        frame_dt=1e-2,
        substeps=substeps,
        dtype=dtype,
        flip=flip,
    )


def weights(sim, frames, seed=1):
    gen = torch.Generator().manual_seed(seed)
    n = sim.n
    return (
        torch.randn(frames + 1, n, 3, generator=gen, dtype=torch.float64),
        torch.randn(frames + 1, n, 3, generator=gen, dtype=torch.float64),
        torch.randn(frames + 1, n, 3, 3, generator=gen, dtype=torch.float64),
    )


STATE_INPUTS = ("density", "positions", "velocities")


def run(sim, frames, inputs, **kwargs):
    """simulate() with ``inputs`` by name: material parameters go into ``params``."""
    params = {k: v for k, v in inputs.items() if k not in STATE_INPUTS}
    return simulate(sim, frames, params=params, **{k: v for k, v in inputs.items() if k in STATE_INPUTS}, **kwargs)


def loss_of(out, w):
    return (w[0] * out.x).sum() + 0.1 * (w[1] * out.v).sum() + (w[2] * out.F).sum()


def make_inputs(sim, dtype, material="elastic"):
    extra = {}
    if material == "plasticine":
        extra["yield_stress"] = torch.tensor(TAU_Y_TRUE, dtype=dtype, requires_grad=True)
    return extra | {
        "youngs_modulus": torch.tensor(E_TRUE, dtype=dtype, requires_grad=True),
        "poissons_ratio": torch.tensor(NU_TRUE, dtype=dtype, requires_grad=True),
        "density": torch.tensor(RHO_TRUE, dtype=dtype, requires_grad=True),
        "positions": sim.state.x.clone().requires_grad_(),
        "velocities": sim.state.v.clone().requires_grad_(),
    }


FRAMES = 3


@pytest.mark.parametrize(
    "material,model,flip",
    [
        ("elastic", "fixed_corotated", 0.0),
        ("elastic", "neo_hookean", 0.0),
        ("plasticine", None, 0.0),
        ("elastic", "neo_hookean", 0.95),
    ],
)
def test_trajectory_gradient_matches_central_differences(material, model, flip):
    sim = scene(model=model, material=material, flip=flip)
    w = weights(sim, FRAMES)
    inputs = make_inputs(sim, torch.float64, material)
    loss_of(run(sim, FRAMES, inputs), w).backward()
    if material == "plasticine":  # the return mapping is active: tau_Y matters
        assert abs(float(inputs["yield_stress"].grad)) > 0
    gen = torch.Generator().manual_seed(2)
    for name, value in inputs.items():
        direction = torch.randn(value.shape, generator=gen, dtype=torch.float64)
        # relative steps for the parameters, 1e-3 cells for the positions, 1e-3 m/s for velocities
        steps = {"positions": 1e-3 / 16, "velocities": 1e-3}
        direction *= steps[name] if name in steps else 1e-4 * float(value.detach())
        predicted = float((value.grad * direction).sum())

        def loss_at(h):
            shifted = {k: v.detach() + (h * direction if k == name else 0) for k, v in inputs.items()}
            with torch.no_grad():
                return float(loss_of(run(sim, FRAMES, shifted), w))

        measured = (loss_at(1.0) - loss_at(-1.0)) / 2
        assert abs(measured - predicted) < 1e-5 * abs(measured), (name, measured, predicted)


def test_float32_gradient_within_a_few_percent():
    grads = {}
    for dtype in (torch.float64, torch.float32):
        sim = scene(dtype)
        inputs = make_inputs(sim, dtype)
        out = run(sim, FRAMES, inputs)
        w = [t.to(dtype) for t in weights(sim, FRAMES)]
        loss_of(out, w).backward()
        grads[dtype] = {k: v.grad.double() for k, v in inputs.items()}
    for name, g64 in grads[torch.float64].items():
        g32 = grads[torch.float32][name]
        assert float((g32 - g64).norm() / g64.norm()) < 0.03, name


def test_gradients_are_bit_identical_across_runs():
    """(On the deterministic P2G path; to ATOMIC_REPEAT_TOL on the atomic one.)"""
    runs = []
    for _ in range(2):
        sim = scene(torch.float32)
        inputs = make_inputs(sim, torch.float32)
        w = [t.float() for t in weights(sim, FRAMES)]
        loss_of(run(sim, FRAMES, inputs), w).backward()
        runs.append({k: v.grad for k, v in inputs.items()})
    for name in runs[0]:
        assert_repeats(runs[0][name], runs[1][name], sim, name)


def test_per_particle_parameters_sum_to_the_global_gradient():
    sim = scene()
    w = weights(sim, FRAMES)
    E_global = torch.tensor(E_TRUE, dtype=torch.float64, requires_grad=True)
    loss_of(simulate(sim, FRAMES, params={"youngs_modulus": E_global}), w).backward()
    E_rows = torch.full((sim.n,), E_TRUE, dtype=torch.float64, requires_grad=True)
    loss_of(simulate(sim, FRAMES, params={"youngs_modulus": E_rows}), w).backward()
    assert torch.allclose(E_rows.grad.sum(), E_global.grad, rtol=1e-12, atol=0)
    assert float(E_rows.grad.abs().min()) > 0  # every particle's stiffness matters


@pytest.mark.parametrize(
    "material,name,true,start,params",
    [
        ("elastic", "youngs_modulus", E_TRUE, 0.4, {"poissons_ratio": NU_TRUE}),
        ("plasticine", "yield_stress", 300.0, 0.5, {"youngs_modulus": E_TRUE}),
        ("foam", "viscosity", 50.0, 2.0, {"youngs_modulus": E_TRUE, "yield_stress": 300.0}),
        ("newtonian", "viscosity", 1.0, 2.0, {"bulk_modulus": 1e4}),
    ],
)
def test_identification_recovers_the_parameter(material, name, true, start, params):
    """Start from a wrong value; 25 Adam steps in the registry's log space on the mismatch of
    a simulated trajectory recover it within 5%. (A parameter the trajectory does not depend
    on cannot be identified: a yield stress above every stress reached has zero gradient.)"""
    x, v = swirling_block()
    sim = Simulator(
        x,
        (0.24 / 6) ** 3,
        MaterialSpec(material, params | {name: true}, density=RHO_TRUE),
        Grid((16, 16, 16), 1 / 16),
        velocities=v,
        frame_dt=1e-2,
        substeps=10,
        dtype=torch.float64,
    )
    frames = 2
    with torch.no_grad():
        target = simulate(sim, frames).x
    p = parameterization(material, name)
    z = p.encode(true * start).requires_grad_()
    # PAC-NeRF's log-space rate, decayed; less momentum than the default: no overshoot
    opt = torch.optim.Adam([z], lr=0.1, betas=(0.5, 0.9))
    schedule = torch.optim.lr_scheduler.ExponentialLR(opt, 0.9)
    for _ in range(25):
        opt.zero_grad()
        out = simulate(sim, frames, params={name: p.decode(z)})
        loss = ((out.x - target) ** 2).sum() / 1e-8  # (0.1 mm)^2: keeps Adam's eps negligible
        loss.backward()
        opt.step()
        schedule.step()
    assert abs(float(p.decode(z.detach())) / true - 1) < 0.05


def test_two_level_checkpointing_gives_identical_gradients():
    """A memory budget that only fits 3 of the 10 substeps of a frame: backward replays
    segments from intermediate states, with bit-identical results (on the deterministic P2G
    path; to ATOMIC_REPEAT_TOL on the atomic one)."""
    sim = scene()
    w = weights(sim, FRAMES)
    full = memory_estimate(sim.n, sim.grid.nodes, FRAMES, sim.substeps, sim.dtype)
    budget = memory_estimate(sim.n, sim.grid.nodes, FRAMES, sim.substeps, sim.dtype, segment=3)
    assert budget < full and replay_segment(sim.n, sim.grid.nodes, FRAMES, sim.substeps, sim.dtype, budget) == 3
    grads = []
    for memory_budget in (None, budget):
        inputs = make_inputs(sim, torch.float64)
        loss_of(run(sim, FRAMES, inputs, memory_budget=memory_budget), w).backward()
        grads.append({k: v.grad for k, v in inputs.items()})
    for name in grads[0]:
        assert_repeats(grads[0][name], grads[1][name], sim, name)
    with pytest.raises(InputError, match="memory_budget .* is too small"):
        simulate(sim, FRAMES, memory_budget=budget // 4)


def test_driver_force_gradient_matches_central_differences():
    """Two chained force stages (N) on half of the block: d loss / d force by the adjoint."""
    x = cube(6, 0.38, 0.62)
    half = x[:, 0] < 0.5
    forces = [Force(half, 0.0, 0.015, force=(0.5, 0.2, 0.0)), Force(half, 0.015, 1.0, force=(0.0, 0.0, -0.3))]
    sim = Simulator(
        x,
        (0.24 / 6) ** 3,
        MaterialSpec("elastic", {"youngs_modulus": E_TRUE}, density=RHO_TRUE),
        Grid((16, 16, 16), 1 / 16),
        frame_dt=1e-2,
        substeps=10,
        dtype=torch.float64,
        forces=forces,
    )
    w = weights(sim, FRAMES)
    mass = region_masses(sim)
    assert torch.allclose(mass, sim.particles.mass[half].sum().expand(2), rtol=1e-12)
    force = torch.tensor([[0.5, 0.2, 0.0], [0.0, 0.0, -0.3]], dtype=torch.float64, requires_grad=True)
    loss_of(simulate(sim, FRAMES, stage_accelerations=force / mass[:, None]), w).backward()
    direction = torch.randn(2, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 1e-3

    def loss_at(h):
        with torch.no_grad():
            return float(loss_of(simulate(sim, FRAMES, stage_accelerations=(force + h * direction) / mass[:, None]), w))

    measured = (loss_at(1.0) - loss_at(-1.0)) / 2
    predicted = float((force.grad * direction).sum())
    assert abs(measured - predicted) < 1e-5 * abs(measured)
    assert float(force.grad[1].abs().sum()) > 0  # the second stage (t >= 0.015 s) is reached


@pytest.mark.parametrize("material", sorted(MATERIAL_CASES))
def test_every_material_parameter_matches_central_differences(material):
    """d loss / d p for every registry parameter p of each material (global), on the swirling
    block with the parameters of tests/mpm/_helpers.py (which make the return mappings active)."""
    x, v = swirling_block()
    sim = Simulator(
        x,
        (0.24 / 6) ** 3,
        MaterialSpec(material, MATERIAL_CASES[material], density=RHO_TRUE),
        Grid((16, 16, 16), 1 / 16),
        velocities=v,
        frame_dt=1e-2,
        substeps=10,
        dtype=torch.float64,
    )
    kernel_material = {int(m) for m in sim.particles.material}.pop()
    names = KERNEL_PARAMETERS[next(k for k, i in MATERIAL_IDS.items() if i == kernel_material)]
    current = get_material(material).defaults() | MATERIAL_CASES[material]
    inputs = {name: torch.tensor(float(current[name]), dtype=torch.float64, requires_grad=True) for name in names}
    w = weights(sim, FRAMES)
    loss = loss_of(simulate(sim, FRAMES, params=inputs), w)
    loss.backward()
    for name, value in inputs.items():

        def loss_at(h):
            shifted = {k: v.detach() + (h if k == name else 0.0) for k, v in inputs.items()}
            with torch.no_grad():
                return float(loss_of(simulate(sim, FRAMES, params=shifted), w))

        # a quotient's step is small where the return mappings have kinks (1e-5 of the value)
        # but must move the loss past its rounding (the swirling block's viscosity, 0.05 Pa s:
        # 1e-5 moves it 4e-10 of itself): the adjoint must match the quotient at either step
        misses = []
        for relative in (1e-5, 1e-4):
            step = relative * max(abs(float(value)), 1e-3)
            # rounding of the loss (a sum of ~5,000 terms) limits what a difference quotient resolves
            resolution = loss_rounding(sim) * float(abs(loss)) / step
            measured = (loss_at(step) - loss_at(-step)) / (2 * step)
            error = abs(measured - float(value.grad))
            misses.append((step, measured, error / (1e-5 * abs(measured) + resolution)))
        assert min(miss for _, _, miss in misses) < 1, (name, float(value.grad), misses)
