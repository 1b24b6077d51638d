"""COLMAP sparse-model writers for the tests (the layouts of COLMAP's reconstruction_io.cc),
written independently of clflow.recon.colmap's readers."""

import struct
from pathlib import Path

import numpy as np

from clflow.recon.colmap import MODEL_IDS
from clflow.splat.cameras import Camera
from clflow.splat.gaussians import rotmat_to_quat


def model_of(cameras: list[Camera], points: np.ndarray | None = None):
    """(cameras rows, images rows, points rows) of a model with one PINHOLE camera per view:
    cameras (id, model, w, h, params), images (id, qvec, tvec, camera id, name, 2D points),
    points (id, xyz, rgb, error, track)."""
    cam_rows, image_rows = [], []
    for i, c in enumerate(cameras, start=1):
        cam_rows.append((i, "PINHOLE", c.width, c.height, [c.fx, c.fy, c.cx, c.cy]))
        q = rotmat_to_quat(c.R[None])[0].numpy()
        image_rows.append((i, q, c.t.numpy(), i, c.name, [(10.5, 20.25, -1), (3.0, 4.0, 1)] if i % 2 else []))
    pts = [] if points is None else [(j + 1, p, (j % 256, 100, 200), 0.5, [(1, 0), (2, 1)]) for j, p in enumerate(points)]
    return cam_rows, image_rows, pts


def write_bin(folder: Path, model) -> None:
    cams, images, points = model
    folder.mkdir(parents=True, exist_ok=True)
    data = struct.pack("<Q", len(cams))
    for cid, name, w, h, params in cams:
        data += struct.pack("<iiQQ", cid, MODEL_IDS[name][0], w, h) + struct.pack(f"<{len(params)}d", *params)
    (folder / "cameras.bin").write_bytes(data)
    data = struct.pack("<Q", len(images))
    for iid, q, t, cid, name, pts2d in images:
        data += struct.pack("<i7di", iid, *q, *t, cid) + name.encode() + b"\0" + struct.pack("<Q", len(pts2d))
        data += b"".join(struct.pack("<ddq", *p) for p in pts2d)
    (folder / "images.bin").write_bytes(data)
    data = struct.pack("<Q", len(points))
    for pid, xyz, rgb, err, track in points:
        data += struct.pack("<Q3d3Bd", pid, *xyz, *rgb, err) + struct.pack("<Q", len(track))
        data += b"".join(struct.pack("<ii", *t) for t in track)
    (folder / "points3D.bin").write_bytes(data)


def write_txt(folder: Path, model) -> None:
    cams, images, points = model
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    lines += [f"{cid} {name} {w} {h} " + " ".join(repr(float(p)) for p in params) for cid, name, w, h, params in cams]
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:", f"# Number of images: {len(images)}"]
    for iid, q, t, cid, name, pts2d in images:
        lines.append(f"{iid} " + " ".join(repr(float(v)) for v in (*q, *t)) + f" {cid} {name}")
        lines.append(" ".join(f"{x} {y} {p}" for x, y, p in pts2d))  # empty when the image has no points
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    lines = ["# 3D point list with one line of data per point:"]
    lines += [f"{pid} {float(xyz[0])!r} {float(xyz[1])!r} {float(xyz[2])!r} {rgb[0]} {rgb[1]} {rgb[2]} {err} " + " ".join(f"{a} {b}" for a, b in track)
              for pid, xyz, rgb, err, track in points]
    (folder / "points3D.txt").write_text("\n".join(lines) + "\n")
