"""Particle sets for the simulator: built-in shapes filled on a lattice, and particle files.

Positions in metres; every particle gets the rest volume spacing^3 of its lattice cell.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from clflow.errors import InputError
from clflow.fileio import load_arrays

SHAPES = ("box", "sphere", "torus")


def lattice_fill(shape: str, size: float, center, spacing: float) -> torch.Tensor:
    """[N, 3] float64 lattice points (spacing, m) inside a shape of extent ``size`` (m) at
    ``center``: a cube of side size, a sphere of diameter size, or a torus of outer diameter
    size (tube radius size/6, axis +y)."""
    if shape not in SHAPES:
        raise InputError(f"unknown shape {shape!r}; choose one of {', '.join(SHAPES)}")
    if not (size > 0 and spacing > 0 and math.isfinite(size) and math.isfinite(spacing)):
        raise InputError(f"shape size and spacing must be positive lengths (m), got {size}, {spacing}")
    n = max(1, int(round(size / spacing)))
    axis = (torch.arange(n, dtype=torch.float64) + 0.5) * spacing - n * spacing / 2
    p = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    if shape == "sphere":
        p = p[p.norm(dim=1) <= size / 2]
    elif shape == "torus":
        tube = size / 6
        ring = size / 2 - tube
        radial = torch.sqrt(p[:, 0] ** 2 + p[:, 2] ** 2)
        p = p[(radial - ring) ** 2 + p[:, 1] ** 2 <= tube**2]
    if p.shape[0] == 0:
        raise InputError(f"a {shape} of size {size} m holds no particle at spacing {spacing} m")
    return p + torch.tensor(center, dtype=torch.float64)


def _read_ply_vertices(path: Path) -> np.ndarray:
    """x, y, z of the vertex element of an ASCII or binary little-endian PLY file."""
    types = {
        "char": "i1",
        "uchar": "u1",
        "short": "i2",
        "ushort": "u2",
        "int": "i4",
        "uint": "u4",
        "float": "f4",
        "double": "f8",
        "int8": "i1",
        "uint8": "u1",
        "int16": "i2",
        "uint16": "u2",
        "int32": "i4",
        "uint32": "u4",
        "float32": "f4",
        "float64": "f8",
    }
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise InputError(f"{path}: not a PLY file (no 'ply' magic line)")
        fmt, elements, current = None, [], None
        while True:
            line = f.readline()
            if not line:
                raise InputError(f"{path}: PLY header has no end_header")
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                current = (words[1], int(words[2]), [])
                elements.append(current)
            elif words[0] == "property":
                if words[1] == "list":
                    current[2].append((words[4], None))
                else:
                    if words[1] not in types:
                        raise InputError(f"{path}: unsupported PLY property type {words[1]!r}")
                    current[2].append((words[2], types[words[1]]))
            elif words[0] == "end_header":
                break
        if not elements or elements[0][0] != "vertex":
            raise InputError(f"{path}: the first PLY element must be 'vertex'")
        _, count, props = elements[0]
        if any(t is None for _, t in props):
            raise InputError(f"{path}: list properties in the vertex element are not supported")
        names = [name for name, _ in props]
        if not {"x", "y", "z"} <= set(names):
            raise InputError(f"{path}: vertex element lacks x, y, z (has {', '.join(names)})")
        if fmt == "ascii":
            data = np.loadtxt(f, max_rows=count, ndmin=2)
            cols = [data[:, names.index(a)] for a in "xyz"]
        elif fmt == "binary_little_endian":
            dtype = np.dtype([(name, "<" + t) for name, t in props])
            data = np.fromfile(f, dtype=dtype, count=count)
            if data.shape[0] != count:
                raise InputError(f"{path}: truncated PLY: {data.shape[0]} of {count} vertices")
            cols = [data[a] for a in "xyz"]
        else:
            raise InputError(f"{path}: PLY format {fmt!r} not supported (ascii or binary_little_endian)")
    return np.stack(cols, 1).astype(np.float64)


#: the particle files load_particles reads
PARTICLE_SUFFIXES = (".npz", ".ply")


def load_particles(path: str | Path) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Positions [N, 3] (m) and, if the file has them, volumes [N] (m^3) from an .npz
    ('positions' or 'x', optional 'volume') or a .ply (vertex x, y, z)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"particle file not found: {path}")
    volume = None
    if path.suffix.lower() == ".npz":
        data = load_arrays(path, "particle file")
        key = next((k for k in ("positions", "x") if k in data), None)
        if key is None:
            raise InputError(f"{path}: no 'positions' (or 'x') array; it has {', '.join(data) or 'none'}")
        x = np.asarray(data[key], dtype=np.float64)
        if "volume" in data:
            volume = torch.from_numpy(np.asarray(data["volume"], dtype=np.float64).reshape(-1))
    elif path.suffix.lower() == ".ply":
        x = _read_ply_vertices(path)
    else:
        raise InputError(f"{path}: particle files must be {' or '.join(PARTICLE_SUFFIXES)}")
    if x.ndim != 2 or x.shape[1] != 3:
        raise InputError(f"{path}: positions must have shape [N, 3], got {list(x.shape)}")
    if x.shape[0] == 0:
        raise InputError(f"{path}: the particle set is empty")
    if not np.isfinite(x).all():
        raise InputError(f"{path}: positions contain NaN or inf")
    return torch.from_numpy(x), volume
