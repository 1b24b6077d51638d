"""Image and video files: the one reader and writer of every image and the one writer of every
video clflow writes, and the video decoder behind :func:`clflow.flow.video.read_video`.

    write_video("out.mp4", frames, 24.0)      # [T, H, W, 3] uint8 RGB -> H.264, yuv420p
    write_video("out.gif", frames, 12.5)      # GIF through Pillow, looping
    frames, times = decode_video("in.mp4")    # [T, H, W, 3] uint8 RGB, [T] s from the first frame
    rgba = read_image("in.png")               # [H, W, 3 or 4] float32 RGB(A) in [0, 1]
    write_image("out.png", to_uint8(rgba))    # values in [0, 1] -> uint8, rounded half up

Videos go through PyAV (FFmpeg's libraries, libx264 included in its wheels): ``.mp4`` and
``.mov`` hold H.264 in yuv420p, which browsers, GitHub and editors play; odd frame sizes are
padded by one pixel (yuv420p needs even sizes). All files are written atomically.
"""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path

import numpy as np

from clflow.errors import ClflowError, InputError
from clflow.fileio import atomic_path
from clflow.limits import why_not_written

#: (codec, pixel format) each video suffix is written with: H.264 where it will be played,
#: FFV1 (lossless) in .mkv, VP9 in .webm, Motion-JPEG in .avi.
VIDEO_CODECS = {
    ".mp4": ("libx264", "yuv420p"),
    ".mov": ("libx264", "yuv420p"),
    ".mkv": ("ffv1", "bgr0"),
    ".webm": ("libvpx-vp9", "yuv420p"),
    ".avi": ("mjpeg", "yuvj420p"),
}
#: x264's constant-rate factor (0 lossless .. 51; 18 looks lossless on flow colours).
H264_CRF = 18


def read_image(path: str | os.PathLike) -> np.ndarray:
    """[H, W, 3 or 4] float32 RGB(A) in [0, 1] of an 8- or 16-bit image file (grey as RGB;
    any format OpenCV reads). A missing, unreadable or other-depth file raises InputError."""
    import cv2

    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: a folder, not an image")
    if not path.exists():
        raise InputError(f"{path}: image not found")
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None or data.size == 0:
        raise InputError(f"{path}: not a readable image (not a format OpenCV knows, or a damaged file)")
    if data.dtype not in (np.uint8, np.uint16):
        raise InputError(f"{path}: {data.dtype} pixels; clflow reads 8- and 16-bit images")
    scale = np.float32(1 / np.iinfo(data.dtype).max)
    if data.ndim == 2:
        data = np.repeat(data[..., None], 3, axis=2)
    order = [2, 1, 0, 3][: data.shape[2]]  # OpenCV's BGR(A) to RGB(A)
    return np.ascontiguousarray(data[..., order]).astype(np.float32) * scale


def to_uint8(values) -> np.ndarray:
    """[..., C] values in [0, 1] (a numpy array or a torch tensor; clamped, NaN as 0) as a
    uint8 array 0..255, rounded half up."""
    if hasattr(values, "detach"):  # a torch tensor, on any device
        values = values.detach().cpu().numpy()
    values = np.clip(np.nan_to_num(np.asarray(values, np.float32)), 0, 1)
    return (values * np.float32(255) + np.float32(0.5)).astype(np.uint8)


