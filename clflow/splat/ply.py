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
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from numpy.lib.recfunctions import structured_to_unstructured

from clflow.errors import InputError
from clflow.fileio import atomic_path
from clflow.splat.gaussians import Gaussians, rgb_to_sh0, sh_degree_of

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
PLY_NAME_OF = {"f4": "float", "f8": "double", "u1": "uchar", "i4": "int", "u4": "uint"}  # types save writes
FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "ascii"}
MAX_HEADER_BYTES = 1 << 20
COLOR_NAMES = (("red", "green", "blue"), ("r", "g", "b"))


@dataclass
class _Element:
    name: str
    count: int
    properties: list[tuple[str, str]]  # (name, numpy type code); list properties are rejected
    has_list: bool = False


# -- the generic PLY layer -----------------------------------------------------------------


def read_ply_vertices(path: str | os.PathLike) -> np.ndarray:
    """The ``vertex`` element of a PLY file as a structured array [N], fields in file order.

    Fields keep the file's types (native byte order). Other elements (faces, ...) are
    skipped. Raises :class:`InputError` naming the file for a malformed header, a missing
    vertex element or truncated data.
    """
    return read_ply_elements(path, ("vertex",))["vertex"]


def ply_vertex_properties(path: str | os.PathLike) -> list[str]:
    """The vertex element's property names, read from the header alone (the first
    MAX_HEADER_BYTES of the file); InputError naming the file for a malformed header or no
    vertex element."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(MAX_HEADER_BYTES)
    except OSError as exc:
        raise InputError(f"{path}: cannot read PLY file ({exc.strerror})") from None
    elements = {e.name: e for e in _parse_header(head, path)[1]}
    if "vertex" not in elements:
        raise InputError(f"{path}: no 'vertex' element (elements: {', '.join(elements) or 'none'})")
    return [name for name, _ in elements["vertex"].properties]


def read_ply_elements(
    path: str | os.PathLike, wanted: tuple[str, ...], optional: tuple[str, ...] = ()
) -> dict[str, np.ndarray]:
    """The elements named ``wanted`` (and those of ``optional`` the file has) of a PLY file,
    each a structured array in the file's types (native byte order); the others are
    skipped. ASCII files give the vertex element only. Raises :class:`InputError` naming the file for a malformed header, a missing
    element, list properties before or in a wanted element, or truncated data."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read PLY file ({exc.strerror})") from None
    fmt, elements, body_start = _parse_header(data, path)
    names = [e.name for e in elements]
    wanted = tuple(wanted) + tuple(name for name in optional if name in names)
    for name in wanted:
        if name not in names:
            raise InputError(f"{path}: no '{name}' element (elements: {', '.join(names) or 'none'})")
        if elements[names.index(name)].has_list:
            raise InputError(f"{path}: the {name} element has list properties, which clflow does not read")
    if fmt == "ascii":
        if tuple(wanted) != ("vertex",):
            raise InputError(
                f"{path}: an ASCII PLY; clflow reads the {', '.join(wanted)} elements from binary files only"
            )
        return {
            "vertex": _read_ascii(
                data[body_start:], elements[: names.index("vertex")], elements[names.index("vertex")], path
            )
        }
    tables, offset = {}, body_start
    for element in elements[: 1 + max(names.index(name) for name in wanted)]:
        if element.has_list:
            raise InputError(
                f"{path}: element '{element.name}' before '{wanted[0]}' has list properties; not supported"
            )
        dtype = _dtype(element, fmt)
        if element.name in wanted:
            available = len(data) - offset
            if available < element.count * dtype.itemsize:
                plural = "vertices" if element.name == "vertex" else f"{element.name} entries"
                raise InputError(
                    f"{path}: truncated: the header declares {element.count} {plural} of {dtype.itemsize} bytes "
                    f"({element.count * dtype.itemsize} bytes) but only {max(available, 0)} bytes follow"
                )
            table = np.frombuffer(data, dtype=dtype, count=element.count, offset=offset)
            tables[element.name] = table.astype(_dtype(element, "="), copy=False)  # read-only view when already native
        offset += element.count * dtype.itemsize
    return tables


def write_ply_vertices(path: str | os.PathLike, table: np.ndarray, *, ascii: bool = False) -> None:
    """Write a structured array [N] as a PLY ``vertex`` element (one property per field), atomically.

    Binary little-endian by default (as every 3DGS trainer writes it), or ASCII with
    float32 values in 9 significant digits (enough to read back the same bits).
    """
    write_ply_elements(path, {"vertex": table}, ascii=ascii)


