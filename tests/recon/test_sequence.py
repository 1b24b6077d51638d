"""PAC-NeRF-style multi-camera sequences: the index reader, `clflow reconstruct --frame`,
the camera convention, and bad input refused with one line."""

import json

import numpy as np
import pytest
import torch

from clflow.errors import InputError
from clflow.recon.sequence import load_sequence
from clflow.recon.views import load_views
from clflow.splat.cameras import load_cameras_json
from clflow.splat.ply import load_ply
from tests.recon._helpers import colour, one_line_error, run, write_sequence

SIZE = 32


def pacnerf_points(c2w, K, pixels, depth=2.0):
    """World points [P, 3] on PAC-NeRF's rays through pixel indices ``pixels`` [P, 2] (i
    right, j down): direction ((i + 0.5 - cx) / fx, -(j + 0.5 - cy) / fy, -1) rotated by c2w
    (lib/nerf/dvgo.py get_rays, mode 'center'), ``depth`` along it from the camera."""
    i, j = pixels[:, 0] + 0.5, pixels[:, 1] + 0.5
    dirs = np.stack([(i - K[0, 2]) / K[0, 0], -(j - K[1, 2]) / K[1, 1], -np.ones_like(i)], axis=1)
    return c2w[:3, 3] + depth * dirs @ c2w[:3, :3].T


def project(camera, points):
    """[P, 2] continuous pixel coordinates of world points through a clflow camera."""
    cam = points @ camera.R.numpy().T + camera.t.numpy()
    uvw = cam @ camera.K.numpy().T
    assert (cam[:, 2] > 0).all()
    return uvw[:, :2] / uvw[:, 2:]


PIXELS = np.array([[0, 0], [SIZE - 1, 0], [5, 20], [16, 16], [SIZE - 1, SIZE - 1]], dtype=np.float64)


def assert_round_trip(camera, c2w, K):
    """A point on PAC-NeRF's ray through each pixel centre lands on that centre through ``camera``."""
    uv = project(camera, pacnerf_points(np.asarray(c2w), np.asarray(K), PIXELS))
    np.testing.assert_allclose(uv, PIXELS + 0.5, atol=1e-9)


