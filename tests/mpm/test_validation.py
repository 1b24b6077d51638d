"""Bad input gives a clear ClflowError naming what is wrong; unstable dt warns or stops."""

import math
import warnings

import pytest
import torch

from clflow.errors import InputError
from clflow.materials import get_material
from clflow.mpm import Force, Grid, HalfSpace, MaterialSpec, SimulationError, Simulator, StabilityWarning
from clflow.mpm.simulator import VISCOUS_NUMBER
from tests.mpm._helpers import cube

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


def test_a_speed_beyond_any_time_step_is_a_clear_error():
    # finite float64 speeds whose CFL limit underflows to 0 (ZeroDivisionError before)
    sim = make(dtype=torch.float64, frame_dt=0.01)
    with pytest.raises(
        SimulationError, match=r"no stable time step is left \(CFL with max speed .*\): the simulation blew up"
    ):
        sim.stable_substeps(torch.full((64, 3), 1e307, dtype=torch.float64))


def test_nan_during_a_run_stops_with_frame_and_cause():
    with pytest.warns(StabilityWarning):
        sim = make(
            MaterialSpec("elastic", {"youngs_modulus": 1e9}),
            frame_dt=0.01,
            substeps=1,
            walls=None,
            gravity=(0, 0, 0),
            velocities=0.1 * torch.randn(64, 3, generator=torch.Generator().manual_seed(0)),
        )
    with pytest.raises(SimulationError, match=r"NaN/inf during frame \d+ .* likely cause: dt = .* too large"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sim.run(50)


def resting_block(material: MaterialSpec, frame_dt: float, **kwargs) -> Simulator:
    """216 particles (2 per cell and axis) filling 3^3 cells on the bottom wall, float64."""
    x = cube(6, 3 * GRID.dx, 6 * GRID.dx)
    x[:, [0, 2]] += 0.25
    return Simulator(x, (GRID.dx / 2) ** 3, material, GRID, frame_dt=frame_dt, dtype=torch.float64, **kwargs)


def max_speed_after(sim: Simulator, frames: int) -> float:
    """max |v| (m/s) after ``frames`` frames; inf if the run turned NaN/inf."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", StabilityWarning)
            sim.run(frames)
    except SimulationError:
        return math.inf
    return float(sim.state.v.norm(dim=-1).max())


def test_viscous_fluid_takes_the_viscous_time_step_limit():
    """A very viscous fluid: at the substeps its CFL and wave limits alone give (the count
    clflow chose before it had a viscous limit) it blows up; the automatic count, set by
    dt <= VISCOUS_NUMBER rho dx^2 / mu, keeps it at rest on the ground."""
    frame_dt, rho, mu = 1 / 24, 1000.0, 1e3
    thick = MaterialSpec("newtonian", {"viscosity": mu, "bulk_modulus": 1e4}, density=rho)
    thin = MaterialSpec("newtonian", {"viscosity": 1e-3, "bulk_modulus": 1e4}, density=rho)
    wave_and_cfl_only = resting_block(thin, frame_dt).substeps  # its viscous limit is 781 s
    auto = resting_block(thick, frame_dt)
    assert auto.substeps == math.ceil(frame_dt / (VISCOUS_NUMBER * rho * GRID.dx**2 / mu))
    assert wave_and_cfl_only < auto.substeps
    with pytest.warns(
        StabilityWarning,
        match=rf"viscous diffusion of newtonian, viscosity 1e\+03 Pa s .* "
        rf"use substeps >= {auto.substeps} per frame",
    ):
        old = resting_block(thick, frame_dt, substeps=wave_and_cfl_only)
    assert max_speed_after(old, 4) > 100.0
    assert max_speed_after(auto, 4) < 0.5  # settling; free fall would reach g t = 1.6 m/s


@pytest.mark.parametrize(
    "material,params,eta",
    [
        ("foam", {"youngs_modulus": 1e5, "poissons_ratio": 0.3}, 1e4),
        ("foam", {"youngs_modulus": 1e5, "poissons_ratio": 0.3}, 1e6),
        ("non_newtonian", {"shear_modulus": 1e4, "bulk_modulus": 1e5}, 1e4),
        ("non_newtonian", {"shear_modulus": 1e4, "bulk_modulus": 1e5}, 1e6),
    ],
)
def test_viscoplastic_viscosity_needs_no_viscous_limit(material, params, eta):
    """The viscoplastic return relaxes the overstress implicitly in eta, so eta adds no time
    step limit: with tau_Y = 0 (always yielding) and eta = 1e4 or 1e6 Pa s, the automatic
    substeps are those of eta = 0, with dt over 10 x what an explicit viscosity eta would
    allow, and the stirred block stays stable."""
    gen = torch.Generator().manual_seed(0)
    v = 0.5 * torch.randn(216, 3, generator=gen, dtype=torch.float64)
    spec = MaterialSpec(material, {**params, "yield_stress": 0.0, "viscosity": eta})
    sim = resting_block(spec, 0.02, velocities=v)
    inviscid = resting_block(
        MaterialSpec(material, {**params, "yield_stress": 0.0, "viscosity": 0.0}), 0.02, velocities=v
    )
    assert sim.substeps == inviscid.substeps
    rho = get_material(material).default_density
    assert sim.dt > 10 * VISCOUS_NUMBER * rho * GRID.dx**2 / eta
    assert max_speed_after(sim, 5) < float(v.norm(dim=-1).max())


@pytest.mark.parametrize(
    "lacks, dtype, p2g, differentiable, match",
    [
        ({"fp64": False}, torch.float64, "private", False, r"no double precision \(cl_khr_fp64\), which float64"),
        ({"fp64": False}, torch.float32, "private", True, "which the adjoint's float64 reductions need"),
        ({"int64_atomics": False}, torch.float64, "atomic", False, r"no 64-bit atomics .* float32, or .*=private"),
    ],
)
def test_a_device_without_a_needed_capability_is_refused_in_one_line(device, lacks, dtype, p2g, differentiable, match):
    """Before any kernel is built or run: the line names the device and what it lacks."""
    import dataclasses

    from clflow.errors import DeviceError
    from clflow.mpm.substep import check_device
    from clflow.runtime.devices import Device

    lacking = Device(dataclasses.replace(device.info, **lacks), device.cl_device)
    with pytest.raises(DeviceError, match=match) as err:
        check_device(lacking, dtype, p2g, differentiable)
    assert "\n" not in str(err.value) and device.info.label in str(err.value)
    check_device(lacking, torch.float32, p2g)  # float32 forward needs neither
    if not differentiable:  # the simulator refuses it as well, before it builds a kernel
        with pytest.raises(DeviceError, match=match):
            Simulator(X, 1e-5, ELASTIC, GRID, dtype=dtype, p2g=p2g, device=lacking)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_state_health_is_the_states_finiteness_and_fastest_speed(device, dtype):
    """state_health (reduced on the device) against torch: the fastest particle's speed, and
    a NaN or inf anywhere in x, v or F, the last particle's included (n not a multiple of the
    kernel's grid), found."""
    from clflow.mpm.constants import HEALTH_GROUPS, HEALTH_WG
    from clflow.mpm.simulator import state_health
    from clflow.mpm.substep import State
    from clflow.runtime.arrays import DeviceArray

    n = 3 * HEALTH_GROUPS * HEALTH_WG + 5
    gen = torch.Generator().manual_seed(0)
    x, v = torch.rand(n, 3, generator=gen, dtype=dtype), torch.randn(n, 3, generator=gen, dtype=dtype)
    F = torch.eye(3, dtype=dtype).expand(n, 3, 3) + 0.1 * torch.randn(n, 3, 3, generator=gen, dtype=dtype)
    v[1234] = torch.tensor([30.0, -40.0, 0.0], dtype=dtype)  # 50 m/s, the fastest

    def health(x, v, F):
        arrays = [
            DeviceArray.of(device, t.contiguous()) for t in (x, v, F, torch.zeros_like(F), torch.zeros(n, dtype=dtype))
        ]
        return state_health(device, State(arrays[0], arrays[1], arrays[3], arrays[2], arrays[4]))

    clean = health(x, v, F)
    assert clean.finite and clean.max_speed == pytest.approx(float(v.double().norm(dim=-1).max()), rel=1e-6)
    assert clean.max_speed == pytest.approx(50.0, rel=1e-6)
    assert clean.cfl_breach(dt=1e-3, dx=0.01) == clean.max_speed and clean.cfl_breach(dt=1e-5, dx=0.01) is None
    for name, row, value in (("x", n - 1, math.nan), ("v", 0, math.inf), ("F", n - 1, -math.inf)):
        bad = {"x": x.clone(), "v": v.clone(), "F": F.clone()}
        bad[name][row].view(-1)[-1] = value
        assert not health(bad["x"], bad["v"], bad["F"]).finite, name
