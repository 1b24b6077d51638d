"""Observed optical flow against known motion; consistency and object masks."""

import numpy as np
import pytest

from clflow.errors import ClflowError, InputError
from clflow.flow.metrics import endpoint_error
from clflow.flow.optical_flow import (
    DIS_PRESETS,
    backward_flow,
    flow_confidence,
    forward_backward_mask,
    mask_from_alpha,
    mask_from_box,
    mask_from_image,
    observed_confidence,
    observed_flow,
    shift_mean_flow,
)
from clflow.flow.synthetic import Motion, moving_texture, textured_image
from clflow.media import write_image

HEIGHT, WIDTH = 96, 128
MOTIONS = {
    "translate": Motion(shift=(2.3, -1.4)),
    "rotate": Motion(angle=np.deg2rad(1.5)),
    "scale": Motion(scale=1.02),
    "similarity": Motion(shift=(1.0, 0.5), angle=0.01, scale=0.99),
}
OBJECT_BOX = (16, 16, WIDTH - 16, HEIGHT - 16)  # away from the frame border, where texture leaves


@pytest.mark.parametrize("motion", MOTIONS.values(), ids=MOTIONS.keys())
@pytest.mark.parametrize("method", ["dis", "farneback"])
def test_flow_of_known_motion(motion, method):
    frames, truth = moving_texture(3, HEIGHT, WIDTH, motion, seed=2)
    flow = observed_flow(frames, method)
    assert flow.shape == (2, HEIGHT, WIDTH, 2) and flow.dtype == np.float32
    assert endpoint_error(flow, truth, mask_from_box(OBJECT_BOX, WIDTH, HEIGHT)) < 0.2


@pytest.mark.parametrize("preset", DIS_PRESETS)
def test_dis_presets(preset):
    frames, truth = moving_texture(2, HEIGHT, WIDTH, MOTIONS["translate"], seed=3)
    assert endpoint_error(observed_flow(frames, preset=preset), truth, mask_from_box(OBJECT_BOX, WIDTH, HEIGHT)) < 0.25


def test_forward_backward_mask(translating):
    frames, _ = moving_texture(3, HEIGHT, WIDTH, MOTIONS["similarity"], seed=4)
    forward = observed_flow(frames)
    backward = observed_flow(frames[::-1].copy())[::-1]
    valid = forward_backward_mask(forward, backward)
    assert valid.shape == (2, HEIGHT, WIDTH)
    assert valid.mean() > 0.9
    # A backward flow that does not undo a 1.7 px motion: |w + w_b|^2 = 2.8 px^2 > bound.
    forward = observed_flow(translating[0])
    assert forward_backward_mask(forward, np.zeros_like(forward)).mean() < 0.01
    # Pixels carried out of the frame are invalid: a 3 px shift right leaves the last 3 columns.
    shift = np.zeros((HEIGHT, WIDTH, 2), np.float32)
    shift[..., 0] = 3.0
    valid = forward_backward_mask(shift, -shift)
    assert valid[:, : WIDTH - 3].all() and not valid[:, WIDTH - 3 :].any()


def square_on_texture(x0: int, size: int, height: int = HEIGHT, width: int = WIDTH) -> np.ndarray:
    """[H, W, 3] uint8: a textured square of side ``size`` px with its left edge at column
    ``x0`` (rows 26 ...) over a different static texture."""
    image = textured_image(height, width, seed=1)
    image[26 : 26 + size, x0 : x0 + size] = textured_image(height, width, seed=2)[26 : 26 + size, 30 : 30 + size]
    return image


def test_fine_preset_follows_a_small_fast_square():
    # A 12 px square moving 3 px over a static texture: at half resolution (medium) DIS
    # blends it with the background and finds 0.9 px on average over the square; at full
    # resolution (fine) 2.7 px.
    frames = np.stack([square_on_texture(40, 12), square_on_texture(43, 12)])
    flow = observed_flow(frames, preset="fine")[0]
    assert flow[26:38, 40:52, 0].mean() == pytest.approx(3.0, rel=0.15)