def test_reader_takes_every_camera_of_the_frame_and_skips_backdrops(tmp_path):
    write_sequence(tmp_path, cameras=4, frames=3, size=SIZE, fps=24.0)
    seq = load_sequence(tmp_path / "all_data.json")  # the index file itself, or its folder
    assert (len(seq.cameras), seq.frames) == (4, 3)
    assert seq.fps == pytest.approx(24.0)
    assert seq.images[2][1].name == "r_2_1.png"
    for frame in range(3):
        views = load_views(tmp_path, frame=frame).views
        assert [v.path.name for v in views] == [f"r_{c}_{frame}.png" for c in range(4)]
        assert [v.camera.name for v in views] == [f"r_{c}_{frame}" for c in range(4)]
        for c, view in enumerate(views):
            assert view.image[SIZE // 2, SIZE // 2].tolist() == pytest.approx([v / 255 for v in colour(c, frame)])
            assert view.image[0, 0].tolist() == [0.0, 0.0, 0.0]  # alpha 0: the background
        white = load_views(tmp_path, frame=frame, background=(1, 1, 1)).views[0].image
        assert white[0, 0].tolist() == [1.0, 1.0, 1.0]


def test_cameras_project_like_pacnerf_rays(tmp_path):
    poses = write_sequence(tmp_path, cameras=4, frames=2, size=SIZE)
    seq = load_sequence(tmp_path)
    for camera, (c2w, K) in zip(seq.cameras, poses):
        assert (camera.width, camera.height) == (SIZE, SIZE)
        assert_round_trip(camera, c2w, K)
        np.testing.assert_allclose(camera.position.numpy(), c2w[:, 3], atol=1e-12)
    # a 4x4 c2w is the same camera
    entries = json.loads((tmp_path / "all_data.json").read_text())
    for e in entries:
        e["c2w"] = e["c2w"] + [[0.0, 0.0, 0.0, 1.0]]
    (tmp_path / "all_data.json").write_text(json.dumps(entries))
    for camera, (c2w, K) in zip(load_sequence(tmp_path).cameras, poses):
        assert_round_trip(camera, c2w, K)


def test_no_times_no_frame_rate(tmp_path):
    write_sequence(tmp_path, times=False)
    assert load_sequence(tmp_path).fps is None


def edit(folder, change):
    """Rewrite all_data.json with ``change(entries)`` applied."""
    entries = json.loads((folder / "all_data.json").read_text())
    change(entries)
    (folder / "all_data.json").write_text(json.dumps(entries))


def entry(entries, camera, frame):
    return next(e for e in entries if e["file_path"] == f"./data/r_{camera}_{frame}.png")


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda es: es.remove(entry(es, 2, 1)), "camera 2 has no image of frame 1 (3 camera(s) do: 0, 1, 3)"),
        (lambda es: entry(es, 1, 2)["c2w"][0].__setitem__(3, 9.0), "camera 1's c2w differs from its frame 0's"),
        (lambda es: entry(es, 3, 1).__setitem__("time", 0.5), "the cameras' times of frame 1 differ"),
        (
            lambda es: [e.__setitem__("time", 0.1) for e in es if e["file_path"].endswith("_2.png")],
            "the frames are not evenly spaced in time",
        ),
        (lambda es: entry(es, 0, 0).__setitem__("file_path", "./data/cam0.png"), "is not named r_CAMERA_FRAME.png"),
        (lambda es: entry(es, 0, 0)["intrinsic"].pop(), "intrinsic must be a finite 3x3 matrix"),
        (lambda es: entry(es, 0, 1).pop("c2w"), "missing c2w"),
    ],
)
def test_bad_index_is_one_clear_error(tmp_path, change, message):
    write_sequence(tmp_path)
    edit(tmp_path, change)
    with pytest.raises(InputError) as info:
        load_sequence(tmp_path)
    assert message in str(info.value)


def test_cli_bad_input(tmp_path):
    one_line_error([tmp_path, "--frame", "0", "-o", tmp_path / "out"], "no all_data.json")
    write_sequence(tmp_path / "seq")
    one_line_error(
        [tmp_path / "seq", "--frame", "3", "-o", tmp_path / "out"],
        "frame 3 is out of range: the sequence has frames 0 to 2",
    )
    one_line_error([tmp_path / "seq", "-o", tmp_path / "out"], "pick the frame to train on with --frame N")
    one_line_error(
        [tmp_path / "seq", "--frame", "0", "--transforms", tmp_path / "seq" / "all_data.json", "-o", tmp_path / "out"],
        "drop --transforms",
    )
    (tmp_path / "seq" / "data" / "r_1_2.png").unlink()
    one_line_error([tmp_path / "seq", "--frame", "2", "-o", tmp_path / "out"], "r_1_2.png")
    assert not (tmp_path / "out").exists()


def test_reconstruct_frame_0(tmp_path):
    write_sequence(tmp_path / "seq", cameras=4, frames=2, size=SIZE)
    code, output = run(
        [
            tmp_path / "seq",
            "--frame",
            "0",
            "-o",
            tmp_path / "recon",
            "--iterations",
            "20",
            "--init-points",
            "200",
            "--holdout-every",
            "0",
            "--preview-every",
            "0",
        ]
    )
    assert code == 0, output
    assert [c.name for c in load_cameras_json(tmp_path / "recon" / "cameras.json")] == [f"r_{c}_0" for c in range(4)]
    assert len(load_ply(tmp_path / "recon" / "point_cloud.ply")) > 0
    assert torch.isfinite(load_ply(tmp_path / "recon" / "point_cloud.ply").means).all()
