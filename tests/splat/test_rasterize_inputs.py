"""Bad inputs give clear InputErrors; the device sort and tile lists against torch."""

import math

import pytest
import torch

from clflow.errors import InputError
from clflow.splat.binning import build_tile_lists, tile_grid
from clflow.splat.constants import TILE_SIZE
from clflow.splat.ops import covariances, project, rasterize_gaussians
from clflow.splat.reference import tile_rect_reference
from tests.splat._helpers import camera, random_scene

W, H = 40, 36


SCENE = ("means", "quats", "scales", "opacities", "colors")  # random_scene's tensors, in order


def render(**change):
    viewmat, K = camera(W, H, 30.0)
    args = dict(zip(SCENE, random_scene(8, seed=0)), viewmat=viewmat, K=K, width=W, height=H)
    args.update(change)
    return rasterize_gaussians(**args)


def with_value(name, index, value):
    t = random_scene(8, seed=0)[SCENE.index(name)].clone()
    t[index] = value
    return {name: t}


@pytest.mark.parametrize(
    "change,message",
    [
        (with_value("means", (3, 1), math.nan), "means has NaN or infinite values (first at index 3)"),
        (with_value("colors", (2, 0), math.inf), "colors has NaN or infinite values (first at index 2)"),
        (with_value("quats", 5, 0.0), "quats[5] is (nearly) zero"),
        (with_value("quats", 2, 1e-9), "quats[2] is (nearly) zero (norm < 1e-08)"),  # as Gaussians.validate
        (with_value("scales", (4, 2), 0.0), "scales[4]"),
        (with_value("scales", (1, 0), -0.1), "zero or negative standard deviation"),
        (with_value("opacities", 6, 1.5), "opacities[6] = 1.5 is outside [0, 1]"),
        ({"means": torch.zeros(8, 2, dtype=torch.float64)}, "means has shape [8, 2], expected [*, 3]"),
        ({"colors": torch.zeros(8, 3)}, "colors is torch.float32 but means are torch.float64"),
        ({"viewmat": torch.diag(torch.tensor([1.0, 2.0, 1.0, 1.0], dtype=torch.float64))}, "not orthonormal"),
        ({"K": torch.zeros(3, 3, dtype=torch.float64)}, "focal lengths must be positive"),
        ({"width": 0}, "width must be a positive int"),
        ({"near": 0.0}, "near must be > 0"),
        ({"background": torch.zeros(4, dtype=torch.float64)}, "background has shape [4], expected [3]"),
        ({"covars": torch.zeros(8, 3, 3, dtype=torch.float64)}, "either covars or quats and scales"),
        ({"sh_degree": 4}, "sh_degree must be 0..3"),
        ({"sh_degree": 1}, "colors (SH coefficients) has shape [8, 3]"),
    ],
)
def test_bad_input_raises_clear_error(change, message):
    with pytest.raises(InputError) as info:
        render(**change)
    assert message in str(info.value)


def test_tile_lists_hold_each_tiles_gaussians_front_to_back():
    means, quats, scales, opacities, _ = random_scene(50, seed=1, spread=1.0)
    viewmat, K = camera(W, H, 30.0)
    covars = covariances(quats, scales).contiguous()
    means2d, conics, depths, radii, touched = project(means, covars, viewmat, K, W, H, 0.01)
    lists = build_tile_lists(means2d, depths, radii, touched, W, H)
    tiles_x, tiles_y = tile_grid(W, H)
    x0, y0, x1, y1 = tile_rect_reference(means2d, radii, tiles_x, tiles_y)
    assert lists.num_entries == int(touched.sum())
    for t in range(tiles_x * tiles_y):
        tx, ty = t % tiles_x, t // tiles_x
        inside = (radii > 0) & (x0 <= tx) & (tx < x1) & (y0 <= ty) & (ty < y1)
        expected = torch.nonzero(inside)[:, 0]
        expected = expected[torch.sort(depths[expected].float(), stable=True).indices]
        start, end = lists.ranges[t].tolist()
        got = lists.slot_gaussian[lists.sorted_slots[start:end].long()]
        assert torch.equal(got.long(), expected), f"tile {t}"
    # slots of a Gaussian are contiguous, starting at first_slot
    for g in torch.nonzero(radii > 0)[:, 0].tolist():
        first = int(lists.first_slot[g])
        assert torch.all(lists.slot_gaussian[first : first + int(touched[g])] == g)


def test_image_size_not_a_multiple_of_the_tile_size():
    img, alpha, _, _ = render(width=TILE_SIZE + 1, height=3)
    assert img.shape == (3, TILE_SIZE + 1, 3) and torch.isfinite(img).all()


def test_bench_raster_command_runs_on_a_small_scene():
    from click.testing import CliRunner

    from clflow_cli.main import cli

    result = CliRunner().invoke(cli, ["bench", "raster", "-n", "2000", "--size", "64", "--repeat", "1"])
    assert result.exit_code == 0, result.output
    assert "tile entries" in result.output and "forward:" in result.output and "backward:" in result.output


@pytest.mark.parametrize("dtype,scale,radius", [(torch.float64, 1e12, 1 << 24), (torch.float32, 1e18, 0)])
def test_huge_gaussians_are_capped_or_culled_never_undefined(dtype, scale, radius):
    """A radius past MAX_RADIUS is capped (the box covers the image); a covariance whose
    2D projection overflows float32 (det is not finite) is culled."""
    means, quats, scales, opacities, colors = (t.to(dtype) for t in random_scene(3, seed=2))
    scales[0] = scale
    viewmat, K = camera(W, H, 30.0, dtype=dtype)
    img, alpha, depth, meta = rasterize_gaussians(means, quats, scales, opacities, colors, viewmat, K, W, H)
    assert int(meta["radii"][0]) == radius
    assert torch.isfinite(img).all() and torch.isfinite(depth).all()


def test_tile_lists_past_the_memory_bound_raise(monkeypatch):
    import clflow.splat.binning as binning

    monkeypatch.setattr(binning, "MAX_TILE_ENTRIES", 3)
    with pytest.raises(InputError, match=r"\(tile, Gaussian\) pairs, more than the bound 3"):
        render()
