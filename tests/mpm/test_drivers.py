"""Boundary conditions and drivers: colliders, velocity regions, forces, release, rotation."""

import pytest
import torch

from clflow.mpm import (
    Box,
    Force,
    Grid,
    HalfSpace,
    MaterialSpec,
    Region,
    RotatingCylinder,
    Simulator,
    layer_release_times,
    reference,
)
from tests.mpm._helpers import assert_repeats, cube, free_body

GRID = Grid((32, 32, 32), 1 / 32)
SOFT = MaterialSpec("elastic", {"youngs_modulus": 2e4, "poissons_ratio": 0.3})
FLOOR_Y = 0.2


def sliding_block(mode: str, friction: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean x-velocity of a block sliding at 1 m/s over a floor collider, and of its bottom
    layer, at frames 0..4 (0.05 s apart)."""
    x = cube(8, 0.0, 0.25) + torch.tensor([0.3, FLOOR_Y + 0.001, 0.3], dtype=torch.float64)
    sim = Simulator(
        x,
        (0.25 / 8) ** 3,
        SOFT,
        GRID,
        velocities=torch.tensor([[1.0, 0, 0]]).expand(x.shape[0], 3),
        boundaries=[HalfSpace((0, FLOOR_Y, 0), (0, 1, 0), mode, friction)],
        frame_dt=0.05,
    )
    traj = sim.run(4)
    bottom = x[:, 1] < FLOOR_Y + 0.04
    return traj.v[:, :, 0].mean(1).double(), traj.v[:, bottom, 0].mean(1).double()


def test_slip_collider_lets_a_block_slide():
    for vx in sliding_block("slip", 0.0):
        assert (vx - 1.0).abs().max() < 0.02


def test_sticky_collider_holds_the_block():
    _, bottom = sliding_block("sticky", 0.0)
    assert bottom[-1].abs() < 0.2  # the bottom stops (the top may rock)


@pytest.mark.parametrize("mode", ["slip", "separate"])
def test_coulomb_friction_decelerates_at_mu_g(mode):
    mu_f = 0.3
    vx, _ = sliding_block(mode, mu_f)
    # v(t) = v0 - mu_f g t on average (the elastic block rocks a little about it)
    decel = (vx[0] - vx[4]) / 0.2
    assert decel == pytest.approx(mu_f * 9.81, rel=0.1)
    assert bool((vx[1:] < vx[:-1]).all()) and float(vx[-1]) > 0  # steadily slower, never reversed


@pytest.mark.parametrize("mode,away_floor_velocity", [("slip", (1.0, 0.0, 0.0)), ("separate", (1.0, 0.5, 0.0))])
def test_collider_friction_acts_only_while_moving_into_the_surface(mode, away_floor_velocity):
    """Two unstressed blocks (F = I, C = 0: a node's velocity is the blocks' before the
    collider) straddle a floor with mu_f = 0.5, one moving into it at (1, -0.5, 0) m/s and one
    away at (1, 0.5, 0) m/s. Floor nodes of the first lose the normal part and mu_f |v.n| =
    0.25 m/s of the tangential 1 m/s; those of the second keep all of the tangential part
    (slip removes the normal part, separate lets it go). The float64 kernel matches the
    reference substep."""
    dx, floor, mu_f = 1 / 16, 0.5 + 1 / 32, 0.5
    block = cube(4, 0.0, 2 * dx) + torch.tensor([0.0, floor - dx, 0.4], dtype=torch.float64)
    x = torch.cat(
        [
            block + torch.tensor([0.25, 0, 0], dtype=torch.float64),
            block + torch.tensor([0.625, 0, 0], dtype=torch.float64),
        ]
    )
    v = torch.tensor([[1.0, -0.5, 0.0]] * 64 + [[1.0, 0.5, 0.0]] * 64, dtype=torch.float64)
    sim = Simulator(
        x,
        (dx / 2) ** 3,
        SOFT,
        Grid((16, 16, 16), dx),
        velocities=v,
        gravity=(0, 0, 0),
        walls=None,
        boundaries=[HalfSpace((0, floor, 0), (0, 1, 0), mode, mu_f)],
        frame_dt=1e-3,
        substeps=1,
        dtype=torch.float64,
    )
    before = sim.state.clone()
    sim.step()
    idx = torch.arange(sim.grid.nodes)
    node_x, node_y = dx * (idx // 256).double(), dx * (idx // 16 % 16).double()
    grid_mv, grid_v = sim.kernels.scratch.grid_mv.read(), sim.kernels.scratch.grid_v.read()
    on_floor = (grid_mv[:, 0] > 0) & (node_y < floor)
    into, away = on_floor & (node_x < 0.5), on_floor & (node_x > 0.5)
    assert int(into.sum()) > 0 and int(away.sum()) > 0
    expected_into = torch.tensor([1 - mu_f * 0.5, 0.0, 0.0], dtype=torch.float64)
    assert torch.allclose(grid_v[into], expected_into, rtol=0, atol=1e-12)
    expected_away = torch.tensor(away_floor_velocity, dtype=torch.float64)
    assert torch.allclose(grid_v[away], expected_away, rtol=0, atol=1e-12)
    ref, _ = reference.substep(
        before, sim.particles, sim.grid, 0.0, sim.dt, sim.gravity, sim.boundaries, sim.drivers.accel(0.0, sim.dtype)
    )
    for f in ("x", "v", "C", "F"):
        assert torch.allclose(getattr(sim.state, f), getattr(ref, f), rtol=0, atol=1e-12), f


def test_collider_time_window():
    """A sticky floor switched on at t = 0.1 s changes nothing before and stops the fall after."""
    x = cube(6, 0.0, 0.15) + torch.tensor([0.4, 0.5, 0.4], dtype=torch.float64)
    runs = []
    for boundaries in ([HalfSpace((0, 0.48, 0), (0, 1, 0), "sticky", start=0.1)], []):
        sim = Simulator(x, 1e-5, SOFT, GRID, boundaries=boundaries, walls=None, frame_dt=0.05)
        runs.append(sim.run(4))
    with_floor, free = runs
    assert_repeats(with_floor.x[2], free.x[2], sim)  # identical up to t = 0.1 s
    assert float(with_floor.x[2][:, 1].min()) < 0.48  # by then the block reached into the floor
    assert float(with_floor.x[-1][:, 1].mean()) > float(free.x[-1][:, 1].mean()) + 0.05


def test_moving_box_region_carries_particles():
    x = cube(6, 0.4, 0.55)
    box = Box((0.35, 0.35, 0.35), (0.6, 0.6, 0.6), velocity=(0.2, 0.0, 0.0), end=0.1)
    sim = Simulator(x, 1e-5, SOFT, GRID, boundaries=[box], gravity=(0, 0, 0), frame_dt=0.05)
    traj = sim.run(2)
    assert (traj.v[1][:, 0] - 0.2).abs().max() < 1e-5
    assert (traj.x[2][:, 0] - traj.x[0][:, 0] - 0.2 * 0.1).abs().max() < 1e-5


def test_rotating_cylinder_spins_particles():
    x = cube(8, 0.4, 0.6)
    omega = 3.0
    center = (0.5, 0.5, 0.5)
    drive = RotatingCylinder(center, axis=(0, 1, 0), radius=0.2, half_length=0.15, angular_velocity=omega)
    sim = Simulator(x, 1e-5, SOFT, GRID, boundaries=[drive], gravity=(0, 0, 0), walls=None, frame_dt=0.02)
    traj = sim.run(1)
    r = traj.x[1].double() - torch.tensor(center, dtype=torch.float64)
    expected = omega * torch.cross(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand_as(r), r, dim=-1)
    # v = omega x r exactly at the nodes; particles interpolate a linear field exactly,
    # up to one substep of rotation
    assert (traj.v[1].double() - expected).abs().max() < 2 * omega * omega * 0.15 * sim.dt + 1e-5


def test_force_stages_add_exact_impulses():
    """Chained stages: the total momentum gained is F1 T1 + F2 T2 (no gravity, no walls)."""
    x = cube(6, 0.4, 0.6)
    n = x.shape[0]
    upper = Region.box((0.0, 0.5, 0.0), (1.0, 1.0, 1.0))
    stages = [Force(upper, 0.0, 0.04, force=(0.5, 0.0, 0.0)), Force(upper, 0.04, 0.1, force=(0.0, 0.0, -0.25))]
    sim = free_body(x, SOFT, GRID, forces=stages)
    traj = sim.run(5)
    p = (sim.particles.mass[:, None] * traj.v[-1]).sum(0)
    assert p.tolist() == pytest.approx([0.5 * 0.04, 0.0, -0.25 * 0.06], abs=1e-12)
    assert int(upper.select(x).sum()) < n  # only part of the body was pushed


def test_acceleration_on_sphere_region_and_mask():
    x = cube(6, 0.4, 0.6)
    mask = torch.zeros(x.shape[0], dtype=torch.bool)
    mask[:10] = True
    stages = [
        Force(Region.sphere((0.5, 0.5, 0.5), 0.05), 0.0, 0.02, acceleration=(0, 3.0, 0)),
        Force(mask, 0.0, 0.02, acceleration=(1.0, 0, 0)),
    ]
    sim = free_body(x, SOFT, GRID, forces=stages)
    sphere_mass = float(sim.particles.mass[stages[0].mask(x)].sum())
    traj = sim.run(1)
    p = (sim.particles.mass[:, None] * traj.v[-1]).sum(0)
    assert p.tolist() == pytest.approx(
        [float(sim.particles.mass[:10].sum()) * 0.02, sphere_mass * 3.0 * 0.02, 0.0], abs=1e-12
    )


def test_layer_release_holds_layers_until_their_time():
    x = cube(6, 0.4, 0.6)
    release = layer_release_times(x, layers=3, interval=0.05)
    assert sorted(release.unique().tolist()) == pytest.approx([0.0, 0.05, 0.1])
    sim = Simulator(x, 1e-5, SOFT, GRID, release_times=release, walls=None, frame_dt=0.025)
    traj = sim.run(2)
    held = release > 0.05 - 1e-9
    assert torch.equal(traj.x[2][held], traj.x[0][held].float())  # still in place at t = 0.05 s
    assert float(traj.v[2][~held, 1].mean()) < -0.1  # the top layer falls


def test_layer_release_rejects_bad_arguments():
    from clflow.errors import InputError

    with pytest.raises(InputError, match="layers >= 1"):
        layer_release_times(cube(2, 0, 1), layers=0, interval=0.1)


def test_boundary_records_put_each_value_in_its_named_slot():
    """The kernels and the reference read records through BC_SLOTS; the records are written
    by position in record(): each value must land in the slot of its name."""
    from clflow.mpm.constants import BC_BOX, BC_CYLINDER, BC_HALFSPACE, BC_SLOTS, COLLIDER_MODES

    def slot(record, name, width=1):
        return record[BC_SLOTS[name] : BC_SLOTS[name] + width]

    half = HalfSpace((1.0, 2.0, 3.0), (0.0, 0.0, 1.0), "separate", 0.25, 0.5, 1.5).record()
    assert slot(half, "BC_KIND") == [BC_HALFSPACE] and slot(half, "BC_T_START") + slot(half, "BC_T_END") == [0.5, 1.5]
    assert slot(half, "BC_A", 3) == [1.0, 2.0, 3.0] and slot(half, "BC_B", 3) == [0.0, 0.0, 1.0]
    assert slot(half, "BC_MODE") == [COLLIDER_MODES["separate"]] and slot(half, "BC_FRICTION") == [0.25]
    box = Box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (4.0, 5.0, 6.0)).record()
    assert slot(box, "BC_KIND") == [BC_BOX] and slot(box, "BC_B", 3) == [1.0, 1.0, 1.0]
    assert slot(box, "BC_C", 3) == [4.0, 5.0, 6.0]
    cylinder = RotatingCylinder((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 0.3, 0.7, 9.0).record()
    assert slot(cylinder, "BC_KIND") == [BC_CYLINDER] and slot(cylinder, "BC_RADIUS") == [0.3]
    assert slot(cylinder, "BC_HALF_LENGTH") == [0.7] and slot(cylinder, "BC_OMEGA") == [9.0]
