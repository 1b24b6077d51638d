"""Adaptive density control on a hand-made table of Gaussians: who is cloned, split, pruned,
and what happens to their Adam moments."""

import math

import torch

from clflow.recon.densify import (
    SPLIT_SHRINK,
    DensifySettings,
    ViewSpaceStats,
    densify_and_prune,
    rebuild,
    reset_opacities,
)

EXTENT = 10.0  # m; percent_dense 0.01 -> 0.1 m separates "small" from "large"
SETTINGS = DensifySettings(
    grad_threshold=1e-3, percent_dense=0.01, min_opacity=0.01, max_screen_radius=20, max_world_scale=0.1
)


def table():
    """Five Gaussians: 0 hot and small (clone), 1 hot and large (split), 2 cold and nearly
    transparent (prune), 3 cold and kept, 4 cold, kept unless large ones are pruned (wide on screen)."""
    log_scale = [math.log(s) for s in (0.05, 0.5, 0.05, 0.05, 0.05)]
    opacity = [0.5, 0.5, 0.005, 0.5, 0.5]
    params = {
        "means": torch.arange(15.0).reshape(5, 3),
        "quats": torch.tensor([[1.0, 0, 0, 0]] * 5),
        "log_scales": torch.tensor(log_scale)[:, None].repeat(1, 3),
        "opacity_logits": torch.logit(torch.tensor(opacity)),
        "sh0": torch.arange(5.0)[:, None, None].repeat(1, 1, 3),
        "shN": torch.zeros(5, 3, 3),
    }
    groups = [{"params": [torch.nn.Parameter(v.clone())], "lr": 0.0, "name": k} for k, v in params.items()]
    optimizer = torch.optim.Adam(groups)
    for g in optimizer.param_groups:  # one step (of rate 0) so every parameter has moments
        g["params"][0].grad = torch.ones_like(g["params"][0])
    optimizer.step()
    stats = ViewSpaceStats.zeros(5)
    # two views; Gaussian 0 and 1 move 2e-3 (NDC) per view, the others 1e-4; 4 is 30 px wide in view 2
    for radius_4 in (5, 30):
        grad = torch.tensor([[2e-3, 0.0], [0.0, 2e-3], [1e-4, 0], [1e-4, 0], [1e-4, 0]]) / torch.tensor([32.0, 24.0])
        stats.add(grad, torch.tensor([3, 3, 3, 3, radius_4], dtype=torch.int32), width=64, height=48)
    return optimizer, stats


def test_view_space_gradient_is_the_mean_ndc_norm_over_the_views_that_saw_it():
    stats = ViewSpaceStats.zeros(3)
    stats.add(torch.tensor([[3.0, 4.0], [1.0, 0.0], [9.0, 9.0]]), torch.tensor([1, 1, 0], dtype=torch.int32), 2, 2)
    stats.add(torch.tensor([[0.0, 1.0], [1.0, 0.0], [9.0, 9.0]]), torch.tensor([1, 0, 0], dtype=torch.int32), 2, 2)
    assert stats.mean_grad().tolist() == [3.0, 1.0, 0.0] and stats.count.tolist() == [2, 1, 0]


def test_clone_split_and_prune_counts_and_rows():
    optimizer, stats = table()
    params, counts = densify_and_prune(
        optimizer, stats, EXTENT, SETTINGS, prune_large=False, generator=torch.Generator().manual_seed(0)
    )
    assert counts == {"cloned": 1, "split": 1, "pruned": 1, "gaussians": 6}
    # kept originals 0, 3, 4 (2 pruned, 1 replaced), then the clone of 0, then 1's two children
    assert params["sh0"][:, 0, 0].tolist() == [0, 3, 4, 0, 1, 1]
    assert torch.equal(params["means"][3], params["means"][0])
    children = params["log_scales"][4:].exp()
    assert torch.allclose(children, torch.full((2, 3), 0.5 / SPLIT_SHRINK))
    assert not torch.equal(params["means"][4], params["means"][5])
    assert ((params["means"][4:] - torch.tensor([3.0, 4.0, 5.0])).norm(dim=-1) < 4 * 0.5 * math.sqrt(3)).all()
    for group in optimizer.param_groups:  # moments kept for old rows, zero for new ones
        state = optimizer.state[group["params"][0]]
        assert group["params"][0] is params[group["name"]]
        assert bool((state["exp_avg"][:3] != 0).all()) and bool((state["exp_avg"][3:] == 0).all())


def test_large_gaussians_are_pruned_only_when_asked():
    optimizer, stats = table()
    _, counts = densify_and_prune(
        optimizer, stats, EXTENT, SETTINGS, prune_large=True, generator=torch.Generator().manual_seed(0)
    )
    # also pruned: Gaussian 4 (30 px > 20 px on screen) and 1's children (0.31 m < 1 m: kept)
    assert counts == {"cloned": 1, "split": 1, "pruned": 2, "gaussians": 5}
    optimizer, stats = table()
    _, counts = densify_and_prune(
        optimizer, stats, 2.0, SETTINGS, prune_large=True, generator=torch.Generator().manual_seed(0)
    )
    # extent 2 m: 0.05 m > 0.02 m, all hot ones split; children 0.03 and 0.31 m vs 0.2 m world limit
    assert counts["split"] == 2 and counts["cloned"] == 0
    assert counts["pruned"] == 1 + 1 + 2  # transparent 2, wide 4, the two large children of 1


def test_rebuild_keeps_rows_and_reset_caps_opacity():
    optimizer, _ = table()
    params = rebuild(optimizer, torch.tensor([True, False, True, False, False]))
    assert params["sh0"][:, 0, 0].tolist() == [0, 2]
    reset_opacities(optimizer, ceiling=0.01)
    assert torch.sigmoid(params["opacity_logits"]).tolist()[0] == torch.sigmoid(torch.logit(torch.tensor(0.01))).item()
    state = optimizer.state[params["opacity_logits"]]
    assert bool((state["exp_avg"] == 0).all()) and bool((state["exp_avg_sq"] == 0).all())


def test_retained_means2d_gradient_matches_the_torch_reference():
    """The densification statistic reads dL/d mean2d from project's means2d output
    (retain_grad); in float64 it equals autograd through clflow.splat.reference."""
    from clflow.splat.cameras import look_at
    from clflow.splat.ops import rasterize_gaussians
    from clflow.splat.reference import rasterize_reference

    g = torch.Generator().manual_seed(3)
    n = 25
    scene = (
        torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5,
        torch.randn(n, 4, generator=g, dtype=torch.float64),
        0.05 + 0.1 * torch.rand(n, 3, generator=g, dtype=torch.float64),
        0.2 + 0.7 * torch.rand(n, generator=g, dtype=torch.float64),
        torch.rand(n, 3, generator=g, dtype=torch.float64),
    )
    cam = look_at((0.3, -2.5, 0.4), (0, 0, 0), fov_x=0.9, width=40, height=36)
    weights = torch.randn(36, 40, 3, generator=g, dtype=torch.float64)
    grads = []
    for fn in (rasterize_gaussians, rasterize_reference):
        image, _, _, meta = fn(*[t.clone().requires_grad_() for t in scene], cam.viewmat, cam.K, 40, 36)
        meta["means2d"].retain_grad()
        (image * weights).sum().backward()
        grads.append(meta["means2d"].grad)
    assert grads[1].abs().max() > 0
    assert torch.allclose(grads[0], grads[1], rtol=0, atol=1e-9 * grads[1].abs().max().item())
