"""Posed views for reconstruction: camera sources, masks, and bad input refused before training."""

import json
import math

import cv2
import numpy as np
import pytest
import torch

from clflow.errors import InputError
from clflow.fileio import atomic_write_text
from clflow.recon.views import load_views
from clflow.splat.cameras import OPENGL_TO_OPENCV, load_cameras_json, orbit, save_cameras_json
from tests.recon._helpers import model_of, one_line_error, run, write_bin

W, H = 16, 12


def cameras(n=4):
    return orbit((0, 0, 0), 3.0, n_views=n, elevation=math.radians(20), fov_x=1.0, width=W, height=H)


def write_png(path, rgba):
    path.parent.mkdir(parents=True, exist_ok=True)
    order = [2, 1, 0, 3][: rgba.shape[2]]
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgba[..., order]))


def capture(folder, n=4, per_frame=False, alpha=None):
    """n images (RGB, or RGBA with ``alpha`` [H, W] uint8) and a transforms.json; per-frame
    intrinsics (fl_x, w, h per frame) when ``per_frame``. Returns the images [n, H, W, 3] uint8."""
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (n, H, W, 3), dtype=np.uint8)
    frames = []
    for i, c in enumerate(cameras(n)):
        rgba = images[i] if alpha is None else np.concatenate([images[i], alpha[..., None]], axis=2)
        write_png(folder / "images" / f"v{i}.png", rgba)
        frame = {"file_path": f"images/v{i}", "transform_matrix": (c.camtoworld() @ OPENGL_TO_OPENCV).tolist()}
        if per_frame:
            frame.update(fl_x=c.fx * (1 + 0.1 * i), w=W, h=H)
        frames.append(frame)
    meta = {} if per_frame else {"camera_angle_x": 1.0, "w": W, "h": H}
    (folder / "transforms.json").write_text(json.dumps({**meta, "frames": frames}))
    return images


def test_transforms_with_shared_intrinsics_and_images(tmp_path):
    images = capture(tmp_path)
    data = load_views(tmp_path / "images")  # transforms.json found in the parent folder
    assert len(data.views) == 4 and data.points_xyz is None
    for view, image, camera in zip(data.views, images, cameras()):
        assert view.image.shape == (H, W, 3) and view.image.dtype == torch.float32
        assert torch.allclose(view.image, torch.from_numpy(image).float() / 255)
        assert torch.allclose(view.camera.viewmat, camera.viewmat, atol=1e-12)
        assert view.camera.fx == pytest.approx(W / (2 * math.tan(0.5)))


def test_transforms_with_per_frame_intrinsics(tmp_path):
    capture(tmp_path, per_frame=True)
    data = load_views(tmp_path / "images", transforms=tmp_path / "transforms.json")
    focal = [v.camera.fx for v in data.views]
    assert focal == pytest.approx([cameras()[0].fx * (1 + 0.1 * i) for i in range(4)])


def test_split_holds_out_every_kth_view(tmp_path):
    capture(tmp_path, n=10)
    train, test = load_views(tmp_path / "images").split(holdout_every=4)
    assert [v.path.stem for v in test] == ["v0", "v4", "v8"] and len(train) == 7


def test_colmap_model_and_cameras_json_give_the_same_views(tmp_path):
    capture(tmp_path)
    truth = [v.camera for v in load_views(tmp_path / "images").views]
    for c in truth:
        c.name = c.name.split("/")[-1] + ".png"
    points = np.array([[0.0, 0.0, 0.0], [0.1, 0.2, 0.3]])
    write_bin(tmp_path / "sparse" / "0", model_of(truth, points))
    from_colmap = load_views(tmp_path / "images", colmap=tmp_path / "sparse" / "0")
    save_cameras_json(tmp_path / "cams" / "cameras.json", truth)
    from_json = load_views(tmp_path / "images", cameras_json=tmp_path / "cams" / "cameras.json")
    assert [c.name for c in load_cameras_json(tmp_path / "cams" / "cameras.json")] == [c.name for c in truth]
    assert torch.allclose(from_colmap.points_xyz, torch.tensor(points, dtype=torch.float32))
    assert from_colmap.points_rgb[:, 1].tolist() == pytest.approx([100 / 255] * 2)
    for a, b, c in zip(from_colmap.views, from_json.views, truth):
        assert torch.allclose(a.camera.viewmat, c.viewmat, atol=1e-12)
        assert torch.allclose(b.camera.viewmat, c.viewmat, atol=1e-12)
        assert torch.equal(a.image, b.image)


