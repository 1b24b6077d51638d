"""Both shapes of the compositing kernels (clflow.runtime.plan: "cpu" runs rasterize_tile_rows.cl, a
work-item per tile; "gpu" runs rasterize_workgroup.cl, a work-group per tile and a work-item per
pixel) against the dense torch reference, against each other, and run twice."""

import pytest
import torch

from clflow.splat.binning import build_tile_lists
from clflow.splat.ops import composite, compositing, covariances, project
from clflow.splat.reference import composite_reference
from tests.splat._helpers import camera, random_scene

PLANS = ("cpu", "gpu")
BACKGROUND = (0.2, 0.3, 0.4, 0.0)  # colours, then depth


@pytest.fixture(params=PLANS)
def plan(request, monkeypatch):
    """Runs the test under each kernel plan ($CLFLOW_KERNELS)."""
    monkeypatch.setenv("CLFLOW_KERNELS", request.param)
    return request.param


def splats(scene: dict, dtype=torch.float64):
    """A projected scene, its tile lists and image size: (composite's tensor inputs, the
    reference's extra inputs (depths, radii), width, height)."""
    scene = dict(scene)
    width, height, shift_x = scene.pop("width"), scene.pop("height"), scene.pop("shift_x", 0.0)
    means, quats, scales, opacities, colors = random_scene(dtype=dtype, **scene)
    means[:, 0] += shift_x
    viewmat, K = camera(width, height, 30.0, dtype=dtype)
    means2d, conics, depths, radii, touched = project(
        means, covariances(quats, scales), viewmat, K, width, height, 0.01
    )
    lists = build_tile_lists(means2d, depths, radii, touched, width, height)
    features = torch.cat([colors, depths[:, None]], dim=1)
    tensors = (means2d, conics, opacities, features, torch.tensor(BACKGROUND, dtype=dtype))
    tiles = (lists.ranges, lists.sorted_slots, lists.slot_gaussian, lists.first_slot, lists.tiles_touched)
    return tensors, tiles, (depths, radii), width, height


def leaves(tensors):
    """Copies of means2d, conics, opacities and features to differentiate, and the background."""
    return [t.detach().clone().requires_grad_() for t in tensors[:4]] + [tensors[4]]


def weighted_loss(out, T_final, seed=0):
    """A fixed random projection of the image and the transmittance."""
    g = torch.Generator().manual_seed(seed)
    weights = [torch.randn(t.shape, generator=g, dtype=torch.float64).to(t.dtype) for t in (out, T_final)]
    return (out * weights[0]).sum() + (T_final * weights[1]).sum()


def run_composite(tensors, tiles, width, height):
    """composite's (out, T_final, n_contrib) and the gradients of weighted_loss w.r.t.
    means2d, conics, opacities and features."""
    inputs = leaves(tensors)
    out, T_final, n_contrib = composite(*inputs, *tiles, width, height)
    grads = torch.autograd.grad(weighted_loss(out, T_final), inputs[:4])
    return out.detach(), T_final.detach(), n_contrib, grads


def entries_per_tile(tiles):
    ranges = tiles[0].reshape(-1, 2)
    return ranges[:, 1] - ranges[:, 0]


SCENES = {
    # 3 x 3 tiles, the last row and column partial
    "partial_tiles": dict(n=60, seed=0, width=40, height=36),
    # wide, faint Gaussians: pixels walk past the first batch of 256 entries
    "deep": dict(n=400, seed=1, width=24, height=20, opacity=(0.02, 0.05), spread=0.1, scale=(0.8, 1.2)),
    # wide, opaque ones: more than 256 entries per tile, every pixel done within the first batch
    "opaque": dict(n=400, seed=2, width=24, height=20, opacity=(0.9, 1.0), spread=0.1, scale=(0.8, 1.2)),
    # all on the left: the right-hand tiles have no entry
    "empty_tiles": dict(n=30, seed=3, width=72, height=20, spread=0.3, shift_x=-1.2),
}


def check_scene_shape(name, tiles, n_contrib):
    """The scene exercises what its name says."""
    per_tile = entries_per_tile(tiles)
    if name == "deep":
        assert int(n_contrib.max()) > 256
    if name == "opaque":
        assert int(per_tile.min()) > 256 and int(n_contrib.max()) < 256
    if name == "empty_tiles":
        assert int(per_tile.min()) == 0 < int(per_tile.max())


