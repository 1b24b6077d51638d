"""Guidance video input: read, select a time window, resample in time, crop and resize.

    video = read_video("guide.mp4")                 # or a .gif, .avi, .webm, an image folder
    video.frames                                    # [T, H, W, 3] uint8 RGB
    video = video.window(0.0, 2.0).every(2)         # seconds [start, end), every 2nd frame
    video = video.resample(sim_times)               # frames at the simulation's times (s)
    video = video.resample_rate(24.0)               # or at a rate (frames/s)
    video, K = fit_to_camera(video, K_video, width, height, K_camera)

Pixel coordinates follow the rasteriser: pixel (i, j) has its centre at (j + 0.5, i + 0.5),
so a crop-and-resize is the affine map u' = s (u - x0) of continuous coordinates and the
intrinsics change by the same map (fx' = s fx, cx' = s (cx - x0)).
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path
from typing import Literal, Sequence

import numpy as np

from clflow.errors import InputError

#: Suffixes read through FFmpeg (PyAV; GIF included).
VIDEO_SUFFIXES = (".mp4", ".avi", ".webm", ".mkv", ".mov", ".gif")
#: Suffixes of frames in an image folder; the number in each name gives the order.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


@dataclasses.dataclass(frozen=True)
class Video:
    """Frames of a guidance video with their times.

    Attributes:
        frames: [T, H, W, 3] uint8 RGB.
        times: [T] float64 seconds from the first frame, or None when the frame
            rate is unknown (an image folder read without ``fps``).
        fps: frames per second of the source (None: unknown, or variable: then ``times``
            holds the file's own timestamps).
        source: the file or folder the frames came from (named in error messages).
    """

    frames: np.ndarray
    times: np.ndarray | None
    fps: float | None
    source: str

    @property
    def frame_count(self) -> int:
        return self.frames.shape[0]

    @property
    def height(self) -> int:
        return self.frames.shape[1]

    @property
    def width(self) -> int:
        return self.frames.shape[2]

    def describe(self) -> str:
        fps = f"{self.fps:g} fps" if self.fps else "unknown fps" if self.times is None else "variable frame rate"
        return f"{self.source}: {self.frame_count} frames, {self.width}x{self.height}, {fps}"

    def _times(self, what: str) -> np.ndarray:
        if self.times is None:
            raise InputError(f"{self.source}: the frame rate is unknown, cannot {what}; pass fps= when reading it")
        return self.times

    def _subset(self, index: np.ndarray, fps: float | None) -> "Video":
        times = None if self.times is None else self.times[index]
        return Video(np.ascontiguousarray(self.frames[index]), times, fps, self.source)

    def window(self, start: float = 0.0, end: float | None = None) -> "Video":
        """Frames whose time lies in [start, end) seconds (end None: to the last frame)."""
        t = self._times("select a time window")
        keep = (t >= start - 1e-9) & (t < (np.inf if end is None else end) - 1e-9)
        if not keep.any():
            raise InputError(
                f"{self.source}: no frame in the window [{start:g}, {end}) s; the video spans [{t[0]:g}, {t[-1]:g}] s"
            )
        return self._subset(np.flatnonzero(keep), self.fps)

    def every(self, stride: int) -> "Video":
        """Every ``stride``-th frame, starting with the first."""
        if int(stride) != stride or stride < 1:
            raise InputError(f"{self.source}: frame stride must be a positive integer, got {stride!r}")
        return self._subset(
            np.arange(0, self.frame_count, int(stride)), fps=None if self.fps is None else self.fps / stride
        )

    def resample(self, times: Sequence[float], mode: Literal["nearest", "linear"] = "nearest") -> "Video":
        """Frames at the given ``times`` (s), e.g. the simulation's frame times.

        ``nearest`` picks the closest source frame (motion stays sharp, the right choice for
        optical flow); ``linear`` blends the two neighbouring frames. Times outside the
        video's span are an error, not an extrapolation.
        """
        t = self._times("resample it")
        times = np.asarray(times, dtype=np.float64).reshape(-1)
        if times.size == 0:
            raise InputError(f"{self.source}: no resampling times given")
        tol = 1e-6 * max(1.0, abs(t[-1]))
        if times.min() < t[0] - tol or times.max() > t[-1] + tol:
            raise InputError(
                f"{self.source}: resampling times [{times.min():g}, {times.max():g}] s leave the "
                f"video's span [{t[0]:g}, {t[-1]:g}] s"
            )
        if len(t) > 1:  # a time in a gap would take a frame from the gap's edge: a false jump in the motion
            period = float(np.median(np.diff(t)))
            nearest = np.abs(t[None, :] - times[:, None]).min(axis=1)
            far = nearest > GAP_TOLERANCE * period + tol
            if far.any():
                when = float(times[np.argmax(far)])
                before, after = t[t < when].max(), t[t > when].min()
                raise InputError(
                    f"{self.source}: no frame near t = {when:.4g} s: the frames jump from {before:.4g} s to "
                    f"{after:.4g} s (they are {period:.4g} s apart elsewhere), so frames are missing; restore "
                    f"them or renumber / re-encode the video without the gap"
                )
        if mode == "nearest":
            index = np.clip(np.searchsorted(t, times), 1, len(t) - 1) if len(t) > 1 else np.zeros(len(times), int)
            if len(t) > 1:
                index = np.where(np.abs(t[index - 1] - times) <= np.abs(t[index] - times), index - 1, index)
            frames = self.frames[index]
        elif mode == "linear":
            position = np.interp(times, t, np.arange(len(t), dtype=np.float64))
            lo = np.floor(position).astype(int)
            hi = np.minimum(lo + 1, len(t) - 1)
            w = (position - lo)[:, None, None, None]
            blend = (1.0 - w) * self.frames[lo] + w * self.frames[hi]
            frames = np.clip(np.rint(blend), 0, 255).astype(np.uint8)
        else:
            raise InputError(f"unknown resampling mode {mode!r}; choose 'nearest' or 'linear'")
        step = np.diff(times)
        uniform = len(times) > 1 and step[0] > 0 and np.allclose(step, step[0], rtol=1e-6, atol=0.0)
        return Video(np.ascontiguousarray(frames), times, 1.0 / float(step[0]) if uniform else None, self.source)

    def resample_rate(self, fps: float, mode: Literal["nearest", "linear"] = "nearest") -> "Video":
        """Frames at ``fps`` frames per second from the first frame's time to the last's."""
        t = self._times("resample it")
        if not (np.isfinite(fps) and fps > 0):
            raise InputError(f"{self.source}: resampling rate must be a positive number of frames/s, got {fps!r}")
        count = int(np.floor((t[-1] - t[0]) * fps + 1e-6)) + 1
        return self.resample(t[0] + np.arange(count) / fps, mode)


def _natural_key(path: Path) -> tuple:
    return tuple(int(p) if p.isdigit() else p for p in re.split(r"(\d+)", path.name))


#: a resampling time farther than this many source frame periods from every frame lies in a
#: gap of the video (a missing frame), not between two frames
GAP_TOLERANCE = 0.5


def _frame_positions(folder: Path, files: list[Path]) -> np.ndarray | None:
    """Each frame's position in frame periods from the first, from the numbers in their names
    (the last number of each, in steps of their greatest common step): a missing frame leaves
    a gap instead of shifting every later frame's time. None for unnumbered names."""
    numbers = []
    for f in files:
        found = re.findall(r"\d+", f.stem)
        if not found:
            return None  # unnumbered names: their natural order is all there is
        numbers.append(int(found[-1]))
    steps = np.diff(numbers)
    if (steps <= 0).any():
        k = int(np.argmax(steps <= 0))
        raise InputError(f"{folder}: {files[k].name} and {files[k + 1].name} have the same frame number {numbers[k]}")
    step = int(np.gcd.reduce(steps)) if len(steps) else 1
    return (np.asarray(numbers) - numbers[0]) / step


def _read_image_folder(folder: Path, fps: float | None) -> Video:
    from clflow.media import read_image, to_uint8

    files = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=_natural_key)
    if not files:
        raise InputError(f"{folder}: the folder holds no image ({', '.join(IMAGE_SUFFIXES)})")
    positions = _frame_positions(folder, files)
    frames = []
    for f in files:
        image = to_uint8(read_image(f)[..., :3])
        if frames and image.shape != frames[0].shape:
            raise InputError(
                f"{f}: image is {image.shape[1]}x{image.shape[0]} but {files[0].name} is "
                f"{frames[0].shape[1]}x{frames[0].shape[0]}; all frames must have one size"
            )
        frames.append(image)
    if positions is None or fps is None or np.array_equal(positions, np.arange(len(files))):
        return _make_video(np.stack(frames), fps, str(folder))
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"{folder}: frame rate must be a positive number, got {fps!r}")
    return Video(np.stack(frames), positions / fps, None, str(folder))  # frames missing: times from the numbers


