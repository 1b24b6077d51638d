"""camera: {colmap: FOLDER, image: NAME | index: I}: the guidance camera from a COLMAP
sparse model (.bin or .txt), read by clflow.recon.colmap."""

import math

import pytest
import torch
import yaml

from clflow.errors import InputError
from clflow.scene.config import load_config
from clflow.scene.load import guidance_camera, to_simulation_camera
from clflow.splat.cameras import orbit
from tests.recon._helpers import model_of, write_bin, write_txt


def config_with(demo, tmp_path, camera, **scene):
    """The quick demo's config with ``camera`` (and ``scene`` keys) replaced, in tmp_path."""
    data = yaml.safe_load((demo / "config.yaml").read_text())
    data["splats"], data["video"] = str(demo / "scene.ply"), str(demo / "guidance")
    data["camera"] = camera
    data["scene"].update(scene)
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(data))
    return load_config(path)


def views():
    cams = orbit((0.0, 0.1, 0.0), 0.8, n_views=4, elevation=math.radians(20), fov_x=0.9, width=64, height=48)
    for i, c in enumerate(cams):
        c.name = f"frame_{3 - i:04d}.jpg"  # name order is the reverse of the orbit's
    return cams


@pytest.mark.parametrize("writer", [write_bin, write_txt], ids=["bin", "txt"])
def test_the_guidance_camera_is_the_named_image(quick_demo, tmp_path, writer):
    truth = views()
    writer(tmp_path / "sparse" / "0", model_of(truth))
    for camera, want in (
        ({"colmap": "sparse/0", "image": "frame_0002.jpg"}, truth[1]),
        ({"colmap": "sparse/0", "index": 0}, truth[3]),
        ({"colmap": "sparse/0"}, truth[3]),
    ):
        cfg = config_with(quick_demo, tmp_path, camera, scale=2.0, up="+z")
        got, expected = guidance_camera(cfg), to_simulation_camera(want, cfg)
        torch.testing.assert_close(got.viewmat, expected.viewmat, rtol=0, atol=1e-9)
        torch.testing.assert_close(got.K, expected.K, rtol=0, atol=1e-9)
        assert (got.width, got.height) == (64, 48)


@pytest.mark.parametrize(
    "camera, message",
    [
        (
            {"colmap": "sparse/0", "image": "nope.jpg"},
            r"camera.image 'nope.jpg' is not an image of the COLMAP model .*sparse/0 \(frame_0000.jpg, frame_0001.jpg",
        ),
        ({"colmap": "sparse/0", "index": 4}, r"camera.index 4 is outside the 4 images of the COLMAP model"),
        ({"colmap": "empty"}, r"empty: no COLMAP model here"),
    ],
)
def test_bad_colmap_cameras_at_run(quick_demo, tmp_path, camera, message):
    write_txt(tmp_path / "sparse" / "0", model_of(views()))
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match=message):
        guidance_camera(config_with(quick_demo, tmp_path, camera))


@pytest.mark.parametrize(
    "camera, message",
    [
        ({"colmap": "sparse/0", "file": "cameras.json"}, "camera: give file or colmap, not both"),
        (
            {"colmap": "sparse/0", "position": [0, 0, 1]},
            "camera: with a camera model, position come from the model: drop them",
        ),
        (
            {"position": [0, 0, 1], "look_at": [0, 0, 0], "image": "a.jpg"},
            "camera.image: names an image of a COLMAP model",
        ),
        ({"colmap": "sparse/0", "image": "frame_0000.jpg", "index": 1}, "camera: give image or index, not both"),
        ({"colmap": "sparse/0", "image": 3}, "camera.image: must be an image name of the COLMAP model, got 3"),
        ({"colmap": "missing"}, "camera.colmap: file or folder not found"),
    ],
)
def test_bad_colmap_cameras_in_the_config(quick_demo, tmp_path, camera, message):
    write_txt(tmp_path / "sparse" / "0", model_of(views()))
    (tmp_path / "cameras.json").write_text("[]")
    with pytest.raises(InputError, match=message):
        config_with(quick_demo, tmp_path, camera)
