"""scene.dataparser_transforms: a splatfacto-style export (the scene moved by nerfstudio's
transform and scale) lines up with the cameras of the capture's transforms.json."""

import json

import numpy as np
import torch
import yaml

from clflow.pipeline.render import render_rgb
from clflow.scene.config import load_config
from clflow.scene.load import guidance_camera, load_scene_gaussians
from clflow.splat.gaussians import Gaussians
from clflow.splat.geometry import covariances_of, rotmat_to_quat
from clflow.splat.ply import load_ply, save_ply
from clflow.splat.sh import rotate_sh
from tests.splat._helpers import rotations


def test_a_transformed_export_renders_like_the_capture(quick_demo, tmp_path):
    data = yaml.safe_load((quick_demo / "config.yaml").read_text())
    data["splats"], data["video"] = str(quick_demo / "scene.ply"), str(quick_demo / "guidance")
    (tmp_path / "capture.yaml").write_text(yaml.safe_dump(data))
    capture = load_config(tmp_path / "capture.yaml")
    camera = guidance_camera(capture)  # scale 1, +y up: the capture's own frame
    # the capture's transforms.json (OpenGL camera-to-world) and nerfstudio's transform of it
    c2w = torch.linalg.inv(camera.viewmat) @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
    K = camera.K
    (tmp_path / "transforms.json").write_text(
        json.dumps(
            {
                "fl_x": float(K[0, 0]),
                "fl_y": float(K[1, 1]),
                "cx": float(K[0, 2]),
                "cy": float(K[1, 2]),
                "w": camera.width,
                "h": camera.height,
                "frames": [{"file_path": "images/0.png", "transform_matrix": c2w.tolist()}],
            }
        )
    )
    R, t, s = rotations(1, seed=2)[0], torch.tensor([0.2, -0.4, 0.1], dtype=torch.float64), 0.6
    (tmp_path / "dataparser_transforms.json").write_text(
        json.dumps({"transform": torch.cat([R, t[:, None]], 1).tolist(), "scale": s})
    )
    # the splatfacto export: the scene in the model frame x' = s (R x + t)
    g = load_ply(quick_demo / "scene.ply").to(torch.float64)
    turned = R @ g.rotations
    save_ply(
        tmp_path / "export.ply",
        Gaussians.from_activated(
            s * (g.means @ R.T + t),
            rotmat_to_quat(turned),
            s * g.scales,
            g.opacities,
            sh=rotate_sh(g.sh, R.expand(len(g), 3, 3)),
        ),
    )
    torch.testing.assert_close(covariances_of(s * g.scales, turned), s**2 * R @ g.covariances @ R.T)

    data["splats"] = str(tmp_path / "export.ply")
    data["camera"] = {"file": "transforms.json"}
    data["scene"]["dataparser_transforms"] = "dataparser_transforms.json"
    data["object"]["select"] = {"sphere": {"center": [0.0, 0.0, 0.0], "radius": 1e6}}  # every Gaussian
    capture_data = dict(
        data, splats=str(quick_demo / "scene.ply"), scene={"scale": 1.0, "up": "+y"}, camera={"file": "transforms.json"}
    )
    images = []
    for name, content in (("export.yaml", data), ("plain.yaml", capture_data)):
        (tmp_path / name).write_text(yaml.safe_dump(content))
        cfg = load_config(tmp_path / name)
        scene, _ = load_scene_gaussians(cfg, torch.float64)
        with torch.no_grad():
            images.append(render_rgb(scene, guidance_camera(cfg)).numpy())
    assert np.abs(images[1] - 1).mean() > 0.02  # the object is in view
    np.testing.assert_allclose(images[0], images[1], atol=1e-3)  # the export holds float32
    # without the transforms the export does not line up
    del data["scene"]["dataparser_transforms"]
    (tmp_path / "unaligned.yaml").write_text(yaml.safe_dump(data))
    cfg = load_config(tmp_path / "unaligned.yaml")
    with torch.no_grad():
        unaligned = render_rgb(load_scene_gaussians(cfg, torch.float64)[0], guidance_camera(cfg)).numpy()
    assert np.abs(unaligned - images[1]).mean() > 0.01
