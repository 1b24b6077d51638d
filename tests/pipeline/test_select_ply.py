"""object.select.ply: the object picked by a PLY of the part (as a splat editor exports it),
its Gaussian centres matched to the scene's within a tolerance."""

import logging

import pytest
import torch
import yaml

from clflow.errors import InputError
from clflow.scene.config import load_config
from clflow.scene.load import PART_TOLERANCE, select_object
from clflow.splat.compressed_ply import morton_order, save_compressed_ply
from clflow.splat.gaussians import Gaussians
from clflow.splat.ply import load_ply, save_ply


def config_with(demo, tmp_path, select):
    """The quick demo's config with ``object.select`` replaced, written in tmp_path."""
    data = yaml.safe_load((demo / "config.yaml").read_text())
    data["splats"], data["video"] = str(demo / "scene.ply"), str(demo / "guidance")
    data["object"]["select"] = select
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(data))
    return load_config(path)


def save_part(path, g: Gaussians, index, shift=0.0):
    """The Gaussians ``index`` of g, moved by ``shift`` (scene units), as a 3DGS PLY."""
    part = g.select(index)
    save_ply(path, Gaussians(part.means + shift, part.quats, part.log_scales, part.opacity_logits, sh=part.sh))


def test_a_part_selects_what_the_box_selects(quick_demo, tmp_path):
    box = config_with(
        quick_demo, tmp_path, yaml.safe_load((quick_demo / "config.yaml").read_text())["object"]["select"]
    )
    scene = load_ply(quick_demo / "scene.ply")
    want = select_object(box, scene.means.double())
    assert 0 < int(want.sum()) < len(scene)
    save_part(tmp_path / "part.ply", scene, want, shift=1e-7)  # an editor's float rounding
    got = select_object(config_with(quick_demo, tmp_path, {"ply": "part.ply"}), scene.means.double())
    assert torch.equal(got, want)
    # a compressed part (as SuperSplat exports it) matches within its quantisation error
    part = load_ply(tmp_path / "part.ply")
    save_compressed_ply(tmp_path / "part.compressed.ply", part)
    moved = (
        (
            load_ply(tmp_path / "part.compressed.ply").means
            - part.means[torch.from_numpy(morton_order(part.means.numpy()))]
        )
        .norm(dim=1)
        .max()
    )
    diagonal = (scene.means.max(0).values - scene.means.min(0).values).norm()
    assert moved > PART_TOLERANCE * diagonal  # farther than the default tolerance of a plain part
    compressed = select_object(config_with(quick_demo, tmp_path, {"ply": "part.compressed.ply"}), scene.means.double())
    assert torch.equal(compressed, want)
    # a loose tolerance takes neighbours too; an exact one nothing
    loose = select_object(
        config_with(quick_demo, tmp_path, {"ply": "part.ply", "tolerance": 0.05}), scene.means.double()
    )
    assert int(loose.sum()) > int(want.sum()) and bool(loose[want].all())
    with pytest.raises(InputError, match=r"part.ply: none of its \d+ Gaussian centres lies within 1e-09 scene units"):
        select_object(config_with(quick_demo, tmp_path, {"ply": "part.ply", "tolerance": 1e-9}), scene.means.double())


def test_a_part_of_another_scene_is_refused_and_a_partial_one_logged(quick_demo, tmp_path, caplog):
    scene = load_ply(quick_demo / "scene.ply")
    save_part(tmp_path / "moved.ply", scene, torch.arange(50), shift=0.3)
    cfg = config_with(quick_demo, tmp_path, {"ply": "moved.ply"})
    with pytest.raises(
        InputError,
        match=r"moved.ply: none of its 50 Gaussian centres lies within .* not a part of "
        r"this splat file, or moved since",
    ):
        select_object(cfg, scene.means.double())
    part = scene.select(torch.arange(20))
    extra = Gaussians.cat(
        [part, Gaussians(part.means + 5.0, part.quats, part.log_scales, part.opacity_logits, sh=part.sh)]
    )
    save_ply(tmp_path / "partial.ply", extra)
    with caplog.at_level(logging.WARNING):
        got = select_object(config_with(quick_demo, tmp_path, {"ply": "partial.ply"}), scene.means.double())
    assert int(got.sum()) == 20 and "partial.ply: 20 of its 40 Gaussian centres match no Gaussian" in caplog.text


@pytest.mark.parametrize(
    "select, message",
    [
        (
            {"ply": "part.ply", "box": {"min": [0, 0, 0], "max": [1, 1, 1]}},
            "object.select: give exactly one of box, sphere, mask and ply",
        ),
        (
            {"box": {"min": [0, 0, 0], "max": [1, 1, 1]}, "tolerance": 0.1},
            "object.select.tolerance: applies to a ply selection only",
        ),
        ({"ply": "part.ply", "tolerance": 0}, r"object.select.tolerance: must be in \(0, 1e\+09\], got 0"),
        ({"ply": "nope.ply"}, "object.select.ply: file not found"),
    ],
)
def test_bad_ply_selections(quick_demo, tmp_path, select, message):
    (tmp_path / "part.ply").write_bytes((quick_demo / "scene.ply").read_bytes())
    with pytest.raises(InputError, match=message):
        config_with(quick_demo, tmp_path, select)
