"""The simulated flow of a run rendered with the scene on the device (clflow.flow.scene_flow)
against its reference, render_flow of frame_gaussians (torch and the rasteriser's ops)."""

import math

import pytest
import torch

from clflow.errors import InputError
from clflow.flow.scene_flow import render_scene_flows
from clflow.pipeline.render import frame_gaussians, render_flow
from clflow.runtime import get_device
from clflow.splat.cameras import Camera
from clflow.splat.device_scene import DeviceScene
from clflow.splat.gaussians import Gaussians

D = torch.float64


def gaussians(n: int, seed: int, centre, spread: float, dtype) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    means = torch.tensor(centre, dtype=D) + (torch.rand(n, 3, generator=g, dtype=D) - 0.5) * spread
    quats = torch.randn(n, 4, generator=g, dtype=D)
    scales = 0.02 + 0.04 * torch.rand(n, 3, generator=g, dtype=D)
    opacities = 0.3 + 0.6 * torch.rand(n, generator=g, dtype=D)
    colors = torch.rand(n, 3, generator=g, dtype=D)
    return Gaussians.from_activated(means, quats, scales, opacities, colors=colors).to(dtype)


def camera(width=72, height=56) -> Camera:
    """A camera 3 m from the origin, turned a little about every axis (with skew-free K)."""
    a = torch.tensor([0.2, -0.15, 0.1], dtype=D)
    R = torch.linalg.matrix_exp(torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=D))
    viewmat = torch.eye(4, dtype=D)
    viewmat[:3, :3], viewmat[:3, 3] = R, torch.tensor([0.05, -0.02, 3.0], dtype=D)
    K = torch.tensor([[90.0, 0.0, width / 2], [0.0, 95.0, height / 2], [0.0, 0.0, 1.0]], dtype=D)
    return Camera(viewmat, K, width, height)


def run(steps: int, n: int, fill: int, seed: int):
    """A made-up run: x [T + 1, n + fill, 3] drifting and F [T + 1, n + fill, 3, 3] shearing."""
    g = torch.Generator().manual_seed(seed)
    x0 = (torch.rand(n + fill, 3, generator=g, dtype=D) - 0.5) * 0.6
    drift = torch.tensor([0.04, -0.03, 0.05], dtype=D)
    x = torch.stack(
        [x0 + t * drift + 0.01 * t * torch.randn(n + fill, 3, generator=g, dtype=D) for t in range(steps + 1)]
    )
    F = torch.eye(3, dtype=D) + 0.05 * torch.randn(steps + 1, n + fill, 3, 3, generator=g, dtype=D)
    return x, F


def reference_flows(static, obj, x, F, cam):
    scenes = [frame_gaussians(static, obj, x[t], F[t]) for t in range(x.shape[0])]
    return [render_flow(scenes[t], scenes[t + 1], cam)[0] for t in range(x.shape[0] - 1)]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_flows_and_gradients_match_the_per_op_path(dtype):
    """Three frame steps of 40 object Gaussians (fill particles after them) in front of 60
    static ones: the flows, and the gradients of a loss of them with respect to every frame's
    x and F, equal the reference's to round-off."""
    n, steps = 40, 3
    obj = gaussians(n, 1, [0.0, 0.0, 0.0], 0.5, dtype)
    static = gaussians(60, 2, [0.0, 0.0, 0.6], 1.4, dtype)
    cam = camera()
    x, F = run(steps, n, 7, seed=3)
    weights = torch.rand(steps, cam.height, cam.width, 2, generator=torch.Generator().manual_seed(4), dtype=D)

    def loss_and_grads(render):
        xs, Fs = x.clone().requires_grad_(), F.clone().requires_grad_()
        flows = render(xs, Fs)
        loss = sum(((f.double() * w) ** 2).sum() for f, w in zip(flows, weights))
        loss.backward()
        return torch.stack(flows).double(), xs.grad, Fs.grad

    scene = DeviceScene(static, obj)
    got = loss_and_grads(lambda xs, Fs: render_scene_flows(scene, xs, Fs, cam))
    want = loss_and_grads(lambda xs, Fs: reference_flows(static, obj, xs, Fs, cam))
    assert float(want[0].detach().abs().max()) > 0.5  # the object moves by pixels
    assert float(want[1][:, :n].abs().max()) > 0 and float(want[2][:, :n].abs().max()) > 0
    tol = dict(rtol=1e-4, atol=1e-4) if dtype == torch.float32 else dict(rtol=1e-10, atol=1e-10)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, **tol)
    assert float(got[1][:, n:].abs().max()) == 0 and float(got[2][:, n:].abs().max()) == 0  # fill particles


