"""Populations: K simulations of one scene in lockstep, each member with its own material
parameters (and initial velocities), advanced by the same kernel launches.

A batch dimension on a :class:`~clflow.mpm.Simulator`'s inputs makes one: a MaterialSpec's
parameters or density given as K values (a [K] tensor or a sequence), velocities [K, N, 3].
What is given once (a number, velocities [N, 3]) every member shares. The trajectory gains the
batch dimension: x [T, K, N, 3].

On the device the K N particles are K blocks, member after member, each on its own copy of the
grid (kernels_cl/mpm/mpm.h), so a substep makes the launches of one run whatever K is: the host
cost of a substep is shared by the members. The members share one time step, the stiffest
member's (the smallest stable step over all of them): what is stable for it is stable for the
others, and lockstep needs one dt. A member therefore equals its own run at the same substeps
(to float rounding: the private P2G path sums the particle chunks of a different split), and a
population of one is the single run to the bit.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Sequence

import torch

from clflow.errors import InputError


def _batch_of(value, what: str) -> int | None:
    """K when ``value`` holds K member values (a 1-d tensor or a sequence), None for a number."""
    if isinstance(value, (int, float)) or value is None:
        return None
    t = torch.as_tensor(value, dtype=torch.float64)
    if t.dim() == 0:
        return None
    if t.dim() != 1 or t.shape[0] < 1:
        raise InputError(f"{what}: expected a number or one value per member [K], got shape {list(t.shape)}")
    return int(t.shape[0])


def _member_value(value, m: int):
    """Member m's value of a number or of K member values."""
    return value if _batch_of(value, "") is None else float(torch.as_tensor(value, dtype=torch.float64)[m])


def _specs(materials) -> list:
    """The MaterialSpecs of ``materials``: one, or a list or tuple of them."""
    return list(materials) if isinstance(materials, (list, tuple)) else [materials]


def population_size(materials, velocities) -> int | None:
    """K, the members the inputs' batch dimension makes (every batched input must agree), or
    None when nothing is batched (a single run)."""
    specs = _specs(materials)
    sizes = {}
    for k, spec in enumerate(specs):
        for name, value in spec.params.items():
            sizes[f"materials[{k}].params[{name!r}]"] = _batch_of(value, f"materials[{k}].params[{name!r}]")
        sizes[f"materials[{k}].density"] = _batch_of(spec.density, f"materials[{k}].density")
    if velocities is not None and torch.as_tensor(velocities).dim() == 3:
        sizes["velocities"] = int(torch.as_tensor(velocities).shape[0])
    batched = {what: size for what, size in sizes.items() if size is not None}
    if len(set(batched.values())) > 1:
        listed = ", ".join(f"{what}: {size}" for what, size in batched.items())
        raise InputError(f"the population's batched inputs disagree on the number of members ({listed})")
    return next(iter(batched.values()), None)


def member_materials(materials, m: int):
    """Member m's materials: ``materials`` (one MaterialSpec or a list) with each batched
    parameter and density replaced by its m-th value."""

    def one(spec):
        params = {name: _member_value(value, m) for name, value in spec.params.items()}
        return replace(spec, params=params, density=_member_value(spec.density, m))

    return [one(spec) for spec in materials] if isinstance(materials, (list, tuple)) else one(materials)


def tile(t: torch.Tensor | None, members: int) -> torch.Tensor | None:
    """[N, ...] -> [members N, ...]: the members' blocks, each a copy of ``t``."""
    if t is None or members == 1:
        return t
    return t.repeat(members, *([1] * (t.dim() - 1))).contiguous()


def member_velocities(velocities, members: int, n: int) -> torch.Tensor | None:
    """Velocities [members N, 3] (m/s) from [K, N, 3] (each member its own) or [N, 3] (shared)."""
    if velocities is None:
        return None
    v = torch.as_tensor(velocities)
    if v.dim() == 3:
        if tuple(v.shape[1:]) != (n, 3):
            raise InputError(f"velocities: expected shape [N, 3] or [K, N, 3] with N = {n}, got {list(v.shape)}")
        return v.reshape(members * n, 3)
    return tile(v, members)


def split_members(t: torch.Tensor, members: int) -> torch.Tensor:
    """[T, members N, ...] -> [T, members, N, ...]."""
    return t.reshape(t.shape[0], members, t.shape[1] // members, *t.shape[2:])


def check_forces_shared_mass(forces: Sequence, materials) -> None:
    """Force stages given as forces (N) act on a group's total mass, the same in every member
    only when the densities are: refuse per-member densities with force stages."""
    if forces and any(_batch_of(spec.density, "density") is not None for spec in _specs(materials)):
        raise InputError(
            "a population with force stages needs one density for all members (a stage's force is "
            "spread over its particles' mass); give density as a number"
        )
