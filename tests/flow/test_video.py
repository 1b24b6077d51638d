"""Video readers, time selection and crop-and-resize with consistent intrinsics."""

import numpy as np
import pytest

from clflow.errors import InputError
from clflow.flow.video import Video, crop_resize, fit_to_camera, read_video, scale_intrinsics
from clflow.media import write_image, write_video
from tests.flow._helpers import mean_abs, write_image_folder

FPS = 12.5  # a GIF stores frame durations in 1/100 s: 80 ms is exact


@pytest.mark.parametrize(
    "suffix, max_error",
    [
        (".mkv", 0.0),  # FFV1, lossless
        (".mp4", 6.0),  # H.264
        (".mov", 6.0),  # H.264 in QuickTime
        (".avi", 8.0),  # Motion-JPEG, 4:2:0 chroma
        (".webm", 6.0),  # VP9
        (".gif", 6.0),  # a palette of 256 colours per frame (Pillow)
    ],
)
def test_containers_give_the_frames_of_the_image_folder(tmp_path, translating, image_folder, suffix, max_error):
    frames = translating[0]
    folder = read_video(image_folder, fps=FPS)
    assert np.array_equal(folder.frames, frames)  # PNG is lossless and the order is numeric
    path = tmp_path / f"clip{suffix}"
    write_video(path, frames, FPS)
    video = read_video(path)
    assert (video.frame_count, video.height, video.width) == (6, 64, 80)
    assert video.fps == pytest.approx(FPS, rel=1e-6)
    np.testing.assert_allclose(video.times, np.arange(6) / FPS)
    assert mean_abs(video.frames, folder.frames) <= max_error
    assert video.describe() == f"{path}: 6 frames, 80x64, 12.5 fps"


def test_gif_reader_agrees_with_opencv_animation_decoder(tmp_path, translating):
    import cv2

    path = tmp_path / "clip.gif"
    write_video(path, translating[0], FPS)
    ok, animation = cv2.imreadanimation(str(path))
    assert ok
    decoded = np.stack([cv2.cvtColor(f[..., :3], cv2.COLOR_BGR2RGB) for f in animation.frames])
    assert np.array_equal(read_video(path).frames, decoded)


def clock(n=10, fps=10.0):
    """A video whose frame k is filled with the value 10 k."""
    frames = np.repeat((10 * np.arange(n, dtype=np.uint8))[:, None, None, None], 3, axis=-1) * np.ones(
        (1, 2, 3, 3), np.uint8
    )
    return Video(frames, np.arange(n) / fps, fps, "clock")


