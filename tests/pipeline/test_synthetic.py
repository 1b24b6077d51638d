"""datasets_tools: synthetic cases of every shape, a drop, and the scene they write."""

import math

import numpy as np
import pytest
import torch

from clflow.pipeline.forward import prepare, simulate_config
from clflow.scene.config import load_config
from clflow_datasets.synthetic import Resolution, SyntheticCase, make_case, sphere_surface, torus_surface

TINY = Resolution(object_detail=7, floor_side=8, image=48, grid=16, frames=4, iterations=2)


def test_surface_gaussians_lie_flat_on_the_shape():
    rng = np.random.default_rng(0)
    means, scales, rotations, _ = sphere_surface(0.2, (0, 0.1, 0), 10, rng)
    radial = (means - [0, 0.1, 0]) / 0.1
    np.testing.assert_allclose(np.linalg.norm(means - [0, 0.1, 0], axis=1), 0.1, rtol=1e-12)
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", rotations[:, :, 2], radial)), 1.0, rtol=1e-12)
    assert np.all(scales[:, 2] < 0.2 * scales[:, 0])  # thin along the normal
    np.testing.assert_allclose(
        np.einsum("nij,nik->njk", rotations, rotations), np.broadcast_to(np.eye(3), rotations.shape), atol=1e-12
    )
    means, _, rotations, _ = torus_surface(0.2, (0, 0.05, 0), 10, rng)
    ring = means.copy()
    ring[:, 1] -= 0.05
    horizontal = np.linalg.norm(ring[:, [0, 2]], axis=1)
    tube = np.hypot(horizontal - 0.05, ring[:, 1])  # R = 0.05, a = 0.05
    np.testing.assert_allclose(tube, 0.05, rtol=1e-12)
    assert np.all(np.linalg.det(rotations) > 0.999)


@pytest.mark.parametrize(
    "shape, volume", [("sphere", math.pi * 0.2**3 / 6), ("torus", 2 * math.pi**2 * 0.05 * 0.05**2)]
)
def test_shapes_are_filled_with_their_volume(tmp_path, shape, volume):
    config = make_case(tmp_path, SyntheticCase(shape=shape, forces=()), TINY)
    cfg = load_config(config)
    particles = prepare(cfg).setup.particles
    assert particles.n_fill > 0
    assert float(particles.volume.sum()) == pytest.approx(volume, rel=0.2)
    assert len(list((tmp_path / "guidance").glob("*.png"))) == TINY.frames + 1


def test_a_dropped_sphere_falls_freely_until_it_lands(tmp_path):
    case = SyntheticCase(
        shape="sphere", lift=0.1, spread=0.5, forces=(), truth={"youngs_modulus": 1e5, "poissons_ratio": 0.3}
    )
    config = make_case(tmp_path, case, TINY)
    result = simulate_config(load_config(tmp_path / "config_truth.yaml"))
    drop = (result.x[:, :, 1].mean(1) - result.x[0, :, 1].mean()).double()
    t = torch.arange(result.x.shape[0], dtype=torch.float64) / 24
    falling = t <= math.sqrt(2 * 0.1 / 9.81) - 1 / 24  # before the first contact
    torch.testing.assert_close(drop[falling], -0.5 * 9.81 * t[falling] ** 2, rtol=0.05, atol=2e-3)
    assert load_config(config).optimize.parameters == ("youngs_modulus",)


@pytest.mark.parametrize("lift", [0.0, 0.37])
def test_the_default_domain_puts_the_ground_a_fixed_fraction_of_a_cell_above_a_node_row(tmp_path, lift):
    """Where the ground plane cuts the cells changes the contact (clflow.pipeline.simulation):
    a default domain always puts it GROUND_OFFSET cells above a node row, above the walls."""
    from clflow.mpm.constants import WALL_CELLS
    from clflow.pipeline.simulation import GROUND_OFFSET

    config = make_case(tmp_path, SyntheticCase(shape="sphere", lift=lift, forces=()), TINY)
    grid = prepare(load_config(config)).setup.grid
    cells = (0.0 - grid.origin[1]) / grid.dx  # the ground is at y = 0
    assert cells % 1 == pytest.approx(GROUND_OFFSET) and cells > WALL_CELLS + 1


@pytest.mark.parametrize("nodes", [16, 23, 37])
def test_a_configured_domain_meets_the_ground_alike_at_every_resolution(tmp_path, nodes):
    """A configured domain keeps its size and moves down by less than one cell, so that the
    ground lies GROUND_OFFSET cells above a node row on any grid over it (a search grid
    coarser than the main phase's meets the ground as that one does)."""
    import dataclasses

    from clflow.pipeline.simulation import GROUND_OFFSET

    config = make_case(tmp_path, SyntheticCase(shape="sphere", lift=0.05, spread=0.75), TINY)
    cfg = load_config(config)
    cfg = dataclasses.replace(cfg, simulation=dataclasses.replace(cfg.simulation, grid_resolution=nodes))
    grid = prepare(cfg).setup.grid
    lower, upper = cfg.simulation.domain_lower, cfg.simulation.domain_upper
    cells = (0.0 - grid.origin[1]) / grid.dx
    assert cells % 1 == pytest.approx(GROUND_OFFSET)
    assert grid.dx == pytest.approx(max(u - lo for lo, u in zip(lower, upper)) / (nodes - 1))
    assert lower[1] - grid.dx < grid.origin[1] <= lower[1] + 1e-12  # moved down by under a cell
    assert grid.origin[0::2] == pytest.approx(lower[0::2])  # only vertically
    assert max(grid.resolution) == nodes