def test_alpha_channel_and_mask_folder_composite_over_the_background(tmp_path):
    alpha = np.zeros((H, W), np.uint8)
    alpha[:, : W // 2] = 255
    images = capture(tmp_path, alpha=alpha)
    white = load_views(tmp_path / "images", background=(1, 1, 1)).views[0].image
    assert torch.allclose(white[:, : W // 2], torch.from_numpy(images[0, :, : W // 2]).float() / 255)
    assert bool((white[:, W // 2 :] == 1).all())
    for i in range(4):  # a mask folder overrides the alpha channel
        write_png(tmp_path / "masks" / f"v{i}.png", np.repeat(255 - alpha[..., None], 3, axis=2))
    black = load_views(tmp_path / "images", masks=tmp_path / "masks").views[0].image
    assert bool((black[:, : W // 2] == 0).all())
    assert torch.allclose(black[:, W // 2 :], torch.from_numpy(images[0, :, W // 2 :]).float() / 255)


def test_images_of_different_sizes_with_one_intrinsic(tmp_path):
    capture(tmp_path)
    write_png(tmp_path / "images" / "v2.png", np.zeros((H + 4, W, 3), np.uint8))
    one_line_error(
        [tmp_path / "images", "-o", tmp_path / "out"],
        "v2.png: the image is 16x16 px but transforms.json gives its camera 16x12 px",
    )


def test_missing_image(tmp_path):
    capture(tmp_path)
    (tmp_path / "images" / "v3.png").unlink()
    one_line_error([tmp_path / "images", "-o", tmp_path / "out"], "camera 'images/v3' names an image that is not in")


def test_non_orthonormal_rotation(tmp_path):
    capture(tmp_path)
    data = json.loads((tmp_path / "transforms.json").read_text())
    data["frames"][1]["transform_matrix"][0][0] += 0.05
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    one_line_error(
        [tmp_path / "images", "-o", tmp_path / "out"],
        "frames[1]: camera 'images/v1': the rotation of viewmat is not orthonormal",
    )


def test_empty_masks(tmp_path):
    capture(tmp_path, alpha=np.full((H, W), 255, np.uint8))
    write_png(tmp_path / "images" / "v1.png", np.zeros((H, W, 4), np.uint8))
    one_line_error([tmp_path / "images", "-o", tmp_path / "out"], "v1.png: the mask is empty")
    (tmp_path / "masks").mkdir()
    one_line_error(
        [tmp_path / "images", "-o", tmp_path / "out", "--masks", tmp_path / "masks"], "no mask for image v0.png"
    )


def test_no_cameras_and_two_camera_sources(tmp_path):
    (tmp_path / "images").mkdir()
    one_line_error([tmp_path / "images", "-o", tmp_path / "out"], "no cameras found")
    capture(tmp_path)
    with pytest.raises(InputError, match="give one cameras source, not transforms and colmap"):
        load_views(tmp_path / "images", transforms=tmp_path / "transforms.json", colmap=tmp_path)


def test_ctrl_c_says_whether_there_is_a_checkpoint_to_resume(tmp_path, monkeypatch):
    import clflow.recon.train

    def interrupted(views, out, *args, **kwargs):
        raise KeyboardInterrupt

    capture(tmp_path)
    monkeypatch.setattr(clflow.recon.train, "reconstruct", interrupted)
    code, output = run([tmp_path / "images", "-o", tmp_path / "out"])
    assert code == 130 and "interrupted before the first checkpoint; nothing was saved" in output
    atomic_write_text(tmp_path / "out" / "checkpoint.pt", "")  # as an earlier run wrote it
    code, output = run([tmp_path / "images", "-o", tmp_path / "out"])
    assert code == 130 and "continue with the same command and --resume" in output


def test_the_training_options_reach_the_settings(tmp_path, monkeypatch):
    import clflow.recon.train

    seen = {}

    def record(views, out, settings, **kwargs):
        seen["settings"] = settings
        raise KeyboardInterrupt

    capture(tmp_path)
    monkeypatch.setattr(clflow.recon.train, "reconstruct", record)
    code, output = run(
        [
            tmp_path / "images",
            "-o",
            tmp_path / "out",
            "--iterations",
            "7",
            "--seed",
            "3",
            "--densify-every",
            "9",
            "--holdout-every",
            "4",
            "--background",
            "white",
        ]
    )
    assert code == 130, output
    s = seen["settings"]
    assert (s.iterations, s.seed, s.densify_every, s.holdout_every) == (7, 3, 9, 4)
    assert s.background == (1.0, 1.0, 1.0)
    assert (s.sh_degree, s.init_points) == (3, 10_000)  # options not given keep Settings' defaults