def test_confidence_of_a_known_translation():
    frames, truth = moving_texture(2, HEIGHT, WIDTH, Motion(shift=(4.0, 0.0)), seed=5)
    forward = observed_flow(frames)
    backward = backward_flow(frames)
    np.testing.assert_allclose(backward[:, 8:-8, 8:-8], -truth[:, 8:-8, 8:-8], atol=0.1)
    confidence = flow_confidence(forward, backward)
    assert confidence.shape == (1, HEIGHT, WIDTH) and confidence.dtype == np.float32
    assert confidence[:, 8:-8, 8 : WIDTH - 12].min() > 0.9  # consistent inside
    assert not confidence[:, :, WIDTH - 4 :].any()  # carried out of the frame: occluded by its border
    # the soft weight is e^-1 on the hard mask's threshold: w = 0 and |w_b|^2 = s with
    # s = 0.01 s + 0.5 px^2
    off = np.zeros((1, 4, 5, 2), np.float32)
    off[..., 0] = (0.5 / 0.99) ** 0.5
    np.testing.assert_allclose(flow_confidence(np.zeros_like(off), off), np.exp(-1.0), rtol=1e-6)


def test_confidence_is_low_where_a_moving_square_covers_the_background():
    frames = np.stack([square_on_texture(30, 24), square_on_texture(35, 24)])  # 5 px to the right
    forward = observed_flow(frames)
    confidence = observed_confidence(frames, forward, "forward_backward")
    assert confidence.shape == (1, HEIGHT, WIDTH)
    covered = confidence[0, 28:48, 55:59]  # background the square's right edge moves over
    assert covered.mean() < 0.3
    assert confidence[0, 30:46, 34:50].mean() > 0.95  # inside the square
    assert confidence[0, :16].mean() > 0.9  # static background away from the square
    np.testing.assert_array_equal(observed_confidence(frames, forward, "none"), np.ones((1, HEIGHT, WIDTH)))
    with pytest.raises(InputError, match="unknown flow confidence 'bogus'; choose one of none, forward_backward"):
        observed_confidence(frames, forward, "bogus")


def test_object_masks(tmp_path):
    box = mask_from_box((1.0, 2.0, 4.0, 3.0), 6, 5)
    expected = np.zeros((5, 6), bool)
    expected[2, 1:4] = True  # pixel centres 1.5, 2.5, 3.5 in x; 2.5 in y
    assert np.array_equal(box, expected)
    image = np.zeros((5, 6, 3), np.uint8)
    image[1:3, 2:5] = 255
    write_image(tmp_path / "mask.png", image)
    assert np.array_equal(mask_from_image(tmp_path / "mask.png", 6, 5), image[..., 0] > 0)
    alpha = np.zeros((5, 6, 1))
    alpha[3, 4] = 0.8
    assert np.argwhere(mask_from_alpha(alpha)).tolist() == [[3, 4]]
    with pytest.raises(InputError, match="mask.png: mask is 6x5 but the video is 7x5"):
        mask_from_image(tmp_path / "mask.png", 7, 5)
    write_image(tmp_path / "black.png", np.zeros((5, 6, 3), np.uint8))
    with pytest.raises(InputError, match="black.png: the object mask is empty"):
        mask_from_image(tmp_path / "black.png", 6, 5)
    with pytest.raises(InputError, match="outside.png: not a readable mask image"):
        mask_from_image(tmp_path / "outside.png", 6, 5)
    with pytest.raises(InputError, match="object box .* the object mask is empty"):
        mask_from_box((10, 10, 20, 20), 6, 5)
    with pytest.raises(InputError, match="rendered alpha above 0.5: the object mask is empty"):
        mask_from_alpha(np.zeros((5, 6)))
    with pytest.raises(InputError, match="NaN"):
        mask_from_alpha(np.full((5, 6), np.nan))


