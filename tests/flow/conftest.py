"""Synthetic guidance videos shared by the flow tests."""

import pytest

from clflow.flow.synthetic import Motion, moving_texture
from tests.flow._helpers import write_image_folder


@pytest.fixture(scope="session")
def translating():
    """6 frames, 64x80, moving (1.5, -0.75) px per frame: (frames [T, H, W, 3], flow [T-1, H, W, 2])."""
    return moving_texture(6, 64, 80, Motion(shift=(1.5, -0.75)), seed=1)


@pytest.fixture
def image_folder(tmp_path, translating):
    return write_image_folder(tmp_path / "frames", translating[0])
