"""The guidance's camera motion and exposure taken out over its static pixels
(clflow.flow.stabilise): a known shake and flicker recovered, a steady video left the same
bits, a plain backdrop said to show no motion, bad input refused."""

import numpy as np
import pytest

from clflow.errors import InputError
from clflow.flow.stabilise import stabilise

SIZE = 96


def scene_frames(shifts, rolls, gains, offsets, textured=True, seed=0):
    """[T, SIZE, SIZE, 3] uint8: a static textured backdrop (or a flat one) seen by a camera
    moved by ``shifts`` [T, 2] px and ``rolls`` [T] deg about the image centre, a square
    object moving 1 px a frame to the right in the middle, each frame's exposure gain x level +
    offset; and the static mask [SIZE, SIZE] (away from the object's path)."""
    import cv2

    rng = np.random.default_rng(seed)
    if textured:  # grain a few pixels across, grey levels 128 +- 40
        backdrop = cv2.GaussianBlur(rng.uniform(0, 255, (SIZE, SIZE, 3)), (0, 0), 2.0)
        backdrop = np.clip((backdrop - backdrop.mean()) * 40 / backdrop.std() + 128, 10, 245)
    else:
        backdrop = np.full((SIZE, SIZE, 3), 90.0)
    frames = []
    for t, ((dx, dy), roll, gain, offset) in enumerate(zip(shifts, rolls, gains, offsets)):
        frame = backdrop.copy()
        frame[40:56, 36 + t : 52 + t] = (230, 40, 40)
        warp = cv2.getRotationMatrix2D((SIZE / 2, SIZE / 2), roll, 1.0)
        warp[:, 2] += (dx, dy)
        frame = cv2.warpAffine(frame, warp, (SIZE, SIZE), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT101)
        frames.append(np.clip(gain * frame + offset + 0.5, 0, 255).astype(np.uint8))
    static = np.ones((SIZE, SIZE), bool)
    static[28:68, 24:76] = False
    return np.stack(frames), static


def steady(count):
    return np.zeros((count, 2)), np.zeros(count), np.ones(count), np.zeros(count)


def test_a_steady_evenly_lit_video_comes_back_the_same_bits():
    frames, static = scene_frames(*steady(6))
    out, report = stabilise(frames, static)
    assert out is frames
    assert report.record()["frames_changed"] == 0 and report.record()["note"] == ""
    assert np.array_equal(report.warps, np.repeat(np.eye(2, 3)[None], 6, axis=0))


def test_an_object_that_moves_across_the_static_pixels_moves_no_camera_and_no_exposure():
    """A bar sweeping down the backdrop and the square moving out of its mask change a third
    of the static pixels (and cover corners there): the robust fits leave the steady, evenly
    lit video as it is."""
    frames, static = scene_frames(*steady(6))
    static[:] = True
    static[40:56, 36:52] = False  # only the square at rest is masked; it then moves 5 px on
    frames = frames.copy()
    for t in range(6):  # and a bright bar sweeps down the left of the backdrop
        frames[t, 6 * t : 6 * t + 20, 4:60] = (250, 250, 60)
    out, report = stabilise(frames, static)
    assert out is frames and report.record()["frames_changed"] == 0


def test_a_shaking_camera_and_a_flickering_exposure_are_recovered_and_removed():
    shifts = np.array([[0, 0], [0.6, -0.3], [1.4, 0.2], [0.9, 1.1], [-0.5, 1.6], [-1.2, 0.8]])
    rolls = np.array([0.0, 0.2, -0.1, 0.4, 0.6, 0.3])
    gains = np.array([1.0, 1.05, 0.96, 1.08, 0.93, 1.02])
    offsets = np.array([0.0, 3.0, -2.0, 4.0, -3.0, 1.0])
    frames, static = scene_frames(shifts, rolls, gains, offsets)
    still, _ = scene_frames(*steady(6))
    out, report = stabilise(frames, static)
    centre = np.array([SIZE / 2, SIZE / 2])
    for t in range(1, 6):
        warp = report.warps[t]
        assert warp[:, :2] @ centre + warp[:, 2] - centre == pytest.approx(-shifts[t], abs=0.08)
        assert np.degrees(np.arctan2(warp[1, 0], warp[0, 0])) == pytest.approx(rolls[t], abs=0.08)  # 0.1 px at a corner
        levels = np.array([40.0, 128.0, 220.0])  # frame t's levels back on frame 0's, within 2 grey levels
        fitted = report.gains[t][:, None] * levels + report.offsets[t][:, None]
        assert np.abs(fitted - (levels - offsets[t]) / gains[t]).max() < 2.0
    inner = static.copy()
    inner[:6], inner[-6:], inner[:, :6], inner[:, -6:] = False, False, False, False  # the warp's replicated border
    before = [np.abs(f.astype(float) - still[0])[inner].mean() for f in frames[1:]]
    after = [np.abs(f.astype(float) - still[0])[inner].mean() for f in out[1:]]
    assert max(after) < 3.0 < min(before)
    record = report.record()
    assert record["frames_changed"] == 5 and record["motion_removed_px"]["max"] > 1.0


def test_the_stabilised_video_shows_a_still_backdrop_to_the_flow():
    from clflow.flow.optical_flow import observed_flow

    shifts = np.cumsum(np.random.default_rng(3).normal(0, 0.5, (8, 2)), axis=0)
    shifts[0] = 0
    frames, static = scene_frames(shifts, np.zeros(8), np.ones(8), np.zeros(8))
    out, _ = stabilise(frames, static)
    inner = static.copy()
    inner[:8], inner[-8:], inner[:, :8], inner[:, -8:] = False, False, False, False
    speed = lambda flow: float(np.linalg.norm(flow, axis=-1)[:, inner].mean())  # noqa: E731
    assert speed(observed_flow(out)) < 0.15 < 0.4 < speed(observed_flow(frames))


def test_a_plain_backdrop_leaves_the_camera_alone_and_says_so():
    shifts = np.array([[0, 0], [1.0, 0.0], [2.0, 0.0]])
    frames, static = scene_frames(shifts, np.zeros(3), np.ones(3), np.zeros(3), textured=False)
    out, report = stabilise(frames, static)
    assert "not removed" in report.note and "static corners" in report.note
    assert np.array_equal(out, frames) and not report.motion_px.any()


def test_bad_frames_and_masks_are_refused():
    frames, static = scene_frames(*steady(3))
    with pytest.raises(InputError, match="uint8"):
        stabilise(frames.astype(np.float32), static)
    with pytest.raises(InputError, match="T >= 2"):
        stabilise(frames[:1], static)
    with pytest.raises(InputError, match="static mask"):
        stabilise(frames, static[:10])
