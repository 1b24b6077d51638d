"""Bad input gives a clear ClflowError naming what is wrong; unstable dt warns or stops."""

import math
import warnings

import pytest
import torch

from clflow.errors import InputError
from clflow.mpm import Force, Grid, HalfSpace, MaterialSpec, SimulationError, Simulator, StabilityWarning
from tests.mpm.scenes import cube

GRID = Grid((16, 16, 16), 1 / 16)
X = cube(4, 0.4, 0.6)
ELASTIC = MaterialSpec("elastic", {"youngs_modulus": 1e4})


def make(materials=ELASTIC, x=X, **kwargs):
    return Simulator(x, 1e-5, materials, GRID, **kwargs)


@pytest.mark.parametrize(
    "spec,match",
    [
        (MaterialSpec("elastic", {"youngs_modulus": -1.0}), r"youngs_modulus \(E\) = -1 Pa is outside"),
        (MaterialSpec("elastic", {"youngs_modulus": math.nan}), "youngs_modulus is nan"),
        (MaterialSpec("elastic", {"poissons_ratio": 0.5}), r"poissons_ratio \(nu\) = 0.5 .* outside"),
        (MaterialSpec("plasticine", {"yield_stress": -5.0}), "yield_stress"),
        (MaterialSpec("sand", {"friction_angle": 95.0}), "friction_angle"),
        (MaterialSpec("newtonian", {"bulk_modulus": 0.0}), "bulk_modulus"),
        (MaterialSpec("honey"), "unknown material 'honey'; known materials: elastic"),
        (MaterialSpec("elastic", {"stiffness": 1.0}), "has no parameter 'stiffness'"),
        (MaterialSpec("elastic", density=-3.0), r"density \(rho\) = -3"),
        (MaterialSpec("elastic", model="mooney"), "elastic model 'mooney' unknown"),
        (MaterialSpec("plasticine", model="neo_hookean"), "has no model option"),
        (MaterialSpec("sand", model="neo_hookean"), "sand model 'neo_hookean' unknown"),
    ],
)
def test_bad_material_is_a_clear_error(spec, match):
    with pytest.raises(InputError, match=match):
        make(spec)


def test_bad_particles_are_clear_errors():
    with pytest.raises(InputError, match="particle set is empty"):
        make(x=torch.zeros(0, 3))
    with pytest.raises(InputError, match=r"expected shape \[N, 3\]"):
        make(x=torch.zeros(5, 2))
    bad = X.clone()
    bad[3, 1] = math.nan
    with pytest.raises(InputError, match="positions contains NaN"):
        make(x=bad)
    with pytest.raises(InputError, match="1 of 64 particles lie outside the grid"):
        make(x=torch.cat([X, torch.tensor([[2.0, 0.5, 0.5]], dtype=torch.float64)])[1:])
    with pytest.raises(InputError, match="volume"):
        Simulator(X, -1.0, ELASTIC, GRID)
    with pytest.raises(InputError, match=r"material_index values must lie in \[0, 2\)"):
        make([ELASTIC, ELASTIC], material_index=torch.full((64,), 2))
    with pytest.raises(InputError, match="pass material_index"):
        make([ELASTIC, ELASTIC])


def test_bad_boundaries_and_forces_are_clear_errors():
    with pytest.raises(InputError, match="collider mode 'glue' unknown"):
        make(boundaries=[HalfSpace((0, 0.2, 0), (0, 1, 0), "glue")])
    with pytest.raises(InputError, match="collider normal must not be the zero vector"):
        make(boundaries=[HalfSpace((0, 0.2, 0), (0, 0, 0))])
    with pytest.raises(InputError, match="walls 'bouncy' unknown"):
        make(walls="bouncy")
    with pytest.raises(InputError, match="exactly one of force"):
        make(forces=[Force(torch.ones(64, dtype=torch.bool), 0.0, 1.0)])
    with pytest.raises(InputError, match="contains no particle"):
        make(forces=[Force(torch.zeros(64, dtype=torch.bool), 0.0, 1.0, force=(1, 0, 0))])
    with pytest.raises(InputError, match="time window"):
        make(forces=[Force(torch.ones(64, dtype=torch.bool), 1.0, 0.5, force=(1, 0, 0))])


def test_too_large_dt_warns_and_offers_a_substep_count():
    stiff = MaterialSpec("elastic", {"youngs_modulus": 1e8})
    auto = make(stiff, frame_dt=0.01)
    c = math.sqrt((lambda E, nu: E * (1 - nu) / ((1 + nu) * (1 - 2 * nu)))(1e8, 0.3) / 1000.0)
    assert auto.dt <= 0.5 * GRID.dx / c
    assert auto.substeps == math.ceil(0.01 / (0.5 * GRID.dx / c))
    with pytest.warns(StabilityWarning, match=rf"elastic wave speed .* use substeps >= {auto.substeps} per frame"):
        make(stiff, frame_dt=0.01, substeps=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        make(stiff, frame_dt=0.01, substeps=auto.substeps)


def test_cfl_limit_counts_initial_speed():
    fast = make(velocities=torch.full((64, 3), 10.0), frame_dt=0.01)
    assert fast.dt <= 0.3 * GRID.dx / math.sqrt(300.0) * (1 + 1e-9)


def test_nan_during_a_run_stops_with_frame_and_cause():
    with pytest.warns(StabilityWarning):
        sim = make(MaterialSpec("elastic", {"youngs_modulus": 1e9}), frame_dt=0.01, substeps=1, walls=None,
                   gravity=(0, 0, 0), velocities=0.1 * torch.randn(64, 3, generator=torch.Generator().manual_seed(0)))
    with pytest.raises(SimulationError, match=r"NaN/inf during frame \d+ .* likely cause: dt = .* too large"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sim.run(50)
