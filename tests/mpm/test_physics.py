"""Physics checks with analytic answers: free fall, momentum, rest, domain clamping."""

import pytest
import torch

from clflow.mpm import Grid, MaterialSpec, Simulator
from tests.mpm._helpers import cube

ELASTIC = MaterialSpec("elastic", {"youngs_modulus": 1e4, "poissons_ratio": 0.3})
GRID = Grid((16, 16, 16), 1 / 16)


def test_free_fall_follows_the_parabola():
    x0 = cube(6, 0.3, 0.6)
    v0 = torch.tensor([0.3, 0.5, -0.2], dtype=torch.float64)
    g = (0.0, -9.81, 0.0)
    sim = Simulator(x0, 1e-5, ELASTIC, GRID, velocities=v0.expand_as(x0), gravity=g, walls=None,
                    frame_dt=0.01, substeps=20, dtype=torch.float64)
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
    v0 = torch.tensor([0.4, -0.3, 0.2], dtype=torch.float64) + 0.3 * torch.randn(x0.shape, generator=gen,
                                                                                 dtype=torch.float64)
    sim = Simulator(x0, 1e-5, ELASTIC, GRID, velocities=v0, gravity=(0, 0, 0), walls=None,
                    frame_dt=0.01, substeps=20, dtype=torch.float64)
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
    sim = Simulator(x0, 1e-5, ELASTIC, GRID, velocities=torch.tensor([[20.0, 0, 0]]).expand(64, 3),
                    gravity=(0, 0, 0), walls=None, frame_dt=0.02, dtype=torch.float32)
    with pytest.warns(RuntimeWarning, match=r"\d+ particles left the grid and were clamped"):
        traj = sim.run(1)
    assert traj.clamped[1] > 0
    hi = GRID.upper[0] - GRID.dx
    assert float(traj.x[-1][:, 0].max()) <= hi + 1e-6
    assert bool(torch.isfinite(traj.x).all())
