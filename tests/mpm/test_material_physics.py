"""Material behaviour with known answers: bar frequency, permanent set, sand repose, fluid."""

import math

import pytest
import torch

from clflow.mpm import Grid, HalfSpace, MaterialSpec, Simulator


def lattice(counts, lower, spacing) -> torch.Tensor:
    """Particles at the cell centres of a counts[0] x counts[1] x counts[2] lattice (m)."""
    axes = [lower[a] + spacing * (0.5 + torch.arange(counts[a], dtype=torch.float64)) for a in range(3)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def test_stretched_bar_oscillates_at_its_longitudinal_frequency():
    """Free-free bar, nu = 0 (bar wave speed c = sqrt(E/rho)): fundamental period 2L/c."""
    dx, E, rho = 1 / 64, 1e5, 1000.0
    h = dx / 2
    x = lattice((64, 6, 6), (8 * dx, 5 * dx, 5 * dx), h)
    L = 64 * h
    s = (x[:, 0] - 8 * dx) / L
    v = torch.zeros_like(x)
    v[:, 0] = 0.05 * torch.cos(math.pi * s)  # the first mode's shape
    sim = Simulator(
        x,
        h**3,
        MaterialSpec("elastic", {"youngs_modulus": E, "poissons_ratio": 0.0}, density=rho),
        Grid((48, 12, 12), dx),
        velocities=v,
        gravity=(0, 0, 0),
        walls=None,
        frame_dt=0.002,
    )
    rel = []
    for _ in range(90):
        sim.advance_frame()
        rel.append(float(sim.state.v[s > 0.9, 0].mean() - sim.state.v[s < 0.1, 0].mean()))
    t = [0.002 * (k + 1) for k in range(len(rel))]
    crossings = [
        t[k] + 0.002 * rel[k] / (rel[k] - rel[k + 1]) for k in range(len(rel) - 1) if (rel[k] > 0) != (rel[k + 1] > 0)
    ]
    period = 2 * (crossings[-1] - crossings[0]) / (len(crossings) - 1)
    assert len(crossings) >= 3
    assert period == pytest.approx(2 * L / math.sqrt(E / rho), rel=0.03)


def stretch_and_release(material: MaterialSpec) -> tuple[float, float]:
    """Stretch a block along x with an initial velocity field v_x = rate (x - centre), then let
    it move freely; returns (initial length, mean length over the last 0.1 s)."""
    dx = 1 / 32
    x = lattice((16, 8, 8), (0.25, 0.375, 0.375), dx / 2)
    v = torch.zeros_like(x)
    v[:, 0] = 2.0 * (x[:, 0] - 0.375)
    sim = Simulator(
        x, (dx / 2) ** 3, material, Grid((32, 32, 32), dx), velocities=v, gravity=(0, 0, 0), walls=None, frame_dt=0.01
    )
    traj = sim.run(30)
    length = traj.x[..., 0].amax(-1) - traj.x[..., 0].amin(-1)
    return float(length[0]), float(length[-10:].mean())


def test_plasticine_keeps_a_permanent_set_elastic_does_not():
    E = {"youngs_modulus": 1e4, "poissons_ratio": 0.3}
    l0, elastic = stretch_and_release(MaterialSpec("elastic", E))
    _, plastic = stretch_and_release(MaterialSpec("plasticine", {**E, "yield_stress": 50.0}))
    assert elastic == pytest.approx(l0, rel=0.02)  # springs back (oscillates about l0)
    assert plastic > 1.15 * l0  # stays stretched


def test_steep_sand_slope_relaxes_to_the_friction_angle():
    """A sand wedge (quasi-2-D slab) steeper than the friction angle slumps to about it."""
    phi, slope = 30.0, 40.0
    dx = 1 / 32
    h = dx / 2
    half = 0.4
    top = half * math.tan(math.radians(slope))
    x = lattice((int(2 * half / h), int(top / h) + 1, 8), (20 * dx - half, 3 * dx, 3 * dx), h)
    x = x[(x[:, 1] - 3 * dx) < top - (x[:, 0] - 20 * dx).abs() * math.tan(math.radians(slope))]
    sim = Simulator(
        x,
        h**3,
        MaterialSpec("sand", {"friction_angle": phi, "youngs_modulus": 5e4}),
        Grid((40, 20, 10), dx),
        walls="slip",
        boundaries=[HalfSpace((0, 3 * dx, 0), (0, 1, 0), "sticky")],
        frame_dt=0.1,
    )
    traj = sim.run(5)

    def surface_angle(p: torch.Tensor) -> float:
        r = (p[:, 0].double() - 20 * dx).abs()
        edges = torch.linspace(0, float(r.max()) + 1e-9, 17)
        bins = torch.bucketize(r, edges, right=True) - 1
        rs, ys = [], []
        for k in range(16):
            if int((bins == k).sum()) > 3:
                rs.append(float(r[bins == k].mean()))
                ys.append(float(p[bins == k, 1].max()) - 3 * dx)
        rs, ys = torch.tensor(rs), torch.tensor(ys)
        flank = (ys > 0.2 * ys.max()) & (ys < 0.8 * ys.max())
        A = torch.stack([rs[flank], torch.ones_like(rs[flank])], 1)
        return math.degrees(math.atan(abs(float(torch.linalg.lstsq(A, ys[flank, None]).solution[0, 0]))))

    assert surface_angle(traj.x[0]) == pytest.approx(slope, abs=2.0)
    assert surface_angle(traj.x[-1]) == pytest.approx(phi, abs=4.0)


def test_fluid_column_spreads():
    dx = 1 / 32
    x = lattice((8, 24, 8), (0.4, 3 * dx, 0.4), dx / 2)
    sim = Simulator(
        x,
        (dx / 2) ** 3,
        MaterialSpec("newtonian", {"viscosity": 1e-3, "bulk_modulus": 2e4}),
        Grid((32, 32, 32), dx),
        frame_dt=0.05,
    )
    traj = sim.run(6)
    width0 = float(traj.x[0][:, 0].amax() - traj.x[0][:, 0].amin())
    width = float(traj.x[-1][:, 0].amax() - traj.x[-1][:, 0].amin())
    assert width > 2.5 * width0
    assert float(traj.x[-1][:, 1].amax()) < 0.5 * float(traj.x[0][:, 1].amax())
    # nearly incompressible: the volume ratio J = det F stays near 1
    J = torch.linalg.det(traj.F[-1].double())
    assert float((J - 1).abs().mean()) < 0.05


def test_newtonian_bulk_modulus_is_kappa():
    """The Newtonian kernel's pressure p(J) = -tau_00 / J (C = 0) has -dp/dJ = kappa at J = 1:
    ``bulk_modulus`` is the bulk modulus, the sound speed is wave_speed() = sqrt(kappa/rho),
    and bulk_modulus = 7 kappa_PAC reproduces PAC-NeRF's p = kappa_PAC (J^-7 - 1)."""
    kappa, rho, h = 7e5, 1000.0, 1e-4
    J = torch.tensor([1 - h, 1 + h, 0.9, 1.1], dtype=torch.float64)
    x = torch.full((4, 3), 0.5, dtype=torch.float64)
    spec = MaterialSpec("newtonian", {"viscosity": 1.0, "bulk_modulus": kappa}, density=rho)
    sim = Simulator(x, 1e-6, spec, Grid((8, 8, 8), 1 / 8), dtype=torch.float64, walls=None, gravity=(0, 0, 0))
    sim.state.F.copy_(J.pow(1 / 3)[:, None, None] * torch.eye(3, dtype=torch.float64))
    sim.step()
    tau = sim.kernels.scratch.tau.read()
    assert torch.equal(tau, tau[:, 0, 0, None, None] * torch.eye(3, dtype=torch.float64))  # a pure pressure
    p = -tau[:, 0, 0] / J
    bulk_modulus = -float(p[1] - p[0]) / (2 * h)
    assert bulk_modulus == pytest.approx(kappa, rel=1e-6)
    assert sim.material_limits[0].wave_speed == pytest.approx(math.sqrt(bulk_modulus / rho), rel=1e-6)
    kappa_pac = kappa / 7
    assert p[2:].tolist() == pytest.approx((kappa_pac * (J[2:] ** -7 - 1)).tolist(), rel=1e-12)
