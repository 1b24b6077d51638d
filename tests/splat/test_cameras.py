"""Cameras: OpenCV conventions, look-at / orbit geometry, cameras.json and transforms.json."""

import json
import math

import numpy as np
import pytest
import torch

from clflow.errors import InputError
from clflow.splat.cameras import (
    Camera,
    framing_distance,
    intrinsics,
    load_cameras_json,
    load_transforms_json,
    look_at,
    orbit,
    save_transforms_json,
)

F64 = torch.float64


def project(camera: Camera, point) -> tuple[float, float, float]:
    """(u, v) pixel coordinates and depth z (m) of a world point, by the pinhole model."""
    x = camera.viewmat @ torch.tensor([*point, 1.0], dtype=F64)
    uvw = camera.K @ x[:3]
    return (uvw[0] / uvw[2]).item(), (uvw[1] / uvw[2]).item(), x[2].item()


def test_look_at_puts_target_at_the_principal_point_and_up_upward():
    cam = look_at((3, 1, 2), (0, 0, 0.5), (0, 0, 1), fov_x=math.radians(60), width=64, height=48)
    u, v, z = project(cam, (0, 0, 0.5))
    assert (u, v) == pytest.approx((32, 24), abs=1e-12)
    assert z == pytest.approx(math.dist((3, 1, 2), (0, 0, 0.5)))
    assert torch.allclose(cam.position, torch.tensor([3.0, 1, 2], dtype=F64), atol=1e-15)
    _, v_up, _ = project(cam, (0, 0, 0.6))
    assert v_up < 24  # +y is down in the image
    u_right, _, _ = project(cam, (-0.1, 0.3, 0.5))  # facing about -x with z up, +y is on the right
    assert u_right > 32
    assert cam.fov_x == pytest.approx(math.radians(60))
    assert torch.allclose(cam.camtoworld() @ cam.viewmat, torch.eye(4, dtype=F64), atol=1e-15)


def test_a_widened_camera_sees_the_same_pixels_with_a_margin_around_them():
    cam = look_at((3, 1, 2), (0, 0, 0.5), (0, 0, 1), fov_x=math.radians(60), width=64, height=48)
    wide = cam.widened(3)
    assert (wide.width, wide.height) == (70, 54) and torch.equal(wide.viewmat, cam.viewmat)
    for point in [(0, 0, 0.5), (-0.1, 0.3, 0.7)]:
        u, v, z = project(cam, point)
        assert project(wide, point) == pytest.approx((u + 3, v + 3, z), abs=1e-12)


def test_focal_length_from_field_of_view():
    K = intrinsics(200, 100, 2 * math.atan(0.5))  # half-width 100 px at tan = 0.5
    assert K[0, 0].item() == pytest.approx(200) and K[1, 1].item() == pytest.approx(200)
    assert K[0, 2].item() == 100 and K[1, 2].item() == 50


def test_orbit_views_lie_on_the_circle_and_look_at_the_center():
    center = torch.tensor([0.5, -1.0, 2.0], dtype=F64)
    up = torch.tensor([0.0, -1.0, 0.0], dtype=F64)  # COLMAP scenes are often -y up
    views = orbit(center, 2.0, n_views=8, elevation=math.radians(30), up=up, fov_x=1.0, width=32, height=32)
    assert len(views) == 8 and len({v.name for v in views}) == 8
    for cam in views:
        offset = cam.position - center
        assert offset.norm().item() == pytest.approx(2.0)
        assert (offset @ up).item() / 2.0 == pytest.approx(math.sin(math.radians(30)))
        assert project(cam, center.tolist())[:2] == pytest.approx((16, 16), abs=1e-9)
    # consecutive views are 45 degrees apart about up
    a, b = (v.position - center for v in views[:2])
    flat = lambda x: x - (x @ up) * up  # noqa: E731
    cos = (flat(a) @ flat(b) / (flat(a).norm() * flat(b).norm())).item()
    assert cos == pytest.approx(math.cos(math.pi / 4))


