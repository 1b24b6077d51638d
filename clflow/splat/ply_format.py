"""The PLY file format itself: a header of elements and their properties, then binary
(little- or big-endian) or ASCII rows. clflow.splat.ply reads and writes 3DGS files with
it, clflow.splat.compressed_ply SuperSplat's compressed layout."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from clflow.errors import InputError
from clflow.fileio import atomic_path

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
    elements = {e.name: e for e in _read_header(path)[1]}
    if "vertex" not in elements:
        raise InputError(f"{Path(path)}: no 'vertex' element (elements: {', '.join(elements) or 'none'})")
    return [name for name, _ in elements["vertex"].properties]


def ply_comments(path: str | os.PathLike) -> list[str]:
    """The header's comment lines, each without its ``comment `` keyword, in file order."""
    return _read_header(path)[3]


def _read_header(path: str | os.PathLike) -> tuple[str, list[_Element], int, list[str]]:
    """:func:`_parse_header` of the first MAX_HEADER_BYTES of the file at ``path``."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(MAX_HEADER_BYTES)
    except OSError as exc:
        raise InputError(f"{path}: cannot read PLY file ({exc.strerror})") from None
    return _parse_header(head, path)


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
    fmt, elements, body_start, _ = _parse_header(data, path)
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
    path: str | os.PathLike, elements: dict[str, np.ndarray], *, ascii: bool = False, comments: tuple[str, ...] = ()
) -> None:
    """Write structured arrays as PLY elements in the order given (one property per field),
    atomically: binary little-endian, or ASCII (float32 in 9 significant digits); each of
    ``comments`` (one line each) a header comment."""
    header = ["ply", f"format {'ascii' if ascii else 'binary_little_endian'} 1.0"]
    header += [f"comment {comment}" for comment in comments]
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


def _parse_header(data: bytes, path: Path) -> tuple[str, list[_Element], int, list[str]]:
    """(format, elements, offset of the body, comments) of a PLY file's bytes ``data``."""
    if not data.startswith(b"ply"):
        raise InputError(f"{path}: not a PLY file (it does not start with 'ply')")
    match = re.search(rb"end_header\r?\n", data[:MAX_HEADER_BYTES])
    if match is None:
        raise InputError(f"{path}: malformed PLY header: no 'end_header' line in the first {MAX_HEADER_BYTES} bytes")
    fmt = None
    elements: list[_Element] = []
    comments: list[str] = []
    for number, raw in enumerate(data[: match.start()].decode("ascii", "replace").splitlines()[1:], start=2):
        words = raw.split()
        if words and words[0] == "comment":
            comments.append(raw.strip()[len("comment") :].strip())
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
    return fmt, elements, match.end(), comments


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
