"""A simulated scene's Gaussians kept on the device, and one frame's rendering there.

A :class:`DeviceScene` holds the object's n Gaussians first (their rest covariances kept),
then the static ones, written to the device once. :meth:`DeviceScene.frame` makes one frame's
scene from the object's particle positions x and deformation gradients F by a kernel
(kernels_cl/splat/scene_frame.cl: means x, covariances F Sigma0 F^T over the first n rows);
:func:`render_frame` composites per-Gaussian channels at a frame's geometry with every
intermediate (projection, tile lists, transmittance) left on the device in a
:class:`RenderTape`, which :func:`render_frame_backward` reads. Nothing of the static
Gaussians crosses to the device again, and their gradients are never formed.

These are the rasteriser's own kernels (clflow.splat.ops: ``launch_project``,
``build_tile_lists``, ``launch_composite`` and their adjoints) on device arrays; the
per-op path (``rasterize_gaussians`` of ``clflow.pipeline.render.frame_gaussians``) is their
reference (tests/flow/test_scene_flow.py, tests/pipeline/test_render_frames.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from clflow.errors import InputError
from clflow.runtime.arrays import DeviceArray, real_of
from clflow.runtime.bridge import bind
from clflow.runtime.devices import Device, get_device
from clflow.splat.binning import TileLists, build_tile_lists
from clflow.splat.constants import SPLAT_LANES
from clflow.splat.gaussians import Gaussians
from clflow.splat.ops.compositing import launch_composite, launch_composite_backward
from clflow.splat.ops.kernels import splat_kernel
from clflow.splat.ops.projection import launch_project, launch_project_backward
from clflow.splat.sh import SH_C0, SH_C1, SH_C2, SH_C3

# the SH basis constants of clflow.splat.sh, for scene_frame.cl's object_colors
SH_DEFINES = {"SH_C0": repr(SH_C0), "SH_C1": repr(SH_C1)}
SH_DEFINES |= {f"SH_C2_{k}": repr(c) for k, c in enumerate(SH_C2)} | {
    f"SH_C3_{k}": repr(c) for k, c in enumerate(SH_C3)
}


def _frame_kernel(name: str, dtype: torch.dtype, state_dtype: torch.dtype | None = None):
    """Kernel ``name`` of kernels_cl/splat/scene_frame.cl for ``dtype``, reading (or writing) a
    simulation state's values in ``state_dtype`` (default ``dtype``)."""
    state_real = real_of(state_dtype or dtype, "a frame's positions")
    return splat_kernel("scene_frame.cl", name, dtype, STATE_REAL=state_real, **SH_DEFINES)


@dataclass
class SceneFrame:
    """One frame's scene on the device: means [N, 3] (m), covariances [N, 3, 3] (m^2), and the
    object's F [n, 3, 3] they were made with."""

    means: DeviceArray
    covars: DeviceArray
    F: DeviceArray


@dataclass
class RenderTape:
    """What a frame's rendering leaves on the device for its backward: the projection
    (means2d, conics, depths, radii, tiles_touched), the tile lists, the channels [N, C], the
    background [C], the transmittance [H, W] and the contributor counts [H, W]."""

    frame: SceneFrame
    projected: tuple[DeviceArray, ...]
    lists: TileLists
    channels: DeviceArray
    background: DeviceArray
    T_final: DeviceArray
    n_contrib: DeviceArray


