"""Every MPM kernel under oclgrind: no out-of-bounds access, no data race (tiny scenes, and a
population of three on the private and the gather paths)."""

import textwrap

import pytest

from tests.mpm._helpers import assert_clean_under_oclgrind

pytestmark = [pytest.mark.oclgrind, pytest.mark.slow]

SCRIPT = textwrap.dedent(
    """
    import warnings
    import torch
    from clflow.mpm import Box, Force, Grid, HalfSpace, MaterialSpec, RotatingCylinder, Simulator
    warnings.simplefilter("ignore")
    gen = torch.Generator().manual_seed(0)
    x = 0.3 + 0.4 * torch.rand(20, 3, generator=gen, dtype=torch.float64)
    x[0] = torch.tensor([0.855, 0.5, 0.5], dtype=torch.float64)  # leaves the grid: clamped
    v = torch.randn(20, 3, generator=gen, dtype=torch.float64)
    v[0] = torch.tensor([30.0, 0.0, 0.0])
    names = ["elastic", "plasticine", "metal", "foam", "sand", "newtonian", "non_newtonian", "snow"]
    specs = [MaterialSpec(m) for m in names] + [MaterialSpec("sand", model="volume_corrected")]
    scenes = [(specs, torch.arange(20) % len(specs)), ([MaterialSpec("elastic")], None)]
    for specs, index in scenes:
        sim = Simulator(x, 1e-5, specs, Grid((8, 8, 8), 1 / 7), material_index=index, velocities=v, walls=None,
                        frame_dt=2e-4, substeps=2, p2g="private",
                        forces=[Force(torch.ones(20, dtype=torch.bool), 0, 1, force=(1, 0, 0))],
                        boundaries=[HalfSpace((0, 0.2, 0), (0, 1, 0), "slip", 0.3), Box((0.4,) * 3, (0.5,) * 3),
                                    RotatingCylinder((0.5,) * 3, (0, 1, 0), 0.2, 0.1, 2.0)])
        assert sim.run(1).clamped[1] == 1
    population = MaterialSpec("elastic", {"youngs_modulus": [1e4, 2e4, 3e4]})  # each member on its own grid
    for path in ("private", "gather"):
        sim = Simulator(x, 1e-5, population, Grid((8, 8, 8), 1 / 7), velocities=v, walls=None, frame_dt=2e-4,
                        substeps=2, p2g=path)
        assert sim.run(1).clamped[1] == 3
    print("done on", sim.device.info.label)
    """
)


def test_kernels_are_clean_under_oclgrind(oclgrind):
    assert_clean_under_oclgrind(oclgrind, SCRIPT)
