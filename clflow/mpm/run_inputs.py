"""The inputs of a differentiable run (clflow.mpm.autograd.simulate) as the kernels' rows,
checked: material parameters by registry name to kernel parameter rows [N, PARAM_COUNT],
densities to masses, initial states, driver stages' accelerations; a global value broadcast
to the particles (and a population's per-member value to its members) with a backward that
sums the rows in a fixed order (clflow.runtime.reduction.sum_rows)."""

from __future__ import annotations

import torch

from clflow.errors import InputError
from clflow.materials import get_material
from clflow.mpm.constants import MATERIAL_IDS
from clflow.mpm.inputs import check_inside
from clflow.mpm.material_model import KERNEL_PARAMETERS, REGISTRY_MATERIAL, kernel_columns
from clflow.mpm.simulator import Simulator
from clflow.runtime.reduction import sum_rows


class BroadcastRows(torch.autograd.Function):
    """value [...] -> [N, ...] (the same for every particle); backward: fixed-order row sum."""

    @staticmethod
    def forward(ctx, value, n: int, device):
        ctx.shape, ctx.device = value.shape, device
        return value.detach().reshape(1, -1).expand(n, -1).reshape((n,) + tuple(value.shape)).clone()

    @staticmethod
    def backward(ctx, grad):
        rows = grad.reshape(grad.shape[0], -1).contiguous()
        return sum_rows(rows, ctx.device).to(grad.dtype).reshape(ctx.shape), None, None


