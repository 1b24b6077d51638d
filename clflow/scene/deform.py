"""Gaussians moved and deformed by a simulation (PhysGaussian's kinematics).

An object Gaussian i that is simulated as particle i moves with it and is deformed by its
deformation gradient F_i: mean x_i, covariance F_i Sigma_i F_i^T. Its SH colours stay in
the rest frame, so the view direction is rotated back by R_i^T, R_i the rotation of F_i's
polar decomposition F = R S (the rasteriser's ``sh_rotations``).
"""

from __future__ import annotations

import torch


def rest_covariances(scales: torch.Tensor, rotations: torch.Tensor) -> torch.Tensor:
    """Sigma = R diag(s)^2 R^T, [N, 3, 3] (m^2), from scales [N, 3] (m) and rotation
    matrices [N, 3, 3]."""
    rs = rotations * scales.unsqueeze(-2)  # R diag(s)
    return rs @ rs.transpose(-1, -2)


def deformed_covariances(rest: torch.Tensor, F: torch.Tensor) -> torch.Tensor:
    """F Sigma F^T, [N, 3, 3], for rest covariances [N, 3, 3] and deformation gradients F."""
    return F @ rest @ F.transpose(-1, -2)


def polar_rotations(F: torch.Tensor) -> torch.Tensor:
    """R of the polar decomposition F = R S, [N, 3, 3] (a proper rotation even for det F < 0
    arising from inverted elements). Not differentiated: colours do not enter the flow loss,
    and the SVD's gradient is singular at F = I, the rest state."""
    with torch.no_grad():
        U, _, Vh = torch.linalg.svd(F.double())
        flip = torch.ones(F.shape[:-2] + (3,), dtype=torch.float64)
        flip[..., 2] = torch.sign(torch.det(U @ Vh))
        R = U @ torch.diag_embed(flip) @ Vh
    return R.to(F.dtype)
