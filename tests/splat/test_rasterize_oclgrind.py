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


SCENE_SCRIPT = textwrap.dedent(
    """
    import sys
    import torch
    sys.path.insert(0, "tests/pipeline")
    sys.path.insert(0, "tests/flow")
    from test_render_frames import camera, run, sh_gaussians
    from clflow.flow.scene_flow import render_scene_flows
    from clflow.pipeline.render import render_rgb_frames
    from clflow.splat.device_scene import DeviceScene
    f32 = torch.float32
    scene = DeviceScene(sh_gaussians(5, 2, [0.0, 0.0, 0.5], 1.2, 2, f32), sh_gaussians(4, 1, [0.0, 0.0, 0.0], 0.4, 2, f32))
    cam = camera(20, 18)
    x, F = run(1, 4, seed=3)
    frames = render_rgb_frames(scene, x, F, cam, supersample=2)
    xs = x.clone().requires_grad_()
    flows = render_scene_flows(scene, xs, F.clone().requires_grad_(), cam)
    sum(f.sum() for f in flows).backward()
    assert frames.max() > 0 and xs.grad is not None
    print("done")
    """
)


def test_the_scene_kernels_are_clean_under_oclgrind(oclgrind):
    """A run's frames (supersampled, averaged on the device) and flows with the scene on the
    device (scene_frame.cl, scene_flow.cl, the polar rotations, the SH colours), forward and
    backward."""
    out, report = oclgrind(SCENE_SCRIPT, timeout=600, uninitialized=False)
    assert "done" in out
    assert report.strip() == "", report[:2000]
