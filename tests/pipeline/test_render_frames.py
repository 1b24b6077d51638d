"""A run's colour frames rendered with the scene on the device (render_rgb_frames) against
the per-op path: render_rgb of frame_gaussians, frame by frame."""

import numpy as np
import pytest
import torch

from clflow.media import to_uint8
from clflow.pipeline.render import frame_gaussians, render_rgb, render_rgb_frames
from clflow.runtime import get_device
from clflow.splat.cameras import Camera
from clflow.splat.device_scene import DeviceScene
from clflow.splat.gaussians import Gaussians

D = torch.float64


def sh_gaussians(n: int, seed: int, centre, spread: float, degree: int | None, dtype) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    means = torch.tensor(centre, dtype=D) + (torch.rand(n, 3, generator=g, dtype=D) - 0.5) * spread
    quats = torch.randn(n, 4, generator=g, dtype=D)
    scales = 0.02 + 0.05 * torch.rand(n, 3, generator=g, dtype=D)
    opacities = 0.3 + 0.6 * torch.rand(n, generator=g, dtype=D)
    if degree is None:
        made = Gaussians.from_activated(means, quats, scales, opacities, colors=torch.rand(n, 3, generator=g, dtype=D))
    else:
        sh = 0.4 * torch.randn(n, (degree + 1) ** 2, 3, generator=g, dtype=D)
        made = Gaussians.from_activated(means, quats, scales, opacities, sh=sh)
    turn = torch.linalg.matrix_exp(torch.tensor([[0, -0.3, 0.2], [0.3, 0, -0.1], [-0.2, 0.1, 0]], dtype=D))
    return made.transformed(turn).to(dtype)  # with sh_rotations, as a loaded scene has


def camera(width=64, height=48) -> Camera:
    viewmat = torch.eye(4, dtype=D)
    viewmat[:3, 3] = torch.tensor([0.02, -0.03, 2.5], dtype=D)
    K = torch.tensor([[70.0, 0.0, width / 2], [0.0, 72.0, height / 2], [0.0, 0.0, 1.0]], dtype=D)
    return Camera(viewmat, K, width, height)


def run(steps: int, n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    x0 = torch.zeros(n, 3, dtype=D)
    x = torch.stack([x0 + (torch.rand(n, 3, generator=g, dtype=D) - 0.5) * 0.5 + 0.03 * t for t in range(steps + 1)])
    angle = torch.linspace(0, 0.6, steps + 1, dtype=D)
    turns = [torch.linalg.matrix_exp(torch.tensor([[0, -a, 0], [a, 0, 0], [0, 0, 0]], dtype=D)) for a in angle]
    stretch = torch.diag(torch.tensor([1.2, 0.9, 1.0], dtype=D))
    F = torch.stack([(R @ stretch).expand(n, 3, 3) for R in turns]).contiguous()
    return x, F


@pytest.mark.parametrize(("degree", "dtype"), [(3, torch.float32), (1, torch.float64), (None, torch.float32)])
def test_frames_match_the_per_op_path(degree, dtype):
    """Three frames of 30 object Gaussians (turned and stretched, so their SH colours turn with
    them) in front of 40 static ones: every byte within 1 of the per-op path's, and at most
    0.5 % of them off by 1 (float32 round-off at a rounding boundary)."""
    obj = sh_gaussians(30, 1, [0.0, 0.0, 0.0], 0.4, degree, dtype)
    static = sh_gaussians(40, 2, [0.0, 0.0, 0.5], 1.2, degree, dtype)
    cam = camera()
    x, F = run(2, 30, seed=3)
    got = render_rgb_frames(DeviceScene(static, obj), x, F, cam)
    want = np.stack([to_uint8(render_rgb(frame_gaussians(static, obj, x[t], F[t]), cam)) for t in range(3)])
    assert got.shape == want.shape == (3, cam.height, cam.width, 3) and got.dtype == np.uint8
    assert np.ptp(want) > 100  # colours, not a blank frame
    diff = np.abs(got.astype(int) - want.astype(int))
    assert diff.max() <= 1 and (diff > 0).mean() <= 0.005


def test_only_the_object_and_the_bytes_cross_in_copy_mode():
    """In copy mode a frame costs the object's x and F (its colours are made on the device)
    and the frame's bytes; the static Gaussians' colours cross once a call."""
    from clflow.runtime.devices import set_bridge_mode

    set_bridge_mode("copy")
    try:
        n, static_n, steps = 20, 4000, 2
        obj = sh_gaussians(n, 1, [0.0, 0.0, 0.0], 0.4, 3, torch.float32)
        static = sh_gaussians(static_n, 2, [0.0, 0.0, 0.5], 1.2, 3, torch.float32)
        cam = camera()
        scene = DeviceScene(static, obj)
        x, F = run(steps, n, seed=3)
        device = get_device()
        mark = device.transfers.mark()
        render_rgb_frames(scene, x, F, cam)
        moved = device.transfers.since(mark)
        frames, real, small = steps + 1, 4, 4096
        colours_once = (n + static_n) * 3 * real
        assert moved.to_device <= colours_once + frames * (n * (3 + 9) * real + small)
        assert moved.to_host <= frames * (cam.width * cam.height * 3 + small)
    finally:
        set_bridge_mode(None)


@pytest.mark.parametrize("factor", [2, 3])
def test_a_supersampled_frame_is_averaged_as_opencv_does(factor):
    """render_rgb_frames(..., supersample=s): the fine frame averaged on the device, block by
    block, rounded half up, equals OpenCV's INTER_AREA of the fine frame for s = 2 (the
    estimator's calibration) and is within one grey level of it for 3 (OpenCV rounds half to
    even there)."""
    import cv2

    obj = sh_gaussians(30, 1, [0.0, 0.0, 0.0], 0.4, 3, torch.float32)
    static = sh_gaussians(40, 2, [0.0, 0.0, 0.5], 1.2, 3, torch.float32)
    cam = camera(36, 28)
    x, F = run(1, 30, seed=3)
    scene = DeviceScene(static, obj)
    fine = render_rgb_frames(scene, x, F, cam.scaled(factor))
    got = render_rgb_frames(scene, x, F, cam, supersample=factor)
    want = np.stack([cv2.resize(f, (cam.width, cam.height), interpolation=cv2.INTER_AREA) for f in fine])
    assert got.shape == want.shape == (2, cam.height, cam.width, 3)
    diff = np.abs(got.astype(int) - want.astype(int))
    assert diff.max() == 0 if factor == 2 else diff.max() <= 1
