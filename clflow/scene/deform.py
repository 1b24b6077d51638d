"""Gaussians moved and deformed by a simulation (PhysGaussian's kinematics).

An object Gaussian i that is simulated as particle i moves with it and is deformed by its
deformation gradient F_i: mean x_i, covariance F_i Sigma_i F_i^T. Its SH colours stay in
the rest frame, so the view direction is rotated back by R_i^T, R_i the rotation of F_i's
polar decomposition F = R S (the rasteriser's ``sh_rotations``)::

    moved = rest.deformed(x, F, polar_rotations(F))   # clflow.splat.gaussians.Gaussians
"""

from __future__ import annotations

import torch

from clflow.runtime.bridge import bind


def polar_rotations(F: torch.Tensor) -> torch.Tensor:
    """R of the polar decomposition F = R S, [N, 3, 3] for F [N, 3, 3] (float32 or float64):
    a proper rotation even for det F <= 0 (inverted or flattened elements). The OpenCL SVD
    of the simulator (kernels_cl/common/svd3.h, 8 matrices per work-item), faster than torch's
    batched SVD (docs/splat_io.md). Not differentiated: colours do not enter
    the flow loss, and the SVD's gradient is singular at F = I, the rest state."""
    import numpy as np

    from clflow.mpm.constants import SIMD_LANES
    from clflow.runtime import get_device
    from clflow.runtime.arrays import real_of

    device = get_device()
    real = real_of(F.dtype, "deformation gradients")
    kernel = device.kernel("common/svd3.cl", "polar_rotation", real, {"CLFLOW_SIMD_LANES": SIMD_LANES})
    F = F.detach().contiguous()
    R = torch.empty_like(F)
    n = F.shape[0]
    if n:
        with bind(device) as b:
            device.launch(kernel, -(-n // SIMD_LANES), dict(n=np.int32(n), F=b.input(F, "F"), R=b.output(R, "R")))
    return R
