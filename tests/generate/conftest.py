"""Tiny image-to-video models (tests/generate/_helpers.py), built once per session; the
tests skip where the optional extra clflow[video] is not installed (CI installs it)."""

import numpy as np
import pytest


@pytest.fixture(scope="session")
def models(tmp_path_factory):
    """{"cog": folder, "svd": folder} of tiny randomly initialised pipelines."""
    pytest.importorskip("diffusers", reason="the optional extra clflow[video] is not installed")
    pytest.importorskip("transformers", reason="the optional extra clflow[video] is not installed")
    from tests.generate import _helpers as tiny_models

    root = tmp_path_factory.mktemp("models")
    return {"cog": tiny_models.cogvideox(root / "cog"), "svd": tiny_models.svd(root / "svd")}


@pytest.fixture(scope="session")
def object_png(tmp_path_factory):
    """A 40x48 px image: a red box on grey."""
    from clflow.media import write_image

    image = np.full((48, 40, 3), 90, np.uint8)
    image[10:30, 12:28] = (200, 60, 30)
    path = tmp_path_factory.mktemp("images") / "object.png"
    write_image(path, image)
    return path