def write_image(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write a [H, W, 3] RGB or [H, W, 4] RGBA uint8 image (PNG, JPEG, ... by suffix) atomically."""
    import cv2

    image = np.asarray(image, np.uint8)
    to_bgr = cv2.COLOR_RGBA2BGRA if image.ndim == 3 and image.shape[2] == 4 else cv2.COLOR_RGB2BGR
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(image, to_bgr)):
            raise ClflowError(f"{path}: {why_not_written(path) or 'OpenCV cannot write an image of this type'}")


def write_video(path: str | os.PathLike, frames: np.ndarray, fps: float) -> None:
    """Write [T, H, W, 3] uint8 RGB frames at ``fps`` frames/s atomically; the suffix picks
    the format (:data:`VIDEO_CODECS`, or ``.gif``)."""
    path = Path(path)
    frames = np.asarray(frames, np.uint8)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] < 1:
        raise InputError(f"{path}: video frames must be [T, H, W, 3] with T >= 1, got shape {frames.shape}")
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"{path}: frame rate must be positive, got {fps!r}")
    suffix = path.suffix.lower()
    if suffix != ".gif" and suffix not in VIDEO_CODECS:
        raise InputError(f"{path}: unsupported video suffix {suffix!r}; use .gif or one of {', '.join(VIDEO_CODECS)}")
    with atomic_path(path) as tmp:
        if suffix == ".gif":
            _write_gif(tmp, frames, fps)
        else:
            _encode(tmp, path, frames, fps, *VIDEO_CODECS[suffix])


def _write_gif(path: Path, frames: np.ndarray, fps: float) -> None:
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    # GIF stores frame durations in 1/100 s; Pillow rounds the milliseconds to that.
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:], duration=1000.0 / fps, loop=0)


def _encode(tmp: Path, path: Path, frames: np.ndarray, fps: float, codec: str, pix_fmt: str) -> None:
    import av

    if pix_fmt == "yuv420p":  # chroma is subsampled 2x2: pad odd sizes with the edge pixels
        frames = np.pad(frames, ((0, 0), (0, frames.shape[1] % 2), (0, frames.shape[2] % 2), (0, 0)), mode="edge")
    options = {"movflags": "+faststart"} if path.suffix.lower() in (".mp4", ".mov") else {}
    try:
        with av.open(str(tmp), "w", options=options) as container:
            stream = container.add_stream(codec, rate=Fraction(fps).limit_denominator(1 << 16))
            stream.height, stream.width = frames.shape[1:3]
            stream.pix_fmt = pix_fmt
            if codec == "libx264":
                stream.options = {"crf": str(H264_CRF)}
            for k, image in enumerate(frames):
                frame = av.VideoFrame.from_ndarray(image, format="rgb24")
                frame.pts = k
                container.mux(stream.encode(frame))
            container.mux(stream.encode())
    except av.error.FFmpegError as e:  # a full disk or an unwritable folder is named as such
        raise ClflowError(f"{path}: {why_not_written(tmp) or f'FFmpeg could not write {codec} video: {e}'}") from e


def decode_video(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None, float | None]:
    """Decode the first video stream of a file (any format FFmpeg reads, GIF included).

    Returns [T, H, W, 3] uint8 RGB frames, their [T] times in seconds from the first frame
    (the file's timestamps, so a variable frame rate keeps its timing; None when the file has
    none), and the stream's declared frame rate (None when it declares none).
    """
    import av

    frames, times, listed = [], [], 0
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise InputError(f"{path}: the file holds no video stream")
            stream = container.streams.video[0]
            listed = stream.frames  # what the container's index says (0: not said)
            rate = stream.average_rate or stream.guessed_rate
            for frame in container.decode(stream):
                image = frame.to_ndarray(format="rgb24")
                if frames and image.shape != frames[0].shape:
                    raise InputError(f"{path}: frame {len(frames)} changes size; cannot read a variable-size video")
                frames.append(image)
                times.append(frame.time)
    except av.error.FFmpegError as e:
        if not frames:
            raise InputError(f"{path}: not a readable video (FFmpeg: {e.strerror or e})") from e
        listed = max(listed, len(frames) + 1)  # decoding broke off: the rest is damaged
    if not frames:
        raise InputError(f"{path}: the video holds no decodable frame")
    if len(frames) < listed:
        raise InputError(f"{path}: damaged video: only the first {len(frames)} of its {listed} frames decode")
    stamps = None if None in times else np.asarray(times, np.float64) - times[0]
    return np.stack(frames), stamps, float(rate) if rate else None
