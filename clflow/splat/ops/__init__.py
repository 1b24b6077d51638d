"""Differentiable tile-based Gaussian splat rasteriser over OpenCL kernels (kernels_cl/splat/).

Pipeline of :func:`rasterize_gaussians`, one view:

1. ``clflow::splat_covariances``: Sigma = R(q) S S^T R(q)^T (covariance.cl), unless given;
   colours from SH in torch (sh.py);
2. ``clflow::splat_project``: EWA projection, culling, radii (project.cl);
3. tile lists sorted by (tile, depth) on the device (binning.py, binning.cl, sort.cl);
4. ``clflow::splat_composite``: per-tile front-to-back compositing of every channel
   (colours, extra features, depth) with early termination, in the shape the device's
   kernel plan picks (clflow.runtime.plan: rasterize_tile_rows.cl for CPUs, rasterize_workgroup.cl for GPUs).

Both ops have OpenCL adjoints (back to front for compositing); per-Gaussian gradients are
summed from per-(tile, Gaussian) slots in a fixed order, so they are deterministic.

One module per op (``covariance``, ``projection``, ``compositing``: the custom op, its fake
shapes, its adjoint) and one for the function that checks its inputs and puts the ops
together (``rasterization``); every name is here as well.
"""

from clflow.splat.ops.compositing import (
    ENTRY_FIELDS,
    MAX_RASTER_LOCAL_BYTES,
    TILE_PIXELS,
    composite,
    composite_backward,
    entry_record_bytes,
)
from clflow.splat.ops.covariance import covariances, covariances_backward
from clflow.splat.ops.projection import project, project_backward
from clflow.splat.ops.rasterization import (
    ORTHONORMAL_TOL,
    assemble_channels,
    rasterize_gaussians,
    split_outputs,
    view_directions,
)

__all__ = [
    "ENTRY_FIELDS",
    "MAX_RASTER_LOCAL_BYTES",
    "ORTHONORMAL_TOL",
    "TILE_PIXELS",
    "assemble_channels",
    "composite",
    "composite_backward",
    "covariances",
    "covariances_backward",
    "entry_record_bytes",
    "project",
    "project_backward",
    "rasterize_gaussians",
    "split_outputs",
    "view_directions",
]
