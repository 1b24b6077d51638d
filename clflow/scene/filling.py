"""Particles from the Gaussians of an object: its Gaussians plus particles filling the inside.

3DGS places Gaussians on surfaces only, so a simulation of their centres alone would be a
hollow shell. The inside is found on a voxel grid whose side is ``spacing`` (m) times an
integer k, the smallest for which the surface's sampling gap (the 90th percentile of the
Gaussians' nearest-neighbour distances) spans at most CLOSED_GAP voxels: finer voxels would
let the flood fill below leak through the gaps between Gaussians and leave the object hollow.
Each voxel then receives (k per_axis)^3 particles, so the particle spacing stays
``spacing / per_axis`` whatever the surface sampling:

1. shell: each Gaussian marks the voxels of its centre and of points at +-1 and +-2 standard
   deviations along its three axes (reach capped at ``max_reach`` voxels, so a degenerate,
   huge Gaussian costs the same bounded work as any other); transparent Gaussians
   (opacity < ``min_opacity``) mark nothing;
2. the shell is closed by ``closing`` voxels of dilation so small gaps do not let the
   outside leak in;
3. outside = flood fill from the grid border through voxels off the closed shell; the
   voxels neither outside nor on the closed shell are the interior; they and the shell
   voxels nearer to the interior than to the outside (the surface runs through the middle
   of the shell) receive ``per_axis^3`` particles each on a regular sub-grid, besides the
   Gaussian centres on the surface.

Every particle (Gaussian centres first, then fill particles) gets the same rest volume:
the object's volume (interior voxels plus the shell voxels nearer to the interior than to
the outside: the surface runs through the middle of the shell) divided by the particle
count.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as nnf

from clflow.errors import InputError
from clflow.limits import check_memory

MAX_VOXELS = 256**3  # refuse grids larger than this (memory/time); choose a larger spacing
FILL_BYTES = 96  # bytes of memory at the peak per fill particle (its sub-grid points, float64, and copies)
# widest gap between neighbouring Gaussians, in voxels, that the shell marks below close
# (docs/pipeline.md, "Modules": what closes and what leaks)
CLOSED_GAP = 2.5


@dataclass
class ObjectParticles:
    """Particles of an object (or of several: clflow.pipeline.simulation.setup_object).
    positions [M, 3] (m): rows 0..n_gaussians-1 are the Gaussians' centres, the rest fill
    particles; volume: rest volume of each particle (m^3), a number or [M]."""

    positions: torch.Tensor
    n_gaussians: int
    volume: float | torch.Tensor

    @property
    def n_fill(self) -> int:
        return self.positions.shape[0] - self.n_gaussians


def _grow(region: torch.Tensor) -> torch.Tensor:
    """``region`` plus its 6-connected neighbours (bool [nx, ny, nz])."""
    grown = region.clone()
    grown[1:] |= region[:-1]
    grown[:-1] |= region[1:]
    grown[:, 1:] |= region[:, :-1]
    grown[:, :-1] |= region[:, 1:]
    grown[:, :, 1:] |= region[:, :, :-1]
    grown[:, :, :-1] |= region[:, :, 1:]
    return grown


def _dilate(region: torch.Tensor, voxels: int) -> torch.Tensor:
    """``region`` grown by ``voxels`` in every direction (a cube structuring element)."""
    if voxels <= 0:
        return region
    k = 2 * voxels + 1
    return nnf.max_pool3d(region[None, None].float(), k, stride=1, padding=voxels)[0, 0] > 0


def _object_voxels(
    interior: torch.Tensor, outside: torch.Tensor, closed: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(inside, tie) bool [nx, ny, nz]: the object's voxels, the interior plus the
    closed-shell voxels nearer to the interior than to the outside (the surface runs through
    the middle of the shell), and the shell voxels as near to both (half inside). A shell
    with no interior (a thin sheet) is all ties."""
    if not bool(interior.any()):
        return interior.clone(), closed.clone()
    reached_in, reached_out = interior.clone(), outside.clone()
    tie = torch.zeros_like(interior)
    while True:
        new_in = _grow(reached_in) & closed & ~reached_in & ~reached_out
        new_out = _grow(reached_out) & closed & ~reached_out & ~reached_in
        if not bool(new_in.any() or new_out.any()):
            return reached_in, tie
        both = new_in & new_out
        tie |= both
        reached_in |= new_in & ~both
        reached_out |= new_out