def test_gradient_matches_difference_quotients():
    """float64: dL/dx and dL/dF of one object particle in the middle frame against central
    difference quotients of the loss."""
    n = 12
    obj = gaussians(n, 5, [0.0, 0.0, 0.0], 0.3, D)
    static = gaussians(20, 6, [0.0, 0.0, 0.5], 1.2, D)
    cam = camera(48, 40)
    x, F = run(2, n, 0, seed=7)
    weights = torch.rand(2, cam.height, cam.width, 2, generator=torch.Generator().manual_seed(8), dtype=D)
    scene = DeviceScene(static, obj)

    def loss(xs, Fs):
        return sum((f * w).sum() for f, w in zip(render_scene_flows(scene, xs, Fs, cam), weights))

    xs, Fs = x.clone().requires_grad_(), F.clone().requires_grad_()
    loss(xs, Fs).backward()
    h = 1e-6
    for tensor, grad, index in ((x, xs.grad, (1, 3, 0)), (x, xs.grad, (1, 5, 2)), (F, Fs.grad, (1, 3, 0, 1))):
        up, down = tensor.clone(), tensor.clone()
        up[index] += h
        down[index] -= h
        args_up = (up, F) if tensor is x else (x, up)
        args_down = (down, F) if tensor is x else (x, down)
        quotient = (float(loss(*args_up)) - float(loss(*args_down))) / (2 * h)
        assert abs(float(grad[index])) > 1e-3
        assert math.isclose(float(grad[index]), quotient, rel_tol=1e-5, abs_tol=1e-8)


def test_a_gaussian_crossing_the_near_plane_has_no_flow_and_no_gradient():
    """One object Gaussian in front of the camera at t and behind it at t+1: no flow and no
    gradient at t+1, as in the reference, which draws it at frame t too."""
    cam = camera(64, 48)
    obj = gaussians(3, 9, [0.0, 0.0, 0.0], 0.3, D)
    static = gaussians(4, 10, [0.0, 0.0, 0.5], 1.0, D)
    x, F = run(1, 3, 0, seed=11)
    W, t = cam.viewmat[:3, :3], cam.viewmat[:3, 3]
    x[1, 0] = (torch.tensor([0.1, 0.0, -0.2], dtype=D) - t) @ W  # behind the camera at t+1
    xs, xr = x.clone().requires_grad_(), x.clone().requires_grad_()
    got = render_scene_flows(DeviceScene(static, obj), xs, F, cam)[0]
    want = reference_flows(static, obj, xr, F, cam)[0]
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)
    got.sum().backward()
    want.sum().backward()
    assert float(xs.grad[1, 0].abs().max()) == 0
    torch.testing.assert_close(xs.grad, xr.grad, rtol=1e-10, atol=1e-10)


def test_bad_shapes_are_refused():
    obj = gaussians(5, 1, [0.0, 0.0, 0.0], 0.3, D)
    scene = DeviceScene(gaussians(5, 2, [0.0, 0.0, 0.5], 1.0, D), obj)
    x, F = run(2, 5, 0, seed=1)
    with pytest.raises(InputError, match="render_scene_flows"):
        render_scene_flows(scene, x[:1], F[:1], camera())
    with pytest.raises(InputError, match="render_scene_flows"):
        render_scene_flows(scene, x[:, :4], F[:, :4], camera())
    with pytest.raises(InputError, match="DeviceScene"):
        DeviceScene(gaussians(5, 2, [0.0, 0.0, 0.5], 1.0, torch.float32), obj)


def test_only_the_object_and_the_images_cross_in_copy_mode():
    """In the bridge's copy mode a run's flows and their backward copy the object's x and F
    in, each frame step's image and transmittance out, their gradients in and the object's
    gradients out: nothing of the static Gaussians after the scene is made."""
    from clflow.runtime.devices import set_bridge_mode

    set_bridge_mode("copy")
    try:
        n, static_n, steps = 30, 3000, 3
        obj = gaussians(n, 1, [0.0, 0.0, 0.0], 0.5, torch.float32)
        static = gaussians(static_n, 2, [0.0, 0.0, 0.6], 1.4, torch.float32)
        cam = camera()
        device = get_device()
        assert not device.zero_copy
        scene = DeviceScene(static, obj)
        x, F = run(steps, n, 0, seed=3)
        xs = x.clone().requires_grad_()
        mark = device.transfers.mark()
        flows = render_scene_flows(scene, xs, F, cam)
        forward = device.transfers.since(mark)
        mark = device.transfers.mark()
        sum(f.sum() for f in flows).backward()
        backward = device.transfers.since(mark)
        pixels, real = cam.width * cam.height, 4
        frames, small = steps + 1, 4096  # the camera, entry counts, zero-fills' patterns
        assert forward.to_device <= frames * n * 12 * real + small
        assert forward.to_host <= steps * pixels * 3 * real + small
        assert backward.to_device <= steps * pixels * 3 * real + small
        assert backward.to_host <= steps * n * 15 * real + small
        assert forward.to_device + backward.to_host < static_n * 12 * real  # less than the static scene once
    finally:
        set_bridge_mode(None)