def values(video):
    return (video.frames[:, 0, 0, 0] // 10).tolist()


def test_window_stride_and_resample():
    video = clock()
    assert values(video.window(0.2, 0.5)) == [2, 3, 4]
    assert values(video.window(0.75)) == [8, 9]
    strided = video.every(3)
    assert values(strided) == [0, 3, 6, 9] and strided.fps == pytest.approx(10 / 3)
    np.testing.assert_allclose(strided.times, [0.0, 0.3, 0.6, 0.9])
    nearest = video.resample([0.0, 0.26, 0.34, 0.9])
    assert values(nearest) == [0, 3, 3, 9]
    sim = video.resample(np.arange(0, 0.9, 1 / 24))  # the simulation's 24 fps frame times
    assert nearest.fps is None and sim.fps == pytest.approx(24.0)
    assert values(sim)[:6] == [0, 0, 1, 1, 2, 2]  # 0, .042, .083, .125, .167, .208 s
    at_rate = video.resample_rate(24.0)
    assert at_rate.frame_count == 22 and at_rate.fps == pytest.approx(24.0)  # 0 .. 21/24 <= 0.9 s
    assert values(at_rate) == values(video.resample(np.arange(22) / 24.0))
    with pytest.raises(InputError, match="clock: resampling rate must be a positive number"):
        video.resample_rate(0.0)
    linear = video.resample([0.25, 0.5], mode="linear")
    assert linear.frames[:, 0, 0, 0].tolist() == [25, 50]


def test_time_selection_errors():
    video = clock()
    with pytest.raises(InputError, match=r"no frame in the window \[5, None\) s"):
        video.window(5.0)
    with pytest.raises(InputError, match="leave the video's span"):
        video.resample([0.0, 1.5])
    with pytest.raises(InputError, match="positive integer"):
        video.every(0)
    with pytest.raises(InputError, match="unknown resampling mode"):
        video.resample([0.1], mode="cubic")
    unknown = Video(video.frames, None, None, "folder")
    with pytest.raises(InputError, match="folder: the frame rate is unknown"):
        unknown.resample([0.1])


def blob(height, width, u, v, sigma=2.0):
    """[H, W, 3] uint8 image of a Gaussian blob centred at continuous pixel coords (u, v)."""
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    g = np.exp(-((jj - u) ** 2 + (ii - v) ** 2) / (2 * sigma**2))
    return np.repeat((255 * g).round().astype(np.uint8)[..., None], 3, -1)


def centroid(image):
    w = image[..., 0].astype(np.float64)
    jj, ii = np.meshgrid(np.arange(image.shape[1]) + 0.5, np.arange(image.shape[0]) + 0.5)
    return np.array([(w * jj).sum() / w.sum(), (w * ii).sum() / w.sum()])


def project(K, point):
    p = K @ point
    return p[:2] / p[2]


def test_crop_resize_keeps_intrinsics_consistent():
    """A 3D point's projection through the new intrinsics lands on the moved blob."""
    K = np.array([[300.0, 0, 62.0], [0, 300.0, 51.0], [0, 0, 1]])
    point = np.array([0.05, -0.02, 1.0])
    u, v = project(K, point)
    video = Video(blob(100, 120, u, v, sigma=4.0)[None], None, None, "blob")
    box = (20.5, 10.25, 110.5, 85.25)  # 90 x 75 px, fractional
    for width, height in ((45, 30), (180, 150)):  # shrink (anisotropic) and enlarge
        out, K2 = crop_resize(video, box, width, height, K)
        np.testing.assert_allclose(centroid(out.frames[0]), project(K2, point), atol=0.05)
        np.testing.assert_allclose(K2, scale_intrinsics(K, box, width, height))
    with pytest.raises(InputError, match="does not lie inside the 120x100 frame"):
        crop_resize(video, (0, 0, 130, 50), 10, 10)


def test_fit_to_camera():
    K_video = np.array([[400.0, 0, 80.0], [0, 400.0, 60.0], [0, 0, 1]])
    K_camera = np.array([[200.0, 0, 30.0], [0, 200.0, 20.0], [0, 0, 1]])
    point = np.array([0.02, 0.03, 1.0])
    u, v = project(K_video, point)
    video = Video(blob(120, 160, u, v, sigma=4.0)[None], None, None, "guide.mp4")
    out, K = fit_to_camera(video, K_video, 64, 48, K_camera)
    assert out.frames.shape == (1, 48, 64, 3)
    np.testing.assert_allclose(centroid(out.frames[0]), project(K_camera, point), atol=0.05)
    with pytest.raises(InputError, match="guide.mp4: the 200x150 camera sees .* video and camera sizes do not match"):
        fit_to_camera(video, K_video, 200, 150, K_camera)
    squashed = K_camera.copy()
    squashed[1, 1] = 150.0
    with pytest.raises(InputError, match="pixel aspect"):
        fit_to_camera(video, K_video, 64, 48, squashed)


def test_reader_errors(tmp_path, translating):
    with pytest.raises(InputError, match="missing.mp4: no such video file or image folder"):
        read_video(tmp_path / "missing.mp4")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="empty: the folder holds no image"):
        read_video(tmp_path / "empty")
    garbage = tmp_path / "garbage.mp4"
    garbage.write_bytes(b"not a video at all" * 10)
    with pytest.raises(InputError, match="garbage.mp4: (not a readable video|the video holds no decodable frame)"):
        read_video(garbage)
    with pytest.raises(InputError, match="unsupported video type '.txt'"):
        (tmp_path / "notes.txt").write_text("x")
        read_video(tmp_path / "notes.txt")
    mixed = write_image_folder(tmp_path / "mixed", translating[0][:2])
    write_image(mixed / "frame_2.png", translating[0][0][:32])
    with pytest.raises(InputError, match="frame_2.png: image is 80x32 but frame_0.png is 80x64"):
        read_video(mixed)
    good = write_image_folder(tmp_path / "good", translating[0][:2])
    with pytest.raises(InputError, match="good: frame rate must be a positive number, got -1.0"):
        read_video(good, fps=-1.0)
