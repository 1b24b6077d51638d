"""Optimisation helpers: parameterisations from the registry ranges, gradient clipping, the
NaN/CFL guard with retries."""

import logging
import math

import pytest
import torch

from clflow.errors import InputError
from clflow.mpm import Grid, MaterialSpec, Simulator, StabilityWarning
from clflow.mpm.autograd import simulate
from clflow.mpm.parameterization import clip_gradients, parameterization
from tests.mpm._helpers import cube


@pytest.mark.parametrize(
    "material,name,value",
    [
        ("elastic", "youngs_modulus", 3e5),
        ("elastic", "poissons_ratio", 0.3),
        ("sand", "friction_angle", 35.0),
        ("metal", "hardening", 2.0),
        ("newtonian", "viscosity", 0.5),
        ("plasticine", "density", 1500.0),
    ],
)
def test_parameterization_round_trip_and_gradient(material, name, value):
    p = parameterization(material, name)
    z = p.encode(value).requires_grad_()
    decoded = p.decode(z)
    assert math.isclose(float(decoded.detach()), value, rel_tol=1e-12)
    decoded.backward()
    h = 1e-6
    fd = (float(p.decode(z.detach() + h)) - float(p.decode(z.detach() - h))) / (2 * h)
    assert math.isclose(float(z.grad), fd, rel_tol=1e-6)


def test_bounded_parameters_stay_in_their_range():
    nu = parameterization("elastic", "nu")
    lo, hi = nu.bounds
    values = nu.decode(torch.tensor([-30.0, 0.0, 30.0], dtype=torch.float64))
    assert bool(((values > lo) & (values < hi)).all()) and lo == -1.0 and hi == 0.5


@pytest.mark.parametrize(
    "material,name,values",
    [
        ("sand", "friction_angle", [10.0, 1e-6, 0.5, 15.0, 37.5, 60.0, 89.5, 90 - 1e-6]),
        ("elastic", "poissons_ratio", [0.45, 0.1, -0.999, -0.5, 0.0, 0.3, 0.49, 0.4999]),
        ("snow", "poissons_ratio", [0.45, 0.1, -0.5, 0.49]),
    ],
)
def test_bounded_parameters_encode_their_whole_valid_range(material, name, values):
    """A start anywhere in the open valid range round-trips (PAC-NeRF's sand starts at
    phi = 10 deg, below the typical 15-60 deg), and z = 0 is the typical range's middle, where
    one unit of z moves the value by a quarter of the typical range."""
    p = parameterization(material, name)
    assert p.bounds == p.param.valid
    values = torch.tensor(values, dtype=torch.float64)
    assert torch.allclose(p.decode(p.encode(values)), values, rtol=1e-12, atol=1e-12)
    z0 = torch.zeros((), dtype=torch.float64, requires_grad=True)
    middle = p.decode(z0)
    middle.backward()
    lo, hi = p.param.typical
    assert math.isclose(float(middle), (lo + hi) / 2, rel_tol=1e-12)
    assert math.isclose(float(z0.grad), (hi - lo) / 4, rel_tol=1e-12)


@pytest.mark.parametrize("value", [0.0, 90.0, -5.0, 95.0, math.nan])
def test_friction_angle_outside_its_open_range_is_a_clear_error(value):
    with pytest.raises(
        InputError,
        match=rf"friction_angle \(phi\) = {value:g} deg is outside the open range "
        rf"\(0, 90\)",
    ):
        parameterization("sand", "friction_angle").encode(value)


def test_parameterization_rejects_values_outside_the_range():
    with pytest.raises(InputError, match="poissons_ratio"):
        parameterization("elastic", "poissons_ratio").encode(0.5)
    with pytest.raises(InputError, match="youngs_modulus"):
        parameterization("elastic", "youngs_modulus").encode(-1.0)
    with pytest.raises(InputError, match="no parameter 'viscosity'"):
        parameterization("elastic", "viscosity")


