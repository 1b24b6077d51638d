"""Single image + depth: back-projection puts a known plane at the known distance."""

import math

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from clflow.errors import InputError
from clflow.recon.depth import backproject, read_depth
from clflow.splat import load_cameras_json, load_ply, look_at
from clflow_cli.main import cli

W, H = 24, 16


def test_plane_lands_at_its_distance_and_fills_the_view():
    camera = look_at((1.0, -3.0, 0.5), (1.0, 0.0, 0.5), fov_x=math.radians(60), width=W, height=H)
    depth = torch.full((H, W), 2.5)
    g = backproject(torch.rand(H, W, 3), depth, camera, shell="none")
    assert len(g) == W * H
    cam_z = (g.means.double() @ camera.R.T + camera.t)[:, 2]
    assert torch.allclose(cam_z, torch.full_like(cam_z, 2.5), atol=1e-5)
    assert torch.allclose(
        g.means[:, 1].double(), torch.full((W * H,), -0.5, dtype=torch.float64), atol=1e-5
    )  # the plane y = -0.5
    # the corners of the plane are the pixel-centre rays of the corner pixels
    half_w = 2.5 * math.tan(math.radians(30)) * (W - 1) / W
    assert g.means[:, 0].min().item() == pytest.approx(1.0 - half_w, abs=1e-5)
    assert g.means[:, 0].max().item() == pytest.approx(1.0 + half_w, abs=1e-5)
    # flat Gaussians facing the camera, a pixel footprint wide
    normals = g.rotations[:, :, 2].double()
    assert torch.allclose(
        normals.abs() @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), torch.ones(W * H, dtype=torch.float64)
    )
    assert g.scales[0, 0].item() == pytest.approx(0.6 * 2.5 / camera.fx, rel=1e-5)


def test_shells_close_the_hidden_side():
    camera = look_at((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), fov_x=1.0, width=W, height=H)
    depth = torch.zeros(H, W)
    depth[4:12, 6:18] = 2.0
    depth[6:10, 10:14] = 1.5  # a bump towards the camera
    z_of = lambda g: (g.means.double() @ camera.R.T + camera.t)[:, 2]  # noqa: E731
    front = int((depth > 0).sum())
    mirrored = z_of(backproject(torch.rand(H, W, 3), depth, camera, shell="mirror"))
    assert len(mirrored) == 2 * front
    assert sorted({round(z, 4) for z in mirrored.tolist()}) == [1.5, 2.0, 2.5]  # 2 z_max - z
    extruded = z_of(backproject(torch.rand(H, W, 3), depth, camera, shell="extrude", thickness=0.25))
    assert sorted({round(z, 4) for z in extruded.tolist()}) == [1.5, 1.75, 2.0, 2.25]
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[:, :12] = True
    assert len(backproject(torch.rand(H, W, 3), depth, camera, mask=mask, shell="none")) == int(
        (depth[:, :12] > 0).sum()
    )


def test_depth_files_and_bad_input(tmp_path):
    np.save(tmp_path / "d.npy", np.full((H, W), 3.0))
    assert torch.equal(read_depth(tmp_path / "d.npy"), torch.full((H, W), 3.0))
    cv2.imwrite(str(tmp_path / "d.png"), np.full((H, W), 2500, np.uint16))
    assert torch.allclose(read_depth(tmp_path / "d.png"), torch.full((H, W), 2.5))
    assert torch.allclose(read_depth(tmp_path / "d.png", 1 / 5000), torch.full((H, W), 0.5))
    cv2.imwrite(str(tmp_path / "d8.png"), np.full((H, W), 25, np.uint8))
    with pytest.raises(InputError, match="16-bit"):
        read_depth(tmp_path / "d8.png")
    np.save(tmp_path / "neg.npy", np.full((H, W), -1.0))
    with pytest.raises(InputError, match="finite and >= 0"):
        read_depth(tmp_path / "neg.npy")
    camera = look_at((0, 0, 0), (0, 1, 0), fov_x=1.0, width=W, height=H)
    with pytest.raises(InputError, match="no pixel with depth > 0"):
        backproject(torch.rand(H, W, 3), torch.zeros(H, W), camera)


def test_cli_writes_splats_and_refuses_a_depth_map_of_the_wrong_size(tmp_path):
    cv2.imwrite(str(tmp_path / "photo.png"), np.full((H, W, 3), 128, np.uint8))
    np.save(tmp_path / "depth.npy", np.full((H, W), 2.0))
    result = CliRunner().invoke(
        cli,
        [
            "reconstruct",
            str(tmp_path / "photo.png"),
            "--depth",
            str(tmp_path / "depth.npy"),
            "-o",
            str(tmp_path / "out"),
            "--fov",
            "60",
        ],
    )
    assert result.exit_code == 0, result.output
    g = load_ply(tmp_path / "out" / "point_cloud.ply")
    assert len(g) == 2 * W * H and g.means[:, 2].min().item() == pytest.approx(2.0, abs=1e-5)
    (camera,) = load_cameras_json(tmp_path / "out" / "cameras.json")
    assert camera.fov_x == pytest.approx(math.radians(60))
    np.save(tmp_path / "small.npy", np.full((H, W - 1), 2.0))
    result = CliRunner().invoke(
        cli,
        [
            "reconstruct",
            str(tmp_path / "photo.png"),
            "--depth",
            str(tmp_path / "small.npy"),
            "-o",
            str(tmp_path / "out2"),
        ],
    )
    assert result.exit_code == 1 and "Traceback" not in result.output
    assert "the depth map is 23x16 px and the image 24x16 px, but the camera is 24x16 px" in result.output