def per_particle(
    value, n: int, name: str, dtype: torch.dtype, device, trailing: tuple[int, ...] = (), members: int | None = None
) -> torch.Tensor:
    """``value`` as [N, *trailing] of ``dtype``: a global value (shape ``trailing``) is
    broadcast with a deterministic backward; a per-particle one is taken as it is; for a
    population of ``members`` (a batched simulator), one value per member [K, *trailing] is
    broadcast to each member's block of N / K particles."""
    value = torch.as_tensor(value)
    if not value.is_floating_point():
        value = value.to(dtype)
    if tuple(value.shape) == trailing:
        out = BroadcastRows.apply(value.to(dtype), n, device)
    elif members is not None and tuple(value.shape) == (members,) + trailing:
        out = torch.cat([BroadcastRows.apply(value[m].to(dtype), n // members, device) for m in range(members)])
    elif tuple(value.shape) == (n,) + trailing:
        out = value.to(dtype)
    else:
        per_member = f", {[members, *trailing]} (per member)" if members is not None else ""
        raise InputError(
            f"{name}: expected shape {list(trailing)} (global){per_member} or {[n, *trailing]} "
            f"(per particle), got {list(value.shape)}"
        )
    if not bool(torch.isfinite(out.detach()).all()):
        raise InputError(f"{name} contains NaN or inf")
    return out


def material_param_rows(sim: Simulator, params: dict, dtype: torch.dtype) -> torch.Tensor:
    """[N, PARAM_COUNT] kernel rows with the registry parameters ``params`` (name -> global or
    per-particle tensor, SI) replacing the simulator's SI values for every particle whose
    material has them, mapped to kernel columns as when the simulator was built."""
    base, n = sim.particles, sim.n
    names = {i: name for name, i in MATERIAL_IDS.items()}
    present = [names[int(m)] for m in torch.unique(base.material)]
    known = {name for m in present for name in KERNEL_PARAMETERS[m]}
    unknown = sorted(set(params) - known)
    if unknown:
        raise InputError(
            f"params: {', '.join(unknown)} is not a parameter of the simulated material(s) "
            f"{', '.join(present)}; their parameters: {', '.join(sorted(known))}"
        )
    members = sim.members if sim.batched else None
    rows = {name: per_particle(value, n, name, dtype, sim.device, members=members) for name, value in params.items()}
    columns = [base.param[:, k] for k in range(base.param.shape[1])]
    for kernel_material in present:
        given = [name for name in KERNEL_PARAMETERS[kernel_material] if name in rows]
        if not given:
            continue
        index = torch.nonzero(base.material == MATERIAL_IDS[kernel_material]).flatten()
        si = sim.spec.material_values[index]  # the SI values the simulator was built with
        values = {name: si[:, k] for k, name in enumerate(KERNEL_PARAMETERS[kernel_material])}
        registry = get_material(REGISTRY_MATERIAL.get(kernel_material, kernel_material))
        for name in given:
            values[name] = rows[name][index].to(torch.float64)
            lo, hi = float(values[name].detach().min()), float(values[name].detach().max())
            registry.param(name).check(lo, "params")
            registry.param(name).check(hi, "params")
        for k, column in enumerate(kernel_columns(kernel_material, values)):
            columns[k] = columns[k].index_put((index,), column.to(dtype))
    return torch.stack(columns, 1)


def parameter_rows(sim: Simulator, params: dict | None, kernel_params) -> torch.Tensor:
    """[N, PARAM_COUNT] kernel parameters of :func:`simulate`: ``kernel_params`` as given,
    or the simulator's with ``params`` (SI, by registry name) put in, or the simulator's."""
    base = sim.particles.param
    if kernel_params is not None and params:
        raise InputError("give kernel_params or params, not both")
    if kernel_params is not None:
        param = torch.as_tensor(kernel_params)
        if tuple(param.shape) != tuple(base.shape):
            raise InputError(f"kernel_params: expected shape {list(base.shape)}, got {list(param.shape)}")
        return param.to(sim.dtype)
    return material_param_rows(sim, dict(params), sim.dtype) if params else base


def masses(sim: Simulator, density) -> torch.Tensor:
    """[N] particle masses (kg): ``density`` (kg/m^3, global or [N]) x rest volume."""
    rho = per_particle(density, sim.n, "density", sim.dtype, sim.device, members=sim.members if sim.batched else None)
    if bool((rho.detach() <= 0).any()):
        raise InputError("density must be > 0 kg/m^3")
    return rho * sim.particles.volume


def initial_state(sim: Simulator, positions, velocities) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """x0 [N, 3] (m) and v0 [N, 3] (m/s) as given (checked), None for the simulator's own (on
    the device already); for a batched simulator each [K, N / K, 3] (per member) or
    [N / K, 3] (every member alike)."""
    x0 = None if positions is None else members_rows(sim, torch.as_tensor(positions).to(sim.dtype))
    v0 = None if velocities is None else members_rows(sim, torch.as_tensor(velocities).to(sim.dtype))
    for name, value in (("positions", x0), ("velocities", v0)):
        if value is None:
            continue
        if tuple(value.shape) != (sim.n, 3):
            raise InputError(f"{name}: expected shape [{sim.n}, 3], got {list(value.shape)}")
        if not bool(torch.isfinite(value.detach()).all()):
            raise InputError(f"{name} contains NaN or inf")
    if x0 is not None:
        check_inside(x0.detach(), sim.grid)
    return x0, v0


def members_rows(sim: Simulator, rows: torch.Tensor) -> torch.Tensor:
    """A batched simulator's [K, N / K, 3] or [N / K, 3] rows as [N, 3] (other shapes pass, to be refused)."""
    k = sim.members
    if not sim.batched or rows.dim() not in (2, 3) or rows.shape[-2] * k != sim.n:
        return rows
    return rows.reshape(sim.n, 3) if rows.dim() == 3 else rows.repeat(k, 1)


def stage_accelerations_of(sim: Simulator, given) -> torch.Tensor:
    """[S, 3] acceleration (m/s^2) of each driver stage: as given (checked), else the simulator's."""
    stages = sim.drivers.stage_accel.shape[0]
    stage_accel = sim.drivers.stage_accel if given is None else torch.as_tensor(given)
    if tuple(stage_accel.shape) != (stages, 3):
        raise InputError(
            f"stage_accelerations: expected shape [{stages}, 3] (one row per force stage), "
            f"got {list(stage_accel.shape)}"
        )
    return stage_accel.to(sim.dtype)


def stage_members(simulator: Simulator, stage: int) -> torch.Tensor:
    """[N] bool: the particles driver stage ``stage`` acts on (in every member of a population)."""
    group = simulator.particles.group.long()
    return (group >= 0) & simulator.drivers.members[group.clamp(min=0), stage]


def region_masses(simulator: Simulator) -> torch.Tensor:
    """[S] total mass (kg) of the particles each driver stage acts on (float64; in one member
    of a population, all alike)."""
    n = simulator.n // simulator.members
    mass = simulator.particles.mass[:n].double()
    return (
        torch.stack([mass[stage_members(simulator, s)[:n]].sum() for s in range(len(simulator.drivers.forces))])
        if simulator.drivers.forces
        else torch.zeros(0, dtype=torch.float64)
    )
