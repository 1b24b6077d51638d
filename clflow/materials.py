"""The material registry: every material type, its parameters, SI units, ranges and defaults.

One source of truth shared by the simulator (clflow.mpm), the material query (clflow.query),
scene configs and the optimiser's parameterisations. Pure Python: importing it is cheap.

    >>> from clflow.materials import MATERIALS, validate_params
    >>> MATERIALS["elastic"].param("youngs_modulus").unit
    'Pa'
    >>> validate_params("elastic", {"youngs_modulus": 1e6})   # fills defaults, checks ranges
    {'youngs_modulus': 1000000.0, 'poissons_ratio': 0.3}
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal

from clflow.errors import InputError

Scale = Literal["log", "linear", "bounded"]


@dataclass(frozen=True)
class Param:
    """One material parameter.

    ``valid`` is the open/closed interval the model accepts at all (outside it the physics
    is undefined: e.g. nu >= 0.5); ``typical`` is the plausible range for real materials,
    used to clamp foundation-model answers and to size the optimiser's steps of bounded
    parameters (never to reject a valid start). ``scale`` says how an optimiser should
    parameterise it (log10 for moduli and viscosities; clflow.mpm.parameterization).
    """

    name: str  # spelled-out API name, e.g. "youngs_modulus"
    symbol: str  # the paper's / kernel's symbol, e.g. "E"
    unit: str  # SI unit ("Pa", "Pa*s", "deg" for angles, "1" for dimensionless)
    default: float
    valid: tuple[float, float]  # (low, high): low < value < high unless *_inclusive
    typical: tuple[float, float]
    scale: Scale = "log"
    low_inclusive: bool = False
    high_inclusive: bool = False
    doc: str = ""

    def check(self, value: float, where: str = "") -> float:
        """``value`` as float, or :class:`InputError` naming the parameter and the range."""
        prefix = f"{where}: " if where else ""
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise InputError(f"{prefix}{self.name} must be a number, got {value!r}") from None
        lo, hi = self.valid
        if math.isnan(value) or math.isinf(value):
            raise InputError(f"{prefix}{self.name} is {value}; it must be finite")
        below = value < lo or (value == lo and not self.low_inclusive)
        above = value > hi or (value == hi and not self.high_inclusive)
        if below or above:
            lb = "[" if self.low_inclusive else "("
            rb = "]" if self.high_inclusive else ")"
            unit = "" if self.unit == "1" else f" {self.unit}"
            raise InputError(
                f"{prefix}{self.name} ({self.symbol}) = {value:g}{unit} is outside the valid "
                f"range {lb}{lo:g}, {hi:g}{rb}"
            )
        return value


@dataclass(frozen=True)
class Material:
    """A material type: a constitutive model and its parameters (density is common to all)."""

    name: str
    model: str  # one-line description of the constitutive model
    params: tuple[Param, ...]
    default_density: float  # kg/m^3
    aliases: tuple[str, ...] = field(default=())

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name or p.symbol == name:
                return p
        raise InputError(
            f"material {self.name!r} has no parameter {name!r}; "
            f"its parameters: {', '.join(p.name for p in self.params)}"
        )

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    def defaults(self) -> dict[str, float]:
        return {p.name: p.default for p in self.params}


INF = math.inf

# the registry is a table, one parameter or material a row: kept as written
# fmt: off
_E = Param("youngs_modulus", "E", "Pa", 1e6, (0.0, INF), (1e3, 2e11), doc="Young's modulus")
_NU = Param(
    "poissons_ratio", "nu", "1", 0.3, (-1.0, 0.5), (0.0, 0.49), scale="bounded",
    doc="Poisson's ratio; 0.5 (incompressible) makes lambda infinite",
)
_TAU_Y = Param("yield_stress", "tau_Y", "Pa", 1e4, (0.0, INF), (1.0, 1e9), low_inclusive=True,
               doc="uniaxial yield stress; von Mises surface ||dev tau|| = sqrt(2/3) tau_Y")
_ETA = Param("viscosity", "eta", "Pa*s", 10.0, (0.0, INF), (1e-3, 1e6), low_inclusive=True,
             doc="plastic (Perzyna) viscosity of the viscoplastic flow rule")
_XI = Param("hardening", "xi", "1", 0.0, (0.0, INF), (0.0, 20.0), scale="linear", low_inclusive=True,
            doc="hardening coefficient")
_KAPPA = Param("bulk_modulus", "kappa", "Pa", 1e5, (0.0, INF), (1e3, 1e10), doc="bulk modulus")

MATERIALS: dict[str, Material] = {
    m.name: m
    for m in (
        Material(
            "elastic",
            "fixed corotated hyperelasticity (neo-Hookean optional)",
            (_E, _NU),
            1000.0,
            aliases=("jelly", "rubber"),
        ),
        Material(
            "plasticine",
            "von Mises perfect plasticity on Hencky strain",
            (_E, _NU, _TAU_Y),
            1500.0,
            aliases=("clay", "playdoh"),
        ),
        Material(
            "metal",
            "von Mises plasticity with linear isotropic hardening on Hencky strain",
            (_E, _NU, _TAU_Y, _XI),
            7800.0,
        ),
        Material(
            "foam",
            "viscoplastic (Perzyna-like) return mapping on Hencky strain",
            (_E, _NU, _ETA, _TAU_Y),
            100.0,
        ),
        Material(
            "sand",
            "Drucker-Prager plasticity (Klar 2016) on Hencky strain",
            (
                Param("friction_angle", "phi", "deg", 30.0, (0.0, 90.0), (15.0, 60.0), scale="bounded",
                      doc="internal friction angle"),
                Param("cohesion", "c", "1", 0.0, (0.0, INF), (0.0, 0.1), scale="linear", low_inclusive=True,
                      doc="cohesion as a log-strain offset of the cone tip"),
                Param("youngs_modulus", "E", "Pa", 3.5e5, (0.0, INF), (1e4, 1e8), doc="Young's modulus"),
                _NU,
            ),
            1600.0,
            aliases=("granular",),
        ),
        Material(
            "newtonian",
            "J-based fluid: Tait pressure (kappa / 7)(J^-7 - 1), kappa the bulk modulus, and viscous "
            "stress 2 mu J dev(sym C)",
            (
                Param("viscosity", "mu", "Pa*s", 1.0, (0.0, INF), (1e-4, 1e5), low_inclusive=True,
                      doc="dynamic viscosity (PAC-NeRF's 'mu' is twice this)"),
                replace(_KAPPA, doc="bulk modulus -J dp/dJ at rest, sound speed sqrt(kappa / rho) "
                                    "(PAC-NeRF's Tait kappa is 1/7 of it)"),
            ),
            1000.0,
            aliases=("newtonian_fluid", "fluid", "water"),
        ),
        Material(
            "non_newtonian",
            "viscoplastic (Bingham / Herschel-Bulkley) fluid on the full F, lambda = kappa - 2 mu / 3",
            (
                Param("shear_modulus", "mu", "Pa", 1e3, (0.0, INF), (1.0, 1e8), doc="shear modulus"),
                _KAPPA,
                _TAU_Y,
                _ETA,
            ),
            1200.0,
            aliases=("non_newtonian_fluid", "viscoplastic_fluid"),
        ),
        Material(
            "snow",
            "Stomakhin et al. 2013: fixed corotated with plastic hardening exp(xi (1 - J_P))",
            (
                Param("youngs_modulus", "E", "Pa", 1.4e5, (0.0, INF), (1e4, 1e7), doc="Young's modulus"),
                Param("poissons_ratio", "nu", "1", 0.2, (-1.0, 0.5), (0.0, 0.45), scale="bounded",
                      doc="Poisson's ratio"),
                Param("critical_compression", "theta_c", "1", 2.5e-2, (0.0, 1.0), (1e-3, 0.1), scale="linear",
                      doc="critical compression theta_c"),
                Param("critical_stretch", "theta_s", "1", 7.5e-3, (0.0, INF), (1e-3, 0.05), scale="linear",
                      doc="critical stretch theta_s"),
                Param("hardening", "xi", "1", 10.0, (0.0, INF), (0.0, 20.0), scale="linear", low_inclusive=True,
                      doc="hardening coefficient xi"),
            ),
            400.0,
        ),
    )
}
# fmt: on

#: up to 1e6 kg/m^3, 44 times osmium's 22,590: beyond it no material, and float32 masses and
#: momenta overflow the kernels (a density of 1e40 used to fail later, blamed on the modulus);
#: from 1e-3 kg/m^3, a thousandth of air's: below it the wave speed sqrt(E / rho) overflows
#: them instead (a density of 1e-308 blew the first frame up)
DENSITY = Param(
    "density", "rho", "kg/m^3", 1000.0, (1e-3, 1e6), (10.0, 2.5e4), low_inclusive=True, high_inclusive=True,
    doc="mass density",
)  # fmt: skip


def get_material(name: str) -> Material:
    """The :class:`Material` of ``name`` (or an alias), else an error listing the types."""
    key = name.strip().lower().replace("-", "_").replace(" ", "_")
    if key in MATERIALS:
        return MATERIALS[key]
    for m in MATERIALS.values():
        if key in m.aliases:
            return m
    raise InputError(f"unknown material {name!r}; known materials: {', '.join(MATERIALS)}")


def validate_params(material: str, params: dict[str, float], where: str = "") -> dict[str, float]:
    """Check ``params`` of ``material`` (SI units): unknown names, NaN, out-of-range values are
    :class:`InputError`; missing parameters take their defaults. Returns name -> float."""
    mat = get_material(material)
    out = mat.defaults()
    for name, value in params.items():
        p = mat.param(name)
        out[p.name] = p.check(value, where or mat.name)
    return out


def lame_parameters(youngs_modulus: float, poissons_ratio: float) -> tuple[float, float]:
    """(mu, lambda) in Pa from E (Pa) and nu."""
    mu = youngs_modulus / (2.0 * (1.0 + poissons_ratio))
    lam = youngs_modulus * poissons_ratio / ((1.0 + poissons_ratio) * (1.0 - 2.0 * poissons_ratio))
    return mu, lam
