"""3DGS PLY files (INRIA / gsplat / nerfstudio layout) and plain point-cloud PLY files.

The 3DGS file has one ``vertex`` element of float32 properties in this order::

    x y z nx ny nz f_dc_0..2 f_rest_0..(3(K-1)-1) opacity scale_0..2 rot_0..3

with K = (d+1)^2 SH coefficients per channel (degree d = 0..3, inferred from the f_rest
count), f_rest channel-major (f_rest[c (K-1) + k-1] is basis k of channel c), opacity a
logit, scales logs and rot an unnormalised w, x, y, z quaternion. :func:`save_ply` writes
exactly this layout (normals zero), so INRIA's, gsplat's and nerfstudio's loaders read it;
extra per-Gaussian features follow as further float properties.

:func:`load_ply` reads binary (little- or big-endian) and ASCII files. A file without the
3DGS attributes but with ``x y z`` (and optionally ``red green blue``) is read as a point
cloud and turned into isotropic Gaussians (:meth:`Gaussians.from_points`).
"""

from __future__ import annotations

import os

import numpy as np
import torch
from numpy.lib.recfunctions import structured_to_unstructured

from clflow.errors import InputError
from clflow.splat.gaussians import Gaussians
from clflow.splat.ply_format import COLOR_NAMES, read_ply_vertices, write_ply_vertices
from clflow.splat.sh import rgb_to_sh0, sh_degree_of


def gaussian_property_names(sh_degree: int, feature_names: tuple[str, ...] = ()) -> list[str]:
    """The 3DGS vertex properties in file order for SH degree ``sh_degree``, then the features."""
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
        + list(feature_names)
    )


def require_gaussians(gaussians: Gaussians, path: str | os.PathLike) -> Gaussians:
    """``gaussians`` read from ``path``; InputError when there are none (an empty PLY: nothing
    to render, select or simulate)."""
    if len(gaussians) == 0:
        raise InputError(f"{path}: holds no Gaussians")
    return gaussians


