"""The simulated flow of a whole run, rendered with the scene on the device.

:func:`render_scene_flows` is :func:`clflow.pipeline.render.render_flow` of every frame step
of a simulation at once, for a :class:`DeviceScene`: the static Gaussians are written to the
device once, each frame's object Gaussians (means x, covariances F Sigma0 F^T) are made
there by a kernel (kernels_cl/splat/scene_flow.cl) from the frame's particle positions and
deformation gradients, and every intermediate of the rasteriser (projections, tile lists,
the transmittance) stays on the device until the backward has used it. What crosses to the
host per frame step: the object's x and F in, the composited flow features and
transmittance out; the backward takes their gradients in and gives the object's gradients
out. The flow model is "mean" (each Gaussian's projected displacement), as
:func:`~clflow.pipeline.render.render_flow` renders it.

The per-op path (``render_flow`` of ``frame_gaussians``: torch and the rasteriser's ops) is
its reference; the two agree to float round-off (tests/flow/test_scene_flow.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from clflow.errors import InputError
from clflow.flow.simulated import flow_from_features
from clflow.runtime.arrays import DeviceArray, numpy_real
from clflow.runtime.bridge import bind
from clflow.runtime.devices import Device, get_device
from clflow.splat.binning import TileLists, build_tile_lists
from clflow.splat.gaussians import Gaussians
from clflow.splat.ops.compositing import launch_composite, launch_composite_backward
from clflow.splat.ops.kernels import splat_kernel
from clflow.splat.ops.projection import launch_project, launch_project_backward


class DeviceScene:
    """A simulated scene's Gaussians on the device: the object's n Gaussians first (their rest
    covariances kept), then the static ones, written once.

    Args:
        static: the Gaussians that do not move. obj_rest: the object's n Gaussians at rest
            (their covariances Sigma0 are deformed by each frame's F); both of one float dtype.
    """

    def __init__(self, static: Gaussians, obj_rest: Gaussians, device: Device | None = None):
        self.device = device or get_device()
        self.dtype = obj_rest.means.dtype
        if static.means.dtype != self.dtype:
            raise InputError(f"DeviceScene: static Gaussians are {static.means.dtype}, the object's {self.dtype}")
        self.n = len(obj_rest)
        dev, dtype = self.device, self.dtype
        self.rest_covars = DeviceArray.of(dev, obj_rest.covariances.to(dtype).contiguous(), "rest covariances")
        scene = Gaussians.cat([obj_rest, static])  # the object's rows are overwritten per frame
        self._means = DeviceArray.of(dev, scene.means.detach().contiguous(), "means")
        self._covars = DeviceArray.of(dev, scene.covariances.detach().to(dtype).contiguous(), "covariances")
        self.opacities = DeviceArray.of(dev, scene.opacities.detach().to(dtype).contiguous(), "opacities")
        self.background = DeviceArray.zeros(dev, (2,), dtype)

    def __len__(self) -> int:
        return self._means.shape[0]

    def frame(self, x: torch.Tensor, F: torch.Tensor) -> _Frame:
        """The scene at one frame: the object's Gaussians at x [n, 3] (m) deformed by F [n, 3, 3]
        (host tensors of the scene's dtype), on the device."""
        dev = self.device
        x_dev, F_dev = DeviceArray.of(dev, x, "positions"), DeviceArray.of(dev, F, "deformation gradients")
        means, covars = self._means.clone(), self._covars.clone()
        kern = splat_kernel("scene_flow.cl", "object_frame", self.dtype)
        args = dict(x=x_dev, F=F_dev, rest_covars=self.rest_covars, means=means, covars=covars)
        dev.launch(kern, self.n, args | dict(n=np.int32(self.n)))
        return _Frame(means, covars, F_dev)


@dataclass
class _Frame:
    """One frame's scene on the device: means [N, 3], covariances [N, 3, 3], the object's F [n, 3, 3]."""

    means: DeviceArray
    covars: DeviceArray
    F: DeviceArray


@dataclass
class _StepTape:
    """What one frame step's backward reads: the projection at frame t, its tile lists, the
    transmittance and the contributor counts, the features."""

    projected: tuple[DeviceArray, ...]  # means2d, conics, depths, radii, tiles_touched
    lists: TileLists
    features: DeviceArray
    T_final: DeviceArray
    n_contrib: DeviceArray


class _SceneFlows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, scene: DeviceScene, camera, near: float, x: torch.Tensor, F: torch.Tensor):
        dev, dtype, N = scene.device, scene.dtype, len(scene)
        view = _view(scene, camera)
        frames = [scene.frame(x[t].contiguous(), F[t].contiguous()) for t in range(x.shape[0])]
        steps = x.shape[0] - 1
        images = torch.empty(steps, camera.height, camera.width, 2, dtype=dtype)
        transmittance = torch.empty(steps, camera.height, camera.width, dtype=dtype)
        tapes = []
        features_kernel = splat_kernel("scene_flow.cl", "mean_flow_features", dtype)
        for t in range(steps):
            features = DeviceArray.empty(dev, (N, 2), dtype)
            args = dict(means_t=frames[t].means, means_t1=frames[t + 1].means, viewmat=view[0], intrinsics=view[1])
            args |= dict(near_plane=numpy_real(dtype)(near), features=features, n=np.int32(N))
            dev.launch(features_kernel, N, args)
            tapes.append(_render_step(scene, frames[t], features, view, camera, near, images[t], transmittance[t]))
        ctx.scene, ctx.camera, ctx.near, ctx.view, ctx.frames, ctx.tapes = scene, camera, near, view, frames, tapes
        return images, transmittance

    @staticmethod
    def backward(ctx, v_images, v_transmittance):
        scene, camera, frames, view = ctx.scene, ctx.camera, ctx.frames, ctx.view
        dtype, n = scene.dtype, scene.n
        v_x = torch.zeros(len(frames), n, 3, dtype=dtype)
        v_F = torch.zeros(len(frames), n, 3, 3, dtype=dtype)
        for t, tape in enumerate(ctx.tapes):
            v_out = _zeros_or(v_images, t, (camera.height, camera.width, 2), dtype)
            v_T = _zeros_or(v_transmittance, t, (camera.height, camera.width), dtype)
            step = _step_backward(scene, frames[t], frames[t + 1], tape, view, camera, ctx.near, v_out, v_T)
            v_x[t] += step[0]
            v_F[t] += step[1]
            v_x[t + 1] += step[2]
        ctx.tapes = ctx.frames = None  # the device memory is given back
        return None, None, None, v_x, v_F


def _zeros_or(grads: torch.Tensor | None, t: int, shape: tuple, dtype) -> torch.Tensor:
    return torch.zeros(shape, dtype=dtype) if grads is None else grads[t].contiguous()


def _view(scene: DeviceScene, camera) -> tuple[DeviceArray, DeviceArray]:
    """The camera's viewmat [4, 4] and intrinsics [3, 3] on the device, in the scene's dtype."""
    dev, dtype = scene.device, scene.dtype
    return DeviceArray.of(dev, camera.viewmat.to(dtype).contiguous()), DeviceArray.of(
        dev, camera.K.to(dtype).contiguous()
    )


def _render_step(scene, frame: _Frame, features, view, camera, near, image_out, T_out) -> _StepTape:
    """Composite one frame step's ``features`` at ``frame``'s geometry; the image [H, W, 2] and
    the transmittance [H, W] read into ``image_out`` and ``T_out``."""
    dev, dtype, N = scene.device, scene.dtype, len(scene)
    width, height = camera.width, camera.height
    projected = (
        DeviceArray.empty(dev, (N, 2), dtype),
        DeviceArray.empty(dev, (N, 3), dtype),
        DeviceArray.empty(dev, (N,), dtype),
        DeviceArray.empty(dev, (N,), torch.int32),
        DeviceArray.empty(dev, (N,), torch.int32),
    )
    with bind(dev) as b:
        launch_project(dev, b, (frame.means, frame.covars, *view), (width, height, near), projected)
    means2d, conics, depths, radii, tiles_touched = projected
    lists = build_tile_lists(means2d, depths, radii, tiles_touched, width, height, dev)
    image = DeviceArray.empty(dev, (height, width, 2), dtype)
    T_final = DeviceArray.empty(dev, (height, width), dtype)
    n_contrib = DeviceArray.empty(dev, (height, width), torch.int32)
    with bind(dev) as b:
        splats = (means2d, conics, scene.opacities, features, scene.background)
        tiles = (lists.ranges, lists.sorted_slots, lists.slot_gaussian)
        launch_composite(dev, b, splats, tiles, (image, T_final, n_contrib))
    image.read(image_out)
    T_final.read(T_out)
    return _StepTape(projected, lists, features, T_final, n_contrib)


def _step_backward(scene, frame, next_frame, tape: _StepTape, view, camera, near, v_out, v_T):
    """The object's (dL/dx [n, 3], dL/dF [n, 3, 3]) at frame t and dL/dx [n, 3] at t + 1 from
    one frame step's image and transmittance gradients."""
    dev, dtype, n = scene.device, scene.dtype, scene.n
    means2d, conics, depths, radii, tiles_touched = tape.projected
    lists = tape.lists
    rows = lambda *shape: DeviceArray.empty(dev, shape, dtype)  # noqa: E731
    v_means2d, v_conics, v_opacities, v_features = rows(n, 2), rows(n, 3), rows(n), rows(n, 2)
    v_means, v_covars, v_means_t1 = rows(n, 3), rows(n, 3, 3), rows(n, 3)
    v_x, v_F = rows(n, 3), rows(n, 3, 3)
    with bind(dev) as b:
        splats = (means2d, conics, scene.opacities, tape.features, scene.background)
        tiles = (lists.ranges, lists.sorted_slots, lists.slot_gaussian, lists.first_slot, lists.tiles_touched)
        grads = (tape.T_final, tape.n_contrib, DeviceArray.of(dev, v_out), DeviceArray.of(dev, v_T))
        launch_composite_backward(dev, b, splats, tiles, grads, (v_means2d, v_conics, v_opacities, v_features), n)
        zero_depths = DeviceArray.zeros(dev, (n,), dtype)
        gaussians = (frame.means, frame.covars, *view, radii)
        launch_project_backward(
            dev, b, gaussians, (v_means2d, v_conics, zero_depths), (v_means, v_covars), camera.width, camera.height, n
        )
        args = dict(means_t=frame.means, means_t1=next_frame.means, viewmat=view[0], intrinsics=view[1])
        args |= dict(near_plane=numpy_real(dtype)(near), v_features=v_features, v_means_t=v_means)
        dev.launch(
            splat_kernel("scene_flow.cl", "mean_flow_features_backward", dtype),
            n,
            args | dict(v_means_t1=v_means_t1, n=np.int32(n)),
        )
        args = dict(F=frame.F, rest_covars=scene.rest_covars, v_means=v_means, v_covars=v_covars)
        dev.launch(
            splat_kernel("scene_flow.cl", "object_frame_backward", dtype),
            n,
            args | dict(v_x=v_x, v_F=v_F, n=np.int32(n)),
        )
    return v_x.read(), v_F.read(), v_means_t1.read()


def render_scene_flows(
    scene: DeviceScene, x: torch.Tensor, F: torch.Tensor, camera, *, normalize: bool = True, near: float = 0.01
) -> list[torch.Tensor]:
    """The simulated flow [H, W, 2] (px per frame) of each frame step t -> t+1 of a run, seen by
    ``camera``, differentiable in x and F.

    Args:
        scene: the scene's Gaussians on the device.
        x: [T + 1, >= n, 3] particle positions (m) per frame; the first n are the object's
            Gaussians (fill particles after them are ignored). F: [T + 1, >= n, 3, 3].
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
    images, transmittance = _SceneFlows.apply(scene, camera, near, x[:, :n].to(scene.dtype), F[:, :n].to(scene.dtype))
    alpha = 1 - transmittance[..., None]
    return [flow_from_features(images[t], alpha[t] if normalize else None) for t in range(images.shape[0])]
