"""Gradients of the OpenCL splat rasteriser: gradcheck in float64, the torch reference's
autograd, float32 against float64, determinism, and opcheck of the custom ops."""

import pytest
import torch

from clflow.splat.binning import build_tile_lists
from clflow.splat.ops import composite, covariances, project, rasterize_gaussians
from clflow.splat.reference import rasterize_reference
from tests.splat._helpers import camera, random_scene, rotations

W, H = 24, 20  # 2 x 2 tiles, partial
GRADCHECK = dict(eps=1e-6, atol=1e-6, rtol=1e-5)


def weighted_sums(outputs, seed=0):
    """Fixed random projections of image, alpha and depth: a few scalars to gradcheck
    (one backward per scalar instead of one per pixel)."""
    g = torch.Generator().manual_seed(seed)
    return tuple(
        (o * torch.randn(o.shape, generator=g, dtype=torch.float64).to(o.dtype)).sum() for o in outputs if o is not None
    )


def small_scene(seed, n=6):
    means, quats, scales, opacities, colors = random_scene(n, seed, spread=0.4, scale=(0.1, 0.25))
    viewmat, K = camera(W, H, 25.0)
    # a rotated, translated camera looking back at the scene from the side
    angle = torch.tensor(0.3, dtype=torch.float64)
    c, s = torch.cos(angle), torch.sin(angle)
    viewmat[:3, :3] = torch.stack(
        [torch.stack([c, 0 * c, -s]), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), torch.stack([s, 0 * c, c])]
    )
    viewmat[:3, 3] = torch.tensor([0.9, 0.05, -0.1], dtype=torch.float64)
    return means, quats, scales, opacities, colors, viewmat, K


def test_gradcheck_means_quats_scales_opacities_colours_and_flow_feature():
    means, quats, scales, opacities, colors, viewmat, K = small_scene(0)
    flow = torch.randn(means.shape[0], 2, dtype=torch.float64)
    background = torch.tensor([0.1, 0.2, 0.3, 0.0, 0.0], dtype=torch.float64)

    def f(means, quats, scales, opacities, colors, flow, background):
        out = rasterize_gaussians(
            means, quats, scales, opacities, colors, viewmat, K, W, H, features=flow, background=background
        )
        return weighted_sums(out[:3])

    inputs = [t.clone().requires_grad_() for t in (means, quats, scales, opacities, colors, flow, background)]
    assert torch.autograd.gradcheck(f, inputs, **GRADCHECK)


def test_gradcheck_covariances():
    means, quats, scales, opacities, colors, viewmat, K = small_scene(1)
    covars = covariances(quats, scales)

    def f(means, covars, opacities):
        out = rasterize_gaussians(means, None, None, opacities, colors, viewmat, K, W, H, covars=covars)
        return weighted_sums(out[:3])

    inputs = [t.clone().requires_grad_() for t in (means, covars, opacities)]
    assert torch.autograd.gradcheck(f, inputs, **GRADCHECK)


def test_gradcheck_and_opcheck_covariances_from_quats_and_scales():
    _, quats, scales, *_ = small_scene(10)
    quats, scales = quats.requires_grad_(), scales.requires_grad_()
    assert torch.autograd.gradcheck(covariances, (quats, scales), **GRADCHECK)
    torch.library.opcheck(
        covariances, (quats, scales), test_utils=("test_schema", "test_autograd_registration", "test_faketensor")
    )


def test_gradcheck_sh_coefficients_and_rotations():
    means, quats, scales, opacities, _, viewmat, K = small_scene(2)
    n = means.shape[0]
    sh = torch.randn(n, 16, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3)) * 0.3
    R = rotations(n, seed=4)
    viewmat[:3, 3] = torch.tensor([0.05, 0.1, -0.2], dtype=torch.float64)

    def f(means, sh, R):
        out = rasterize_gaussians(means, quats, scales, opacities, sh, viewmat, K, W, H, sh_degree=3, sh_rotations=R)
        return weighted_sums(out[:3])

    inputs = [t.clone().requires_grad_() for t in (means, sh, R)]
    assert torch.autograd.gradcheck(f, inputs, **GRADCHECK)


