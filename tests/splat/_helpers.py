"""Small random splat scenes shared by the rasteriser tests."""

import torch


def camera(width: int, height: int, focal: float, dtype=torch.float64):
    """OpenCV camera at the origin looking down +z: (viewmat [4,4], K [3,3])."""
    viewmat = torch.eye(4, dtype=dtype)
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    return viewmat, K


def random_scene(n: int, seed: int, dtype=torch.float64, opacity=(0.2, 0.9), spread=0.5, scale=(0.08, 0.2)):
    """n Gaussians around (0, 0, 3) m: means, quats, scales, opacities, colors [n, 3]."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1) * spread + torch.tensor([0.0, 0.0, 3.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * (scale[1] - scale[0]) + scale[0]
    opacities = torch.rand(n, generator=g, dtype=dtype) * (opacity[1] - opacity[0]) + opacity[0]
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    return means, quats, scales, opacities, colors


def rotations(n: int, seed: int, dtype=torch.float64):
    """n random rotation matrices [n, 3, 3]."""
    g = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=dtype))
    return q * torch.linalg.det(q).sign().reshape(-1, 1, 1)
