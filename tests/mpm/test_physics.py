"""Physics checks with analytic answers: free fall, momentum, rest, domain clamping."""

import pytest
import torch

from clflow.mpm import Grid, MaterialSpec, Simulator
from tests.mpm._helpers import cube, free_body

ELASTIC = MaterialSpec("elastic", {"youngs_modulus": 1e4, "poissons_ratio": 0.3})
GRID = Grid((16, 16, 16), 1 / 16)


def test_free_fall_follows_the_parabola():
    x0 = cube(6, 0.3, 0.6)
    v0 = torch.tensor([0.3, 0.5, -0.2], dtype=torch.float64)
    g = (0.0, -9.81, 0.0)
    sim = Simulator(
        x0,
        1e-5,
        ELASTIC,
        GRID,
        velocities=v0.expand_as(x0),
        gravity=g,
        walls=None,
        frame_dt=0.01,
        substeps=20,
        dtype=torch.float64,
    )
    traj = sim.run(2)
    k, dt = 2 * sim.substeps, sim.dt
    t = k * dt
    gv = torch.tensor(g, dtype=torch.float64)
    # symplectic Euler (v first, then x += dt v) is exact for the discrete schedule ...
    discrete = x0 + t * v0 + dt * dt * gv * k * (k + 1) / 2
    assert (traj.x[-1] - discrete).abs().max() < 1e-12
    # ... and first-order close to x0 + v0 t + g t^2 / 2
    analytic = x0 + t * v0 + 0.5 * gv * t * t
    assert (traj.x[-1] - analytic).abs().max() <= 9.81 * t * dt / 2 + 1e-12
    assert (traj.v[-1] - (v0 + t * gv)).abs().max() < 1e-12


def test_translating_body_conserves_momentum():
    gen = torch.Generator().manual_seed(5)
    x0 = cube(8, 0.3, 0.6)
    v0 = torch.tensor([0.4, -0.3, 0.2], dtype=torch.float64) + 0.3 * torch.randn(
        x0.shape, generator=gen, dtype=torch.float64
    )
    sim = free_body(x0, ELASTIC, GRID, velocities=v0, frame_dt=0.01)
    p0 = (sim.particles.mass[:, None] * v0).sum(0)
    traj = sim.run(3)
    p = (sim.particles.mass[:, None] * traj.v[-1]).sum(0)
    assert (p - p0).abs().max() < 1e-11 * float((sim.particles.mass[:, None] * v0).abs().sum())
    assert (traj.F[-1] - torch.eye(3, dtype=torch.float64)).abs().max() > 1e-3  # it did deform


def test_block_at_rest_stays_at_rest():
    x0 = cube(8, 0.3, 0.6)
    sim = Simulator(x0, 1e-5, ELASTIC, GRID, gravity=(0, 0, 0), frame_dt=0.01, substeps=10, dtype=torch.float64)
    traj = sim.run(2)
    assert traj.v.abs().max() < 1e-14
    assert (traj.x[-1] - x0).abs().max() < 1e-14


def test_particles_leaving_the_domain_are_clamped_and_counted():
    x0 = cube(4, 0.7, 0.85)
    sim = Simulator(
        x0,
        1e-5,
        ELASTIC,
        GRID,
        velocities=torch.tensor([[20.0, 0, 0]]).expand(64, 3),
        gravity=(0, 0, 0),
        walls=None,
        frame_dt=0.02,
        dtype=torch.float32,
    )
    with pytest.warns(RuntimeWarning, match=r"\d+ particles left the grid and were clamped"):
        traj = sim.run(1)
    assert traj.clamped[1] > 0
    hi = GRID.upper[0] - GRID.dx
    assert float(traj.x[-1][:, 0].max()) <= hi + 1e-6
    assert bool(torch.isfinite(traj.x).all())


def squeezed_torus_energy(flip: float, substep_factor: int, frames: int = 9) -> float:
    """Total energy (kinetic + neo-Hookean elastic) after ``frames`` frames at 24 fps over the
    energy at the start, of a free 1 m torus (E = 1 MPa, nu = 0.3, no gravity, no walls)
    started with a squeezing velocity field, on a 24-node grid at ``substep_factor`` times its
    stable substeps (docs/mpm.md, "Transfers and time step")."""
    from clflow.mpm.shapes import lattice_fill

    E, nu, rho, res = 1e6, 0.3, 1000.0, 24
    dx = 3.0 / (res - 1)
    x = lattice_fill("torus", 1.0, (1.5, 1.5, 1.5), dx / 2)
    v = (1.5 - x) * torch.tensor([1.0, -1.0, 1.0], dtype=torch.float64)  # squeeze x, z; stretch y
    V0, mu, lam = (dx / 2) ** 3, E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))

    def energy(s) -> float:
        J = torch.linalg.det(s.F)
        psi = mu / 2 * ((s.F * s.F).sum((1, 2)) - 3) - mu * torch.log(J) + lam / 2 * torch.log(J) ** 2
        return float(0.5 * rho * V0 * (s.v * s.v).sum() + V0 * psi.sum())

    sim = Simulator(
        x,
        V0,
        MaterialSpec("elastic", {"youngs_modulus": E, "poissons_ratio": nu}, rho, "neo_hookean"),
        Grid((res,) * 3, dx),
        velocities=v,
        gravity=(0, 0, 0),
        walls=None,
        dtype=torch.float64,
        flip=flip,
    )
    sim.use_substeps(sim.substeps * substep_factor)
    start = energy(sim.state)
    sim.run(frames)
    return energy(sim.state) / start


def test_apic_damping_grows_with_the_substeps_and_flip_takes_most_of_it_out():
    """APIC filters every particle velocity through the grid at every substep, so 8x the
    substeps keeps far less energy; with flip = 0.99 the loss depends much less on dt
    (measured: APIC 0.159 -> 0.000, flip 0.99 0.457 -> 0.357 after 9 frames)."""
    apic = squeezed_torus_energy(0.0, 1), squeezed_torus_energy(0.0, 8)
    blend = squeezed_torus_energy(0.99, 1), squeezed_torus_energy(0.99, 8)
    assert apic[1] < 0.1 * apic[0]
    assert blend[1] > 0.6 * blend[0] and blend[0] > 2 * apic[0]
