"""The one video writer (H.264 in .mp4, GIF through Pillow) and the FFmpeg decoder behind read_video."""

from fractions import Fraction

import av
import numpy as np
import pytest

from clflow.errors import InputError
from clflow.fileio import WRITTEN_RECORD
from clflow.flow.video import read_video
from clflow.media import write_video


def ramp(count, height, width):
    """Frames whose grey level rises 20 per frame, with a horizontal colour gradient."""
    x = np.linspace(0, 200, width, dtype=np.float64)
    frames = np.empty((count, height, width, 3), np.uint8)
    for k in range(count):
        frames[k] = np.stack(
            [
                np.broadcast_to(x, (height, width)),
                np.full((height, width), 20.0 * k),
                np.broadcast_to(x[::-1], (height, width)),
            ],
            axis=-1,
        ).astype(np.uint8)
    return frames


def test_mp4_is_h264_in_yuv420p_with_odd_sizes_padded(tmp_path):
    frames = ramp(9, 33, 47)
    path = tmp_path / "clip.mp4"
    write_video(path, frames, 24.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == [WRITTEN_RECORD, "clip.mp4"]  # no temporary file left
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264"
        assert stream.codec_context.pix_fmt == "yuv420p"
        assert (stream.codec_context.width, stream.codec_context.height) == (48, 34)
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
    assert len(decoded) == 9
    decoded = np.stack(decoded)
    assert np.abs(decoded[:, :33, :47].astype(int) - frames).mean() < 3.0
    assert np.abs(decoded[:, 33, :47].astype(int) - frames[:, 32]).mean() < 3.0  # edge-padded row
    video = read_video(path)
    assert video.fps == pytest.approx(24.0) and video.frame_count == 9


def test_gif_is_written_by_pillow_and_loops(tmp_path):
    from PIL import Image

    frames = ramp(4, 10, 12)
    write_video(tmp_path / "clip.gif", frames, 12.5)
    with Image.open(tmp_path / "clip.gif") as gif:
        assert gif.n_frames == 4 and gif.info["loop"] == 0 and gif.info["duration"] == 80
    video = read_video(tmp_path / "clip.gif")
    assert video.fps == pytest.approx(12.5) and np.abs(video.frames.astype(int) - frames).max() <= 2


def frame_numbers(video):
    """k of each frame made by :func:`ramp` (its green level is 20 k)."""
    return np.rint(video.frames[..., 1].mean(axis=(1, 2)) / 20).astype(int).tolist()


def write_vfr(path, frames, times_ms):
    """An H.264 .mkv whose frames carry the given millisecond timestamps."""
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=30)
        stream.height, stream.width = frames.shape[1:3]
        stream.pix_fmt = "yuv420p"
        stream.codec_context.time_base = Fraction(1, 1000)
        for image, ms in zip(frames, times_ms):
            frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            frame.pts, frame.time_base = ms, Fraction(1, 1000)
            container.mux(stream.encode(frame))
        container.mux(stream.encode())


def test_variable_frame_rate_keeps_the_file_timestamps(tmp_path):
    times_ms = [0, 33, 100, 133, 250, 283]
    write_vfr(tmp_path / "vfr.mkv", ramp(6, 16, 16), times_ms)
    video = read_video(tmp_path / "vfr.mkv")
    np.testing.assert_allclose(video.times, np.array(times_ms) / 1000.0)
    assert video.fps is None and video.describe().endswith("variable frame rate")
    assert frame_numbers(video) == [0, 1, 2, 3, 4, 5]
    # the frame nearest each time is taken, not the k-th frame at an assumed rate
    assert frame_numbers(video.resample([0.1, 0.25])) == [2, 4]
    forced = read_video(tmp_path / "vfr.mkv", fps=10.0)
    np.testing.assert_allclose(forced.times, np.arange(6) / 10.0)


def test_undecodable_video_is_one_clear_line(tmp_path):
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(200))
    with pytest.raises(InputError, match=r"broken.mp4: not a readable video \(FFmpeg: .+\)") as error:
        read_video(bad)
    assert "\n" not in str(error.value)


def test_images_round_trip_rgb_rgba_and_16_bit(tmp_path):
    import cv2

    from clflow.media import read_image, to_uint8, write_image

    rgba = np.random.default_rng(0).integers(0, 256, (5, 7, 4), dtype=np.uint8)
    write_image(tmp_path / "a.png", rgba)  # RGBA kept, in RGBA order
    write_image(tmp_path / "b.png", rgba[..., :3])
    np.testing.assert_array_equal(to_uint8(read_image(tmp_path / "a.png")), rgba)
    np.testing.assert_array_equal(to_uint8(read_image(tmp_path / "b.png")), rgba[..., :3])
    grey16 = np.array([[0, 65535], [32768, 257]], np.uint16)
    cv2.imwrite(str(tmp_path / "g.png"), grey16)
    image = read_image(tmp_path / "g.png")  # grey as RGB, 16 bits scaled to [0, 1]
    assert image.shape == (2, 2, 3) and image.dtype == np.float32
    np.testing.assert_allclose(image[..., 1], grey16 / 65535, rtol=1e-6)
    for bad, message in ((tmp_path / "none.png", "image not found"), (tmp_path, "a folder, not an image")):
        with pytest.raises(InputError, match=message):
            read_image(bad)
    (tmp_path / "text.png").write_text("hello")
    with pytest.raises(InputError, match="not a readable image"):
        read_image(tmp_path / "text.png")


def test_to_uint8_clamps_rounds_half_up_and_takes_tensors():
    import torch

    from clflow.media import to_uint8

    values = np.array([-1.0, 0.0, 0.5 / 255, 1.5 / 255, 254.49 / 255, 1.0, 7.0, np.nan], np.float32)
    expected = [0, 0, 1, 2, 254, 255, 255, 0]
    assert to_uint8(values).tolist() == expected
    assert to_uint8(torch.from_numpy(values).requires_grad_()).tolist() == expected
