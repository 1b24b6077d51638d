"""`clflow pacnerf`: a PAC-NeRF-style capture + its frame-0 splats as a clflow scene
(config, camera, guidance video), PAC-NeRF configs read without running them."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from clflow.errors import InputError
from clflow.media import decode_video
from clflow.scene.config import load_config
from clflow.scene.load import guidance_camera
from clflow.splat.gaussians import Gaussians
from clflow.splat.ply import save_ply
from clflow_datasets.pacnerf import pacnerf_boundaries, pacnerf_material, read_pacnerf_config
from tests.recon._helpers import colour, one_line_error, run, write_sequence
from tests.recon.test_sequence import assert_round_trip

SIZE = 32

BASE = """cfg = dict(
    frame_dt=1/24,
    gravity=[0, -9.8, 0],
    BC = {"ground": [[0, 0, 0], [0, 1, 0]]},
    physical_params=dict(),
)
"""

TORUS = """from lib.engine import MPMSimulator

_base_ = 'default.py'

cfg = dict(
    n_cameras = 4,
    n_frames = 3,
    material = MPMSimulator.elasticity,
    dt = 1/24/200,
    E = 1e5,
    nu = 0.1,
    rho = 1000,
    hit_frame = 1,
    physical_params = dict(global_E=1e-1, global_nu=1e-2),
)

