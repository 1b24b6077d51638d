"""Every splat kernel under oclgrind: no out-of-bounds access, no access against a
buffer's read/write flags, no data race (a tiny forward and backward, float32)."""

import textwrap

import pytest

pytestmark = pytest.mark.oclgrind

SCRIPT = textwrap.dedent(
    """
    import torch
    from tests.splat._helpers import camera, random_scene
    from clflow.splat.ops import rasterize_gaussians
    scene = [t.requires_grad_() for t in random_scene(6, seed=0, dtype=torch.float32)]
    flow = torch.ones(6, 2, requires_grad=True)
    viewmat, K = camera(20, 18, 20.0, dtype=torch.float32)
    img, alpha, depth, meta = rasterize_gaussians(*scene, viewmat, K, 20, 18, features=flow)
    (img.sum() + alpha.sum() + depth.sum()).backward()
    assert meta["num_tile_entries"] > 0 and scene[0].grad.abs().sum() > 0
    print("done")
    """
)


@pytest.mark.parametrize("plan", ["cpu", "gpu"])  # both shapes of the compositing kernels
def test_kernels_are_clean_under_oclgrind(oclgrind, monkeypatch, plan):
    monkeypatch.setenv("CLFLOW_KERNELS", plan)
    out, report = oclgrind(
        SCRIPT, timeout=600, uninitialized=False
    )  # --uninitialized: Oclgrind 21.10 zeroes the gradient
    assert "done" in out
    assert report.strip() == "", report[:2000]