@pytest.mark.parametrize("seed,opacity,spread", [(5, (0.2, 0.9), 0.3), (6, (0.9, 1.0), 0.3), (11, (0.2, 0.9), 2.6)])
def test_gradients_match_reference_autograd(seed, opacity, spread):
    """Kernel adjoint vs torch autograd through the dense reference, including opaque,
    overlapping scenes where alpha clamps and compositing stops early, and a wide one whose
    Gaussians past 1.3 x the field of view have J evaluated at the clamped x/z, y/z."""
    means, quats, scales, opacities, colors = random_scene(30, seed, opacity=opacity, spread=spread)
    viewmat, K = camera(40, 36, 30.0)
    inputs = [t.clone().requires_grad_() for t in (means, quats, scales, opacities, colors)]
    grads = []
    for fn in (rasterize_gaussians, rasterize_reference):
        loss = sum(weighted_sums(fn(*inputs, viewmat, K, 40, 36)[:3], seed=seed))
        grads.append(torch.autograd.grad(loss, inputs))
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors"), *grads):
        scale = b.abs().max().item()
        assert scale > 0, name
        assert (a - b).abs().max().item() <= 1e-9 * max(1.0, scale), name


def test_float32_gradients_match_float64():
    """gsplat's float32 tolerances (d means 1e-2/6e-2, d quats 0.2/1e-2, d scales 0.1/0.2,
    d opacities and colours 2e-3 / 1e-3)."""
    scene = random_scene(30, seed=7)
    viewmat, K = camera(40, 36, 30.0)
    grads = {}
    for dtype in (torch.float64, torch.float32):
        inputs = [t.to(dtype).requires_grad_() for t in scene]
        out = rasterize_gaussians(*inputs, viewmat.to(dtype), K.to(dtype), 40, 36)
        loss = sum(weighted_sums(out[:3]))
        grads[dtype] = torch.autograd.grad(loss, inputs)
    tolerances = [(1e-2, 6e-2), (0.2, 1e-2), (0.1, 0.2), (2e-3, 2e-3), (1e-3, 1e-3)]
    for g32, g64, (rtol, atol) in zip(grads[torch.float32], grads[torch.float64], tolerances):
        torch.testing.assert_close(g32.double(), g64, rtol=rtol, atol=atol)


def test_gradients_are_deterministic():
    scene = random_scene(300, seed=8, dtype=torch.float32, scale=(0.02, 0.1), spread=0.6)
    viewmat, K = camera(64, 48, 40.0, dtype=torch.float32)
    runs = []
    for _ in range(3):
        inputs = [t.clone().requires_grad_() for t in scene]
        out = rasterize_gaussians(*inputs, viewmat, K, 64, 48)
        runs.append(torch.autograd.grad(sum(weighted_sums(out[:3])), inputs))
    for run in runs[1:]:
        for a, b in zip(runs[0], run):
            assert torch.equal(a, b)


def test_opcheck_project_and_composite():
    means, quats, scales, opacities, colors, viewmat, K = small_scene(9)
    covars = covariances(quats, scales).contiguous()
    args = (means.requires_grad_(), covars.requires_grad_(), viewmat, K, W, H, 0.01)
    torch.library.opcheck(project, args, test_utils=("test_schema", "test_autograd_registration", "test_faketensor"))
    means2d, conics, depths, radii, touched = project(*args)
    lists = build_tile_lists(means2d.detach(), depths.detach(), radii, touched, W, H)
    comp_args = (
        means2d.detach().requires_grad_(),
        conics.detach().requires_grad_(),
        opacities.requires_grad_(),
        colors.requires_grad_(),
        torch.zeros(3, dtype=torch.float64),
        lists.ranges,
        lists.sorted_slots,
        lists.slot_gaussian,
        lists.first_slot,
        lists.tiles_touched,
        W,
        H,
    )
    torch.library.opcheck(
        composite, comp_args, test_utils=("test_schema", "test_autograd_registration", "test_faketensor")
    )
