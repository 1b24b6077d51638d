"""What a :class:`~clflow.mpm.Simulator` is given, checked and made into its per-particle
arrays: the materials (:class:`MaterialSpec`, to kernel ids, kernel parameters, SI values,
densities and time-step limits), the particles (positions inside the grid, velocities, rest
volumes, release times), for one run or a population of K (clflow.mpm.population)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from clflow.errors import InputError
from clflow.materials import DENSITY, get_material
from clflow.mpm.constants import CLAMP_MARGIN
from clflow.mpm.material_model import explicit_viscosity, kernel_params, wave_speed
from clflow.mpm.population import member_materials, member_velocities, tile
from clflow.mpm.substep import Grid


@dataclass(frozen=True)
class MaterialSpec:
    """A material (a registry name or alias), its SI parameters (missing ones take the
    registry defaults), density (kg/m^3, default: the material's) and, for elastic, the
    model ("fixed_corotated" or "neo_hookean"), for sand "drucker_prager" (default) or
    "volume_corrected" (Tampubolon et al. 2017's volume correction; docs/mpm.md)."""

    name: str
    params: dict[str, float] = field(default_factory=dict)
    density: float | None = None
    model: str | None = None


@dataclass(frozen=True)
class MaterialLimits:
    """What limits the time step of one material spec: its fastest elastic wave speed (m/s),
    the viscosity it applies explicitly (Pa s) and its density (kg/m^3)."""

    name: str
    wave_speed: float
    viscosity: float
    density: float


def as_tensor(value, shape: tuple[int, ...], what: str, dtype: torch.dtype) -> torch.Tensor:
    t = torch.as_tensor(value, dtype=torch.float64)
    if t.dim() == 0 and len(shape) == 1:
        t = t.expand(shape)
    if tuple(t.shape) != shape:
        raise InputError(f"{what}: expected shape {list(shape)}, got {list(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise InputError(f"{what} contains NaN or inf")
    return t.to(dtype, copy=True).contiguous()  # never alias the caller's tensor


def particle_inputs(positions: torch.Tensor, volume, velocities, grid: Grid, dtype: torch.dtype, members: int):
    """Checked copies for a population of ``members`` (1: a single run): x [K N, 3] (m, inside
    ``grid``), v [K N, 3] (m/s, zero when None; from [N, 3] or [K, N, 3]) in ``dtype``; rest
    volumes [K N] (m^3, > 0) in float64."""
    if positions.dim() != 2 or positions.shape[1] != 3:
        raise InputError(f"positions: expected shape [N, 3], got {list(positions.shape)}")
    n = positions.shape[0]
    if n == 0:
        raise InputError("positions: the particle set is empty")
    x = as_tensor(positions, (n, 3), "positions", dtype)
    check_inside(x, grid)
    x, k_n = tile(x, members), members * n
    velocities = member_velocities(velocities, members, n)
    v = torch.zeros(k_n, 3, dtype=dtype) if velocities is None else as_tensor(velocities, (k_n, 3), "velocities", dtype)
    vol = tile(as_tensor(volume, (n,), "volume", torch.float64), members)
    if not bool((vol > 0).all()):
        raise InputError("volume: every particle volume must be > 0 m^3")
    return x, v, vol


def release_time_array(release_times, n: int, dtype: torch.dtype) -> torch.Tensor:
    """[N] time (s) each particle is released (-inf: from the start)."""
    if release_times is None:
        return torch.full((n,), -math.inf, dtype=dtype)
    release = torch.as_tensor(release_times, dtype=torch.float64)
    if release.shape != (n,) or bool(torch.isnan(release).any()):
        raise InputError(f"release_times: expected [{n}] numbers, got shape {list(release.shape)}")
    return release.to(dtype).contiguous()


def population_materials(materials, material_index, n: int, dtype: torch.dtype, members: int):
    """material_arrays of each of ``members`` (population.member_materials), member after
    member: the arrays [K N, ...], the limits of every member's specs."""
    parts = [material_arrays(member_materials(materials, m), material_index, n, dtype) for m in range(members)]
    if members == 1:
        return parts[0]
    arrays = [torch.cat(column).contiguous() for column in list(zip(*parts))[:5]]
    return (*arrays, [limit for part in parts for limit in part[5]])


def material_arrays(materials, material_index, n: int, dtype: torch.dtype):
    """Per-particle kernel material ids [N] int32, kernel parameters [N, PARAM_COUNT], their
    SI values [N, PARAM_COUNT] (float64, material_model.KernelMaterial), densities [N]
    (kg/m^3, float64), initial plastic state [N], and each spec's :class:`MaterialLimits`."""
    specs = [materials] if isinstance(materials, MaterialSpec) else list(materials)
    if not specs:
        raise InputError("materials: give at least one MaterialSpec")
    if material_index is None:
        if len(specs) > 1:
            raise InputError(f"{len(specs)} materials given: pass material_index [N] to assign them")
        index = torch.zeros(n, dtype=torch.long)
    else:
        index = torch.as_tensor(material_index).long()
        if index.shape != (n,):
            raise InputError(f"material_index: expected shape [{n}], got {list(index.shape)}")
        if int(index.min()) < 0 or int(index.max()) >= len(specs):
            raise InputError(
                f"material_index values must lie in [0, {len(specs)}), got [{int(index.min())}, {int(index.max())}]"
            )
    rows, si_rows, densities, plastic0, limits = [], [], [], [], []
    for k, spec in enumerate(specs):
        mat = get_material(spec.name)
        rho = DENSITY.check(mat.default_density if spec.density is None else spec.density, f"materials[{k}]")
        kernel = kernel_params(mat.name, spec.params, spec.model)
        rows.append([kernel.id, *kernel.columns])
        si_rows.append(kernel.si_values)
        densities.append(rho)
        plastic0.append(kernel.plastic)
        speed, viscosity = wave_speed(mat.name, spec.params, rho), explicit_viscosity(mat.name, spec.params)
        limits.append(MaterialLimits(mat.name, speed, viscosity, rho))
    table = torch.tensor(rows, dtype=torch.float64)[index]
    return (
        table[:, 0].to(torch.int32).contiguous(),
        table[:, 1:].to(dtype).contiguous(),
        torch.tensor(si_rows, dtype=torch.float64)[index],
        torch.tensor(densities, dtype=torch.float64)[index],
        torch.tensor(plastic0, dtype=dtype)[index].contiguous(),
        limits,
    )


def check_inside(x: torch.Tensor, grid: Grid) -> None:
    """InputError unless every position of ``x`` [N, 3] (m) lies inside ``grid`` by CLAMP_MARGIN cells."""
    lo = torch.tensor(grid.origin, dtype=x.dtype) + CLAMP_MARGIN * grid.dx
    hi = torch.tensor(grid.upper, dtype=x.dtype) - CLAMP_MARGIN * grid.dx
    outside = int(((x < lo) | (x > hi)).any(-1).sum())
    if outside:
        raise InputError(
            f"positions: {outside} of {x.shape[0]} particles lie outside the grid's interior "
            f"[{lo.tolist()}, {hi.tolist()}] m; enlarge or move the grid"
        )
