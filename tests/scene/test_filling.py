"""Filling an object's Gaussian shell with particles."""

import math

import pytest
import torch

from clflow.errors import InputError
from clflow.scene.filling import fill_object


def sphere_shell(n=3000, radius=0.1, sigma=0.004, seed=0):
    """Gaussians on a sphere: means [n, 3], isotropic covariances, opacities."""
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=torch.Generator().manual_seed(seed)), dim=-1)
    return radius * d, sigma**2 * torch.eye(3).repeat(n, 1, 1), torch.full((n,), 0.9)


def test_a_sphere_shell_is_filled_with_the_sphere_volume():
    means, covs, opac = sphere_shell()
    obj = fill_object(means, covs, opac, spacing=0.01)
    assert torch.equal(obj.positions[: obj.n_gaussians], means)  # Gaussians first, unchanged
    fill = obj.positions[obj.n_gaussians :]
    assert obj.n_fill > 0 and fill.norm(dim=1).max() < 0.1 + 2 * 0.004 + 0.01 * math.sqrt(3) / 2
    assert fill.norm(dim=1).min() < 0.02  # the centre is filled
    total = obj.volume * obj.positions.shape[0]
    assert total == pytest.approx(4 / 3 * math.pi * 0.1**3, rel=0.1)


def test_a_shell_with_a_wide_hole_is_not_filled():
    means, covs, opac = sphere_shell()
    keep = means[:, 2] < 0.06  # cut the cap off: the outside reaches the centre
    obj = fill_object(means[keep], covs[keep], opac[keep], spacing=0.01)
    assert obj.n_fill < 0.05 * fill_object(means, covs, opac, spacing=0.01).n_fill


def test_degenerate_huge_gaussians_cost_bounded_work():
    means, covs, opac = sphere_shell(n=500)
    covs[0] = 1e12 * torch.eye(3)  # a runaway Gaussian from a bad trainer
    obj = fill_object(means, covs, opac, spacing=0.01)
    assert obj.positions.shape[0] < 50_000


def test_transparent_gaussians_do_not_close_the_shell():
    means, covs, opac = sphere_shell()
    obj = fill_object(means, covs, torch.full_like(opac, 0.01), spacing=0.01)
    assert obj.n_fill == 0


def test_bad_inputs():
    means, covs, opac = sphere_shell(n=10)
    with pytest.raises(InputError, match="selection is empty"):
        fill_object(means[:0], covs[:0], opac[:0], spacing=0.01)
    with pytest.raises(InputError, match="positive length"):
        fill_object(means, covs, opac, spacing=0.0)
    with pytest.raises(InputError, match="larger spacing"):
        fill_object(means * 1000, covs, opac, spacing=0.001)


def test_more_fill_particles_than_the_memory_holds_are_refused_before_they_are_made(monkeypatch):
    """per_axis 16 on a fine grid asked for billions of particles: the allocation failed (or
    the machine ran out of memory) instead of a refusal."""
    means, covs, opac = sphere_shell()
    monkeypatch.setattr("clflow.limits.physical_memory", lambda: 10**9)
    with pytest.raises(InputError, match=r"filling the object with [\d,]+ particles would hold about .* GB in memory"):
        fill_object(means, covs, opac, spacing=0.01, per_axis=16)


def test_a_cube_of_flat_face_gaussians_is_filled_inside_only():
    # Face Gaussians overhang the cube's edges by two standard deviations: the fill must
    # still stay inside the cube, and the volume must be the cube's.
    import numpy as np

    from clflow_datasets.synthetic import cube_surface

    means, scales, _, _ = cube_surface(0.2, (0.0, 0.1, 0.0), 8, np.random.default_rng(0))
    means, covs = torch.tensor(means), torch.diag_embed(torch.tensor(scales) ** 2)
    for spacing in (0.0167, 0.01):
        obj = fill_object(means, covs, torch.full((len(means),), 0.95, dtype=torch.float64), spacing, per_axis=1)
        fill = obj.positions[obj.n_gaussians :] - torch.tensor([0.0, 0.1, 0.0], dtype=torch.float64)
        assert obj.n_fill > 0 and float(fill.abs().max()) < 0.1
        assert obj.volume * obj.positions.shape[0] == pytest.approx(0.2**3, rel=0.1)


def test_voxels_finer_than_the_surface_sampling_do_not_leave_the_object_hollow():
    # 8 x 8 Gaussians per 0.2 m face are 25 mm apart: a 4 mm fill voxel grid sees gaps
    # between their marks, and the flood fill used to leak in and leave only the shell.
    import numpy as np

    from clflow.scene.filling import surface_gap
    from clflow_datasets.synthetic import cube_surface

    means, scales, _, _ = cube_surface(0.2, (0.0, 0.1, 0.0), 8, np.random.default_rng(0))
    means, covs = torch.tensor(means), torch.diag_embed(torch.tensor(scales) ** 2)
    assert surface_gap(means) == pytest.approx(0.025, rel=0.01)
    obj = fill_object(means, covs, torch.full((len(means),), 0.95, dtype=torch.float64), 0.004, per_axis=1)
    fill = obj.positions[obj.n_gaussians :]
    assert obj.volume * obj.positions.shape[0] == pytest.approx(0.2**3, rel=0.1)
    assert obj.n_fill == pytest.approx(0.2**3 / 0.004**3, rel=0.25)  # the requested particle spacing
    spacing = torch.cdist(fill[:500], fill).topk(2, largest=False).values[:, 1]
    assert float(spacing.median()) == pytest.approx(0.004, rel=0.05)
