"""The one boundary between a material's SI parameters and the kernels' parameter columns.

A material enters the simulator once, as a registry name, an optional model and SI
parameters (clflow.materials); :func:`kernel_material` picks the kernel's material, and
:func:`kernel_columns` maps the SI values to the kernels' columns, for numbers (a simulator
being built) and for tensors (a differentiable run's parameters) alike. The simulator keeps
the SI values beside the columns (``SimulationSpec.material_values``), so nothing is ever
converted back. Also here: the physics the time step needs (wave speed, explicit viscosity).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from clflow.errors import InputError
from clflow.materials import get_material, lame_parameters, validate_params
from clflow.mpm.constants import MATERIAL_IDS, PARAM_COUNT

# the registry material of each kernel material that is a model option of another
REGISTRY_MATERIAL: dict[str, str] = {"neo_hookean": "elastic", "sand_volume_corrected": "sand"}
ELASTIC_MODELS = ("fixed_corotated", "neo_hookean")
SAND_MODELS = ("drucker_prager", "volume_corrected")


def drucker_prager_alpha(friction_angle_deg):
    """alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi)) of the Drucker-Prager cone; a number or
    a tensor (differentiable) of angles in degrees."""
    if isinstance(friction_angle_deg, (int, float)):
        sin_phi = math.sin(math.radians(friction_angle_deg))
    else:
        sin_phi = friction_angle_deg.deg2rad().sin()
    return math.sqrt(2.0 / 3.0) * 2.0 * sin_phi / (3.0 - sin_phi)


_LAME = ("youngs_modulus", "poissons_ratio")
# registry parameters of each kernel material, in kernel-column order where they map one to
# one (kernel_columns): E, nu -> (mu, lambda); friction_angle -> alpha;
# non-Newtonian (shear_modulus, bulk_modulus) -> (mu, kappa - 2 mu / 3)
KERNEL_PARAMETERS: dict[str, tuple[str, ...]] = {
    "elastic": _LAME,
    "neo_hookean": _LAME,
    "plasticine": _LAME + ("yield_stress",),
    "metal": _LAME + ("yield_stress", "hardening"),
    "foam": _LAME + ("yield_stress", "viscosity"),
    "sand": _LAME + ("friction_angle", "cohesion"),
    "sand_volume_corrected": _LAME + ("friction_angle", "cohesion"),  # the same kernel row
    "snow": _LAME + ("critical_compression", "critical_stretch", "hardening"),
    "newtonian": ("viscosity", "bulk_modulus"),
    "non_newtonian": ("shear_modulus", "bulk_modulus", "yield_stress", "viscosity"),
}


def kernel_columns(kernel_material: str, values: dict) -> list:
    """The kernel parameters (kernels_cl/mpm/materials/*.h) of a kernel material from its SI
    registry parameters ``values`` (name -> number, or tensor for a differentiable map): one
    per name of KERNEL_PARAMETERS[kernel_material], in that order."""
    names = KERNEL_PARAMETERS[kernel_material]
    columns = [values[name] for name in names]
    if names[:2] == _LAME:
        columns[0], columns[1] = lame_parameters(values["youngs_modulus"], values["poissons_ratio"])
    if "friction_angle" in names:
        columns[2] = drucker_prager_alpha(values["friction_angle"])
    if kernel_material == "non_newtonian":  # lambda = kappa - 2 mu / 3
        columns[1] = values["bulk_modulus"] - 2 * values["shear_modulus"] / 3
    return columns


def kernel_material(material: str, model: str | None = None) -> str:
    """The kernel material (a key of MATERIAL_IDS) of a registry ``material`` and its
    ``model``: elastic's (ELASTIC_MODELS) or sand's (SAND_MODELS) variant, else None."""
    name = get_material(material).name
    if model is not None and name not in ("elastic", "sand"):
        raise InputError(f"material {name!r} has no model option (got model={model!r})")
    if name == "elastic":
        if (model or "fixed_corotated") not in ELASTIC_MODELS:
            raise InputError(f"elastic model {model!r} unknown; choose one of {', '.join(ELASTIC_MODELS)}")
        return "neo_hookean" if model == "neo_hookean" else "elastic"
    if name == "sand":
        if (model or "drucker_prager") not in SAND_MODELS:
            raise InputError(f"sand model {model!r} unknown; choose one of {', '.join(SAND_MODELS)}")
        return "sand_volume_corrected" if model == "volume_corrected" else "sand"
    return name


@dataclass(frozen=True)
class KernelMaterial:
    """One material as the kernels take it: its kernel id, SI values (the registry's
    parameters in KERNEL_PARAMETERS order) and kernel columns, both padded to PARAM_COUNT,
    and its initial plastic state."""

    name: str
    id: int
    si_values: tuple[float, ...]
    columns: tuple[float, ...]
    plastic: float


def kernel_params(material: str, params: dict[str, float], model: str | None = None) -> KernelMaterial:
    """The :class:`KernelMaterial` of a registry ``material`` with SI ``params`` (missing
    ones take their defaults) and ``model`` (:func:`kernel_material`).

    Kernel columns per material (kernels_cl/mpm/materials/*.h):
      elastic (mu, lambda) | plasticine (mu, lambda, tau_Y) | metal (mu, lambda, tau_Y, xi) |
      foam, non_newtonian (mu, lambda, tau_Y, eta) | sand (mu, lambda, alpha, c) |
      newtonian (mu, kappa) | snow (mu0, lambda0, theta_c, theta_s, xi).
    The plastic state is the metal's gained yield stress (0 Pa), snow's J_P (1) or the
    volume-corrected sand's log volume correction v_c (0).
    """
    name = kernel_material(material, model)
    p = validate_params(get_material(material).name, params)
    pad = lambda values: tuple(values) + (0.0,) * (PARAM_COUNT - len(values))  # noqa: E731
    si = [float(p[key]) for key in KERNEL_PARAMETERS[name]]
    columns = [float(v) for v in kernel_columns(name, p)]
    return KernelMaterial(name, MATERIAL_IDS[name], pad(si), pad(columns), 1.0 if name == "snow" else 0.0)


def explicit_viscosity(material: str, params: dict[str, float]) -> float:
    """Dynamic viscosity (Pa s) whose stress the kernels take explicitly from the current
    velocity gradient, so that it limits dt like diffusion: the Newtonian fluid's
    (tau = 2 mu J dev(sym C)). 0 for every other material: the viscoplastic return of foam and
    the non-Newtonian fluid relaxes the overstress implicitly in eta (||s'|| = ||s|| -
    y / (1 + eta / (2 mu_hat dt))), which never stiffens it beyond its elastic response, so
    their elastic wave limit suffices (docs/mpm.md, "Safety")."""
    mat = get_material(material)
    return validate_params(mat.name, params)["viscosity"] if mat.name == "newtonian" else 0.0


def wave_speed(material: str, params: dict[str, float], density: float) -> float:
    """Speed (m/s) of the fastest elastic (pressure) wave of the material at rest."""
    mat = get_material(material)
    p = validate_params(mat.name, params)
    if mat.name == "newtonian":
        modulus = p["bulk_modulus"]
    elif mat.name == "non_newtonian":
        modulus = p["bulk_modulus"] + 4.0 * p["shear_modulus"] / 3.0
    else:
        mu, lam = lame_parameters(p["youngs_modulus"], p["poissons_ratio"])
        modulus = lam + 2.0 * mu
    return math.sqrt(max(modulus, 0.0) / density)
