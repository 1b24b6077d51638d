"""The simulated flow of a whole run, rendered with the scene on the device.

:func:`render_scene_flows` is :func:`clflow.pipeline.render.render_flow` of every frame step
of a run at once, for a :class:`~clflow.splat.device_scene.DeviceScene`: the static Gaussians
are on the device already, each frame's object Gaussians are made there from the frame's
particle positions and deformation gradients, each Gaussian's projected displacement by a
kernel (kernels_cl/splat/scene_flow.cl), and every intermediate of the rasteriser
(projections, tile lists, transmittance) stays on the device until the backward has used it.
Per frame step the object's x and F go in (nothing where the run's states on the device are
given), the composited features and transmittance come out; the backward takes their
gradients in and gives the object's out. :class:`FlowReader` renders the same inside the
run's own op (clflow.mpm.autograd.simulate's ``reader``): the frames are read from the run's
states and the gradients handed to its adjoint on the device. The flow model is "mean" (each
Gaussian's projected displacement), as ``render_flow`` renders it.

The per-op path (``render_flow`` of ``frame_gaussians``: torch and the rasteriser's ops) is
its reference; the two agree to float round-off (tests/flow/test_scene_flow.py).
"""

from __future__ import annotations

import numpy as np
import torch

from clflow.errors import InputError
from clflow.flow.simulated import flow_from_features
from clflow.runtime.arrays import DeviceArray, numpy_real
from clflow.splat.device_scene import (
    DeviceScene,
    object_frame_backward,
    render_frame,
    render_frame_backward,
    rows_in_state,
)
from clflow.splat.ops.kernels import splat_kernel


class _FlowRender:
    """Every frame step's flow features and transmittance of a run in each of ``cameras``
    (forward), the tapes kept on the device until the backward gives the object's gradients
    there."""

    def __init__(self, scene: DeviceScene, cameras: list, near: float):
        self.scene, self.cameras, self.near = scene, cameras, near
        self.frames, self.tapes = None, None  # each frame's SceneFrame; each camera's step tapes

    def forward(self, frames) -> list[torch.Tensor]:
        """(images [T, H, W, 2], transmittance [T, H, W]) of each camera, in camera order, from
        the run's T + 1 SceneFrames."""
        frames = list(frames)
        scene, near = self.scene, self.near
        dev, dtype, N = scene.device, scene.dtype, len(scene)
        steps = len(frames) - 1
        background = DeviceArray.zeros(dev, (2,), dtype)
        features_kernel = splat_kernel("scene_flow.cl", "mean_flow_features", dtype)
        outputs, self.tapes = [], []
        for camera in self.cameras:
            images = torch.empty(steps, camera.height, camera.width, 2, dtype=dtype)
            transmittance = torch.empty(steps, camera.height, camera.width, dtype=dtype)
            tapes = []
            for t in range(steps):
                features = DeviceArray.empty(dev, (N, 2), dtype)
                viewmat, intrinsics = scene.view(camera)
                args = dict(means_t=frames[t].means, means_t1=frames[t + 1].means, viewmat=viewmat)
                args |= dict(intrinsics=intrinsics, near_plane=numpy_real(dtype)(near), features=features)
                dev.launch(features_kernel, N, args | dict(n=np.int32(N)))
                image, tape = render_frame(scene, frames[t], features, background, camera, near)
                image.read(images[t])
                tape.T_final.read(transmittance[t])
                tapes.append(tape)
            outputs += [images, transmittance]
            self.tapes.append(tapes)
        self.frames = frames
        return outputs

    def backward(self, grads) -> tuple[list[DeviceArray], list[DeviceArray]]:
        """Each frame's (dL/dx [n, 3], dL/dF [n, 3, 3]) of the object on the device, summed over
        the cameras, from the gradients of forward's outputs (host tensors or None)."""
        scene, frames = self.scene, self.frames
        dev, dtype, n = scene.device, scene.dtype, scene.n
        v_x = [DeviceArray.zeros(dev, (n, 3), dtype) for _ in frames]
        v_F = [DeviceArray.zeros(dev, (n, 3, 3), dtype) for _ in frames]
        for k, (camera, tapes) in enumerate(zip(self.cameras, self.tapes)):
            v_images, v_transmittance = grads[2 * k], grads[2 * k + 1]
            if v_images is None and v_transmittance is None:
                continue
            for t, tape in enumerate(tapes):
                v_out = _zeros_or(v_images, t, (camera.height, camera.width, 2), dtype)
                v_T = _zeros_or(v_transmittance, t, (camera.height, camera.width), dtype)
                step = _step_backward(scene, frames[t + 1], tape, camera, self.near, v_out, v_T)
                v_x[t].add_(step[0])
                v_F[t].add_(step[1])
                v_x[t + 1].add_(step[2])
        self.frames = self.tapes = None  # the device memory is given back
        return v_x, v_F


class _SceneFlows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, scene: DeviceScene, camera, near: float, states, x: torch.Tensor, F: torch.Tensor):
        ctx.render = _FlowRender(scene, [camera], near)
        return tuple(ctx.render.forward(scene.frames(x, F, states)))

    @staticmethod
    def backward(ctx, v_images, v_transmittance):
        v_x, v_F = ctx.render.backward((v_images, v_transmittance))
        ctx.render = None
        return None, None, None, None, torch.stack([g.read() for g in v_x]), torch.stack([g.read() for g in v_F])


