"""Pinhole cameras (OpenCV axes), 3DGS ``cameras.json`` / NeRF ``transforms.json`` loaders,
look-at and orbit helpers.

Conventions: ``viewmat`` is the 4x4 world-to-camera matrix with camera axes +x right,
+y down, +z forward (OpenCV / COLMAP); ``K`` holds fx, fy, cx, cy in pixels with pixel
centres at i + 0.5. Positions in m, angles in rad. NeRF / Blender / nerfstudio files use
OpenGL camera axes (+y up, -z forward); their loader flips the y and z camera axes.

    cams = load_cameras_json("output/cameras.json")           # what 3DGS trainers write
    cam = look_at(eye=(2, 0, 1), target=(0, 0, 0), up=(0, 0, 1), fov_x=math.radians(50),
                  width=640, height=480)
    views = orbit(center=(0, 0, 0), radius=3, n_views=60, elevation=math.radians(20), ...)
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import torch

from clflow.errors import InputError

ORTHONORMAL_TOLERANCE = 1e-4  # max |R R^T - I| accepted (files store rotations in ~7 digits)
OPENGL_TO_OPENCV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))

Vector = torch.Tensor | Sequence[float]


@dataclass(eq=False)
class Camera:
    """A pinhole camera.

    Attributes:
        viewmat: [4, 4] float64 world-to-camera transform [[R, t], [0, 1]], OpenCV axes;
            a world point X (m) is at R X + t in the camera frame.
        K: [3, 3] float64 intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], pixels.
        width, height: image size in pixels.
        name: label (an image name from a dataset, or a generated view's name).
    """

    viewmat: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    name: str = ""

    def __post_init__(self) -> None:
        label = f"camera {self.name!r}" if self.name else "camera"
        self.viewmat = _matrix(self.viewmat, (4, 4), f"{label}: viewmat")
        self.K = _matrix(self.K, (3, 3), f"{label}: K")
        for what in ("width", "height"):
            value = getattr(self, what)
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                raise InputError(f"{label}: {what} must be a positive integer number of pixels, got {value!r}")
        if not torch.equal(self.viewmat[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)):
            raise InputError(f"{label}: the last row of viewmat must be [0, 0, 0, 1], got {self.viewmat[3].tolist()}")
        R = self.viewmat[:3, :3]
        error = (R @ R.T - torch.eye(3, dtype=torch.float64)).abs().max().item()
        if error > ORTHONORMAL_TOLERANCE:
            raise InputError(
                f"{label}: the rotation of viewmat is not orthonormal (max |R R^T - I| = {error:.3g} > "
                f"{ORTHONORMAL_TOLERANCE:g}); R = {R.tolist()}"
            )
        if torch.linalg.det(R) < 0:
            raise InputError(
                f"{label}: the rotation of viewmat is a reflection (det R = -1); check the axis convention"
            )
        K = self.K
        if K[0, 1] != 0 or K[1, 0] != 0 or not torch.equal(K[2], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)):
            raise InputError(f"{label}: K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise InputError(
                f"{label}: focal lengths must be > 0 pixels, got fx={K[0, 0].item():g}, fy={K[1, 1].item():g}"
            )

    @property
    def R(self) -> torch.Tensor:
        """[3, 3] world-to-camera rotation."""
        return self.viewmat[:3, :3]

    @property
    def t(self) -> torch.Tensor:
        """[3] world-to-camera translation, m."""
        return self.viewmat[:3, 3]

    @property
    def position(self) -> torch.Tensor:
        """[3] camera centre in the world, m."""
        return -self.R.T @ self.t

    @property
    def forward(self) -> torch.Tensor:
        """[3] unit viewing direction (camera +z) in the world."""
        return self.R[2]

    @property
    def fx(self) -> float:
        return self.K[0, 0].item()

    @property
    def fy(self) -> float:
        return self.K[1, 1].item()

    @property
    def cx(self) -> float:
        return self.K[0, 2].item()

    @property
    def cy(self) -> float:
        return self.K[1, 2].item()

    @property
    def fov_x(self) -> float:
        """Horizontal field of view, rad."""
        return 2 * math.atan(self.width / (2 * self.fx))

    @property
    def fov_y(self) -> float:
        """Vertical field of view, rad."""
        return 2 * math.atan(self.height / (2 * self.fy))

    def scaled(self, factor: int) -> "Camera":
        """The same view with ``factor`` times the pixels per side (pixel i of this camera
        covers pixels factor i .. factor i + factor - 1 of the scaled one)."""
        K = self.K.clone()
        K[:2] *= factor
        return Camera(self.viewmat, K, self.width * factor, self.height * factor, self.name)

    def widened(self, margin: int) -> "Camera":
        """The same view with ``margin`` more pixels on each side (pixel (i, j) of this camera
        is pixel (i + margin, j + margin) of the wider one): a larger image of the same
        pixels, no resampling."""
        K = self.K.clone()
        K[:2, 2] += margin
        return Camera(self.viewmat, K, self.width + 2 * margin, self.height + 2 * margin, self.name)

    def camtoworld(self) -> torch.Tensor:
        """[4, 4] camera-to-world transform (OpenCV axes), the inverse of ``viewmat``."""
        out = torch.eye(4, dtype=torch.float64)
        out[:3, :3] = self.R.T
        out[:3, 3] = self.position
        return out


def intrinsics(width: int, height: int, fov_x: float, fov_y: float | None = None) -> torch.Tensor:
    """[3, 3] K with the principal point at the image centre; ``fov_y`` defaults to square pixels."""
    if not 0 < fov_x < math.pi:
        raise InputError(f"horizontal field of view must be in (0, pi) rad, got {fov_x}")
    fx = width / (2 * math.tan(fov_x / 2))
    if fov_y is None:
        fy = fx
    elif 0 < fov_y < math.pi:
        fy = height / (2 * math.tan(fov_y / 2))
    else:
        raise InputError(f"vertical field of view must be in (0, pi) rad, got {fov_y}")
    return torch.tensor([[fx, 0.0, width / 2], [0.0, fy, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)


def from_camtoworld(camtoworld: torch.Tensor, K: torch.Tensor, width: int, height: int, name: str = "") -> Camera:
    """A camera from its [4, 4] camera-to-world transform in OpenCV axes."""
    camtoworld = _matrix(camtoworld, (4, 4), f"camera {name!r}: camera-to-world matrix")
    R_c2w, position = camtoworld[:3, :3], camtoworld[:3, 3]
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = R_c2w.T
    viewmat[:3, 3] = -R_c2w.T @ position
    viewmat[3] = camtoworld[3]  # keeps a malformed last row visible to Camera's check
    return Camera(viewmat, K, width, height, name)


# -- novel views ---------------------------------------------------------------------------


def look_at(
    eye: Vector,
    target: Vector,
    up: Vector = (0.0, 0.0, 1.0),
    *,
    fov_x: float,
    width: int,
    height: int,
    name: str = "look_at",
    keys: tuple[str, str, str] = ("eye", "target", "up"),
) -> Camera:
    """A camera at ``eye`` (m) looking at ``target`` (m) with world direction ``up`` upward in
    the image; ``keys``: how the errors name the three (the options or config keys that gave them)."""
    eye, target, up = (_vector(v, what) for v, what in zip((eye, target, up), keys))
    forward = target - eye
    if forward.norm() == 0:
        raise InputError(f"{keys[0]} and {keys[1]} are the same point {eye.tolist()}")
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, up)
    if right.norm() < 1e-9 * up.norm() or up.norm() == 0:
        raise InputError(
            f"{keys[2]} {up.tolist()} is zero or parallel to the viewing direction {forward.tolist()} "
            f"({keys[0]} to {keys[1]})"
        )
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    camtoworld = torch.eye(4, dtype=torch.float64)
    camtoworld[:3, :3] = torch.stack([right, down, forward], dim=1)
    camtoworld[:3, 3] = eye
    return from_camtoworld(camtoworld, intrinsics(width, height, fov_x), width, height, name)


def orbit(
    center: Vector,
    radius: float,
    *,
    n_views: int,
    elevation: float,
    up: Vector = (0.0, 0.0, 1.0),
    azimuth: float = 0.0,
    fov_x: float,
    width: int,
    height: int,
) -> list[Camera]:
    """``n_views`` cameras evenly spaced on a circle around ``center``, all looking at it.

    Args:
        radius: distance from ``center`` to every camera, m.
        elevation: angle above the plane normal to ``up``, rad (in (-pi/2, pi/2)).
        azimuth: angle of the first view about ``up``, rad; views advance counter-clockwise.
    """
    if n_views < 1:
        raise InputError(f"orbit needs n_views >= 1, got {n_views}")
    if not radius > 0:
        raise InputError(f"orbit radius must be > 0 m, got {radius}")
    if not abs(elevation) < math.pi / 2:
        raise InputError(f"orbit elevation must be in (-pi/2, pi/2) rad, got {elevation}")
    center, up = _vector(center, "center"), _vector(up, "up")
    if up.norm() == 0:
        raise InputError("orbit: up must be a non-zero vector")
    up = up / up.norm()
    # e1, e2: an orthonormal basis of the plane normal to up.
    helper = torch.eye(3, dtype=torch.float64)[int(torch.argmin(up.abs()))]
    e1 = torch.linalg.cross(up, helper)
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(up, e1)
    cameras = []
    for i in range(n_views):
        phi = azimuth + 2 * math.pi * i / n_views
        direction = math.cos(elevation) * (math.cos(phi) * e1 + math.sin(phi) * e2) + math.sin(elevation) * up
        cameras.append(
            look_at(
                center + radius * direction, center, up, fov_x=fov_x, width=width, height=height, name=f"orbit_{i:04d}"
            )
        )
    return cameras


def framing_distance(radius: float, fov_x: float, width: int, height: int) -> float:
    """Distance (m) at which a sphere of ``radius`` m exactly fits the narrower field of view."""
    fov_y = 2 * math.atan(height / width * math.tan(fov_x / 2))
    return radius / math.sin(min(fov_x, fov_y) / 2)


def frame_box(low: Vector, high: Vector, *, fov_x: float, width: int, height: int, **orbit_options) -> list[Camera]:
    """An :func:`orbit` of cameras around the box [low, high] (m) that each see all of it
    (``orbit_options``: orbit's n_views, elevation, azimuth and up).

    The cameras look at the box centre from the distance at which the box's circumscribed
    sphere fits the narrower field of view.
    """
    low, high = _vector(low, "box low"), _vector(high, "box high")
    if not bool((low <= high).all()):
        raise InputError(f"box low {low.tolist()} is not <= high {high.tolist()} on every axis")
    radius = max(0.5 * (high - low).norm().item(), 1e-6)  # a single point still gets a view
    distance = framing_distance(radius, fov_x, width, height)
    return orbit(0.5 * (low + high), distance, fov_x=fov_x, width=width, height=height, **orbit_options)


# -- dataset files -------------------------------------------------------------------------


def load_cameras_json(path: str | os.PathLike) -> list[Camera]:
    """Cameras from a 3DGS ``cameras.json`` (INRIA's trainer writes it next to the PLY).

    Each entry: ``id``, ``img_name``, ``width``, ``height``, ``position`` [3] (m),
    ``rotation`` [3][3] camera-to-world (OpenCV axes), ``fx``, ``fy`` (pixels); the
    principal point is the image centre, as in 3DGS.
    """
    entries = _read_json(path)
    if not isinstance(entries, list) or not entries:
        raise InputError(f"{path}: expected a non-empty JSON list of cameras")
    cameras = []
    for i, entry in enumerate(entries):
        where = f"{path}: camera {i}"
        if not isinstance(entry, dict):
            raise InputError(f"{where}: expected an object, got {type(entry).__name__}")
        missing = [k for k in ("width", "height", "position", "rotation", "fx", "fy") if k not in entry]
        if missing:
            raise InputError(f"{where}: missing keys {', '.join(missing)}")
        width, height = _size(entry, "width", where), _size(entry, "height", where)
        camtoworld = torch.eye(4, dtype=torch.float64)
        camtoworld[:3, :3] = _matrix(entry["rotation"], (3, 3), f"{where}: rotation")
        camtoworld[:3, 3] = _matrix(entry["position"], (3,), f"{where}: position")
        K = torch.tensor(
            [[_number(entry, "fx", where), 0, width / 2], [0, _number(entry, "fy", where), height / 2], [0, 0, 1]],
            dtype=torch.float64,
        )
        name = str(entry.get("img_name", entry.get("id", i)))
        cameras.append(_located(from_camtoworld, where, camtoworld, K, width, height, name))
    return cameras


def save_cameras_json(path: str | os.PathLike, cameras: Sequence[Camera]) -> None:
    """Write ``cameras`` as a 3DGS ``cameras.json`` (the layout :func:`load_cameras_json`
    reads), atomically. The format has no principal point: readers put it at the image centre."""
    from clflow.fileio import atomic_write_text

    entries = [
        {
            "id": i,
            "img_name": c.name,
            "width": c.width,
            "height": c.height,
            "position": c.position.tolist(),
            "rotation": c.R.T.tolist(),
            "fy": c.fy,
            "fx": c.fx,
        }
        for i, c in enumerate(cameras)
    ]
    atomic_write_text(path, json.dumps(entries) + "\n")


def save_transforms_json(path: str | os.PathLike, cameras: Sequence[Camera]) -> None:
    """Write ``cameras`` as a NeRF-style ``transforms.json`` (OpenGL camera-to-world, per-frame
    ``w``, ``h``, ``fl_x``, ``fl_y``, ``cx``, ``cy``), atomically: unlike ``cameras.json`` it
    keeps the principal point. :func:`load_transforms_json` reads it back."""
    from clflow.fileio import atomic_write_text

    frames = [
        {
            "file_path": c.name,
            "transform_matrix": (c.camtoworld() @ OPENGL_TO_OPENCV).tolist(),
            "w": c.width,
            "h": c.height,
            "fl_x": c.fx,
            "fl_y": c.fy,
            "cx": c.cx,
            "cy": c.cy,
        }
        for c in cameras
    ]
    atomic_write_text(path, json.dumps({"frames": frames}, indent=1) + "\n")


def load_transforms_json(
    path: str | os.PathLike, *, width: int | None = None, height: int | None = None
) -> list[Camera]:
    """Cameras from a NeRF-style ``transforms.json`` (NeRF synthetic, instant-ngp, nerfstudio).

    ``frames[].transform_matrix`` is camera-to-world in OpenGL axes (converted here).
    Intrinsics: ``fl_x``/``fl_y``/``cx``/``cy`` (pixels) when present (top level or per
    frame), else ``camera_angle_x`` (rad, and ``camera_angle_y`` if given). Image size: ``w``
    and ``h`` when present, else ``width``/``height`` here, else read from the first
    frame's image file (NeRF synthetic stores ``file_path`` without the ``.png``).
    """
    path = Path(path)
    data = _read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise InputError(f"{path}: expected an object with a non-empty 'frames' list")
    cameras = []
    for i, frame in enumerate(data["frames"]):
        where = f"{path}: frames[{i}]"
        if not isinstance(frame, dict) or "transform_matrix" not in frame:
            raise InputError(f"{where}: missing 'transform_matrix'")
        meta = {**data, **frame}  # per-frame intrinsics override the shared ones
        if "w" in meta and "h" in meta:
            w, h = _size(meta, "w", where), _size(meta, "h", where)
        elif width is not None and height is not None:
            w, h = width, height
        else:
            w, h = _image_size(path.parent, frame, where)
        if "fl_x" in meta:
            fx = _number(meta, "fl_x", where)
            fy = _number(meta, "fl_y", where) if "fl_y" in meta else fx
        elif "camera_angle_x" in meta:
            fx = w / (2 * math.tan(_number(meta, "camera_angle_x", where) / 2))
            fy = h / (2 * math.tan(_number(meta, "camera_angle_y", where) / 2)) if "camera_angle_y" in meta else fx
        else:
            raise InputError(f"{where}: no intrinsics: neither 'fl_x' nor 'camera_angle_x' is given")
        cx = _number(meta, "cx", where) if "cx" in meta else w / 2
        cy = _number(meta, "cy", where) if "cy" in meta else h / 2
        K = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=torch.float64)
        camtoworld = _matrix(frame["transform_matrix"], (4, 4), f"{where}: transform_matrix") @ OPENGL_TO_OPENCV
        name = str(frame.get("file_path", i))
        cameras.append(_located(from_camtoworld, where, camtoworld, K, w, h, name))
    return cameras


def load_dataparser_transforms(path: str | os.PathLike) -> tuple[torch.Tensor, float]:
    """nerfstudio's ``dataparser_transforms.json``: ``transform`` [3, 4] = [R | t] (a proper
    rotation and a translation) and ``scale`` s > 0, which took the capture's world frame to
    the model's (a splatfacto PLY export's): x_model = s (R x + t)."""
    data = _read_json(path)
    if not isinstance(data, dict) or "transform" not in data or "scale" not in data:
        raise InputError(
            f"{path}: expected nerfstudio's dataparser transforms: an object with 'transform' (3x4) and 'scale'"
        )
    transform = _matrix(data["transform"], (3, 4), f"{path}: transform")
    scale = _number(data, "scale", str(path))
    if scale <= 0:
        raise InputError(f"{path}: 'scale' must be > 0, got {scale:g}")
    R = transform[:, :3]
    error = (R @ R.T - torch.eye(3, dtype=torch.float64)).abs().max().item()
    if error > ORTHONORMAL_TOLERANCE or torch.linalg.det(R) < 0:
        raise InputError(
            f"{path}: the transform's 3x3 part is not a rotation (max |R R^T - I| = {error:.3g}, "
            f"det {torch.linalg.det(R).item():.3g})"
        )
    return transform, scale


def transform_camera(camera: Camera, transform: torch.Tensor, scale: float) -> Camera:
    """The camera seen in the frame x' = scale (R x + t), ``transform`` = [R | t] [3, 4]:
    the same pixels; depths scale by ``scale``."""
    R, t = transform[:, :3], transform[:, 3]
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = camera.viewmat[:3, :3] @ R.T
    view[:3, 3] = scale * (camera.viewmat[:3, 3] - view[:3, :3] @ t)
    return Camera(view, camera.K.clone(), camera.width, camera.height, camera.name)


def _located(fn, where: str, *args) -> Camera:
    """Call ``fn``; prefix an :class:`InputError` with the file location ``where``."""
    try:
        return fn(*args)
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


def _read_json(path: str | os.PathLike) -> Any:
    from clflow.fileio import read_json

    return read_json(path, "camera file")


def _image_size(folder: Path, frame: dict, where: str) -> tuple[int, int]:
    import cv2

    file_path = frame.get("file_path")
    if not isinstance(file_path, str):
        raise InputError(f"{where}: no image size ('w', 'h') and no 'file_path' to read it from; give 'w' and 'h'")
    candidates = [folder / file_path, folder / (file_path + ".png")]
    for candidate in candidates:
        if candidate.is_file():
            image = cv2.imread(str(candidate), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise InputError(f"{where}: {candidate} is not a readable image (no 'w', 'h': its size is needed)")
            return int(image.shape[1]), int(image.shape[0])
    raise InputError(f"{where}: image {candidates[0]}[.png] not found (no 'w', 'h': its size is needed)")


def _matrix(value: Any, shape: tuple[int, ...], what: str) -> torch.Tensor:
    try:
        out = torch.as_tensor(value, dtype=torch.float64).clone()
    except (TypeError, ValueError, RuntimeError):
        raise InputError(f"{what}: expected numbers of shape {list(shape)}, got {value!r}") from None
    if tuple(out.shape) != shape:
        raise InputError(f"{what}: expected shape {list(shape)}, got {list(out.shape)}")
    if not torch.isfinite(out).all():
        raise InputError(f"{what}: contains non-finite values: {out.tolist()}")
    return out


def _vector(value: Vector, what: str) -> torch.Tensor:
    return _matrix(value, (3,), what)


def _number(mapping: dict, key: str, where: str) -> float:
    value = mapping[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{where}: '{key}' must be a finite number, got {value!r}")
    return float(value)


def _size(mapping: dict, key: str, where: str) -> int:
    value = _number(mapping, key, where)
    if value != int(value) or value <= 0:
        raise InputError(f"{where}: '{key}' must be a positive integer number of pixels, got {mapping[key]!r}")
    return int(value)
