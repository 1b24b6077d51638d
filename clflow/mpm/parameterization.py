"""Optimisation helpers: unconstrained parameterisations of material parameters built from
the registry's ranges (clflow/materials.py), and gradient clipping.

    p = parameterization("elastic", "youngs_modulus")     # log10 scale
    z = p.encode(1e5).requires_grad_()                    # z = 5.0
    frames = simulate(sim, 10, youngs_modulus=p.decode(z))

Scales (``Param.scale``): "log" -> value = 10^z (moduli, viscosities, yield stresses);
"bounded" -> value = lo + (hi - lo) sigmoid(z) on the parameter's typical range (Poisson's
ratio in (0, 0.49), friction angle); "linear" -> value = z, clamped into the valid range by
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
        """(lower, upper) of a bounded parameter: its typical range."""
        return self.param.typical

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """The parameter value (SI) of z; differentiable."""
        scale = self.param.scale
        if scale == "log":
            return torch.pow(10.0, z)
        if scale == "bounded":
            lo, hi = self.bounds
            return lo + (hi - lo) * torch.sigmoid(z)
        return z

    def encode(self, value, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """z of a parameter value (a number or tensor, SI); InputError outside the range."""
        value = torch.as_tensor(value, dtype=dtype).clone()
        scale, name = self.param.scale, self.param.name
        if scale == "log":
            if bool((value <= 0).any()):
                raise InputError(f"{name}: log parameterisation needs values > 0, got {value.tolist()}")
            return torch.log10(value)
        if scale == "bounded":
            lo, hi = self.bounds
            if bool(((value <= lo) | (value >= hi)).any()):
                raise InputError(f"{name}: value {value.tolist()} outside the bounded range ({lo:g}, {hi:g})")
            u = (value - lo) / (hi - lo)
            return torch.log(u) - torch.log1p(-u)
        return value


def parameterization(material: str, name: str) -> Parameterization:
    """The parameterisation of parameter ``name`` (API name or symbol) of ``material``, or of
    "density" for any material."""
    if name in ("density", DENSITY.symbol):
        get_material(material)  # validates the material name
        return Parameterization(DENSITY)
    return Parameterization(get_material(material).param(name))


def clip_gradients(parameters: Iterable[torch.Tensor], max_norm: float) -> float:
    """Scale the gradients of ``parameters`` so their joint 2-norm is at most ``max_norm``.

    Returns the norm before clipping. A NaN/inf gradient (a diverged run) zeroes every
    gradient, so an optimiser step leaves the parameters unchanged, and returns that norm.
    The norm is summed in float64 in a fixed order (deterministic)."""
    if not (max_norm > 0 and math.isfinite(max_norm)):
        raise InputError(f"clip_gradients: max_norm must be a positive number, got {max_norm}")
    grads = [p.grad for p in parameters if p.grad is not None]
    total = math.sqrt(sum(float((g.double() ** 2).sum()) for g in grads))
    if not math.isfinite(total):
        for g in grads:
            g.zero_()
    elif total > max_norm:
        for g in grads:
            g.mul_(max_norm / total)
    return total


__all__ = ["Parameterization", "clip_gradients", "parameterization"]
