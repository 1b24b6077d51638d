"""Images, boxes and masks: crops and clear errors for bad input."""

from __future__ import annotations

import base64

import cv2
import numpy as np
import pytest

from clflow.errors import InputError
from clflow.query import crop_object, query_material


def test_box_crop_is_exact_and_fractional_boxes_widen(photo):
    path, pixels = photo
    crop = crop_object(path, box=(8, 4, 40, 36))
    np.testing.assert_array_equal(crop.pixels, pixels[4:36, 8:40])
    assert crop_object(path, box=(8.5, 4.2, 39.1, 35.9)).box == (8, 4, 40, 36)
    whole = crop_object(path)
    assert whole.box == (0, 0, 64, 48)
    np.testing.assert_array_equal(whole.pixels, pixels)


def test_data_url_downscales_to_max_side(photo):
    crop = crop_object(photo[0])
    url = crop.data_url("png", max_side=16)
    img = cv2.imdecode(np.frombuffer(base64.b64decode(url.split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (12, 16, 3)


@pytest.mark.parametrize(
    "box, message",
    [
        ((0, 0, 65, 48), r"outside the 64x48 px image: need 0 <= x0 < x1 <= 64 and 0 <= y0 < y1 <= 48"),
        ((-1, 0, 10, 10), "outside the 64x48 px image"),
        ((100, 100, 120, 120), "outside the 64x48 px image"),
        ((10, 10, 10, 20), "is empty: need x0 < x1 and y0 < y1"),
        ((30, 10, 20, 20), "is empty"),
        ((0, 0, 10), "needs 4 numbers x0 y0 x1 y1, got 3"),
        ((0, 0, float("nan"), 10), "non-finite"),
        ((0, 0, "a", 10), "needs 4 numbers"),
    ],
)
def test_bad_boxes(photo, box, message):
    with pytest.raises(InputError, match=message):
        crop_object(photo[0], box=box)


def test_unreadable_images(tmp_path):
    with pytest.raises(InputError, match=r"image .*missing.png does not exist"):
        query_material(tmp_path / "missing.png")
    (tmp_path / "notes.png").write_text("this is text, not a PNG")
    with pytest.raises(InputError, match=r"cannot read image .*notes.png: not an image format"):
        query_material(tmp_path / "notes.png")
    with pytest.raises(InputError, match="is not a file"):
        query_material(tmp_path)


def test_bad_masks(tmp_path, photo):
    empty = tmp_path / "empty.png"
    cv2.imwrite(str(empty), np.zeros((48, 64), np.uint8))
    with pytest.raises(InputError, match=r"mask .*empty.png is empty: no nonzero pixel"):
        query_material(photo[0], mask=empty)
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.full((10, 10), 255, np.uint8))
    with pytest.raises(InputError, match=r"mask .*small.png is 10x10 px but the image is 64x48 px"):
        query_material(photo[0], mask=small)
    (tmp_path / "junk.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(InputError, match="cannot read mask"):
        query_material(photo[0], mask=tmp_path / "junk.png")
    with pytest.raises(InputError, match="either a box or a mask, not both"):
        query_material(photo[0], box=(0, 0, 5, 5), mask=small)


def test_bad_backend_and_missing_image(photo):
    with pytest.raises(InputError, match="unknown backend 'gpt'; choose one of offline, openai"):
        query_material(photo[0], backend="gpt")
    with pytest.raises(InputError, match="need an image"):
        query_material(prompt="rubber", backend="openai")
    with pytest.raises(InputError, match="endpoint"):
        query_material(photo[0], backend="openai")  # no --llm-url and no $CLFLOW_LLM_URL
