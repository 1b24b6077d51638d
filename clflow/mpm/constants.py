"""Constants shared by the MPM kernels, the host code and the torch reference.

Each is written once here; the kernels get them as ``-D`` defines (:func:`kernel_defines`).
What a material's SI parameters mean to the kernels is clflow.mpm.material_model.
"""

from __future__ import annotations

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
# the models that need the SVD of F_tr (all but neo-Hookean and the J-only Newtonian fluid)
SVD_MATERIALS = sum(1 << i for name, i in MATERIAL_IDS.items() if name not in ("neo_hookean", "newtonian"))
SIMD_LANES = 8  # particles per work-item of the SIMD stress kernels (vector registers)

PARAM_COUNT = 5  # kernel parameters per particle (material_model.kernel_params)
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


def uses_flip(flip: float) -> bool:
    """Whether the PIC/FLIP blend ``flip`` (0..1) needs the FLIP transfers: any blend above 0
    (0 is APIC). The one place that decides it: channels, kernels and buffers follow."""
    return flip > 0


def grid_channels(flip: float) -> int:
    """Reals per node of the P2G grid (kernels_cl/mpm/mpm.h GRID_CH): m and mv, and with a
    PIC/FLIP blend (``flip`` > 0) also mv0, the momentum before the substep's forces."""
    return 7 if uses_flip(flip) else 4


def velocity_channels(flip: float) -> int:
    """Reals per node of the grid velocities the adjoint scatters into (mpm.h GV_CH): vbar,
    and with a PIC/FLIP blend also dvbar; as many as the forward's grid_v[, grid_dv]."""
    return 6 if uses_flip(flip) else 3


# kernels_cl/mpm/health.cl: a work-group's items, and the fixed number of groups whose
# (largest |v|^2, not finite) pairs the host reads after a frame
HEALTH_WG, HEALTH_GROUPS = 64, 64


def kernel_defines(flip: float = 0.0) -> dict[str, object]:
    """The -D switches every MPM kernel is built with; ``flip`` > 0 builds the PIC/FLIP
    blend's transfers (CLFLOW_FLIP)."""
    defines: dict[str, object] = {f"MAT_{name.upper()}": i for name, i in MATERIAL_IDS.items()}
    defines["CLFLOW_FLIP"] = int(uses_flip(flip))
    defines.update(
        PARAM_COUNT=PARAM_COUNT,
        SVD_MATERIALS=SVD_MATERIALS,
        CLFLOW_SIMD_LANES=SIMD_LANES,
        HENCKY_S_MIN=repr(HENCKY_S_MIN),
        SAND_S_MIN=repr(SAND_S_MIN),
        SAFE_NORM_EPS2=repr(SAFE_NORM_EPS2),
        NEWTONIAN_J_MIN=repr(NEWTONIAN_J_MIN),
        CLAMP_MARGIN=CLAMP_MARGIN,
        HEALTH_WG=HEALTH_WG,
        BC_STRIDE=BC_STRIDE,
        BC_HALFSPACE=BC_HALFSPACE,
        BC_BOX=BC_BOX,
        BC_CYLINDER=BC_CYLINDER,
        **BC_SLOTS,
        **{f"COLLIDE_{name.upper()}": i for name, i in COLLIDER_MODES.items()},
    )
    return defines