def test_a_runs_states_on_the_device_stand_for_its_x_and_F():
    """Given the run's states on the device (float64, as a simulation's), the flows and their
    gradients equal those made from the host x and F, and in copy mode the forward copies
    neither to the device."""
    from types import SimpleNamespace

    from clflow.runtime.arrays import DeviceArray
    from clflow.runtime.devices import set_bridge_mode

    set_bridge_mode("copy")
    try:
        n, steps = 30, 2
        obj = gaussians(n, 1, [0.0, 0.0, 0.0], 0.5, torch.float32)
        static = gaussians(2000, 2, [0.0, 0.0, 0.6], 1.4, torch.float32)
        cam, device = camera(), get_device()
        scene = DeviceScene(static, obj)
        x, F = run(steps, n, 5, seed=3)  # float64, fill particles after the object's
        states = [
            SimpleNamespace(x=DeviceArray.of(device, x[t]), F=DeviceArray.of(device, F[t])) for t in range(steps + 1)
        ]

        def flows_and_grad(**kw):
            xs, Fs = x.clone().requires_grad_(), F.clone().requires_grad_()
            mark = device.transfers.mark()
            flows = render_scene_flows(scene, xs, Fs, cam, **kw)
            copied = device.transfers.since(mark)
            sum((f * f).sum() for f in flows).backward()
            return torch.stack(flows), xs.grad, Fs.grad, copied

        *got, on_device = flows_and_grad(states=states)
        *want, _ = flows_and_grad()
        for a, b in zip(got, want):
            assert torch.equal(a, b)
        assert on_device.to_device <= (steps + 1) * 4096  # the camera's matrices and zero fills
    finally:
        set_bridge_mode(None)
    with pytest.raises(InputError, match="device states"):
        render_scene_flows(scene, x, F, cam, states=states[:2])


def test_a_flow_read_in_the_runs_op_gives_the_per_op_gradient():
    """simulate(..., reader=FlowReader(...)): the flows of a swirling block's run and the
    gradient of a loss of them with respect to E, rho and the initial velocity equal those of
    the run's host frames rendered after it (render_scene_flows), to round-off; the first
    particles are the object's Gaussians, the rest fill."""
    from clflow.flow.scene_flow import FlowReader, flows_of
    from clflow.mpm.autograd import simulate
    from tests.mpm.test_adjoint_trajectory import scene as swirling_scene

    sim = swirling_scene(substeps=4)
    n = 60
    g = torch.Generator().manual_seed(2)
    x0 = sim.state.x[:n].float()
    obj = Gaussians.from_activated(
        x0.double(),
        torch.randn(n, 4, generator=g, dtype=D),
        0.01 + 0.02 * torch.rand(n, 3, generator=g, dtype=D),
        0.3 + 0.6 * torch.rand(n, generator=g, dtype=D),
        colors=torch.rand(n, 3, generator=g, dtype=D),
    ).to(torch.float32)
    static = gaussians(50, 3, [0.5, 0.5, 1.0], 1.0, torch.float32)
    viewmat = torch.eye(4, dtype=D)
    viewmat[:3, 3] = torch.tensor([-0.5, -0.5, 1.2], dtype=D)
    cam = Camera(viewmat, torch.tensor([[60.0, 0, 24], [0, 60.0, 20], [0, 0, 1]], dtype=D), 48, 40)
    scene = DeviceScene(static, obj)
    weights = torch.rand(3, cam.height, cam.width, 2, generator=torch.Generator().manual_seed(4), dtype=D)

    def loss_and_grads(fused: bool):
        E = torch.tensor(2e4, dtype=D, requires_grad=True)
        rho = torch.tensor(800.0, dtype=D, requires_grad=True)
        v0 = sim.state.v.clone().requires_grad_()
        inputs = dict(params={"youngs_modulus": E}, density=rho, velocities=v0)
        if fused:
            frames, read = simulate(sim, 3, **inputs, reader=FlowReader(scene, [cam]))
            flows = flows_of(*read)
        else:
            frames = simulate(sim, 3, **inputs)
            flows = render_scene_flows(scene, frames.x, frames.F, cam)
        loss = sum((f.double() * w).sum() for f, w in zip(flows, weights))
        loss.backward()
        return torch.stack(flows).double(), E.grad, rho.grad, v0.grad

    got, want = loss_and_grads(True), loss_and_grads(False)
    assert float(want[0].detach().abs().max()) > 0.1 and float(want[1].abs()) > 0
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-12)
    # a population's states hold every member's rows: its frames are read on the host
    from clflow.mpm import MaterialSpec, Simulator

    spec = MaterialSpec("elastic", {"youngs_modulus": torch.tensor([1e4, 2e4]), "poissons_ratio": 0.3})
    pop = Simulator(sim.state.x.float(), 1e-5, spec, sim.grid, velocities=torch.zeros(2, sim.n, 3), dtype=torch.float32)
    with pytest.raises(InputError, match="reader"):
        simulate(pop, 1, reader=FlowReader(scene, [cam]))