def test_framing_distance_fits_the_sphere_in_the_narrow_fov():
    d = framing_distance(1.0, math.radians(90), 200, 100)
    cam = look_at((d, 0, 0), (0, 0, 0), fov_x=math.radians(90), width=200, height=100)
    # the sphere's silhouette touches the top edge: the tangent ray at angle asin(r/d)
    _, v, _ = project(cam, (0, 0, 1 / math.cos(math.asin(1 / d))))
    assert v == pytest.approx(0, abs=1e-9)


def write_cameras_json(path, cameras):
    """cameras.json as 3DGS's trainer writes it: camera-to-world rotation and the centre."""
    entries = [
        dict(
            id=i,
            img_name=c.name,
            width=c.width,
            height=c.height,
            position=c.position.tolist(),
            rotation=c.R.T.tolist(),
            fy=c.fy,
            fx=c.fx,
        )
        for i, c in enumerate(cameras)
    ]
    path.write_text(json.dumps(entries))


def test_cameras_json_round_trip(tmp_path):
    cams = [
        look_at((2, -3, 1), (0, 0, 0), fov_x=0.9, width=80, height=60, name="img_0"),
        look_at((-1, 0, 4), (0, 1, 0), fov_x=1.2, width=40, height=50, name="img_1"),
    ]
    write_cameras_json(tmp_path / "cameras.json", cams)
    loaded = load_cameras_json(tmp_path / "cameras.json")
    assert [c.name for c in loaded] == ["img_0", "img_1"]
    for a, b in zip(cams, loaded):
        assert torch.allclose(a.viewmat, b.viewmat, atol=1e-14) and torch.allclose(a.K, b.K)
        assert (a.width, a.height) == (b.width, b.height)


def test_transforms_json_round_trip_keeps_the_principal_point(tmp_path):
    cam = look_at((2, -3, 1), (0, 0, 0), fov_x=0.9, width=80, height=60, name="r_1_0")
    K = cam.K.clone()
    K[0, 2], K[1, 1] = 37.25, 1.1 * K[1, 1]  # off-centre, non-square pixels
    cam = Camera(cam.viewmat, K, 80, 60, "r_1_0")
    save_transforms_json(tmp_path / "camera.json", [cam])
    frame = json.loads((tmp_path / "camera.json").read_text())["frames"][0]
    assert (frame["cx"], frame["w"], frame["h"]) == (37.25, 80, 60)
    (loaded,) = load_transforms_json(tmp_path / "camera.json")
    assert torch.allclose(loaded.viewmat, cam.viewmat, atol=1e-14) and torch.equal(loaded.K, cam.K)
    assert (loaded.width, loaded.height, loaded.name) == (80, 60, "r_1_0")


def test_cameras_json_hand_written_entry(tmp_path):
    # Identity camera-to-world rotation at z = -5: the camera looks along +z at the origin.
    entry = dict(
        id=0, img_name="front", width=100, height=80, position=[0, 0, -5], rotation=np.eye(3).tolist(), fx=50.0, fy=60.0
    )
    (tmp_path / "cameras.json").write_text(json.dumps([entry]))
    (cam,) = load_cameras_json(tmp_path / "cameras.json")
    assert project(cam, (0, 0, 0)) == pytest.approx((50, 40, 5))
    assert project(cam, (1, 1, 0)) == pytest.approx((50 + 50 / 5, 40 + 60 / 5, 5))


def test_transforms_json_converts_opengl_axes(tmp_path):
    # NeRF-synthetic style: camera at z = 4 (OpenGL: looks down -z, +y up), 2*atan(0.5) fov.
    c2w_gl = np.eye(4)
    c2w_gl[2, 3] = 4
    data = dict(
        camera_angle_x=2 * math.atan(0.5), frames=[dict(file_path="./train/r_0", transform_matrix=c2w_gl.tolist())]
    )
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    (cam,) = load_transforms_json(tmp_path / "transforms.json", width=100, height=100)
    assert cam.fx == pytest.approx(100) and cam.name == "./train/r_0"
    assert project(cam, (0, 0, 0)) == pytest.approx((50, 50, 4))
    u, v, _ = project(cam, (1, 1, 0))  # world +y is image up, world +x image right
    assert u == pytest.approx(75) and v == pytest.approx(25)


