"""Compressed 3DGS PLY files, the layout SuperSplat and PlayCanvas read (``*.compressed.ply``).

Gaussians are sorted along a Morton curve and cut into chunks of 256. The file holds three
binary little-endian elements::

    chunk  [ceil(N / 256)]  float  min_x min_y min_z max_x max_y max_z          (centres)
                                   min_scale_x..z max_scale_x..z                (log scales, in [-20, 20])
                                   min_r min_g min_b max_r max_g max_b          (0.5 + SH_C0 f_dc)
    vertex [N]              uint   packed_position  x 11 | y 10 | z 11 bits, within the chunk's bounds
                                   packed_rotation  2 bits: index of the largest |q_i| of the unit
                                                    quaternion (rot_0..3 order, made positive),
                                                    then the other three, each q sqrt(1/2) + 1/2 in 10 bits
                                   packed_scale     log scales as positions
                                   packed_color     r 8 | g 8 | b 8 (within the chunk's bounds) | opacity 8 bits
    sh     [N]              uchar  f_rest_0..3(K-1)-1 (degree >= 1 only; channel-major as in a
                                   3DGS PLY): byte = trunc(256 (f / 8 + 1/2)) clamped to 0..255

A field of b bits holds round(t (2^b - 1)) for t in [0, 1] the value's place between the
chunk's bounds; the SH bytes cover [-4, 4) in steps of 1/32 (values beyond are clipped).
Written here from the format's description (PlayCanvas's splat-transform is the reference).

Gaussians with an integer feature ``object`` (clflow's exports: each Gaussian's object,
-1 static) are written object by object, each object's along the Morton curve, and the
header says which runs of vertices are which object::

    comment clflow objects -1:5000 0:152 1:236       (value:count, in file order)

The layout has no room for another vertex property or element: the PlayCanvas engine reads
a file as compressed only when its elements and their properties are exactly the ones above,
and every reader skips comments.
"""

from __future__ import annotations

import math
import os
import re

import numpy as np
import torch

from clflow.errors import InputError
from clflow.splat.gaussians import Gaussians
from clflow.splat.ply_format import ply_comments, ply_vertex_properties, read_ply_elements, write_ply_elements
from clflow.splat.sh import SH_C0, rgb_to_sh0, sh_degree_of

CHUNK = 256  # Gaussians per chunk
POSITION_BITS = (11, 10, 11)  # x, y, z (also the log scales)
LOG_SCALE_LIMIT = 20.0  # chunk bounds of log scales are clamped to +-this
SH_RANGE = 4.0  # SH bytes span [-SH_RANGE, SH_RANGE)
CHUNK_FIELDS = ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
                "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z",
                "min_r", "min_g", "min_b", "max_r", "max_g", "max_b")  # fmt: skip
VERTEX_FIELDS = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
OBJECT_FEATURE = "object"  # the feature written as runs of vertices
OBJECT_COMMENT = "clflow objects"  # the header comment of those runs: OBJECT_COMMENT value:count ...


