"""COLMAP sparse models (``cameras``, ``images``, ``points3D`` as ``.bin`` or ``.txt``).

The layouts are COLMAP's own (``src/colmap/scene/reconstruction_io.cc``): binary files
are little-endian; text files have ``#`` comment lines and, in ``images.txt``, two lines
per image (the pose, then its 2D points, which may be an empty line). Poses are
world-to-camera (R from the unit quaternion qw qx qy qz, t), OpenCV camera axes; units are
the model's (metres when the model was scaled to metres).

    model = read_model("sparse/0")           # .bin if present, else .txt
    cameras = model_cameras(model)            # [Camera] in image-name order
    xyz, rgb = model.points_xyz, model.points_rgb
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from clflow.errors import InputError
from clflow.splat.cameras import Camera
from clflow.splat.geometry import quat_to_rotmat

# model id -> (name, number of parameters), COLMAP's camera models (sensor/models.h)
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
}
MODEL_IDS = {name: (model_id, count) for model_id, (name, count) in CAMERA_MODELS.items()}
# models whose first parameters are f, cx, cy (one focal length) or fx, fy, cx, cy
SINGLE_FOCAL = {"SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "FOV", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"}
UNIT_QUATERNION_TOLERANCE = 1e-3  # | |q| - 1 | accepted (files store ~17 digits; hand edits less)


@dataclass
class ColmapCamera:
    """An intrinsic camera: ``model`` name, size (pixels), ``params`` as COLMAP orders them."""

    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    """A registered image: world-to-camera rotation ``qvec`` (w, x, y, z), ``tvec`` (model
    units), its camera id and file name (relative to the image folder)."""

    image_id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str


@dataclass
class ColmapModel:
    """A sparse model: cameras and images by id, points [P, 3] (model units) and colours [P, 3] uint8."""

    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    points_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    points_rgb: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))


# -- binary ---------------------------------------------------------------------------------


class _Reader:
    """Little-endian struct reads from ``data`` with an error naming the file when it ends early."""

    def __init__(self, path: Path):
        self.path, self.data, self.offset = path, path.read_bytes(), 0

    def read(self, fmt: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.offset + size > len(self.data):
            raise InputError(
                f"{self.path}: file ends early (byte {self.offset} of {len(self.data)}); a truncated COLMAP model?"
            )
        values = struct.unpack_from("<" + fmt, self.data, self.offset)
        self.offset += size
        return values

    def name(self) -> str:
        end = self.data.find(b"\0", self.offset)
        if end < 0:
            raise InputError(f"{self.path}: an image name has no terminating NUL byte")
        text = self.data[self.offset : end].decode("utf-8")
        self.offset = end + 1
        return text


def read_cameras_bin(path: str | Path) -> dict[int, ColmapCamera]:
    """``cameras.bin``: uint64 count, then per camera int32 id, int32 model, uint64 width,
    uint64 height, float64 params[model's count]."""
    r = _Reader(Path(path))
    cameras = {}
    for _ in range(r.read("Q")[0]):
        camera_id, model_id, width, height = r.read("iiQQ")
        if model_id not in CAMERA_MODELS:
            raise InputError(f"{path}: camera {camera_id} has unknown model id {model_id}")
        name, count = CAMERA_MODELS[model_id]
        cameras[camera_id] = ColmapCamera(camera_id, name, width, height, np.array(r.read("d" * count)))
    return cameras


def read_images_bin(path: str | Path) -> dict[int, ColmapImage]:
    """``images.bin``: uint64 count, then per image int32 id, float64 qw qx qy qz tx ty tz,
    int32 camera id, NUL-terminated name, uint64 point count, (float64 x, y, int64 id) each."""
    r = _Reader(Path(path))
    images = {}
    for _ in range(r.read("Q")[0]):
        image_id, *pose, camera_id = r.read("i7di")
        name = r.name()
        r.read("ddq" * r.read("Q")[0])  # the 2D points: not needed here
        images[image_id] = ColmapImage(image_id, np.array(pose[:4]), np.array(pose[4:]), camera_id, name)
    return images


def read_points3d_bin(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``points3D.bin``: uint64 count, then per point uint64 id, float64 xyz, uint8 rgb,
    float64 error, uint64 track length, (int32 image id, int32 point index) each.
    Returns xyz [P, 3] float64 and rgb [P, 3] uint8."""
    r = _Reader(Path(path))
    count = r.read("Q")[0]
    xyz, rgb = np.zeros((count, 3)), np.zeros((count, 3), np.uint8)
    for i in range(count):
        values = r.read("Q3d3Bd")
        xyz[i], rgb[i] = values[1:4], values[4:7]
        r.read("ii" * r.read("Q")[0])
    return xyz, rgb


# -- text -----------------------------------------------------------------------------------


def _data_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of every line that is not a comment; blank lines are kept."""
    from clflow.fileio import read_text

    text = read_text(path, "COLMAP text file")
    return [(n, line.strip()) for n, line in enumerate(text.splitlines(), 1) if not line.lstrip().startswith("#")]


def _fields(path: Path, n: int, line: str, types: tuple, what: str) -> list:
    """The first ``len(types)`` whitespace-separated fields of ``line`` converted by ``types``."""
    parts = line.split()
    try:
        if len(parts) < len(types):
            raise ValueError
        return [t(p) for t, p in zip(types, parts)] + parts[len(types) :]
    except ValueError:
        raise InputError(f"{path}:{n}: expected {what}, got {line!r}") from None


def read_cameras_txt(path: str | Path) -> dict[int, ColmapCamera]:
    """``cameras.txt``: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`` per line."""
    path = Path(path)
    cameras = {}
    for n, line in _data_lines(path):
        if not line:
            continue
        camera_id, model, width, height, *params = _fields(
            path, n, line, (int, str, int, int), "CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]"
        )
        if model not in MODEL_IDS:
            raise InputError(f"{path}:{n}: unknown camera model {model!r}")
        if len(params) != MODEL_IDS[model][1]:
            raise InputError(f"{path}:{n}: {model} takes {MODEL_IDS[model][1]} parameters, got {len(params)}")
        values = _fields(path, n, " ".join(params), (float,) * len(params), f"{len(params)} numbers")
        cameras[camera_id] = ColmapCamera(camera_id, model, width, height, np.array(values))
    return cameras


def read_images_txt(path: str | Path) -> dict[int, ColmapImage]:
    """``images.txt``: per image ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` and a
    second line of 2D points (possibly empty)."""
    path = Path(path)
    lines = _data_lines(path)
    images = {}
    i = 0
    while i < len(lines):
        n, line = lines[i]
        if not line:  # blank lines between records (a blank points line is consumed below)
            i += 1
            continue
        image_id, *pose, camera_id, name = _fields(
            path, n, line, (int,) + (float,) * 7 + (int, str), "IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"
        )[:10]
        images[image_id] = ColmapImage(image_id, np.array(pose[:4]), np.array(pose[4:]), camera_id, name)
        i += 2  # skip this image's 2D points line
    return images


def read_points3d_txt(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``points3D.txt``: ``POINT3D_ID X Y Z R G B ERROR TRACK[]`` per line; xyz [P, 3], rgb [P, 3] uint8."""
    path = Path(path)
    rows = [
        _fields(path, n, line, (int,) + (float,) * 3 + (int,) * 3, "POINT3D_ID X Y Z R G B ERROR TRACK[]")
        for n, line in _data_lines(path)
        if line
    ]
    xyz = np.array([r[1:4] for r in rows], dtype=np.float64).reshape(-1, 3)
    return xyz, np.array([r[4:7] for r in rows], dtype=np.uint8).reshape(-1, 3)


# -- model ----------------------------------------------------------------------------------


def read_model(folder: str | Path) -> ColmapModel:
    """The sparse model in ``folder`` (e.g. ``sparse/0``): the ``.bin`` files when
    ``cameras.bin`` exists, else the ``.txt`` files; ``points3D`` is optional."""
    folder = Path(folder)
    ext = ".bin" if (folder / "cameras.bin").is_file() else ".txt"
    readers = {
        ".bin": (read_cameras_bin, read_images_bin, read_points3d_bin),
        ".txt": (read_cameras_txt, read_images_txt, read_points3d_txt),
    }[ext]
    for stem in ("cameras", "images"):
        if not (folder / f"{stem}{ext}").is_file():
            raise InputError(f"{folder}: no COLMAP model here (cameras.bin/.txt and images.bin/.txt are needed)")
    model = ColmapModel(readers[0](folder / f"cameras{ext}"), readers[1](folder / f"images{ext}"))
    if (folder / f"points3D{ext}").is_file():
        model.points_xyz, model.points_rgb = readers[2](folder / f"points3D{ext}")
    if not model.images:
        raise InputError(f"{folder}: the COLMAP model registers no images")
    return model


def intrinsic_matrix(camera: ColmapCamera, where: str) -> torch.Tensor:
    """[3, 3] K (pixels) of a pinhole camera; models with non-zero distortion raise
    :class:`InputError` (undistort first: ``colmap image_undistorter``)."""
    p = camera.params
    single = camera.model in SINGLE_FOCAL
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if single else tuple(p[:4])
    distortion = p[3:] if single else p[4:]
    if camera.model in (
        "FOV",
        "OPENCV_FISHEYE",
        "SIMPLE_RADIAL_FISHEYE",
        "RADIAL_FISHEYE",
        "THIN_PRISM_FISHEYE",
    ) or np.any(distortion != 0):
        raise InputError(
            f"{where}: camera {camera.camera_id} is {camera.model} with distortion {distortion.tolist()}; "
            "clflow renders pinhole cameras: undistort the images first (colmap image_undistorter)"
        )
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)


def model_cameras(model: ColmapModel, where: str = "COLMAP model") -> list[Camera]:
    """The model's images as :class:`Camera` s named by image file name, sorted by name."""
    cameras = []
    for image in sorted(model.images.values(), key=lambda im: im.name):
        label = f"{where}: image {image.name!r}"
        if image.camera_id not in model.cameras:
            raise InputError(f"{label}: camera {image.camera_id} is not in the model's cameras")
        norm = float(np.linalg.norm(image.qvec))
        if abs(norm - 1) > UNIT_QUATERNION_TOLERANCE:
            raise InputError(f"{label}: the rotation quaternion has norm {norm:.6g}, not 1 (not a rotation)")
        camera = model.cameras[image.camera_id]
        viewmat = torch.eye(4, dtype=torch.float64)
        viewmat[:3, :3] = quat_to_rotmat(torch.from_numpy(image.qvec)[None])[0]
        viewmat[:3, 3] = torch.from_numpy(image.tvec)
        try:
            cameras.append(
                Camera(viewmat, intrinsic_matrix(camera, label), int(camera.width), int(camera.height), image.name)
            )
        except InputError as exc:
            raise InputError(f"{label}: {exc}") from None
    return cameras