def assert_close(a, b, tol):
    err = (a - b).abs().max().item()
    assert err <= tol, f"max abs error {err:.3g} > {tol:.3g}"


@pytest.mark.parametrize("name", SCENES)
def test_forward_and_backward_match_reference_float64(plan, name):
    """The tolerances of test_rasterize.py (1e-9) and test_rasterize_backward.py (1e-9 of the
    largest gradient)."""
    tensors, tiles, (depths, radii), width, height = splats(SCENES[name])
    out, T_final, n_contrib, grads = run_composite(tensors, tiles, width, height)
    check_scene_shape(name, tiles, n_contrib)
    inputs = leaves(tensors)
    r_out, r_T = composite_reference(*inputs, depths, radii, width, height)
    r_grads = torch.autograd.grad(weighted_loss(r_out, r_T), inputs[:4])
    assert out.shape == r_out.shape == (height, width, len(BACKGROUND))
    assert_close(out, r_out, 1e-9)
    assert_close(T_final, r_T, 1e-9)
    for what, a, b in zip(("means2d", "conics", "opacities", "features"), grads, r_grads):
        scale = b.abs().max().item()
        assert scale > 0, what
        assert (a - b).abs().max().item() <= 1e-9 * max(1.0, scale), what


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
@pytest.mark.parametrize("name", SCENES)
def test_the_two_shapes_agree(monkeypatch, name, dtype, tol):
    """Same skip/stop decisions and per-pixel terms; the sums differ in order only
    (tolerances relative to the largest value)."""
    tensors, tiles, _, width, height = splats(SCENES[name], dtype)
    runs = {}
    for kind in PLANS:
        monkeypatch.setenv("CLFLOW_KERNELS", kind)
        runs[kind] = run_composite(tensors, tiles, width, height)
    (out, T_final, n_contrib, grads), (g_out, g_T, g_n, g_grads) = runs["cpu"], runs["gpu"]
    assert torch.equal(n_contrib, g_n)
    for a, b in zip((out, T_final, *grads), (g_out, g_T, *g_grads)):
        assert_close(a, b, tol * max(1.0, a.abs().max().item()))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_small_local_memory_gives_the_same_results(monkeypatch, dtype):
    """With 8 KiB of local memory the GPU kernels stage fewer entries per batch (forward: 101
    in float64, 203 in float32; backward: 1 and 2 entries, most row work-items idle)."""
    monkeypatch.setenv("CLFLOW_KERNELS", "gpu")
    tensors, tiles, _, width, height = splats(SCENES["deep"], dtype)
    full = run_composite(tensors, tiles, width, height)
    monkeypatch.setattr(compositing, "MAX_RASTER_LOCAL_BYTES", 8 * 1024)
    small = run_composite(tensors, tiles, width, height)
    assert torch.equal(full[2], small[2])
    for a, b in zip((full[0], full[1], *full[3]), (small[0], small[1], *small[3])):
        # the forward sums in the same order; the backward's row and tile sums too
        assert torch.equal(a, b)


def test_gpu_backward_gives_the_same_bits_twice(monkeypatch):
    monkeypatch.setenv("CLFLOW_KERNELS", "gpu")
    tensors, tiles, _, width, height = splats(SCENES["deep"], torch.float32)
    first, second = (run_composite(tensors, tiles, width, height)[3] for _ in range(2))
    for a, b in zip(first, second):
        assert torch.equal(a, b)


def test_each_plan_launches_the_compositing_kernels_it_registers(plan, device, monkeypatch):
    """The compositing kernels a call launches are those of its plan's raster shape in
    clflow.runtime.plan.STAGE_KERNELS (the registry docs/gpu.md lists)."""
    from clflow.runtime.plan import kernel_plan

    launched, launch = [], device.launch
    monkeypatch.setattr(
        device, "launch", lambda kernel, *args, **kw: launched.append(kernel) or launch(kernel, *args, **kw)
    )
    tensors, tiles, _, width, height = splats(SCENES["partial_tiles"])
    run_composite(tensors, tiles, width, height)
    names = {kernel.function_name for kernel in launched}
    for role in ("forward", "backward"):
        assert kernel_plan(device).kernel("raster", role).entry in names, (plan, role, names)