class DeviceScene:
    """A simulated scene's Gaussians on the device (see the module docstring).

    Args:
        static: the Gaussians that do not move. obj_rest: the object's n Gaussians at rest
            (their covariances Sigma0 are deformed by each frame's F); both of one float dtype.
    """

    def __init__(self, static: Gaussians, obj_rest: Gaussians, device: Device | None = None):
        self.device = device or get_device()
        self.dtype = obj_rest.means.dtype
        if static.means.dtype != self.dtype:
            raise InputError(f"DeviceScene: static Gaussians are {static.means.dtype}, the object's {self.dtype}")
        self.static, self.obj_rest = static, obj_rest
        self.n = len(obj_rest)
        dev, dtype = self.device, self.dtype
        self.rest_covars = DeviceArray.of(dev, obj_rest.covariances.to(dtype).contiguous(), "rest covariances")
        scene = Gaussians.cat([obj_rest, static])  # the object's rows are overwritten per frame
        self._means = DeviceArray.of(dev, scene.means.detach().contiguous(), "means")
        self._covars = DeviceArray.of(dev, scene.covariances.detach().to(dtype).contiguous(), "covariances")
        self.opacities = DeviceArray.of(dev, scene.opacities.detach().to(dtype).contiguous(), "opacities")
        # the object's SH coefficients and rest sh_rotations, uploaded when colours are first asked for
        self._sh: DeviceArray | None = None
        self._rest_rotations: DeviceArray | None = None
        self._views: dict[bytes, tuple[DeviceArray, ...]] = {}  # a camera's matrices, uploaded once

    def __len__(self) -> int:
        return self._means.shape[0]

    def frame(self, x: torch.Tensor | DeviceArray, F: torch.Tensor | DeviceArray) -> SceneFrame:
        """The scene at one frame: the object's Gaussians at x [n, 3] (m) deformed by F [n, 3, 3]:
        host tensors of the scene's dtype (copied to the device), or a simulation state's
        device arrays x [>= n, 3], F [>= n, 3, 3] of any float dtype (read there: nothing
        crosses), whose first n rows are the object's."""
        dev, n = self.device, self.n
        if not isinstance(x, DeviceArray):
            x, F = DeviceArray.of(dev, x, "positions"), DeviceArray.of(dev, F, "deformation gradients")
        if x.shape[0] < n or x.shape[1:] != (3,) or F.shape[0] < n or F.shape[1:] != (3, 3) or x.dtype != F.dtype:
            raise InputError(f"DeviceScene.frame: x [>= {n}, 3] and F [>= {n}, 3, 3] of one dtype, got {x!r} and {F!r}")
        means, covars = self._means.clone(), self._covars.clone()
        F_own = DeviceArray.empty(dev, (n, 3, 3), self.dtype)
        kern = _frame_kernel("object_frame", self.dtype, x.dtype)
        args = dict(x=x, F=F, rest_covars=self.rest_covars, means=means, covars=covars, F_out=F_own)
        dev.launch(kern, n, args | dict(n=np.int32(n)))
        return SceneFrame(means, covars, F_own)

    def frames(self, x: torch.Tensor, F: torch.Tensor, states=None):
        """Each frame's :meth:`frame` of a run x [T+1, n, 3], F [T+1, n, 3, 3] (host tensors of
        the scene's dtype), or of its ``states`` on the device (clflow.mpm.Frames.states: the
        same values, read there), one at a time."""
        if states is None:
            return (self.frame(x[t].contiguous(), F[t].contiguous()) for t in range(x.shape[0]))
        return (self.frame(state.x, state.F) for state in states)

    @property
    def object_colors_vary(self) -> bool:
        """Whether the object's colours change from frame to frame (SH of degree >= 1 turn
        with each Gaussian and depend on the view direction)."""
        return bool(self.obj_rest.sh is not None and self.obj_rest.sh_degree)

    def object_colors(self, frame: SceneFrame, camera, colors: DeviceArray) -> None:
        """Write the object's colours at ``frame`` seen by ``camera`` over the first n rows of
        ``colors`` [N, 3] (SH of degree >= 1: the polar rotations of the frame's F and the SH
        evaluated on the device; the coefficients uploaded on first use)."""
        if not self.object_colors_vary:
            raise InputError("DeviceScene.object_colors: the object's colours do not change; take them once")
        dev, dtype, n, g = self.device, self.dtype, self.n, self.obj_rest
        if self._sh is None:
            self._sh = DeviceArray.of(dev, g.sh.detach().to(dtype).contiguous(), "SH coefficients")
            rest = g.sh_rotations
            self._rest_rotations = None if rest is None else DeviceArray.of(dev, rest.to(dtype).contiguous())
        polar = DeviceArray.empty(dev, (n, 3, 3), dtype)
        kern = dev.kernel("common/svd3.cl", "polar_rotation", real_of(dtype), {"CLFLOW_SIMD_LANES": SPLAT_LANES})
        dev.launch(kern, -(-n // SPLAT_LANES), dict(n=np.int32(n), F=frame.F, R=polar))
        *_, centre = self._view(camera)
        rest = self._rest_rotations
        args = dict(means=frame.means, polar=polar, rest_rotations=polar if rest is None else rest)
        args |= dict(has_rest=np.int32(rest is not None), sh=self._sh, bases=np.int32(g.sh.shape[1]))
        args |= dict(degree=np.int32(g.sh_degree), camera=centre, colors=colors, n=np.int32(n))
        dev.launch(_frame_kernel("object_colors", dtype), n, args)

    def view(self, camera) -> tuple[DeviceArray, DeviceArray]:
        """``camera``'s viewmat [4, 4] and intrinsics [3, 3] on the device, in the scene's dtype
        (uploaded on the camera's first use: an upload waits for the queue)."""
        return self._view(camera)[:2]

    def _view(self, camera) -> tuple[DeviceArray, DeviceArray, DeviceArray]:
        """(viewmat, intrinsics, the camera's centre [3], m) of ``camera`` on the device."""
        key = camera.viewmat.numpy().tobytes() + camera.K.numpy().tobytes()
        if key not in self._views:
            dev, dtype = self.device, self.dtype
            W, t = camera.viewmat[:3, :3].to(dtype), camera.viewmat[:3, 3].to(dtype)
            matrices = (camera.viewmat.to(dtype), camera.K.to(dtype), -W.T @ t)
            self._views[key] = tuple(DeviceArray.of(dev, m.contiguous(), "camera") for m in matrices)
        return self._views[key]


def render_frame(
    scene: DeviceScene, frame: SceneFrame, channels: DeviceArray, background: DeviceArray, camera, near: float = 0.01
) -> tuple[DeviceArray, RenderTape]:
    """``channels`` [N, C] composited over ``background`` [C] at ``frame``'s geometry, seen by
    ``camera``: the image [H, W, C] (sum_i c_i alpha_i T_i + T_final background) and the tape
    (with the transmittance T_final [H, W]), all on the device."""
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
        launch_project(dev, b, (frame.means, frame.covars, *scene.view(camera)), (width, height, near), projected)
    means2d, conics, depths, radii, tiles_touched = projected
    lists = build_tile_lists(means2d, depths, radii, tiles_touched, width, height, dev)
    image = DeviceArray.empty(dev, (height, width, channels.shape[1]), dtype)
    T_final = DeviceArray.empty(dev, (height, width), dtype)
    n_contrib = DeviceArray.empty(dev, (height, width), torch.int32)
    with bind(dev) as b:
        splats = (means2d, conics, scene.opacities, channels, background)
        tiles = (lists.ranges, lists.sorted_slots, lists.slot_gaussian)
        launch_composite(dev, b, splats, tiles, (image, T_final, n_contrib))
    return image, RenderTape(frame, projected, lists, channels, background, T_final, n_contrib)


def render_frame_backward(
    scene: DeviceScene, tape: RenderTape, v_image: DeviceArray, v_T: DeviceArray, camera
) -> tuple[DeviceArray, DeviceArray, DeviceArray]:
    """The object's gradients from a frame's image [H, W, C] and transmittance [H, W]
    gradients: (dL/dmeans [n, 3] through the geometry, dL/dcovars [n, 3, 3], dL/dchannels
    [n, C]), on the device."""
    dev, dtype, n = scene.device, scene.dtype, scene.n
    means2d, conics, _depths, radii, _tiles_touched = tape.projected
    lists, channels = tape.lists, tape.channels
    rows = lambda *shape: DeviceArray.empty(dev, shape, dtype)  # noqa: E731
    v_means2d, v_conics, v_opacities, v_channels = rows(n, 2), rows(n, 3), rows(n), rows(n, channels.shape[1])
    v_means, v_covars = rows(n, 3), rows(n, 3, 3)
    with bind(dev) as b:
        splats = (means2d, conics, scene.opacities, channels, tape.background)
        tiles = (lists.ranges, lists.sorted_slots, lists.slot_gaussian, lists.first_slot, lists.tiles_touched)
        grads = (tape.T_final, tape.n_contrib, v_image, v_T)
        launch_composite_backward(dev, b, splats, tiles, grads, (v_means2d, v_conics, v_opacities, v_channels), n)
        view = (tape.frame.means, tape.frame.covars, *scene.view(camera), radii)
        v_projected = (v_means2d, v_conics, DeviceArray.zeros(dev, (n,), dtype))
        launch_project_backward(dev, b, view, v_projected, (v_means, v_covars), camera.width, camera.height, n)
    return v_means, v_covars, v_channels


def object_frame_backward(scene: DeviceScene, frame: SceneFrame, v_means: DeviceArray, v_covars: DeviceArray):
    """(dL/dx [n, 3], dL/dF [n, 3, 3]) of the object from its Gaussians' mean and covariance
    gradients at ``frame`` (Sigma = F Sigma0 F^T), on the device."""
    dev, n = scene.device, scene.n
    v_x, v_F = DeviceArray.empty(dev, (n, 3), scene.dtype), DeviceArray.empty(dev, (n, 3, 3), scene.dtype)
    args = dict(F=frame.F, rest_covars=scene.rest_covars, v_means=v_means, v_covars=v_covars, v_x=v_x, v_F=v_F)
    dev.launch(_frame_kernel("object_frame_backward", scene.dtype), n, args | dict(n=np.int32(n)))
    return v_x, v_F


def rgb_uint8(scene: DeviceScene, image: DeviceArray, factor: int = 1) -> np.ndarray:
    """[H, W, C] uint8 of a rendered image [H factor, W factor, C] (values in [0, 1] clamped,
    NaN as 0, x 255 rounded half up: clflow.media.to_uint8; then, with ``factor`` > 1, each
    factor x factor block's mean rounded half up, as OpenCV's INTER_AREA), made on the device
    and read."""
    fine_height, fine_width, channels = image.shape
    dev = scene.device
    out = DeviceArray.empty(dev, image.shape, torch.uint8)
    kern = _frame_kernel("rgb_uint8", scene.dtype)
    dev.launch(kern, image.numel(), dict(image=image, out=out, n=np.int32(image.numel())))
    if factor == 1:
        return out.read().numpy()
    if fine_height % factor or fine_width % factor:
        raise InputError(f"rgb_uint8: a {fine_width} x {fine_height} image is no whole {factor}x supersample")
    height, width = fine_height // factor, fine_width // factor
    small = DeviceArray.empty(dev, (height, width, channels), torch.uint8)
    args = dict(image=out, out=small, height=np.int32(height), width=np.int32(width))
    args |= dict(channels=np.int32(channels), factor=np.int32(factor))
    dev.launch(_frame_kernel("area_average_uint8", scene.dtype), small.numel(), args)
    return small.read().numpy()


def rows_in_state(scene: DeviceScene, rows: DeviceArray, particles: int, state_dtype: torch.dtype) -> DeviceArray:
    """The object's rows [n, ...] (a gradient, the scene's dtype) as a simulation state's
    [particles, ...] of ``state_dtype``: the object's first, zero for the fill particles."""
    full = DeviceArray.zeros(scene.device, (particles, *rows.shape[1:]), state_dtype)
    count = rows.numel()
    kern = _frame_kernel("rows_to_state", scene.dtype, state_dtype)
    scene.device.launch(kern, count, dict(rows=rows, out=full, count=np.int32(count)))
    return full
