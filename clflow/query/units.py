"""Units a model may write instead of the registry's SI unit, and their factors to SI.

Only unit spellings of the same quantity are converted (MPa -> Pa, cP -> Pa*s, g/cm^3 ->
kg/m^3, rad -> deg); anything else is not a unit of that quantity and the value is unusable.
Prefixes are case-sensitive where case changes the meaning (mPa*s vs MPa); otherwise the
spelling may be in any case ("pa", "KG/M3").
"""

from __future__ import annotations

import math

# registry unit -> {spelling: factor to the registry unit}; spellings as _normalise writes them
_FACTORS: dict[str, dict[str, float]] = {
    "Pa": {
        "Pa": 1.0,
        "hPa": 1e2,
        "kPa": 1e3,
        "MPa": 1e6,
        "GPa": 1e9,
        "N/m2": 1.0,
        "N/mm2": 1e6,
        "bar": 1e5,
        "psi": 6894.757293168,
    },
    "Pa*s": {"Pa*s": 1.0, "mPa*s": 1e-3, "kPa*s": 1e3, "N*s/m2": 1.0, "cP": 1e-3, "P": 0.1, "cps": 1e-3},
    "kg/m3": {
        "kg/m3": 1.0,
        "g/cm3": 1e3,
        "g/cc": 1e3,
        "g/ml": 1e3,
        "g/mL": 1e3,
        "kg/l": 1e3,
        "kg/L": 1e3,
        "g/l": 1.0,
        "g/L": 1.0,
        "t/m3": 1e3,
    },
    "deg": {
        "deg": 1.0,
        "degree": 1.0,
        "degrees": 1.0,
        "°": 1.0,
        "rad": 180.0 / math.pi,
        "radian": 180.0 / math.pi,
        "radians": 180.0 / math.pi,
    },
    "1": {"1": 1.0, "": 1.0, "-": 1.0, "dimensionless": 1.0, "unitless": 1.0, "none": 1.0},
}


def _normalise(unit: str) -> str:
    u = unit.strip().replace("³", "3").replace("²", "2").replace("^", "").replace("**", "")
    for sep in ("·", "⋅", "×", " ", "."):
        u = u.replace(sep, "*")
    while "**" in u:
        u = u.replace("**", "*")
    return u.strip("*")


def si_factor(unit: str, si_unit: str) -> float | None:
    """Factor that turns a value written in ``unit`` into ``si_unit`` (a registry unit), or
    None if ``unit`` is not a spelling of that quantity's unit."""
    table = _FACTORS[_normalise(si_unit)]
    u = _normalise(unit)
    if u in table:
        return table[u]
    factors = {f for k, f in table.items() if k.lower() == u.lower()}
    return factors.pop() if len(factors) == 1 else None