def _read_container(path: Path, fps: float | None) -> Video:
    from clflow.media import decode_video

    frames, stamps, rate = decode_video(path)
    if fps is not None or stamps is None or len(stamps) < 2:
        return _make_video(frames, fps or rate, str(path))
    steps = np.diff(stamps)
    if not (steps > 0).all():
        raise InputError(f"{path}: frame timestamps do not increase (frame {int(np.argmin(steps)) + 1})")
    period = 1.0 / rate if rate else float(np.median(steps))
    if np.all(np.abs(steps - period) <= 0.01 * period):  # constant rate (timestamps are rounded)
        return _make_video(frames, 1.0 / period, str(path))
    return Video(frames, stamps, None, str(path))  # variable frame rate: the file's own times


def _make_video(frames: np.ndarray, fps: float | None, source: str) -> Video:
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise InputError(f"{source}: frame rate must be a positive number, got {fps!r}")
    times = None if fps is None else np.arange(frames.shape[0], dtype=np.float64) / fps
    return Video(frames, times, fps, source)


def read_video(path: str | os.PathLike, *, fps: float | None = None) -> Video:
    """Read a video file (mp4, avi, webm, mkv, mov, GIF) or a folder of numbered images.

    Args:
        path: the file, or a folder of images ordered by the number in their names.
        fps: frame rate in frames per second; overrides the file's and is the only source
            of timing for an image folder (without it the folder's times are unknown).
            Without it a file with a variable frame rate keeps its own timestamps.

    Returns:
        :class:`Video` with [T, H, W, 3] uint8 RGB frames.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such video file or image folder")
    if path.is_dir():
        return _read_image_folder(path, fps)
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise InputError(
            f"{path}: unsupported video type {path.suffix!r}; expected one of {', '.join(VIDEO_SUFFIXES)} or an image folder"
        )
    return _read_container(path, fps)


def scale_intrinsics(K: np.ndarray, box: Sequence[float], width: int, height: int) -> np.ndarray:
    """Intrinsics after cropping ``box`` = (x0, y0, x1, y1) (continuous pixel coordinates)
    and resizing the crop to ``width`` x ``height`` pixels. K: [3, 3] pinhole."""
    x0, y0, x1, y1 = (float(v) for v in box)
    sx, sy = width / (x1 - x0), height / (y1 - y0)
    K = np.array(K, dtype=np.float64)
    out = K.copy()
    out[0, 0], out[0, 1], out[0, 2] = sx * K[0, 0], sx * K[0, 1], sx * (K[0, 2] - x0)
    out[1, 1], out[1, 2] = sy * K[1, 1], sy * (K[1, 2] - y0)
    return out


def crop_resize(
    video: Video, box: Sequence[float], width: int, height: int, K: np.ndarray | None = None
) -> tuple[Video, np.ndarray | None]:
    """Crop ``box`` = (x0, y0, x1, y1) in continuous pixel coordinates (may be fractional)
    and resize to ``width`` x ``height``; returns the video and the matching intrinsics
    (None when ``K`` is None). The box must lie inside the frame."""
    import cv2

    x0, y0, x1, y1 = (float(v) for v in box)
    if not (0 <= x0 < x1 <= video.width + 1e-6 and 0 <= y0 < y1 <= video.height + 1e-6):
        raise InputError(
            f"{video.source}: crop box ({x0:g}, {y0:g}, {x1:g}, {y1:g}) does not lie inside the "
            f"{video.width}x{video.height} frame"
        )
    if int(width) < 1 or int(height) < 1:
        raise InputError(f"{video.source}: output size must be positive, got {width}x{height}")
    sx, sy = width / (x1 - x0), height / (y1 - y0)
    # u' = s (u - x0) on continuous coordinates, u = j + 0.5; warpAffine works on indices j.
    M = np.array([[sx, 0.0, sx * (0.5 - x0) - 0.5], [0.0, sy, sy * (0.5 - y0) - 0.5]])
    # Low-pass before shrinking so the bilinear resampling does not alias.
    sigma_x, sigma_y = (0.5 * np.sqrt(max(1.0 / s**2 - 1.0, 0.0)) for s in (sx, sy))
    frames = []
    for frame in video.frames:
        if sigma_x > 0.1 or sigma_y > 0.1:
            frame = cv2.GaussianBlur(frame, (0, 0), sigmaX=max(sigma_x, 1e-3), sigmaY=max(sigma_y, 1e-3))
        frames.append(
            cv2.warpAffine(frame, M, (int(width), int(height)), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        )
    out = Video(np.stack(frames), video.times, video.fps, video.source)
    return out, None if K is None else scale_intrinsics(K, (x0, y0, x1, y1), width, height)


def fit_to_camera(
    video: Video, K_video: np.ndarray, width: int, height: int, K_camera: np.ndarray
) -> tuple[Video, np.ndarray]:
    """Crop and resize a video taken with intrinsics ``K_video`` so that it is what a
    ``width`` x ``height`` camera with intrinsics ``K_camera`` sees (same optical axis).

    The two cameras must share their pixel aspect (fx/fy) and have no skew; the camera's
    field of view must lie inside the video's. Returns the video and K_camera (float64).
    """
    Kv, Kc = np.asarray(K_video, np.float64), np.asarray(K_camera, np.float64)
    for name, K in (("video", Kv), ("camera", Kc)):
        if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0 or K[0, 1] != 0:
            raise InputError(
                f"{video.source}: {name} intrinsics must be a finite [3, 3] pinhole matrix without skew, got {K.tolist()}"
            )
    sx, sy = Kc[0, 0] / Kv[0, 0], Kc[1, 1] / Kv[1, 1]
    if abs(sx - sy) > 1e-6 * max(sx, sy):
        raise InputError(
            f"{video.source}: the video's pixel aspect fx/fy = {Kv[0, 0] / Kv[1, 1]:g} differs from the "
            f"camera's {Kc[0, 0] / Kc[1, 1]:g}; cannot map one onto the other by crop and resize"
        )
    x0, y0 = Kv[0, 2] - Kc[0, 2] / sx, Kv[1, 2] - Kc[1, 2] / sy
    box = (x0, y0, x0 + width / sx, y0 + height / sy)
    tol = 1e-6 * max(video.width, video.height)
    if box[0] < -tol or box[1] < -tol or box[2] > video.width + tol or box[3] > video.height + tol:
        raise InputError(
            f"{video.source}: the {width}x{height} camera sees the video region "
            f"({box[0]:.1f}, {box[1]:.1f})-({box[2]:.1f}, {box[3]:.1f}) px, which leaves the "
            f"{video.width}x{video.height} frame: video and camera sizes do not match"
        )
    box = (max(box[0], 0.0), max(box[1], 0.0), min(box[2], video.width), min(box[3], video.height))
    out, _ = crop_resize(video, box, width, height)
    return out, Kc.copy()
