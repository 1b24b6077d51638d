"""Constants shared by the MPM kernels, the host code and the torch reference.

Each is written once here; the kernels get them as ``-D`` defines (:func:`kernel_defines`).
"""

from __future__ import annotations

import math

from clflow.errors import InputError
from clflow.materials import get_material, lame_parameters, validate_params

# Kernel material ids. "neo_hookean" is the elastic material's optional model,
# "sand_volume_corrected" sand's (Drucker-Prager with Tampubolon et al. 2017's volume correction).
MATERIAL_IDS: dict[str, int] = {
    "elastic": 0,
    "neo_hookean": 1,
    "plasticine": 2,
    "metal": 3,
    "foam": 4,
    "sand": 5,
    "newtonian": 6,
    "non_newtonian": 7,
    "snow": 8,
    "sand_volume_corrected": 9,
}
# the registry material of each kernel material that is a model option of another
REGISTRY_MATERIAL: dict[str, str] = {"neo_hookean": "elastic", "sand_volume_corrected": "sand"}
ELASTIC_MODELS = ("fixed_corotated", "neo_hookean")
SAND_MODELS = ("drucker_prager", "volume_corrected")
# the models that need the SVD of F_tr (all but neo-Hookean and the J-only Newtonian fluid)
SVD_MATERIALS = sum(1 << i for name, i in MATERIAL_IDS.items() if name not in ("neo_hookean", "newtonian"))
SIMD_LANES = 8  # particles per work-item of the SIMD stress kernels (vector registers)

PARAM_COUNT = 5  # kernel parameters per particle (see kernel_params)
HENCKY_S_MIN = 0.05  # singular values are floored here before the log of Hencky strain
SAND_S_MIN = 1e-4  # the same for Drucker-Prager (on |s|)
SAFE_NORM_EPS2 = 1e-16  # ||x|| = sqrt(x.x + eps2) wherever a norm is divided by
NEWTONIAN_J_MIN = 0.05  # floor of the fluid's volume ratio J
CLAMP_MARGIN = 1  # particles are kept >= this many cells inside the grid
WALL_CELLS = 3  # cells of the domain walls (clflow.mpm.Simulator's default wall_cells)
MASS_EPS_REL = 1e-12  # grid nodes lighter than this x the lightest particle are empty (see docs/mpm.md)

# Boundary-condition records (kernels_cl/mpm/grid.cl): BC_STRIDE reals each, in these slots
BC_STRIDE = 16
BC_HALFSPACE, BC_BOX, BC_CYLINDER = 1, 2, 3
BC_SLOTS: dict[str, int] = {
    "BC_KIND": 0,  # BC_HALFSPACE, BC_BOX or BC_CYLINDER
    "BC_T_START": 1,  # active during [t_start, t_end) s
    "BC_T_END": 2,
    "BC_A": 3,  # 3 reals: half-space point, box lower corner, cylinder centre (m)
    "BC_B": 6,  # 3 reals: half-space outward unit normal, box upper corner (m), cylinder unit axis
    "BC_C": 9,  # box: 3 reals, the velocity imposed inside (m/s)
    "BC_MODE": 9,  # half-space: COLLIDE_* mode
    "BC_FRICTION": 10,  # half-space: Coulomb coefficient
    "BC_RADIUS": 9,  # cylinder: radius (m)
    "BC_HALF_LENGTH": 10,  # cylinder: half length along the axis (m)
    "BC_OMEGA": 11,  # cylinder: angular velocity about the axis (rad/s)
}
COLLIDER_MODES: dict[str, int] = {"sticky": 0, "slip": 1, "separate": 2}


def grid_channels(flip: float) -> int:
    """Reals per node of the P2G grid (kernels_cl/mpm/mpm.h GRID_CH): m and mv, and with a
    PIC/FLIP blend (``flip`` > 0) also mv0, the momentum before the substep's forces."""
    return 7 if flip > 0 else 4


def velocity_channels(flip: float) -> int:
    """Reals per node of the grid velocities the adjoint scatters into (mpm.h GV_CH): vbar,
    and with a PIC/FLIP blend also dvbar; as many as the forward's grid_v[, grid_dv]."""
    return 6 if flip > 0 else 3


def kernel_defines(flip: float = 0.0) -> dict[str, object]:
    """The -D switches every MPM kernel is built with; ``flip`` > 0 builds the PIC/FLIP
    blend's transfers (CLFLOW_FLIP)."""
    defines: dict[str, object] = {f"MAT_{name.upper()}": i for name, i in MATERIAL_IDS.items()}
    defines["CLFLOW_FLIP"] = int(flip > 0)
    defines.update(
        PARAM_COUNT=PARAM_COUNT,
        SVD_MATERIALS=SVD_MATERIALS,
        CLFLOW_SIMD_LANES=SIMD_LANES,
        HENCKY_S_MIN=repr(HENCKY_S_MIN),
        SAND_S_MIN=repr(SAND_S_MIN),
        SAFE_NORM_EPS2=repr(SAFE_NORM_EPS2),
        NEWTONIAN_J_MIN=repr(NEWTONIAN_J_MIN),
        CLAMP_MARGIN=CLAMP_MARGIN,
        BC_STRIDE=BC_STRIDE,
        BC_HALFSPACE=BC_HALFSPACE,
        BC_BOX=BC_BOX,
        BC_CYLINDER=BC_CYLINDER,
        **BC_SLOTS,
        **{f"COLLIDE_{name.upper()}": i for name, i in COLLIDER_MODES.items()},
    )
    return defines


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


def kernel_params(material: str, params: dict[str, float], model: str | None = None) -> tuple[int, list[float], float]:
    """(material id, PARAM_COUNT kernel parameters, initial plastic state) of one material.

    ``params`` are SI registry parameters (missing ones take their defaults). Kernel
    parameters per material (kernels_cl/mpm/materials/*.h):
      elastic (mu, lambda) | plasticine (mu, lambda, tau_Y) | metal (mu, lambda, tau_Y, xi) |
      foam, non_newtonian (mu, lambda, tau_Y, eta) | sand (mu, lambda, alpha, c) |
      newtonian (mu, kappa) | snow (mu0, lambda0, theta_c, theta_s, xi).
    The plastic state is the metal's gained yield stress (0 Pa), snow's J_P (1) or the
    volume-corrected sand's log volume correction v_c (0). ``model`` picks elastic's
    (ELASTIC_MODELS) or sand's (SAND_MODELS) variant.
    """
    mat = get_material(material)
    p = validate_params(mat.name, params)
    if model is not None and mat.name not in ("elastic", "sand"):
        raise InputError(f"material {mat.name!r} has no model option (got model={model!r})")
    if mat.name == "sand" and (model or "drucker_prager") not in SAND_MODELS:
        raise InputError(f"sand model {model!r} unknown; choose one of {', '.join(SAND_MODELS)}")
    name = mat.name
    if mat.name == "elastic":
        model = model or "fixed_corotated"
        if model not in ELASTIC_MODELS:
            raise InputError(f"elastic model {model!r} unknown; choose one of {', '.join(ELASTIC_MODELS)}")
        name = "neo_hookean" if model == "neo_hookean" else "elastic"
    elif mat.name == "sand" and model == "volume_corrected":
        name = "sand_volume_corrected"
    values = [float(v) for v in kernel_columns(name, p)]
    plastic = 1.0 if name == "snow" else 0.0
    return MATERIAL_IDS[name], values + [0.0] * (PARAM_COUNT - len(values)), plastic


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
