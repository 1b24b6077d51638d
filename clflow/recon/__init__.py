"""Reconstruction: 3D Gaussians trained from posed images on clflow's rasteriser (3DGS recipe).

    from clflow.recon import Settings, load_views, reconstruct
    result = reconstruct(load_views("scene/images"), "out", Settings(iterations=7000))

Cameras from a NeRF transforms.json, a COLMAP sparse model (:mod:`clflow.recon.colmap`) or a
3DGS cameras.json (:mod:`clflow.recon.views`); the training loop and its outputs in
:mod:`clflow.recon.train`; densification in :mod:`clflow.recon.densify`. Importing this
package builds no OpenCL kernels.
"""

from clflow.recon.train import Result, Settings, reconstruct
from clflow.recon.views import View, ViewSet, load_views

__all__ = ["Result", "Settings", "View", "ViewSet", "load_views", "reconstruct"]