def surface_gap(centres: torch.Tensor) -> float:
    """The 90th percentile (m) of the distances from each of ``centres`` [N, 3] (m) to its
    nearest neighbour: how far apart the Gaussians sample the surface (0 for N < 2)."""
    from scipy.spatial import cKDTree

    if centres.shape[0] < 2:
        return 0.0
    points = centres.numpy()
    distances, _ = cKDTree(points).query(points, k=2)
    return float(torch.quantile(torch.from_numpy(distances[:, 1]), 0.9))


def fill_object(
    means: torch.Tensor,
    covariances: torch.Tensor,
    opacities: torch.Tensor,
    spacing: float,
    *,
    per_axis: int = 2,
    min_opacity: float = 0.1,
    max_reach: int = 3,
    closing: int = 1,
) -> ObjectParticles:
    """Fill the object outlined by Gaussians (means [N, 3] m, covariances [N, 3, 3] m^2,
    opacities [N]) with particles on a grid of ``spacing`` m (see module docstring)."""
    if means.shape[0] == 0:
        raise InputError("the object selection is empty: no Gaussians to fill")
    if not (spacing > 0 and math.isfinite(spacing)):
        raise InputError(f"fill spacing must be a positive length in metres, got {spacing}")
    if per_axis < 1:
        raise InputError(f"fill particles per axis must be >= 1, got {per_axis}")
    means64 = means.detach().double()
    extent = means64.max(0).values - means64.min(0).values
    needed = torch.ceil(extent / spacing).long() + 1
    if int(needed.prod()) > MAX_VOXELS:
        raise InputError(
            f"filling needs a {needed.tolist()} voxel grid at spacing {spacing} m (more than "
            f"{round(MAX_VOXELS ** (1 / 3))}^3); use a larger spacing"
        )
    visible = opacities.detach() >= min_opacity
    k = max(1, math.ceil(surface_gap(means64[visible]) / (CLOSED_GAP * spacing) - 1e-9))
    spacing, per_axis = spacing * k, per_axis * k
    pad = closing + 2
    lower = means64.min(0).values - pad * spacing
    dims = torch.ceil((means64.max(0).values + pad * spacing - lower) / spacing).long() + 1
    nx, ny, nz = dims.tolist()

    centres = means64[visible]
    variances, axes = torch.linalg.eigh(covariances.detach()[visible].double())  # axes: columns
    sigma = variances.clamp(min=0).sqrt()
    reach = sigma.clamp(max=max_reach * spacing / 2).unsqueeze(1)  # [n, 1, 3]: capped std devs
    offsets = [torch.zeros(1, 3, dtype=torch.float64)]
    for k in (-2.0, -1.0, 1.0, 2.0):
        offsets.append(k * torch.eye(3, dtype=torch.float64))
    factors = torch.cat(offsets)  # [13, 3]: multiples of each axis' standard deviation
    points = centres.unsqueeze(1) + torch.einsum("kj,nij->nki", factors * 1.0, axes * reach)
    cells = torch.floor((points.reshape(-1, 3) - lower) / spacing).long()
    cells = torch.maximum(torch.minimum(cells, dims - 1), torch.zeros(3, dtype=torch.long))
    shell = torch.zeros(nx, ny, nz, dtype=torch.bool)
    shell[cells[:, 0], cells[:, 1], cells[:, 2]] = True

    closed = _dilate(shell, closing)
    outside = torch.zeros_like(shell)
    outside[[0, -1], :, :] = True
    outside[:, [0, -1], :] = True
    outside[:, :, [0, -1]] = True
    outside &= ~closed
    while True:  # 6-connected flood fill through empty voxels
        grown = _grow(outside) & ~closed
        if torch.equal(grown, outside):
            break
        outside = grown
    interior = ~outside & ~closed
    inside, tie = _object_voxels(interior, outside, closed)
    count = int(inside.sum()) * per_axis**3
    check_memory(
        count * FILL_BYTES,
        f"filling the object with {count:,} particles",
        "use a larger fill spacing or fewer particles per axis (fill.per_axis)",
    )
    fill_cells = inside.nonzero().double()  # [M, 3]
    sub = (torch.arange(per_axis, dtype=torch.float64) + 0.5) / per_axis
    sub = torch.stack(torch.meshgrid(sub, sub, sub, indexing="ij"), -1).reshape(-1, 3)
    fill = (lower + spacing * (fill_cells.unsqueeze(1) + sub)).reshape(-1, 3)
    positions = torch.cat([means64, fill]).to(means.dtype)
    object_volume = (float(inside.sum()) + 0.5 * float(tie.sum())) * spacing**3
    volume = object_volume / positions.shape[0]
    return ObjectParticles(positions=positions, n_gaussians=means.shape[0], volume=volume)