del MPMSimulator
"""


def write_config(folder: Path, text: str = TORUS) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "default.py").write_text(BASE)
    (folder / "case.py").write_text(text)
    return folder / "case.py"


def write_splats(path: Path) -> None:
    """Three opaque Gaussians in [-0.2, 0.3] and a faint one far away (outside the object box)."""
    means = torch.tensor([[-0.2, 0.1, 0.0], [0.3, 0.4, 0.1], [0.0, 0.2, -0.1], [5.0, 5.0, 5.0]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(4, 1)
    save_ply(
        path,
        Gaussians.from_activated(
            means, quats, torch.full((4, 3), 0.05), torch.tensor([0.9, 0.8, 0.7, 0.02]), colors=torch.full((4, 3), 0.5)
        ),
    )


def test_read_config_merges_its_base_without_running_it(tmp_path):
    cfg = read_pacnerf_config(write_config(tmp_path))
    assert cfg["material"] == "elasticity" and cfg["E"] == 1e5 and cfg["dt"] == pytest.approx(1 / 4800)
    assert cfg["frame_dt"] == pytest.approx(1 / 24) and cfg["BC"] == {"ground": [[0, 0, 0], [0, 1, 0]]}
    assert cfg["physical_params"] == {"global_E": 0.1, "global_nu": 0.01}  # the case's, over the base's
    (tmp_path / "case.json").write_text(json.dumps({"material": "viscous_fluid", "mu": 1.0, "kappa": 1e3}))
    assert read_pacnerf_config(tmp_path / "case.json")["kappa"] == 1e3


@pytest.mark.parametrize(
    "name, text, match",
    [
        (
            "bad.py",
            "import os\ncfg = dict(E=os.getcwd())\n",
            "line 2: cannot read 'os.getcwd\\(\\)' without running the file",
        ),
        ("loop.py", "_base_ = 'loop.py'\ncfg = dict(E=1)\n", "is a cycle of base files"),
        ("orphan.py", "_base_ = 'gone.py'\ncfg = dict(E=1)\n", "gone.py: PAC-NeRF config not found \\(the _base_ of"),
    ],
)
def test_read_config_refuses_what_it_cannot_read_without_running(tmp_path, name, text, match):
    (tmp_path / name).write_text(text)
    with pytest.raises(InputError, match=match):
        read_pacnerf_config(tmp_path / name)


@pytest.mark.parametrize(
    "cfg, material, params, fit",
    [
        (
            {"material": "elasticity", "E": 1e5, "nu": 0.1, "physical_params": {"global_E": 0.1, "global_nu": 0.01}},
            {"type": "elastic", "model": "neo_hookean"},
            {"youngs_modulus": 1e5, "poissons_ratio": 0.1},
            ["youngs_modulus", "poissons_ratio"],
        ),
        (
            {
                "material": "von_mises",
                "E": 1e5,
                "nu": 0.4,
                "yield_stress": 1e3,
                "physical_params": {"yield_stress": 0.1},
            },
            {"type": "plasticine"},
            {"youngs_modulus": 1e5, "poissons_ratio": 0.4, "yield_stress": 1e3},
            ["yield_stress"],
        ),
        (
            {
                "material": "von_mises",
                "mu": 100,
                "kappa": 1e4,
                "yield_stress": 10,
                "plastic_viscosity": 0.1,
                "physical_params": {
                    "global_mu": 0.2,
                    "global_kappa": 0.2,
                    "yield_stress": 0.2,
                    "plastic_viscosity": 0.1,
                },
            },
            {"type": "non_newtonian"},
            {"shear_modulus": 100, "bulk_modulus": 1e4, "yield_stress": 10, "viscosity": 0.1},
            ["shear_modulus", "bulk_modulus", "yield_stress", "viscosity"],
        ),
        (
            {"material": 11, "mu": 10, "kappa": 1e4, "physical_params": {"global_mu": 0.1, "global_kappa": 0.1}},
            {"type": "newtonian"},
            {"viscosity": 5.0, "bulk_modulus": 7e4},
            ["viscosity", "bulk_modulus"],
        ),
        (
            {
                "material": "drucker_prager",
                "E": 1e6,
                "nu": 0.3,
                "friction_angle": 10,
                "physical_params": {"friction_angle": 1},
            },
            {"type": "sand", "model": "drucker_prager"},
            {"friction_angle": 10, "youngs_modulus": 1e6, "poissons_ratio": 0.3},
            ["friction_angle"],
        ),
    ],
)
def test_materials_in_clflow_conventions(cfg, material, params, fit):
    section, names = pacnerf_material(cfg, "case.py")
    assert {k: section[k] for k in material} == material
    assert section["parameters"] == pytest.approx(params) and section["density"] == 1000.0
    assert names == fit


def test_boundary_planes():
    bc = {"ground": [[0, 0.1, 0], [0, 2, 0]], "wall": [[0.5, 0, 0], [-1, 0, 0]]}
    assert pacnerf_boundaries({"BC": bc}, "case.py") == {
        "ground": {"height": 0.1, "mode": "sticky"},
        "colliders": [{"point": [0.5, 0.0, 0.0], "normal": [-1.0, 0.0, 0.0], "mode": "sticky"}],
    }
    with pytest.raises(InputError, match="BC 'pole' is not a plane"):
        pacnerf_boundaries({"BC": {"pole": [[0, 0, 0], [0, 1, 0], 0.1]}}, "case.py")


def test_unmappable_configs_are_refused(tmp_path):
    with pytest.raises(InputError, match="material elasticity needs the number\\(s\\) nu"):
        pacnerf_material({"material": "elasticity", "E": 1e5}, "case.py")
    with pytest.raises(InputError, match="poissons_ratio"):
        pacnerf_material({"material": "elasticity", "E": 1e5, "nu": 0.7}, "case.py")
    with pytest.raises(InputError, match="physical_params damping have no clflow counterpart"):
        pacnerf_material({"material": "elasticity", "E": 1e5, "nu": 0.2, "physical_params": {"damping": 1}}, "c")


def test_scene_from_config_is_optimize_ready(tmp_path):
    poses = write_sequence(tmp_path / "seq", cameras=4, frames=3, size=SIZE)
    write_splats(tmp_path / "splats.ply")
    code, output = pacnerf(
        tmp_path,
        "splats.ply",
        "scene",
        "--camera",
        "1",
        "--config",
        write_config(tmp_path / "configs"),
        "--video",
        "mkv",
    )
    assert code == 0, output
    assert "3 frames at 24 fps (from " in output and "frame_dt" in output
    cfg = load_config(tmp_path / "scene" / "config.yaml")
    assert (cfg.objects[0].material.type, cfg.objects[0].material.model) == ("elastic", "neo_hookean")
    assert cfg.objects[0].material.parameters == {"youngs_modulus": 1e5, "poissons_ratio": 0.1}
    assert cfg.objects[0].material.density == 1000.0 and cfg.simulation.gravity == (0.0, -9.8, 0.0)
    (ground,) = cfg.colliders
    assert (ground.point, ground.normal, ground.mode) == ((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), "sticky")
    assert (cfg.simulation.fps, cfg.simulation.frames) == (24.0, 2)
    assert cfg.optimize.parameters == ("youngs_modulus", "poissons_ratio")
    assert (cfg.optimize.estimate_velocity_frames, cfg.optimize.estimate_velocity_iterations) == (1, 10)
    box = cfg.objects[0].selection.region
    assert box.kind == "box" and box.lower[0] < -0.2 < 0.3 < box.upper[0] and box.upper[1] < 5.0  # faint one out
    # the camera: camera 1's PAC-NeRF pose and intrinsic, through the config (+y up, scale 1)
    c2w, K = poses[1]
    assert_round_trip(guidance_camera(cfg), c2w, K)
    # the video: camera 1's frames at 24 fps, lossless, composited over white (the default)
    frames, times, fps = decode_video(tmp_path / "scene" / "guidance.mkv")
    assert frames.shape == (3, SIZE, SIZE, 3) and fps == pytest.approx(24.0)
    np.testing.assert_allclose(times, [0, 1 / 24, 2 / 24], atol=1e-3)
    for t in range(3):
        assert frames[t, SIZE // 2, SIZE // 2].tolist() == list(colour(1, t))
        assert frames[t, 0, 0].tolist() == [255, 255, 255]
    assert not (tmp_path / "scene" / "object.png").exists()


def test_scene_without_config_leaves_the_material_to_the_query(tmp_path):
    write_sequence(tmp_path / "seq", cameras=3, frames=4, size=SIZE, fps=12.0)
    write_splats(tmp_path / "recon" / "point_cloud.ply")
    code, output = pacnerf(
        tmp_path, "recon", "scene", "--prompt", "a jelly torus", "--background", "black", "--ground", "0.05"
    )
    assert code == 0, output
    assert "--set optimize.parameters=" in output
    cfg = load_config(tmp_path / "scene" / "config.yaml")
    assert cfg.objects[0].material.type == "query" and cfg.objects[0].material.query_prompt == "a jelly torus"
    assert cfg.objects[0].material.query_image == (tmp_path / "scene" / "object.png").resolve()
    assert (cfg.simulation.fps, cfg.simulation.frames) == (pytest.approx(12.0), 3)
    assert cfg.colliders[0].point == (0.0, 0.05, 0.0) and cfg.optimize.parameters == ()
    frames, _, fps = decode_video(tmp_path / "scene" / "guidance.mp4")
    assert frames.shape[0] == 4 and fps == pytest.approx(12.0)
    assert (frames[:, 0, 0] <= 3).all()  # black behind the object (H.264)
    code, output = pacnerf(tmp_path, "recon", "scene2", "--optimize", "youngs_modulus", "--fps", "30")
    assert code == 0, output
    cfg = load_config(tmp_path / "scene2" / "config.yaml")
    assert cfg.optimize.parameters == ("youngs_modulus",) and cfg.simulation.fps == 30.0


def pacnerf(tmp_path, splats, scene, *args):
    """(exit code, output) of ``clflow pacnerf TMP/seq TMP/SPLATS -o TMP/SCENE ARGS...``."""
    return run([tmp_path / "seq", tmp_path / splats, "-o", tmp_path / scene, *args], "pacnerf")


def pacnerf_error(args, match):
    one_line_error(args, match, "pacnerf")


def test_bad_input_is_one_line_and_writes_nothing(tmp_path):
    write_splats(tmp_path / "splats.ply")
    out = tmp_path / "scene"
    pacnerf_error([tmp_path, tmp_path / "splats.ply", "-o", out], "no all_data.json")
    write_sequence(tmp_path / "seq", cameras=4, frames=3, size=SIZE, times=False)
    pacnerf_error([tmp_path / "seq", tmp_path / "splats.ply", "-o", out], "no frame rate: the index has no times")
    pacnerf_error(
        [tmp_path / "seq", tmp_path / "splats.ply", "-o", out, "--fps", "24", "--camera", "4"],
        "camera 4 is out of range: the sequence has cameras 0 to 3",
    )
    pacnerf_error([tmp_path / "seq", tmp_path / "nothing", "-o", out, "--fps", "24"], "no splats")
    config = write_config(tmp_path / "configs", TORUS.replace("n_cameras = 4", "n_cameras = 11"))
    pacnerf_error([tmp_path / "seq", tmp_path / "splats.ply", "-o", out, "--config", config], "n_cameras = 11 but")
    config = write_config(tmp_path / "configs", TORUS.replace("n_frames = 3", "n_frames = 1"))
    pacnerf_error(
        [tmp_path / "seq", tmp_path / "splats.ply", "-o", out, "--config", config],
        "1 frame(s); a guidance video needs at least 2",
    )
    (tmp_path / "seq" / "data" / "r_2_1.png").unlink()
    pacnerf_error([tmp_path / "seq", tmp_path / "splats.ply", "-o", out, "--fps", "24", "--camera", "2"], "r_2_1.png")
    assert not out.exists()


def test_guidance_frame_0_is_the_scene_as_the_optimiser_renders_it(tmp_path):
    """A capture rendered from known splats: the converted video's frame 0 equals those
    splats rendered by clflow's pipeline from the config's camera (pose, intrinsics, background)."""
    from clflow.pipeline.render import render_rgb
    from clflow.recon.sequence import pacnerf_camera
    from clflow.scene.load import load_scene_gaussians
    from clflow.splat.render import rasterize

    poses = write_sequence(tmp_path / "seq", cameras=3, frames=2, size=SIZE)
    rng = np.random.default_rng(0)
    splats = Gaussians.from_activated(
        torch.from_numpy(rng.uniform(-0.3, 0.3, (40, 3))).float(),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(40, 1),
        torch.full((40, 3), 0.06),
        torch.full((40,), 0.9),
        colors=torch.from_numpy(rng.uniform(0, 1, (40, 3))).float(),
    )
    save_ply(tmp_path / "splats.ply", splats)
    for c, (c2w, K) in enumerate(poses):  # every frame: the splats, straight (not premultiplied) RGBA
        with torch.no_grad():
            render = rasterize(splats, pacnerf_camera(c2w, K, SIZE, SIZE), render_depth=False)
        rgb = render.image / render.alpha.clamp_min(1e-6)
        rgba = np.concatenate([np.clip(rgb.numpy(), 0, 1), render.alpha.numpy()], axis=2)
        for f in range(2):
            bgra = np.round(255 * rgba[..., [2, 1, 0, 3]]).astype(np.uint8)
            assert cv2.imwrite(str(tmp_path / "seq" / "data" / f"r_{c}_{f}.png"), bgra)
    code, output = pacnerf(
        tmp_path, "splats.ply", "scene", "--camera", "2", "--video", "mkv", "--box", "-1", "-1", "-1", "1", "1", "1"
    )
    assert code == 0, output
    cfg = load_config(tmp_path / "scene" / "config.yaml")
    scene, _ = load_scene_gaussians(cfg, torch.float32)
    with torch.no_grad():
        expected = (render_rgb(scene, guidance_camera(cfg)).clamp(0, 1) * 255).numpy()
    frames, _, _ = decode_video(tmp_path / "scene" / "guidance.mkv")
    assert np.abs(frames[0].astype(float) - expected).max() <= 2.5  # 8-bit rounding of colour and alpha
    assert np.abs(frames[0].astype(float) - expected).mean() < 0.5