def test_clip_gradients_scales_and_zeroes_non_finite():
    a = torch.zeros(2, requires_grad=True)
    b = torch.zeros(1, requires_grad=True)
    a.grad, b.grad = torch.tensor([3.0, 0.0]), torch.tensor([4.0])
    assert clip_gradients([a, b], 1.0) == 5.0
    assert torch.allclose(a.grad, torch.tensor([0.6, 0.0])) and torch.allclose(b.grad, torch.tensor([0.8]))
    a.grad = torch.tensor([float("nan"), 1.0])
    assert math.isnan(clip_gradients([a, b], 1.0))
    assert float(a.grad.abs().sum()) == 0.0 and float(b.grad.abs().sum()) == 0.0
    with pytest.raises(InputError, match="max_norm"):
        clip_gradients([a], 0.0)


def stiff_scene(substeps):
    """A stiff block with a shear velocity: 1 substep per frame is far beyond the wave-speed limit."""
    x = cube(5, 0.4, 0.6)
    v = torch.zeros_like(x)
    v[:, 0] = torch.linspace(-1, 1, x.shape[0], dtype=torch.float64)
    with pytest.warns(StabilityWarning, match="exceeds the stable limit"):
        return Simulator(
            x,
            1e-5,
            MaterialSpec("elastic", {"youngs_modulus": 1e6}),
            Grid((16, 16, 16), 1 / 16),
            velocities=v,
            frame_dt=1e-2,
            substeps=substeps,
            dtype=torch.float64,
        )


def test_guard_retries_with_smaller_dt(caplog):
    sim = stiff_scene(1)
    with caplog.at_level(logging.INFO, logger="clflow.mpm"):
        out = simulate(sim, 3, retries=5)
    assert "retrying with 2 substeps" in caplog.text  # a routine retry: INFO, not a warning
    speed = out.v.norm(dim=-1).max()
    assert float(speed) * 1e-2 / 8 <= 0.3 / 16  # the accepted run keeps the CFL limit


def test_guard_reports_when_out_of_retries(caplog):
    """The last attempt keeps its (unstable) result and says so; it would raise on NaN."""
    sim = stiff_scene(1)
    with pytest.warns(StabilityWarning) as record, caplog.at_level(logging.INFO, logger="clflow.mpm"):
        simulate(sim, 3, retries=1)
    messages = [str(w.message) for w in record]
    assert "retrying with 2 substeps" in caplog.text
    assert any("breaks the CFL limit" in m and "(2 substeps per frame)" in m and "retrying" not in m for m in messages)


def test_bad_inputs_are_named():
    sim = Simulator(
        cube(3, 0.4, 0.6),
        1e-5,
        MaterialSpec("elastic"),
        Grid((16, 16, 16), 1 / 16),
        substeps=2,
        frame_dt=1e-3,
        dtype=torch.float64,
    )
    with pytest.raises(InputError, match="youngs_modulus: expected shape"):
        simulate(sim, 1, params={"youngs_modulus": torch.ones(5)})
    with pytest.raises(InputError, match="poissons_ratio .* outside the valid range"):
        simulate(sim, 1, params={"poissons_ratio": torch.tensor(0.5)})
    with pytest.raises(InputError, match="positions: expected shape"):
        simulate(sim, 1, positions=torch.zeros(2, 3))
    with pytest.raises(InputError, match="outside the grid's interior"):
        simulate(sim, 1, positions=sim.state.x + 0.5)
    with pytest.raises(InputError, match="density must be > 0"):
        simulate(sim, 1, density=torch.tensor(-1.0))
    with pytest.raises(InputError, match="yield_stress is not a parameter of the simulated material"):
        simulate(sim, 1, params={"yield_stress": torch.tensor(100.0)})


def test_clamped_particles_are_reported():
    x = cube(3, 0.4, 0.6)
    x[0, 0] = 0.87  # at the upper end of the grid's interior (0.875 m), moving out
    v = torch.zeros_like(x)
    v[0, 0] = 5.0
    sim = Simulator(
        x,
        1e-5,
        MaterialSpec("elastic"),
        Grid((16, 16, 16), 1 / 16),
        velocities=v,
        walls=None,
        frame_dt=2e-3,
        substeps=2,
        dtype=torch.float64,
    )
    positions = sim.state.x.clone().requires_grad_()
    with pytest.warns(RuntimeWarning, match="1 particles left the grid"):
        out = simulate(sim, 1, positions=positions)
    out.x[-1, 0, 0].backward()
    assert float(out.x[-1, 0, 0]) == 0.875 and float(positions.grad[0, 0]) == 0.0
