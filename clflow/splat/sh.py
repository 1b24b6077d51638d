"""Real spherical harmonics of degree 0..3 (the 3DGS convention) evaluated in torch.

Colour = sum_k c_k Y_k(dir) + 0.5, clamped at 0, with coefficients [N, K, 3],
K = (degree + 1)^2 and dir a unit view direction (Gaussian centre minus camera centre);
the degree of a coefficient count, and the colour of degree-0 coefficients both ways.
"""

from __future__ import annotations

import torch

from clflow.errors import InputError

SH_C0 = 0.28209479177387814  # Y_0^0: RGB = SH_C0 * f_dc + 0.5 for degree 0
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """K = (degree + 1)^2 coefficients per colour channel."""
    return (degree + 1) ** 2


def sh_degree_of(num_coeffs: int) -> int:
    """The SH degree d with (d + 1)^2 == num_coeffs (0..3), else :class:`InputError`."""
    for degree in range(MAX_SH_DEGREE + 1):
        if (degree + 1) ** 2 == num_coeffs:
            return degree
    raise InputError(f"{num_coeffs} SH coefficients per channel is not (d+1)^2 for a degree d in 0..{MAX_SH_DEGREE}")


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """Degree-0 SH coefficient that renders as colour ``rgb`` (in [0, 1]) from every direction."""
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    """The view-independent colour of degree-0 coefficients (before clamping at 0)."""
    return sh0 * SH_C0 + 0.5


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """Basis values Y_k(dir): [N, 3] unit directions -> [N, (degree + 1)^2]."""
    x, y, z = dirs.unbind(-1)
    basis = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        basis += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        basis += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(basis, dim=-1)


def sh_to_rgb(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """RGB [N, 3] from SH coefficients [N, K, 3] seen along unit directions dirs [N, 3]."""
    basis = sh_basis(degree, dirs)  # [N, K]
    rgb = torch.einsum("nk,nkc->nc", basis, coeffs[:, : basis.shape[1]])
    return torch.clamp_min(rgb + 0.5, 0.0)


def _sample_directions(count: int) -> torch.Tensor:
    """``count`` unit directions [count, 3] (float64) spread over the sphere (Fibonacci
    lattice): a set on which the degree <= 3 basis has full column rank."""
    i = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / count
    phi = torch.pi * (3 - 5**0.5) * i
    r = (1 - z * z).sqrt()
    return torch.stack([r * phi.cos(), r * phi.sin(), z], -1)


def rotate_sh(coeffs: torch.Tensor, rotations: torch.Tensor, chunk: int = 8192) -> torch.Tensor:
    """SH coefficients [N, K, 3] turned by rotations R [N, 3, 3]: the result seen along d
    equals ``coeffs`` seen along R^T d (what the rasteriser's ``sh_rotations`` does), so a
    file without rotations shows the same colours. Returned in coeffs' dtype, computed in
    float64.

    Exact: a rotated function of degree <= L is again one of degree <= L, so its coefficients
    are the least-squares fit of its values at 2 (L + 1)^2 fixed directions, on which the
    basis has full column rank (equivalent to the Wigner-D matrices of each band). Degree 0
    does not change.
    """
    degree = round(coeffs.shape[1] ** 0.5) - 1
    if degree == 0 or coeffs.shape[0] == 0:
        return coeffs.clone()
    dirs = _sample_directions(2 * coeffs.shape[1])  # [M, 3]
    fit = torch.linalg.pinv(sh_basis(degree, dirs))  # [K, M]: values at dirs -> coefficients
    out = torch.empty_like(coeffs)
    for start in range(0, coeffs.shape[0], chunk):
        R = rotations[start : start + chunk].double()
        c = coeffs[start : start + chunk].double()
        turned = torch.einsum("nji,mj->nmi", R, dirs)  # R^T d for every Gaussian and direction
        values = sh_basis(degree, turned.reshape(-1, 3)).reshape(R.shape[0], dirs.shape[0], -1)  # [n, M, K]
        out[start : start + chunk] = (fit @ (values @ c)).to(coeffs.dtype)  # values at dirs, then fitted
    return out