def test_transforms_json_intrinsics_and_size_from_keys_and_from_the_image(tmp_path):
    import cv2

    c2w = np.eye(4).tolist()
    data = dict(
        fl_x=30.0,
        fl_y=40.0,
        cx=11.0,
        cy=7.0,
        w=22,
        h=14,
        frames=[dict(file_path="a.png", transform_matrix=c2w), dict(file_path="b", transform_matrix=c2w, fl_x=33.0)],
    )
    (tmp_path / "t.json").write_text(json.dumps(data))
    a, b = load_transforms_json(tmp_path / "t.json")
    assert a.K.tolist() == [[30, 0, 11], [0, 40, 7], [0, 0, 1]] and (a.width, a.height) == (22, 14)
    assert b.fx == 33.0

    cv2.imwrite(str(tmp_path / "r_0.png"), np.zeros((12, 20, 3), np.uint8))
    data = dict(camera_angle_x=1.0, frames=[dict(file_path="r_0", transform_matrix=c2w)])
    (tmp_path / "n.json").write_text(json.dumps(data))
    (cam,) = load_transforms_json(tmp_path / "n.json")
    assert (cam.width, cam.height) == (20, 12)


ROT = np.eye(3).tolist()


@pytest.mark.parametrize(
    "content, message",
    [
        ("{not json", "not valid JSON: line 1"),
        ("{}", "non-empty JSON list"),
        (json.dumps([dict(width=4, height=4, position=[0, 0, 0], rotation=ROT, fx=1)]), "camera 0: missing keys fy"),
        (
            json.dumps([dict(width=4, height=4, position=[0, 0], rotation=ROT, fx=1, fy=1)]),
            "position: expected shape \\[3\\]",
        ),
        (
            json.dumps([dict(width=4.5, height=4, position=[0, 0, 0], rotation=ROT, fx=1, fy=1)]),
            "'width' must be a positive integer",
        ),
        (
            json.dumps([dict(width=4, height=4, position=[0, 0, 0], rotation=ROT, fx=-1, fy=1)]),
            "focal lengths must be > 0",
        ),
        (
            json.dumps(
                [dict(width=4, height=4, position=[0, 0, 0], rotation=[[1, 0, 0], [0, 2, 0], [0, 0, 1]], fx=1, fy=1)]
            ),
            "camera 0: .*not orthonormal",
        ),
        (
            json.dumps(
                [dict(width=4, height=4, position=[0, 0, 0], rotation=[[1, 0, 0], [0, 1, 0], [0, 0, -1]], fx=1, fy=1)]
            ),
            "reflection",
        ),
        (json.dumps([dict(width=4, height=4, position=[0, "a", 0], rotation=ROT, fx=1, fy=1)]), "expected numbers"),
    ],
)
def test_bad_cameras_json(tmp_path, content, message):
    (tmp_path / "cameras.json").write_text(content)
    with pytest.raises(InputError, match="cameras.json") as info:
        load_cameras_json(tmp_path / "cameras.json")
    assert info.match(message)


