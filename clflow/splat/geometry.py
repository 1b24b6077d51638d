"""The geometry of Gaussians as tensors: wxyz quaternions and rotation matrices both ways,
covariances Sigma = R diag(s)^2 R^T and their deformation F Sigma F^T, and the spacing of a
point cloud (3DGS's initial scales)."""

from __future__ import annotations

import numpy as np
import torch


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] of wxyz quaternions [N, 4] (normalised here)."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(quats.shape[:-1] + (3, 3))


def covariances_of(scales: torch.Tensor, rotations: torch.Tensor) -> torch.Tensor:
    """Sigma = R diag(s)^2 R^T, [N, 3, 3] (m^2), from scales [N, 3] (m) and rotation
    matrices [N, 3, 3]."""
    rs = rotations * scales.unsqueeze(-2)  # R diag(s)
    return rs @ rs.transpose(-1, -2)


def deformed_covariances(rest: torch.Tensor, F: torch.Tensor) -> torch.Tensor:
    """F Sigma F^T, [N, 3, 3], for rest covariances [N, 3, 3] and deformation gradients F."""
    return F @ rest @ F.transpose(-1, -2)


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """wxyz quaternions [N, 4] of proper rotation matrices [N, 3, 3] (Shepperd's method)."""
    m = R
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cand = torch.stack(
        [
            torch.stack([1 + trace, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]], -1),
            torch.stack(
                [
                    m[:, 2, 1] - m[:, 1, 2],
                    1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
                    m[:, 0, 1] + m[:, 1, 0],
                    m[:, 0, 2] + m[:, 2, 0],
                ],
                -1,
            ),
            torch.stack(
                [
                    m[:, 0, 2] - m[:, 2, 0],
                    m[:, 0, 1] + m[:, 1, 0],
                    1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2],
                    m[:, 1, 2] + m[:, 2, 1],
                ],
                -1,
            ),
            torch.stack(
                [
                    m[:, 1, 0] - m[:, 0, 1],
                    m[:, 0, 2] + m[:, 2, 0],
                    m[:, 1, 2] + m[:, 2, 1],
                    1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2],
                ],
                -1,
            ),
        ],
        1,
    )  # [N, 4 candidates, 4]; the one with the largest norm is the best conditioned
    best = cand.norm(dim=-1).argmax(dim=1)
    q = cand[torch.arange(R.shape[0]), best]
    return q / q.norm(dim=-1, keepdim=True)


def nearest_neighbour_rms(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """[N] root mean square distance (m) of each point to its ``k`` nearest other points
    (exact, with a KD-tree: scipy's cKDTree)."""
    from scipy.spatial import cKDTree

    xyz = points.detach().cpu().double().numpy()
    k = min(k, len(xyz) - 1)
    # k + 1 nearest include the point itself (distance 0); a duplicate point is a neighbour at 0.
    distances, _ = cKDTree(xyz).query(xyz, k=k + 1)
    rms = np.sqrt(np.mean(np.square(distances[:, 1:]), axis=1))
    return torch.from_numpy(rms).to(points.dtype)