def write_ply_elements(
    path: str | os.PathLike, elements: dict[str, np.ndarray], *, ascii: bool = False, comment: str | None = None
) -> None:
    """Write structured arrays as PLY elements in the order given (one property per field),
    atomically: binary little-endian, or ASCII (float32 in 9 significant digits)."""
    header = ["ply", f"format {'ascii' if ascii else 'binary_little_endian'} 1.0"]
    header += [f"comment {comment}"] if comment else []
    bodies = []
    for name, table in elements.items():
        if table.dtype.names is None or table.ndim != 1:
            raise InputError(f"write_ply_elements takes 1-D structured arrays, got {table.dtype} {table.shape}")
        codes = [table.dtype[field].str[1:] for field in table.dtype.names]
        unknown = [f"{field} ({code})" for field, code in zip(table.dtype.names, codes) if code not in PLY_NAME_OF]
        if unknown:
            raise InputError(f"cannot write PLY properties of these types: {', '.join(unknown)}")
        header.append(f"element {name} {len(table)}")
        header += [f"property {PLY_NAME_OF[code]} {field}" for field, code in zip(table.dtype.names, codes)]
        if ascii:
            formats = ["%.9g" if c == "f4" else "%.17g" if c == "f8" else "%d" for c in codes]
            lines = [" ".join(f % v for f, v in zip(formats, row)) for row in table.tolist()]
            bodies.append(("\n".join(lines) + ("\n" if lines else "")).encode("ascii"))
        else:
            little = np.dtype([(field, "<" + code) for field, code in zip(table.dtype.names, codes)])
            bodies.append(table.astype(little, copy=False).tobytes())
    header.append("end_header")
    with atomic_path(path) as tmp:
        tmp.write_bytes(("\n".join(header) + "\n").encode("ascii") + b"".join(bodies))


def _parse_header(data: bytes, path: Path) -> tuple[str, list[_Element], int]:
    if not data.startswith(b"ply"):
        raise InputError(f"{path}: not a PLY file (it does not start with 'ply')")
    match = re.search(rb"end_header\r?\n", data[:MAX_HEADER_BYTES])
    if match is None:
        raise InputError(f"{path}: malformed PLY header: no 'end_header' line in the first {MAX_HEADER_BYTES} bytes")
    fmt = None
    elements: list[_Element] = []
    for number, raw in enumerate(data[: match.start()].decode("ascii", "replace").splitlines()[1:], start=2):
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        where = f"{path}: header line {number} {raw.strip()!r}"
        if words[0] == "format":
            if len(words) != 3 or words[1] not in FORMATS or words[2] != "1.0":
                raise InputError(f"{where}: expected 'format ascii|binary_little_endian|binary_big_endian 1.0'")
            fmt = FORMATS[words[1]]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise InputError(f"{where}: expected 'element NAME COUNT'")
            elements.append(_Element(words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise InputError(f"{where}: property before any element")
            if len(words) == 5 and words[1] == "list":
                elements[-1].has_list = True
            elif len(words) == 3 and words[1] in PLY_TYPES:
                if any(words[2] == name for name, _ in elements[-1].properties):
                    raise InputError(f"{where}: property '{words[2]}' appears twice in element '{elements[-1].name}'")
                elements[-1].properties.append((words[2], PLY_TYPES[words[1]]))
            else:
                raise InputError(f"{where}: expected 'property TYPE NAME' with a PLY scalar type")
        else:
            raise InputError(f"{where}: unknown header keyword {words[0]!r}")
    if fmt is None:
        raise InputError(f"{path}: malformed PLY header: no 'format' line")
    return fmt, elements, match.end()


def _dtype(element: _Element, byte_order: str) -> np.dtype:
    return np.dtype([(name, byte_order + code) for name, code in element.properties])


def _read_ascii(body: bytes, before: list[_Element], vertex: _Element, path: Path) -> np.ndarray:
    skip = sum(e.count for e in before)  # in ASCII every element instance is one line
    lines = body.split(b"\n", skip + vertex.count)[skip : skip + vertex.count]
    if len(lines) < vertex.count or (lines and not lines[-1].strip()):
        found = sum(1 for line in lines if line.strip())
        raise InputError(f"{path}: truncated: the header declares {vertex.count} vertices, found {found} lines")
    width = len(vertex.properties)
    try:
        values = np.array(b" ".join(lines).split(), dtype=np.float64)
    except ValueError:
        bad = next(i for i, line in enumerate(lines) if not _all_numbers(line))
        raise InputError(f"{path}: vertex {bad} has a value that is not a number: {lines[bad][:80]!r}") from None
    if values.size != vertex.count * width:
        bad = next(i for i, line in enumerate(lines) if len(line.split()) != width)
        raise InputError(f"{path}: vertex {bad} has {len(lines[bad].split())} values, the header declares {width}")
    values = values.reshape(vertex.count, width)
    table = np.empty(vertex.count, dtype=_dtype(vertex, "="))
    for j, (name, _) in enumerate(vertex.properties):
        table[name] = values[:, j]
    return table


def _all_numbers(line: bytes) -> bool:
    try:
        [float(word) for word in line.split()]
    except ValueError:
        return False
    return True


# -- Gaussians -----------------------------------------------------------------------------


def gaussian_property_names(sh_degree: int, feature_names: tuple[str, ...] = ()) -> list[str]:
    """The 3DGS vertex properties in file order for SH degree ``sh_degree``, then the features."""
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
        + list(feature_names)
    )


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