def test_flow_errors(tmp_path, translating):
    frames = translating[0]
    with pytest.raises(InputError, match="guide.mp4: optical flow needs at least 2 frames, the video has 1"):
        observed_flow(frames[:1], source="guide.mp4")
    with pytest.raises(InputError, match="unknown DIS preset 'slow'"):
        observed_flow(frames, preset="slow")
    with pytest.raises(InputError, match="unknown optical flow method 'lk'"):
        observed_flow(frames, "lk")
    with pytest.raises(InputError, match="needs a weights file"):
        observed_flow(frames, "raft")
    with pytest.raises(InputError, match="raft.pth: RAFT weights file not found"):
        observed_flow(frames, "raft", raft_weights=tmp_path / "raft.pth")
    (tmp_path / "raft.pth").write_bytes(b"weights")
    try:
        import torchvision  # noqa: F401
    except Exception:
        with pytest.raises(ClflowError, match="needs torchvision"):
            observed_flow(frames, "raft", raft_weights=tmp_path / "raft.pth")
    else:
        with pytest.raises(InputError, match="raft.pth: not a torchvision RAFT-large state dict"):
            observed_flow(frames, "raft", raft_weights=tmp_path / "raft.pth")


MARGIN = 3
SHIFTS = ((0, 0), (0, -3), (1, 2), (-3, -1), (-2, -2), (2, 3), (-1, 0), (3, 1))


def pointwise(frames: np.ndarray) -> np.ndarray:
    """A made-up 'estimator' [T-1, H, W, 2] that answers each pixel from that pixel alone:
    the same wherever the camera stands, so the shift-mean must give it back exactly."""
    grey = frames.mean(axis=-1)
    return np.stack([grey[:-1], 2.0 * grey[1:] - grey[:-1]], axis=-1)


def test_the_shift_mean_puts_each_shifted_answer_back_on_its_own_pixel():
    wide = np.stack([textured_image(HEIGHT + 2 * MARGIN, WIDTH + 2 * MARGIN, seed=s) for s in (5, 6, 7)])
    central = wide[:, MARGIN:-MARGIN, MARGIN:-MARGIN]
    mean = shift_mean_flow(wide, MARGIN, SHIFTS, pointwise)
    assert mean.shape == (2, HEIGHT, WIDTH, 2)
    np.testing.assert_allclose(mean, pointwise(central), atol=1e-9)
    # the crops really differ: one estimate of a shifted crop, not moved back, does not match
    moved = pointwise(wide[:, MARGIN + 2 : MARGIN + 2 + HEIGHT, MARGIN - 2 : MARGIN - 2 + WIDTH])
    assert np.abs(moved - pointwise(central)).mean() > 1.0


def test_the_shift_mean_of_dis_on_a_whole_pixel_translation_agrees_with_one_estimate():
    # the texture moves (2, -1) px per frame: DIS at every shift of the camera finds it, so the
    # mean over the shifts is the one estimate's answer (px, u right and v down) within noise
    frames, truth = moving_texture(2, HEIGHT + 2 * MARGIN, WIDTH + 2 * MARGIN, Motion(shift=(2.0, -1.0)), seed=8)
    mean = shift_mean_flow(frames, MARGIN, SHIFTS, observed_flow)
    one = observed_flow(np.ascontiguousarray(frames[:, MARGIN:-MARGIN, MARGIN:-MARGIN]))
    assert mean.shape == one.shape == (1, HEIGHT, WIDTH, 2)
    inside = mask_from_box(OBJECT_BOX, WIDTH, HEIGHT)
    assert endpoint_error(mean, truth[:, MARGIN:-MARGIN, MARGIN:-MARGIN], inside) < 0.2
    assert endpoint_error(mean, one, inside) < 0.1
    np.testing.assert_allclose(mean[0][inside].mean(axis=0), (2.0, -1.0), atol=0.05)


@pytest.mark.parametrize("shifts", [((0, 0), (4, 0)), ((1, 1), (-1, -1))], ids=["beyond the margin", "no (0, 0)"])
def test_the_shift_mean_refuses_shifts_it_cannot_take(shifts):
    wide = np.zeros((2, 20, 20), np.uint8)
    with pytest.raises(InputError, match="shifts"):
        shift_mean_flow(wide, MARGIN, shifts, pointwise)
