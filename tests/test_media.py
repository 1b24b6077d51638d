"""The one video writer (H.264 in .mp4, GIF through Pillow) and the FFmpeg decoder behind read_video."""

from fractions import Fraction

import av
import numpy as np
import pytest

from clflow.errors import InputError
from clflow.flow.video import read_video
from clflow.media import write_video


def ramp(count, height, width):
    """Frames whose grey level rises 20 per frame, with a horizontal colour gradient."""
    x = np.linspace(0, 200, width, dtype=np.float64)
    frames = np.empty((count, height, width, 3), np.uint8)
    for k in range(count):
        frames[k] = np.stack([np.broadcast_to(x, (height, width)), np.full((height, width), 20.0 * k),
                              np.broadcast_to(x[::-1], (height, width))], axis=-1).astype(np.uint8)
    return frames


def test_mp4_is_h264_in_yuv420p_with_odd_sizes_padded(tmp_path):
    frames = ramp(9, 33, 47)
    path = tmp_path / "clip.mp4"
    write_video(path, frames, 24.0)
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]  # no temporary file left
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
