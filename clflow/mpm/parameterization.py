"""Optimisation helpers: unconstrained parameterisations of material parameters built from
the registry's ranges (clflow/materials.py), and gradient clipping.

    p = parameterization("elastic", "youngs_modulus")     # log10 scale
    z = p.encode(1e5).requires_grad_()                    # z = 5.0
    frames = simulate(sim, 10, youngs_modulus=p.decode(z))

Scales (``Param.scale``): "log" -> value = 10^z (moduli, viscosities, yield stresses);
"bounded" -> value = lo + (hi - lo) sigmoid(a z + b) on the parameter's whole valid range
(lo, hi) (Poisson's ratio in (-1, 0.5), friction angle in (0, 90) deg), so every valid value
is a possible start; the typical range only sets the step: z = 0 is its middle, where one
unit of z is a quarter of its width (friction angle 11.25 deg, Poisson's ratio 0.1225: what a
logistic map onto the typical range alone would give, and near PAC-NeRF's Adam rates at the
default rate of 0.1 per iteration); "linear" -> value = z, clamped into the valid range by
the caller's choice of steps (hardening, cohesion).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable

import torch

from clflow.errors import InputError
from clflow.materials import DENSITY, Param, get_material


@dataclass(frozen=True)
class Parameterization:
    """Map between an unconstrained variable z and a parameter value (SI units)."""

    param: Param

    @property
    def bounds(self) -> tuple[float, float]:
        """(lower, upper) of a bounded parameter: its valid range, open at both ends."""
        return self.param.valid

    @property
    def logistic(self) -> tuple[float, float]:
        """(a, b) of a bounded parameter's map u = sigmoid(a z + b), value = lo + (hi - lo) u:
        z = 0 at the middle of the typical range, d value / dz there = a quarter of its width."""
        lo, hi = self.bounds
        typical_lo, typical_hi = self.param.typical
        u0 = ((typical_lo + typical_hi) / 2 - lo) / (hi - lo)
        return (typical_hi - typical_lo) / (4 * (hi - lo) * u0 * (1 - u0)), math.log(u0 / (1 - u0))

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """The parameter value (SI) of z; differentiable."""
        scale = self.param.scale
        if scale == "log":
            return torch.pow(10.0, z)
        if scale == "bounded":
            lo, hi = self.bounds
            a, b = self.logistic
            return lo + (hi - lo) * torch.sigmoid(a * z + b)
        return z

    def encode(self, value, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """z of a parameter value (a number or tensor, SI); InputError outside the range
        (for a bounded parameter: its valid range without the ends, which no z reaches)."""
        value = torch.as_tensor(value, dtype=dtype).clone()
        scale, name = self.param.scale, self.param.name
        if scale == "log":
            if bool((value <= 0).any()):
                raise InputError(f"{name}: log parameterisation needs values > 0, got {value.tolist()}")
            return torch.log10(value)
        if scale == "bounded":
            lo, hi = self.bounds
            outside = ~((value > lo) & (value < hi))  # NaN too
            if bool(outside.any()):
                shown = f"{float(value):g}" if value.dim() == 0 else str(value[outside].tolist())
                unit = "" if self.param.unit == "1" else f" {self.param.unit}"
                raise InputError(
                    f"{name} ({self.param.symbol}) = {shown}{unit} is outside the open range "
                    f"({lo:g}, {hi:g}) that its optimisation variable covers"
                )
            a, b = self.logistic
            u = (value - lo) / (hi - lo)
            return (torch.log(u) - torch.log1p(-u) - b) / a
        return value


def parameterization(material: str, name: str) -> Parameterization:
    """The parameterisation of parameter ``name`` (API name or symbol) of ``material``, or of
    "density" for any material."""
    if name in ("density", DENSITY.symbol):
        get_material(material)  # validates the material name
        return Parameterization(DENSITY)
    return Parameterization(get_material(material).param(name))


def clip_factor(norm: float, max_norm: float) -> float:
    """The factor (<= 1) that brings a gradient of 2-norm ``norm`` to at most ``max_norm``; 0
    for a NaN/inf norm (a diverged run), so that a step with it leaves the parameters be."""
    if not math.isfinite(norm):
        return 0.0
    return max_norm / norm if norm > max_norm else 1.0


def clip_gradients(parameters: Iterable[torch.Tensor], max_norm: float) -> float:
    """Scale the gradients of ``parameters`` so their joint 2-norm is at most ``max_norm``.

    Returns the norm before clipping. A NaN/inf gradient (a diverged run) zeroes every
    gradient, so an optimiser step leaves the parameters unchanged, and returns that norm.
    The norm is summed in float64 in a fixed order (deterministic)."""
    if not (max_norm > 0 and math.isfinite(max_norm)):
        raise InputError(f"clip_gradients: max_norm must be a positive number, got {max_norm}")
    grads = [p.grad for p in parameters if p.grad is not None]
    total = math.sqrt(sum(float((g.double() ** 2).sum()) for g in grads))
    factor = clip_factor(total, max_norm)
    if factor != 1.0:
        for g in grads:
            g.mul_(factor) if factor else g.zero_()  # zero_ also clears NaN entries
    return total


__all__ = ["Parameterization", "clip_factor", "clip_gradients", "parameterization"]
