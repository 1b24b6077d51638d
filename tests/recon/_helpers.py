"""Input writers for the tests, independent of clflow's readers: COLMAP sparse models (the
layouts of COLMAP's reconstruction_io.cc) and PAC-NeRF-style multi-camera sequences; the
CLI runner of the bad-input tests."""

import json
import struct
from pathlib import Path

import numpy as np

from clflow.recon.colmap import MODEL_IDS
from clflow.splat.cameras import Camera
from clflow.splat.geometry import rotmat_to_quat


def model_of(cameras: list[Camera], points: np.ndarray | None = None):
    """(cameras rows, images rows, points rows) of a model with one PINHOLE camera per view:
    cameras (id, model, w, h, params), images (id, qvec, tvec, camera id, name, 2D points),
    points (id, xyz, rgb, error, track)."""
    cam_rows, image_rows = [], []
    for i, c in enumerate(cameras, start=1):
        cam_rows.append((i, "PINHOLE", c.width, c.height, [c.fx, c.fy, c.cx, c.cy]))
        q = rotmat_to_quat(c.R[None])[0].numpy()
        image_rows.append((i, q, c.t.numpy(), i, c.name, [(10.5, 20.25, -1), (3.0, 4.0, 1)] if i % 2 else []))
    pts = (
        [] if points is None else [(j + 1, p, (j % 256, 100, 200), 0.5, [(1, 0), (2, 1)]) for j, p in enumerate(points)]
    )
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
    lines += [
        f"{pid} {float(xyz[0])!r} {float(xyz[1])!r} {float(xyz[2])!r} {rgb[0]} {rgb[1]} {rgb[2]} {err} "
        + " ".join(f"{a} {b}" for a, b in track)
        for pid, xyz, rgb, err, track in points
    ]
    (folder / "points3D.txt").write_text("\n".join(lines) + "\n")


def colour(camera: int, frame: int) -> tuple[int, int, int]:
    """The flat RGB colour of camera ``camera``'s image of ``frame`` in :func:`write_sequence`."""
    return 40 + 50 * camera, 30 + 50 * frame, 200


def write_sequence(
    folder: Path, cameras: int = 4, frames: int = 3, size: int = 32, fps: float = 24.0, times: bool = True
) -> list[tuple[np.ndarray, np.ndarray]]:
    """A multi-camera capture in PAC-NeRF's layout: ``folder/all_data.json`` and
    ``folder/data/r_{camera}_{frame}.png`` (RGBA, flat :func:`colour`, alpha a centred disc),
    each camera's backdrop as frame -1 (as PAC-NeRF ships it); cameras on a ring around the
    origin, y up, looking at it, with 3x4 OpenGL c2w and an off-centre principal point.
    Returns each camera's (c2w [3, 4], K [3, 3])."""
    import cv2

    (folder / "data").mkdir(parents=True, exist_ok=True)
    yy, xx = np.mgrid[:size, :size] + 0.5
    disc = ((xx - size / 2) ** 2 + (yy - size / 2) ** 2 <= (size / 4) ** 2).astype(np.uint8) * 255
    entries, poses = [], []
    for c in range(cameras):
        angle = 2 * np.pi * c / cameras
        eye = np.array([2.5 * np.sin(angle), 0.8, 2.5 * np.cos(angle)])
        back = eye / np.linalg.norm(eye)  # OpenGL camera +z points away from the target
        right = np.cross([0.0, 1.0, 0.0], back)
        right /= np.linalg.norm(right)
        c2w = np.concatenate([np.stack([right, np.cross(back, right), back], axis=1), eye[:, None]], axis=1)
        K = np.array([[1.1 * size, 0.0, size / 2 + 1.5], [0.0, 1.2 * size, size / 2 - 2.0], [0.0, 0.0, 1.0]])
        poses.append((c2w, K))
        for f in [-1, *range(frames)]:
            rgb = (90, 90, 90) if f < 0 else colour(c, f)
            rgba = np.concatenate(
                [
                    np.broadcast_to(np.array(rgb, np.uint8), (size, size, 3)),
                    np.full((size, size, 1), 255, np.uint8) if f < 0 else disc[..., None],
                ],
                axis=2,
            )
            name = f"./data/r_{c}_{f}.png"
            assert cv2.imwrite(str(folder / name), np.ascontiguousarray(rgba[..., [2, 1, 0, 3]]))
            entry = {"file_path": name, "c2w": c2w.tolist(), "intrinsic": K.tolist()}
            if times:
                entry["time"] = max(f, 0) / fps
            entries.append(entry)
    (folder / "all_data.json").write_text(json.dumps(entries))
    return poses


def run(args, command: str = "reconstruct") -> tuple[int, str]:
    """(exit code, output) of ``clflow COMMAND ARGS``."""
    from click.testing import CliRunner

    from clflow_cli.main import cli

    result = CliRunner().invoke(cli, [command, *map(str, args)])
    return result.exit_code, result.output


def one_line_error(args, match: str, command: str = "reconstruct") -> None:
    """``clflow COMMAND ARGS`` fails with exit status 1 and one line holding ``match``."""
    code, output = run(args, command)
    assert code == 1, output
    assert "Traceback" not in output and len(output.strip().splitlines()) == 1, output
    assert match in output, output
