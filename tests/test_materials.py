"""The material registry: names, units, ranges, defaults, validation messages."""

import math

import pytest

from clflow.errors import InputError
from clflow.materials import DENSITY, MATERIALS, get_material, lame_parameters, validate_params

PAPER_TYPES = {"elastic", "plasticine", "metal", "foam", "sand", "newtonian", "non_newtonian", "snow"}


def test_every_material_of_the_method_is_registered_with_consistent_params():
    assert set(MATERIALS) == PAPER_TYPES
    for mat in MATERIALS.values():
        assert len(set(mat.param_names)) == len(mat.params)
        for p in mat.params:
            lo, hi = p.valid
            assert lo <= p.typical[0] <= p.typical[1] <= hi, (mat.name, p.name)
            if p.scale == "bounded":  # its logistic map covers (lo, hi), steps set by the typical range
                assert math.isfinite(hi - lo) and p.typical[0] < p.typical[1], (mat.name, p.name)
            assert p.check(p.default) == p.default  # defaults are valid
            assert p.unit and p.doc
        assert DENSITY.check(mat.default_density)


@pytest.mark.parametrize(
    "material, params, message",
    [
        ("elastic", {"poissons_ratio": 0.5}, r"poissons_ratio \(nu\) = 0.5 is outside the valid range \(-1, 0.5\)"),
        ("elastic", {"youngs_modulus": -1.0}, r"youngs_modulus \(E\) = -1 Pa is outside"),
        ("elastic", {"youngs_modulus": math.nan}, "youngs_modulus is nan; it must be finite"),
        ("elastic", {"youngs_modulus": "stiff"}, "youngs_modulus must be a number"),
        ("elastic", {"yield_stress": 1.0}, "material 'elastic' has no parameter 'yield_stress'"),
        ("sand", {"friction_angle": 90.0}, r"friction_angle \(phi\) = 90 deg"),
        ("lava", {}, "unknown material 'lava'; known materials: elastic"),
    ],
)
def test_bad_parameters_get_specific_messages(material, params, message):
    with pytest.raises(InputError, match=message):
        validate_params(material, params)


def test_a_density_is_refused_where_the_kernels_would_overflow():
    """1e-308 kg/m^3 made the wave speed infinite in float32: the first frame blew up."""
    with pytest.raises(
        InputError, match=r"density \(rho\) = 1e-308 kg/m\^3 is outside the valid range \[0.001, 1e\+06\]"
    ):
        DENSITY.check(1e-308)
    assert DENSITY.check(1e-3) == 1e-3 and DENSITY.check(1e6) == 1e6


def test_defaults_fill_in_and_symbols_are_accepted():
    assert validate_params("plasticine", {"E": 2e6, "tau_Y": 1.54e4}) == {
        "youngs_modulus": 2e6,
        "poissons_ratio": 0.3,
        "yield_stress": 1.54e4,
    }


def test_aliases_and_spelling():
    assert get_material("Non-Newtonian").name == "non_newtonian"
    assert get_material("jelly").name == "elastic"


def test_lame_parameters():
    mu, lam = lame_parameters(1e6, 0.25)
    assert mu == pytest.approx(4e5) and lam == pytest.approx(4e5)
