"""The object's image: read with OpenCV, cropped to a box or mask, encoded inline.

Pixel coordinates: x to the right, y down, (0, 0) the top-left corner of the top-left
pixel; a box (x0, y0, x1, y1) covers x0 <= x < x1, y0 <= y < y1 (fractional boxes from a
detector are widened to whole pixels).
"""

from __future__ import annotations

import base64
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Sequence

import numpy as np

from clflow.errors import InputError

ImageFormat = Literal["png", "jpeg"]
MAX_SIDE = 1024  # px; the longer side sent to a model (vision models downscale larger images anyway)
BACKGROUND = 255  # value of pixels outside a mask: white, so the object stands alone


@dataclass(frozen=True)
class ObjectImage:
    """The object cut out of an image: ``pixels`` [H, W, 3] uint8 BGR, ``box`` (x0, y0, x1,
    y1) in pixels of the source image, ``source`` its path."""

    pixels: np.ndarray
    box: tuple[int, int, int, int]
    source: str

    def data_url(self, image_format: ImageFormat = "png", max_side: int = MAX_SIDE) -> str:
        """``data:image/png;base64,...`` of the crop, its longer side at most ``max_side`` px."""
        import cv2

        img = self.pixels
        scale = max_side / max(img.shape[:2])
        if scale < 1.0:
            size = (max(1, round(img.shape[1] * scale)), max(1, round(img.shape[0] * scale)))
            img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        ext = {"png": ".png", "jpeg": ".jpg"}[image_format]
        ok, buf = cv2.imencode(ext, img)
        if not ok:  # pragma: no cover - OpenCV always encodes a uint8 BGR image
            raise InputError(f"OpenCV could not encode the crop of {self.source} as {image_format}")
        return f"data:image/{image_format};base64,{base64.b64encode(buf.tobytes()).decode('ascii')}"


def _imread(path: str | Path, what: str, flags: int) -> np.ndarray:
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} {path} does not exist" if not path.exists() else f"{what} {path} is not a file")
    img = cv2.imread(str(path), flags)
    if img is None or img.size == 0:
        raise InputError(f"cannot read {what} {path}: not an image format OpenCV knows, or a damaged file")
    return img


def read_image(path: str | Path) -> np.ndarray:
    """[H, W, 3] uint8 BGR pixels of an image file (any format OpenCV reads)."""
    import cv2

    return _imread(path, "image", cv2.IMREAD_COLOR)


def read_mask(path: str | Path, shape: tuple[int, int]) -> np.ndarray:
    """[H, W] bool mask (nonzero pixels are the object) of an image file of size ``shape``."""
    import cv2

    mask = _imread(path, "mask", cv2.IMREAD_GRAYSCALE)
    if mask.shape != tuple(shape):
        raise InputError(f"mask {path} is {mask.shape[1]}x{mask.shape[0]} px but the image is {shape[1]}x{shape[0]} px")
    if not mask.any():
        raise InputError(f"mask {path} is empty: no nonzero pixel marks the object")
    return mask > 0


def check_box(box: Sequence[float], width: int, height: int, where: str = "box") -> tuple[int, int, int, int]:
    """Whole-pixel (x0, y0, x1, y1) of a box that must lie inside a ``width`` x ``height`` image."""
    if len(box) != 4:
        raise InputError(f"{where} needs 4 numbers x0 y0 x1 y1, got {len(box)}")
    try:
        x0, y0, x1, y1 = (float(v) for v in box)
    except (TypeError, ValueError):
        raise InputError(f"{where} needs 4 numbers x0 y0 x1 y1, got {list(box)!r}") from None
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
        raise InputError(f"{where} ({x0:g}, {y0:g}, {x1:g}, {y1:g}) has a non-finite coordinate")
    if not (x0 < x1 and y0 < y1):
        raise InputError(f"{where} ({x0:g}, {y0:g}, {x1:g}, {y1:g}) is empty: need x0 < x1 and y0 < y1")
    if x0 < 0 or y0 < 0 or x1 > width or y1 > height:
        raise InputError(
            f"{where} ({x0:g}, {y0:g}, {x1:g}, {y1:g}) is outside the {width}x{height} px image: "
            f"need 0 <= x0 < x1 <= {width} and 0 <= y0 < y1 <= {height}"
        )
    return math.floor(x0), math.floor(y0), math.ceil(x1), math.ceil(y1)


def crop_object(
    image_path: str | Path,
    box: Sequence[float] | None = None,
    mask_path: str | Path | None = None,
) -> ObjectImage:
    """Read an image and cut out the object: the ``box`` (pixels), or the bounding box of the
    mask with pixels outside the mask set to white, or the whole image if neither is given."""
    if box is not None and mask_path is not None:
        raise InputError("give either a box or a mask, not both")
    img = read_image(image_path)
    height, width = img.shape[:2]
    if mask_path is not None:
        mask = read_mask(mask_path, (height, width))
        ys, xs = np.nonzero(mask)
        x0, y0, x1, y1 = int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1
        pixels = np.where(mask[y0:y1, x0:x1, None], img[y0:y1, x0:x1], np.uint8(BACKGROUND))
    else:
        x0, y0, x1, y1 = (0, 0, width, height) if box is None else check_box(box, width, height)
        pixels = img[y0:y1, x0:x1]
    return ObjectImage(np.ascontiguousarray(pixels), (x0, y0, x1, y1), str(image_path))