class FlowReader:
    """The simulated flow of a run read from its frames on the device, in the run's own op
    (clflow.mpm.autograd.simulate's ``reader``): forward gives each camera's (images
    [T, H, W, 2], transmittance [T, H, W]) of every frame step (turn them into flows with
    :func:`flows_of`); backward hands the run's adjoint the object's gradients as device
    arrays of the run's layout, so neither the frames nor their gradients cross to the host
    for the flow."""

    def __init__(self, scene: DeviceScene, cameras: list, near: float = 0.01):
        self.render = _FlowRender(scene, list(cameras), near)
        self.state_shape: tuple | None = None  # (particles, dtype) of the run's states

    def forward(self, states) -> list[torch.Tensor]:
        self.state_shape = (states[0].x.shape[0], states[0].x.dtype)
        return self.render.forward(self.render.scene.frames(None, None, states))

    def backward(self, grads):
        v_x, v_F = self.render.backward(grads)
        scene, (particles, state_dtype) = self.render.scene, self.state_shape

        def state_grads(frame: int) -> tuple[DeviceArray, DeviceArray]:
            """(dL/dx [N, 3], dL/dF [N, 3, 3]) of frame ``frame`` in the run's dtype."""
            return tuple(rows_in_state(scene, rows[frame], particles, state_dtype) for rows in (v_x, v_F))

        return state_grads


def flows_of(images: torch.Tensor, transmittance: torch.Tensor, normalize: bool = True) -> list[torch.Tensor]:
    """The flows [H, W, 2] of each frame step from a reader's images [T, H, W, 2] and
    transmittance [T, H, W] (divided by the rendered alpha: flow_from_features)."""
    alpha = 1 - transmittance[..., None]
    return [flow_from_features(images[t], alpha[t] if normalize else None) for t in range(images.shape[0])]


def _zeros_or(grads: torch.Tensor | None, t: int, shape: tuple, dtype) -> torch.Tensor:
    return torch.zeros(shape, dtype=dtype) if grads is None else grads[t].contiguous()


def _step_backward(scene: DeviceScene, next_frame, tape, camera, near: float, v_out, v_T):
    """The object's (dL/dx [n, 3], dL/dF [n, 3, 3]) at frame t and dL/dx [n, 3] at t + 1 (device
    arrays) from one frame step's image [H, W, 2] and transmittance [H, W] gradients (host
    tensors)."""
    dev, dtype, n = scene.device, scene.dtype, scene.n
    v_image, v_transmittance = DeviceArray.of(dev, v_out), DeviceArray.of(dev, v_T)
    v_means, v_covars, v_features = render_frame_backward(scene, tape, v_image, v_transmittance, camera)
    v_means_t1 = DeviceArray.empty(dev, (n, 3), dtype)
    viewmat, intrinsics = scene.view(camera)
    args = dict(means_t=tape.frame.means, means_t1=next_frame.means, viewmat=viewmat, intrinsics=intrinsics)
    args |= dict(near_plane=numpy_real(dtype)(near), v_features=v_features, v_means_t=v_means, v_means_t1=v_means_t1)
    dev.launch(splat_kernel("scene_flow.cl", "mean_flow_features_backward", dtype), n, args | dict(n=np.int32(n)))
    v_x, v_F = object_frame_backward(scene, tape.frame, v_means, v_covars)
    return v_x, v_F, v_means_t1


def render_scene_flows(
    scene: DeviceScene,
    x: torch.Tensor,
    F: torch.Tensor,
    camera,
    *,
    states=None,
    normalize: bool = True,
    near: float = 0.01,
) -> list[torch.Tensor]:
    """The simulated flow [H, W, 2] (px per frame) of each frame step t -> t+1 of a run, seen by
    ``camera``, differentiable in x and F.

    Args:
        scene: the scene's Gaussians on the device.
        x: [T + 1, >= n, 3] particle positions (m) per frame; the first n are the object's
            Gaussians (fill particles after them are ignored). F: [T + 1, >= n, 3, 3].
        states: the run's states on the device, one a frame (clflow.mpm.Frames.states: the
            same values as x and F): the frames are read from them, not copied from x and F,
            which still carry the gradients.
        normalize: divide by the rendered alpha (:func:`~clflow.flow.simulated.flow_from_features`).
        near: Gaussians with camera z <= near (m) are culled; one not ahead of it at both
            frames has no flow.
    """
    n = scene.n
    if x.dim() != 3 or F.dim() != 4 or x.shape[0] < 2 or x.shape[0] != F.shape[0] or x.shape[1] < n:
        raise InputError(
            f"render_scene_flows: x [T + 1, >= {n}, 3] and F [T + 1, >= {n}, 3, 3] of T >= 1 frame steps, "
            f"got {tuple(x.shape)} and {tuple(F.shape)}"
        )
    if states is not None and len(states) != x.shape[0]:
        raise InputError(f"render_scene_flows: {len(states)} device states for {x.shape[0]} frames")
    x, F = x[:, :n].to(scene.dtype), F[:, :n].to(scene.dtype)
    images, transmittance = _SceneFlows.apply(scene, camera, near, states, x, F)
    return flows_of(images, transmittance, normalize)
