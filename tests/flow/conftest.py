"""Synthetic guidance videos shared by the flow tests."""

import numpy as np
import pytest

from clflow.flow.synthetic import Motion, moving_texture


@pytest.fixture(scope="session")
def translating():
    """6 frames, 64x80, moving (1.5, -0.75) px per frame: (frames [T, H, W, 3], flow [T-1, H, W, 2])."""
    return moving_texture(6, 64, 80, Motion(shift=(1.5, -0.75)), seed=1)


def write_image_folder(folder, frames, names=None):
    from clflow.flow.visualize import write_image

    folder.mkdir(parents=True, exist_ok=True)
    names = names or [f"frame_{i}.png" for i in range(len(frames))]  # unpadded: order by number, not text
    for name, frame in zip(names, frames):
        write_image(folder / name, frame)
    return folder


@pytest.fixture
def image_folder(tmp_path, translating):
    return write_image_folder(tmp_path / "frames", translating[0])


def mean_abs(a, b):
    return float(np.abs(a.astype(np.int32) - b.astype(np.int32)).mean())
