"""clflow.mpm.material_model: a material's SI parameters become kernel columns in one place,
for a simulator being built and for a differentiable run's parameters alike."""

import pytest
import torch

from clflow.errors import InputError
from clflow.mpm import Grid, MaterialSpec, Simulator
from clflow.mpm.autograd import simulate
from clflow.mpm.constants import PARAM_COUNT
from clflow.mpm.material_model import KERNEL_PARAMETERS, kernel_material, kernel_params
from tests.mpm._helpers import cube

CASES = [
    ("elastic", None, {"youngs_modulus": 3e5}),
    ("plasticine", None, {"poissons_ratio": 0.2, "yield_stress": 2e3}),
    ("sand", "volume_corrected", {"friction_angle": 30.0}),
    ("newtonian", None, {"viscosity": 2.0}),
    ("non_newtonian", None, {"shear_modulus": 2e3, "bulk_modulus": 5e4}),
]


@pytest.mark.parametrize("material, model, given", CASES)
def test_a_runs_parameters_are_what_a_simulator_built_with_them_runs(material, model, given):
    """simulate(base, params=given) runs what Simulator(MaterialSpec(given)) runs: the SI
    values replace the simulator's own and go through the same map to kernel columns."""
    x = cube(4, 0.4, 0.6)
    build = lambda params: Simulator(  # noqa: E731
        x, 1e-5, MaterialSpec(material, params, model=model), Grid((16,) * 3, 1 / 16),
        velocities=torch.tensor([0.3, -0.5, 0.2]).expand(64, 3), frame_dt=4e-3, substeps=8, dtype=torch.float64,
    )  # fmt: skip
    built = build(given)
    run = simulate(build({}), 2, params={k: torch.tensor(v, dtype=torch.float64) for k, v in given.items()})
    assert torch.allclose(run.x, simulate(built, 2).x, rtol=0, atol=1e-13)
    assert torch.allclose(run.F, simulate(built, 2).F, rtol=0, atol=1e-12)


def test_the_si_values_a_simulator_keeps_are_the_registrys_in_kernel_order():
    kernel = kernel_params("sand", {"friction_angle": 30.0}, "volume_corrected")
    assert kernel.name == "sand_volume_corrected" and len(kernel.si_values) == PARAM_COUNT
    assert dict(zip(KERNEL_PARAMETERS[kernel.name], kernel.si_values))["friction_angle"] == 30.0
    sim = Simulator(cube(2, 0.4, 0.6), 1e-5, MaterialSpec("plasticine", {"yield_stress": 2e3}), Grid((16,) * 3, 1 / 16))
    names = KERNEL_PARAMETERS["plasticine"]
    assert sim.spec.material_values[0, names.index("yield_stress")] == 2e3


@pytest.mark.parametrize(
    "material, model, expected",
    [("elastic", None, "elastic"), ("elastic", "neo_hookean", "neo_hookean"), ("sand", None, "sand"),
     ("foam", "neo_hookean", "has no model option"), ("sand", "mohr", "sand model 'mohr' unknown")],
)  # fmt: skip
def test_kernel_material_resolves_models_and_refuses_what_has_none(material, model, expected):
    if expected.isidentifier():
        assert kernel_material(material, model) == expected
    else:
        with pytest.raises(InputError, match=expected):
            kernel_material(material, model)
