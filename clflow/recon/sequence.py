"""Multi-camera dynamic captures laid out as PAC-NeRF's data (Li et al., ICLR 2023).

A capture folder holds ``all_data.json``, a JSON list with one entry per image:

- ``file_path``: the image, relative to the folder, named ``r_{camera}_{frame}.png``
  (``./data/r_3_0.png``); frames -1 (the empty backdrop) and -2 (a mask of static
  objects) are PAC-NeRF's extras and are skipped;
- ``c2w``: [3, 4] or [4, 4] camera-to-world in NeRF / Blender axes (camera +x right, +y
  up, looking down -z), positions in m;
- ``intrinsic``: [3, 3] K in pixels, pixel centres at i + 0.5 (PAC-NeRF casts rays
  through (i + 0.5 - cx) / fx);
- ``time`` (optional): the frame's time in s, the same for every camera.

    seq = load_sequence("data/torus")            # the folder or its all_data.json
    seq.cameras[0]                               # clflow Camera (OpenCV axes) of camera 0
    seq.images[0][5]                             # camera 0's image of frame 5
    seq.fps                                      # from the times (None without them)

Every camera must see every frame from one fixed pose; each problem is an
:class:`InputError` naming the file and entry.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import torch

from clflow.errors import InputError
from clflow.splat.cameras import OPENGL_TO_OPENCV, Camera, from_camtoworld

INDEX_NAME = "all_data.json"
FILE_NAME = re.compile(r"^r_(\d+)_(-?\d+)$")  # PAC-NeRF's r_{camera}_{frame}
POSE_TOLERANCE = 1e-6  # max change of c2w / K entries between one camera's frames
TIME_TOLERANCE = 1e-6  # s: max disagreement of the cameras' times of one frame
SPACING_TOLERANCE = 1e-3  # max relative deviation of a frame interval from their mean


@dataclass
class Sequence:
    """A capture: ``cameras[c]`` (clflow cameras, OpenCV axes, image size from camera c's
    first image), ``images[c][f]`` (camera c's image of frame f), ``times[f]`` (s, or None
    when the index has no times) and the index file it came from."""

    index: Path
    cameras: list[Camera]
    images: list[list[Path]]
    times: list[float] | None

    @property
    def frames(self) -> int:
        return len(self.images[0])

    @property
    def fps(self) -> float | None:
        """Frames per second from the times (None without times or with one frame)."""
        if self.times is None or self.frames < 2:
            return None
        return (self.frames - 1) / (self.times[-1] - self.times[0])

    def check_frame(self, frame: int) -> None:
        """:class:`InputError` unless 0 <= ``frame`` < the frame count."""
        if not 0 <= frame < self.frames:
            raise InputError(
                f"{self.index}: frame {frame} is out of range: the sequence has frames 0 to {self.frames - 1}"
            )

    def check_camera(self, camera: int) -> None:
        """:class:`InputError` unless 0 <= ``camera`` < the camera count."""
        if not 0 <= camera < len(self.cameras):
            raise InputError(
                f"{self.index}: camera {camera} is out of range: the sequence has cameras 0 to {len(self.cameras) - 1}"
            )


def find_index(path: str | os.PathLike) -> Path:
    """The index file: ``path`` itself if it is a file, else ``path/all_data.json``."""
    path = Path(path)
    index = path if path.is_file() else path / INDEX_NAME
    if not index.is_file():
        raise InputError(
            f"{path}: no {INDEX_NAME} (the index of a PAC-NeRF-style multi-camera sequence: one "
            f"entry per image with file_path, c2w, intrinsic and time)"
        )
    return index


def pacnerf_camera(c2w, intrinsic, width: int, height: int, name: str = "") -> Camera:
    """A clflow camera from a PAC-NeRF / NeRF camera-to-world ``c2w`` [3, 4] or [4, 4]
    (OpenGL axes, m) and ``intrinsic`` [3, 3] (pixels, centres at i + 0.5)."""
    c2w = torch.as_tensor(c2w, dtype=torch.float64)
    if tuple(c2w.shape) not in ((3, 4), (4, 4)):
        raise InputError(f"c2w must be a 3x4 or 4x4 matrix, got shape {list(c2w.shape)}")
    if c2w.shape[0] == 3:
        c2w = torch.cat([c2w, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)])
    return from_camtoworld(c2w @ OPENGL_TO_OPENCV, intrinsic, width, height, name)


def load_sequence(path: str | os.PathLike) -> Sequence:
    """Read and check a PAC-NeRF-style index (the folder holding ``all_data.json``, or the
    file); see the module docstring. Reads one image per camera for its size."""

    from clflow.media import read_image

    index = find_index(path)
    from clflow.fileio import read_json

    entries = read_json(index, "sequence index")
    if not isinstance(entries, list) or not entries:
        raise InputError(f"{index}: expected a non-empty JSON list of image entries")
    table: dict[tuple[int, int], dict] = {}
    for i, entry in enumerate(entries):
        where = f"{index}: entry {i}"
        if not isinstance(entry, dict) or not isinstance(entry.get("file_path"), str):
            raise InputError(f"{where}: expected an object with a 'file_path' string")
        match = FILE_NAME.match(Path(entry["file_path"]).stem)
        if match is None:
            raise InputError(f"{where}: file_path {entry['file_path']!r} is not named r_CAMERA_FRAME.png")
        camera, frame = int(match[1]), int(match[2])
        if frame < 0:  # PAC-NeRF's backdrop (-1) and static-object mask (-2)
            continue
        missing = [k for k in ("c2w", "intrinsic") if k not in entry]
        if missing:
            raise InputError(f"{where} ({entry['file_path']}): missing {' and '.join(missing)}")
        if (camera, frame) in table:
            raise InputError(f"{where}: {entry['file_path']} is listed twice (camera {camera}, frame {frame})")
        table[camera, frame] = {**entry, "where": f"{where} ({entry['file_path']})"}
    if not table:
        raise InputError(f"{index}: no image of a frame >= 0 (only backdrops or masks)")
    n_cameras = 1 + max(c for c, _ in table)
    n_frames = 1 + max(f for _, f in table)
    for camera in range(n_cameras):
        absent = [f for f in range(n_frames) if (camera, f) not in table]
        if absent:
            seen = sorted({c for c, f in table if f == absent[0]})
            raise InputError(
                f"{index}: camera {camera} has no image of frame {absent[0]} ({len(seen)} camera(s) do: "
                f"{', '.join(map(str, seen)) or 'none'}); every one of the {n_cameras} cameras must see all {n_frames} frames"
            )
    cameras, images = [], []
    for camera in range(n_cameras):
        first = table[camera, 0]
        c2w, K = _matrix(first, "c2w", ((3, 4), (4, 4))), _matrix(first, "intrinsic", ((3, 3),))
        for frame in range(1, n_frames):
            other = table[camera, frame]
            for key, value in (("c2w", c2w), ("intrinsic", K)):
                if (_matrix(other, key, (tuple(value.shape),)) - value).abs().max() > POSE_TOLERANCE:
                    raise InputError(
                        f"{other['where']}: camera {camera}'s {key} differs from its frame 0's; "
                        f"clflow reads captures from fixed cameras"
                    )
        paths = [index.parent / table[camera, f]["file_path"] for f in range(n_frames)]
        if not paths[0].is_file():
            raise InputError(f"{first['where']}: the image {paths[0]} does not exist")
        height, width = read_image(paths[0]).shape[:2]
        try:
            cameras.append(pacnerf_camera(c2w, K, width, height, paths[0].stem))
        except InputError as exc:
            raise InputError(f"{first['where']}: {exc}") from None
        images.append(paths)
    return Sequence(index, cameras, images, _times(table, n_cameras, n_frames, index))


def _matrix(entry: dict, key: str, shapes: tuple[tuple[int, ...], ...]) -> torch.Tensor:
    try:
        value = torch.as_tensor(entry[key], dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise InputError(f"{entry['where']}: {key} must be a matrix of numbers, got {entry[key]!r}") from None
    if tuple(value.shape) not in shapes or not torch.isfinite(value).all():
        raise InputError(
            f"{entry['where']}: {key} must be a finite {' or '.join('x'.join(map(str, s)) for s in shapes)} "
            f"matrix, got {entry[key]!r}"
        )
    return value


def _times(table: dict, n_cameras: int, n_frames: int, index: Path) -> list[float] | None:
    """Each frame's time (s), checked: the same for every camera, evenly spaced and
    increasing; None when no entry has a time."""
    timed = [e for e in table.values() if "time" in e]
    if not timed:
        return None
    if len(timed) != len(table):
        untimed = next(e for e in table.values() if "time" not in e)
        raise InputError(f"{untimed['where']}: has no time while other entries have one")
    times = []
    for frame in range(n_frames):
        values = []
        for camera in range(n_cameras):
            entry = table[camera, frame]
            value = entry["time"]
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise InputError(f"{entry['where']}: time must be a finite number of seconds, got {value!r}")
            values.append(float(value))
        if max(values) - min(values) > TIME_TOLERANCE:
            raise InputError(
                f"{index}: the cameras' times of frame {frame} differ ({min(values):g} to {max(values):g} "
                f"s); clflow needs synchronised cameras"
            )
        times.append(values[0])
    steps = [b - a for a, b in zip(times, times[1:])]
    if steps and min(steps) <= 0:
        raise InputError(f"{index}: the times must increase with the frame number, got {times}")
    if steps and max(abs(s - sum(steps) / len(steps)) for s in steps) > SPACING_TOLERANCE * sum(steps) / len(steps):
        raise InputError(f"{index}: the frames are not evenly spaced in time ({times}); a video needs one frame rate")
    return times