def load_ply(path: str | os.PathLike, *, point_scale: float | None = None, point_opacity: float = 0.1) -> Gaussians:
    """Read Gaussians from a 3DGS PLY file, a compressed one (SuperSplat / PlayCanvas,
    :mod:`clflow.splat.compressed_ply`), or a plain ``x y z [red green blue]`` point cloud.

    Values are float32 (the file's precision). Vertex properties beyond the 3DGS set
    (other than normals) become ``features`` named after them. A point cloud becomes
    isotropic degree-0 Gaussians, see :meth:`Gaussians.from_points` for ``point_scale`` (m)
    and ``point_opacity``.

    Raises :class:`InputError` naming the file for malformed or truncated files, missing
    attributes, non-finite values, degenerate quaternions and scales that are 0 after exp.
    """
    from clflow.splat.compressed_ply import is_compressed_ply, load_compressed_ply

    if is_compressed_ply(path):
        return load_compressed_ply(path)
    table = read_ply_vertices(path)
    where = str(path)
    names = list(table.dtype.names)
    values = _float32_matrix(table)  # [N, P], one column per property
    finite = np.isfinite(values)
    if not finite.all():
        j = int(np.flatnonzero(~finite.all(axis=0))[0])
        bad = np.flatnonzero(~finite[:, j])
        raise InputError(
            f"{where}: attribute '{names[j]}' has {len(bad)} non-finite values "
            f"(first: vertex {bad[0]}, {values[bad[0], j]})"
        )
    missing_xyz = [a for a in ("x", "y", "z") if a not in names]
    if missing_xyz:
        raise InputError(f"{where}: vertex element has no {', '.join(missing_xyz)} (properties: {', '.join(names)})")
    column = {name: j for j, name in enumerate(names)}

    def take(keys: list[str]) -> torch.Tensor:  # [N, len(keys)] float32
        return torch.from_numpy(values[:, [column[k] for k in keys]])

    splat_keys = [
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
    ]
    if not any(key in column for key in splat_keys):
        return _points_to_gaussians(table, take, where, point_scale, point_opacity)
    missing = [key for key in splat_keys if key not in column]
    if missing:
        raise InputError(f"{where}: 3DGS PLY is missing attributes: {', '.join(missing)}")
    rest_names = sorted((k for k in names if k.startswith("f_rest_")), key=lambda k: int(k[7:]))
    if rest_names != [f"f_rest_{i}" for i in range(len(rest_names))]:
        raise InputError(f"{where}: f_rest_* attributes are not numbered 0..{len(rest_names) - 1}")
    if len(rest_names) % 3:
        raise InputError(f"{where}: {len(rest_names)} f_rest attributes is not a multiple of 3 (R, G, B)")
    try:
        degree = sh_degree_of(len(rest_names) // 3 + 1)
    except InputError as exc:
        raise InputError(f"{where}: {len(rest_names)} f_rest attributes: {exc}") from None
    n = len(table)
    dc = take(["f_dc_0", "f_dc_1", "f_dc_2"])  # [N, 3]
    rest = take(rest_names).reshape(n, 3, len(rest_names) // 3).transpose(1, 2)  # channel-major in the file
    known = set(gaussian_property_names(degree))
    feature_names = tuple(k for k in names if k not in known)
    gaussians = Gaussians(
        means=take(["x", "y", "z"]),
        quats=take(["rot_0", "rot_1", "rot_2", "rot_3"]),
        log_scales=take(["scale_0", "scale_1", "scale_2"]),
        opacity_logits=take(["opacity"])[:, 0].contiguous(),
        sh=torch.cat([dc[:, None, :], rest], dim=1),
        features=take(list(feature_names)) if feature_names else None,
        feature_names=feature_names,
    )
    return gaussians.validate(where)


def save_ply(path: str | os.PathLike, gaussians: Gaussians, *, ascii: bool = False) -> None:
    """Write ``gaussians`` as a 3DGS PLY file (float32, the layout in the module docstring), atomically.

    Gaussians with plain RGB ``colors`` [N, 3] (in [0, 1]) are written as degree-0 SH;
    deformed or turned ones are refused (:meth:`Gaussians.check_undeformed`).
    """
    gaussians.check_undeformed(str(path))
    g = gaussians.detach().to(dtype=torch.float32, device="cpu")
    if g.sh is not None:
        sh = g.sh
    elif g.colors.shape[1] == 3:
        sh = rgb_to_sh0(g.colors)[:, None, :]
    else:
        raise InputError(f"{path}: a 3DGS PLY stores RGB; these Gaussians have {g.colors.shape[1]} colour channels")
    n = len(g)
    rest = sh[:, 1:, :].transpose(1, 2).flatten(1)  # channel-major
    values = torch.cat(
        [g.means, torch.zeros(n, 3), sh[:, 0, :], rest, g.opacity_logits[:, None], g.log_scales, g.quats]
        + ([g.features] if g.features is not None else []),
        dim=1,
    ).numpy()
    names = gaussian_property_names(sh_degree_of(sh.shape[1]), g.feature_names)
    clashes = sorted({name for name in g.feature_names if names.count(name) > 1})
    if clashes:
        raise InputError(f"{path}: feature names {', '.join(clashes)} clash with 3DGS attributes or repeat")
    table = values.view(np.dtype([(name, "<f4") for name in names]))[:, 0]  # rows as records, no copy
    write_ply_vertices(path, table, ascii=ascii)


def _float32_matrix(table: np.ndarray) -> np.ndarray:
    """[N, P] float32 of a structured array's P fields (a view when they all are float32)."""
    if all(table.dtype[name] == np.float32 for name in table.dtype.names):
        return table.view(np.float32).reshape(len(table), len(table.dtype.names))
    return structured_to_unstructured(table, dtype=np.float32)


def _points_to_gaussians(table: np.ndarray, take, where: str, scale: float | None, opacity: float) -> Gaussians:
    rgb = None
    for names in COLOR_NAMES:
        present = [k for k in names if k in table.dtype.names]
        if present and len(present) < 3:
            raise InputError(f"{where}: point colours need all of {', '.join(names)}, found {', '.join(present)}")
        if present:
            # Integer colours are 0..max of their type (uchar: 255); float colours are in [0, 1].
            kind = table.dtype[names[0]]
            full = float(np.iinfo(kind).max) if np.issubdtype(kind, np.integer) else 1.0
            rgb = take(list(names)) / full
            break
    try:
        return Gaussians.from_points(take(["x", "y", "z"]), rgb, scale=scale, opacity=opacity)
    except InputError as exc:
        raise InputError(f"{where}: point cloud: {exc}") from None