def morton_order(points: np.ndarray) -> np.ndarray:
    """Indices [N] sorting points [N, 3] along a Z-order curve (10 bits per axis in their
    bounding box), so that consecutive chunks are compact."""
    if not len(points):
        return np.zeros(0, np.int64)
    lo, hi = points.min(0), points.max(0)
    cells = ((points - lo) / np.where(hi > lo, hi - lo, 1.0) * 1023).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((cells[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + 2 - axis)
    return np.argsort(code, kind="stable")


def _unorm(t: np.ndarray, bits: int) -> np.ndarray:
    """t in [0, 1] (clipped) as a ``bits``-bit integer, rounded to nearest."""
    top = (1 << bits) - 1
    return np.clip(np.floor(t * top + 0.5), 0, top).astype(np.uint32)


def _chunk_bounds(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-chunk min and max [C, D] of values [N, D] (the last chunk may be short)."""
    starts = np.arange(0, len(values), CHUNK)
    return np.minimum.reduceat(values, starts), np.maximum.reduceat(values, starts)


def _pack_in_bounds(values: np.ndarray, lo: np.ndarray, hi: np.ndarray, bits: tuple[int, ...]) -> np.ndarray:
    """values [N, D] as one uint32 per row: each column's place between its chunk's bounds,
    in ``bits[d]`` bits, the first column highest."""
    chunk = np.arange(len(values)) // CHUNK
    span = hi[chunk] - lo[chunk]
    t = np.where(span > 0, (values - lo[chunk]) / np.where(span > 0, span, 1.0), 0.0)
    packed = np.zeros(len(values), np.uint32)
    for d, b in enumerate(bits):
        packed = (packed << np.uint32(b)) | _unorm(t[:, d], b)
    return packed


def _unpack_in_bounds(packed: np.ndarray, lo: np.ndarray, hi: np.ndarray, bits: tuple[int, ...]) -> np.ndarray:
    """The inverse of :func:`_pack_in_bounds`: [N, D] float64."""
    chunk = np.arange(len(packed)) // CHUNK
    out = np.empty((len(packed), len(bits)))
    shift = sum(bits)
    for d, b in enumerate(bits):
        shift -= b
        t = ((packed >> np.uint32(shift)) & np.uint32((1 << b) - 1)) / ((1 << b) - 1)
        out[:, d] = lo[chunk, d] + t * (hi[chunk, d] - lo[chunk, d])
    return out


def _pack_rotations(quats: np.ndarray) -> np.ndarray:
    """Unnormalised quaternions [N, 4] (rot_0..3 order) as 2-10-10-10 smallest-three uint32."""
    q = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    largest = np.abs(q).argmax(1)
    q = q * np.where(q[np.arange(len(q)), largest] < 0, -1.0, 1.0)[:, None]
    packed = largest.astype(np.uint32)
    for k in range(3):
        index = k + (k >= largest)  # the k-th component that is not the largest
        packed = (packed << np.uint32(10)) | _unorm(q[np.arange(len(q)), index] * math.sqrt(0.5) + 0.5, 10)
    return packed


def _unpack_rotations(packed: np.ndarray) -> np.ndarray:
    """Unit quaternions [N, 4] (rot_0..3 order) of 2-10-10-10 smallest-three uint32."""
    three = np.stack([(packed >> np.uint32(20 - 10 * k)) & np.uint32(1023) for k in range(3)], 1) / 1023.0
    three = (three - 0.5) / math.sqrt(0.5)
    largest = (packed >> np.uint32(30)).astype(np.int64)
    q = np.empty((len(packed), 4))
    rows = np.arange(len(packed))
    for k in range(3):
        q[rows, k + (k >= largest)] = three[:, k]
    q[rows, largest] = np.sqrt(np.clip(1 - (three**2).sum(1), 0, None))
    return q


def _store_bounds(chunks: np.ndarray, values: np.ndarray, first: int, limit: float | None = None):
    """Write the per-chunk bounds of values [N, 3] into the chunk fields CHUNK_FIELDS[first:
    first + 6] (mins, then maxes; clamped to +-limit) and return them as the file holds
    them (float32 made float64), so that packing and reading use the same bounds."""
    lo, hi = _chunk_bounds(values)
    if limit is not None:
        lo, hi = np.clip(lo, -limit, limit), np.clip(hi, -limit, limit)
    names = CHUNK_FIELDS[first : first + 6]
    for d in range(3):
        chunks[names[d]], chunks[names[3 + d]] = lo[:, d], hi[:, d]
    return tuple(np.stack([chunks[name] for name in part], 1).astype(np.float64) for part in (names[:3], names[3:]))


def save_compressed_ply(path: str | os.PathLike, gaussians: Gaussians) -> None:
    """Write ``gaussians`` as a compressed PLY (layout in the module docstring), sorted by
    :func:`morton_order` of their centres (by object first when they have the feature
    ``object``, kept as the header's runs), atomically. Gaussians with plain RGB ``colors``
    are written as degree 0; other features are not kept; deformed or turned ones are refused."""
    gaussians.check_undeformed(str(path))
    objects = _objects_of(gaussians, path)
    g = gaussians.detach().to(dtype=torch.float64, device="cpu")
    if g.sh is not None:
        sh = g.sh.numpy()
    elif g.colors.shape[1] == 3:
        sh = rgb_to_sh0(g.colors).numpy()[:, None, :]
    else:
        raise InputError(
            f"{path}: a compressed PLY stores RGB; these Gaussians have {g.colors.shape[1]} colour channels"
        )
    order = morton_order(g.means.numpy())
    if objects is not None:
        order = order[np.argsort(objects[order], kind="stable")]  # object by object, each along the curve
    means, log_scales, quats = g.means.numpy()[order], g.log_scales.numpy()[order], g.quats.numpy()[order]
    sh, opacities = sh[order], g.opacities.numpy()[order]
    n = len(order)
    chunks = np.zeros(-(-n // CHUNK), np.dtype([(name, "<f4") for name in CHUNK_FIELDS]))
    vertex = np.zeros(n, np.dtype([(name, "<u4") for name in VERTEX_FIELDS]))
    if n:
        rgb = SH_C0 * sh[:, 0] + 0.5
        vertex["packed_position"] = _pack_in_bounds(means, *_store_bounds(chunks, means, 0), POSITION_BITS)
        vertex["packed_scale"] = _pack_in_bounds(
            log_scales, *_store_bounds(chunks, log_scales, 6, LOG_SCALE_LIMIT), POSITION_BITS
        )
        vertex["packed_color"] = (
            _pack_in_bounds(rgb, *_store_bounds(chunks, rgb, 12), (8, 8, 8)) << np.uint32(8)
        ) | _unorm(opacities, 8)
        vertex["packed_rotation"] = _pack_rotations(quats)
    elements = {"chunk": chunks, "vertex": vertex}
    if sh.shape[1] > 1:
        rest = sh[:, 1:, :].transpose(0, 2, 1).reshape(n, -1)  # channel-major
        count = rest.shape[1]
        table = np.zeros(n, np.dtype([(f"f_rest_{i}", "u1") for i in range(count)]))
        codes = np.clip(np.trunc((rest / (2 * SH_RANGE) + 0.5) * 256), 0, 255).astype(np.uint8)
        table.view(np.uint8).reshape(n, count)[:] = codes
        elements["sh"] = table
    comments = ["clflow compressed 3DGS (PlayCanvas layout)"]
    if objects is not None:
        values, counts = np.unique(objects[order], return_counts=True)  # sorted: one run per object
        comments.append(" ".join([OBJECT_COMMENT, *(f"{v}:{c}" for v, c in zip(values, counts))]))
    write_ply_elements(path, elements, comments=tuple(comments))


def _objects_of(g: Gaussians, path: str | os.PathLike) -> np.ndarray | None:
    """[N] int64: the feature ``object`` of ``g`` (None without it); InputError unless integers."""
    if OBJECT_FEATURE not in g.feature_names:
        return None
    column = g.features[:, g.feature_names.index(OBJECT_FEATURE)].detach().double().cpu().numpy()
    if not np.array_equal(column, np.round(column)):
        raise InputError(f"{path}: the feature {OBJECT_FEATURE!r} must hold integers (each Gaussian's object)")
    return column.astype(np.int64)


def _read_objects(path: str | os.PathLike, n: int) -> np.ndarray | None:
    """[n] int64: each vertex's object, from the header's runs (None when it has none)."""
    lines = [c.split()[2:] for c in ply_comments(path) if c.split()[:2] == OBJECT_COMMENT.split()]
    if not lines:
        return None
    pairs = [[int(v) for v in run.split(":")] for run in lines[0] if re.fullmatch(r"-?\d+:\d+", run)]
    if len(lines) > 1 or len(pairs) < len(lines[0]) or sum(count for _, count in pairs) != n:
        raise InputError(
            f"{path}: the header's '{OBJECT_COMMENT}' comment must be one line of value:count runs covering "
            f"the {n} Gaussians, got {' | '.join(' '.join(line) for line in lines)!r}"
        )
    return np.repeat([value for value, _ in pairs], [count for _, count in pairs]).astype(np.int64)


def is_compressed_ply(path: str | os.PathLike) -> bool:
    """Whether the PLY file at ``path`` has the compressed layout (packed vertices)."""

    return "packed_position" in ply_vertex_properties(path)


def position_error(path: str | os.PathLike) -> float:
    """The largest distance (file units) between a centre written to the compressed PLY at
    ``path`` and the one it reads back: half a quantisation step on each axis of the
    widest chunk."""
    chunks = read_ply_elements(path, ("chunk",))["chunk"]
    if not len(chunks):
        return 0.0
    span = np.stack([chunks[f"max_{a}"].astype(np.float64) - chunks[f"min_{a}"] for a in "xyz"], 1)
    return float(np.linalg.norm(0.5 * span / (2.0 ** np.array(POSITION_BITS) - 1), axis=1).max())


def load_compressed_ply(path: str | os.PathLike) -> Gaussians:
    """Read a compressed PLY (SuperSplat / PlayCanvas / :func:`save_compressed_ply`) as
    float32 :class:`Gaussians` in file order; opacities are kept inside (0, 1) by half a
    step; the header's object runs, when it has them, as the feature ``object``. Raises
    :class:`InputError` naming the file for a malformed one."""
    try:
        elements = read_ply_elements(path, ("chunk", "vertex"), optional=("sh",))
    except InputError as exc:
        raise InputError(f"{exc} (reading it as a compressed 3DGS PLY)") from None
    chunks, vertex = elements["chunk"], elements["vertex"]
    n = len(vertex)
    missing = [f for f in CHUNK_FIELDS[:12] if f not in (chunks.dtype.names or ())]
    missing += [f for f in VERTEX_FIELDS if f not in (vertex.dtype.names or ())]
    if missing:
        raise InputError(f"{path}: not a compressed 3DGS PLY: missing {', '.join(missing)}")
    if len(chunks) != -(-n // CHUNK):
        raise InputError(f"{path}: {len(chunks)} chunks for {n} Gaussians; a compressed PLY has ceil(N / {CHUNK})")
    column = lambda names: np.stack([chunks[name].astype(np.float64) for name in names], 1)  # noqa: E731
    field = lambda name: vertex[name].astype(np.uint32)  # noqa: E731
    means = _unpack_in_bounds(
        field("packed_position"), column(CHUNK_FIELDS[0:3]), column(CHUNK_FIELDS[3:6]), POSITION_BITS
    )
    log_scales = _unpack_in_bounds(
        field("packed_scale"), column(CHUNK_FIELDS[6:9]), column(CHUNK_FIELDS[9:12]), POSITION_BITS
    )
    color = field("packed_color")
    if "min_r" in chunks.dtype.names:
        rgb = _unpack_in_bounds(
            color >> np.uint32(8), column(CHUNK_FIELDS[12:15]), column(CHUNK_FIELDS[15:18]), (8, 8, 8)
        )
    else:  # older files: colours over [0, 1]
        rgb = _unpack_in_bounds(color >> np.uint32(8), np.zeros((len(chunks), 3)), np.ones((len(chunks), 3)), (8, 8, 8))
    alpha = np.clip((color & np.uint32(255)) / 255.0, 0.5 / 255, 1 - 0.5 / 255)
    sh = ((rgb - 0.5) / SH_C0)[:, None, :]
    if "sh" in elements:
        table = elements["sh"]
        count = len(table.dtype.names)
        if count % 3 or len(table) != n:
            raise InputError(
                f"{path}: the sh element has {count} properties for {len(table)} Gaussians; expected a "
                f"multiple of 3 for each of the {n}"
            )
        try:
            sh_degree_of(count // 3 + 1)
        except InputError as exc:
            raise InputError(f"{path}: {count} f_rest attributes: {exc}") from None
        if any(table.dtype[name] != np.uint8 for name in table.dtype.names):
            raise InputError(f"{path}: the sh element's properties must be uchar (one byte per coefficient)")
        codes = np.stack([table[name].astype(np.float64) for name in table.dtype.names], 1)  # f_rest_0.. in file order
        unit = np.where(codes == 0, 0.0, np.where(codes == 255, 1.0, (codes + 0.5) / 256))
        rest = ((unit - 0.5) * 2 * SH_RANGE).reshape(n, 3, count // 3).transpose(0, 2, 1)
        sh = np.concatenate([sh, rest], 1)
    f32 = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    objects = _read_objects(path, n)
    return Gaussians(
        means=f32(means),
        quats=f32(_unpack_rotations(field("packed_rotation"))),
        log_scales=f32(log_scales),
        opacity_logits=f32(np.log(alpha / (1 - alpha))),
        sh=f32(sh),
        features=None if objects is None else f32(objects[:, None]),
        feature_names=() if objects is None else (OBJECT_FEATURE,),
    ).validate(str(path))
