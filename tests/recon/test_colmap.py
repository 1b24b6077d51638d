"""COLMAP sparse-model readers (bin and txt) on models the tests write."""

import math
import struct

import numpy as np
import pytest
import torch

from clflow.errors import InputError
from clflow.recon.colmap import model_cameras, read_model
from clflow.splat.cameras import orbit
from tests.recon._helpers import model_of, write_bin, write_txt


def cameras():
    views = orbit((0.1, -0.2, 0.3), 3.0, n_views=5, elevation=math.radians(25), fov_x=1.0, width=40, height=30)
    for i, c in enumerate(views):
        c.name = f"img_{4 - i}.png"  # not in name order: the readers sort by name
    return views


POINTS = np.array([[0.0, 0.5, 1.0], [-1.25, 2.0, 0.125], [3.0, -4.0, 5.5]])


@pytest.mark.parametrize("writer", [write_bin, write_txt], ids=["bin", "txt"])
def test_reader_gives_back_the_written_cameras_and_points(tmp_path, writer):
    truth = cameras()
    writer(tmp_path, model_of(truth, POINTS))
    model = read_model(tmp_path)
    loaded = model_cameras(model)
    assert [c.name for c in loaded] == sorted(c.name for c in truth)
    by_name = {c.name: c for c in truth}
    for c in loaded:
        t = by_name[c.name]
        assert (c.width, c.height) == (40, 30)
        assert torch.allclose(c.viewmat, t.viewmat, atol=1e-12)
        assert torch.allclose(c.K, t.K, atol=1e-12)
    assert np.allclose(model.points_xyz, POINTS, atol=0) and model.points_rgb[:, 1].tolist() == [100] * 3
    assert model.points_rgb[:, 0].tolist() == [0, 1, 2]


def test_bin_is_preferred_and_txt_points_are_optional(tmp_path):
    truth = cameras()
    write_txt(tmp_path, model_of(truth[:2]))
    (tmp_path / "points3D.txt").unlink()
    model = read_model(tmp_path)
    assert len(model.images) == 2 and model.points_xyz.shape == (0, 3)
    write_bin(tmp_path, model_of(truth))
    assert len(read_model(tmp_path).images) == 5


def test_simple_pinhole_and_zero_distortion_are_pinhole_cameras(tmp_path):
    truth = cameras()[:1]
    cams, images, points = model_of(truth)
    cams = [(1, "SIMPLE_RADIAL", 40, 30, [50.0, 20.0, 15.0, 0.0])]
    write_txt(tmp_path, (cams, images, points))
    (c,) = model_cameras(read_model(tmp_path))
    assert c.K.tolist() == [[50.0, 0.0, 20.0], [0.0, 50.0, 15.0], [0.0, 0.0, 1.0]]


def test_distorted_camera_is_refused(tmp_path):
    cams, images, points = model_of(cameras()[:1])
    write_bin(tmp_path, ([(1, "OPENCV", 40, 30, [50.0, 50.0, 20.0, 15.0, 0.1, 0.0, 0.0, 0.0])], images, points))
    with pytest.raises(InputError, match="OPENCV with distortion.*undistort"):
        model_cameras(read_model(tmp_path))


def test_non_unit_quaternion_is_refused(tmp_path):
    cams, images, points = model_of(cameras()[:1])
    iid, q, t, cid, name, pts = images[0]
    write_txt(tmp_path, (cams, [(iid, 1.2 * q, t, cid, name, pts)], points))
    with pytest.raises(InputError, match="norm 1.2, not 1"):
        model_cameras(read_model(tmp_path))


def test_damaged_files_name_the_problem(tmp_path):
    write_bin(tmp_path, model_of(cameras()))
    data = (tmp_path / "images.bin").read_bytes()
    (tmp_path / "images.bin").write_bytes(data[:-20])
    with pytest.raises(InputError, match="images.bin: file ends early"):
        read_model(tmp_path)
    (tmp_path / "cameras.bin").unlink()
    write_txt(tmp_path, model_of(cameras()))
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 40 30 1 2 3\n")
    with pytest.raises(InputError, match="cameras.txt:1: PINHOLE takes 4 parameters, got 3"):
        read_model(tmp_path)
    (tmp_path / "cameras.txt").write_text("1 PINHOLE forty 30 1 2 3 4\n")
    with pytest.raises(InputError, match="cameras.txt:1: expected CAMERA_ID MODEL WIDTH HEIGHT"):
        read_model(tmp_path)
    with pytest.raises(InputError, match="no COLMAP model"):
        read_model(tmp_path / "nowhere")
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "cameras.bin").write_bytes(struct.pack("<Q", 0))
    (tmp_path / "x" / "images.bin").write_bytes(struct.pack("<Q", 0))
    with pytest.raises(InputError, match="registers no images"):
        read_model(tmp_path / "x")
