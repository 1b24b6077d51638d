"""Errors per material class and parameter, as the field reports them, beside the peers'.

The newest peers (GIC, ProJo4D) report, per material class of PAC-NeRF's data, the mean
absolute error of log10 of each modulus, viscosity and yield stress, the absolute error of
Poisson's ratio and the friction angle's absolute error in degrees. ``per_class`` computes
the same from a ``clflow eval sysid`` summary; ``bounded_ranges`` the mean RE over the
parameters whose range is bounded on both sides (what the video determines) and the median
width of those ranges in decades.
"""

from __future__ import annotations

import math
import statistics

#: ProJo4D's project page (github.com/daniel03c1/ProJo4D, index.html, "Sparse-view results on
#: the PAC-NeRF Dataset"): class -> clflow parameter -> (GIC, ProJo4D), each the mean over the
#: class's scenes of |log10 found - log10 truth|, |found - truth| for Poisson's ratio, degrees
#: for the friction angle. PAC-NeRF's mu / kappa of a Newtonian fluid are clflow's viscosity /
#: bulk modulus (scaled by constants: log errors unchanged); a non-Newtonian fluid's mu, kappa,
#: tau_Y, eta its shear modulus, bulk modulus, yield stress and viscosity.
PEERS = ("GIC", "ProJo4D")
PEER_ERRORS: dict[str, dict[str, tuple[float, float]]] = {
    "elastic": {"youngs_modulus": (0.189, 0.087), "poissons_ratio": (0.123, 0.106)},
    "plasticine": {"youngs_modulus": (1.597, 0.892), "poissons_ratio": (0.134, 0.158), "yield_stress": (0.327, 0.132)},
    "newtonian": {"viscosity": (0.103, 0.071), "bulk_modulus": (3.180, 1.900)},
    "non_newtonian": {
        "shear_modulus": (0.869, 0.937),
        "bulk_modulus": (0.725, 0.722),
        "yield_stress": (0.069, 0.032),
        "viscosity": (0.519, 0.507),
    },
    "sand": {"friction_angle": (6.785, 0.903)},
}
PEER_SOURCE = (
    "GIC and ProJo4D: ProJo4D's project page (sparse views of PAC-NeRF's renders; GIC as ProJo4D ran it). "
    "Their data differ from these cases (PAC-NeRF's scenes and renders, a few of its views; here clflow's "
    "re-made shapes, one view, a 2x finer ground truth): a guide to the scale, not a same-data comparison."
)


def error_kind(material: str, name: str) -> str:
    """How a parameter's error is measured: "log10" (moduli, viscosities, yield stresses),
    "deg" (the friction angle) or "abs" (Poisson's ratio and other bounded values)."""
    from clflow.mpm.parameterization import parameterization

    if name == "friction_angle":
        return "deg"
    return "log10" if parameterization(material, name).param.scale == "log" else "abs"


def parameter_error(kind: str, found: float, truth: float) -> float:
    return abs(math.log10(found / truth)) if kind == "log10" else abs(found - truth)


def per_class(cases: dict) -> dict:
    """material -> parameter -> {"kind", "error" (the mean over the class's finished cases),
    "cases", and each peer's figure where published} over the finished cases of a summary."""
    table: dict[str, dict[str, dict]] = {}
    for record in cases.values():
        if record.get("status") != "ok":
            continue
        for name, p in record["parameters"].items():
            # a case of several objects: each parameter of its object's material, by its own name
            material, name = p.get("material", record["material"]), p.get("parameter", name)
            kind = error_kind(material, name)
            row = table.setdefault(material, {}).setdefault(name, {"kind": kind, "errors": []})
            row["errors"].append(parameter_error(kind, p["found"], p["truth"]))
    for material, params in table.items():
        for name, row in params.items():
            errors = row.pop("errors")
            row.update(error=statistics.fmean(errors), cases=len(errors))
            peers = PEER_ERRORS.get(material, {}).get(name)
            if peers:
                row.update(zip(PEERS, peers))
    return table


def bounded_ranges(cases: dict) -> dict:
    """Over the finished cases' parameters whose range is bounded on both sides: how many,
    their mean RE, and the median width of those ranges in decades (log10 high / low; ranges
    reaching zero or below left out of the width)."""
    bounded = [
        p
        for r in cases.values()
        if r.get("status") == "ok"
        for p in r["parameters"].values()
        if "range" in p and None not in p["range"]
    ]
    widths = [math.log10(p["range"][1] / p["range"][0]) for p in bounded if p["range"][0] > 0]
    return {
        "parameters": len(bounded),
        "mean_re": statistics.fmean(p["re"] for p in bounded) if bounded else None,
        "median_width_decades": statistics.median(widths) if widths else None,
    }


UNITS = {"log10": "log10", "deg": "deg", "abs": ""}


def markdown(cases: dict) -> list[str]:
    """The per-class table's lines (empty when no case finished)."""
    table = per_class(cases)
    if not table:
        return []
    lines = [
        "",
        "Per material class, as GIC and ProJo4D report it: the mean absolute error of log10 of each modulus, "
        "viscosity and yield stress, of Poisson's ratio itself, and of the friction angle in degrees.",
        "",
        "| class | parameter | error | cases | " + " | ".join(PEERS) + " |",
        "|---|---|---|---|" + "---|" * len(PEERS),
    ]
    for material, params in table.items():
        for name, row in params.items():
            unit = UNITS[row["kind"]]
            peers = " | ".join(f"{row[p]:.3f}" if p in row else "-" for p in PEERS)  # as published
            lines.append(f"| {material} | {name} ({unit or 'abs'}) | {row['error']:.3g} | {row['cases']} | {peers} |")
    lines += ["", PEER_SOURCE]
    return lines
