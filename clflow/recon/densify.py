"""Adaptive density control of 3DGS (Kerbl et al. 2023, sec. 5.2) on a parameter table
whose rows are Gaussians, with the Adam moments kept in step.

Parameters (one Adam group each, named as the keys): ``means`` [N, 3] (m), ``quats``
[N, 4], ``log_scales`` [N, 3] (log m), ``opacity_logits`` [N], ``sh0`` [N, 1, 3],
``shN`` [N, K - 1, 3].

- view-space gradient: per Gaussian, the mean over the views that saw it of |dL/d mean2d|
  in normalised device units (pixels x W/2, H/2, as 3DGS measures it);
- where that exceeds ``grad_threshold``: small Gaussians (largest scale <= ``percent_dense``
  x scene extent) are cloned, large ones split into two drawn from the Gaussian itself,
  with scales divided by 1.6;
- pruned: opacity below ``min_opacity``; after the first opacity reset also those wider
  than ``max_screen_radius`` pixels in some view or ``max_world_scale`` x extent.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from clflow.splat.geometry import quat_to_rotmat

SPLIT_CHILDREN = 2  # each split Gaussian becomes this many (3DGS's N)
SPLIT_SHRINK = 0.8 * SPLIT_CHILDREN  # children's scales are the parent's / 1.6


@dataclass
class ViewSpaceStats:
    """Per-Gaussian accumulators between densification steps: sum of view-space mean
    gradient norms, number of views that saw the Gaussian, largest screen radius (pixels)."""

    grad_sum: torch.Tensor  # [N] float64
    count: torch.Tensor  # [N] int64
    max_radius: torch.Tensor  # [N] int32

    @classmethod
    def zeros(cls, n: int) -> "ViewSpaceStats":
        return cls(
            torch.zeros(n, dtype=torch.float64), torch.zeros(n, dtype=torch.int64), torch.zeros(n, dtype=torch.int32)
        )

    def add(self, means2d_grad: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> None:
        """Add one view: ``means2d_grad`` [N, 2] dL/d mean2d (1/pixel), ``radii`` [N] (0 = not seen)."""
        seen = radii > 0
        ndc = means2d_grad.detach().double() * torch.tensor([0.5 * width, 0.5 * height], dtype=torch.float64)
        self.grad_sum += torch.where(seen, ndc.norm(dim=-1), 0.0)
        self.count += seen.long()
        self.max_radius = torch.maximum(self.max_radius, radii.to(torch.int32))

    def mean_grad(self) -> torch.Tensor:
        """[N] mean view-space gradient norm over the views that saw each Gaussian (0 if none)."""
        return self.grad_sum / self.count.clamp_min(1)


@dataclass(frozen=True)
class DensifySettings:
    """Thresholds of adaptive density control (3DGS defaults)."""

    grad_threshold: float = 2e-4  # mean view-space gradient norm (NDC units) that densifies
    percent_dense: float = 0.01  # clone at most, split above this largest scale (x extent)
    min_opacity: float = 0.005  # prune below
    max_screen_radius: int = 20  # pixels; prune wider (only after the first opacity reset)
    max_world_scale: float = 0.1  # x extent; prune larger (only after the first opacity reset)


def rebuild(
    optimizer: torch.optim.Adam, rows, new_rows: dict[str, torch.Tensor] | None = None
) -> dict[str, torch.nn.Parameter]:
    """Replace every parameter by ``param[rows]`` followed by ``new_rows[name]`` (if given),
    keeping Adam's moments of the kept rows and zero moments for the new ones. Returns the
    new parameters by name (each group of ``optimizer`` holds one, named ``group["name"]``)."""
    params = {}
    for group in optimizer.param_groups:
        old = group["params"][0]
        extra = [] if new_rows is None else [new_rows[group["name"]].to(old.dtype)]
        new = torch.nn.Parameter(torch.cat([old.detach()[rows]] + extra))
        state = optimizer.state.pop(old, None)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                state[key] = torch.cat([state[key][rows]] + [torch.zeros_like(e) for e in extra])
            optimizer.state[new] = state
        group["params"][0] = new
        params[group["name"]] = new
    return params


def split_rows(
    params: dict[str, torch.Tensor], index: torch.Tensor, generator: torch.Generator
) -> dict[str, torch.Tensor]:
    """The children of the Gaussians ``index``: SPLIT_CHILDREN each, means drawn from the
    parent's Gaussian (seeded by ``generator``), scales / SPLIT_SHRINK, the rest copied."""
    rows = {name: p.detach()[index].repeat_interleave(SPLIT_CHILDREN, dim=0) for name, p in params.items()}
    scales = rows["log_scales"].exp()
    offset = torch.randn(scales.shape, generator=generator, dtype=scales.dtype) * scales  # in the local frame
    rows["means"] = rows["means"] + (quat_to_rotmat(rows["quats"]) @ offset[..., None])[..., 0]
    rows["log_scales"] = torch.log(scales / SPLIT_SHRINK)
    return rows


def densify_and_prune(
    optimizer: torch.optim.Adam,
    stats: ViewSpaceStats,
    extent: float,
    settings: DensifySettings,
    *,
    prune_large: bool,
    generator: torch.Generator,
) -> tuple[dict[str, torch.nn.Parameter], dict[str, int]]:
    """Clone, split, then prune (see the module docstring); ``extent`` is the scene radius
    (m), ``prune_large`` enables the screen- and world-size prunes. Returns the new
    parameters and the counts {"cloned", "split", "pruned", "gaussians"}."""
    params = {g["name"]: g["params"][0] for g in optimizer.param_groups}
    with torch.no_grad():
        hot = stats.mean_grad() >= settings.grad_threshold
        largest = params["log_scales"].exp().amax(dim=-1)
        small = largest <= settings.percent_dense * extent
        clone, split = hot & small, hot & ~small
        new = {name: p.detach()[clone] for name, p in params.items()}
        children = split_rows(params, torch.nonzero(split)[:, 0], generator)
        new = {name: torch.cat([new[name], children[name]]) for name in new}
        params = rebuild(optimizer, ~split, new)  # parents of splits go, clones and children come
        largest = params["log_scales"].exp().amax(dim=-1)
        prune = torch.sigmoid(params["opacity_logits"]) < settings.min_opacity
        if prune_large:
            kept_radius = stats.max_radius[~split]
            radius = torch.cat([kept_radius, torch.zeros(len(largest) - len(kept_radius), dtype=kept_radius.dtype)])
            prune |= (radius > settings.max_screen_radius) | (largest > settings.max_world_scale * extent)
        params = rebuild(optimizer, ~prune)
    counts = {
        "cloned": int(clone.sum()),
        "split": int(split.sum()),
        "pruned": int(prune.sum()),
        "gaussians": params["means"].shape[0],
    }
    return params, counts


def reset_opacities(optimizer: torch.optim.Adam, ceiling: float = 0.01) -> None:
    """Clamp every opacity to at most ``ceiling`` and zero its Adam moments (3DGS's reset)."""
    for group in optimizer.param_groups:
        if group["name"] == "opacity_logits":
            p = group["params"][0]
            with torch.no_grad():
                p.clamp_(max=torch.logit(torch.tensor(ceiling, dtype=p.dtype)).item())
            for moment in optimizer.state.get(p, {}).values():
                if moment.dim():  # the moments, not the step counter
                    moment.zero_()