@pytest.mark.parametrize(
    "data, message",
    [
        (dict(frames=[]), "non-empty 'frames'"),
        (dict(w=4, h=4, frames=[dict(file_path="x")]), "frames\\[0\\]: missing 'transform_matrix'"),
        (dict(w=4, h=4, frames=[dict(transform_matrix=np.eye(4).tolist())]), "no intrinsics"),
        (
            dict(camera_angle_x=1, frames=[dict(file_path="gone", transform_matrix=np.eye(4).tolist())]),
            r"image .*gone\[.png\] not found \(no 'w', 'h': its size is needed\)$",  # not "pass width and height"
        ),
        (
            dict(camera_angle_x=1, frames=[dict(file_path="transforms.json", transform_matrix=np.eye(4).tolist())]),
            r"transforms.json is not a readable image",
        ),
        (dict(w=4, h=4, fl_x=2, frames=[dict(transform_matrix=(np.eye(4) * 1.1).tolist())]), "last row"),
        (dict(w=4, h=4, fl_x=2, frames=[dict(transform_matrix=np.eye(3).tolist())]), "expected shape \\[4, 4\\]"),
    ],
)
def test_bad_transforms_json(tmp_path, data, message):
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match="transforms.json") as info:
        load_transforms_json(tmp_path / "transforms.json")
    assert info.match(message)


def test_camera_validation():
    K = intrinsics(10, 10, 1.0)
    with pytest.raises(InputError, match="K must be"):
        Camera(torch.eye(4), K + torch.tensor([[0, 0.5, 0], [0, 0, 0], [0, 0, 0]], dtype=F64), 10, 10)
    with pytest.raises(InputError, match="height must be a positive integer"):
        Camera(torch.eye(4), K, 10, 0)
    with pytest.raises(InputError, match="non-finite"):
        Camera(torch.full((4, 4), float("nan")), K, 10, 10)
    with pytest.raises(InputError, match="parallel to the viewing direction"):
        look_at((0, 0, 1), (0, 0, 0), (0, 0, 1), fov_x=1, width=4, height=4)
    with pytest.raises(InputError, match="same point"):
        look_at((0, 0, 1), (0, 0, 1), fov_x=1, width=4, height=4)
    with pytest.raises(InputError, match="field of view"):
        intrinsics(10, 10, math.pi)
    with pytest.raises(InputError, match="elevation"):
        orbit((0, 0, 0), 1, n_views=3, elevation=2.0, fov_x=1, width=4, height=4)


def test_transform_camera_sees_transformed_points_at_the_same_pixels(tmp_path):
    from clflow.splat.cameras import load_dataparser_transforms, transform_camera
    from tests.splat._helpers import rotations

    R, t, s = rotations(1, seed=4)[0], torch.tensor([0.3, -1.0, 2.0], dtype=F64), 0.25
    (tmp_path / "dataparser_transforms.json").write_text(
        json.dumps({"transform": torch.cat([R, t[:, None]], 1).tolist(), "scale": s})
    )
    transform, scale = load_dataparser_transforms(tmp_path / "dataparser_transforms.json")
    cam = look_at((3, 1, 2), (0, 0, 0.5), (0, 0, 1), fov_x=1.0, width=64, height=48)
    moved = transform_camera(cam, transform, scale)
    for point in ((0.0, 0.0, 0.5), (0.4, -0.2, 0.9), (-1.0, 0.5, 0.0)):
        u, v, z = project(cam, point)
        model = s * (R @ torch.tensor(point, dtype=F64) + t)  # the point in the model's frame
        assert project(moved, model.tolist()) == pytest.approx((u, v, s * z), abs=1e-9)
    assert transform_camera(cam, transform, 1.0).viewmat[:3, :3].det() == pytest.approx(1.0)


@pytest.mark.parametrize(
    "content, message",
    [
        ({"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}, "an object with 'transform' \\(3x4\\) and 'scale'"),
        ({"transform": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "scale": 1}, "transform: expected shape \\[3, 4\\]"),
        ({"transform": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": 1}, "3x3 part is not a rotation"),
        ({"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": 0}, "'scale' must be > 0"),
    ],
)
def test_bad_dataparser_transforms(tmp_path, content, message):
    from clflow.splat.cameras import load_dataparser_transforms

    (tmp_path / "d.json").write_text(json.dumps(content))
    with pytest.raises(InputError, match=f"d.json: .*{message}"):
        load_dataparser_transforms(tmp_path / "d.json")
